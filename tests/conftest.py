"""Shared fixtures: the real samples in ../shared/data and small random scenes."""

from __future__ import annotations

import os

# OpenMP's threads (torch's here, in subprocesses and in Ray's workers) sleep while they wait
# instead of spinning: with other tests running beside them (``-n``) spinning threads took the
# cores from the work; the Ray tests took 2.8 times as long next to one busy process, 1.5 times
# with this. Set before anything loads OpenMP, which reads it once.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import collections
import contextlib
import functools
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from thgs import Cameras, Gaussians
from thgs.cli import entrypoint

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
RAY_IDLE_WORKER_MS = 600_000
"""How long the session's Ray keeps an idle worker (and its imports) alive: past its tests."""


DISTRIBUTED = bool(os.environ.get("PYTEST_XDIST_WORKER"))
"""This process is one of pytest-xdist's workers (``-n``): other workers share its cores."""
RAY_UNIT = "ray"
"""The unit of work that holds every module using Ray under ``-n``: sent first."""


@functools.cache
def modules_using_ray() -> frozenset[str]:
    """The test modules that ask for the session's Ray (their source names ``local_ray``), as
    pytest's node ids spell them (``tests/test_suite.py``)."""
    here = Path(__file__).parent
    return frozenset(
        f"{here.name}/{path.name}"
        for path in here.glob("test_*.py")
        if "local_ray" in path.read_text(encoding="utf-8")
    )


def pytest_configure(config: pytest.Config) -> None:
    """A worker of a distributed run computes on one thread (numba's kernels, torch's
    operators) while other workers use the other cores: threads that wait for each other across
    busy cores cost more than they bring. Tests of parallel paths set their own number
    (:func:`numba_threads`); subprocesses and Ray's workers keep the machine's defaults."""
    if DISTRIBUTED:
        import numba

        numba.set_num_threads(1)
        torch.set_num_threads(1)


@pytest.hookimpl(optionalhook=True)  # pytest-xdist's hook: absent without it
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """How ``-n`` shares the suite among pytest-xdist's workers: every module is one unit of
    work (its module fixtures are made once) and the modules that use Ray together are one
    unit, sent in the order :func:`pytest_collection_modifyitems` gives. pytest-xdist's own
    ``loadgroup`` cannot group them: it marks groups in the node ids, which pytest 9.2 no
    longer lets a plugin change (pytest-dev/pytest-xdist#1386)."""
    from xdist.scheduler import LoadScopeScheduling

    config.option.loadscopereorder = False  # keep the collection's order
    with_ray = modules_using_ray()

    class ModulesWithRayTogether(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return RAY_UNIT if module in with_ray else module

    return ModulesWithRayTogether(config, log)


@contextlib.contextmanager
def numba_threads(count: int):
    """numba's kernels on ``count`` threads (at most ``NUMBA_NUM_THREADS``) while inside."""
    import numba

    before = numba.get_num_threads()
    numba.set_num_threads(min(count, numba.config.NUMBA_NUM_THREADS))
    try:
        yield
    finally:
        numba.set_num_threads(before)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests on a local Ray or in a browser are slow by nature: every test that uses a
    ``local_ray`` fixture is marked ``ray``, and every ``ray`` or ``browser`` test ``slow``.

    The modules that use Ray (:func:`modules_using_ray`) run one after another, each whole and
    in its order (so their module fixtures are made once): the session's one Ray, once started,
    keeps processes alive on the machine's cores until the session ends. In one process they
    run last, so that no other test runs beside them. Under ``-n``
    (:func:`pytest_xdist_make_scheduler`) they are one unit of work, sent first (the longest:
    one worker runs it while the others take the remaining modules), and the other modules
    follow in the order of their number of slow tests, most first, so that the workers end
    together on short modules."""
    for item in items:
        if "local_ray" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.ray)
        if item.get_closest_marker("ray") or item.get_closest_marker("browser"):
            item.add_marker(pytest.mark.slow)
    with_ray = modules_using_ray()
    missed = {_module(item) for item in items if item.get_closest_marker("ray")} - with_ray
    assert not missed, f"{sorted(missed)}: Ray tests in a module whose source never names local_ray"
    slow = collections.Counter(_module(item) for item in items if item.get_closest_marker("slow"))

    # stable: the collection's order is kept otherwise
    def order(item: pytest.Item) -> tuple[bool, int]:
        module = _module(item)
        if not DISTRIBUTED:
            return module in with_ray, 0
        return module not in with_ray, 0 if module in with_ray else -slow[module]

    items.sort(key=order)


def _module(item: pytest.Item) -> str:
    return item.nodeid.split("::", 1)[0]


_SESSION_RAY: list = []
"""The :class:`thgs.cluster.RayConnection` of the session's local Ray while it is up."""


@pytest.fixture(scope="session")
def local_ray():
    """One local Ray with 2 CPUs for the whole session, started by
    :func:`thgs.cluster.connect_ray` when the first test that asks for it runs and shut down at
    the session's end: its connection (``local``, started here). The library and the CLI use a
    Ray already initialised in this process as it is, so every Ray test shares this one."""
    ray = pytest.importorskip("ray")
    from thgs.cluster import connect_ray

    assert not ray.is_initialized(), "a test left Ray initialised: the session's would not start"
    with pytest.MonkeyPatch.context() as patch:
        # Ray's raylet kills a worker idle for 1 s while more workers than CPUs exist (the
        # actors of a preprocessing run count), so each test's tasks started fresh processes
        # that imported torch and transformers again (ray-project/ray#27863); the raylet
        # started here reads this from its environment
        patch.setenv("RAY_idle_worker_killing_time_threshold_ms", str(RAY_IDLE_WORKER_MS))
        connection = connect_ray(None, num_cpus=2)
    assert connection.started
    _SESSION_RAY.append(connection)
    try:
        yield connection
    finally:
        _SESSION_RAY.clear()
        connection.shutdown()
    assert not ray.is_initialized()


@pytest.fixture(autouse=True)
def _session_ray_hidden(request):
    """While the session's Ray is up, a test not marked ``ray`` finds Ray not initialised
    (``ray.is_initialized()`` is False, as in a process that never started it), whatever ran
    before it; starting a Ray there is an error naming the ``local_ray`` fixture."""
    if not _SESSION_RAY or request.node.get_closest_marker("ray"):
        yield
        return
    ray = sys.modules["ray"]

    def init(*args, **kwargs):
        raise AssertionError(
            "ray.init() in a test not marked ray while the session's Ray is up: use the "
            "local_ray fixture"
        )

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ray, "is_initialized", lambda: False)
        patch.setattr(ray, "init", init)
        yield


