"""Time, peak memory and per-level quality of ``build_field`` on the synthetic presets.

    .venv/bin/python benchmarks/bench_build.py                          # synth-small, medium
    .venv/bin/python benchmarks/bench_build.py --presets synth-small --seeds 0 1 2 3
    .venv/bin/python benchmarks/bench_build.py --backends numba torch gsplat   # side by side
    .venv/bin/python benchmarks/bench_build.py --runs numba:cpu gsplat:cuda --no-reference
    .venv/bin/python benchmarks/bench_build.py --set superpoints.partition.cp_it_max=6

Each (preset, seed) runs in its own process. The guidance is the synthetic oracle's at its default
fault severity (0.5) with all-MiniLM-L6-v2 text features (as in ``thgs demo``: the grouping of
repeated parts and the region features depend on them). The field is built with the LERF preset
(ours) by every backend in ``--backends`` (default numba) on every device present where it runs
(``--devices``), and with the authors' behaviour (``FieldConfig.as_reference``) on the same
inputs.
Reported: seconds per stage (``SemanticField.timings``), the total, the peak resident memory of
the whole build (sampled every 5 ms, so it counts what the process already held), region counts
per level, superpoint purity, the matched-region mIoU of levels 1–3 against the ground-truth
sub-parts, parts and objects, and the feature accuracy of levels 1–3: the share of Gaussians
whose region's feature is nearest to the name of the region's majority ground-truth node among
the names of that level. One JSON line per run, then a markdown table.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
import torch
from bench_partition import measured, oracle_views, runs_in_subprocesses
from bench_render import present_devices

from thgs.device import resolve_device
from thgs.errors import InputError
from thgs.eval import matched_miou, purity
from thgs.pipeline import FieldConfig, build_field, chosen_field_config
from thgs.render import BACKENDS, resolve_backend
from thgs.synthetic import OracleConfig, generate_scene, preset
from thgs.text import MiniLMEncoder


def feature_accuracy(regions: np.ndarray, truth: np.ndarray, features, names, encoder) -> float:
    """Share of Gaussians whose region's feature is nearest to the name of the region's majority
    ground-truth node, among the level's names (a region no view saw counts as wrong).

    Args:
        regions: [N] region id per Gaussian; truth: [N] ground-truth node per Gaussian (−1 none).
        features: [R, D] unit region features; names: the level's node names.
    """
    vocabulary = sorted(set(names))
    nearest = np.asarray(features @ encoder.encode(vocabulary).T).argmax(axis=1)
    nearest[~np.any(features != 0, axis=1)] = -1
    pairs, counts = np.unique(np.stack([regions, truth], axis=1), axis=0, return_counts=True)
    pairs, counts = pairs[pairs[:, 1] >= 0], counts[pairs[:, 1] >= 0]
    order = np.lexsort((-counts, pairs[:, 0]))
    pairs, counts = pairs[order], counts[order]
    first = np.ones(len(pairs), dtype=bool)
    first[1:] = pairs[1:, 0] != pairs[:-1, 0]
    majority = dict(zip(pairs[first, 0].tolist(), pairs[first, 1].tolist()))
    right = [
        nearest[r] >= 0 and vocabulary[nearest[r]] == names[node] for r, node in majority.items()
    ]
    sizes = np.bincount(regions)[list(majority)]
    return float(np.sum(sizes * np.array(right)) / sizes.sum())


def _variants(args: argparse.Namespace) -> dict[str, tuple[FieldConfig, torch.device]]:
    """ "ours" on the ``--runs`` pairs, or on every asked backend and device present, and the
    authors' behaviour once unless ``--no-reference``."""
    if args.runs:
        pairs = [run.split(":", 1) for run in args.runs]
        if any(len(pair) != 2 for pair in pairs):
            raise SystemExit(f"--runs takes BACKEND:DEVICE pairs, got {args.runs}")
    else:
        devices = args.devices if args.devices else present_devices()
        pairs = [(backend, device) for device in devices for backend in args.backends]
    variants = {}
    chosen = chosen_field_config(settings=args.set)
    for backend, device_name in pairs:
        device = resolve_device(device_name)
        raster = replace(chosen.superpoints.lift.raster, backend=backend)  # keeps --set's
        try:
            resolve_backend(raster, device)
        except InputError:
            if args.runs:
                raise
            continue
        lift = replace(chosen.superpoints.lift, raster=raster)
        config = replace(chosen, superpoints=replace(chosen.superpoints, lift=lift))
        variants[f"ours {backend} {device}"] = (config, device)
    if args.reference:
        variants["reference"] = (FieldConfig().as_reference(), torch.device("cpu"))
    return variants


