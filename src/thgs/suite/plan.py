"""What a suite run would do for a scene, and the stamps that decide it: a scene's stages
(preprocess → build → eval), its output folder, and when a stage is current.

Outputs of scene ``<benchmark>/<scene>`` go to ``OUT/<benchmark>/<scene>/``:

- ``language_features/`` — only for a scene without its own (the user's dataset is never
  written into): SAM masks and CLIP features (:func:`thgs.guidance.preprocess.preprocess_images`);
- ``field.thgs`` — the semantic field (:func:`thgs.pipeline.build_field`);
- ``eval.json``, ``eval.md`` — the scene's evaluation (:func:`thgs.eval.evaluate_dataset`);
- ``stages.json`` — one stamp per finished stage: a digest of the stage's inputs (settings, and
  the size and modification time of every input file), the size and modification time of its
  outputs, and its recorded times;
- ``error.log`` — the traceback of the last failure, if the scene failed.

A stage is **current** when its outputs exist as its stamp recorded them (a truncated or replaced
``field.thgs`` is built again; stamps written before outputs were recorded are trusted), its
stamp's digest equals its inputs' digest now, and no stage before it ran in this run; a current
stage is skipped. So a changed field config reruns build and eval, a changed selection mode
only eval, and a suite interrupted anywhere (every output is written atomically, the stamp after
it) resumes where it stopped.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from thgs._json import load_json
from thgs.errors import InputError
from thgs.export import write_json
from thgs.suite.config import SuiteConfig
from thgs.suite.discover import SuiteScene

__all__ = [
    "EVAL",
    "FIELD",
    "GUIDANCE",
    "STAGES",
    "STAMPS",
    "StagePlan",
    "plan_scene",
    "read_stamps",
    "scene_folder",
    "scene_guidance",
    "stage_digest",
    "write_stamp",
]

logger = logging.getLogger(__name__)


STAGES = ("preprocess", "build", "eval")
"""A scene's stages, in the order they run."""

STAMPS = "stages.json"
FIELD = "field.thgs"
EVAL = "eval.json"
GUIDANCE = "language_features"

_CAMERA_FILES = (
    "sparse",
    "transforms.json",
    "transforms_train.json",
    "transforms_test.json",
    "cameras.json",
)
_MODEL_FILES = ("point_cloud", "ckpts", "cameras.json", "cfg_args", "cfg.yml", "cfg.json")


@dataclass(frozen=True)
class StagePlan:
    """What a stage of a scene will do and why.

    Attributes:
        stage: one of :data:`STAGES`.
        action: ``"run"``, ``"current"`` (skipped: outputs current) or ``"not needed"`` (the
            scene's own language features; no preprocessing).
        reason: why, in words.
    """

    stage: str
    action: Literal["run", "current", "not needed"]
    reason: str


def scene_folder(out: str | os.PathLike[str], scene: SuiteScene) -> Path:
    """``OUT/<benchmark>/<scene>``: where a scene's outputs go."""
    return Path(out) / scene.benchmark / scene.name


# --- digests of stage inputs ----------------------------------------------------------------------


def _files_state(path: Path, names: Sequence[str] | None = None) -> list[list[Any]]:
    """``[relative path, size, mtime_ns]`` of every file under ``path`` (or of its entries
    ``names``), sorted; following links."""
    state: list[list[Any]] = []
    roots = [path] if names is None else [path / name for name in names]
    for top in roots:
        if top.is_file():
            info = top.stat()
            state.append([os.path.relpath(top, path), info.st_size, info.st_mtime_ns])
            continue
        for folder, _, files in os.walk(top, followlinks=True):
            for name in files:
                file = Path(folder) / name
                with contextlib.suppress(FileNotFoundError):
                    info = file.stat()
                    state.append([os.path.relpath(file, path), info.st_size, info.st_mtime_ns])
    return sorted(state)


def _digest(value: Any) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()


def scene_guidance(scene: SuiteScene, folder: Path) -> Path:
    """The scene's language features: its own, else those preprocessed into its output folder."""
    return scene.guidance if scene.guidance is not None else folder / GUIDANCE


