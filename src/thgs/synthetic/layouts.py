"""A synthetic dataset (:func:`thgs.synthetic.write_dataset`) laid out as a real benchmark's
release, so that the commands that find scenes by their layout (``thgs build`` through
``cfg_args``, ``thgs eval`` through LangSplat's label folder, ``thgs suite``) are exercised on the
layouts they meet in practice.

- :func:`write_langsplat_lerf` — LangSplat's LERF-OVS release with a 3DGS-style model::

      root/lerf_ovs/<scene>/{images, sparse/0, language_features}
      root/lerf_ovs/label/<scene>/frame_*.json
      root/output/<scene>/{point_cloud/iteration_30000/point_cloud.ply, cameras.json, cfg_args}

- :func:`write_3dovs` — the 3D-OVS release (``Kunhao-Liu/3D-OVS``, ``dataLoader/llff.py``: one
  folder per scene with ``images/``, ``segmentations/classes.txt`` and
  ``segmentations/<NN>/<class>.png``, NN the view's index, and COLMAP's ``sparse/``), with the
  LangSplat-layout guidance THGS reads beside the images and a model in ``root/output/<scene>``::

      root/3dovs/<scene>/{images, sparse/0, segmentations, language_features}
      root/output/<scene>/{point_cloud/iteration_30000/point_cloud.ply, cameras.json, cfg_args}

Each model folder's ``cfg_args`` names its training data (``source_path``) as a trainer writes
it. The folders are copied, or linked (``link=True``: cheap, for tests) to the dataset's.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from thgs.errors import InputError

__all__ = ["write_3dovs", "write_langsplat_lerf"]

_CFG_ARGS = (
    "Namespace(sh_degree=3, source_path={source!r}, model_path={model!r}, images='images', "
    "resolution=-1, white_background=False, data_device='cuda', eval=True, "
    "render_items=['RGB', 'Alpha', 'Normal', 'Depth'], depth_ratio=0.0, debug=False)\n"
)


def _place(original: Path, target: Path, link: bool) -> None:
    """``target`` as a copy of (or a link to) the file or folder ``original``."""
    if not original.exists():
        raise InputError(original, "not found in the synthetic dataset (written by thgs synth?)")
    target.parent.mkdir(parents=True, exist_ok=True)
    if link:
        target.symlink_to(original.resolve(), target_is_directory=original.is_dir())
    elif original.is_dir():
        shutil.copytree(original, target)
    else:
        shutil.copy2(original, target)


def _write_model(
    dataset: Path, root: Path, scene: str, source: str, *, cameras_json: bool, link: bool
) -> Path:
    model = root / "output" / scene
    model.mkdir(parents=True, exist_ok=True)
    (model / "cfg_args").write_text(
        _CFG_ARGS.format(source=source, model=f"output/{scene}"), encoding="utf-8"
    )
    _place(dataset / "point_cloud", model / "point_cloud", link)
    if cameras_json:
        _place(dataset / "cameras.json", model / "cameras.json", link=False)
    return model


def _checked(dataset: str | os.PathLike[str], root: str | os.PathLike[str], scene: str):
    dataset, root = Path(dataset), Path(root)
    if not (dataset / "synthetic.json").is_file():
        raise InputError(dataset, "is not a synthetic dataset (no synthetic.json; thgs synth)")
    if not scene or "/" in scene or scene in (".", ".."):
        raise InputError("scene", f"must be a folder name, got {scene!r}")
    return dataset, root


def write_langsplat_lerf(
    dataset: str | os.PathLike[str],
    root: str | os.PathLike[str],
    scene: str,
    *,
    source: str | None = None,
    cameras_json: bool = True,
    link: bool = False,
) -> Path:
    """Lay a synthetic dataset out as LangSplat's LERF-OVS release (module docstring).

    Args:
        dataset: a folder written by ``thgs synth``.
        root: the folder to lay it out in (``lerf_ovs/`` and ``output/`` are made there).
        scene: the scene's folder name, e.g. ``"teatime"``.
        source: what the model's ``cfg_args`` names as its training data (default the data
            folder's absolute path; a path from another machine, e.g.
            ``/home/author/data/lerf_ovs/teatime``, is found by its tail).
        cameras_json: also put the 3DGS ``cameras.json`` into the model folder.
        link: link to the dataset's folders instead of copying them.

    Returns:
        the scene's data folder, ``root/lerf_ovs/<scene>``.

    Raises:
        InputError: ``dataset`` is not a synthetic dataset, or ``scene`` is not a folder name.
    """
    dataset, root = _checked(dataset, root, scene)
    data = root / "lerf_ovs" / scene
    data.mkdir(parents=True)
    for name in ("images", "sparse", "language_features"):
        _place(dataset / name, data / name, link)
    _place(dataset / "label", root / "lerf_ovs" / "label" / scene, link)
    source = source if source is not None else os.path.abspath(data)
    _write_model(dataset, root, scene, source, cameras_json=cameras_json, link=link)
    return data


def write_3dovs(
    dataset: str | os.PathLike[str],
    root: str | os.PathLike[str],
    scene: str,
    *,
    source: str | None = None,
    link: bool = False,
) -> Path:
    """Lay a synthetic dataset out as the 3D-OVS release, with guidance and a model (module
    docstring). The synthetic dataset's ``segmentations/`` is already in 3D-OVS's format.

    Args:
        dataset: a folder written by ``thgs synth``.
        root: the folder to lay it out in (``3dovs/`` and ``output/`` are made there).
        scene: the scene's folder name, e.g. ``"bed"``.
        source: what the model's ``cfg_args`` names as its training data (default the data
            folder's absolute path).
        link: link to the dataset's folders instead of copying them.

    Returns:
        the scene's data folder, ``root/3dovs/<scene>``.

    Raises:
        InputError: ``dataset`` is not a synthetic dataset, or ``scene`` is not a folder name.
    """
    dataset, root = _checked(dataset, root, scene)
    data = root / "3dovs" / scene
    data.mkdir(parents=True)
    for name in ("images", "sparse", "segmentations", "language_features"):
        _place(dataset / name, data / name, link)
    source = source if source is not None else os.path.abspath(data)
    _write_model(dataset, root, scene, source, cameras_json=True, link=link)
    return data
