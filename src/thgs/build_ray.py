"""A build's per-view and per-block work as Ray tasks (the ``cluster`` extra), for scenes past
one machine's cores: ``build_field(..., ray=True)`` or ``thgs build --ray [ADDRESS]``.

The lift sends chunks of views to tasks, each lifting its views with :func:`thgs.lift.lift_view`
(a view's lift does not depend on where or with which others it is computed); the partition
sends its blocks' single-threaded solver calls. Results come back in order and the field is the
one built in-process, byte for byte. The Gaussians go to Ray's object store once; the tasks
compute on the CPU and need thgs (and pycut-pursuit) installed where they run, and a lazily
loaded guidance reads its masks in the driver, so a cluster needs no shared folder.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from thgs.errors import ThgsError
from thgs.guidance import ViewGuidance
from thgs.lift import LiftConfig, ViewLift, iter_lift_views, lift_view
from thgs.scene import Cameras, Gaussians

__all__ = ["ray_lift_views", "ray_solve", "ray_workers"]

logger = logging.getLogger(__name__)


def _ray():
    """The ``ray`` module, initialised in this process."""
    try:
        import ray
    except ImportError as error:
        raise ThgsError("a build on Ray needs it: pip install 'thgs[cluster]'") from error
    if not ray.is_initialized():
        raise ThgsError(
            "Ray is not initialised in this process: connect first with "
            "thgs.cluster.connect_ray() (or ray.init())"
        )
    return ray


def _cpus(ray) -> int:
    return max(1, int(ray.cluster_resources().get("CPU", 1)))


def _lift_chunk(
    gaussians: Gaussians,
    cameras: Cameras,
    guidance: list[ViewGuidance],
    first: int,
    config: LiftConfig,
) -> list[ViewLift]:
    """Views ``first …`` lifted on a Ray worker, as :func:`thgs.lift.lift_view` does."""
    return [
        lift_view(gaussians, cameras.select([i]), view, first + i, config)
        for i, view in enumerate(guidance)
    ]


def ray_lift_views(
    gaussians: Gaussians,
    cameras: Cameras,
    guidance: Sequence[ViewGuidance],
    config: LiftConfig = LiftConfig(),
    progress: Callable[[int, int], None] | None = None,
) -> Iterator[ViewLift]:
    """:func:`thgs.lift.iter_lift_views` as Ray tasks: the same views, in camera order, on the
    Gaussians' device. About four chunks of views per CPU of the cluster, at most two per CPU in
    flight (what the driver holds besides the views it has been given).

    Raises:
        ThgsError: Ray is not installed or not initialised.
        InputError: as :func:`thgs.lift.iter_lift_views`, before any task starts.
    """
    ray = _ray()
    iter_lift_views(gaussians, cameras, guidance, config)  # its checks, before any task
    return _lifted_on_ray(ray, gaussians, cameras, guidance, config, progress)


def _lifted_on_ray(ray, gaussians, cameras, guidance, config, progress) -> Iterator[ViewLift]:
    count, cpus = len(guidance), _cpus(ray)
    size = max(1, math.ceil(count / (4 * cpus)))
    task = ray.remote(_lift_chunk).options(num_cpus=1, max_retries=0)
    device = gaussians.device
    shared = ray.put(gaussians.to("cpu"))
    starts = range(0, count, size)
    pending: deque = deque()
    submitted = done = 0
    while submitted < len(starts) or pending:
        while submitted < len(starts) and len(pending) < 2 * cpus:
            indices = list(range(starts[submitted], min(starts[submitted] + size, count)))
            chunk = [guidance[i] for i in indices]
            pending.append(task.remote(shared, cameras.select(indices), chunk, indices[0], config))
            submitted += 1
        for view in ray.get(pending.popleft()):
            done += 1
            yield view.to(device)
            if progress is not None:
                progress(done, count)


def _solve_share(calls: list[tuple[tuple, dict]]) -> list[np.ndarray]:
    from pycut_pursuit.cp_d0_dist import cp_d0_dist

    return [cp_d0_dist(*args, **kwargs)[0] for args, kwargs in calls]


def ray_solve(shares: list[list[tuple[tuple, dict]]]) -> list[list[np.ndarray]]:
    """Each share of ``cp_d0_dist`` calls ``(args, kwargs)`` solved by one Ray task (one CPU),
    in order: per share, the component ids of each call.

    Raises:
        ThgsError: Ray is not installed or not initialised.
    """
    ray = _ray()
    task = ray.remote(_solve_share).options(num_cpus=1, max_retries=0)
    return ray.get([task.remote(share) for share in shares])


def ray_workers() -> int:
    """The CPUs of the Ray this process is connected to (the partition's shares)."""
    return _cpus(_ray())
