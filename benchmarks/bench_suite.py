"""Wall time of a synthetic suite in-process against a local Ray with 2 CPUs: Ray's overhead.

    PYTHONPATH=src .venv/bin/python benchmarks/bench_suite.py
    PYTHONPATH=src .venv/bin/python benchmarks/bench_suite.py --gaussians 4000 --views 8 --repeats 2

Two synthetic datasets (seeds 0 and 1) are laid out as 2 LERF-OVS scenes, 2 3D-OVS scenes and 1
synthetic dataset (thgs.synthetic.layouts, linked); the suite (build and eval of every scene, the
language features given) runs into a fresh folder in-process, then on a local Ray started with
``num_cpus=2`` (its start-up timed apart), ``--repeats`` times each, alternating. The reports are
checked to be the same, timings aside. Prints one JSON line per run and a summary.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path


def make_root(folder: Path, gaussians: int, views: int) -> Path:
    from thgs.synthetic import OracleConfig, generate_scene, preset, write_dataset
    from thgs.synthetic.layouts import write_3dovs, write_langsplat_lerf
    from thgs.text import MiniLMEncoder

    encoder = MiniLMEncoder()
    datasets = []
    for seed in (0, 1):
        scene = generate_scene(preset("synth-small", seed=seed, gaussians=gaussians, views=views))
        oracle = OracleConfig(seed=seed)
        datasets.append(write_dataset(folder / f"synth{seed}", scene, encoder, oracle=oracle).path)
    root = folder / "root"
    write_langsplat_lerf(datasets[0], root, "teatime", link=True)
    write_langsplat_lerf(datasets[1], root, "ramen", link=True)
    write_3dovs(datasets[0], root, "bed", link=True)
    write_3dovs(datasets[1], root, "sofa", link=True)
    (root / "synthetic").mkdir()
    (root / "synthetic" / "kitchen").symlink_to(datasets[1], target_is_directory=True)
    return root


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=4000)
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args()

    import ray

    from thgs.suite import SuiteConfig, find_suite, run_suite

    config = SuiteConfig(device="cpu")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        root = make_root(folder, args.gaussians, args.views)
        scenes = find_suite(root)
        # warm the imports and the text model once, as a long-running suite would have them
        run_suite(scenes[-1:], folder / "warm", config)
        runs: dict[str, list[float]] = {"in-process": [], "ray": []}
        reports = {}
        started = time.perf_counter()
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        ray_start = time.perf_counter() - started
        for repeat in range(args.repeats):
            for executor in ("in-process", "ray"):
                out = folder / f"{executor}-{repeat}"
                begin = time.perf_counter()
                report = run_suite(scenes, out, config, use_ray=executor == "ray")
                seconds = time.perf_counter() - begin
                assert not report.failed, report.failed
                runs[executor].append(seconds)
                reports[executor] = report.comparable()
                print(json.dumps({"executor": executor, "repeat": repeat, "seconds": seconds}))
        ray.shutdown()
        assert reports["in-process"] == reports["ray"], "the reports differ"
    best = {executor: min(times) for executor, times in runs.items()}
    print(
        json.dumps(
            {
                "scenes": len(scenes),
                "gaussians": args.gaussians,
                "views": args.views,
                "in_process_s": round(best["in-process"], 1),
                "ray_s": round(best["ray"], 1),
                "ray_start_s": round(ray_start, 1),
                "overhead_s": round(best["ray"] - best["in-process"], 1),
                "overhead_with_start_s": round(best["ray"] + ray_start - best["in-process"], 1),
            }
        )
    )


if __name__ == "__main__":
    main()
