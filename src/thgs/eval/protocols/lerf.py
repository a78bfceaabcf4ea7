"""``lerf``: LERF-OVS under the THGS rule (P-3D): the selection rendered as accumulated opacity
> 0.5 against each category's polygons (:func:`thgs.eval.evaluate_lerf`). Two results: ``lerf``
with the engine's selection rule (``auto`` unless the caller chose another) and ``lerf-paper``
with the paper's (the number the paper reports). Also registers LERF-OVS's ground truth, which
the other two LERF protocols read too."""

from __future__ import annotations

from pathlib import Path

from thgs.eval.evaluate import evaluate_lerf, read_lerf_frames
from thgs.eval.protocols import (
    EvalContext,
    GroundTruthSource,
    Protocol,
    register_protocol,
    register_source,
)

__all__ = ["find_lerf_labels", "frames"]


def find_lerf_labels(dataset: Path) -> Path | None:
    """``label/`` with ``frame_*.json`` in the dataset, or the dataset folder itself."""
    for candidate in (dataset / "label", dataset):
        if candidate.is_dir() and any(candidate.glob("frame_*.json")):
            return candidate
    return None


def frames(context: EvalContext):
    """The LERF-OVS frames of the context's label folder, read once per evaluation."""
    return context.read("lerf frames", read_lerf_frames)


register_source(
    GroundTruthSource(
        "lerf",
        find_lerf_labels,
        "LERF-OVS frame labels: label/*.json, or frame_*.json in the folder",
    )
)

register_protocol(
    Protocol(
        name="lerf",
        summary="THGS: 3D selection → rendered mask",
        source="lerf",
        needs_cameras=True,
        headline=(("lerf", "miou"), ("lerf-paper", "miou"), ("lerf", "accuracy")),
        evaluate=lambda c: [
            evaluate_lerf(
                c.engine, c.gaussians, c.cameras, frames(c), raster=c.raster, progress=c.progress
            ),
            evaluate_lerf(
                c.engine.using(mode="paper", levels=None),
                c.gaussians,
                c.cameras,
                frames(c),
                protocol="lerf-paper",
                raster=c.raster,
            ),
        ],
    )
)
