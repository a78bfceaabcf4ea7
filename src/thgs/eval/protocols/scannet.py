"""``scannet``: per-point classes from the features of one level against ScanNet's label PLY,
over the 19 / 15 / 10-class subsets (or every class of a synthetic label table)
(:func:`thgs.eval.evaluate_scannet`)."""

from __future__ import annotations

from pathlib import Path

from thgs.eval.evaluate import evaluate_scannet
from thgs.eval.protocols import GroundTruthSource, Protocol, register_protocol, register_source
from thgs.eval.scannet import read_scannet_labels

__all__ = ["find_scannet_labels"]


def find_scannet_labels(dataset: Path) -> Path | None:
    """``scannet/*.labels.ply``, else ``*_vh_clean_2.labels.ply`` in the folder (first by name)."""
    candidates = sorted(dataset.glob("scannet/*.labels.ply")) + sorted(
        dataset.glob("*_vh_clean_2.labels.ply")
    )
    return candidates[0] if candidates else None


register_source(
    GroundTruthSource(
        "scannet",
        find_scannet_labels,
        "ScanNet point labels: scannet/*.labels.ply or *_vh_clean_2.labels.ply",
    )
)

register_protocol(
    Protocol(
        name="scannet",
        summary="ScanNet",
        source="scannet",
        needs_cameras=False,
        headline=(
            ("scannet-all", "miou"),
            ("scannet-19", "miou"),
            ("scannet-15", "miou"),
            ("scannet-10", "miou"),
        ),
        evaluate=lambda c: evaluate_scannet(
            c.engine,
            c.gaussians,
            read_scannet_labels(c.ground_truth),
            level=c.options.get("scannet_level", 3),
        ),
    )
)
