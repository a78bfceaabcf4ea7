"""``thgs preprocess``: posed images → SAM masks and CLIP mask features in LangSplat's layout."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import tyro

from thgs.cli._console import setup_logging, stderr, stdout
from thgs.cli._outputs import check_output_folder
from thgs.errors import InputError, settings_as_flags
from thgs.text import LANGSPLAT_SPACE

__all__ = ["preprocess"]

DTYPES = ("float32", "bfloat16", "float16")


def preprocess(
    source: Annotated[Path, tyro.conf.arg(metavar="SOURCE")],
    /,
    *,
    out: Annotated[Path | None, tyro.conf.arg(aliases=("-o",))] = None,
    images: str = "images",
    sam: str = "facebook/sam-vit-huge",
    clip: str = LANGSPLAT_SPACE,
    space: str | None = None,
    device: str = "cpu",
    dtype: Literal["float32", "bfloat16", "float16"] = "float32",
    points_per_side: int = 32,
    points_per_batch: int = 64,
    crop_layers: int = 1,
    pred_iou_threshold: float = 0.7,
    stability_threshold: float = 0.85,
    min_region_area: int = 100,
    resolution: int | None = None,
    cameras: Path | None = None,
    overwrite: bool = False,
    verbose: bool = False,
) -> None:
    """Make a scene's 2D guidance: SAM masks at levels default/s/m/l and a CLIP feature per mask.

    Writes language_features/<stem>_s.npy ([4, H, W] mask ids, −1 = none) and <stem>_f.npy
    ([n, D] unit features, D the CLIP model's projection size: 512 for LangSplat's ViT-B/16),
    LangSplat's layout, and embedding.json (the features' space, D and the local --clip
    folder, which thgs build records in the field). Each view is written atomically; run the
    same command again after an interruption and finished views are skipped. A warning ends the
    run when SAM kept no mask in most images.

    Args:
        source: the dataset folder holding the images (SOURCE/images by default).
        out: the output folder (default SOURCE/language_features).
        images: the image folder's name inside SOURCE, e.g. images_2.
        sam: SAM or SAM 2 in Hugging Face format: a local folder, or a model id read from the
            Hugging Face cache (never downloaded).
        clip: the CLIP model, likewise (a local folder or a model id).
        space: the features' embedding space when --clip is a folder; default: the folder's
            Hugging Face id (from the cache's folder name, its config.json or a folder named
            like LangSplat's model), else the folder's absolute path. Queries use the same
            model: the field remembers the folder.
        device: torch device, e.g. cuda.
        dtype: model precision (bfloat16 or float16 on a GPU).
        points_per_side: SAM's prompt grid per crop side.
        points_per_batch: prompts decoded together (GPU memory).
        crop_layers: SAM's crop layers after the whole image (LangSplat: 1).
        pred_iou_threshold: keep masks whose predicted IoU is above this, in [0, 1] (SAM's
            pred_iou_thresh); lower keeps more masks.
        stability_threshold: keep masks whose stability score is at least this, in [0, 1]
            (SAM's stability_score_thresh); lower keeps more masks.
        min_region_area: holes and islands under this many pixels are removed from each mask
            (SAM's min_mask_region_area; 0 keeps them); masks left empty are dropped.
        resolution: output width in pixels, height scaled to match (LangSplat's --resolution);
            default: images taller than 1080 px are scaled to 1080 px tall.
        cameras: make each view's masks at its camera's size (a camera file, or a folder with
            cameras.json, transforms.json or a COLMAP model); only those cameras' images.
        overwrite: redo finished views and forget the folder's earlier settings.
        verbose: log each image's mask counts and time.
    """
    import torch

    from thgs.guidance.preprocess import (
        MaskGeneratorConfig,
        PreprocessConfig,
        image_jobs,
        load_preprocess_models,
        preprocess_images,
    )
    from thgs.scene import load_cameras

    setup_logging(verbose)
    if out is not None:
        check_output_folder(out)
    if resolution is not None and cameras is not None:
        raise InputError("--resolution", "give either --resolution or --cameras, not both")
    camera_set = None
    if cameras is not None:
        camera_set, camera_path, _ = load_cameras(cameras)
        stdout.print(f"cameras: {camera_path} ({len(camera_set)} views)")
    jobs = image_jobs(source / images, cameras=camera_set, target_width=resolution)
    output = out if out is not None else source / "language_features"
    masks = {
        "points_per_side": points_per_side,
        "points_per_batch": points_per_batch,
        "crop_layers": crop_layers,
        "pred_iou_threshold": pred_iou_threshold,
        "stability_threshold": stability_threshold,
        "min_region_area": min_region_area,
    }
    with settings_as_flags(*masks):
        config = PreprocessConfig(masks=MaskGeneratorConfig(**masks))
    segmenter, encoder = load_preprocess_models(
        sam, clip, space=space, device=device, dtype=getattr(torch, dtype)
    )
    stdout.print(
        f"{len(jobs)} images → {output}; SAM {segmenter.name} ({segmenter.kind}), "
        f"CLIP {encoder.space} ({encoder.dim}-D), {device}"
    )

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[last]}"),
        console=stderr,
    ) as bar:
        task = bar.add_task("preprocessing", total=len(jobs), last="")

        def on_image(stem: str, seconds: float | None) -> None:
            last = f"{stem}: skipped (done)" if seconds is None else f"{stem}: {seconds:.2f} s"
            bar.update(task, advance=1, last=last)

        summary = preprocess_images(
            jobs, output, segmenter, encoder, config, overwrite=overwrite, on_image=on_image
        )
    seconds = list(summary.done.values())
    timing = (
        f", {sum(seconds) / len(seconds):.2f} s per image (slowest {max(seconds):.2f} s)"
        if seconds
        else ""
    )
    stdout.print(
        f"done {len(summary.done)}, skipped {len(summary.skipped)} finished{timing}; "
        "masks per level (default/s/m/l): " + " / ".join(f"{n:,}" for n in summary.masks)
    )
    if summary.empty:
        stdout.print(
            f"{len(summary.empty)} of {len(summary.done)} images without a mask (first: "
            f"{summary.empty[0]})"
        )
    stdout.print(f"wrote {output}")
