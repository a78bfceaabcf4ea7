"""Lay a synthetic dataset (:func:`thgs.synthetic.write_dataset`) out as a benchmark's real
release and the trained model its authors' code writes, to test thgs on those layouts with no
extra flags.

OpenGaussian's ScanNet scenes (:func:`write_opengaussian_scannet`; the layout of the README's
"Data preparation" and of ``scripts/scannet2blender.py``, read by ``readNerfSyntheticInfo`` in
``scene/dataset_readers.py``, github.com/yanmin-wu/OpenGaussian)::

    ROOT/scannet/<scene>/
        color/<stem>.jpg                     the views' images
        transforms_train.json                the training views (every view here), the Blender
                                             layout: {"w", "h", "fl_x", "fl_y", "cx", "cy"
                                             (pixels, all views), "frames": [{"file_path":
                                             "color/<stem>" (no extension), "transform_matrix":
                                             camera→world 4×4, OpenGL axes (x right, y up,
                                             z back)}]}
        transforms_test.json                 the held-out split, same layout: here every 8th view
                                             from the first, repeated from the train split (thgs
                                             lifts from the train split only, so it lifts from
                                             every view, as on the synthetic dataset)
        points3d.ply                         the initial points: the Gaussians' centres and
                                             colours (x y z nx ny nz red green blue), which
                                             OpenGaussian freezes (--frozen_init_pts)
        language_features/<stem>_{s,f}.npy   the dataset's guidance (LangSplat's layout) and its
                                             embedding.json
        <scene>_vh_clean_2.labels.ply        the per-Gaussian class labels (Gaussian i is point
                                             i), with its .classes.json sidecar
    ROOT/output/<scene>/                     the trained model
        point_cloud/iteration_30000/point_cloud.ply
        cameras.json                         3DGS's cameras of the model
        cfg_args                             the settings, as OpenGaussian's train.py writes them
                                             (scripts/train_scannet.sh: -s <data>/scannet/<scene>
                                             -r 2 --eval), source_path from another machine

Each folder is written whole or not at all (:func:`thgs._atomic.atomic_folder`).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np
import plyfile

from thgs._atomic import atomic_folder
from thgs.errors import InputError
from thgs.eval.scannet import read_scannet_labels, write_scannet_labels
from thgs.scene import SH_C0, Cameras, read_cameras_json, read_ply
from thgs.scene.transforms_json import OPENGL_TO_OPENCV

__all__ = ["write_opengaussian_scannet"]

logger = logging.getLogger(__name__)

_DATASET_PARTS = (
    "cameras.json",
    "images",
    "language_features",
    "point_cloud/iteration_30000/point_cloud.ply",
    "scannet/synthetic_vh_clean_2.labels.ply",
)
"""What a synthetic dataset must hold to be laid out (:mod:`thgs.synthetic.dataset`)."""

_CFG_ARGS = (
    "Namespace(sh_degree=3, source_path={source!r}, model_path={model!r}, images='images', "
    "resolution=2, white_background=False, data_device='cuda', eval=True, "
    "convert_SHs_python=False, compute_cov3D_python=False, debug=False, iterations=90000, "
    "frozen_init_pts=True, start_ins_feat_iter=30000, start_root_cb_iter=50000, "
    "start_leaf_cb_iter=70000, sam_level=0, root_node_num=64, leaf_node_num=5, "
    "pos_weight=1.0, ip='127.0.0.1', port=6013, debug_from=-1, detect_anomaly=False, "
    "test_iterations=[30000], save_iterations=[30000, 90000], quiet=False, "
    "checkpoint_iterations=[], start_checkpoint=None)"
)
"""``cfg_args`` as OpenGaussian's ``train.py`` writes it (``str(Namespace(**vars(args)))``) for
``scripts/train_scannet.sh``; ``{source}`` and ``{model}`` are filled in."""


def _check_dataset(dataset: Path) -> None:
    for part in _DATASET_PARTS:
        if not (dataset / part).exists():
            raise InputError(dataset, f"not a synthetic dataset (thgs synth): no {part}")


def _blender_document(cameras: Cameras, indices: list[int]) -> dict:
    """The Blender-layout transforms of ``cameras[indices]``: shared intrinsics at the top, as
    scannet2blender.py writes them (per frame where the cameras differ)."""

    def intrinsics(i: int) -> dict[str, float | int]:
        K = cameras.Ks[i].numpy()
        return {
            "w": int(cameras.widths[i]),
            "h": int(cameras.heights[i]),
            "fl_x": float(K[0, 0]),
            "fl_y": float(K[1, 1]),
            "cx": float(K[0, 2]),
            "cy": float(K[1, 2]),
        }

    per_view = [intrinsics(i) for i in range(len(cameras))]
    shared = all(values == per_view[0] for values in per_view)
    camtoworlds = cameras.camtoworlds().numpy() @ OPENGL_TO_OPENCV
    document: dict = dict(per_view[0]) if shared else {}
    document["frames"] = [
        {
            "file_path": f"color/{cameras.stems[i]}",
            "transform_matrix": camtoworlds[i].tolist(),
            **({} if shared else per_view[i]),
        }
        for i in indices
    ]
    return document


def _write_points(path: Path, dataset: Path) -> None:
    """``points3d.ply`` as 3DGS's ``storePly`` writes it: the Gaussians' centres and DC colours."""
    gaussians = read_ply(dataset / "point_cloud" / "iteration_30000" / "point_cloud.ply")
    means = gaussians.means.double().numpy()
    colours = np.clip(0.5 + SH_C0 * gaussians.sh[:, 0].double().numpy(), 0.0, 1.0)
    records = np.zeros(
        len(means),
        dtype=[(n, "f4") for n in ("x", "y", "z", "nx", "ny", "nz")]
        + [(n, "u1") for n in ("red", "green", "blue")],
    )
    for axis, name in enumerate("xyz"):
        records[name] = means[:, axis]
    for channel, name in enumerate(("red", "green", "blue")):
        records[name] = np.rint(colours[:, channel] * 255.0)
    plyfile.PlyData([plyfile.PlyElement.describe(records, "vertex")]).write(path)


def write_opengaussian_scannet(
    dataset: str | os.PathLike[str], root: str | os.PathLike[str], scene: str = "scene0000_00"
) -> Path:
    """Lay a synthetic dataset out as one of OpenGaussian's ScanNet scenes and its trained model
    (the module docstring's layout).

    Args:
        dataset: a folder written by ``thgs synth`` (:func:`thgs.synthetic.write_dataset`).
        root: the folder to hold ``scannet/<scene>`` and ``output/<scene>``; created if needed.
        scene: the scene's name (a ScanNet scan id such as ``scene0000_00``).

    Returns:
        the scene's data folder, ``root/scannet/<scene>``.

    Raises:
        InputError: ``dataset`` is not a synthetic dataset, or either folder already exists and
            is not empty.
    """
    dataset, root = Path(dataset), Path(root)
    _check_dataset(dataset)
    cameras = read_cameras_json(dataset / "cameras.json")
    data, model = root / "scannet" / scene, root / "output" / scene
    for folder in (data, model):
        if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
            raise InputError(folder, "already exists and is not empty")
    for folder in (data, model):
        folder.parent.mkdir(parents=True, exist_ok=True)

    with atomic_folder(data) as staging:
        (staging / "color").mkdir()
        for stem in cameras.stems:
            shutil.copyfile(dataset / "images" / f"{stem}.jpg", staging / "color" / f"{stem}.jpg")
        every = list(range(len(cameras)))
        for name, indices in (("train", every), ("test", every[::8])):
            with open(staging / f"transforms_{name}.json", "w", encoding="utf-8") as handle:
                json.dump(_blender_document(cameras, indices), handle, indent=4)
        _write_points(staging / "points3d.ply", dataset)
        shutil.copytree(dataset / "language_features", staging / "language_features")
        labels = read_scannet_labels(dataset / "scannet" / "synthetic_vh_clean_2.labels.ply")
        write_scannet_labels(staging / f"{scene}_vh_clean_2.labels.ply", labels)

    with atomic_folder(model) as staging:
        iteration = staging / "point_cloud" / "iteration_30000"
        iteration.mkdir(parents=True)
        shutil.copyfile(
            dataset / "point_cloud" / "iteration_30000" / "point_cloud.ply",
            iteration / "point_cloud.ply",
        )
        shutil.copyfile(dataset / "cameras.json", staging / "cameras.json")
        (staging / "cfg_args").write_text(
            _CFG_ARGS.format(
                source=f"/home/author/OpenGaussian/data/onedrive/scannet/{scene}",
                model=f"output/{scene}",
            ),
            encoding="utf-8",
        )
    logger.info("wrote OpenGaussian's ScanNet layout of %s: %s and %s", dataset, data, model)
    return data
