"""``thgs build`` and ``thgs demo``: from scene and guidance to a semantic field."""

from __future__ import annotations

import contextlib
import math
from pathlib import Path
from typing import Annotated, Literal

import tyro
from rich.table import Table

from thgs.choices import Device, FieldPreset, ScenePreset
from thgs.cli._console import StageBars, setup_logging, stage_progress, stdout
from thgs.cli._outputs import check_output_file, check_output_folder
from thgs.errors import InputError

__all__ = ["build", "demo"]


def _counts_table(title: str, counts, timings: dict[str, float]) -> Table:
    from thgs.hierarchy.levels import LEVEL_NAMES

    table = Table(title=title, show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    table.add_row(
        "regions", ", ".join(f"{name} {count:,}" for name, count in zip(LEVEL_NAMES, counts))
    )
    table.add_row(
        "time",
        f"{sum(timings.values()):.1f} s ("
        + ", ".join(f"{stage} {seconds:.2f}" for stage, seconds in timings.items())
        + ")",
    )
    return table


def _splat_options(**options) -> dict:
    """The ``--from-splat`` options the user gave (None, False or an empty tuple: not given;
    a 0 is given)."""
    return {
        name: value
        for name, value in options.items()
        if value is not None and value is not False and value != ()
    }


def _guidance_source(given: dict, space: str | None, device: str, oracle: Path | None):
    from thgs.splat_views import ModelGuidance, OracleGuidance

    models = {name: given[name] for name in ("sam", "clip", "dtype") if name in given}
    if oracle is None:
        from thgs.device import resolve_device

        return ModelGuidance(**models, space=space, device=str(resolve_device(device)))
    clashing = [f"--{name}" for name in models] + (["--space"] if space is not None else [])
    if clashing:
        raise InputError("--oracle", f"makes its own guidance; leave out {', '.join(clashing)}")
    return OracleGuidance(oracle)


def _splat_views_request(out: Path, given: dict, guidance):
    from thgs.errors import settings_as_flags
    from thgs.splat_views import PlacementConfig, SplatViewsRequest, default_views_folder

    settings = {}
    if "view_size" in given:
        settings["width"], settings["height"] = given["view_size"]
    for flag, setting in (
        ("orbit_views", "orbit_views"),
        ("orbit_spheres", "core_percentiles"),
        ("close_views", "close_views"),
    ):
        if flag in given:
            settings[setting] = given[flag]
    defaults = PlacementConfig()
    orbit_views = settings.get("orbit_views", defaults.orbit_views)
    orbit_spheres = settings.get("core_percentiles", defaults.core_percentiles)
    if len(orbit_views) != len(orbit_spheres):
        raise InputError(
            "--orbit-views",
            f"give one count per orbit sphere (--orbit-spheres has {len(orbit_spheres)}), got "
            f"{len(orbit_views)}",
        )
    with settings_as_flags(
        "orbit_views",
        "close_views",
        width="view_size",
        height="view_size",
        core_percentiles="orbit_spheres",
    ):
        placement = PlacementConfig(**settings)
    return SplatViewsRequest(
        folder=given.get("views", default_views_folder(out)),
        guidance=guidance,
        placement=placement,
        model_cameras="no_model_cameras" not in given,
        overwrite="overwrite_views" in given,
    )


def build(
    scene: Path,
    /,
    *,
    out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
    guidance: Path | None = None,
    preset: FieldPreset | None = None,
    config: Path | None = None,
    set: tuple[str, ...] = (),
    source: Path | None = None,
    iteration: int | None = None,
    images: str | None = None,
    scale: float = 1.0,
    resize: bool = False,
    space: str | None = None,
    text_model: Path | None = None,
    reference: bool = False,
    repeated_parts: bool = True,
    device: Device = "auto",
    lift_cache: Path | None = None,
    threads: int | None = None,
    ray: Annotated[str | None, tyro.conf.arg(metavar="[ADDRESS]")] = None,
    from_splat: bool = False,
    views: Path | None = None,
    overwrite_views: bool = False,
    model_cameras: bool = True,
    orbit_views: tuple[int, ...] = (),
    orbit_spheres: tuple[float, ...] = (),
    close_views: int | None = None,
    view_size: tuple[int, int] | None = None,
    sam: str | None = None,
    clip: str | None = None,
    dtype: Literal["float32", "bfloat16", "float16"] | None = None,
    oracle: Path | None = None,
    verbose: bool = False,
) -> None:
    """Build the semantic field of a scene from its views' masks and mask features.

    Runs lift → KNN graph → reweighting → cut pursuit → merging (levels 1–3) → region features
    and writes one field file (thgs.field), atomically.

    Args:
        scene: a trained 3DGS/2DGS model folder, a gsplat result folder (ckpts/ckpt_*.pt) or
            a .ply file. A model folder's cfg_args names its training data (source_path), a
            gsplat result folder's cfg.yml or cfg.json its data_dir, used as --source when
            found here (docs/build.md); else the cameras are the folder's cameras.json.
        out: the field file to write (e.g. scene.thgs); replaced if it exists.
        guidance: the language_features folder (LangSplat layout: <stem>_s.npy, <stem>_f.npy);
            default: language_features in the source (--source, or cfg_args's), else in the
            scene folder.
        preset: the reference's settings for LERF-OVS (lerf, the default) or 3D-OVS (3dovs).
        config: every setting from a file instead of a preset: a JSON config (the "config"
            object of a field's record, FieldConfig.to_json) or a field file, to rebuild a
            field exactly as it was built.
        set: change single settings, e.g. --set merge.min_region_gaussians=30
            superpoints.lift.raster.backend=torch (dotted names as in the config; values are
            JSON, or text); every setting of every stage is reachable (docs/build.md). Applied
            after --preset or --config and --reference; naming a setting twice is an error.
        source: the training data folder (COLMAP sparse/0 or transforms.json, images/,
            language_features/) or a camera file; decides over the model's cfg_args (or
            gsplat's cfg.yml) and cameras.json.
        iteration: which iteration_* of a model folder (default: the newest).
        images: image folder name inside the source, e.g. images_4.
        scale: image size / camera-file size, e.g. 0.25 for images_4. Never guessed.
        resize: resample masks whose size differs from their camera's (nearest neighbour)
            instead of stopping.
        space: embedding space of the mask features; default: language_features/embedding.json,
            else LangSplat's OpenCLIP ViT-B/16 (laion/CLIP-ViT-B-16-laion2B-s34B-b88K) for 512-D
            features.
        text_model: the local folder of the features' model, recorded in the field so that
            thgs query, view and eval find it; default: the --clip folder thgs preprocess
            recorded in embedding.json (a model from the Hugging Face cache needs none).
        reference: the authors' behaviour where thgs differs (absolute vote offsets, reweighted
            edge-weight scale, every label voting in merging and in the features, one part per
            connected piece), to compare.
        repeated_parts: group an object's alike parts that touch only through another part (a
            table's legs) into one part; --no-repeated-parts keeps one part per piece (the
            paper's top-3 query selection scores such pieces better: docs/build.md).
        device: where to compute: auto (a CUDA GPU if torch sees one, else MPS, else the CPU),
            cpu, cuda or mps; rendering uses the device's best backend (docs/rendering.md).
        lift_cache: a folder to keep the lift in and reuse it from: a build of the same scene,
            guidance and lift settings (e.g. trying merge or partition settings with --set)
            reads it instead of lifting again (docs/build.md).
        threads: CPU threads (default: every core, or NUMBA_NUM_THREADS); the field is the
            same for any number.
        ray: lift the views and solve the partition's blocks as Ray tasks: --ray starts a
            local Ray, --ray ADDRESS joins a running cluster (e.g. 10.0.0.1:6379), whose
            workers need thgs installed; needs thgs[cluster]. The field is the same.
        from_splat: build from the splat alone, without photos: place virtual cameras (the
            model's cameras.json when present, else an orbit; then close-ups of what they
            leave unseen), render them, run SAM and CLIP on the renders (--sam, --clip) and
            build from that (docs/build.md). Not with --source, --guidance, --images,
            --scale or --resize.
        views: with --from-splat: the folder for the cameras, renders and guidance, kept so
            that a rerun resumes (default: OUT's name with .views, beside it).
        overwrite_views: with --from-splat: replace a views folder made for another scene or
            other settings.
        model_cameras: with --from-splat: start from the model's own cameras when it has
            them; --no-model-cameras always places the orbit.
        orbit_views: with --from-splat: the number of orbit views, one count per orbit sphere
            (default 30).
        orbit_spheres: with --from-splat: each orbit frames the sphere around the scene's centre
            that holds this percentage of its opaque Gaussians (default 50: where the objects
            are; e.g. --orbit-spheres 50 90 --orbit-views 20 10 adds a second, wider orbit).
        close_views: with --from-splat: at most this many close-ups of what the orbit leaves
            unseen (default 12).
        view_size: with --from-splat: width and height of the virtual views in pixels (default
            512 384).
        sam: with --from-splat: SAM or SAM 2 (a local folder or a cached Hugging Face id), as
            in thgs preprocess (default facebook/sam-vit-huge).
        clip: with --from-splat: the CLIP model, likewise (default LangSplat's OpenCLIP
            ViT-B/16).
        dtype: with --from-splat: the models' precision (default float32; bfloat16 or float16
            on a GPU).
        oracle: with --from-splat, for a scene thgs synth wrote: make the guidance from this
            dataset folder's exact ground truth with its own oracle settings instead of SAM
            and CLIP (to score the splat-only path against exact answers).
        verbose: log every stage with its time.
    """
    from thgs.device import set_cpu_threads
    from thgs.pipeline import chosen_field_config, read_field_config
    from thgs.workflows import BuildRequest, build_field_file

    setup_logging(verbose)
    check_output_file(out)
    if threads is not None:
        set_cpu_threads(threads, "--threads")
    given = _splat_options(
        views=views,
        overwrite_views=overwrite_views,
        no_model_cameras=not model_cameras,
        orbit_views=orbit_views,
        orbit_spheres=orbit_spheres,
        close_views=close_views,
        view_size=view_size,
        sam=sam,
        clip=clip,
        dtype=dtype,
        oracle=oracle,
    )
    splat_views = None
    if from_splat:
        splat_views = _splat_views_request(
            out, given, _guidance_source(given, space, device, oracle)
        )
    elif given:
        flag = "--" + next(iter(given)).replace("_", "-")
        raise InputError(flag, "applies only with --from-splat")
    settings = chosen_field_config(
        preset,
        read_field_config(config) if config is not None else None,
        set,
        reference=reference,
        repeated_parts=repeated_parts,
    )
    request = BuildRequest(
        scene=scene,
        out=out,
        config=settings,
        guidance=guidance,
        source=source,
        iteration=iteration,
        images=images,
        scale=scale,
        resize=resize,
        space=space,
        text_model=text_model,
        device=device,
        lift_cache=lift_cache,
        ray=ray is not None,
        splat_views=splat_views,
    )
    with contextlib.ExitStack() as stack:
        if ray is not None:
            from thgs.cli.suite import LOCAL_RAY
            from thgs.cluster import connect_ray

            stack.enter_context(connect_ray(None if ray == LOCAL_RAY else ray))
        bar = stack.enter_context(stage_progress())
        built = build_field_file(request, progress=StageBars(bar))
    field = built.field
    stdout.print(_counts_table(f"thgs build {scene}", field.region_counts, field.timings))
    stdout.print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB, space {built.space})")
    stdout.print(f"explore it in a browser: thgs view {out}")


