"""The demo: a synthetic scene, its semantic field, a few text queries, a report and pictures.

:func:`run_demo` generates a synthetic dataset once (cached), builds its field with the LERF
preset, scores every level against the exact ground truth, runs text queries with the automatic
selection (and the paper's, for comparison) and writes into ``out``::

    field.thgs              the semantic field (thgs.field.load_field)
    report.json, report.md  per-level agreement with ground truth, timings, query results
    levels.png              one view coloured by region at levels 0–3, beside the input image
    query-<text>.png        each query's selection (rendered opacity > 0.5) tinted, in the view
                            that shows most of it (:func:`thgs.views.best_views`)

The synthetic features are all-MiniLM-L6-v2 text embeddings standing in for CLIP
(docs/synthetic.md), so the queries run offline.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from thgs._atomic import atomic_output
from thgs.errors import InputError
from thgs.eval import matched_miou, purity
from thgs.eval.ground_truth import Hierarchy, read_hierarchy
from thgs.export import region_colors, slug, write_json, write_map_png
from thgs.field import SemanticField
from thgs.hierarchy.levels import LEVEL_NAMES
from thgs.pipeline import FieldConfig, Progress
from thgs.query import FieldQuery
from thgs.render import render
from thgs.scene import Scene, load_scene
from thgs.synthetic import evaluation_views
from thgs.synthetic.cache import default_cache, synthetic_dataset
from thgs.text import MINILM_SPACE, load_text_encoder
from thgs.views import best_views, highlighted, selection_masks
from thgs.workflows import BuildRequest, build_field_file

__all__ = [
    "DemoReport",
    "QueryResult",
    "demo_queries",
    "run_demo",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class QueryResult:
    """One text query.

    Attributes:
        text: the query.
        regions: ``(level, region, relevancy)`` the automatic selection chose, closest first.
        selected: number of Gaussians selected.
        truth: number of Gaussians whose ground-truth name (at any level) is the query.
        iou: 3-D IoU of the selection with those Gaussians (NaN when there are none).
        image: the picture of the selection.
        view: the view it is drawn in (its stem): the one that shows most of the selection,
            or the levels picture's view when nothing was selected.
        level: the field level of the query's name (3 objects, 2 parts, 1 sub-parts; 3 when the
            name is not in the scene).
        best_iou: 3-D IoU of the single most relevant region of ``level`` (the ``level``
            selection mode) with the same Gaussians.
        paper_iou: 3-D IoU of the paper's selection (top 3 of parts and objects).
        reason: why the automatic selection chose nothing, else None.
        confidence: the calibrated probability that the scene holds what the query names
            (:attr:`thgs.query.Selection.confidence`), None when unknown.
    """

    text: str
    regions: tuple[tuple[int, int, float], ...]
    selected: int
    truth: int
    iou: float
    image: Path
    view: str
    level: int
    best_iou: float
    paper_iou: float
    reason: str | None = None
    confidence: float | None = None


@dataclass(frozen=True)
class DemoReport:
    """What :func:`run_demo` did and measured.

    Attributes:
        dataset: the cached synthetic dataset.
        generated: whether it was generated now (False: reused from the cache).
        field_path: the saved semantic field.
        gaussians, views: scene size.
        region_counts: regions at levels 0–3.
        ground_truth_counts: ground-truth sub-parts, parts, objects.
        miou: matched-region mIoU of levels 1–3 against sub-parts, parts, objects.
        superpoint_purity: share of Gaussians whose superpoint's majority sub-part is theirs.
        timings: seconds per build stage.
        seconds: wall time of the whole demo.
        queries: one :class:`QueryResult` per query.
        files: everything written to ``out``.
    """

    dataset: Path
    generated: bool
    field_path: Path
    gaussians: int
    views: int
    region_counts: tuple[int, int, int, int]
    ground_truth_counts: tuple[int, int, int]
    miou: tuple[float, float, float]
    superpoint_purity: float
    timings: dict[str, float]
    seconds: float
    queries: tuple[QueryResult, ...]
    files: tuple[Path, ...]

    def to_json(self) -> dict:
        return {
            "dataset": str(self.dataset),
            "generated": self.generated,
            "field": str(self.field_path),
            "gaussians": self.gaussians,
            "views": self.views,
            "region_counts": dict(zip(LEVEL_NAMES, self.region_counts)),
            "ground_truth_counts": dict(zip(LEVEL_NAMES[1:], self.ground_truth_counts)),
            "miou": dict(zip(LEVEL_NAMES[1:], self.miou)),
            "superpoint_purity": self.superpoint_purity,
            "timings": self.timings,
            "build_seconds": sum(self.timings.values()),
            "seconds": self.seconds,
            "queries": [
                {
                    "text": q.text,
                    "regions": [
                        {"level": level, "region": region, "relevancy": score}
                        for level, region, score in q.regions
                    ],
                    "selected": q.selected,
                    "truth": q.truth,
                    "iou": None if np.isnan(q.iou) else q.iou,
                    "image": q.image.name,
                    "view": q.view,
                    "level": q.level,
                    "best_iou": None if np.isnan(q.best_iou) else q.best_iou,
                    "paper_iou": None if np.isnan(q.paper_iou) else q.paper_iou,
                    **({"reason": q.reason} if q.reason is not None else {}),
                    "confidence": q.confidence,
                }
                for q in self.queries
            ],
        }

    def markdown(self) -> str:
        levels = LEVEL_NAMES[1:]
        lines = [
            "# thgs demo",
            "",
            f"Scene: {self.dataset} ({self.gaussians:,} Gaussians, {self.views} views); "
            f"field: {self.field_path.name}.",
            "",
            "| level | regions | ground truth | matched mIoU |",
            "|---|---|---|---|",
            f"| superpoint | {self.region_counts[0]:,} | – | purity {self.superpoint_purity:.3f} |",
        ]
        for k, name in enumerate(levels):
            lines.append(
                f"| {name} | {self.region_counts[k + 1]:,} | {self.ground_truth_counts[k]} "
                f"| {self.miou[k]:.3f} |"
            )
        lines += [
            "",
            "| query | confidence | automatic selection (level:region relevancy) | 3-D IoU "
            "| paper's selection: 3-D IoU | best region of its level: 3-D IoU |",
            "|---|---|---|---|---|---|",
        ]
        for q in self.queries:
            regions = ", ".join(f"{lv}:{r} {s:.3f}" for lv, r, s in q.regions) or q.reason
            iou, paper, best = (
                "–" if np.isnan(value) else f"{value:.3f}"
                for value in (q.iou, q.paper_iou, q.best_iou)
            )
            confidence = "–" if q.confidence is None else f"{q.confidence:.2f}"
            lines.append(
                f"| {q.text} | {confidence} | {regions} | {iou} | {paper} "
                f"| {LEVEL_NAMES[q.level]}: {best} |"
            )
        timings = ", ".join(f"{stage} {seconds:.2f} s" for stage, seconds in self.timings.items())
        lines += [
            "",
            f"Build: {sum(self.timings.values()):.1f} s ({timings}).",
            f"Whole demo: {self.seconds:.1f} s.",
            "",
        ]
        return "\n".join(lines)


def demo_queries(hierarchy: Hierarchy, objects: int = 3, parts: int = 2) -> tuple[str, ...]:
    """Default queries: the first ``objects`` object names and ``parts`` part names that are not
    also object names (the floor left out), in the scene's order."""
    object_names = [n for n in dict.fromkeys(hierarchy.names[3]) if n != "floor"]
    part_names = [
        n for n in dict.fromkeys(hierarchy.names[2]) if n != "floor" and n not in object_names
    ]
    return tuple(object_names[:objects] + part_names[:parts])


