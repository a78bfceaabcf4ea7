"""Preprocessing in process vs through Ray Data (``preprocess_with_ray``), and the costs of the
scaling model for N actors (GPUs).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_preprocess_ray.py
    .venv/bin/python benchmarks/bench_preprocess_ray.py --device cuda --gpus-per-actor 1 \
        --sam vit-h --clip vit-b-16 --actors 1 2 4 8

The same images (``--scenes`` scenes of ``--images`` random images each) are preprocessed into
fresh folders three ways: in this process (:func:`preprocess_images`, one thread per process as a
Ray actor gets on a CPU), and with :func:`preprocess_with_ray` on each ``--actors`` count, on one
local Ray started once. The files must come out identical (checked). Measured:

- ``ray_start_s``: starting the local Ray (:func:`thgs.cluster.connect_ray`);
- ``model_load_s``: loading SAM and CLIP once, in process;
- ``seconds_per_image``: in process (mean), and as the actors measured it, per actor count;
- ``worker_start_and_model_load_s``: a fresh Ray worker starting, importing thgs and loading the
  models (a distributed run pays it twice in a row: the driver's check of the folders, then the
  actors, in parallel);
- ``per_task_overhead_s``: what Ray Data adds per image, from a pipeline of the same shape whose
  actors do nothing (its wall time on 64 images minus on 1, over 63);
- ``fixed_overhead_s``: per actor count, the wall time less images × per-image seconds / actors:
  the two worker starts and model loads above, and the dataset's start and end.

The scaling model written from these: T(N) ≈ startup + model_load + images × t_image / N +
overhead. Models are randomly initialised with the architecture named (see bench_preprocess.py),
so timings are real and masks are random. One JSON line.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from bench_preprocess import CLIP_MODELS, SAM_ENCODERS, save_clip, save_sam
from PIL import Image

from thgs.cluster import connect_ray
from thgs.guidance.preprocess import (
    MaskGeneratorConfig,
    PreprocessConfig,
    PreprocessTarget,
    image_jobs,
    load_preprocess_models,
    preprocess_images,
    preprocess_with_ray,
)


class _Idle:
    """A Ray Data actor that does nothing: the pipeline's own cost per image."""

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {"stem": batch["stem"]}


def per_task_overhead(ray, actors: int) -> float:
    def run(count: int) -> float:
        rows = [{"stem": f"frame_{i:05d}"} for i in range(count)]
        start = time.perf_counter()
        dataset = ray.data.from_items(rows, override_num_blocks=count)
        dataset.context.enable_progress_bars = False
        dataset.map_batches(
            _Idle,
            compute=ray.data.ActorPoolStrategy(size=actors, max_tasks_in_flight_per_actor=2),
            batch_size=1,
            batch_format="numpy",
        ).take_all()
        return time.perf_counter() - start

    run(1)  # warm-up: the workers' first start
    return (run(64) - run(1)) / 63


def _load_models(sam: str, clip: str, device: str, dtype: str) -> None:
    load_preprocess_models(sam, clip, device=device, dtype=getattr(torch, dtype))


def worker_model_load(ray, sam: str, clip: str, device: str, dtype: str, gpus: float) -> float:
    """Seconds for a fresh Ray worker to start, import thgs and load the models."""
    start = time.perf_counter()
    ray.get(ray.remote(_load_models).options(num_gpus=gpus).remote(sam, clip, device, dtype))
    return time.perf_counter() - start


