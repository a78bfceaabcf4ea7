"""The least memory a build needs, and the memory this process can still have: a build that
cannot fit stops with one clear error before any work, instead of being killed half-way.

The floor is a lower bound by construction (every term is at most what the build holds at its
peak), so the check refuses only builds that cannot fit; one that passes may still run short
when the machine's memory is taken by others meanwhile. Measured peaks, for comparison
(docs/build.md): synth-medium (300k Gaussians, 60 views at 640×480) 0.90 GiB, synth-large (1M,
200 views at 986×728) 2.95 GiB; the floor says 0.69 and 2.35 GiB.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import torch

from thgs.errors import ThgsError

__all__ = ["BuildMemory", "available_memory", "build_memory_floor", "check_build_memory"]

logger = logging.getLogger(__name__)

_GIB = float(1 << 30)

BASE_BYTES = 256 << 20
"""The interpreter with torch, numba and SciPy imported (about 0.3 GiB measured)."""

BYTES_PER_GAUSSIAN = 1200
"""What every Gaussian costs besides its lift: its parameters, the KNN graph and its weights, the
partition's features and ids, the levels (1.5–1.6 KB measured on synth-medium and synth-large)."""

LIFT_BYTES_PER_SEEN = 20
"""A lifted (Gaussian, view) pair: index, four labels, depth and largest weight (thgs.lift)."""

SEEN_SHARE_FLOOR = 0.25
"""The least share of the Gaussians a view sees in the captures measured (LERF-like ~30 %,
synthetic 65–68 %)."""

BYTES_PER_PIXEL = 40
"""A view being lifted: its four mask levels in int64 and the per-pixel rasterization state."""


@dataclass(frozen=True)
class BuildMemory:
    """The floor of a build's memory on one device, in bytes, by what holds it."""

    base: int
    gaussians: int
    lift: int
    views: int

    @property
    def total(self) -> int:
        return self.base + self.gaussians + self.lift + self.views


def build_memory_floor(
    gaussians: int,
    views: int,
    width: int,
    height: int,
    lift_memory: int | None,
    workers: int,
    device: torch.device | str = "cpu",
) -> BuildMemory:
    """The least memory :func:`thgs.pipeline.build_field` holds at its peak.

    Args:
        gaussians: N; views: M views of ``width`` × ``height`` pixels (the largest).
        lift_memory: the lift held in memory before it moves to a file (bytes; None: all).
        workers: views lifted at once.
        device: on a GPU only the lift and the views being lifted count (the Gaussians are
            already there; the rasterizer sizes its buffers by the free memory).
    """
    lift = LIFT_BYTES_PER_SEEN * SEEN_SHARE_FLOOR * gaussians * views
    if lift_memory is not None:
        lift = min(lift, lift_memory)
    frames = workers * BYTES_PER_PIXEL * width * height
    if torch.device(device).type != "cpu":
        return BuildMemory(0, 0, int(lift), frames)
    return BuildMemory(BASE_BYTES, BYTES_PER_GAUSSIAN * gaussians, int(lift), frames)


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _stat(path: Path, key: str) -> int:
    try:
        for line in path.read_text().splitlines():
            fields = line.split()
            if len(fields) >= 2 and fields[0] == key and fields[1].isdigit():
                return int(fields[1])
    except OSError:
        pass
    return 0


def _cgroup_room(proc: Path, cgroup_root: Path) -> tuple[int, str] | None:
    """Bytes left under this process's cgroup memory limit (v2 or v1), counting inactive file
    cache as free, with the limit file; None without a limit."""
    try:
        lines = (proc / "self" / "cgroup").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        _, controllers, path = line.split(":", 2)
        relative = path.lstrip("/")
        if controllers == "":
            names, mount = ("memory.max", "memory.current", "inactive_file"), cgroup_root
        elif "memory" in controllers.split(","):
            names = ("memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file")
            mount = cgroup_root / "memory"
        else:
            continue
        for folder in (mount / relative, mount):
            limit = _read_int(folder / names[0])
            usage = _read_int(folder / names[1])
            if limit is None or usage is None or limit >= 1 << 60:
                continue
            room = limit - usage + _stat(folder / "memory.stat", names[2])
            return max(room, 0), str(folder / names[0])
    return None


def available_memory(
    proc: str | os.PathLike[str] = "/proc", cgroup_root: str | os.PathLike[str] = "/sys/fs/cgroup"
) -> tuple[int, str] | None:
    """``(bytes, where from)``: what this process can still allocate on the CPU, the smaller of
    the kernel's ``MemAvailable`` and the room under its cgroup's memory limit; None where
    neither can be read (not Linux)."""
    proc, cgroup_root = Path(proc), Path(cgroup_root)
    found = []
    available = _stat(proc / "meminfo", "MemAvailable:")
    if available:
        found.append((available * 1024, str(proc / "meminfo")))
    room = _cgroup_room(proc, cgroup_root)
    if room is not None:
        found.append(room)
    return min(found) if found else None


def _resident(proc: Path) -> int:
    return _stat(proc / "self" / "status", "VmRSS:") * 1024


def check_build_memory(
    gaussians: int,
    views: int,
    width: int,
    height: int,
    lift_memory: int | None,
    workers: int,
    device: torch.device | str = "cpu",
    *,
    proc: str | os.PathLike[str] = "/proc",
    cgroup_root: str | os.PathLike[str] = "/sys/fs/cgroup",
) -> None:
    """Raise unless the build's floor (:func:`build_memory_floor`) fits what the device has
    left (what this process already holds counts towards it on the CPU).

    Raises:
        ThgsError: the floor exceeds the memory left, with both numbers and what to change.
    """
    device = torch.device(device)
    floor = build_memory_floor(gaussians, views, width, height, lift_memory, workers, device)
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        left, source, needed = int(free), f"torch.cuda.mem_get_info({device})", floor.total
    elif device.type == "cpu":
        found = available_memory(proc, cgroup_root)
        if found is None:
            logger.debug("memory check skipped: the available memory cannot be read")
            return
        (left, source), needed = found, floor.total - _resident(Path(proc))
    else:
        return
    if needed <= left:
        return
    parts = (
        f"Gaussians {floor.gaussians / _GIB:.2f}, lift held {floor.lift / _GIB:.2f}, views "
        f"being lifted {floor.views / _GIB:.2f}, interpreter and libraries {floor.base / _GIB:.2f}"
    )
    raise ThgsError(
        f"a build of {gaussians:,} Gaussians and {views} views of {width}×{height} needs at "
        f"least {floor.total / _GIB:.2f} GiB on {device} ({parts}), but only {left / _GIB:.2f} "
        f"GiB are left ({source}); free memory, use a larger machine, or lower the lift held in "
        "memory (lift_memory: the rest goes to a temporary file) or the threads (--threads)"
    )