def options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--backends", nargs="*", default=["numba"], help=f"of {BACKENDS}")
    parser.add_argument("--devices", nargs="*", default=None, help="default: every one present")
    parser.add_argument(
        "--runs",
        nargs="*",
        default=None,
        metavar="BACKEND:DEVICE",
        help="exactly these pairs (e.g. numba:cpu torch:cuda) instead of --backends × --devices",
    )
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="NAME=VALUE",
        help="settings of ours changed as thgs build --set (superpoints.partition.cp_it_max=6)",
    )
    parser.add_argument(
        "--reference",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also build with the authors' behaviour (numba, CPU)",
    )


def run_one(name: str, seed: int, args: argparse.Namespace) -> dict:
    scene = generate_scene(preset(name, seed=seed))
    encoder, oracle = MiniLMEncoder(), OracleConfig(seed=seed)
    views = oracle_views(scene, encoder, oracle)
    truth = scene.hierarchy.labels
    results = {}
    for variant, (config, device) in _variants(args).items():
        posed = replace(scene, gaussians=scene.gaussians.to(device))
        field, seconds, peak_gib = measured(
            lambda config=config, posed=posed: build_field(
                posed, views, config, space=encoder.space
            )
        )
        results[variant] = {
            "seconds": seconds,
            "peak_gib": peak_gib,
            "stages": {stage: round(value, 3) for stage, value in field.timings.items()},
            "region_counts": list(field.region_counts),
            "purity": round(purity(field.labels[:, 0], truth[:, 1]), 4),
            "miou": [round(matched_miou(field.labels[:, k], truth[:, k]), 4) for k in (1, 2, 3)],
            "feature_accuracy": [
                round(
                    feature_accuracy(
                        field.labels[:, k],
                        truth[:, k],
                        field.features[k - 1],
                        scene.hierarchy.names[k],
                        encoder,
                    ),
                    4,
                )
                for k in (1, 2, 3)
            ],
        }
    return {
        "preset": name,
        "seed": seed,
        "gaussians": len(scene.gaussians),
        "views": len(scene.cameras),
        "threads": torch.get_num_threads(),
        "ground_truth_counts": [len(level) for level in scene.hierarchy.names.values()],
        "variants": results,
    }


def table(runs: list[dict]) -> str:
    lines = [
        "| preset | seed | variant | total s | lift s | peak GiB | regions L0–L3 | purity "
        "| mIoU sub-part | part | object | feature accuracy sub-part | part | object |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run in runs:
        for variant, r in run["variants"].items():
            counts = " / ".join(str(c) for c in r["region_counts"])
            lines.append(
                f"| {run['preset']} | {run['seed']} | {variant} | {r['seconds']:.1f} "
                f"| {r['stages']['lift']:.1f} | {r['peak_gib']:.2f} | {counts} "
                f"| {r['purity']:.3f} | "
                + " | ".join(f"{m:.3f}" for m in r["miou"] + r["feature_accuracy"])
                + " |"
            )
    lines.append("")
    for variant in runs[0]["variants"] if runs else ():
        for key, what in (("miou", "mIoU"), ("feature_accuracy", "feature accuracy")):
            scores = [run["variants"][variant][key] for run in runs]
            if scores:
                mean = np.mean(scores, axis=0)
                lines.append(f"mean {what} ({variant}): " + " / ".join(f"{m:.3f}" for m in mean))
    return "\n".join(lines)


def main() -> None:
    print(table(runs_in_subprocesses(__doc__, __file__, run_one, options)))


if __name__ == "__main__":
    main()
