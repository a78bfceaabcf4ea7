"""The ``thgs`` command line: a thin layer over the library, and the only code that prints."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import sys
import time
from pathlib import Path
from typing import Annotated, ClassVar, Literal

import tyro
from rich.console import Console
from rich.logging import RichHandler
from rich.table import Table

from thgs.errors import ThgsError
from thgs.scene import SceneSummary, load_scene, summarize

__all__ = ["build", "demo", "entrypoint", "info", "synth"]

_stdout = Console()
_stderr = Console(stderr=True)


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(message)s",
        handlers=[RichHandler(console=_stderr, show_path=False, show_time=False)],
        force=True,
    )


def _span(low: float, high: float, digits: int = 3) -> str:
    return f"{low:.{digits}g}" if low == high else f"{low:.{digits}g}–{high:.{digits}g}"


def _render_summary(path: Path, found: tuple[str, ...], summary: SceneSummary) -> Table:
    table = Table(title=f"thgs info {path}", show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    details = [f"{summary.kind.upper()}", f"SH degree {summary.sh_degree}"]
    if summary.has_normals:
        details.append("normals stored")
    if summary.extra_properties:
        details.append(f"extra properties {', '.join(summary.extra_properties)}")
    table.add_row("Gaussians", f"{summary.count:,} ({', '.join(details)})")

    def box(low: tuple[float, ...], high: tuple[float, ...]) -> str:
        return "  ".join(f"{axis} [{lo:.3f}, {hi:.3f}]" for axis, lo, hi in zip("xyz", low, high))

    table.add_row("bounding box", box(summary.bbox_min, summary.bbox_max))
    table.add_row("1–99th pct box", box(*summary.bbox_1_99))
    q = summary.opacity_quantiles
    table.add_row(
        "opacity",
        f"mean {summary.opacity_mean:.3f}, median {q[2]:.3f}, quartiles {q[1]:.3f}–{q[3]:.3f}, "
        f"range {q[0]:.3f}–{q[4]:.3f}; {100 * summary.low_opacity_share:.1f} % below 0.1",
    )
    table.add_row("largest scale", f"median {summary.scale_median:.4g} scene units")
    cameras = summary.cameras
    if cameras is None:
        table.add_row(
            "cameras", "none (pass --source with COLMAP, transforms.json or cameras.json)"
        )
    else:
        table.add_row(
            "cameras",
            f"{cameras.count} from {cameras.source}, {_span(*cameras.width_range, 6)}×"
            f"{_span(*cameras.height_range, 6)} px, focal {_span(*cameras.focal_range, 5)} px",
        )
    for line in found:
        table.add_row("found", line)
    return table


def info(
    path: Path,
    /,
    *,
    source: Path | None = None,
    iteration: int | None = None,
    images: str | None = None,
    scale: float = 1.0,
    undo_applied_transform: bool = False,
    json_output: Annotated[bool, tyro.conf.arg(name="json")] = False,
    verbose: bool = False,
) -> None:
    """Describe a Gaussian scene: count, kind, SH degree, bounding box, opacities, cameras.

    Args:
        path: a trained 3DGS/2DGS model folder (point_cloud/iteration_*/point_cloud.ply,
            cameras.json) or a .ply file.
        source: cameras from here instead of the model's cameras.json: a training data folder
            (COLMAP sparse/0 + images/, transforms.json) or a camera file.
        iteration: which iteration_* of a model folder (default: the newest).
        images: image folder name inside the source, e.g. images_4 (default: images, if present).
        scale: image size / camera-file size, e.g. 0.25 for images_4. Never guessed.
        undo_applied_transform: map nerfstudio transforms.json poses back to the COLMAP frame.
        json_output: print the summary as JSON instead of a table.
        verbose: log what is read.
    """
    _setup_logging(verbose)
    scene = load_scene(
        path,
        source=source,
        iteration=iteration,
        images=images,
        scale=scale,
        undo_applied_transform=undo_applied_transform,
    )
    summary = summarize(scene)
    if json_output:
        document = {"path": str(path), "found": list(scene.found), **dataclasses.asdict(summary)}
        _stdout.print_json(json.dumps(document))
    else:
        _stdout.print(_render_summary(path, scene.found, summary))


def synth(
    preset: Literal["synth-small", "synth-medium", "synth-large"],
    out: Path,
    /,
    *,
    seed: int = 0,
    kind: Literal["2dgs", "3dgs"] = "2dgs",
    gaussians: int | None = None,
    views: int | None = None,
    severity: float = 0.5,
    feature_noise: float = 0.5,
    evaluation_views: int = 4,
    overwrite: bool = False,
    verbose: bool = False,
) -> None:
    """Generate a synthetic benchmark scene with exact hierarchy ground truth.

    Writes a trained-model-like folder (PLY, cameras.json), COLMAP sparse/0, transforms.json,
    rendered images, oracle guidance in LangSplat's language_features layout, LERF-OVS-style
    labels, 3DOVS-style segmentations, ScanNet-style labels and the ground-truth hierarchy.

    Args:
        preset: scene size (synth-small: ~50k Gaussians, 24 views, 320×240; synth-medium: ~300k,
            60, 640×480; synth-large: ~1M, 200, 986×728).
        out: the dataset folder to create.
        seed: every random draw derives from it; same seed, same bytes.
        kind: 2DGS surfels or 3DGS ellipsoids.
        gaussians: override the preset's Gaussian count.
        views: override the preset's number of views.
        severity: SAM-like fault rate multiplier for the oracle masks (0 = clean ground truth).
        feature_noise: noise on the oracle's text-embedding features.
        evaluation_views: views that get LERF-OVS / 3DOVS labels.
        overwrite: replace an existing dataset folder.
        verbose: log what is done.
    """
    from rich.progress import Progress

    from thgs.synthetic import (
        DatasetConfig,
        OracleConfig,
        generate_scene,
        write_dataset,
    )
    from thgs.synthetic import preset as scene_preset
    from thgs.text import MiniLMEncoder

    _setup_logging(verbose)
    overrides = {"seed": seed, "kind": kind}
    if gaussians is not None:
        overrides["gaussians"] = gaussians
    if views is not None:
        overrides["views"] = views
    config = scene_preset(preset, **overrides)
    start = time.perf_counter()
    scene = generate_scene(config)
    encoder = MiniLMEncoder()
    oracle = OracleConfig(severity=severity, feature_noise=feature_noise, seed=seed)
    with Progress(console=_stderr, transient=True) as bar:
        task = bar.add_task("rendering views", total=len(scene.cameras))
        summary = write_dataset(
            out,
            scene,
            encoder,
            oracle=oracle,
            config=DatasetConfig(evaluation_views=evaluation_views),
            overwrite=overwrite,
            progress=lambda done, total: bar.update(task, completed=done),
        )
    seconds = time.perf_counter() - start
    _stdout.print(
        f"wrote {summary.path}: {summary.gaussians:,} Gaussians, {summary.views} views, "
        f"{summary.masks:,} masks, {len(summary.categories)} label categories in "
        f"{len(summary.evaluation_views)} evaluation views; {summary.bytes / 1e6:.1f} MB "
        f"in {seconds:.1f} s"
    )


class _StageBars:
    """A rich progress display for ``progress(stage, done, total)`` callbacks: one bar per stage,
    each finished bar showing its time."""

    _LABELS: ClassVar[dict[str, str]] = {
        "generate": "generating the synthetic scene",
        "lift": "lifting masks onto Gaussians",
        "partition": "KNN graph, reweighting, cut pursuit",
        "merge": "merging levels 1–3",
        "features": "region features",
    }

    def __init__(self, bar) -> None:
        self._bar = bar
        self._tasks: dict[str, int] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage not in self._tasks:
            label = self._LABELS.get(stage, stage)
            self._tasks[stage] = self._bar.add_task(label, total=total)
        self._bar.update(self._tasks[stage], completed=done, total=total)


def _stage_progress():
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=_stderr,
    )


def _counts_table(title: str, counts, timings: dict[str, float]) -> Table:
    from thgs.field import FIELD_LEVELS

    table = Table(title=title, show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    table.add_row(
        "regions", ", ".join(f"{name} {count:,}" for name, count in zip(FIELD_LEVELS, counts))
    )
    table.add_row(
        "time",
        f"{sum(timings.values()):.1f} s ("
        + ", ".join(f"{stage} {seconds:.2f}" for stage, seconds in timings.items())
        + ")",
    )
    return table


def build(
    scene: Path,
    /,
    *,
    out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
    guidance: Path | None = None,
    preset: Literal["lerf", "3dovs"] = "lerf",
    source: Path | None = None,
    iteration: int | None = None,
    images: str | None = None,
    scale: float = 1.0,
    resize: bool = False,
    space: str | None = None,
    reference: bool = False,
    verbose: bool = False,
) -> None:
    """Build the semantic field of a scene from its views' masks and mask features.

    Runs lift → KNN graph → reweighting → cut pursuit → merging (levels 1–3) → region features
    and writes one field file (thgs.field), atomically.

    Args:
        scene: a trained 3DGS/2DGS model folder or a .ply file (with cameras: cameras.json in the
            folder, or --source).
        out: the field file to write (e.g. scene.thgs); replaced if it exists.
        guidance: the language_features folder (LangSplat layout: <stem>_s.npy, <stem>_f.npy);
            default: language_features in --source, else in the scene folder.
        preset: the reference's settings for LERF-OVS (lerf) or 3D-OVS (3dovs).
        source: cameras from here instead of the model's cameras.json (COLMAP, transforms.json).
        iteration: which iteration_* of a model folder (default: the newest).
        images: image folder name inside the source, e.g. images_4.
        scale: image size / camera-file size, e.g. 0.25 for images_4. Never guessed.
        resize: resample masks whose size differs from their camera's (nearest neighbour)
            instead of stopping.
        space: embedding space of the mask features; default: language_features/embedding.json,
            else LangSplat's OpenCLIP ViT-B/16 (laion/CLIP-ViT-B-16-laion2B-s34B-b88K) for 512-D
            features.
        reference: the authors' behaviour where thgs differs (absolute vote offsets, reweighted
            edge-weight scale, every label voting in merging), to compare.
        verbose: log every stage with its time.
    """
    from thgs.field import save_field
    from thgs.guidance import load_guidance, read_embedding_space
    from thgs.pipeline import PRESETS, build_field
    from thgs.text import LANGSPLAT_SPACE

    _setup_logging(verbose)
    loaded = load_scene(scene, source=source, iteration=iteration, images=images, scale=scale)
    if loaded.cameras is None:
        raise ThgsError(f"{scene}: no cameras; pass --source with COLMAP or transforms.json")
    if guidance is None:
        root = source if source is not None and source.is_dir() else scene
        guidance = (root if root.is_dir() else root.parent) / "language_features"
    views = load_guidance(guidance, loaded.cameras, resize=resize)
    if space is None:
        recorded = read_embedding_space(guidance)
        dim = int(views[0].features.shape[1])
        if recorded is not None:
            space = recorded[0]
        elif dim == 512:
            space = LANGSPLAT_SPACE
        else:
            raise ThgsError(
                f"{guidance}: {dim}-D features and no embedding.json; name their space with --space"
            )
    config = PRESETS[preset]()
    if reference:
        config = config.as_reference()
    with _stage_progress() as bar:
        field = build_field(loaded, views, config, space=space, progress=_StageBars(bar))
    save_field(out, field)
    _stdout.print(_counts_table(f"thgs build {scene}", field.region_counts, field.timings))
    _stdout.print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB, space {space})")


def demo(
    *,
    out: Annotated[Path, tyro.conf.arg(aliases=("-o",))] = Path("thgs-demo"),
    preset: Literal["synth-small", "synth-medium", "synth-large"] = "synth-small",
    seed: int = 0,
    gaussians: int | None = None,
    views: int | None = None,
    query: tuple[str, ...] = (),
    cache: Path | None = None,
    verbose: bool = False,
) -> None:
    """The whole method on a built-in synthetic scene: build, query, score, picture.

    Generates the scene once (kept in the cache), builds its semantic field with the LERF
    preset, runs a few text queries and writes the field, a report (per-level agreement with
    the exact ground truth, timings) and pictures of the query results to --out.

    Args:
        out: folder for field.thgs, report.md/json and the PNG pictures.
        preset: scene size (synth-small: ~50k Gaussians, 24 views).
        seed: scene and oracle seed.
        gaussians: override the preset's Gaussian count.
        views: override the preset's number of views.
        query: texts to query, e.g. --query mug "teddy bear"; default a few object and part
            names of the scene.
        cache: where generated scenes are kept (default $THGS_CACHE or ~/.cache/thgs).
        verbose: log every stage with its time.
    """
    from thgs.demo import run_demo

    _setup_logging(verbose)
    with _stage_progress() as bar:
        report = run_demo(
            out,
            cache=cache,
            scene_preset=preset,
            seed=seed,
            gaussians=gaussians,
            views=views,
            queries=query or None,
            progress=_StageBars(bar),
        )
    state = "generated" if report.generated else "cached"
    _stdout.print(
        f"scene: {report.dataset} ({state}; {report.gaussians:,} Gaussians, {report.views} views)"
    )
    levels = Table(title="hierarchy against ground truth", title_justify="left")
    for column in ("level", "regions", "ground truth", "matched mIoU"):
        levels.add_column(column)
    levels.add_row(
        "superpoint", f"{report.region_counts[0]:,}", "–", f"purity {report.superpoint_purity:.3f}"
    )
    for k, name in enumerate(("sub-part", "part", "object")):
        levels.add_row(
            name,
            f"{report.region_counts[k + 1]:,}",
            str(report.ground_truth_counts[k]),
            f"{report.miou[k]:.3f}",
        )
    _stdout.print(levels)
    queries = Table(title="text queries (the paper's selection)", title_justify="left")
    for column in ("query", "Gaussians", "3-D IoU", "picture"):
        queries.add_column(column)
    for result in report.queries:
        iou = "–" if math.isnan(result.iou) else f"{result.iou:.3f}"
        queries.add_row(result.text, f"{result.selected:,}", iou, result.image.name)
    _stdout.print(queries)
    _stdout.print(
        f"build {sum(report.timings.values()):.1f} s, whole demo {report.seconds:.1f} s; "
        f"wrote {len(report.files)} files to {out}/ (report.md, levels.png, query-*.png, "
        "field.thgs)"
    )


def entrypoint(argv: list[str] | None = None) -> None:
    """Run the CLI; bad input ends with one line on stderr and exit status 2."""
    try:
        tyro.extras.subcommand_cli_from_dict(
            {"demo": demo, "build": build, "info": info, "synth": synth},
            prog="thgs",
            description="thgs: open-vocabulary, hierarchical understanding of Gaussian scenes.",
            args=argv,
        )
    except ThgsError as exc:
        _stderr.print(f"[bold red]error:[/] {exc}", highlight=False)
        sys.exit(2)
