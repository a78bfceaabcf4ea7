"""``3dovs``: 3D-OVS: each class's selection rendered per view against its mask
(:func:`thgs.eval.evaluate_3dovs`); ground truth ``segmentations/`` with ``classes.txt``."""

from __future__ import annotations

from pathlib import Path

from thgs.eval.evaluate import evaluate_3dovs
from thgs.eval.protocols import GroundTruthSource, Protocol, register_protocol, register_source
from thgs.eval.three_dovs import read_3dovs_segmentations

__all__ = ["find_segmentations"]


def find_segmentations(dataset: Path) -> Path | None:
    """``segmentations/`` holding ``classes.txt``."""
    folder = dataset / "segmentations"
    return folder if (folder / "classes.txt").is_file() else None


register_source(
    GroundTruthSource(
        "three_dovs", find_segmentations, "3D-OVS masks: segmentations/ with classes.txt"
    )
)

register_protocol(
    Protocol(
        name="3dovs",
        summary="3D-OVS",
        source="three_dovs",
        needs_cameras=True,
        headline=(("3dovs", "miou"),),
        evaluate=lambda c: [
            evaluate_3dovs(
                c.engine,
                c.gaussians,
                c.cameras,
                read_3dovs_segmentations(c.ground_truth),
                raster=c.raster,
                progress=c.progress,
                rescale_labels=c.options.get("rescale_labels", False),
            )
        ],
    )
)
