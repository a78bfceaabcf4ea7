"""Every scene of every benchmark under a folder, in the layouts the benchmarks are released in.

:func:`find_suite` walks ``ROOT`` (following links) and recognises a scene's data folder by its
ground truth, or by the folder it sits in:

============= ============================================================================
benchmark     a data folder ``D`` that
============= ============================================================================
``synthetic`` holds ``synthetic.json`` (``thgs synth``)
``scannet``   holds ``<scene>_vh_clean_2.labels.ply`` (OpenGaussian's ``scannet/<scene>/``
              with ``color/``, ``transforms_train.json``), or sits in a folder ``scannet/``
``3dovs``     holds ``segmentations/classes.txt`` (the 3D-OVS release), or sits in a folder
              ``3dovs/`` (also ``3d_ovs``, ``3d-ovs``)
``lerf_ovs``  has labels in LangSplat's ``../label/<D's name>/frame_*.json`` or in
              ``label/``, or sits in a folder ``lerf_ovs/``
``openhype``  looks like training data and has OpenHype's ScanNet++ annotations in
              ``openhype_scannetpp_benchmark/<D's name>/*.json`` beside it or beside its
              folder (a scene processed by OpenHype's ``scannetpp_preprocess.py``:
              ``transforms.json``, ``images/``), or sits in a folder ``scannetpp/``
============= ============================================================================

A folder recognised only by where it sits must look like training data (``images/``,
``color/``, ``sparse/``, ``transforms*.json``); it is a scene whose missing ground truth is a
problem, reported, not skipped.

Each scene's trained model is, in this order: the data folder itself when it holds
``point_cloud/`` or gsplat's ``ckpts/`` (synthetic datasets); a model folder under ``ROOT``
whose ``cfg_args`` names the data folder (:func:`thgs.scene.cfg_args.find_model_source`); else
``ROOT/output/<scene>``. Two model folders naming one data folder are a problem naming both.

Protocols run per benchmark (:data:`BENCHMARK_PROTOCOLS`): LERF-OVS scenes ``lerf`` (which
reports the chosen selection and the paper's, ``lerf-paper``) and ``lerf-langsplat``; 3D-OVS
scenes ``3dovs``; ScanNet scenes ``scannet``; OpenHype's ScanNet++ scenes ``openhype`` (which
reports the chosen selection and the paper's, ``openhype-paper``); synthetic scenes every
protocol with ground truth.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from thgs.errors import InputError
from thgs.eval.dataset import GroundTruth, find_ground_truth
from thgs.eval.protocols import get_protocol
from thgs.eval.protocols.openhype import ANNOTATION_FOLDER, find_openhype_annotations
from thgs.scene.cfg_args import CFG_ARGS, find_model_source

__all__ = ["BENCHMARKS", "BENCHMARK_PROTOCOLS", "SuiteScene", "find_suite"]

logger = logging.getLogger(__name__)

BENCHMARKS = ("lerf_ovs", "3dovs", "scannet", "openhype", "synthetic")
"""The benchmarks a suite is made of, in report order."""

BENCHMARK_PROTOCOLS: dict[str, tuple[str, ...] | None] = {
    "lerf_ovs": ("lerf", "lerf-langsplat"),
    "3dovs": ("3dovs",),
    "scannet": ("scannet",),
    "openhype": ("openhype",),
    "synthetic": None,
}
"""The protocols run on each benchmark's scenes (None: every protocol with ground truth)."""

_PARENTS = {
    "lerf_ovs": "lerf_ovs",
    "3dovs": "3dovs",
    "3d_ovs": "3dovs",
    "3d-ovs": "3dovs",
    "scannet": "scannet",
    "scannetpp": "openhype",
}
"""A folder name (lower case) whose sub-folders are scenes of a benchmark."""

_DATA_SIGNS = ("images", "color", "sparse", "transforms.json", "transforms_train.json")
"""What makes a folder look like a scene's training data."""