@pytest.fixture
def shared_data() -> Path:
    """../shared/data, or a clean skip where it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real sample data not found at {SHARED_DATA}")
    return SHARED_DATA


def random_gaussians(
    n: int, *, kind: str = "3dgs", sh_degree: int = 3, normals: bool = True, seed: int = 0
) -> Gaussians:
    """Gaussians with values spread like trained ones (float32, CPU)."""
    generator = torch.Generator().manual_seed(seed)

    def randn(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=generator)

    k = (sh_degree + 1) ** 2
    return Gaussians(
        means=randn(n, 3) * 3,
        quats=randn(n, 4),
        scales=randn(n, 2 if kind == "2dgs" else 3) - 4,
        opacities=randn(n) * 2,
        sh=randn(n, k, 3) * 0.5,
        normals=randn(n, 3) if normals else None,
    )


def look_at(
    eye: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0.0, 0.0, 1.0)
) -> np.ndarray:
    """World→camera 4×4 (OpenCV axes) of a camera at ``eye`` looking at ``target``."""
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])  # rows: camera axes in world coordinates
    viewmat = np.eye(4)
    viewmat[:3, :3] = rotation
    viewmat[:3, 3] = -rotation @ eye
    return viewmat


def random_cameras(m: int, *, seed: int = 0, centred: bool = False) -> Cameras:
    """Cameras on a sphere around the origin, looking at it, with varied intrinsics and sizes."""
    rng = np.random.default_rng(seed)
    viewmats, Ks, widths, heights = [], [], [], []
    for i in range(m):
        theta = 2 * math.pi * i / m
        eye = np.array([4 * math.cos(theta), 4 * math.sin(theta), 1.5 + rng.uniform(-0.5, 0.5)])
        viewmats.append(look_at(eye, rng.normal(size=3) * 0.1))
        width, height = int(rng.integers(200, 400)), int(rng.integers(150, 300))
        cx = width / 2 if centred else rng.uniform(0.4, 0.6) * width
        cy = height / 2 if centred else rng.uniform(0.4, 0.6) * height
        fx = rng.uniform(200, 400)
        Ks.append([[fx, 0, cx], [0, fx * rng.uniform(0.98, 1.02), cy], [0, 0, 1]])
        widths.append(width)
        heights.append(height)
    return Cameras(
        viewmats=torch.tensor(np.stack(viewmats)),
        Ks=torch.tensor(Ks, dtype=torch.float64),
        widths=torch.tensor(widths),
        heights=torch.tensor(heights),
        names=tuple(f"view_{i:03d}.png" for i in range(m)),
    ).check()


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory):
    """A reduced synthetic dataset written by `thgs synth` (4,000 Gaussians, 8 views)."""
    folder = tmp_path_factory.mktemp("synth") / "scene"
    argv = ["synth", "synth-small", str(folder), "--gaussians", "4000", "--views", "8"]
    try:
        entrypoint(argv)
    except SystemExit as exc:  # pragma: no cover - the command returns normally
        assert not exc.code
    return folder


@pytest.fixture(scope="session")
def small_field(small_dataset, tmp_path_factory):
    """The small dataset's field, built by `thgs build` (which records where the scene is)."""
    out = tmp_path_factory.mktemp("field") / "scene.thgs"
    try:
        entrypoint(["build", str(small_dataset), "-o", str(out)])
    except SystemExit as exc:  # pragma: no cover - the command returns normally
        assert not exc.code
    return out


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """Run the ``thgs`` CLI in-process: ``(exit code, stdout, stderr)``."""
    from thgs.cli import entrypoint

    try:
        entrypoint(argv)
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err
