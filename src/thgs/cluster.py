"""Connecting to Ray: a local one started here, or an existing cluster (the ``cluster`` extra).

:func:`connect_ray` initialises Ray in this process and returns a :class:`RayConnection`, which
as a context manager shuts down what it started::

    with connect_ray(None, num_cpus=4) as connection:   # a local Ray with 4 CPUs
        preprocess_with_ray(targets, sam=..., clip=...)

An address that does not answer fails within ``timeout`` seconds with a message naming it,
instead of Ray's own endless retries.
"""

from __future__ import annotations

import logging
import os
import socket
from dataclasses import dataclass

from thgs.errors import InputError, ThgsError

__all__ = ["RayConnection", "connect_ray"]

logger = logging.getLogger(__name__)

CLIENT_PREFIX = "ray://"
"""Addresses of Ray Client servers (port 10001 by default) start with this; others are a head
node's GCS (``host:6379``) or ``auto``."""


@dataclass(frozen=True)
class RayConnection:
    """Ray, initialised in this process by :func:`connect_ray`.

    Attributes:
        address: ``local`` for a Ray started here, else the address connected to.
        started: whether :func:`connect_ray` initialised Ray (False when it found Ray already
            initialised and left it as it was); :meth:`shutdown` and leaving a ``with`` block
            shut Ray down only then.
        cpus, gpus: the cluster's CPUs and GPUs when connected.
    """

    address: str
    started: bool
    cpus: float
    gpus: float

    def shutdown(self) -> None:
        """Shut down Ray in this process (a local Ray stops; a cluster only loses this driver)
        if :func:`connect_ray` initialised it."""
        if self.started:
            import ray

            ray.shutdown()

    def __enter__(self) -> RayConnection:
        return self

    def __exit__(self, *exc_info) -> None:
        self.shutdown()


def _import_ray():
    try:
        import ray
    except ImportError as error:
        raise ThgsError("running on Ray needs it: pip install 'thgs[cluster]'") from error
    return ray


def _host_port(address: str) -> tuple[str, int]:
    """The host and port of ``host:port`` or ``ray://host:port``."""
    bare = address.removeprefix(CLIENT_PREFIX)
    host, _, port = bare.rpartition(":")
    if not host or not port.isdigit():
        raise InputError(
            address,
            "not a Ray address: expected host:port (a head node, port 6379 by default), "
            "ray://host:port (Ray Client, port 10001) or auto",
        )
    return host.strip("[]"), int(port)


def _check_answers(address: str, timeout: float) -> None:
    host, port = _host_port(address)
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return
    except OSError as error:
        raise ThgsError(
            f"{address}: no Ray cluster answers there ({error}); check that the head node runs "
            "(ray start --head on it, or ray status there), that host and port are right (6379 "
            "for a head node, ray://host:10001 for Ray Client) and that no firewall blocks the "
            "port"
        ) from error


def connect_ray(
    address: str | None = None,
    *,
    num_cpus: int | None = None,
    num_gpus: int | None = None,
    timeout: float = 10.0,
) -> RayConnection:
    """Initialise Ray in this process.

    Args:
        address: None starts a local Ray (no dashboard, workers' output not forwarded); an
            address connects to a running cluster: ``host:port`` (a head node), ``ray://host:port``
            (Ray Client) or ``auto`` (the cluster started on this machine by ``ray start``, or
            ``$RAY_ADDRESS``).
        num_cpus, num_gpus: a local Ray's resources (default: the CPUs this process may use, and
            the GPUs Ray detects); not with an address (the cluster has its own).
        timeout: seconds to wait for the address to answer.

    If Ray is already initialised, it is used as it is (``started`` False); an address given
    must still answer.

    Raises:
        ThgsError: Ray is not installed, or the address does not answer (the message names it and
            what to check).
        InputError: the address is malformed, or resources are given with an address.
    """
    ray = _import_ray()
    if address is not None and address != "auto":
        _host_port(address)  # a malformed address is refused whatever runs
    if ray.is_initialized():
        if address is not None and address != "auto":
            _check_answers(address, timeout)  # asked for a cluster: it must be there
        logger.info("Ray is already initialised; using it as it is")
        return _connection(ray, "existing", started=False)
    quiet = {"include_dashboard": False, "log_to_driver": False, "logging_level": logging.WARNING}
    if address is None:
        if num_cpus is None:
            num_cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
        ray.init(address="local", num_cpus=num_cpus, num_gpus=num_gpus, **quiet)
        connection = _connection(ray, "local", started=True)
        logger.info("started a local Ray: %g CPUs, %g GPUs", connection.cpus, connection.gpus)
        return connection
    if num_cpus is not None or num_gpus is not None:
        raise InputError(
            address,
            "a running cluster has its own CPUs and GPUs: give num_cpus/num_gpus only "
            "for a local Ray",
        )
    if address != "auto":
        _check_answers(address, timeout)
    try:
        if address.startswith(CLIENT_PREFIX):
            ray.init(address=address, logging_level=logging.WARNING)
        else:
            ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
    except ConnectionError as error:
        raise ThgsError(
            f"{address}: no Ray cluster found ({error}); start one with ray start --head, or "
            "give its address"
        ) from error
    except ValueError as error:
        if "ray[client]" in str(error):
            raise ThgsError(
                f"{address}: Ray Client needs grpcio: pip install 'thgs[cluster]'"
            ) from error
        raise
    connection = _connection(ray, address, started=True)
    logger.info(
        "connected to Ray at %s: %g CPUs, %g GPUs", address, connection.cpus, connection.gpus
    )
    return connection


def _connection(ray, address: str, *, started: bool) -> RayConnection:
    resources = ray.cluster_resources()
    return RayConnection(
        address, started, float(resources.get("CPU", 0.0)), float(resources.get("GPU", 0.0))
    )
