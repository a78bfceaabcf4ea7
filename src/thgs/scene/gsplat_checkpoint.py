"""Checkpoints of gsplat's example trainers (``simple_trainer.py``, ``simple_trainer_2dgs.py``).

A result folder looks like::

    <result_dir>/ckpts/ckpt_29999_rank0.pt   # simple_trainer (3DGS), one file per GPU rank
    <result_dir>/ckpts/ckpt_29999.pt         # simple_trainer_2dgs (2DGS)
    <result_dir>/cfg.yml                     # simple_trainer only

and each file is ``torch.save({"step": int, "splats": state_dict, ...})`` with the raw parameters::

    means      [N, 3]     world frame of the trainer (see below)
    quats      [N, 4]     (w, x, y, z), not normalised
    scales     [N, 3]     log; 2DGS uses the first two (the surfel plane)
    opacities  [N]        logits
    sh0        [N, 1, 3]  SH DC term;  shN [N, K − 1, 3] the other coefficients
    (or features [N, F] and colors [N, 3] (logits) when trained with appearance optimisation)

These are thgs's own conventions (docs/conventions.md), so :func:`read_gsplat_checkpoint` takes them
as they are, like the PLY reader. A multi-GPU run writes one file per rank, each with its share of
the Gaussians; they are concatenated in rank order, as the trainer does when it loads them.

The checkpoint does not say whether it is 3DGS or 2DGS (both store three scales). Unless told, the
reader takes ``ckpt_<step>_rank<r>.pt`` and any checkpoint beside a ``cfg.yml`` as 3DGS (the
names simple_trainer writes) and ``ckpt_<step>.pt`` without a ``cfg.yml`` as 2DGS (what
simple_trainer_2dgs writes).

gsplat normalises the world frame by default (``normalize_world_space``), so a checkpoint's
Gaussians are usually not in the COLMAP frame of their training data: a result folder whose
settings say so is refused by :func:`thgs.scene.load_scene` (:mod:`thgs.scene.gsplat_config`,
docs/build.md).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import Literal

import torch

from thgs._torch_load import load_tensors
from thgs.errors import InputError
from thgs.scene.gaussians import SH_C0, Gaussians, warn_if_invisible

__all__ = ["find_gsplat_checkpoint", "gsplat_kind", "read_gsplat_checkpoint"]

logger = logging.getLogger(__name__)

_CHECKPOINT = re.compile(r"^ckpt_(\d+)(?:_rank(\d+))?\.pt$")
_SH_SIZES = (1, 4, 9, 16)


def find_gsplat_checkpoint(folder: str | os.PathLike[str], step: int | None = None) -> Path:
    """The checkpoint of a gsplat result folder (``<folder>/ckpts/ckpt_<step>[_rank0].pt``).

    Args:
        folder: the trainer's ``result_dir`` (or its ``ckpts`` folder).
        step: which step; default the newest.

    Raises:
        InputError: no checkpoint, or none of that step.
    """
    folder = Path(folder)
    ckpts = folder if folder.name == "ckpts" else folder / "ckpts"
    steps: dict[int, Path] = {}
    for child in sorted(ckpts.iterdir()) if ckpts.is_dir() else []:
        match = _CHECKPOINT.match(child.name)
        if match and child.is_file() and match.group(2) in (None, "0"):
            steps[int(match.group(1))] = child
    if not steps:
        raise InputError(folder, "not a gsplat result folder: no ckpts/ckpt_<step>[_rank0].pt")
    if step is None:
        step = max(steps)
    elif step not in steps:
        raise InputError(folder, f"no checkpoint of step {step}; the folder has {sorted(steps)}")
    return steps[step]


def gsplat_kind(path: str | os.PathLike[str]) -> Literal["2dgs", "3dgs"] | None:
    """Which trainer wrote the checkpoint, from its name and folder (see the module docstring);
    None when the name is not one of gsplat's."""
    path = Path(path)
    match = _CHECKPOINT.match(path.name)
    if match is None:
        return None
    if match.group(2) is not None:
        return "3dgs"
    result_dir = path.parent.parent if path.parent.name == "ckpts" else path.parent
    return "3dgs" if (result_dir / "cfg.yml").is_file() else "2dgs"


def _rank_files(path: Path) -> list[Path]:
    match = _CHECKPOINT.match(path.name)
    if match is None or match.group(2) is None:
        return [path]
    ranks = sorted(
        (int(m.group(2)), child)
        for child in path.parent.iterdir()
        if (m := _CHECKPOINT.match(child.name)) and m.group(1) == match.group(1) and m.group(2)
    )
    numbers = [rank for rank, _ in ranks]
    if numbers != list(range(len(numbers))):
        raise InputError(path, f"the checkpoint's ranks are {numbers}, not 0 … {len(numbers) - 1}")
    return [child for _, child in ranks]