_NOT_SCENES = frozenset(
    {
        "images",
        "color",
        "sparse",
        "language_features",
        "point_cloud",
        "segmentations",
        "label",
        "ckpts",
        "depth",
        "intrinsic",
        "pose",
        ANNOTATION_FOLDER,
    }
)
"""Folders never walked into: parts of a scene, never a scene."""

_MAX_DEPTH = 6
"""How deep below ROOT scenes are looked for."""


@dataclass(frozen=True)
class SuiteScene:
    """One scene of a suite: where its data, model and ground truth are.

    Attributes:
        benchmark: one of :data:`BENCHMARKS`.
        name: the scene's name (its data folder's name).
        data: the data folder (images, cameras, ground truth).
        model: the trained model folder (or the data folder itself for synthetic datasets);
            None when none was found (see ``problems``).
        guidance: the scene's own ``language_features`` folder; None when it has none (the
            suite preprocesses ``images``).
        images: the image folder, for preprocessing; None when there is none.
        ground_truth: the ground truth found in ``data``.
        protocols: the protocols to run, in report order.
        problems: why the scene cannot run (empty when it can); reported, never skipped
            silently.
    """

    benchmark: str
    name: str
    data: Path
    model: Path | None
    guidance: Path | None
    images: Path | None
    ground_truth: GroundTruth = field(default_factory=GroundTruth)
    protocols: tuple[str, ...] = ()
    problems: tuple[str, ...] = ()

    @property
    def key(self) -> str:
        """``<benchmark>/<name>``: the scene in ``--select``, reports and the output folder."""
        return f"{self.benchmark}/{self.name}"


def _looks_like_data(folder: Path) -> bool:
    return any((folder / sign).exists() for sign in _DATA_SIGNS)


def _lerf_labels(folder: Path) -> bool:
    for labels in (folder.parent / "label" / folder.name, folder / "label"):
        if labels.is_dir() and any(labels.glob("frame_*.json")):
            return True
    return False


def _openhype_annotations(folder: Path) -> bool:
    try:
        return find_openhype_annotations(folder) is not None
    except InputError:  # in two places: a scene all the same, whose problem says so
        return True


def _benchmark(folder: Path) -> str | None:
    """The benchmark whose scene ``folder`` is, or None."""
    if (folder / "synthetic.json").is_file():
        return "synthetic"
    if any(folder.glob("*_vh_clean_2.labels.ply")):
        return "scannet"
    if (folder / "segmentations" / "classes.txt").is_file():
        return "3dovs"
    if _looks_like_data(folder) and _lerf_labels(folder):
        return "lerf_ovs"
    if _looks_like_data(folder) and _openhype_annotations(folder):
        return "openhype"
    parent = _PARENTS.get(folder.parent.name.lower())
    if parent is not None and _looks_like_data(folder):
        return parent
    return None


def _warn_unmatched_labels(folder: Path) -> None:
    """Warn of every LERF-OVS ``folder/label/<scene>/frame_*.json`` set whose scene folder
    ``folder/<scene>`` is missing or not a folder: it is not run, so the benchmark's mean covers
    one scene fewer."""
    labels = folder / "label"
    try:
        sets = sorted(entry for entry in labels.iterdir() if entry.is_dir())
    except OSError:
        return
    for found in sets:
        scene = folder / found.name
        if any(found.glob("frame_*.json")) and not scene.is_dir():
            state = "is not a folder" if scene.exists() or scene.is_symlink() else "is missing"
            logger.warning(
                "%s has LERF-OVS labels but its scene folder %s %s: not run, so the mean "
                "covers one scene fewer",
                found,
                scene,
                state,
            )