def same_files(folder: Path, reference: Path) -> bool:
    names = sorted(path.name for path in reference.iterdir())
    return names == sorted(path.name for path in folder.iterdir()) and all(
        (folder / name).read_bytes() == (reference / name).read_bytes() for name in names
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "bfloat16", "float16"])
    parser.add_argument("--sam", default="tiny", choices=sorted(SAM_ENCODERS))
    parser.add_argument("--clip", default="tiny", choices=sorted(CLIP_MODELS))
    parser.add_argument("--scenes", type=int, default=2)
    parser.add_argument("--images", type=int, default=6, help="images per scene")
    parser.add_argument("--size", default="320x240", help="W×H of the images")
    parser.add_argument("--points-per-side", type=int, default=8)
    parser.add_argument("--actors", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--gpus-per-actor", type=float, default=0.0)
    parser.add_argument("--num-cpus", type=int, default=None, help="the local Ray's CPUs")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    config = PreprocessConfig(
        masks=MaskGeneratorConfig(
            points_per_side=args.points_per_side,
            pred_iou_threshold=0.0,
            stability_threshold=0.0,
            min_region_area=20,
        )
    )
    if args.device == "cpu":
        torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        torch.manual_seed(0)
        sam = str(save_sam(root / "sam", args.sam))
        clip = str(save_clip(root / "clip", args.clip))
        generator = np.random.default_rng(0)
        scenes = []
        for s in range(args.scenes):
            folder = root / f"scene_{s}" / "images"
            folder.mkdir(parents=True)
            for i in range(args.images):
                pixels = generator.integers(0, 256, (height, width, 3), dtype=np.uint8)
                Image.fromarray(pixels).save(folder / f"frame_{i:03d}.png")
            scenes.append((tuple(image_jobs(folder)), folder.parent))
        images = args.scenes * args.images

        start = time.perf_counter()
        segmenter, encoder = load_preprocess_models(
            sam, clip, device=args.device, dtype=getattr(torch, args.dtype)
        )
        model_load = time.perf_counter() - start
        start = time.perf_counter()
        for jobs, scene in scenes:
            preprocess_images(jobs, scene / "in_process", segmenter, encoder, config)
        in_process = time.perf_counter() - start
        t_image = in_process / images

        start = time.perf_counter()
        with connect_ray(None, num_cpus=args.num_cpus) as connection:
            ray_start = time.perf_counter() - start
            import ray

            record = {
                "device": torch.cuda.get_device_name() if args.device != "cpu" else "cpu",
                "ray_cpus": connection.cpus,
                "ray_gpus": connection.gpus,
                "sam": args.sam,
                "clip": args.clip,
                "image": f"{width}x{height}",
                "points_per_side": args.points_per_side,
                "images": images,
                "scenes": args.scenes,
                "ray_start_s": round(ray_start, 2),
                "model_load_s": round(model_load, 2),
                "seconds_per_image": round(t_image, 3),
                "in_process_total_s": round(model_load + in_process, 2),
                "worker_start_and_model_load_s": round(
                    worker_model_load(ray, sam, clip, args.device, args.dtype, args.gpus_per_actor),
                    2,
                ),
                "per_task_overhead_s": round(per_task_overhead(ray, max(args.actors)), 4),
                "ray": [],
            }
            for actors in args.actors:
                targets = [
                    PreprocessTarget(jobs, scene / f"ray_{actors}") for jobs, scene in scenes
                ]
                start = time.perf_counter()
                summaries = preprocess_with_ray(
                    targets,
                    sam=sam,
                    clip=clip,
                    config=config,
                    device=args.device,
                    dtype=args.dtype,
                    actors=actors,
                    gpus_per_actor=args.gpus_per_actor,
                )
                wall = time.perf_counter() - start
                worker = np.mean([s for summary in summaries for s in summary.done.values()])
                record["ray"].append(
                    {
                        "actors": actors,
                        "total_s": round(wall, 2),
                        "seconds_per_image_in_actor": round(float(worker), 3),
                        "fixed_overhead_s": round(wall - images * worker / actors, 2),
                        "speed_up": None,
                        "same_files_as_in_process": all(
                            same_files(scene / f"ray_{actors}", scene / "in_process")
                            for _, scene in scenes
                        ),
                    }
                )
            first = record["ray"][0]["total_s"]
            for run in record["ray"]:
                run["speed_up"] = round(first / run["total_s"], 2)  # vs the first count
    print(json.dumps(record), flush=True)


if __name__ == "__main__":
    main()
