"""Lifted views kept in a file instead of memory, read back one view at a time.

A build reads every view's lift several times (votes, each merging pass, features), so the lift
of a scene is held from the first stage to the last: 20 bytes per view and Gaussian it sees,
2.5 GB for 1M Gaussians in 200 views that each see two thirds of them. :class:`LiftStore` holds
the same :class:`thgs.lift.ViewLift` tensors in an unnamed temporary file (its bytes, one view
after the other) and an index of offsets in memory; indexing it reads that view back onto the
store's device, bit for bit what was appended. Iterating it therefore costs one read of the file,
mostly from the operating system's page cache, and holds one view at a time.

:func:`thgs.pipeline.lift_scene` moves a lift into a store once the views lifted so far exceed
its ``memory`` budget (``lift_memory`` of :func:`thgs.pipeline.build_field`); the field is the
same either way.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Sequence
from typing import overload

import numpy as np
import torch

from thgs.errors import ThgsError
from thgs.lift import ViewLift

__all__ = ["DEFAULT_LIFT_MEMORY", "LiftStore", "lift_bytes"]

logger = logging.getLogger(__name__)

DEFAULT_LIFT_MEMORY = 1 << 30
"""Bytes of lifted views held in memory before they move to a :class:`LiftStore` (1 GiB: about
400k Gaussians in 200 views)."""

_FIELDS = ("gaussians", "labels", "depths", "max_weights")


def lift_bytes(view: ViewLift) -> int:
    """The bytes of ``view``'s four tensors."""
    return sum(getattr(view, name).numel() * getattr(view, name).element_size() for name in _FIELDS)


class LiftStore(Sequence[ViewLift]):
    """Views' lifts in a temporary file: ``append`` adds one, ``store[i]`` reads view i back.

    Args:
        device: where the views read back are placed.
        folder: the folder of the temporary file (default: the system's, ``TMPDIR``). The file is
            unlinked as soon as it is created, so nothing is left behind, even by a killed
            process; its space is returned when the store is closed or collected.

    Raises:
        ThgsError: the file cannot be created or written (a missing folder, a full disk),
            naming the folder and what to do.
    """

    def __init__(self, device: torch.device | str, folder: str | os.PathLike[str] | None = None):
        self.device = torch.device(device)
        self.folder = os.fspath(folder) if folder is not None else tempfile.gettempdir()
        try:
            self._file = tempfile.TemporaryFile(prefix="thgs-lift-", dir=self.folder)
        except OSError as error:
            raise ThgsError(self._problem(error)) from error
        self._size = 0
        # per view: its offset, its Gaussian count and its labels' dtype
        self._index: list[tuple[int, int, np.dtype]] = []

    def append(self, view: ViewLift) -> None:
        """Write ``view`` at the end of the file (its tensors as stored; labels int16 or int32)."""
        n = len(view)
        labels = view.labels.detach().cpu().numpy()
        arrays = (
            view.gaussians.detach().cpu().numpy().astype(np.int32, copy=False),
            labels,
            view.depths.detach().cpu().numpy().astype(np.float32, copy=False),
            view.max_weights.detach().cpu().numpy().astype(np.float32, copy=False),
        )
        offset = self._size
        try:
            for array in arrays:
                data = np.ascontiguousarray(array).tobytes()
                if os.pwrite(self._file.fileno(), data, self._size) != len(data):
                    raise OSError(f"a short write of view {len(self)}")
                self._size += len(data)
        except OSError as error:
            raise ThgsError(self._problem(error)) from error
        self._index.append((offset, n, labels.dtype))

    def _problem(self, error: OSError) -> str:
        return (
            f"cannot keep the lift in a temporary file in {self.folder} ({error}): point TMPDIR "
            "at a folder with room for it, or hold it in memory (a larger lift_memory)"
        )

    def __len__(self) -> int:
        return len(self._index)

    @overload
    def __getitem__(self, index: int) -> ViewLift: ...

    @overload
    def __getitem__(self, index: slice) -> Sequence[ViewLift]: ...

    def __getitem__(self, index: int | slice) -> ViewLift | Sequence[ViewLift]:
        if isinstance(index, slice):
            return _Selection(self, range(len(self))[index])
        offset, n, label_dtype = self._index[index]
        layout = ((np.int32, n), (label_dtype, 4 * n), (np.float32, n), (np.float32, n))
        data = bytearray(sum(np.dtype(dtype).itemsize * count for dtype, count in layout))
        read = os.preadv(self._file.fileno(), [data], offset)
        if read != len(data):
            raise OSError(f"lift store: view {index} is cut short ({read} of {len(data)} bytes)")
        arrays, start = [], 0
        for dtype, count in layout:
            arrays.append(np.frombuffer(data, dtype=dtype, count=count, offset=start))
            start += np.dtype(dtype).itemsize * count
        gaussians, labels, depths, max_weights = (torch.from_numpy(a) for a in arrays)
        return ViewLift(gaussians, labels.reshape(n, 4), depths, max_weights).to(self.device)

    @property
    def nbytes(self) -> int:
        """Bytes written to the file."""
        return self._size

    def close(self) -> None:
        """Give the file's space back (also done when the store is collected)."""
        self._file.close()


class _Selection(Sequence[ViewLift]):
    """Some views of a :class:`LiftStore` (a slice of it), read on access like the store's."""

    def __init__(self, store: LiftStore, indices: range):
        self._store, self._indices = store, indices

    def __len__(self) -> int:
        return len(self._indices)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return _Selection(self._store, self._indices[index])
        return self._store[self._indices[index]]