def _walk(root: Path, skip: Path | None) -> tuple[list[tuple[str, Path]], list[Path]]:
    """The scene folders ``(benchmark, folder)`` and the model folders (with ``cfg_args``)
    under ``root``, sorted by path."""
    scenes: list[tuple[str, Path]] = []
    models: list[Path] = []
    seen: set[Path] = set()
    stack = [(root, 0)]
    while stack:
        folder, depth = stack.pop()
        try:
            resolved = folder.resolve()
        except (OSError, RuntimeError) as error:  # a symbolic link loop
            logger.warning("%s: not searched for scenes (%s)", folder, error)
            continue
        if resolved in seen or (skip is not None and resolved == skip):
            continue
        seen.add(resolved)
        if (folder / CFG_ARGS).is_file():
            models.append(folder)
        benchmark = _benchmark(folder)
        if benchmark is not None:
            scenes.append((benchmark, folder))
            continue
        if depth >= _MAX_DEPTH:
            continue
        try:
            children = sorted(os.scandir(folder), key=lambda entry: entry.name)
        except OSError as error:
            logger.warning("%s: not searched for scenes (%s)", folder, error.strerror or error)
            continue
        _warn_unmatched_labels(folder)
        for child in reversed(children):
            name = child.name
            if name.startswith(".") or name in _NOT_SCENES:
                continue
            try:
                is_folder = child.is_dir()
            except OSError as error:  # e.g. a link to itself
                logger.warning("%s: not searched for scenes (%s)", child.path, error.strerror)
                continue
            if is_folder:
                stack.append((folder / name, depth + 1))
    return sorted(scenes, key=lambda item: str(item[1])), sorted(models, key=str)


def _holds_model(folder: Path) -> bool:
    return (folder / "point_cloud").is_dir() or any(folder.glob("ckpts/ckpt_*.pt"))


def _find_model(data: Path, root: Path, named: dict[Path, list[Path]]) -> tuple[Path | None, str]:
    """The model folder of ``data`` and '' or (None, the problem)."""
    if _holds_model(data):
        return data, ""
    naming = named.get(data.resolve(), [])
    if len(naming) > 1:
        return None, (
            f"{len(naming)} model folders name this data folder in their cfg_args: "
            + ", ".join(map(str, naming))
            + "; keep one under the root"
        )
    if naming:
        return naming[0], ""
    default = root / "output" / data.name
    if default.is_dir() and _holds_model(default):
        return default, ""
    return None, (
        f"no trained model: no model folder under {root} names {data} in its cfg_args, and "
        f"{default} holds no point_cloud/"
    )


def _named_sources(models: Sequence[Path], root: Path) -> dict[Path, list[Path]]:
    """Resolved data folder → the model folders whose cfg_args names it."""
    named: dict[Path, list[Path]] = {}
    for model in models:
        try:
            source = find_model_source(model, cwd=root)
        except InputError as error:
            logger.warning("model folder %s left out: %s", model, error)
            continue
        if source is not None and source.folder is not None:
            named.setdefault(source.folder.resolve(), []).append(model)
    return named


_NEEDS = {
    "lerf": "LERF-OVS labels (label/frame_*.json, or LangSplat's ../label/<scene>/frame_*.json)",
    "three_dovs": "3D-OVS masks (segmentations/classes.txt with segmentations/<NN>/<class>.png)",
    "scannet": "ScanNet point labels (<scene>_vh_clean_2.labels.ply)",
    "openhype": (
        f"OpenHype's ScanNet++ annotations ({ANNOTATION_FOLDER}/<scene>/*.json beside the scene "
        "or beside its folder)"
    ),
}


def _protocols(benchmark: str, truth: GroundTruth) -> tuple[tuple[str, ...], list[str]]:
    """The protocols to run and the problems (missing ground truth)."""
    wanted = BENCHMARK_PROTOCOLS[benchmark]
    available = truth.available()
    if wanted is None:
        if not available:
            return (), ["no ground truth of any benchmark"]
        return available, []
    problems = sorted(
        {
            f"missing its ground truth: {_NEEDS.get(get_protocol(name).source, name)}"
            for name in wanted
            if name not in available
        }
    )
    return tuple(name for name in available if name in wanted), problems