def _load_splats(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise InputError(path, "no such file")
    data = load_tensors(path)
    splats = data.get("splats") if isinstance(data, dict) else None
    if not isinstance(splats, dict):
        raise InputError(
            path, "expected a gsplat trainer checkpoint: a dict with 'splats' (the parameters)"
        )
    return splats


def _tensor(splats: dict, key: str, path: Path) -> torch.Tensor:
    value = splats.get(key)
    if not isinstance(value, torch.Tensor):
        raise InputError(path, f"'splats' has no {key!r} tensor (keys: {sorted(splats)})")
    if not value.is_floating_point():
        raise InputError(path, f"splats[{key!r}] has dtype {value.dtype}, expected floats")
    return value.detach().to(torch.float32)


def _gaussians(splats: dict, path: Path, kind: str) -> Gaussians:
    means = _tensor(splats, "means", path)
    n = means.shape[0] if means.ndim == 2 else -1
    expected = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
    tensors = {"means": means}
    for key in ("quats", "scales", "opacities"):
        tensors[key] = _tensor(splats, key, path)
    if "sh0" in splats:
        sh0, shN = _tensor(splats, "sh0", path), _tensor(splats, "shN", path)
        if shN.ndim != 3 or shN.shape[1] + 1 not in _SH_SIZES:
            raise InputError(
                path,
                f"splats['shN'] must be [N, K − 1, 3], K in 1, 4, 9, 16; got {list(shN.shape)}",
            )
        expected |= {"sh0": (n, 1, 3), "shN": (n, shN.shape[1], 3)}
        tensors |= {"sh0": sh0, "shN": shN}
    elif "colors" in splats:
        tensors["colors"] = _tensor(splats, "colors", path)
        expected["colors"] = (n, 3)
    else:
        raise InputError(path, f"'splats' has neither sh0/shN nor colors (keys: {sorted(splats)})")
    for key, shape in expected.items():
        if tuple(tensors[key].shape) != shape:
            raise InputError(
                path, f"splats[{key!r}] must be {list(shape)}, got {list(tensors[key].shape)}"
            )
    if "sh0" in tensors:
        sh = torch.cat([tensors["sh0"], tensors["shN"]], dim=1)
    else:
        logger.warning(
            "%s: trained with appearance optimisation; keeping its base colours only", path
        )
        sh = ((torch.sigmoid(tensors["colors"]) - 0.5) / SH_C0)[:, None, :]
    scales = tensors["scales"][:, :2] if kind == "2dgs" else tensors["scales"]
    return Gaussians(
        means=means.contiguous(),
        quats=tensors["quats"].contiguous(),
        scales=scales.contiguous(),
        opacities=tensors["opacities"].contiguous(),
        sh=sh.contiguous(),
    )


def read_gsplat_checkpoint(
    path: str | os.PathLike[str], *, kind: Literal["2dgs", "3dgs"] | None = None
) -> Gaussians:
    """Read the Gaussians of a gsplat trainer checkpoint (``ckpt_<step>[_rank<r>].pt``).

    Args:
        path: the ``.pt`` file; the other ranks' files of the same step beside it are read too.
        kind: ``"3dgs"`` (simple_trainer) or ``"2dgs"`` (simple_trainer_2dgs; the third scale,
            which its rasterizer does not use, is dropped); default from the file's name
            (:func:`gsplat_kind`).

    Returns:
        :class:`Gaussians` with float32 CPU tensors in thgs's conventions (the same raw
        parameters the PLY export of the same model holds), checked.

    Raises:
        InputError: the file is missing or not a torch checkpoint; no ``splats``; a parameter
            missing, not floating point or of the wrong shape; the kind cannot be told from the
            name; or a value :meth:`Gaussians.check` refuses. The message names the file.
    """
    path = Path(path)
    if kind is None:
        kind = gsplat_kind(path)
        if kind is None:
            raise InputError(
                path,
                "cannot tell whether this checkpoint is 3DGS or 2DGS from its name: keep "
                "gsplat's names (simple_trainer writes ckpt_<step>_rank<r>.pt, "
                "simple_trainer_2dgs ckpt_<step>.pt) or pass kind= to read_gsplat_checkpoint",
            )
    elif kind not in ("2dgs", "3dgs"):
        raise InputError(path, f"kind must be '2dgs' or '3dgs', got {kind!r}")
    files = _rank_files(path)
    parts = [_gaussians(_load_splats(file), file, kind) for file in files]
    if len(parts) == 1:
        gaussians = parts[0]
    else:
        logger.info("%s: %d ranks' checkpoints concatenated", path, len(parts))
        gaussians = Gaussians(
            **{
                name: torch.cat([getattr(part, name) for part in parts])
                for name in ("means", "quats", "scales", "opacities", "sh")
            }
        )
    if len(gaussians) == 0:
        raise InputError(path, "the checkpoint holds no Gaussians")
    gaussians.check(source=str(path))
    warn_if_invisible(gaussians, str(path))
    return gaussians
