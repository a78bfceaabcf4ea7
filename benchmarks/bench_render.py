"""Time rasterization, splat-back and label weighing per view, for every backend on every device.

    .venv/bin/python benchmarks/bench_render.py        # 100k and 1M, 320x240 and 986x728
    .venv/bin/python benchmarks/bench_render.py --gaussians 100000 --size 320x240 --kind 3dgs
    .venv/bin/python benchmarks/bench_render.py --backends numba torch --devices cpu

Each (configuration, backend, device) runs in its own process so that its peak memory is its own:
resident memory on the CPU, ``torch.cuda.max_memory_allocated`` on CUDA. Every backend usable on
every device present is run (numba on the CPU, torch everywhere, gsplat on CUDA), and a markdown
table puts them side by side. The scene is surfels/ellipsoids sampled on the surfaces of a ground
plane and a few spheres in front of the camera, with sizes like a trained scene's (a few pixels
each), so that depth complexity and coverage are realistic rather than one giant blob. The label
maps of ``splat_labels`` are four levels of blocks (64, 32, 16 and 8 px), like the four SAM levels
the lifting weighs.
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
from thgs.device import resolve_device
from thgs.errors import InputError
from thgs.render import BACKENDS, RasterConfig, render, resolve_backend, splat_back, splat_labels


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


def block_labels(width: int, height: int) -> torch.Tensor:
    """[4, H, W] int64 labels: blocks of 64, 32, 16 and 8 px, numbered level after level."""
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    levels, offset = [], 0
    for block in (64, 32, 16, 8):
        columns = -(-width // block)
        levels.append(offset + (ys // block) * columns + xs // block)
        offset += columns * -(-height // block)
    return torch.stack(levels)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def run_one(
    n: int, width: int, height: int, kind: str, backend: str, device_name: str, repeats: int
) -> dict:
    device = resolve_device(device_name)
    config = RasterConfig(backend=backend)
    _, dtype = resolve_backend(config, device)
    gaussians = surface_scene(n, kind).to(device)
    camera = front_camera(width, height)
    codes = torch.randn(height, width, 20, device=device)
    features = torch.randn(n, 3, device=device)
    labels = block_labels(width, height).to(device)
    calls = {
        "render": lambda: render(gaussians, camera, features, config=config),
        "splat_back_20ch": lambda: splat_back(gaussians, camera, codes, config=config),
        "splat_labels_4": lambda: splat_labels(gaussians, camera, labels, config=config),
    }
    for call in calls.values():  # compile (numba caches to disk, gsplat builds once), warm up
        call()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    timings = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            _sync(device)
            start = time.perf_counter()
            call()
            _sync(device)
            timings[name].append(time.perf_counter() - start)
    coverage = float(
        (render(gaussians, camera, features, config=config).alpha > 0.5).double().mean()
    )
    peak = (
        torch.cuda.max_memory_allocated(device) / 2**20
        if device.type == "cuda"
        else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    )
    return {
        "gaussians": n,
        "size": f"{width}x{height}",
        "kind": kind,
        "backend": backend,
        "device": str(device),
        "dtype": str(dtype).removeprefix("torch."),
        "threads": torch.get_num_threads(),
        **{f"{name}_s": round(min(values), 4) for name, values in timings.items()},
        "coverage_alpha_gt_0.5": round(coverage, 3),
        "peak_mib": round(peak, 1),
        "peak_kind": "cuda allocated" if device.type == "cuda" else "rss",
    }


def present_devices() -> list[str]:
    """The devices this machine has: the CPU, and CUDA and MPS when torch sees them."""
    devices = ["cpu"]
    for name in ("cuda", "mps"):
        try:
            resolve_device(name)
            devices.append(name)
        except InputError:
            pass
    return devices


def usable(backend: str, device: str) -> bool:
    try:
        resolve_backend(RasterConfig(backend=backend), resolve_device(device))
    except InputError:
        return False
    return True


def table(results: list[dict]) -> str:
    """The results side by side: one row per configuration, a column group per backend."""
    lines = [
        "| kind | Gaussians | size | backend | device | render | splat-back 20 ch "
        "| splat_labels 4 levels | peak |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['kind']} | {r['gaussians']:,} | {r['size']} | {r['backend']} | {r['device']} "
            f"| {r['render_s']:.3f} s | {r['splat_back_20ch_s']:.3f} s "
            f"| {r['splat_labels_4_s']:.3f} s | {r['peak_mib']:.0f} MiB |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, nargs="*", default=[100_000, 1_000_000])
    parser.add_argument("--size", nargs="*", default=["320x240", "986x728"])
    parser.add_argument("--kind", nargs="*", default=["2dgs", "3dgs"])
    parser.add_argument("--backends", nargs="*", default=list(BACKENDS))
    parser.add_argument("--devices", nargs="*", default=None, help="default: every one present")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        width, height = map(int, args.size[0].split("x"))
        result = run_one(
            args.gaussians[0],
            width,
            height,
            args.kind[0],
            args.backends[0],
            args.devices[0],
            args.repeats,
        )
        print(json.dumps(result))
        return
    devices = args.devices if args.devices is not None else present_devices()
    results = []
    for kind in args.kind:
        for n in args.gaussians:
            for size in args.size:
                for device in devices:
                    for backend in args.backends:
                        if not usable(backend, device):
                            continue
                        command = [
                            sys.executable, __file__, "--one", "--gaussians", str(n),
                            "--size", size, "--kind", kind, "--backends", backend,
                            "--devices", device, "--repeats", str(args.repeats),
                        ]  # fmt: skip
                        run = subprocess.run(command, capture_output=True, text=True, check=True)
                        results.append(json.loads(run.stdout.strip().splitlines()[-1]))
                        print(json.dumps(results[-1]), flush=True)
    print(table(results))


if __name__ == "__main__":
    main()
