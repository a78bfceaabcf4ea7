"""Per-image time of ``thgs preprocess`` (SAM masks at four levels + CLIP mask features).

    .venv/bin/python benchmarks/bench_preprocess.py                       # CPU, small models
    .venv/bin/python benchmarks/bench_preprocess.py --device cuda --sam vit-h --clip vit-b-16 \
        --dtype bfloat16                                                  # the reference's sizes

No weights can be downloaded here, so the models are randomly initialised with the architecture
named (``tiny``: the tests' small configs; ``vit-b``/``vit-l``/``vit-h``: SAM's image encoders;
``vit-b-16``: CLIP ViT-B/16, LangSplat's) and saved and loaded through the real loading code.
Random weights make random masks: almost none pass SAM's quality thresholds, so the end-to-end
time (default settings, 32 points per side, one crop layer) is SAM's part plus the filters; it is
timed again with no predicted-IoU threshold, so that every candidate mask is upsampled and scored
(an upper bound: a real SAM passes a fraction). The parts that depend on how many masks survive
are timed on their own with a typical count (``--masks`` per level, LangSplat's order of
magnitude): LangSplat's mask NMS per level and CLIP on every level's masks. The estimate for a
real image is the upper bound plus those two. One JSON line per image size.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import transformers

from thgs.guidance.preprocess import (
    CLIPImageEncoder,
    MaskGeneratorConfig,
    PointSegmenter,
    generate_masks,
    mask_features,
)
from thgs.guidance.preprocess.masks import langsplat_mask_nms

SAM_ENCODERS = {
    "tiny": {"hidden_size": 32, "num_hidden_layers": 2, "num_attention_heads": 2,
             "global_attn_indexes": [1], "mlp_dim": 64},
    "vit-b": {"hidden_size": 768, "num_hidden_layers": 12, "num_attention_heads": 12,
              "global_attn_indexes": [2, 5, 8, 11]},
    "vit-l": {"hidden_size": 1024, "num_hidden_layers": 24, "num_attention_heads": 16,
              "global_attn_indexes": [5, 11, 17, 23]},
    "vit-h": {"hidden_size": 1280, "num_hidden_layers": 32, "num_attention_heads": 16,
              "global_attn_indexes": [7, 15, 23, 31]},
}  # fmt: skip

CLIP_MODELS = {
    "tiny": {"hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 1,
             "num_attention_heads": 2, "image_size": 32, "patch_size": 16, "projection": 16},
    "vit-b-16": {"hidden_size": 768, "intermediate_size": 3072, "num_hidden_layers": 12,
                 "num_attention_heads": 12, "image_size": 224, "patch_size": 16,
                 "projection": 512},
}  # fmt: skip


def save_sam(folder: Path, size: str) -> Path:
    encoder = SAM_ENCODERS[size]
    if size == "tiny":
        config = transformers.SamConfig(
            vision_config={**encoder, "output_channels": 32, "image_size": 256, "window_size": 4,
                           "num_pos_feats": 16},
            prompt_encoder_config={"hidden_size": 32, "image_size": 256, "mask_input_channels": 4},
            mask_decoder_config={"hidden_size": 32, "mlp_dim": 64, "num_attention_heads": 2,
                                 "iou_head_hidden_dim": 32},
        )  # fmt: skip
    else:
        config = transformers.SamConfig(vision_config=encoder)
    transformers.SamModel(config).save_pretrained(folder)
    return folder


def save_clip(folder: Path, size: str) -> Path:
    vision = dict(CLIP_MODELS[size])
    projection = vision.pop("projection")
    config = transformers.CLIPConfig(vision_config=vision, projection_dim=projection)
    transformers.CLIPModel(config).save_pretrained(folder)
    return folder


def timed(function, device: str):
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    start = time.perf_counter()
    result = function()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return result, time.perf_counter() - start


def blob_masks(count: int, height: int, width: int, device: str, seed: int) -> torch.Tensor:
    """``count`` elliptical masks of random size and place: stand-ins for SAM's masks."""
    generator = np.random.default_rng(seed)
    ys, xs = np.mgrid[:height, :width]
    masks = np.empty((count, height, width), dtype=bool)
    for i in range(count):
        cx, cy = generator.uniform(0, width), generator.uniform(0, height)
        rx, ry = generator.uniform(5, width / 3), generator.uniform(5, height / 3)
        masks[i] = ((xs - cx) / rx) ** 2 + ((ys - cy) / ry) ** 2 <= 1
    return torch.from_numpy(masks).to(device)


