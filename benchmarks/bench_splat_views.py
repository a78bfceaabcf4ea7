"""Building from the splat alone against building from the real cameras (docs/build.md, "From
the splat alone").

    .venv/bin/python benchmarks/bench_splat_views.py --seeds 5 6 7 8 9 --out /tmp/splat-views

Every seed × Gaussian kind (2dgs, 3dgs) is one synth-small dataset (mask severity 0.5,
name-perfect features; ``thgs.synthetic.cache.synthetic_dataset``, cached in ``--out``). Each
is built twice with the LERF preset: from its real cameras and guidance (``thgs build DATASET``)
and from its PLY alone (``thgs build point_cloud.ply --from-splat --oracle DATASET``: virtual
cameras placed around the Gaussians, rendered, and guidance made on them by the same oracle with
the dataset's own settings). Both fields are scored by ``thgs eval`` on the dataset's ground
truth (its real evaluation views): part and object matched mIoU, LERF-style P-3D (automatic
selection) and 3D-OVS mIoU. Times: the splat's views (placement, renders, guidance) and each
build, in seconds. One JSON line per scene, then a markdown table with the means, the worst
difference (splat − real) per metric and the coverage the placement reached.

``--gaussians N`` gives the scenes that many Gaussians (e.g. 1000000 for the cost of a large
scene; the preset's other settings stay synth-small's); ``--timing-only`` then times the build
from the real cameras and the splat's views and stops there (no splat build, no scores).
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from thgs.eval import find_ground_truth
from thgs.field_config import FieldConfig
from thgs.splat_views import OracleGuidance, PlacementConfig, SplatViewsRequest
from thgs.splat_views.prepare import prepare_splat_views
from thgs.synthetic.cache import synthetic_dataset
from thgs.text import MiniLMEncoder
from thgs.workflows import BuildRequest, EvalRequest, build_field_file, evaluate_field_file

METRICS = (
    ("part", "hierarchy", "miou_part"),
    ("object", "hierarchy", "miou_object"),
    ("lerf", "lerf", "miou"),
    ("3dovs", "3dovs", "miou"),
)


def score(dataset: Path, field: Path) -> dict[str, float]:
    outcome = evaluate_field_file(
        EvalRequest(dataset=dataset, field=field, out=field.with_suffix(".json"), scene=dataset),
        find_ground_truth(dataset),
    )
    return {name: outcome.report.metric(protocol, key) for name, protocol, key in METRICS}


def run_scene(
    out: Path, seed: int, kind: str, gaussians: int | None, timing_only: bool = False
) -> dict:
    dataset, _ = synthetic_dataset(
        out / "datasets", "synth-small", seed, gaussians, None, MiniLMEncoder(), kind=kind
    )
    config = FieldConfig.lerf()
    tag = f"seed{seed}-{kind}" + (f"-{gaussians}g" if gaussians else "")
    row: dict = {"seed": seed, "kind": kind, "gaussians": gaussians or 50_000}

    real = out / f"{tag}-real.thgs"
    start = time.perf_counter()
    build_field_file(BuildRequest(scene=dataset, out=real, config=config))
    row["real build s"] = time.perf_counter() - start
    if not timing_only:
        row["real"] = score(dataset, real)

    folder = out / f"{tag}.views"
    shutil.rmtree(folder, ignore_errors=True)
    request = SplatViewsRequest(folder, OracleGuidance(dataset), PlacementConfig())
    ply = dataset / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    start = time.perf_counter()
    prepared = prepare_splat_views(ply, request)
    row["views s"] = time.perf_counter() - start
    row["views"] = len(prepared.views.cameras)
    row["covered"] = prepared.views.record["covered"]
    if timing_only:
        return row
    splat = out / f"{tag}-splat.thgs"
    start = time.perf_counter()
    build_field_file(BuildRequest(scene=ply, out=splat, config=config, splat_views=request))
    row["splat build s"] = time.perf_counter() - start
    row["splat"] = score(dataset, splat)
    return row


def table(rows: list[dict]) -> str:
    lines = [
        "| metric | real cameras (mean) | splat alone (mean) | mean difference "
        "| worst difference |",
        "|---|---|---|---|---|",
    ]
    for name, _, _ in METRICS:
        real = [row["real"][name] for row in rows]
        splat = [row["splat"][name] for row in rows]
        differences = [s - r for s, r in zip(splat, real)]
        lines.append(
            f"| {name} | {sum(real) / len(real):.3f} | {sum(splat) / len(splat):.3f} | "
            f"{sum(differences) / len(differences):+.3f} | {min(differences):+.3f} |"
        )
    views = sum(row["views"] for row in rows) / len(rows)
    covered = min(row["covered"] for row in rows)
    seconds = [(row["views s"], row["splat build s"], row["real build s"]) for row in rows]
    lines.append("")
    lines.append(
        f"{len(rows)} scenes; {views:.1f} virtual views on average, ≥ {100 * covered:.1f} % of "
        "the opaque Gaussians seen in ≥ 2 of them; seconds per scene (mean): views "
        f"{sum(s[0] for s in seconds) / len(seconds):.1f}, splat build "
        f"{sum(s[1] for s in seconds) / len(seconds):.1f}, real build "
        f"{sum(s[2] for s in seconds) / len(seconds):.1f}"
    )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[5, 6])
    parser.add_argument("--kinds", nargs="+", default=["2dgs", "3dgs"])
    parser.add_argument("--gaussians", type=int, default=None)
    parser.add_argument("--timing-only", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("/tmp/thgs-bench-splat-views"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in args.seeds:
        for kind in args.kinds:
            row = run_scene(args.out, seed, kind, args.gaussians, args.timing_only)
            rows.append(row)
            print(json.dumps(row), flush=True)
    if not args.timing_only:
        print(table(rows))


if __name__ == "__main__":
    main()
