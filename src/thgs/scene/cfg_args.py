"""A trained model folder's ``cfg_args``: which training data it was trained on, and where that
data is on this machine.

The 3DGS trainer and its descendants (2DGS, THGS, LangSplat, OpenGaussian …) write the parsed
command line into ``<model>/cfg_args`` as the text of a ``Namespace(...)`` call, e.g.::

    Namespace(sh_degree=3, source_path='/data/lerf_ovs/teatime', model_path='output/teatime',
              images='images', resolution=-1, white_background=False, eval=True)

``source_path`` names the training data folder (``images/``, ``sparse/0``, and for LangSplat-style
scenes ``language_features/``). It is usually absolute and written on another machine, so
:func:`find_model_source` looks for it here in this order, stopping at the first step that finds
something:

1. the path as written (an absolute path, or a relative one from the working folder);
2. a relative path from where training ran (the model folder with cfg_args's ``model_path``
   taken off its end, e.g. ``work/`` for ``work/output/teatime`` and
   ``model_path='output/teatime'``) and from the model folder's parent;
3. the path's last three, two and one parts (``data/lerf_ovs/teatime``, ``lerf_ovs/teatime``,
   ``teatime`` for ``/home/me/data/lerf_ovs/teatime``), under where training ran, the model
   folder's parent, its grandparent and the working folder; a candidate must be a folder other
   than the model folder that looks like training data (``sparse/``, ``transforms.json``,
   ``transforms_train.json``, ``images/`` or ``language_features/`` in it). The first tail
   length with a match decides; two different matching folders are an error, not a guess.
"""

from __future__ import annotations

import ast
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from thgs._json import read_text
from thgs.errors import InputError

__all__ = ["CFG_ARGS", "ModelSource", "find_model_source", "locate_source", "read_cfg_args"]

CFG_ARGS = "cfg_args"
"""The file name the 3DGS-family trainers write their settings to, in the model folder."""

_SOURCE_SIGNS = (
    "sparse",
    "transforms.json",
    "transforms_train.json",
    "images",
    "language_features",
)


