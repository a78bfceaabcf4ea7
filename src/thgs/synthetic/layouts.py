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

- OpenGaussian's ScanNet scenes (:func:`write_opengaussian_scannet`; the layout of the README's
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

  Each of its folders is written whole or not at all (:func:`thgs._atomic.atomic_folder`).

- :func:`write_openhype_scannetpp` — OpenHype's ScanNet++ benchmark as
  ``benchmark/scannetpp_preprocess.py`` lays a scene out (github.com/lisaweijler/openhype) and
  its annotation folder, with a model in ``root/output/<scene>``::

      ROOT/scannetpp/<scene>/                  the processed nerfstudio scene (--output_dir)
          transforms.json                      every view, camera→world in OpenGL axes: the
                                               annotated views first, renamed
                                               images/frame_eval_00001.jpg … in the sorted order
                                               of their annotation files, then the others,
                                               images/frame_train_00001.jpg …
          images/                              the views' images under those names
          language_features/                   the dataset's guidance, renamed likewise
      ROOT/openhype_scannetpp_benchmark/<scene>/   the annotations (--test_dir), per evaluation
          <stem>.json                          view: info (name <stem>.jpg, size, intrinsics,
                                               camera_model, transform_matrix) and objects
                                               (category, is_part, bbox, path_to_mask)
          masks/<stem>/<NN>.png                one mask per prompt, 255 = in
          <stem>.jpg                           the view's image (the preprocessing copies it)
      ROOT/output/<scene>/{point_cloud/iteration_30000/point_cloud.ply, cfg_args}

  The prompts of a view are the names of the objects it shows (except the floor) and, for the
  parts named differently from their object, OpenHype's "[PART] of a [OBJ]"
  (:func:`thgs.eval.openhype.part_prompt`: part "mug handle" of a "mug" is "handle of a mug");
  each mask is the union of the prompt's nodes covering at least ``min_label_pixels`` pixels of
  the view (the dataset's setting, as for its LERF-OVS labels), with one box per node. The
  ground truth is the dataset's ``ground_truth.safetensors`` at each pixel's max-weight
  Gaussian.

Each model folder's ``cfg_args`` names its training data (``source_path``) as a trainer writes
it. The LERF-OVS and 3D-OVS folders are copied, or linked (``link=True``: cheap, for tests) to
the dataset's.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import plyfile

from thgs._atomic import atomic_folder
from thgs.errors import InputError
from thgs.eval.ground_truth import read_hierarchy
from thgs.eval.openhype import (
    EVAL_VIEW_PREFIX,
    OpenHypeFrame,
    OpenHypeObject,
    part_prompt,
    write_openhype_annotations,
)
from thgs.eval.protocols.openhype import ANNOTATION_FOLDER
from thgs.eval.scannet import read_scannet_labels, write_scannet_labels
from thgs.scene import (
    SH_C0,
    Cameras,
    read_cameras_json,
    read_ply,
    write_transforms_json,
)
from thgs.scene.transforms_json import OPENGL_TO_OPENCV
from thgs.synthetic.dataset import label_categories, render_view
from thgs.synthetic.sam_masks import ground_truth_maps
from thgs.synthetic.scene import SceneConfig, SyntheticScene

__all__ = [
    "write_3dovs",
    "write_langsplat_lerf",
    "write_opengaussian_scannet",
    "write_openhype_scannetpp",
]

logger = logging.getLogger(__name__)

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


_DATASET_PARTS = (
    "cameras.json",
    "images",
    "language_features",
    "point_cloud/iteration_30000/point_cloud.ply",
    "scannet/synthetic_vh_clean_2.labels.ply",
)
"""What a synthetic dataset must hold to be laid out (:mod:`thgs.synthetic.dataset`)."""

_OPENGAUSSIAN_CFG_ARGS = (
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
            _OPENGAUSSIAN_CFG_ARGS.format(
                source=f"/home/author/OpenGaussian/data/onedrive/scannet/{scene}",
                model=f"output/{scene}",
            ),
            encoding="utf-8",
        )
    logger.info("wrote OpenGaussian's ScanNet layout of %s: %s and %s", dataset, data, model)
    return data


def _dataset_scene(dataset: Path) -> tuple[SyntheticScene, dict]:
    """The dataset's scene as written (Gaussians, cameras, ground truth; its objects are not
    stored) and its ``synthetic.json`` record."""
    record = json.loads((dataset / "synthetic.json").read_text(encoding="utf-8"))
    scene = SyntheticScene(
        gaussians=read_ply(dataset / "point_cloud" / "iteration_30000" / "point_cloud.ply"),
        cameras=read_cameras_json(dataset / "cameras.json"),
        hierarchy=read_hierarchy(dataset / "ground_truth.safetensors"),
        objects=(),
        config=SceneConfig(**record["scene"]),
    )
    return scene, record


def _openhype_frame(
    scene: SyntheticScene, index: int, background: tuple[float, float, float], min_pixels: int
) -> OpenHypeFrame:
    """The OpenHype annotations of view ``index``: its objects and its parts named differently
    from their object, from each pixel's max-weight Gaussian."""
    cameras, hierarchy = scene.cameras, scene.hierarchy
    parents = hierarchy.levels.parents
    assert parents is not None  # ground truth always nests
    stem = cameras.stems[index]
    _, max_id = render_view(scene, index, background)
    maps = ground_truth_maps(max_id, hierarchy)
    prompts: dict[str, tuple[int, list[int]]] = {}
    for name, (level, nodes) in label_categories(maps, scene, min_pixels).items():
        if level == 2:
            prompts.setdefault(name, (2, []))[1].extend(nodes)
        elif level == 1:
            for node in nodes:
                whole = hierarchy.names[3][parents[2][node]]
                prompts.setdefault(part_prompt(name, whole), (1, []))[1].append(node)
    objects = []
    for number, (prompt, (level, nodes)) in enumerate(prompts.items()):
        boxes = []
        for node in nodes:
            rows, cols = np.nonzero(maps[level] == node)
            boxes.append([cols.min(), rows.min(), cols.max(), rows.max()])
        objects.append(
            OpenHypeObject(
                prompt,
                level == 1,
                np.isin(maps[level], nodes),
                np.asarray(boxes, dtype=np.float64),
                f"masks/{stem}/{number:02d}.png",
            )
        )
    camtoworld = cameras.camtoworlds()[index].numpy() @ OPENGL_TO_OPENCV
    return OpenHypeFrame(
        stem=stem,
        image_name=f"{stem}.jpg",
        width=int(cameras.widths[index]),
        height=int(cameras.heights[index]),
        K=cameras.Ks[index].numpy(),
        camtoworld=camtoworld,
        camera_model="PINHOLE",
        objects=tuple(objects),
    )


def write_openhype_scannetpp(
    dataset: str | os.PathLike[str],
    root: str | os.PathLike[str],
    scene: str = "5ee7c22ba0",
    *,
    link: bool = False,
) -> Path:
    """Lay a synthetic dataset out as a scene of OpenHype's ScanNet++ benchmark, processed by
    its ``scannetpp_preprocess.py``, with the annotation folder and a trained model (the module
    docstring's layout). The annotated views are the dataset's evaluation views.

    Args:
        dataset: a folder written by ``thgs synth`` (:func:`thgs.synthetic.write_dataset`).
        root: the folder to hold ``scannetpp/<scene>``, ``openhype_scannetpp_benchmark/<scene>``
            and ``output/<scene>``; created if needed.
        scene: the scene's name (a ScanNet++ scene id such as ``5ee7c22ba0``).
        link: link the model's point cloud to the dataset's instead of copying it.

    Returns:
        the processed scene's folder, ``root/scannetpp/<scene>``.

    Raises:
        InputError: ``dataset`` is not a synthetic dataset, ``scene`` is not a folder name, or
            one of the three folders already exists and is not empty.
    """
    dataset, root = _checked(dataset, root, scene)
    _check_dataset(dataset)
    data = root / "scannetpp" / scene
    annotations = root / ANNOTATION_FOLDER / scene
    for folder in (data, annotations, root / "output" / scene):
        if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
            raise InputError(folder, "already exists and is not empty")
    synthetic, record = _dataset_scene(dataset)
    cameras = synthetic.cameras
    evaluated = [cameras.stems.index(stem) for stem in record["evaluation_views"]]
    red, green, blue = (float(v) for v in record["dataset"]["background"])
    min_pixels = max(1, int(record["dataset"]["min_label_pixels"]))
    frames = [_openhype_frame(synthetic, i, (red, green, blue), min_pixels) for i in evaluated]

    others = [i for i in range(len(cameras)) if i not in evaluated]
    order = sorted(evaluated, key=lambda i: f"{cameras.stems[i]}.JPG") + others
    names = {i: f"{EVAL_VIEW_PREFIX}{k + 1:05d}" for k, i in enumerate(order[: len(evaluated)])}
    names |= {i: f"frame_train_{k + 1:05d}" for k, i in enumerate(others)}

    data.parent.mkdir(parents=True, exist_ok=True)
    with atomic_folder(data) as staging:
        (staging / "images").mkdir()
        features = staging / "language_features"
        features.mkdir()
        shutil.copyfile(
            dataset / "language_features" / "embedding.json", features / "embedding.json"
        )
        for i in order:
            stem, name = cameras.stems[i], names[i]
            shutil.copyfile(dataset / "images" / f"{stem}.jpg", staging / "images" / f"{name}.jpg")
            for kind in ("s", "f"):
                shutil.copyfile(
                    dataset / "language_features" / f"{stem}_{kind}.npy",
                    features / f"{name}_{kind}.npy",
                )
        write_transforms_json(
            staging / "transforms.json",
            replace(cameras.select(order), names=tuple(f"images/{names[i]}.jpg" for i in order)),
        )

    write_openhype_annotations(annotations, frames)
    for i in evaluated:
        stem = cameras.stems[i]
        shutil.copyfile(dataset / "images" / f"{stem}.jpg", annotations / f"{stem}.jpg")

    _write_model(dataset, root, scene, os.path.abspath(data), cameras_json=False, link=link)
    logger.info(
        "wrote OpenHype's ScanNet++ layout of %s: %s, %s and %s",
        dataset,
        data,
        annotations,
        root / "output" / scene,
    )
    return data
