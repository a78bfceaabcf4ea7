"""A gsplat result folder's settings (``cfg.yml``, ``cfg.json``): which COLMAP scene it was
trained on, where that is on this machine, and whether its Gaussians are in that scene's frame.

gsplat's example trainers write their whole configuration beside ``ckpts/``:
``simple_trainer.py`` as ``<result_dir>/cfg.yml`` (``yaml.dump(vars(cfg))``, so nested settings
carry Python tags such as ``!!python/object:gsplat.strategy.default.DefaultStrategy``) and
``simple_trainer_2dgs.py`` as ``<result_dir>/cfg.json``. thgs reads four keys:

- ``data_dir``: the COLMAP scene (``sparse/0`` or ``sparse``, ``images/``); looked for here as
  ``cfg_args``'s ``source_path`` is (:func:`thgs.scene.cfg_args.locate_source`), with
  ``result_dir`` telling where training ran;
- ``data_factor``: gsplat trained on ``images_<factor>`` with the intrinsics divided by it. The
  Gaussians' frame does not depend on it, so thgs still checks the cameras against ``images/``
  (what ``thgs preprocess`` reads by default) and only reports it;
- ``normalize_world_space`` (default true; gsplat versions without the key always normalised):
  gsplat then moves its world (rotated so the cameras' mean up is +z, centred on the point the
  cameras look at, scaled to a median camera distance of 1, rotated onto the principal axes of the
  SfM points, and possibly flipped upside down). The checkpoint's Gaussians are in that frame,
  where COLMAP's cameras do not fit them, and the rotation depends on eigenvector signs LAPACK
  does not fix, so thgs does not redo it: such a folder is refused;
- ``data_type`` (newer gsplat): only ``colmap`` scenes are read.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from thgs._json import read_text
from thgs.errors import InputError
from thgs.scene.cfg_args import ModelSource, locate_source

__all__ = ["GSPLAT_CONFIGS", "find_gsplat_source", "gsplat_config_file", "read_gsplat_config"]

GSPLAT_CONFIGS = ("cfg.yml", "cfg.json")
"""The settings files gsplat's trainers write into their result folder (simple_trainer,
simple_trainer_2dgs)."""

_KEYS = ("data_dir", "data_factor", "normalize_world_space", "data_type")
"""The settings thgs reads."""

_RETRAIN = (
    "retrain with --no-normalize-world-space (gsplat's flag), or pass --source with cameras in "
    "gsplat's normalised frame"
)


def _safe_loader() -> type:
    """PyYAML's SafeLoader that reads any ``!!python/...`` tag as None instead of refusing it
    (and never builds the object)."""
    import yaml

    class _Loader(yaml.SafeLoader):
        pass

    def unknown(loader: yaml.SafeLoader, suffix: str, node: yaml.Node) -> None:
        return None

    _Loader.add_multi_constructor("tag:yaml.org,2002:python/", unknown)
    return _Loader


def read_gsplat_config(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The settings of a gsplat result folder's ``cfg.yml`` or ``cfg.json`` as a dict.

    YAML is read with a safe loader: Python objects (``!!python/object:...``, the nested strategy
    and similar) become None and nothing is executed.

    Raises:
        InputError: the file is missing, unreadable or not a mapping of settings.
    """
    import yaml

    path = Path(path)
    text = read_text(path)
    try:
        if path.suffix.lower() == ".json":
            settings = json.loads(text)
        else:
            settings = yaml.load(text, Loader=_safe_loader())
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise InputError(path, f"not valid {path.suffix.lstrip('.').upper()} ({exc})") from exc
    if not isinstance(settings, dict):
        raise InputError(path, "expected the trainer's settings (a mapping of keys to values)")
    return settings


def gsplat_config_file(result_dir: str | os.PathLike[str]) -> Path | None:
    """``<result_dir>/cfg.yml`` or ``cfg.json``, whichever is there (cfg.yml first); None when
    neither is."""
    for name in GSPLAT_CONFIGS:
        if (Path(result_dir) / name).is_file():
            return Path(result_dir) / name
    return None


def find_gsplat_source(
    result_dir: str | os.PathLike[str], *, cwd: str | os.PathLike[str] | None = None
) -> ModelSource | None:
    """Where the COLMAP scene a gsplat result folder was trained on is on this machine.

    Args:
        result_dir: gsplat's ``result_dir`` (the folder holding ``ckpts/`` and ``cfg.yml``).
        cwd: the working folder relative paths start from (default the process's).

    Returns:
        None when the folder has neither ``cfg.yml`` nor ``cfg.json``; else a
        :class:`~thgs.scene.cfg_args.ModelSource` (``key="data_dir"``) whose ``folder`` is the
        scene found (or None when it is nowhere here) and whose ``images`` is
        ``images_<data_factor>`` when the factor is above 1.

    Raises:
        InputError: a malformed file or ``data_dir``/``data_factor``; a ``data_type`` other than
            ``colmap``; ``normalize_world_space`` true or absent (the Gaussians are in gsplat's
            normalised frame, not COLMAP's: the message says to retrain with
            ``--no-normalize-world-space`` or to pass ``--source``); ``cfg.yml`` and
            ``cfg.json`` both there and disagreeing on these settings; two folders that fit
            ``data_dir`` equally well. Each message names the file.
    """
    path = gsplat_config_file(result_dir)
    if path is None:
        return None
    settings = read_gsplat_config(path)
    other = Path(result_dir) / GSPLAT_CONFIGS[1]
    if other != path and other.is_file():
        second = read_gsplat_config(other)
        differ = [key for key in _KEYS if settings.get(key) != second.get(key)]
        if differ:
            raise InputError(
                path,
                f"and {other} (simple_trainer's and simple_trainer_2dgs's settings) are both "
                f"here and differ in {', '.join(differ)}; --source decides which scene",
            )
    data_type = settings.get("data_type", "colmap")
    if data_type != "colmap":
        raise InputError(
            path,
            f"data_type is {data_type!r}; thgs reads gsplat result folders trained on COLMAP "
            "scenes only (pass --source with cameras in the checkpoint's frame)",
        )
    normalized = settings.get("normalize_world_space", True)
    if normalized is not False:
        raise InputError(
            path,
            f"normalize_world_space is {normalized!r}: gsplat moved its world (rotated, centred "
            "and scaled by the cameras and SfM points), so the checkpoint's Gaussians are not in "
            f"the COLMAP frame of data_dir and its cameras would not fit them; {_RETRAIN}",
        )
    named = settings.get("data_dir")
    if not isinstance(named, str) or not named.strip():
        raise InputError(
            path, f"data_dir must be a folder name, got {named!r}; --source decides instead"
        )
    factor = settings.get("data_factor", 1)
    if isinstance(factor, bool) or not isinstance(factor, int) or factor < 1:
        raise InputError(path, f"data_factor must be a whole number ≥ 1, got {factor!r}")
    return locate_source(
        path,
        named,
        result_dir,
        run_path=settings.get("result_dir"),
        key="data_dir",
        images=f"images_{factor}" if factor > 1 else None,
        cwd=cwd,
    )
