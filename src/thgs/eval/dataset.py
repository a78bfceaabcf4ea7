"""Evaluate a segmentation against every benchmark ground truth found in a dataset folder.

:func:`find_ground_truth` asks every registered kind of ground truth
(:mod:`thgs.eval.protocols`) where it lies in the folder:

==================== ============================================================================
source (protocols)   ground truth
==================== ============================================================================
``lerf`` (``lerf``,  ``label/frame_*.json`` (LERF-OVS, one file per frame), LangSplat's sibling
``lerf-langsplat``,  ``../label/<scene>/`` (``lerf_ovs/label/teatime`` for ``lerf_ovs/teatime``),
``lerf-opengaussian``) or the folder itself when it holds ``frame_*.json``; ``lerf=`` may name
                     the scene's label folder or the ``label/`` folder of every scene
``three_dovs``       ``segmentations/`` with ``classes.txt``
(``3dovs``)
``scannet``          ``scannet/*.labels.ply`` or ``*_vh_clean_2.labels.ply`` in the folder
``openhype``         ``openhype_scannetpp_benchmark/<scene>/*.json`` (OpenHype's ScanNet++
(``openhype``)       annotations) beside the folder or beside its parent; ``openhype=`` may name
                     the scene's annotation folder or the one of every scene
``hierarchy``        ``ground_truth.safetensors`` (synthetic scenes)
==================== ============================================================================

A synthetic dataset (``thgs synth``) has all of them. :func:`evaluate_dataset` runs the
requested protocols, in the registry's order, and returns an :class:`EvalReport` (JSON and a
markdown table).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from thgs.errors import InputError
from thgs.eval.evaluate import ProtocolResult
from thgs.eval.protocols import EvalContext, get_protocol, protocol_names, source_names, sources
from thgs.query import FieldQuery
from thgs.render import RasterConfig
from thgs.scene import Cameras, Gaussians, load_cameras
from thgs.scene.loader import camera_disagreement

__all__ = [
    "EvalReport",
    "GroundTruth",
    "check_ground_truth_scene",
    "evaluate_dataset",
    "find_ground_truth",
    "mean_over_scenes",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class GroundTruth:
    """Where each kind of ground truth of one scene is.

    Attributes:
        paths: source name (:func:`thgs.eval.protocols.source_names`, e.g. ``"lerf"``,
            ``"three_dovs"``) → its file or folder; a kind the scene lacks is absent.
        scene_name: the scene's name: the dataset folder's name as given (a symbolic link's
            own name, not its target's); it chooses OpenGaussian's prompt list and LangSplat's
            ``../label/<scene>`` folder.
    """

    paths: Mapping[str, Path] = field(default_factory=dict)
    scene_name: str = ""

    def path(self, source: str) -> Path | None:
        """The path of ``source``'s ground truth, or None."""
        return self.paths.get(source)

    def available(self) -> tuple[str, ...]:
        """The protocols whose ground truth is present, in report order."""
        return tuple(name for name in protocol_names() if get_protocol(name).source in self.paths)


def find_ground_truth(dataset: str | Path, **given: str | Path | None) -> GroundTruth:
    """The ground truth in ``dataset`` (see the module table); explicit paths take precedence.

    Args:
        dataset: the scene's dataset folder.
        given: a path per source name where it is not in the usual place, e.g.
            ``lerf="lerf_ovs/label/teatime"`` (or ``lerf="lerf_ovs/label"``, the folder of
            every scene's labels: its ``<scene name>/`` is taken), ``three_dovs=…``,
            ``scannet=…``, ``openhype=…`` (None: look).

    Raises:
        InputError: ``dataset`` is not a folder, an explicit path does not exist or holds no
            ground truth of that kind, a keyword names no source, or two places in and around
            ``dataset`` hold the same kind (the message names both and the flag that decides).
    """
    dataset = Path(dataset)
    if not dataset.is_dir():
        raise InputError(dataset, "dataset folder not found")
    unknown = sorted(set(given) - set(source_names()))
    if unknown:
        raise InputError(
            "ground truth", f"unknown kind {unknown[0]!r}; known: {', '.join(source_names())}"
        )
    scene_name = Path(os.path.abspath(dataset)).name
    paths = {}
    for source in sources():
        explicit = given.get(source.name)
        if explicit is not None and not Path(explicit).exists():
            raise InputError(explicit, f"not found (given for {source.name})")
        if explicit is None:
            found = source.find(dataset)
        elif source.given is not None:
            found = source.given(Path(explicit), scene_name)
        else:
            found = Path(explicit)
        if found is not None:
            paths[source.name] = found
    return GroundTruth(paths, scene_name)


@dataclass(frozen=True)
class EvalReport:
    """The results of every protocol run on one scene.

    Attributes:
        results: one :class:`ProtocolResult` per protocol (ScanNet: one per class subset).
        seconds: wall time per protocol.
        info: what was evaluated (dataset, field, embedding space, …).
    """

    results: tuple[ProtocolResult, ...]
    seconds: dict[str, float]
    info: dict[str, Any]

    def metric(self, protocol: str, name: str) -> float:
        """One headline number, e.g. ``report.metric("lerf", "miou")``."""
        for result in self.results:
            if result.protocol == protocol:
                return result.metrics[name]
        raise KeyError(f"no protocol {protocol!r} in this report")

    def to_json(self) -> dict[str, Any]:
        return {
            "info": self.info,
            "seconds": self.seconds,
            "results": [result.to_json() for result in self.results],
        }

    def notes(self) -> list[str]:
        """Every result's notes as ``"<protocol>: <note>"``, in result order."""
        return [f"{result.protocol}: {note}" for result in self.results for note in result.notes]

    def table(self) -> str:
        """A markdown table: one row per (protocol, metric), values in [0, 1]; the results'
        notes (:meth:`notes`) follow it as a list."""
        lines = ["| protocol | metric | value | scored items |", "|---|---|---|---|"]
        for result in self.results:
            for name, value in result.metrics.items():
                lines.append(f"| {result.protocol} | {name} | {value:.4f} | {len(result.items)} |")
        if self.notes():
            lines += ["", *(f"- {note}" for note in self.notes())]
        return "\n".join(lines)


def check_ground_truth_scene(dataset: str | os.PathLike[str], cameras: Cameras | None) -> None:
    """Refuse a dataset whose cameras are not the field's scene's: when ``dataset`` holds
    cameras (:func:`thgs.scene.load_cameras`) and ``cameras`` are known, the images they share
    must exist and agree (:func:`thgs.scene.loader.camera_disagreement`, intrinsics and camera
    centres up to a similarity). A dataset without cameras (labels only) is not checked.

    Raises:
        InputError: the dataset is another capture (``thgs eval --other-scene`` skips this).
    """
    if cameras is None:
        return
    try:
        theirs = load_cameras(dataset)[0]
    except InputError:
        return
    problem = camera_disagreement(theirs, cameras, subset=True)
    if problem is not None:
        raise InputError(
            dataset,
            f"is not the scene the field was built on: {problem}; its ground truth would be "
            "scored against another capture (--other-scene scores it anyway)",
        )


def evaluate_dataset(
    ground_truth: GroundTruth,
    engine: FieldQuery,
    gaussians: Gaussians,
    cameras: Cameras | None,
    *,
    protocols: Sequence[str] | None = None,
    scannet_level: int = 3,
    raster: RasterConfig = RasterConfig(),
    progress: Callable[[str, int, int], None] | None = None,
    rescale_labels: bool = False,
) -> EvalReport:
    """Run ``protocols`` (default: every one whose ground truth is present).

    Args:
        ground_truth: from :func:`find_ground_truth`.
        engine: the query engine, text → Gaussians (``FieldQuery(field, encoder)``, or on any
            :class:`thgs.query.Regions`).
        gaussians: the N Gaussians; cameras: the scene's cameras (needed by the 2D protocols).
        protocols: registered protocol names (:func:`thgs.eval.protocols.protocol_names`).
        scannet_level: the level whose features classify ScanNet points.
        raster: how the 2D protocols render views: the settings the field was lifted with
            (:func:`thgs.pipeline.lifted_raster`), so that masks are rendered as they were lifted.
        progress: ``progress(protocol, done, total)`` per evaluated frame.
        rescale_labels: score 2-D labels whose aspect ratio is not their camera's by stretching
            them (by default that is refused: they belong to another capture). Labels of the
            camera's aspect ratio at another size are always scaled to it.

    Raises:
        InputError: an unknown protocol, one whose ground truth is missing, or a 2D protocol
            without cameras.
    """
    available = ground_truth.available()
    if protocols is None:
        protocols = available
        if not protocols:
            raise InputError("dataset", "holds no ground truth of any benchmark (see thgs eval)")
    for name in protocols:
        protocol = get_protocol(name)
        if name not in available:
            raise InputError("protocol", f"{name}: its ground truth is not in the dataset")
        if protocol.needs_cameras and cameras is None:
            raise InputError("protocol", f"{name} renders views, but the scene has no cameras")
    results: list[ProtocolResult] = []
    seconds: dict[str, float] = {}
    shared: dict = {}
    for name in [p for p in protocol_names() if p in protocols]:
        protocol = get_protocol(name)
        started = time.perf_counter()

        def step(done: int, total: int, name: str = name) -> None:
            if progress is not None:
                progress(name, done, total)

        path = ground_truth.path(protocol.source)
        assert path is not None  # checked above
        context = EvalContext(
            engine,
            gaussians,
            cameras,
            path,
            scene_name=ground_truth.scene_name,
            raster=raster,
            options={"scannet_level": scannet_level, "rescale_labels": rescale_labels},
            progress=step,
            shared=shared,
        )
        results.extend(protocol.evaluate(context))
        seconds[name] = time.perf_counter() - started
        logger.info("%s: %.2f s", name, seconds[name])
    info = {
        "scene": ground_truth.scene_name,
        "space": engine.regions.space,
        "gaussians": len(gaussians),
        "ground_truth": {
            source: None if ground_truth.path(source) is None else str(ground_truth.path(source))
            for source in source_names()
        },
    }
    return EvalReport(tuple(results), seconds, info)


def mean_over_scenes(reports: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """The last step of every protocol's averaging: each metric's mean over scenes.

    Args:
        reports: :meth:`EvalReport.to_json` documents (e.g. read from ``thgs eval`` reports),
            one per scene.

    Returns:
        protocol → metric → mean over the scenes that report it (null metrics are skipped).

    Raises:
        InputError: a document that is not a ``thgs eval`` report.
    """
    values: dict[str, dict[str, list[float]]] = {}
    for index, report in enumerate(reports):
        results = report.get("results") if isinstance(report, Mapping) else None
        if not isinstance(results, list):
            raise InputError(f"report {index}", "is not a thgs eval report (no 'results' list)")
        for result in results:
            metrics = values.setdefault(result["protocol"], {})
            for name, value in result["metrics"].items():
                if value is not None:
                    metrics.setdefault(name, []).append(float(value))
    return {
        protocol: {name: float(np.mean(v)) for name, v in metrics.items()}
        for protocol, metrics in values.items()
    }