def read_cfg_args(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The settings of a ``cfg_args`` file: ``Namespace(key=value, ...)`` → ``{key: value}``.

    The text is parsed, never executed: it must be one call of ``Namespace`` with keyword
    arguments only, and each value a Python literal (strings, numbers, booleans, None, lists,
    tuples, dicts).

    Raises:
        InputError: the file is missing, unreadable, or not such a call.
    """
    path = Path(path)
    text = read_text(path)
    try:
        call = ast.parse(text.strip(), mode="eval").body
    except SyntaxError as exc:
        raise InputError(path, f"expected the text Namespace(key=value, ...), ({exc.msg})") from exc
    if not (
        isinstance(call, ast.Call)
        and isinstance(call.func, ast.Name)
        and call.func.id == "Namespace"
        and not call.args
        and all(keyword.arg is not None for keyword in call.keywords)
    ):
        raise InputError(path, "expected the text Namespace(key=value, ...) a trainer writes")
    settings: dict[str, Any] = {}
    for keyword in call.keywords:
        try:
            settings[keyword.arg] = ast.literal_eval(keyword.value)
        except ValueError as exc:
            raise InputError(path, f"{keyword.arg}= is not a literal value") from exc
    return settings


@dataclass(frozen=True)
class ModelSource:
    """The training data a model folder's ``cfg_args`` names, and where it is here.

    Attributes:
        cfg_args: the settings file: ``cfg_args``, or a gsplat result folder's ``cfg.yml`` /
            ``cfg.json`` (:func:`thgs.scene.gsplat_config.find_gsplat_source`).
        named: its ``source_path`` (gsplat: ``data_dir``) as written; None when it has none.
        folder: the training data folder found here (see the module docstring), or None.
        searched: the folders under which ``named`` (or its tails) was looked for.
        tails: the tails of ``named`` looked for under ``searched`` (empty when ``named`` was
            found as written).
        images: the image folder inside the source the model was trained on, if the file names
            one (cfg_args's ``images``; gsplat's ``images_<data_factor>`` when the factor is > 1).
        key: the setting that names the source (``source_path``, gsplat's ``data_dir``).
    """

    cfg_args: Path
    named: str | None
    folder: Path | None
    searched: tuple[Path, ...] = ()
    tails: tuple[str, ...] = ()
    images: str | None = None
    key: str = "source_path"

    def describe(self) -> str:
        """One line: what cfg_args names and where (or whether) it was found."""
        if self.named is None:
            return f"{self.cfg_args} names no {self.key}"
        if self.folder is None:
            return (
                f"{self.cfg_args} names the source {self.named!r}, which is not here "
                f"({self.looked()})"
            )
        if os.path.normpath(self.named) == os.path.normpath(self.folder):
            return f"source {self.folder} (named by {self.cfg_args})"
        return f"source {self.folder} (found for {self.named!r}, named by {self.cfg_args})"

    def looked(self) -> str:
        """Where it was looked for, in words."""
        if not self.tails:
            return "no such folder"
        tails = ", ".join(repr(tail) for tail in self.tails)
        return f"looked for {tails} under {', '.join(map(str, self.searched))}"


def _parts(named: str) -> list[str]:
    return [part for part in re.split(r"[\\/]+", named) if part not in ("", ".", "..")]


def _drop_drive(parts: list[str]) -> list[str]:
    return parts[1:] if parts and re.fullmatch(r"[A-Za-z]:", parts[0]) else parts


def _training_root(model_dir: Path, model_path: Any) -> Path | None:
    """The folder training ran in: ``model_dir`` with the relative ``model_path`` taken off."""
    if not isinstance(model_path, str) or not model_path or os.path.isabs(model_path):
        return None
    parts = _parts(model_path)
    if not parts or ".." in re.split(r"[\\/]+", model_path):
        return None
    absolute = Path(os.path.abspath(model_dir))
    if list(absolute.parts[-len(parts) :]) != parts or len(absolute.parts) <= len(parts):
        return None
    return absolute.parents[len(parts) - 1]


def _looks_like_source(folder: Path) -> bool:
    return folder.is_dir() and any((folder / sign).exists() for sign in _SOURCE_SIGNS)


def _unique(folders: list[Path]) -> list[Path]:
    seen: dict[Path, Path] = {}
    for folder in folders:
        seen.setdefault(folder.resolve(), folder)
    return list(seen.values())


def find_model_source(
    model_dir: str | os.PathLike[str], *, cwd: str | os.PathLike[str] | None = None
) -> ModelSource | None:
    """Where the training data named by ``model_dir/cfg_args`` is on this machine.

    Args:
        model_dir: a trained model folder.
        cwd: the working folder relative paths start from (default the process's).

    Returns:
        None when the folder has no ``cfg_args``; else a :class:`ModelSource` whose ``folder`` is
        the training data found (module docstring: as written, relative to where training ran
        or to the model's parent, then by the path's tails) or None when it is nowhere here.

    Raises:
        InputError: a malformed ``cfg_args`` or ``source_path``, or two different folders that
            fit ``source_path`` equally well (the message names both; ``--source`` decides).
    """
    model_dir = Path(model_dir)
    path = model_dir / CFG_ARGS
    if not path.is_file():
        return None
    try:
        settings = read_cfg_args(path)
    except InputError as exc:
        raise InputError(path, f"{exc.problem}; --source decides instead") from exc
    named = settings.get("source_path")
    images = settings.get("images") if isinstance(settings.get("images"), str) else None
    if named is None:
        return ModelSource(path, None, None, images=images)
    if not isinstance(named, str) or not named.strip():
        raise InputError(
            path, f"source_path must be a folder name, got {named!r}; --source decides instead"
        )
    return locate_source(
        path, named, model_dir, run_path=settings.get("model_path"), images=images, cwd=cwd
    )


def locate_source(
    settings_file: Path,
    named: str,
    model_dir: str | os.PathLike[str],
    *,
    run_path: Any = None,
    key: str = "source_path",
    images: str | None = None,
    cwd: str | os.PathLike[str] | None = None,
) -> ModelSource:
    """Where the training data folder ``named`` by a trainer's settings file is on this machine.

    The search of the module docstring, shared by ``cfg_args`` and gsplat's ``cfg.yml``.

    Args:
        settings_file: the file that names it (``cfg_args``, ``cfg.yml`` …), for messages.
        named: the folder as written there.
        model_dir: the trained model (or result) folder.
        run_path: the model folder as written in the same file (cfg_args's ``model_path``,
            gsplat's ``result_dir``); when relative, where training ran is the model folder with
            it taken off.
        key: the setting that named the folder, for messages.
        images: recorded in the result (the image folder the model was trained on).
        cwd: the working folder relative paths start from (default the process's).

    Returns:
        a :class:`ModelSource`; its ``folder`` is None when nothing here fits.

    Raises:
        InputError: two different folders fit ``named`` equally well.
    """
    path = settings_file
    here = Path(os.path.abspath(cwd if cwd is not None else os.getcwd()))
    model = Path(os.path.abspath(model_dir))
    root = _training_root(Path(model_dir), run_path)

    given = Path(named)
    direct = [given if given.is_absolute() else here / given]
    if not given.is_absolute():
        direct += [folder / given for folder in (root, model.parent) if folder is not None]
    for candidate in _unique(direct):
        if candidate.is_dir() and candidate.resolve() != model.resolve():
            return ModelSource(
                path, named, Path(os.path.normpath(candidate)), images=images, key=key
            )

    bases = _unique([b for b in (root, model.parent, model.parent.parent, here) if b is not None])
    parts = _drop_drive(_parts(named))
    tails = tuple("/".join(parts[start:]) for start in range(max(0, len(parts) - 3), len(parts)))
    for tail in tails:
        matches = _unique(
            [
                Path(os.path.normpath(base / tail))
                for base in bases
                if _looks_like_source(base / tail) and (base / tail).resolve() != model.resolve()
            ]
        )
        if len(matches) > 1:
            raise InputError(
                path,
                f"names the source {named!r}, which is not here; {len(matches)} folders fit "
                f"it: {', '.join(map(str, matches))}; choose one with --source",
            )
        if matches:
            return ModelSource(path, named, matches[0], tuple(bases), tails, images, key)
    return ModelSource(path, named, None, tuple(bases), tails, images, key)
