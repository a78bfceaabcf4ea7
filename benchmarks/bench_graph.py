"""Time the superpoint-graph stages: KNN graph, edge votes + reweighting, cut-pursuit partition.

    .venv/bin/python benchmarks/bench_graph.py                  # 100k and 1M Gaussians
    .venv/bin/python benchmarks/bench_graph.py --gaussians 100000 --views 50

Each size runs in its own process so that its peak resident memory is its own. The scene is 2DGS
surfels on a ground plane (a checkerboard of 1-unit tiles in two colours) and five spheres of one
colour each, colours with a little noise, so that the colour part of the 6-D search space is
spatially coherent as in a trained scene. The views are synthetic lifts: each sees a random share
of the Gaussians (``--visibility``), labels them with a per-view permutation of their object or
tile id, leaves 10 % unlabelled, at depths uniform in 2–10 scene units.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time

import numpy as np
import torch

from thgs import Gaussians
from thgs.graph import (
    GraphConfig,
    PartitionConfig,
    ReweightConfig,
    edge_counts,
    knn_graph,
    partition,
    reweight,
)
from thgs.lift import ViewLift
from thgs.scene.gaussians import SH_C0


def surface_scene(n: int, seed: int = 0) -> tuple[Gaussians, np.ndarray]:
    """n surfels on a plane and five spheres, and their [n] segment ids (tile or sphere)."""
    rng = np.random.default_rng(seed)
    n_plane = n // 3
    plane = np.column_stack([rng.uniform(-4, 4, (n_plane, 2)), np.zeros(n_plane)])
    tiles = np.floor(plane[:, 0]).astype(np.int64) + 8 * np.floor(plane[:, 1]).astype(np.int64)
    checker = (np.floor(plane[:, 0]) + np.floor(plane[:, 1])) % 2
    plane_rgb = np.where(checker[:, None] == 0, [0.8, 0.8, 0.7], [0.3, 0.3, 0.35])
    centres = np.array(
        [[-1.5, 0, 1], [1, 0.2, 1], [0, -2.5, 1], [2.5, 2.5, 1], [-2.5, 2.5, 1]], dtype=float
    )
    sphere_colours = np.array(
        [[0.9, 0.1, 0.1], [0.1, 0.8, 0.2], [0.1, 0.2, 0.9], [0.9, 0.8, 0.1], [0.6, 0.2, 0.7]]
    )
    n_sphere = n - n_plane
    which = rng.integers(0, 5, n_sphere)
    directions = rng.normal(size=(n_sphere, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    means = np.concatenate([plane, centres[which] + 0.9 * directions])
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (n_plane, 1)), directions])
    rgb = np.concatenate([plane_rgb, sphere_colours[which]]) + 0.03 * rng.normal(size=(n, 3))
    segments = np.concatenate([tiles - tiles.min(), 1000 + which])
    # a rotation whose third column is the normal: the quaternion taking z to the normal
    w = 1.0 + normals[:, 2:3]
    axis = np.column_stack([-normals[:, 1], normals[:, 0], np.zeros(n)])
    quats = np.concatenate([w, axis], axis=1) + 1e-9
    spacing = math.sqrt(60.0 / n)
    gaussians = Gaussians(
        means=torch.tensor(means, dtype=torch.float32),
        quats=torch.tensor(quats, dtype=torch.float32),
        scales=torch.full((n, 2), math.log(spacing)),
        opacities=torch.full((n,), 2.0),
        sh=torch.tensor((rgb - 0.5) / SH_C0, dtype=torch.float32)[:, None, :],
    )
    return gaussians.check(), segments


def synthetic_views(
    segments: np.ndarray, views: int, visibility: float, seed: int = 1
) -> list[ViewLift]:
    """Random lifts: per view a random share of Gaussians, permuted segment ids as labels."""
    rng = np.random.default_rng(seed)
    n = segments.size
    out = []
    for _ in range(views):
        seen = np.flatnonzero(rng.random(n) < visibility).astype(np.int32)
        permutation = rng.permutation(int(segments.max()) + 1).astype(np.int32)
        labels = np.full((seen.size, 4), -1, dtype=np.int32)
        labels[:, 1] = np.where(rng.random(seen.size) < 0.9, permutation[segments[seen]], -1)
        depths = rng.uniform(2.0, 10.0, seen.size).astype(np.float32)
        weights = rng.uniform(0.01, 1.0, seen.size).astype(np.float32)
        out.append(ViewLift(seen, labels, depths, weights))
    return out


def run_one(
    n: int, views: int, visibility: float, alternatives: int, polish: bool, coarsen: int
) -> dict:
    gaussians, segments = surface_scene(n)
    lifts = synthetic_views(segments, views, visibility)
    tiny = knn_graph(gaussians.select(np.arange(1000)))
    edge_counts(tiny, synthetic_views(segments[:1000], 1, 0.5))  # compile the numba kernel
    timings = {}
    start = time.perf_counter()
    graph = knn_graph(gaussians, GraphConfig())
    timings["knn_s"] = time.perf_counter() - start
    start = time.perf_counter()
    pos, neg = edge_counts(graph, lifts, ReweightConfig())
    timings["edge_counts_s"] = time.perf_counter() - start
    start = time.perf_counter()
    distances = reweight(graph, pos, neg, ReweightConfig())
    timings["reweight_s"] = time.perf_counter() - start
    start = time.perf_counter()
    config = PartitionConfig(split_alternatives=alternatives, polish=polish, coarsen_levels=coarsen)
    labels = partition(gaussians, graph, distances, config)
    timings["partition_s"] = time.perf_counter() - start
    return {
        "gaussians": n,
        "views": views,
        "visibility": visibility,
        "split_alternatives": alternatives,
        "polish": polish,
        "coarsen_levels": coarsen,
        "threads": torch.get_num_threads(),
        **{key: round(value, 2) for key, value in timings.items()},
        "total_s": round(sum(timings.values()), 2),
        "superpoints": int(labels.max()) + 1,
        "mean_squared_distance": float(graph.distances[graph.valid()].mean()),
        "edges_with_negative_votes": round(float((neg > 0).mean()), 3),
        "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, nargs="*", default=[100_000, 1_000_000])
    parser.add_argument("--views", type=int, default=200)
    parser.add_argument("--visibility", type=float, default=0.2)
    parser.add_argument(
        "--split-alternatives",
        type=int,
        default=PartitionConfig().split_alternatives,
        help="cut pursuit's K (the reference's is 2)",
    )
    parser.add_argument(
        "--no-polish", action="store_true", help="keep the solver's superpoints (the reference)"
    )
    parser.add_argument(
        "--coarsen-levels",
        type=int,
        default=PartitionConfig().coarsen_levels,
        help="passes of heavy-edge matching before the solver (0: every Gaussian)",
    )
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        result = run_one(
            args.gaussians[0],
            args.views,
            args.visibility,
            args.split_alternatives,
            not args.no_polish,
            args.coarsen_levels,
        )
        print(json.dumps(result))
        return
    for n in args.gaussians:
        command = [
            sys.executable,
            __file__,
            "--one",
            "--gaussians",
            str(n),
            "--views",
            str(args.views),
            "--visibility",
            str(args.visibility),
            "--split-alternatives",
            str(args.split_alternatives),
            *(["--no-polish"] if args.no_polish else []),
            "--coarsen-levels",
            str(args.coarsen_levels),
        ]
        result = subprocess.run(command, capture_output=True, text=True, check=True)
        print(result.stdout.strip(), flush=True)


if __name__ == "__main__":
    main()
