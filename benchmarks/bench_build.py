"""Time, peak memory and per-level quality of ``build_field`` on the synthetic presets.

    .venv/bin/python benchmarks/bench_build.py                          # synth-small, medium
    .venv/bin/python benchmarks/bench_build.py --presets synth-small --seeds 0 1 2 3

Each (preset, seed) runs in its own process. The guidance is the synthetic oracle's at its default
fault severity (0.5) with hash features (quality here is about regions, not text). The field is
built with the LERF preset (ours) and with the authors' behaviour (``FieldConfig.as_reference``)
on the same inputs. Reported: seconds per stage (``SemanticField.timings``), the total, the peak
resident memory of the whole build (sampled every 5 ms, so it counts what the process already
held), region counts per level, superpoint purity and the matched-region mIoU of levels 1–3
against the ground-truth sub-parts, parts and objects. One JSON line per run, then a markdown
table.
"""

from __future__ import annotations

import numpy as np
import torch
from bench_partition import HashEncoder, measured, oracle_views, runs_in_subprocesses

from thgs.eval import matched_miou, purity
from thgs.pipeline import FieldConfig, build_field
from thgs.synthetic import OracleConfig, generate_scene, preset


def run_one(name: str, seed: int) -> dict:
    scene = generate_scene(preset(name, seed=seed))
    encoder, oracle = HashEncoder(), OracleConfig(seed=seed)
    views = oracle_views(scene, encoder, oracle)
    truth = scene.hierarchy.labels
    results = {}
    for variant, config in {
        "ours": FieldConfig.lerf(),
        "reference": FieldConfig().as_reference(),
    }.items():
        field, seconds, peak_gib = measured(
            lambda config=config: build_field(scene, views, config, space=encoder.space)
        )
        results[variant] = {
            "seconds": seconds,
            "peak_gib": peak_gib,
            "stages": {stage: round(value, 3) for stage, value in field.timings.items()},
            "region_counts": list(field.region_counts),
            "purity": round(purity(field.labels[:, 0], truth[:, 0]), 4),
            "miou": [
                round(matched_miou(field.labels[:, k], truth[:, k - 1]), 4) for k in (1, 2, 3)
            ],
        }
    return {
        "preset": name,
        "seed": seed,
        "gaussians": len(scene.gaussians),
        "views": len(scene.cameras),
        "threads": torch.get_num_threads(),
        "ground_truth_counts": [len(level) for level in scene.hierarchy.names],
        "variants": results,
    }


def table(runs: list[dict]) -> str:
    lines = [
        "| preset | seed | variant | total s | lift s | peak GiB | regions L0–L3 | purity "
        "| mIoU sub-part | part | object |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run in runs:
        for variant, r in run["variants"].items():
            counts = " / ".join(str(c) for c in r["region_counts"])
            lines.append(
                f"| {run['preset']} | {run['seed']} | {variant} | {r['seconds']:.1f} "
                f"| {r['stages']['lift']:.1f} | {r['peak_gib']:.2f} | {counts} "
                f"| {r['purity']:.3f} | " + " | ".join(f"{m:.3f}" for m in r["miou"]) + " |"
            )
    lines.append("")
    for variant in ("ours", "reference"):
        scores = [run["variants"][variant]["miou"] for run in runs]
        if scores:
            mean = np.mean(scores, axis=0)
            lines.append(f"mean mIoU ({variant}): " + " / ".join(f"{m:.3f}" for m in mean))
    return "\n".join(lines)


def main() -> None:
    print(table(runs_in_subprocesses(__doc__, __file__, run_one)))


if __name__ == "__main__":
    main()