def demo(
    *,
    out: Annotated[Path, tyro.conf.arg(aliases=("-o",))] = Path("thgs-demo"),
    preset: ScenePreset = "synth-small",
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

    setup_logging(verbose)
    check_output_folder(out)
    with stage_progress() as bar:
        report = run_demo(
            out,
            cache=cache,
            scene_preset=preset,
            seed=seed,
            gaussians=gaussians,
            views=views,
            queries=query or None,
            progress=StageBars(bar),
        )
    state = "generated" if report.generated else "cached"
    stdout.print(
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
    stdout.print(levels)
    queries = Table(title="text queries (the automatic selection)", title_justify="left")
    columns = ("query (confidence)", "Gaussians", "3-D IoU", "paper's: 3-D IoU")
    for column in (*columns, "best region of its level"):
        queries.add_column(column)
    for result in report.queries:
        iou, paper, best = (
            "–" if math.isnan(value) else f"{value:.3f}"
            for value in (result.iou, result.paper_iou, result.best_iou)
        )
        confidence = "–" if result.confidence is None else f"{result.confidence:.2f}"
        level = ("sub-part", "part", "object")[result.level - 1]
        queries.add_row(
            f"{result.text} ({confidence})",
            f"{result.selected:,}",
            iou,
            paper,
            f"{level}: {best}",
        )
    stdout.print(queries)
    stdout.print(
        f"build {sum(report.timings.values()):.1f} s, whole demo {report.seconds:.1f} s; "
        f"wrote {len(report.files)} files to {out}/ (report.md, levels.png, query-*.png, "
        "field.thgs)"
    )
    stdout.print(f"explore it in a browser: thgs view {out / 'field.thgs'}")
