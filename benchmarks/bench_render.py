"""Time rasterization and splat-back per view; report peak memory.

    .venv/bin/python benchmarks/bench_render.py        # 100k and 1M, 320x240 and 986x728
    .venv/bin/python benchmarks/bench_render.py --gaussians 100000 --size 320x240 --kind 3dgs

Each configuration runs in its own process so that its peak resident memory is its own. The scene
is surfels/ellipsoids sampled on the surfaces of a ground plane and a few spheres in front of the
camera, with sizes like a trained scene's (a few pixels each), so that depth complexity and
coverage are realistic rather than one giant blob.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time

import torch

from thgs import Cameras, Gaussians
from thgs.render import render, splat_back


def surface_scene(n: int, kind: str, seed: int = 0) -> Gaussians:
    """n Gaussians on a plane (z = 0 … depth 4–12) and five spheres, oriented along the surface."""
    generator = torch.Generator().manual_seed(seed)
    n_plane = n // 3
    plane = torch.rand(n_plane, 3, generator=generator) * torch.tensor([8.0, 0.0, 8.0])
    plane += torch.tensor([-4.0, 1.0, 4.0])
    plane_normals = torch.tensor([0.0, -1.0, 0.0]).expand(n_plane, 3)
    centres = torch.tensor(
        [[-1.5, 0.0, 6.0], [1.0, 0.2, 5.0], [0.0, -0.5, 8.0], [2.5, 0.3, 9.0], [-2.5, 0.4, 10.0]]
    )
    n_sphere = n - n_plane
    which = torch.randint(0, 5, (n_sphere,), generator=generator)
    directions = torch.nn.functional.normalize(torch.randn(n_sphere, 3, generator=generator), dim=1)
    sphere = centres[which] + 0.9 * directions
    means = torch.cat([plane, sphere])
    normals = torch.cat([plane_normals, directions])
    # a rotation whose third column is the normal: quaternion from the z axis to the normal
    z = torch.tensor([0.0, 0.0, 1.0]).expand_as(normals)
    axis = torch.cross(z, normals, dim=1)
    w = 1.0 + (z * normals).sum(1, keepdim=True)
    quats = torch.nn.functional.normalize(torch.cat([w, axis], dim=1) + 1e-9, dim=1)
    spacing = math.sqrt(60.0 / n)  # about the distance between neighbouring samples
    n_scales = 2 if kind == "2dgs" else 3
    scales = torch.full((n, n_scales), math.log(spacing))
    if kind == "3dgs":
        scales[:, 2] = math.log(spacing * 0.1)  # flat ellipsoids
    scales += 0.3 * torch.randn(n, n_scales, generator=generator)
    opacities = torch.randn(n, generator=generator) + 2.0
    sh = torch.randn(n, 1, 3, generator=generator) * 0.5
    return Gaussians(means, quats, scales, opacities, sh).check()


def front_camera(width: int, height: int) -> Cameras:
    focal = 0.9 * width
    K = torch.tensor(
        [[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float64
    )
    return Cameras(
        torch.eye(4, dtype=torch.float64)[None],
        K[None],
        torch.tensor([width]),
        torch.tensor([height]),
        ("bench",),
    )


def run_one(n: int, width: int, height: int, kind: str, repeats: int) -> dict:
    gaussians = surface_scene(n, kind)
    camera = front_camera(width, height)
    codes = torch.randn(height, width, 20)
    features = torch.randn(n, 3)
    render(gaussians, camera, features)  # compile (numba caches to disk) and warm up
    splat_back(gaussians, camera, codes)
    timings = {"render": [], "splat_back": []}
    coverage = 0.0
    for _ in range(repeats):
        start = time.perf_counter()
        out = render(gaussians, camera, features)
        timings["render"].append(time.perf_counter() - start)
        start = time.perf_counter()
        splat_back(gaussians, camera, codes)
        timings["splat_back"].append(time.perf_counter() - start)
        coverage = float((out.alpha > 0.5).double().mean())
    return {
        "gaussians": n,
        "size": f"{width}x{height}",
        "kind": kind,
        "device": "cpu",
        "threads": torch.get_num_threads(),
        "render_s": min(timings["render"]),
        "splat_back_20ch_s": min(timings["splat_back"]),
        "coverage_alpha_gt_0.5": round(coverage, 3),
        "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, nargs="*", default=[100_000, 1_000_000])
    parser.add_argument("--size", nargs="*", default=["320x240", "986x728"])
    parser.add_argument("--kind", nargs="*", default=["2dgs", "3dgs"])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        width, height = map(int, args.size[0].split("x"))
        print(json.dumps(run_one(args.gaussians[0], width, height, args.kind[0], args.repeats)))
        return
    for kind in args.kind:
        for n in args.gaussians:
            for size in args.size:
                command = [
                    sys.executable,
                    __file__,
                    "--one",
                    "--gaussians",
                    str(n),
                    "--size",
                    size,
                    "--kind",
                    kind,
                    "--repeats",
                    str(args.repeats),
                ]
                result = subprocess.run(command, capture_output=True, text=True, check=True)
                print(result.stdout.strip(), flush=True)


if __name__ == "__main__":
    main()