def _scene(benchmark: str, data: Path, root: Path, named: dict[Path, list[Path]]) -> SuiteScene:
    problems: list[str] = []
    try:
        truth = find_ground_truth(data)
    except InputError as error:
        truth = GroundTruth({}, data.name)
        problems.append(str(error))
    protocols, missing = _protocols(benchmark, truth)
    problems += [] if problems else missing
    model, why = _find_model(data, root, named)
    if why:
        problems.append(why)
    guidance = data / "language_features"
    has_guidance = guidance.is_dir() and any(guidance.glob("*_s.npy"))
    images = next((data / name for name in ("images", "color") if (data / name).is_dir()), None)
    if not has_guidance and images is None:
        problems.append(
            f"neither language features ({guidance}) nor images (images/ or color/) to make them"
        )
    return SuiteScene(
        benchmark=benchmark,
        name=data.name,
        data=data,
        model=model,
        guidance=guidance if has_guidance else None,
        images=images,
        ground_truth=truth,
        protocols=protocols,
        problems=tuple(problems),
    )


def _selected(scenes: Sequence[SuiteScene], select: Sequence[str]) -> tuple[SuiteScene, ...]:
    if not select:
        return tuple(scenes)
    chosen: set[str] = set()
    for name in select:
        matches = [
            scene.key for scene in scenes if name in (scene.benchmark, scene.key, scene.name)
        ]
        if not matches:
            benchmarks = sorted({scene.benchmark for scene in scenes})
            raise InputError(
                "--select",
                f"{name!r} is no benchmark or scene here; benchmarks: {', '.join(benchmarks)}; "
                f"scenes: {', '.join(scene.key for scene in scenes)}",
            )
        chosen.update(matches)
    return tuple(scene for scene in scenes if scene.key in chosen)


def find_suite(
    root: str | os.PathLike[str],
    select: Sequence[str] = (),
    *,
    skip: str | os.PathLike[str] | None = None,
) -> tuple[SuiteScene, ...]:
    """Every scene under ``root`` (module docstring), sorted by benchmark then name.

    Args:
        root: the folder holding the benchmarks' releases and the trained models.
        select: benchmark names (``lerf_ovs``), ``benchmark/scene`` keys or scene names; empty:
            every scene.
        skip: a folder under ``root`` not to search (the suite's output folder).

    Returns:
        the scenes, each with its ``problems`` (empty when it can run).

    Raises:
        InputError: ``root`` is not a folder, is ``skip``, or holds no recognisable scene
            (naming the layouts looked for), two scenes have the same ``benchmark/scene`` key, or a
            ``select`` name matches nothing (listing what exists).
    """
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise InputError(root, "is a file; the suite root is the folder holding the benchmarks")
    if not root.is_dir():
        raise InputError(root, "suite root folder not found")
    if skip is not None and root.resolve() == Path(skip).resolve():
        raise InputError(
            root, "is also the output folder (-o): write the results to another folder"
        )
    folders, models = _walk(root, None if skip is None else Path(skip).resolve())
    if not folders:
        raise InputError(
            root,
            "holds no recognisable scene; looked for LangSplat's LERF-OVS release "
            "(lerf_ovs/<scene> with lerf_ovs/label/<scene>/frame_*.json), 3D-OVS scenes "
            "(<scene>/segmentations/classes.txt), ScanNet as OpenGaussian prepares it "
            "(scannet/<scene>/<scene>_vh_clean_2.labels.ply), OpenHype's ScanNet++ scenes "
            f"(scannetpp/<scene> with {ANNOTATION_FOLDER}/<scene>/*.json) and synthetic "
            "datasets (synthetic.json, thgs synth)",
        )
    named = _named_sources(models, root)
    scenes = [_scene(benchmark, folder, root, named) for benchmark, folder in folders]
    by_key: dict[str, SuiteScene] = {}
    for scene in scenes:
        if scene.key in by_key:
            raise InputError(
                root,
                f"two scenes are called {scene.key}: {by_key[scene.key].data} and {scene.data}; "
                "rename one, or --select a subfolder's scenes by running the suite on it",
            )
        by_key[scene.key] = scene
    ordered = sorted(scenes, key=lambda s: (BENCHMARKS.index(s.benchmark), s.name))
    return _selected(ordered, select)
