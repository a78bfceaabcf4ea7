"""The torch device thgs computes on, from a name: ``auto``, ``cpu``, ``cuda`` (``cuda:N``) or
``mps``.

``auto`` takes a CUDA GPU when torch sees one, else Apple's MPS when available, else the CPU. A
device that is asked for by name but is not there is an :class:`~thgs.errors.InputError`, never
a silent fall back to the CPU.
"""

from __future__ import annotations

import torch

from thgs.choices import DEVICES
from thgs.errors import InputError

__all__ = ["DEVICES", "resolve_device", "set_cpu_threads"]


def _mps_available() -> bool:
    backend = getattr(torch.backends, "mps", None)
    return backend is not None and backend.is_available()


def resolve_device(name: str | torch.device = "auto") -> torch.device:
    """The torch device called ``name``.

    Raises:
        InputError: an unknown name, CUDA asked for where torch has no CUDA build or sees no GPU,
            or MPS where it is not available.
    """
    if isinstance(name, torch.device):
        name = str(name)
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        return torch.device("mps") if _mps_available() else torch.device("cpu")
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise InputError("device", f"unknown device {name!r}; choose one of {DEVICES}") from exc
    if device.type == "cuda":
        if torch.version.cuda is None:
            raise InputError(
                "device",
                f"{name}: this torch ({torch.__version__}) is built without CUDA; install a CUDA "
                "build of torch (https://pytorch.org) or use --device cpu",
            )
        if not torch.cuda.is_available():
            raise InputError("device", f"{name}: torch sees no CUDA GPU (check the driver)")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise InputError(
                "device", f"{name}: only {torch.cuda.device_count()} CUDA device(s) are visible"
            )
    elif device.type == "mps":
        if not _mps_available():
            raise InputError("device", f"{name}: MPS is not available on this machine")
    elif device.type != "cpu":
        raise InputError("device", f"unknown device {name!r}; choose one of {DEVICES}")
    return device


def set_cpu_threads(count: int, source: str = "threads") -> None:
    """Use ``count`` CPU threads in this process: numba's (the CPU rasterizer and graph kernels,
    and the partition's solver processes) and torch's. What is built does not depend on it.

    Raises:
        InputError: ``count`` is not between 1 and the most numba started with
            (``NUMBA_NUM_THREADS``, by default the number of cores), named by ``source``.
    """
    import numba

    most = numba.config.NUMBA_NUM_THREADS
    if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= most:
        raise InputError(
            source,
            f"must be a whole number from 1 to {most}, got {count!r} (more than the cores: set "
            "NUMBA_NUM_THREADS before starting)",
        )
    numba.set_num_threads(count)
    torch.set_num_threads(count)
