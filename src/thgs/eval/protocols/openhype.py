"""``openhype``: OpenHype's ScanNet++ object and part benchmark under the THGS rule (P-3D): each
prompt's selection rendered as accumulated opacity > 0.5 against its mask, IoU and
localization averaged flat over (frame, prompt) as OpenHype's evaluator does, overall and per
kind (object prompts, "[PART] of a [OBJ]" prompts) (:func:`thgs.eval.evaluate_openhype`). Two
results: ``openhype`` with the engine's selection rule and ``openhype-paper`` with the THGS
paper's. Also registers the ground truth: a scene's annotation folder
``openhype_scannetpp_benchmark/<scene>/`` beside the processed scenes."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

from thgs.eval.evaluate import evaluate_openhype
from thgs.eval.openhype import read_openhype_annotations
from thgs.eval.protocols import (
    EvalContext,
    GroundTruthSource,
    Protocol,
    one_place,
    register_protocol,
    register_source,
    scene_folder,
)

__all__ = ["ANNOTATION_FOLDER", "find_openhype_annotations", "openhype_annotation_folder"]


ANNOTATION_FOLDER = "openhype_scannetpp_benchmark"
"""The folder of every scene's annotations, ``<scene id>/`` each (OpenHype's configs'
``gt_path``: ``…/openhype_scannetpp_benchmark/<scene id>``)."""


def _has_json(folder: Path) -> bool:
    return folder.is_dir() and any(
        path.name.endswith(".json") and not path.name.startswith(".") for path in folder.iterdir()
    )


def find_openhype_annotations(dataset: Path) -> Path | None:
    """The OpenHype annotation folder of a processed scene folder, or None when there is none.

    Looks for ``openhype_scannetpp_benchmark/<scene>/`` holding ``*.json`` beside the scene
    (``data/openhype_scannetpp_benchmark/<scene>`` for ``data/<scene>``) and beside the folder
    of the processed scenes (``data/openhype_scannetpp_benchmark/<scene>`` for
    ``data/scannetpp/<scene>``); the scene is the dataset folder's name as given.

    Raises:
        InputError: both hold annotations (two different folders: the message names them).
    """
    dataset = Path(os.path.abspath(dataset))
    candidates = (
        dataset.parent / ANNOTATION_FOLDER / dataset.name,
        dataset.parent.parent / ANNOTATION_FOLDER / dataset.name,
    )
    choose = "with --openhype (openhype= in Python)"
    return one_place(dataset, candidates, _has_json, "OpenHype annotations", choose)


def openhype_annotation_folder(given: Path, scene: str) -> Path:
    """The annotation folder of ``scene`` from a folder given for it: the folder itself when it
    holds ``*.json`` files, else its ``<scene>/`` sub-folder (the unpacked benchmark, what
    OpenHype's multi-scene configs are given), else ``openhype_scannetpp_benchmark/<scene>/``
    in it.

    Raises:
        InputError: none holds annotation files (the message lists the sub-folders there are).
    """
    what = "OpenHype annotation files (*.json)"
    return scene_folder(given, scene, ANNOTATION_FOLDER, what, "*.json", "--openhype")


def frames(context: EvalContext):
    """The annotation frames of the context's folder, read once per evaluation."""
    return context.read("openhype frames", read_openhype_annotations)


register_source(
    GroundTruthSource(
        "openhype",
        find_openhype_annotations,
        "OpenHype ScanNet++ annotations: openhype_scannetpp_benchmark/<scene>/*.json (with "
        "their mask PNGs) beside the scene or beside its folder",
        openhype_annotation_folder,
    )
)


def _evaluate(context: EvalContext):
    annotations = frames(context)
    shared = {
        "source": str(context.ground_truth),
        "raster": context.raster,
        "rescale_labels": context.options.get("rescale_labels", False),
    }
    return [
        evaluate_openhype(
            context.engine,
            context.gaussians,
            context.cameras,
            annotations,
            progress=context.progress,
            **shared,
        ),
        replace(
            evaluate_openhype(
                context.engine.using(mode="paper", levels=None),
                context.gaussians,
                context.cameras,
                annotations,
                protocol="openhype-paper",
                **shared,
            ),
            notes=(),  # the same frames and views: the first result's note says how they match
        ),
    ]


register_protocol(
    Protocol(
        name="openhype",
        summary="OpenHype ScanNet++ objects and parts",
        source="openhype",
        needs_cameras=True,
        headline=(
            ("openhype", "miou"),
            ("openhype", "miou_objects"),
            ("openhype", "miou_parts"),
            ("openhype-paper", "miou"),
            ("openhype", "localization"),
        ),
        evaluate=_evaluate,
    )
)