def _iou(selected: np.ndarray, wanted: np.ndarray) -> float:
    if not wanted.any():
        return float("nan")
    return float((selected & wanted).sum() / (selected | wanted).sum())


def _render(scene: Scene, view: int, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    out = render(
        scene.gaussians, scene.cameras.select([view]), torch.from_numpy(values.astype(np.float32))
    )
    return out.image.numpy().astype(np.float64), out.alpha.numpy().astype(np.float64)


def _levels_picture(scene: Scene, field: SemanticField, view: int, rgb: np.ndarray) -> np.ndarray:
    panels = [rgb]
    for k in range(4):
        colors = region_colors(field.labels[:, k], seed=k)
        image, _ = _render(scene, view, colors)
        panels.append(image)
    return np.concatenate(panels, axis=1)


def run_demo(
    out: str | os.PathLike[str],
    *,
    cache: str | os.PathLike[str] | None = None,
    scene_preset: str = "synth-small",
    seed: int = 0,
    gaussians: int | None = None,
    views: int | None = None,
    queries: Sequence[str] | None = None,
    progress: Progress | None = None,
) -> DemoReport:
    """Generate (or reuse) a synthetic scene, build its field, query it, and report.

    Args:
        out: folder for the field, the report and the pictures (created; files replaced).
        cache: where generated datasets are kept (default :func:`default_cache`).
        scene_preset: ``synth-small`` (50k Gaussians, 24 views), ``synth-medium`` or
            ``synth-large``.
        seed: scene and oracle seed.
        gaussians, views: override the preset's size (smaller scenes for quick checks).
        queries: texts to query; default :func:`demo_queries` of the scene.
        progress: ``progress(stage, done, total)`` for ``generate`` (views written) and the
            stages of :func:`thgs.pipeline.build_field`.

    Returns:
        a :class:`DemoReport`; the files it lists are written atomically.

    Raises:
        InputError: an unknown preset, ``out`` that is a file, or an empty query.
        ThgsError: the offline text model is not installed (``pip install 'thgs[demo]'``).
    """
    started = time.perf_counter()
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    if queries is not None and not all(q.strip() for q in queries):
        raise InputError("queries", "an empty query")
    cache = Path(cache) if cache is not None else default_cache()
    encoder = load_text_encoder(MINILM_SPACE)
    folder, generated = synthetic_dataset(
        cache, scene_preset, seed, gaussians, views, encoder, progress
    )
    out.mkdir(parents=True, exist_ok=True)
    field_path = out / "field.thgs"
    request = BuildRequest(
        scene=folder, out=field_path, config=FieldConfig.lerf(), space=encoder.space, device="cpu"
    )
    field = build_field_file(request, progress=progress).field
    scene = load_scene(folder)
    files = [field_path]

    hierarchy = read_hierarchy(folder / "ground_truth.safetensors")
    truth = hierarchy.labels
    miou = tuple(matched_miou(field.labels[:, k], truth[:, k]) for k in (1, 2, 3))
    view = evaluation_views(len(scene.cameras))[0]
    colors = scene.gaussians.dc_colors().detach().cpu().numpy()
    rgb, _ = _render(scene, view, colors)
    levels_path = out / "levels.png"
    write_map_png(levels_path, _levels_picture(scene, field, view, rgb))
    files.append(levels_path)

    texts = tuple(queries) if queries is not None else demo_queries(hierarchy)
    names = {level: hierarchy.level_names(level) for level in (1, 2, 3)}
    results = []
    fq = FieldQuery(field, encoder)
    selections = fq.select(list(texts))
    shown = best_views(
        scene.gaussians, scene.cameras, np.stack([s.gaussians for s in selections], 1)
    )
    pictures = {view: rgb}
    for selection, best_view in zip(selections, shown.tolist()):
        text = selection.text
        drawn = view if best_view < 0 else best_view
        if drawn not in pictures:
            pictures[drawn] = _render(scene, drawn, colors)[0]
        camera = scene.cameras.select([drawn])
        wanted = np.zeros(len(field), dtype=bool)
        for level_names in names.values():
            wanted |= level_names == text
        # the coarsest level whose ground truth has this name (objects first)
        level = next((k for k in (3, 2, 1) if (names[k] == text).any()), 3)
        best = fq.select([text], fq.with_config(mode="level", level=level))[0]
        paper = fq.select([text], fq.with_config(mode="paper"))[0]
        iou, best_iou, paper_iou = (
            _iou(chosen.gaussians, wanted) for chosen in (selection, best, paper)
        )
        mask = selection_masks(scene.gaussians, camera, selection.gaussians)
        photo = pictures[drawn]
        tinted = highlighted(photo, mask)
        image = out / f"query-{slug(text)}.png"
        write_map_png(image, np.concatenate([photo, tinted], axis=1))
        files.append(image)
        results.append(
            QueryResult(
                text=text,
                regions=selection.regions,
                selected=int(selection.gaussians.sum()),
                truth=int(wanted.sum()),
                iou=iou,
                image=image,
                view=camera.stems[0],
                level=level,
                best_iou=best_iou,
                paper_iou=paper_iou,
                reason=selection.reason,
                confidence=selection.confidence,
            )
        )
        logger.info(
            "query %r: %d Gaussians, IoU %.3f (best region of level %d: %.3f)",
            text,
            selection.gaussians.sum(),
            iou,
            level,
            best_iou,
        )

    json_path, markdown_path = out / "report.json", out / "report.md"
    report = DemoReport(
        dataset=folder,
        generated=generated,
        field_path=field_path,
        gaussians=len(field),
        views=len(scene.cameras),
        region_counts=field.region_counts,
        ground_truth_counts=tuple(len(hierarchy.names[k]) for k in (1, 2, 3)),
        miou=miou,
        superpoint_purity=purity(field.labels[:, 0], truth[:, 0]),
        timings=dict(field.timings),
        seconds=time.perf_counter() - started,
        queries=tuple(results),
        files=(*files, json_path, markdown_path),
    )
    write_json(json_path, report.to_json())
    with atomic_output(markdown_path, "w") as handle:
        handle.write(report.markdown())
    return report
