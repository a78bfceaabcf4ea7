"""The build's memory floor and the memory left, read from hand-written /proc and cgroup trees;
a build that cannot fit stops before any work."""

from __future__ import annotations

from pathlib import Path

import pytest

from test_pipeline import oracle_views, plane_scene
from thgs.errors import ThgsError
from thgs.memory import available_memory, build_memory_floor, check_build_memory
from thgs.pipeline import lift_scene
from thgs.synthetic import OracleConfig

GIB = 1 << 30


def fake_proc(root: Path, available_kib: int, resident_kib: int = 0, cgroup: str = "0::/\n"):
    proc = root / "proc"
    (proc / "self").mkdir(parents=True)
    (proc / "meminfo").write_text(
        f"MemTotal:       99999999 kB\nMemFree:         1000 kB\n"
        f"MemAvailable:   {available_kib} kB\n"
    )
    (proc / "self" / "status").write_text(f"Name:\tpython\nVmRSS:\t  {resident_kib} kB\n")
    (proc / "self" / "cgroup").write_text(cgroup)
    return proc


def test_floor_by_hand():
    """N = 1000, 10 views of 100×50, 2 workers: 1000 × 1200 B, the lift 20 B × ¼ × 1000 × 10
    (or the lift memory when smaller), 2 × 40 B × 5000 pixels, plus the base."""
    floor = build_memory_floor(1000, 10, 100, 50, None, 2)
    assert (floor.gaussians, floor.lift, floor.views) == (1_200_000, 50_000, 400_000)
    assert floor.total == floor.base + 1_650_000
    assert build_memory_floor(1000, 10, 100, 50, 30_000, 2).lift == 30_000
    on_gpu = build_memory_floor(1000, 10, 100, 50, None, 1, "cuda")
    assert (on_gpu.base, on_gpu.gaussians, on_gpu.total) == (0, 0, 50_000 + 200_000)


def test_available_memory_from_meminfo_alone(tmp_path):
    proc = fake_proc(tmp_path, 2_000_000)
    assert available_memory(proc, tmp_path / "no-cgroup") == (2_048_000_000, str(proc / "meminfo"))
    assert available_memory(tmp_path / "missing", tmp_path / "missing") is None


def test_a_cgroup_v2_limit_below_meminfo_wins(tmp_path):
    """Limit 3 GB, 2.5 GB used of which 0.2 GB inactive file cache: 0.7 GB left."""
    proc = fake_proc(tmp_path, 8_000_000, cgroup="0::/job/step\n")
    group = tmp_path / "cg" / "job" / "step"
    group.mkdir(parents=True)
    (group / "memory.max").write_text("3000000000\n")
    (group / "memory.current").write_text("2500000000\n")
    (group / "memory.stat").write_text("anon 1\ninactive_file 200000000\nactive_file 5\n")
    assert available_memory(proc, tmp_path / "cg") == (700_000_000, str(group / "memory.max"))
    (group / "memory.max").write_text("max\n")  # no limit: meminfo decides
    assert available_memory(proc, tmp_path / "cg")[0] == 8_192_000_000


def test_a_cgroup_v1_limit_at_the_mount_root(tmp_path):
    """The process's cgroup path is not mounted inside the container: the mount root's files."""
    proc = fake_proc(tmp_path, 8_000_000, cgroup="4:memory:/docker/abc\n1:cpu:/\n")
    memory = tmp_path / "cg" / "memory"
    memory.mkdir(parents=True)
    (memory / "memory.limit_in_bytes").write_text("1000000000\n")
    (memory / "memory.usage_in_bytes").write_text("600000000\n")
    (memory / "memory.stat").write_text("cache 9\ntotal_inactive_file 100000000\n")
    left, source = available_memory(proc, tmp_path / "cg")
    assert (left, source) == (500_000_000, str(memory / "memory.limit_in_bytes"))


def test_check_counts_what_the_process_holds(tmp_path):
    """Floor 1.65 MB + base; the process already holds the base and 1 MB of it."""
    floor = build_memory_floor(1000, 10, 100, 50, None, 2).total
    held = floor - 1_000_000
    enough = fake_proc(tmp_path / "a", 1000, resident_kib=held // 1024)  # 1.02 MB left
    check_build_memory(1000, 10, 100, 50, None, 2, proc=enough, cgroup_root=tmp_path / "none")
    short = fake_proc(tmp_path / "b", 900, resident_kib=held // 1024)  # 0.92 MB left
    with pytest.raises(
        ThgsError, match=r"1,000 Gaussians and 10 views of 100×50 needs .*proc/meminfo"
    ):
        check_build_memory(1000, 10, 100, 50, None, 2, proc=short, cgroup_root=tmp_path / "none")


def test_a_build_that_cannot_fit_stops_before_lifting(tmp_path, monkeypatch):
    """lift_scene with 1 MB left (and nothing held yet): ThgsError naming the numbers, no view
    lifted, no cache."""
    scene, hierarchy = plane_scene(side=20, views=2)
    guidance = oracle_views(scene, hierarchy, OracleConfig())
    monkeypatch.setattr("thgs.memory._resident", lambda _: 0)
    monkeypatch.setattr("thgs.memory.available_memory", lambda *_: (1 << 20, "a test"))
    lifted = []
    with pytest.raises(ThgsError, match=r"400 Gaussians and 2 views of 160×120 needs at least"):
        lift_scene(scene, guidance, progress=lambda *step: lifted.append(step), cache=tmp_path)
    assert lifted == [] and list(tmp_path.iterdir()) == []
    monkeypatch.setattr("thgs.memory.available_memory", lambda *_: (64 * GIB, "a test"))
    assert len(lift_scene(scene, guidance).lifted) == 2
