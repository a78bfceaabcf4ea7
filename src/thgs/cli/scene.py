"""``thgs info`` and ``thgs synth``: look at a scene, generate a synthetic one."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Annotated, Literal

import tyro
from rich.table import Table

from thgs.choices import ScenePreset
from thgs.cli._console import setup_logging, stderr, stdout
from thgs.scene import SceneSummary, load_scene, summarize

__all__ = ["info", "synth"]


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
            cameras.json, cfg_args), a gsplat result folder (ckpts/ckpt_*.pt, cfg.yml) or a
            .ply file.
        source: cameras from here: a training data folder (COLMAP sparse/0 + images/,
            transforms.json) or a camera file; default the source the model's cfg_args (a
            gsplat result folder's cfg.yml: data_dir) names when it is found here, else the
            model's cameras.json.
        iteration: which iteration_* of a model folder (default: the newest).
        images: image folder name inside the source, e.g. images_4 (default: images, if present).
        scale: image size / camera-file size, e.g. 0.25 for images_4. Never guessed.
        undo_applied_transform: map nerfstudio transforms.json poses back to the COLMAP frame.
        json_output: print the summary as JSON instead of a table.
        verbose: log what is read.
    """
    setup_logging(verbose)
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
        stdout.print_json(json.dumps(document))
    else:
        stdout.print(_render_summary(path, scene.found, summary))


def synth(
    preset: ScenePreset,
    out: Path,
    /,
    *,
    seed: int = 0,
    kind: Literal["2dgs", "3dgs"] = "2dgs",
    gaussians: int | None = None,
    views: int | None = None,
    severity: float = 0.5,
    feature_noise: float = 0.5,
    stand_in: str = "name-perfect",
    clip_like: bool = False,
    subpart_drift: float | None = None,
    part_drift: float | None = None,
    surroundings: float | None = None,
    confusion: float | None = None,
    compression: float | None = None,
    context_mix: float | None = None,
    evaluation_views: int | None = None,
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
        stand_in: how CLIP-like the oracle's features are: name-perfect (each mask's feature
            is its name's embedding plus noise), clip-like (parts look like their object,
            surroundings and look-alikes leak in, cosines compressed), either with changes
            such as clip-like:parent_drift=0.8,surroundings=0.3 (docs/synthetic.md).
        clip_like: the same as --stand-in clip-like.
        subpart_drift: share of a sub-part's feature that is its part's (overrides the
            stand-in; 0 to 1).
        part_drift: share of a part's feature that is its object's (0 to 1).
        surroundings: share of a mask's feature that is the bordering object's name (0 to 1).
        confusion: share of a name's feature that is its look-alike's (0 to 0.5).
        compression: pull of every feature towards one fixed direction (0 to below 1).
        context_mix: the older single knob, mixing the parent's and the surroundings' names
            with one weight (0 to 1; not combined with the four above).
        evaluation_views: views that get LERF-OVS / 3DOVS labels (default 4, or every view if
            fewer; more than the scene's views is an error).
        overwrite: replace an existing dataset folder that thgs wrote (its synthetic.json
            marks it; a folder holding other files, the current folder or one holding it is
            refused, and nothing is deleted).
        verbose: log what is done.
    """
    from rich.progress import Progress

    from thgs.errors import InputError, settings_as_flags
    from thgs.synthetic import (
        DatasetConfig,
        OracleConfig,
        check_dataset_output,
        generate_scene,
        write_dataset,
    )
    from thgs.synthetic import evaluation_views as spread_views
    from thgs.synthetic import preset as scene_preset
    from thgs.synthetic import stand_in as stand_in_settings
    from thgs.text import MiniLMEncoder

    setup_logging(verbose)
    check_dataset_output(out, overwrite=overwrite)
    overrides = {"seed": seed, "kind": kind}
    if gaussians is not None:
        overrides["gaussians"] = gaussians
    if views is not None:
        overrides["views"] = views
    config = scene_preset(preset, **overrides)
    if clip_like and stand_in != "name-perfect":
        raise InputError("--clip-like", f"is --stand-in clip-like; --stand-in {stand_in} too")
    overrides = {
        name: value
        for name, value in (
            ("subpart_drift", subpart_drift),
            ("part_drift", part_drift),
            ("surroundings", surroundings),
            ("confusion", confusion),
            ("compression", compression),
            ("context_mix", context_mix),
        )
        if value is not None
    }
    flags = ("severity", "feature_noise", "evaluation_views", *overrides)
    with settings_as_flags(*flags):
        try:
            named = stand_in_settings("clip-like" if clip_like else stand_in)
        except InputError as error:
            raise InputError("--stand-in", error.problem) from error
        oracle = OracleConfig(
            severity=severity,
            feature_noise=feature_noise,
            seed=seed,
            **(named | overrides),
        )
        dataset_config = DatasetConfig(evaluation_views=evaluation_views)
        spread_views(config.views, evaluation_views)
    start = time.perf_counter()
    scene = generate_scene(config)
    encoder = MiniLMEncoder()
    with Progress(console=stderr, transient=True) as bar:
        task = bar.add_task("rendering views", total=len(scene.cameras))
        summary = write_dataset(
            out,
            scene,
            encoder,
            oracle=oracle,
            config=dataset_config,
            overwrite=overwrite,
            progress=lambda done, total: bar.update(task, completed=done),
        )
    seconds = time.perf_counter() - start
    stdout.print(
        f"wrote {summary.path}: {summary.gaussians:,} Gaussians, {summary.views} views, "
        f"{summary.masks:,} masks, {len(summary.categories)} label categories in "
        f"{len(summary.evaluation_views)} evaluation views; {summary.bytes / 1e6:.1f} MB "
        f"in {seconds:.1f} s"
    )
