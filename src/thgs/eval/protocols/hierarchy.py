"""``hierarchy``: every level of the segmentation against a synthetic scene's exact ground
truth (matched mIoU per level, superpoint purity; :func:`thgs.eval.evaluate_hierarchy`)."""

from __future__ import annotations

from pathlib import Path

from thgs.eval.evaluate import evaluate_hierarchy
from thgs.eval.ground_truth import read_hierarchy
from thgs.eval.protocols import GroundTruthSource, Protocol, register_protocol, register_source

__all__ = ["find_hierarchy"]


def find_hierarchy(dataset: Path) -> Path | None:
    """``ground_truth.safetensors`` (written by ``thgs synth``)."""
    path = dataset / "ground_truth.safetensors"
    return path if path.is_file() else None


register_source(
    GroundTruthSource(
        "hierarchy", find_hierarchy, "synthetic ground truth: ground_truth.safetensors"
    )
)

register_protocol(
    Protocol(
        name="hierarchy",
        summary="synthetic levels",
        source="hierarchy",
        needs_cameras=False,
        headline=(
            ("hierarchy", "miou_subpart"),
            ("hierarchy", "miou_part"),
            ("hierarchy", "miou_object"),
            ("hierarchy", "purity"),
        ),
        evaluate=lambda c: [
            evaluate_hierarchy(c.engine.regions.levels, read_hierarchy(c.ground_truth))
        ],
    )
)
