"""A query's or a pick's results as files: what ``thgs query``, ``thgs pick`` and ``thgs export``
write, as library calls (the CLI only parses arguments and prints).

- :func:`write_query_results` — ``results.json`` (each query's regions, sizes, Gaussian count,
  the selection settings) and, for the views asked, each query's 2D mask and relevancy maps
  (``<out>/<query>/<view>.png``, ``<view>-relevancy-<level>.png``).
- :func:`write_query_selections` — each non-empty selection as ``<query>.ply`` in the scene's own
  PLY layout, and ``selections.json``.
- :func:`write_pick_results` — the picked region's mask in the view, its Gaussians as a PLY and
  ``pick.json`` (the region chain, parent and children).

Every file is written atomically (:mod:`thgs.export`), and the JSON summary is written last, so a
summary that exists lists files that exist.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from thgs._atomic import staging_folder
from thgs.errors import InputError
from thgs.export import slug, write_json, write_map_png, write_mask_png, write_selection_ply
from thgs.field import SemanticField
from thgs.hierarchy.levels import LEVEL_NAMES
from thgs.query import FieldQuery, QueryConfig, Selection
from thgs.render import RasterConfig
from thgs.scene import Cameras, Gaussians
from thgs.views import Pick, best_views, relevancy_map, selection_masks

__all__ = [
    "PickFiles",
    "QueryFiles",
    "pick_summary",
    "unique_names",
    "write_pick_results",
    "write_query_results",
    "write_query_selections",
]

logger = logging.getLogger(__name__)


def unique_names(texts: Sequence[str], taken: Collection[str] = ()) -> list[str]:
    """File-name-safe names for queries (:func:`thgs.export.slug`), a repeated one, or one in
    ``taken`` (names other outputs use), numbered ``-2``, ``-3`` …, in order."""
    names: list[str] = []
    for text in texts:
        name, k = slug(text), 2
        while name in names or name in taken:
            name, k = f"{slug(text)}-{k}", k + 1
        names.append(name)
    return names


@dataclass(frozen=True)
class QueryFiles:
    """What :func:`write_query_results` wrote.

    Attributes:
        selections: one :class:`thgs.query.Selection` per query, in order.
        results: the ``results.json`` path.
        files: per query's file name (:func:`unique_names`), its masks and maps, view by view.
    """

    selections: tuple[Selection, ...]
    results: Path
    files: dict[str, tuple[Path, ...]]


def _settings(engine: FieldQuery, config: QueryConfig) -> dict[str, Any]:
    return {
        "mode": config.mode,
        "searched_levels": list(config.searched_levels),
        "threshold": next(
            (v for v in (config.min_relevancy, config.threshold) if v is not None),
            engine.threshold,
        ),
        "top": config.top,
        "min_gaussians": (
            engine.min_gaussians if config.min_gaussians is None else config.min_gaussians
        ),
    }


def write_query_results(
    out: str | os.PathLike[str],
    engine: FieldQuery,
    texts: Sequence[str],
    *,
    field_name: str,
    gaussians: Gaussians | None = None,
    cameras: Cameras | None = None,
    mask_threshold: float = 0.5,
    relevancy: bool = False,
    best_view: bool = False,
    raster: RasterConfig = RasterConfig(),
) -> QueryFiles:
    """Answer ``texts`` with ``engine`` and write the answers to ``out``.

    Args:
        out: the folder to write into (created if missing). Everything is first written to a
            hidden folder beside it and moved in only when all of it is written, results.json
            last: a failure part-way (a full disk, Ctrl-C) leaves ``out`` as it was.
        engine: the query engine (its config is the selection rule).
        texts: the queries, at least one.
        field_name: how ``results.json`` names the field (e.g. its path).
        gaussians: the scene's N Gaussians, needed with ``cameras``.
        cameras: the views to draw masks in (none: only ``results.json``).
        mask_threshold: rendered opacity of the selection above which a pixel is in the mask.
        relevancy: also draw per-pixel relevancy maps (0–255) for every searched level.
        best_view: draw each query only in the one of ``cameras`` that shows most of its
            selection (:func:`thgs.views.best_views`; none when no view shows it), recorded as
            its ``"view"`` in ``results.json``.
        raster: the rasterization settings (the ones the field was lifted with:
            :func:`thgs.pipeline.lifted_raster`).

    Raises:
        InputError: no query, cameras without Gaussians, or what the engine refuses.
    """
    out = Path(out)
    if not texts:
        raise InputError("texts", "give at least one query text")
    if cameras is not None and gaussians is None:
        raise InputError("gaussians", "drawing masks in views needs the scene's Gaussians")
    if relevancy and cameras is None:
        raise InputError("relevancy", "relevancy maps are drawn in views: pass the cameras")
    config = engine.config
    selections = engine.select(list(texts))
    names = unique_names(texts)
    written: dict[str, list[Path]] = {name: [] for name in names}  # relative to ``out``
    shown: list[str | None] = [None] * len(names)
    with staging_folder(out) as stage:
        if cameras is not None and gaussians is not None and len(cameras):
            selected = np.stack([s.gaussians for s in selections], axis=1)
            relevancies = {
                k: np.stack([engine.gaussian_relevancy(text, k) for text in texts], axis=1)
                for k in (config.searched_levels if relevancy else ())
            }
            drawn = {index: list(range(len(names))) for index in range(len(cameras))}
            if best_view:
                views = best_views(
                    gaussians, cameras, selected, threshold=mask_threshold, config=raster
                )
                drawn = {
                    index: [q for q, view in enumerate(views.tolist()) if view == index]
                    for index in sorted(set(views.tolist()) - {-1})
                }
                shown = [None if view < 0 else cameras.stems[view] for view in views.tolist()]
            for index, queries in drawn.items():
                camera = cameras.select([index])
                stem = camera.stems[0]
                masks = selection_masks(
                    gaussians, camera, selected[:, queries], threshold=mask_threshold, config=raster
                )
                for column, q in enumerate(queries):
                    write_mask_png(stage / names[q] / f"{stem}.png", masks[..., column])
                    written[names[q]].append(Path(names[q]) / f"{stem}.png")
                for k, per_gaussian in relevancies.items():
                    maps = relevancy_map(gaussians, camera, per_gaussian[:, queries], config=raster)
                    for column, q in enumerate(queries):
                        relative = Path(names[q]) / f"{stem}-relevancy-{LEVEL_NAMES[k]}.png"
                        write_map_png(stage / relative, maps[..., column])
                        written[names[q]].append(relative)
        files = {name: [out / relative for relative in paths] for name, paths in written.items()}
        write_json(
            stage / "results.json",
            {
                "field": field_name,
                "space": engine.regions.space,
                "config": _settings(engine, config),
                "queries": [
                    {
                        **selection.to_json(engine.regions),
                        **({"view": view} if best_view else {}),
                        "files": [str(p) for p in files[name]],
                    }
                    for selection, name, view in zip(selections, names, shown)
                ],
            },
        )
        # everything is written: move it into ``out`` (renames), results.json last
        out.mkdir(parents=True, exist_ok=True)
        for relative in [path for paths in written.values() for path in paths]:
            (out / relative).parent.mkdir(parents=True, exist_ok=True)
            os.replace(stage / relative, out / relative)
        results = out / "results.json"
        os.replace(stage / "results.json", results)
    logger.info("wrote %s (%d queries)", results, len(selections))
    return QueryFiles(tuple(selections), results, {k: tuple(v) for k, v in files.items()})


def write_query_selections(
    out: str | os.PathLike[str],
    engine: FieldQuery,
    texts: Sequence[str],
    gaussians: Gaussians,
    *,
    field_name: str,
    taken: Collection[str] = (),
) -> tuple[tuple[Selection, ...], list[Path]]:
    """Each query's selection as ``<out>/<query>.ply`` (empty ones skipped; names as
    :func:`unique_names`, clear of ``taken``), then ``selections.json`` listing every query.
    If a file cannot be written, the ones already written are removed: all or nothing.

    Returns:
        the selections, and the written paths (``selections.json`` last).

    Raises:
        InputError: no query, Gaussians of another number than the engine's regions, or a file
            that cannot be written (the message names it and the system's reason).
    """
    out = Path(out)
    if not texts:
        raise InputError("texts", "give at least one query text")
    if len(gaussians) != len(engine.regions):
        raise InputError(
            "gaussians",
            f"the field has {len(engine.regions)} Gaussians, the scene {len(gaussians)}",
        )
    selections = engine.select(list(texts))
    written: list[Path] = []
    summary = []
    path = out / "selections.json"
    try:
        for selection, name in zip(selections, unique_names(texts, taken)):
            entry = selection.to_json(engine.regions)
            if not selection.empty:
                path = out / f"{name}.ply"
                write_selection_ply(path, gaussians, selection.gaussians)
                written.append(path)
                entry["ply"] = str(path)
            summary.append(entry)
        path = out / "selections.json"
        write_json(path, {"field": field_name, "mode": engine.config.mode, "queries": summary})
        written.append(path)
    except BaseException as error:
        for done in written:
            done.unlink(missing_ok=True)
        if isinstance(error, OSError):
            raise InputError(path, f"cannot be written: {error.strerror or error}") from error
        raise
    return tuple(selections), written


def pick_summary(field: SemanticField, picked: Pick, level: int) -> dict[str, Any]:
    """JSON-ready description of a pick at ``level`` (0..3): the regions at every level, the
    chosen region, its Gaussian count, parent (None at level 3) and children (none at 0)."""
    level = field.levels.checked_level(level)
    region = picked.region(level)
    return {
        "view": picked.view,
        "pixel": list(picked.pixel),
        "gaussian": picked.gaussian,
        "regions": dict(zip(LEVEL_NAMES, picked.regions)),
        "level": level,
        "region": region,
        "gaussians": int(field.sizes(level)[region]),
        "parent": field.parent(level, region) if level < 3 else None,
        "children": field.children(level, region).tolist() if level > 0 else [],
    }


@dataclass(frozen=True)
class PickFiles:
    """What :func:`write_pick_results` wrote: the summary (:func:`pick_summary` plus the field
    and the files) and the paths of the mask, the PLY and ``pick.json``."""

    summary: dict[str, Any]
    mask: Path
    ply: Path
    json: Path


def write_pick_results(
    out: str | os.PathLike[str],
    field: SemanticField,
    gaussians: Gaussians,
    camera: Cameras,
    picked: Pick,
    level: int,
    *,
    field_name: str,
    raster: RasterConfig = RasterConfig(),
) -> PickFiles:
    """The picked region at ``level``: its mask in ``camera`` (one view) as
    ``<view>-<level name>-<region>.png``, its Gaussians as ``<level name>-<region>.ply`` and
    ``pick.json``, written last.

    Raises:
        InputError: a camera that is not one view, a level outside 0..3.
    """
    out = Path(out)
    if len(camera) != 1:
        raise InputError("camera", f"must be one view, got {len(camera)}")
    summary = pick_summary(field, picked, level)
    name = f"{LEVEL_NAMES[summary['level']]}-{summary['region']}"
    members = field.labels[:, summary["level"]] == summary["region"]
    mask_path = out / f"{camera.stems[0]}-{name}.png"
    ply_path = out / f"{name}.ply"
    write_mask_png(mask_path, selection_masks(gaussians, camera, members, config=raster))
    write_selection_ply(ply_path, gaussians, members)
    summary = {"field": field_name, **summary, "files": [str(mask_path), str(ply_path)]}
    json_path = out / "pick.json"
    write_json(json_path, summary)
    return PickFiles(summary, mask_path, ply_path, json_path)
