"""Evaluate a segmentation against every benchmark ground truth found in a dataset folder.

:func:`find_ground_truth` looks for each benchmark's files in their usual places:

==================== ============================================================================
protocol             ground truth
==================== ============================================================================
``lerf`` (and        ``label/*.json`` (LERF-OVS, one file per frame; LangSplat's release keeps
``lerf-langsplat``,  them in ``label/<scene>/``: pass that folder with ``lerf=``), or the folder
``lerf-opengaussian``) itself when it holds ``frame_*.json``
``3dovs``            ``segmentations/`` with ``classes.txt``
``scannet``          ``scannet/*.labels.ply`` or ``*_vh_clean_2.labels.ply`` in the folder
``hierarchy``        ``ground_truth.safetensors`` (synthetic scenes)
==================== ============================================================================

A synthetic dataset (``thgs synth``) has all of them. :func:`evaluate_dataset` runs the
requested protocols and returns an :class:`EvalReport` (JSON and a markdown table).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from thgs.errors import InputError
from thgs.eval.evaluate import (
    ProtocolResult,
    evaluate_3dovs,
    evaluate_hierarchy,
    evaluate_lerf,
    evaluate_lerf_langsplat,
    evaluate_lerf_opengaussian,
    evaluate_scannet,
    read_lerf_frames,
)
from thgs.eval.ground_truth import read_hierarchy
from thgs.eval.scannet import read_scannet_labels
from thgs.eval.three_dovs import read_3dovs_segmentations
from thgs.query import FieldQuery
from thgs.render import RasterConfig
from thgs.scene import Cameras, Gaussians

__all__ = [
    "PROTOCOLS",
    "EvalReport",
    "GroundTruth",
    "evaluate_dataset",
    "find_ground_truth",
    "mean_over_scenes",
]

logger = logging.getLogger(__name__)

PROTOCOLS = ("lerf", "lerf-langsplat", "lerf-opengaussian", "3dovs", "scannet", "hierarchy")
"""Every protocol :func:`evaluate_dataset` runs, in report order."""

_NEEDS = {
    "lerf": "lerf",
    "lerf-langsplat": "lerf",
    "lerf-opengaussian": "lerf",
    "3dovs": "three_dovs",
    "scannet": "scannet",
    "hierarchy": "hierarchy",
}


@dataclass(frozen=True)
class GroundTruth:
    """Where each benchmark's ground truth of one scene is (None: not available).

    Attributes:
        lerf: folder of LERF-OVS frame label JSONs.
        three_dovs: 3D-OVS ``segmentations`` folder.
        scannet: ScanNet-style label PLY.
        hierarchy: synthetic ``ground_truth.safetensors``.
        scene_name: the scene's name (the folder's), for OpenGaussian's prompt lists.
    """

    lerf: Path | None = None
    three_dovs: Path | None = None
    scannet: Path | None = None
    hierarchy: Path | None = None
    scene_name: str = ""

    def available(self) -> tuple[str, ...]:
        """The protocols whose ground truth is present."""
        return tuple(p for p in PROTOCOLS if getattr(self, _NEEDS[p]) is not None)


def _lerf_folder(folder: Path) -> Path | None:
    for candidate in (folder / "label", folder):
        if candidate.is_dir() and any(candidate.glob("frame_*.json")):
            return candidate
    return None


def find_ground_truth(
    dataset: str | Path,
    *,
    lerf: str | Path | None = None,
    three_dovs: str | Path | None = None,
    scannet: str | Path | None = None,
) -> GroundTruth:
    """The ground truth in ``dataset`` (see the module table); explicit paths take precedence.

    Raises:
        InputError: ``dataset`` is not a folder, or an explicit path does not exist.
    """
    dataset = Path(dataset)
    if not dataset.is_dir():
        raise InputError(dataset, "dataset folder not found")
    for name, given in (("lerf", lerf), ("three_dovs", three_dovs), ("scannet", scannet)):
        if given is not None and not Path(given).exists():
            raise InputError(given, f"not found (given for {name})")
    if scannet is None:
        candidates = sorted(dataset.glob("scannet/*.labels.ply")) + sorted(
            dataset.glob("*_vh_clean_2.labels.ply")
        )
        scannet = candidates[0] if candidates else None
    segmentations = dataset / "segmentations"
    hierarchy = dataset / "ground_truth.safetensors"
    return GroundTruth(
        lerf=Path(lerf) if lerf is not None else _lerf_folder(dataset),
        three_dovs=Path(three_dovs)
        if three_dovs is not None
        else (segmentations if (segmentations / "classes.txt").is_file() else None),
        scannet=Path(scannet) if scannet is not None else None,
        hierarchy=hierarchy if hierarchy.is_file() else None,
        scene_name=dataset.resolve().name,
    )


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

    def table(self) -> str:
        """A markdown table: one row per (protocol, metric), values in [0, 1]."""
        lines = ["| protocol | metric | value | scored items |", "|---|---|---|---|"]
        for result in self.results:
            for name, value in result.metrics.items():
                lines.append(f"| {result.protocol} | {name} | {value:.4f} | {len(result.items)} |")
        return "\n".join(lines)


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
) -> EvalReport:
    """Run ``protocols`` (default: every one whose ground truth is present).

    Args:
        ground_truth: from :func:`find_ground_truth`.
        engine: the query engine, text → Gaussians (``FieldQuery(field, encoder)``, or on any
            :class:`thgs.query.Regions`).
        gaussians: the N Gaussians; cameras: the scene's cameras (needed by the 2D protocols).
        protocols: names from :data:`PROTOCOLS`.
        scannet_level: the level whose features classify ScanNet points.
        raster: how the 2D protocols render views: the settings the field was lifted with
            (:func:`thgs.pipeline.lifted_raster`), so that masks are rendered as they were lifted.
        progress: ``progress(protocol, done, total)`` per evaluated frame.

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
        if name not in PROTOCOLS:
            raise InputError("protocol", f"unknown {name!r}; choose from {', '.join(PROTOCOLS)}")
        if name not in available:
            raise InputError("protocol", f"{name}: its ground truth is not in the dataset")
        if name not in ("scannet", "hierarchy") and cameras is None:
            raise InputError("protocol", f"{name} renders views, but the scene has no cameras")
    results: list[ProtocolResult] = []
    seconds: dict[str, float] = {}
    wants_lerf = any(name.startswith("lerf") for name in protocols)
    frames = read_lerf_frames(ground_truth.lerf) if wants_lerf and ground_truth.lerf else []
    for name in [p for p in PROTOCOLS if p in protocols]:
        started = time.perf_counter()

        def step(done: int, total: int, name: str = name) -> None:
            if progress is not None:
                progress(name, done, total)

        assert cameras is not None or name in ("scannet", "hierarchy")
        if name == "lerf":
            results.append(
                evaluate_lerf(engine, gaussians, cameras, frames, raster=raster, progress=step)
            )
        elif name == "lerf-langsplat":
            results.append(
                evaluate_lerf_langsplat(
                    engine, gaussians, cameras, frames, raster=raster, progress=step
                )
            )
        elif name == "lerf-opengaussian":
            results.append(
                evaluate_lerf_opengaussian(
                    engine,
                    gaussians,
                    cameras,
                    frames,
                    scene_name=ground_truth.scene_name,
                    raster=raster,
                    progress=step,
                )
            )
        elif name == "3dovs":
            segmentations = read_3dovs_segmentations(ground_truth.three_dovs)
            results.append(
                evaluate_3dovs(
                    engine, gaussians, cameras, segmentations, raster=raster, progress=step
                )
            )
        elif name == "scannet":
            labels = read_scannet_labels(ground_truth.scannet)
            results.extend(evaluate_scannet(engine, gaussians, labels, level=scannet_level))
        else:
            hierarchy = read_hierarchy(ground_truth.hierarchy)
            results.append(evaluate_hierarchy(np.asarray(engine.regions.labels), hierarchy))
        seconds[name] = time.perf_counter() - started
        logger.info("%s: %.2f s", name, seconds[name])
    info = {
        "scene": ground_truth.scene_name,
        "space": engine.regions.space,
        "gaussians": len(gaussians),
        "ground_truth": {
            key: None if value is None else str(value)
            for key, value in (
                ("lerf", ground_truth.lerf),
                ("3dovs", ground_truth.three_dovs),
                ("scannet", ground_truth.scannet),
                ("hierarchy", ground_truth.hierarchy),
            )
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