def _inputs(scene: SuiteScene, folder: Path, config: SuiteConfig, stage: str) -> dict[str, Any]:
    """The inputs a stage's digest is made of."""
    if stage == "preprocess":
        assert scene.images is not None
        return {
            "sam": config.sam,
            "clip": config.clip,
            "preprocess": config.to_json()["preprocess"],
            "images": _files_state(scene.images),
        }
    assert scene.model is not None
    build = {
        "field": config.field_config(scene.benchmark).to_json(),
        "model": _files_state(scene.model, _MODEL_FILES),
        "cameras": _files_state(scene.data, _CAMERA_FILES),
        "guidance": _files_state(scene_guidance(scene, folder)),
    }
    if stage == "build":
        return build
    return {
        "build": _digest(build),
        "field": _files_state(folder, (FIELD,)),
        "selection": config.selection,
        "protocols": list(scene.protocols),
        "scannet_level": config.scannet_level,
        "ground_truth": {
            source: _files_state(path) for source, path in sorted(scene.ground_truth.paths.items())
        },
    }


def stage_digest(scene: SuiteScene, folder: Path, config: SuiteConfig, stage: str) -> str:
    """The digest of a stage's inputs now (what its stamp records)."""
    return _digest(_inputs(scene, folder, config, stage))


def _outputs_exist(folder: Path, scene: SuiteScene, stage: str) -> bool:
    if stage == "preprocess":
        return (folder / GUIDANCE).is_dir()
    if stage == "build":
        return (folder / FIELD).is_file()
    return (folder / EVAL).is_file() and (folder / EVAL).with_suffix(".md").is_file()


def _output_state(folder: Path, stage: str) -> list[list[Any]]:
    """The size and modification time of the stage's outputs (:func:`_files_state`)."""
    if stage == "preprocess":
        return _files_state(folder, (GUIDANCE,))
    if stage == "build":
        return _files_state(folder, (FIELD,))
    return _files_state(folder, (EVAL, Path(EVAL).with_suffix(".md").name))


def read_stamps(folder: Path) -> dict[str, Any]:
    """A scene folder's stamps (``stages.json``); none when missing or unreadable (logged)."""
    path = folder / STAMPS
    if not path.is_file():
        return {}
    try:
        stamps = load_json(path)
    except InputError as error:
        logger.warning("%s; its stages run again", error)
        return {}
    return stamps if isinstance(stamps, dict) else {}


def write_stamp(folder: Path, stage: str, stamp: dict[str, Any]) -> None:
    """Record ``stamp`` for ``stage``, with its outputs' state as they are now, and drop the
    stamps of the stages after it."""
    stamps = read_stamps(folder)
    stamps[stage] = {**stamp, "outputs": _output_state(folder, stage)}
    for later in STAGES[STAGES.index(stage) + 1 :]:
        stamps.pop(later, None)
    write_json(folder / STAMPS, stamps)


def _stage_plan(
    scene: SuiteScene, folder: Path, config: SuiteConfig, stage: str, stamps: dict, earlier: bool
) -> StagePlan:
    """The plan of one stage, given whether an earlier stage runs."""
    if stage == "preprocess" and scene.guidance is not None:
        return StagePlan(stage, "not needed", "the scene has language_features")
    if earlier:
        return StagePlan(stage, "run", "an earlier stage runs")
    if not _outputs_exist(folder, scene, stage):
        return StagePlan(stage, "run", "no output yet")
    stamp = stamps.get(stage) if isinstance(stamps.get(stage), dict) else {}
    recorded = stamp.get("digest")
    if recorded is None:
        return StagePlan(stage, "run", "output without a stamp (interrupted?)")
    if recorded != stage_digest(scene, folder, config, stage):
        return StagePlan(stage, "run", "its inputs or settings changed")
    if "outputs" in stamp and stamp["outputs"] != _output_state(folder, stage):
        return StagePlan(stage, "run", "its output changed since it was written (damaged?)")
    return StagePlan(stage, "current", "output current")


def plan_scene(
    scene: SuiteScene, out: str | os.PathLike[str], config: SuiteConfig
) -> tuple[StagePlan, ...]:
    """What :func:`run_scene` would do for ``scene`` now, stage by stage (``thgs suite
    --dry-run``). A scene with problems plans nothing (its problems are the reason).

    Raises:
        InputError: ``scene`` has problems (the message lists them).
    """
    if scene.problems:
        raise InputError(scene.data, "; ".join(scene.problems))
    folder = scene_folder(out, scene)
    stamps = read_stamps(folder)
    plans: list[StagePlan] = []
    for stage in STAGES:
        earlier = any(plan.action == "run" for plan in plans)
        plans.append(_stage_plan(scene, folder, config, stage, stamps, earlier))
    return tuple(plans)
