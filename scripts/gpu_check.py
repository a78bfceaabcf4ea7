"""The GPU measurements of one device call, written to one JSON report as they finish.

    bash scripts/gpu_check.sh                       # on a fresh GPU machine (wheels, kernels, this)
    .venv/bin/python scripts/gpu_check.py --tiny --out /tmp/gpu_check.json   # the CPU dry run

Steps, in order, each recorded as ``ok``, ``failed`` (with the error) or ``skipped`` (with why),
the report rewritten atomically after each so that a call cut short still returns what it measured:

1. ``environment``: versions, the device, cores.
2. ``kernels``: gsplat's CUDA extension loaded (compiled on first use; its seconds).
3. ``cuda_tests``: the gsplat and torch-backend tests (pytest, JUnit counts).
4. ``render``: ``render`` / ``splat_back`` (20 channels) / ``splat_labels`` (4 levels) per view at
   1M Gaussians and 986×728, 2DGS and 3DGS, gsplat and torch (benchmarks/bench_render.py's scene).
5. ``build``: synth-large generated in memory (the oracle's views rendered on the device, their
   masks made on every core) and built with the LERF preset on the device: per-stage seconds,
   regions, matched mIoU per level, peak memory.
6. ``preprocess``: per image with SAM ViT-H and SAM 2 (Hiera-L) and CLIP ViT-B/16 of random
   weights (saved and loaded through the real loading code): SAM's predicted-IoU filter is set
   from a first pass so that about ``--clip-masks`` masks reach CLIP, then the whole
   ``preprocess_image`` is timed.

``--tiny`` runs every step on the CPU at toy sizes (a 3,000-Gaussian scene, tiny models): the steps
that need CUDA say so and are skipped. A step that would not finish before ``--deadline-s`` is
skipped with the time it would have needed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import traceback
import xml.etree.ElementTree as ElementTree
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from functools import partial
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_partition import HashEncoder  # noqa: E402
from bench_preprocess import save_clip, save_sam, timed  # noqa: E402
from bench_render import block_labels, front_camera, surface_scene  # noqa: E402

from thgs._atomic import atomic_output  # noqa: E402
from thgs.device import set_cpu_threads  # noqa: E402
from thgs.eval import matched_miou  # noqa: E402
from thgs.pipeline import FieldConfig, build_field  # noqa: E402
from thgs.render import RasterConfig, render, splat_back, splat_labels  # noqa: E402
from thgs.synthetic import OracleConfig, generate_scene, oracle_guidance, preset  # noqa: E402

SAM2_HIERA_LARGE = {
    "vision_config": {
        "backbone_config": {
            "model_type": "sam2_hiera_det_model",
            "hidden_size": 144,
            "num_attention_heads": 2,
            "blocks_per_stage": [2, 6, 36, 4],
            "embed_dim_per_stage": [144, 288, 576, 1152],
            "num_attention_heads_per_stage": [2, 4, 8, 16],
            "window_size_per_stage": [8, 4, 16, 8],
            "global_attention_blocks": [23, 33, 43],
            "window_positional_embedding_background_size": [7, 7],
        },
        "backbone_channel_list": [1152, 576, 288, 144],
    }
}
"""SAM 2.1 Hiera-L (facebook/sam2.1-hiera-large): its image encoder; the rest is the default."""

SAM2_TINY = {
    "vision_config": {
        "backbone_config": {
            "model_type": "sam2_hiera_det_model",
            "hidden_size": 8,
            "image_size": [256, 256],
            "blocks_per_stage": [1, 1, 2, 1],
            "embed_dim_per_stage": [8, 16, 32, 64],
            "num_attention_heads_per_stage": [1, 1, 1, 1],
            "window_size_per_stage": [4, 4, 4, 4],
            "global_attention_blocks": [3],
            "window_positional_embedding_background_size": [2, 2],
        },
        "backbone_channel_list": [64, 32, 16, 8],
        "backbone_feature_sizes": [[64, 64], [32, 32], [16, 16]],
        "fpn_hidden_size": 32,
    },
    "prompt_encoder_config": {
        "hidden_size": 32, "image_size": 256, "patch_size": 16, "mask_input_channels": 4,
    },
    "mask_decoder_config": {
        "hidden_size": 32, "mlp_dim": 64, "num_hidden_layers": 2, "num_attention_heads": 2,
        "iou_head_hidden_dim": 32,
    },
}  # fmt: skip
"""A 5-block Hiera at 256² input for the dry run (tests/tiny_models.py's)."""


@dataclass(frozen=True)
class Sizes:
    """What each step measures at."""

    device: str
    render_gaussians: int
    render_size: tuple[int, int]
    render_backends: tuple[str, ...]
    repeats: int
    scene: str
    scene_overrides: dict
    build_backend: str
    sam_models: tuple[str, ...]
    clip_model: str
    image_size: tuple[int, int]
    points_per_side: int
    clip_masks: int
    dtype: str


FULL = Sizes(
    device="cuda",
    render_gaussians=1_000_000,
    render_size=(986, 728),
    render_backends=("gsplat", "torch"),
    repeats=5,
    scene="synth-large",
    scene_overrides={},
    build_backend="gsplat",
    sam_models=("vit-h", "sam2-hiera-l"),
    clip_model="vit-b-16",
    image_size=(986, 728),
    points_per_side=32,
    clip_masks=100,
    dtype="bfloat16",
)
TINY = Sizes(
    device="cpu",
    render_gaussians=3000,
    render_size=(64, 48),
    render_backends=("numba",),
    repeats=1,
    scene="synth-small",
    scene_overrides={"gaussians": 3000, "views": 4, "width": 96, "height": 72},
    build_backend="numba",
    sam_models=("tiny", "sam2-tiny"),
    clip_model="tiny",
    image_size=(96, 72),
    points_per_side=4,
    clip_masks=3,
    dtype="float32",
)

NEEDS_S = {"kernels": 150, "cuda_tests": 60, "render": 60, "build": 200, "preprocess": 150}
"""Seconds each step may take on a GPU machine (what the deadline is checked against)."""

TINY_NEEDS_S = {name: 5 for name in NEEDS_S}


def _best_seconds(call: Callable[[], object], device: torch.device, repeats: int) -> float:
    """The fastest of ``repeats`` timed calls after one warm-up."""
    call()
    return min(timed(call, device.type)[1] for _ in range(repeats))


def _peak_reset(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


def _peak_gib(device: torch.device) -> float | None:
    if device.type != "cuda":
        return None
    return round(torch.cuda.max_memory_allocated(device) / 2**30, 3)


def environment(tiny: bool) -> dict:
    from importlib.metadata import PackageNotFoundError, version

    versions = {}
    for name in ("torch", "numpy", "numba", "gsplat", "pycut-pursuit", "transformers", "thgs"):
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = None
    cuda = torch.cuda.is_available()
    return {
        "python": platform.python_version(),
        "versions": versions,
        "cuda": torch.version.cuda,
        "device": torch.cuda.get_device_name() if cuda else "cpu",
        "device_memory_gib": (
            round(torch.cuda.get_device_properties(0).total_memory / 2**30, 1) if cuda else None
        ),
        "cores": os.cpu_count(),
        "mode": "tiny" if tiny else "full",
    }


def _unrunnable(name: str, sizes: Sizes) -> str | None:
    """Why step ``name`` cannot run here at these sizes, or None."""
    if name == "kernels" and sizes.device != "cuda":
        return "the tiny dry run uses the CPU"
    if name in ("kernels", "render", "build", "preprocess") and sizes.device == "cuda":
        if not torch.cuda.is_available():
            return "torch sees no CUDA device"
    return None


def kernels() -> dict:
    start = time.perf_counter()
    from gsplat.cuda._backend import _C

    if _C is None:
        raise RuntimeError("gsplat could not load or build its CUDA extension")
    return {"seconds": round(time.perf_counter() - start, 1)}


def cuda_tests() -> dict:
    with tempfile.TemporaryDirectory() as folder:
        report = Path(folder) / "junit.xml"
        command = [
            sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
            "tests/test_render_gsplat.py", "tests/test_render_torch.py", "-k", "gsplat or cuda",
            f"--junitxml={report}",
        ]  # fmt: skip
        start = time.perf_counter()
        run = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
        suite = ElementTree.parse(report).getroot()
        suite = suite if suite.tag == "testsuite" else suite.find("testsuite")
        counts = {key: int(suite.get(key, 0)) for key in ("tests", "failures", "errors", "skipped")}
        failed = [
            f"{case.get('classname')}::{case.get('name')}"
            for case in suite.iter("testcase")
            if case.find("failure") is not None or case.find("error") is not None
        ]
    return {
        "seconds": round(time.perf_counter() - start, 1),
        "exit_code": run.returncode,
        **counts,
        "passed": counts["tests"] - counts["failures"] - counts["errors"] - counts["skipped"],
        "failed_tests": failed,
        "output_tail": run.stdout[-2000:] if run.returncode not in (0, 5) else "",
    }


def render_step(sizes: Sizes) -> dict:
    device = torch.device(sizes.device)
    width, height = sizes.render_size
    camera = front_camera(width, height)
    codes = torch.randn(height, width, 20, generator=torch.Generator().manual_seed(0)).to(device)
    labels = block_labels(width, height).to(device)
    rows = []
    for kind in ("2dgs", "3dgs"):
        gaussians = surface_scene(sizes.render_gaussians, kind).to(device)
        colors = gaussians.dc_colors()
        for backend in sizes.render_backends:
            config = RasterConfig(backend=backend)
            _peak_reset(device)
            calls = {
                "render": (render, colors),
                "splat_back_20ch": (splat_back, codes),
                "splat_labels_4": (splat_labels, labels),
            }
            seconds = {
                name: round(
                    _best_seconds(
                        lambda f=function, x=values, g=gaussians, c=config: f(
                            g, camera, x, config=c
                        ),
                        device,
                        sizes.repeats,
                    ),
                    4,
                )
                for name, (function, values) in calls.items()
            }
            rows.append(
                {"kind": kind, "backend": backend, **seconds, "peak_gib": _peak_gib(device)}
            )
    return {"gaussians": sizes.render_gaussians, "size": f"{width}x{height}", "runs": rows}


_ORACLE: tuple | None = None


def _oracle_start(scene_name: str, overrides: dict, seed: int) -> None:
    """Worker set-up: the scene's ground truth (regenerated: the same seed gives the same
    scene), the text encoder and the oracle's settings."""
    global _ORACLE
    scene = generate_scene(preset(scene_name, seed=seed, **overrides))
    _ORACLE = (scene.hierarchy, HashEncoder(), OracleConfig(seed=seed))


def _oracle_view(stem: str, max_id: np.ndarray, index: int):
    hierarchy, encoder, config = _ORACLE
    return oracle_guidance(stem, max_id.astype(np.int64), hierarchy, encoder, config, index)


def build_step(sizes: Sizes, seed: int) -> dict:
    device = torch.device(sizes.device)
    timings = {}
    start = time.perf_counter()
    scene = generate_scene(preset(sizes.scene, seed=seed, **sizes.scene_overrides))
    timings["generate_s"] = round(time.perf_counter() - start, 2)
    gaussians = scene.gaussians.to(device)
    colors = gaussians.dc_colors()
    raster = RasterConfig(backend=sizes.build_backend)
    start = time.perf_counter()
    ids = [
        render(gaussians, scene.cameras.select([i]), colors, config=raster).max_id.int().cpu()
        for i in range(len(scene.cameras))
    ]
    timings["render_views_s"] = round(time.perf_counter() - start, 2)
    start = time.perf_counter()
    workers = max(1, min(len(ids), (os.cpu_count() or 2) - 1))
    arguments = (sizes.scene, sizes.scene_overrides, seed)
    with ProcessPoolExecutor(
        workers, mp_context=get_context("spawn"), initializer=_oracle_start, initargs=arguments
    ) as pool:
        views = list(
            pool.map(
                _oracle_view,
                scene.cameras.stems,
                [max_id.numpy() for max_id in ids],
                range(len(ids)),
            )
        )
    timings["oracle_masks_s"] = round(time.perf_counter() - start, 2)
    config = FieldConfig.lerf()
    lift = replace(config.superpoints.lift, raster=raster)
    config = replace(config, superpoints=replace(config.superpoints, lift=lift))
    set_cpu_threads(os.cpu_count() or 1)
    _peak_reset(device)
    start = time.perf_counter()
    posed = replace(scene, gaussians=gaussians)
    field = build_field(posed, views, config, space=HashEncoder().space)
    timings["build_s"] = round(time.perf_counter() - start, 2)
    truth = scene.hierarchy.labels
    return {
        "scene": sizes.scene,
        "seed": seed,
        "gaussians": len(scene.gaussians),
        "views": len(scene.cameras),
        "size": f"{scene.cameras.widths[0]}x{scene.cameras.heights[0]}",
        "backend": sizes.build_backend,
        **timings,
        "stages_s": {name: round(value, 3) for name, value in field.timings.items()},
        "region_counts": list(field.region_counts),
        "miou_subpart_part_object": [
            round(matched_miou(field.labels[:, k], truth[:, k]), 4) for k in (1, 2, 3)
        ],
        "peak_gpu_gib": _peak_gib(device),
        "text_features": "hashed names (benchmarks/bench_partition.py), not MiniLM",
    }


def _segmenter_folder(folder: Path, model: str) -> Path:
    """A randomly initialised SAM (ViT-B/L/H, tiny) or SAM 2 (Hiera-L, tiny) saved to
    ``folder``."""
    import transformers

    configs = {"sam2-hiera-l": SAM2_HIERA_LARGE, "sam2-tiny": SAM2_TINY}
    if model in configs:
        config = transformers.Sam2Config(**configs[model])
        transformers.Sam2Model(config).save_pretrained(folder)
        return folder
    return save_sam(folder, model)


def preprocess_step(sizes: Sizes, clip_masks: int) -> dict:
    from thgs.guidance.preprocess import (
        CLIPImageEncoder,
        MaskGeneratorConfig,
        PointSegmenter,
        PreprocessConfig,
        generate_masks,
        preprocess_image,
    )

    device = torch.device(sizes.device)
    dtype = getattr(torch, sizes.dtype)
    width, height = sizes.image_size
    image = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        torch.manual_seed(0)
        encoder = CLIPImageEncoder(
            f"random-{sizes.clip_model}",
            save_clip(Path(tmp) / "clip", sizes.clip_model),
            device=sizes.device,
            dtype=dtype,
        )
        for model in sizes.sam_models:
            start = time.perf_counter()
            folder = _segmenter_folder(Path(tmp) / model, model)
            segmenter = PointSegmenter(f"random-{model}", folder, device=sizes.device, dtype=dtype)
            made_s = time.perf_counter() - start
            # a first pass keeping every candidate: its predicted IoUs set the filter so that
            # about clip_masks masks reach CLIP
            everything = MaskGeneratorConfig(
                points_per_side=sizes.points_per_side,
                pred_iou_threshold=0.0,
                stability_threshold=0.0,
                nms_score_threshold=0.0,
            )
            levels, every_candidate_s = timed(
                partial(generate_masks, segmenter, image, everything), sizes.device
            )
            scores = torch.cat([level.predicted_iou.float().cpu() for level in levels.values()])
            ranked = torch.sort(scores, descending=True).values
            threshold = float(ranked[clip_masks]) if len(ranked) > clip_masks else 0.0
            config = PreprocessConfig(masks=replace(everything, pred_iou_threshold=threshold))
            _peak_reset(device)
            guidance = None

            def one_image(config=config, segmenter=segmenter):
                nonlocal guidance
                guidance = preprocess_image(image, "image", segmenter, encoder, config)

            seconds = _best_seconds(one_image, device, max(1, min(2, sizes.repeats)))
            results.append(
                {
                    "sam": model,
                    "model_setup_s": round(made_s, 1),
                    "every_candidate_s": round(every_candidate_s, 3),
                    "pred_iou_threshold": round(threshold, 4),
                    "masks_to_clip": int(guidance.features.shape[0]),
                    "seconds_per_image": round(seconds, 3),
                    "peak_gpu_gib": _peak_gib(device),
                }
            )
            del segmenter
    return {
        "image": f"{width}x{height}",
        "clip": sizes.clip_model,
        "dtype": sizes.dtype,
        "points_per_side": sizes.points_per_side,
        "runs": results,
    }


def _write(report: dict, out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(out, "w") as handle:
        json.dump(report, handle, indent=2)
        handle.write("\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="the JSON report to write")
    parser.add_argument("--tiny", action="store_true", help="toy sizes on the CPU (the dry run)")
    parser.add_argument("--deadline-s", type=float, default=480.0, help="seconds from now")
    parser.add_argument("--seed", type=int, default=0, help="of the synthetic scene")
    parser.add_argument(
        "--setup-s", type=float, default=None, help="the set-up's seconds, reported"
    )
    parser.add_argument(
        "--clip-masks", type=int, default=None, help="masks per image for CLIP (100; tiny: 3)"
    )
    parser.add_argument(
        "--steps", nargs="*", default=None, help="only these steps (default: every one)"
    )
    args = parser.parse_args(argv)
    sizes, needs = (TINY, TINY_NEEDS_S) if args.tiny else (FULL, NEEDS_S)
    deadline = time.monotonic() + args.deadline_s
    report: dict = {"setup_s": args.setup_s, "sizes": {**sizes.__dict__}, "steps": {}}
    steps: dict[str, Callable[[], dict]] = {
        "environment": lambda: environment(args.tiny),
        "kernels": kernels,
        "cuda_tests": cuda_tests,
        "render": lambda: render_step(sizes),
        "build": lambda: build_step(sizes, args.seed),
        "preprocess": lambda: preprocess_step(sizes, args.clip_masks or sizes.clip_masks),
    }
    unknown = sorted(set(args.steps or ()) - set(steps))
    if unknown:
        parser.error(f"unknown steps {unknown}; choose from {sorted(steps)}")
    for name, step in steps.items():
        if args.steps is not None and name not in args.steps:
            continue
        left = deadline - time.monotonic()
        if why := _unrunnable(name, sizes):
            entry = {"status": "skipped", "why": why}
        elif name in needs and left < needs[name]:
            entry = {"status": "skipped", "why": f"{left:.0f} s left, {needs[name]} s needed"}
        else:
            start = time.perf_counter()
            try:
                entry = {"status": "ok", **step()}
            except Exception as error:  # the report says what failed, and the next step runs
                entry = {
                    "status": "failed",
                    "error": f"{type(error).__name__}: {error}",
                    "traceback": traceback.format_exc()[-3000:],
                }
            entry["step_s"] = round(time.perf_counter() - start, 1)
        report["steps"][name] = entry
        _write(report, args.out)
        print(f"{name}: {entry['status']}", flush=True)
    failed = [name for name, entry in report["steps"].items() if entry["status"] == "failed"]
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
