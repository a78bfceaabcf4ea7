"""Time synthetic dataset generation per preset; report the size on disk and peak memory.

    .venv/bin/python benchmarks/bench_synth.py                      # synth-small and synth-medium
    .venv/bin/python benchmarks/bench_synth.py --presets synth-large --keep /data/synth

Each preset runs in its own process (its peak resident memory is its own) and writes into a
temporary folder that is deleted afterwards unless ``--keep`` names a folder to keep it in. Times:
scene generation, loading the text model, and writing the dataset (rendering every view, oracle
guidance, labels, files).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run_one(preset: str, out: Path) -> dict:
    from thgs.synthetic import generate_scene, write_dataset
    from thgs.synthetic import preset as scene_preset
    from thgs.text import MiniLMEncoder

    start = time.perf_counter()
    scene = generate_scene(scene_preset(preset))
    generated = time.perf_counter()
    encoder = MiniLMEncoder()
    loaded = time.perf_counter()
    summary = write_dataset(out, scene, encoder, overwrite=True)
    written = time.perf_counter()
    return {
        "preset": preset,
        "gaussians": summary.gaussians,
        "views": summary.views,
        "size": f"{scene.config.width}x{scene.config.height}",
        "masks": summary.masks,
        "generate_s": round(generated - start, 2),
        "text_model_s": round(loaded - generated, 2),
        "write_s": round(written - loaded, 2),
        "total_s": round(written - start, 2),
        "per_view_s": round((written - loaded) / summary.views, 3),
        "disk_mb": round(summary.bytes / 1e6, 1),
        "peak_rss_gib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["synth-small", "synth-medium"])
    parser.add_argument("--keep", type=Path, help="keep the datasets in this folder")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(run_one(args.child, args.out)))
        return
    print(
        "| preset | Gaussians | views | size | masks | generate s | text model s | write s "
        "| s/view | total s | disk MB | peak RSS GiB |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for preset in args.presets:
        with tempfile.TemporaryDirectory() as scratch:
            out = (args.keep or Path(scratch)) / preset
            result = subprocess.run(
                [sys.executable, __file__, "--child", preset, "--out", str(out)],
                check=True,
                capture_output=True,
                text=True,
            )
        r = json.loads(result.stdout.strip().splitlines()[-1])
        print(
            f"| {r['preset']} | {r['gaussians']:,} | {r['views']} | {r['size']} | {r['masks']:,} "
            f"| {r['generate_s']} | {r['text_model_s']} | {r['write_s']} | {r['per_view_s']} "
            f"| {r['total_s']} | {r['disk_mb']} | {r['peak_rss_gib']} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