def timed_jobs(segmenter, encoder, config, image, masks, scores, boxes) -> dict:
    """The four measured steps for one image, as functions of nothing."""
    every_candidate = replace(config, pred_iou_threshold=0.0)
    pixels = torch.from_numpy(image).to(masks.device).float() / 255
    return {
        "masks": lambda: generate_masks(segmenter, image, config),
        "masks_every_candidate": lambda: generate_masks(segmenter, image, every_candidate),
        "nms": lambda: [langsplat_mask_nms(masks, scores) for _ in range(4)],
        "clip": lambda: [mask_features(encoder, pixels, masks, boxes) for _ in range(4)],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "bfloat16", "float16"])
    parser.add_argument("--sam", default="tiny", choices=sorted(SAM_ENCODERS))
    parser.add_argument("--clip", default="tiny", choices=sorted(CLIP_MODELS))
    parser.add_argument("--sizes", nargs="+", default=["986x728"], help="W×H of the images")
    parser.add_argument("--points-per-side", type=int, default=32)
    parser.add_argument("--points-per-batch", type=int, default=64)
    parser.add_argument("--masks", type=int, default=100, help="masks per level (4 levels)")
    parser.add_argument("--repeat", type=int, default=2, help="timed runs after one warm-up")
    args = parser.parse_args()
    dtype = getattr(torch, args.dtype)
    with tempfile.TemporaryDirectory() as tmp:
        torch.manual_seed(0)
        segmenter = PointSegmenter(
            f"random-{args.sam}",
            save_sam(Path(tmp) / "sam", args.sam),
            device=args.device,
            dtype=dtype,
        )
        encoder = CLIPImageEncoder(
            f"random-{args.clip}",
            save_clip(Path(tmp) / "clip", args.clip),
            device=args.device,
            dtype=dtype,
        )
    config = MaskGeneratorConfig(
        points_per_side=args.points_per_side, points_per_batch=args.points_per_batch
    )
    for size in args.sizes:
        width, height = (int(v) for v in size.lower().split("x"))
        image = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
        masks = blob_masks(args.masks, height, width, args.device, seed=1)
        scores = torch.rand(args.masks, generator=torch.Generator().manual_seed(2)).to(args.device)
        boxes = torch.stack(
            [
                torch.stack([xs.min(), ys.min(), xs.max(), ys.max()])
                for ys, xs in (torch.nonzero(mask, as_tuple=True) for mask in masks)
            ]
        )
        if args.device.startswith("cuda"):
            torch.cuda.reset_peak_memory_stats()
        jobs = timed_jobs(segmenter, encoder, config, image, masks, scores, boxes)
        times = {key: [] for key in jobs}
        for run in range(args.repeat + 1):
            for key, job in jobs.items():
                result, seconds = timed(job, args.device)
                if key == "masks":
                    levels = result
                if run > 0:  # the first run warms up kernels and caches
                    times[key].append(seconds)
        median = {key: float(np.median(values)) for key, values in times.items()}
        record = {
            "device": torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu",
            "threads": torch.get_num_threads(),
            "dtype": args.dtype,
            "sam": args.sam,
            "clip": args.clip,
            "image": f"{width}x{height}",
            "points_per_side": args.points_per_side,
            "masks_surviving_random_model": [len(level) for level in levels.values()],
            "seconds_sam_and_filters": round(median["masks"], 3),
            "seconds_sam_and_filters_every_candidate_upsampled": round(
                median["masks_every_candidate"], 3
            ),
            f"seconds_langsplat_nms_4x{args.masks}": round(median["nms"], 3),
            f"seconds_clip_4x{args.masks}": round(median["clip"], 3),
            "seconds_per_image_estimate": round(
                median["masks_every_candidate"] + median["nms"] + median["clip"], 3
            ),
        }
        if args.device.startswith("cuda"):
            record["peak_cuda_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
        print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
