"""``lerf``: LERF-OVS under the THGS rule (P-3D): the selection rendered as accumulated opacity
> 0.5 against each category's polygons (:func:`thgs.eval.evaluate_lerf`). Two results: ``lerf``
with the engine's selection rule (``auto`` unless the caller chose another) and ``lerf-paper``
with the paper's (the number the paper reports). Also registers LERF-OVS's ground truth, which
the other two LERF protocols read too."""

from __future__ import annotations

import os
from pathlib import Path

from thgs.eval.evaluate import evaluate_lerf, read_lerf_frames
from thgs.eval.protocols import (
    EvalContext,
    GroundTruthSource,
    Protocol,
    one_place,
    register_protocol,
    register_source,
    scene_folder,
)

__all__ = ["find_lerf_labels", "frames", "lerf_label_folder"]


def _has_frames(folder: Path) -> bool:
    return folder.is_dir() and any(folder.glob("frame_*.json"))


def find_lerf_labels(dataset: Path) -> Path | None:
    """The LERF-OVS label folder of a scene's dataset folder, or None when there is none.

    Looks for ``frame_*.json`` in ``dataset/label/``, in LangSplat's sibling
    ``dataset/../label/<scene>/`` (``lerf_ovs/label/teatime`` for ``lerf_ovs/teatime``; the
    scene is the dataset folder's name as given) and in ``dataset`` itself.

    Raises:
        InputError: more than one of these holds labels (two different folders: the message
            names them; ``thgs eval --labels``, or ``lerf=`` in Python, decides).
    """
    dataset = Path(os.path.abspath(dataset))
    candidates = (dataset / "label", dataset.parent / "label" / dataset.name, dataset)
    what = "LERF-OVS labels (frame_*.json)"
    return one_place(dataset, candidates, _has_frames, what, "with --labels (lerf= in Python)")


def lerf_label_folder(given: Path, scene: str) -> Path:
    """The label folder of ``scene`` from a folder given for it: the folder itself when it holds
    ``*.json`` label files, else its ``<scene>/`` sub-folder (LangSplat's ``lerf_ovs/label``,
    which THGS's and LangSplat's evaluation scripts are given), else ``label/<scene>/`` in it
    (LangSplat's ``lerf_ovs``).

    Raises:
        InputError: none holds label files (the message lists the sub-folders there are).
    """
    what = "LERF-OVS label files (frame_*.json)"
    return scene_folder(given, scene, "label", what, "frame_*.json", "--labels")


def frames(context: EvalContext):
    """The LERF-OVS frames of the context's label folder, read once per evaluation."""
    return context.read("lerf frames", read_lerf_frames)


register_source(
    GroundTruthSource(
        "lerf",
        find_lerf_labels,
        "LERF-OVS frame labels: label/frame_*.json, ../label/<scene>/ (LangSplat's release), "
        "or frame_*.json in the folder",
        lerf_label_folder,
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
                c.engine,
                c.gaussians,
                c.cameras,
                frames(c),
                raster=c.raster,
                progress=c.progress,
                rescale_labels=c.options.get("rescale_labels", False),
            ),
            evaluate_lerf(
                c.engine.using(mode="paper", levels=None),
                c.gaussians,
                c.cameras,
                frames(c),
                protocol="lerf-paper",
                raster=c.raster,
                rescale_labels=c.options.get("rescale_labels", False),
            ),
        ],
    )
)
