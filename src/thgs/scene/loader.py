"""Recognise a scene on disk (a trained model folder, a gsplat checkpoint, or a PLY plus a source)
and load it."""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from thgs._json import load_json
from thgs.errors import InputError
from thgs.scene.cameras import Cameras
from thgs.scene.cameras_json import read_cameras_json
from thgs.scene.cfg_args import ModelSource, find_model_source
from thgs.scene.colmap import read_colmap
from thgs.scene.gaussians import Gaussians
from thgs.scene.gsplat_checkpoint import find_gsplat_checkpoint, read_gsplat_checkpoint
from thgs.scene.gsplat_config import find_gsplat_source, gsplat_config_file, read_gsplat_config
from thgs.scene.images import IMAGE_EXTENSIONS, find_images, fit_to_images
from thgs.scene.ply import read_ply
from thgs.scene.transforms_json import read_transforms_json

__all__ = ["Scene", "camera_disagreement", "load_cameras", "load_scene"]

logger = logging.getLogger(__name__)

_ITERATION = re.compile(r"^iteration_(\d+)$")

_TRAIN_SPLIT = "transforms_train.json"
"""The Blender split file of the training views (NeRF Blender scenes, OpenGaussian's ScanNet)."""
_TEST_SPLIT = "transforms_test.json"
"""Its held-out views: never read as cameras (see :func:`load_cameras`)."""


@dataclass(frozen=True, eq=False)
class Scene:
    """Gaussians, their cameras (if any were found) and where each came from.

    Attributes:
        gaussians: the scene's Gaussians.
        cameras: its cameras at the resolution of the images (when they were checked) or of the
            camera file, or None when only a PLY was given.
        ply_path: the file the Gaussians were read from: a PLY, or a gsplat checkpoint (.pt).
        cameras_path: the camera file or COLMAP folder, or None.
        found: what was recognised, one line each, in the order it was looked at.
        source: the training data folder (or camera file) the cameras were read from: the one
            given, or the one the model folder's ``cfg_args`` names; None when the cameras came
            from the model's ``cameras.json`` or there are none.
        model_source: what the model folder's ``cfg_args`` says about its training data and
            where that was found (:func:`thgs.scene.cfg_args.find_model_source`); None when no
            ``cfg_args`` was read (a PLY file, no such file, or a source was given).
    """

    gaussians: Gaussians
    cameras: Cameras | None
    ply_path: Path
    cameras_path: Path | None
    found: tuple[str, ...]
    source: Path | None = None
    model_source: ModelSource | None = None

    def to(self, device: torch.device | str) -> Scene:
        """The scene with its Gaussians on ``device`` (cameras stay on the CPU in float64:
        whatever renders moves the one camera it needs)."""
        return replace(self, gaussians=self.gaussians.to(device))


def _model_ply(model_dir: Path, iteration: int | None) -> tuple[Path, int]:
    point_cloud = model_dir / "point_cloud"
    iterations = sorted(
        int(m.group(1))
        for child in (point_cloud.iterdir() if point_cloud.is_dir() else [])
        if (m := _ITERATION.match(child.name)) and (child / "point_cloud.ply").is_file()
    )
    if not iterations:
        raise InputError(
            model_dir,
            "not a trained model folder: no point_cloud/iteration_*/point_cloud.ply and no "
            "gsplat ckpts/ckpt_*.pt (give the PLY or .pt file itself, or the folder the "
            "3DGS/2DGS or gsplat trainer wrote)",
        )
    if iteration is None:
        iteration = iterations[-1]
    elif iteration not in iterations:
        raise InputError(model_dir, f"no iteration {iteration}; the folder has {iterations}")
    return point_cloud / f"iteration_{iteration}" / "point_cloud.ply", iteration


def load_cameras(
    source: str | os.PathLike[str],
    *,
    images: str | None = None,
    scale: float = 1.0,
    undo_applied_transform: bool = False,
) -> tuple[Cameras, Path, list[str]]:
    """Read the cameras of a source: a camera file, or a folder holding one.

    A folder is searched, in this order, for a COLMAP model in the folder itself, in ``sparse/0/``
    or in ``sparse/``, then for ``transforms_train.json``, ``transforms.json`` and
    ``cameras.json``. A folder holding both a COLMAP model and a ``transforms.json`` must describe
    the same cameras in both (else an :class:`InputError` says what differs and that ``--source``
    chooses). A file is read by its content: a JSON list is a 3DGS ``cameras.json``, a JSON
    object with ``frames`` a ``transforms.json``.

    A folder with ``transforms_train.json`` (the NeRF Blender split, and OpenGaussian's ScanNet
    scenes: ``color/``, ``transforms_train.json``, ``transforms_test.json``) gives the views of
    ``transforms_train.json`` only: the 3DGS-family trainers read this split before
    ``transforms.json``, and OpenGaussian trains its ScanNet scenes with ``--eval``, which holds
    out ``transforms_test.json`` from training and from its language association, so thgs lifts
    from the same views. Every frame's image must exist (OpenGaussian skips missing ones
    silently; thgs refuses them); frames with NaN or infinite poses (ScanNet's lost tracking) are
    left out with a warning. A ``transforms.json`` beside it must hold every train frame with the
    same cameras.

    Images: for COLMAP and cameras.json, the folder ``source/<images>`` must hold every camera's
    image (``images=None`` means ``images/``, checked only when present; a folder named
    explicitly must exist); for transforms.json the images are where ``file_path`` says and are
    checked when any of them exists. Checked images fix the cameras' sizes (see
    :func:`thgs.scene.images.fit_to_images`). ``scale`` is image size / camera-file size.

    Returns:
        ``(cameras, camera_path, found)`` with ``found`` lines describing what was recognised.

    Raises:
        InputError: nothing recognisable, or any reader's error.
    """
    source = Path(source)
    found: list[str] = []
    if source.is_dir():
        camera_path = _find_cameras(source)
    elif source.is_file():
        camera_path = source
    else:
        raise InputError(source, "no such file or folder")

    image_root: Path | None = None
    if camera_path.is_dir():
        cameras = read_colmap(camera_path)
        for other in _colmap_models(source):
            if other != camera_path:
                found.append(_check_models_agree(cameras, camera_path, other, source))
        if source.is_dir() and (source / "transforms.json").is_file():
            found.append(
                _check_agreement(
                    cameras, camera_path, source / "transforms.json", undo_applied_transform
                )
            )
        found.append(f"COLMAP model {camera_path} ({len(cameras)} registered images)")
        if source.is_dir() and (source / _TRAIN_SPLIT).is_file():
            found.append(
                f"{source / _TRAIN_SPLIT} not read: the COLMAP model comes first, as in the "
                "3DGS-family trainers"
            )
        image_root = source / (images or "images")
    else:
        document = load_json(camera_path)
        if images is not None and isinstance(document, dict) and "frames" in document:
            raise InputError(
                camera_path,
                f"names every image's path itself (file_path), so images={images!r} "
                "(--images) does not apply; leave it out",
            )
        if isinstance(document, list):
            cameras = read_cameras_json(camera_path)
            found.append(f"3DGS cameras.json {camera_path} ({len(cameras)} cameras)")
            if source.is_dir():
                image_root = source / (images or "images")
        elif isinstance(document, dict) and "frames" in document:
            if source.is_dir() and camera_path.name == _TRAIN_SPLIT:
                cameras = _read_train_split(
                    camera_path, len(document["frames"]), undo_applied_transform, found
                )
                image_root = source
            else:
                cameras = read_transforms_json(
                    camera_path, undo_applied_transform=undo_applied_transform
                )
                found.append(f"transforms.json {camera_path} ({len(cameras)} frames)")
                if any(path is not None for path in find_images(cameras, camera_path.parent)):
                    image_root = camera_path.parent
        else:
            raise InputError(
                camera_path, "neither a 3DGS cameras.json (a list) nor a transforms.json (frames)"
            )

    if images is not None and (image_root is None or not image_root.is_dir()):
        raise InputError(
            source / images, "image folder not found (images= names a folder inside the source)"
        )
    if image_root is not None and image_root.is_dir():
        cameras = fit_to_images(cameras, image_root, scale=scale)
        found.append(f"images {image_root} checked, {_size_range(cameras)}")
    else:
        if scale != 1.0:
            cameras = cameras.scaled(scale)
        found.append(
            f"images not checked (none found), {_size_range(cameras)} from the camera file"
        )
    return cameras, camera_path, found


def _check_agreement(
    first: Cameras, colmap: Path, transforms: Path, undo_applied_transform: bool
) -> str:
    """A folder holding both a COLMAP model and a ``transforms.json`` is read from COLMAP only
    when both describe the same cameras: the same image stems, intrinsics within 0.1 % and camera
    centres equal up to a similarity transform (nerfstudio rescales, rotates and shifts the world)
    within 0.1 % of their spread. ``first`` is the model's cameras, already read from ``colmap``.
    Returns the line for ``found``.

    Raises:
        InputError: they disagree (naming both, what differs and ``--source``, which decides).
    """
    second = read_transforms_json(transforms, undo_applied_transform=undo_applied_transform)
    problem = camera_disagreement(first, second)
    if problem is not None:
        raise InputError(
            colmap.parent if colmap.parent.name == "sparse" else colmap,
            f"holds a COLMAP model ({colmap}) and {transforms}, and they disagree: {problem}; "
            f"choose one with --source {colmap} or --source {transforms}",
        )
    return f"{transforms} describes the same cameras as the COLMAP model; reading COLMAP"


def camera_disagreement(first: Cameras, second: Cameras, *, subset: bool = False) -> str | None:
    """What differs between two descriptions of one capture, or None: the image stems (all of
    them; with ``subset``, only that they share some), then on the shared images the intrinsics
    (within 0.1 %, after scaling to the same image width) and the camera centres up to a
    similarity transform (within 0.1 % of their spread; needs 3 shared cameras)."""
    shared = [stem for stem in second.stems if stem in set(first.stems)]
    if not subset and sorted(first.stems) != sorted(second.stems):
        only = sorted(set(first.stems) ^ set(second.stems))
        return f"different images ({len(only)} in one only, e.g. {only[:3]})"
    if not shared:
        return f"no image in common (e.g. {list(first.stems[:2])} and {list(second.stems[:2])})"
    second = second.select([second.stems.index(stem) for stem in shared])
    order = [first.stems.index(stem) for stem in second.stems]
    scale = (second.widths.double() / first.widths[order].double())[:, None]
    ratio = second.Ks[:, :2, :].reshape(len(second), -1) / (
        first.Ks[order, :2, :].reshape(len(second), -1) * scale
    ).clamp_min(1e-12)
    known = first.Ks[order, :2, :].reshape(len(second), -1).abs() > 0
    if ((ratio - 1).abs()[known] > 1e-3).any():
        return "different intrinsics (focal lengths or principal points)"
    a = first.centers()[order].numpy()
    b = second.centers().numpy()
    a, b = a - a.mean(axis=0), b - b.mean(axis=0)
    spread_a, spread_b = np.sqrt((a**2).sum(axis=1).mean()), np.sqrt((b**2).sum(axis=1).mean())
    if len(a) < 3 or spread_a == 0 or spread_b == 0:
        return None
    rotation, _ = Rotation.align_vectors(a / spread_a, b / spread_b)
    residual = a / spread_a - rotation.apply(b / spread_b)
    if np.sqrt((residual**2).sum(axis=1).mean()) > 1e-3:
        return "different camera positions (no rotation, scale and shift maps one onto the other)"
    return None


def _read_train_split(
    path: Path, frames: int, undo_applied_transform: bool, found: list[str]
) -> Cameras:
    """The cameras of a folder's ``transforms_train.json`` (see :func:`load_cameras`), checked
    against its images and against a ``transforms.json`` beside it; lines go to ``found``."""
    folder = path.parent
    cameras = read_transforms_json(
        path, undo_applied_transform=undo_applied_transform, skip_invalid_poses=True
    )
    missing = [
        name for name, image in zip(cameras.names, find_images(cameras, folder)) if image is None
    ]
    if missing:
        raise InputError(
            path,
            f"{len(missing)} of {len(cameras)} frames name images that do not exist (first: "
            f"{missing[:3]}, looked for under {folder} as written or with "
            f"{', '.join(IMAGE_EXTENSIONS[:2])}, …); restore them or remove those frames",
        )
    found.append(f"{_TRAIN_SPLIT} {path} ({len(cameras)} frames, the training views)")
    if frames > len(cameras):
        found.append(
            f"{frames - len(cameras)} frames of {path.name} left out: their transform_matrix is "
            "not finite (ScanNet's frames with lost tracking)"
        )
    test = folder / _TEST_SPLIT
    if test.is_file():
        found.append(
            f"{test} not read: its views are held out, as OpenGaussian trains its ScanNet scenes "
            "(--eval: train split only)"
        )
    whole = folder / "transforms.json"
    if whole.is_file():
        every = read_transforms_json(whole, undo_applied_transform=undo_applied_transform)
        outside = sorted(set(cameras.stems) - set(every.stems))
        problem = (
            f"{len(outside)} train frames are not in {whole.name} (e.g. {outside[:3]})"
            if outside
            else camera_disagreement(every, cameras, subset=True)
        )
        if problem is not None:
            raise InputError(
                folder,
                f"holds {whole.name} and {path.name}, and they disagree: {problem}; choose one "
                f"with --source {whole} or --source {path}",
            )
        found.append(f"{whole} describes the same cameras; reading {path.name}")
    return cameras


def _colmap_models(folder: Path) -> list[Path]:
    """The COLMAP models of a folder, in the order they are read: itself, sparse/0, sparse."""
    return [
        candidate
        for candidate in (folder, folder / "sparse" / "0", folder / "sparse")
        if (candidate / "cameras.bin").is_file() or (candidate / "cameras.txt").is_file()
    ]


def _check_models_agree(cameras: Cameras, read: Path, other: Path, folder: Path) -> str:
    """A folder with two COLMAP models is read from the first only when the second describes
    the same cameras (:func:`camera_disagreement`); returns the line for ``found``.

    Raises:
        InputError: they disagree, naming both and ``--source``, which decides.
    """
    problem = camera_disagreement(cameras, read_colmap(other))
    if problem is not None:
        raise InputError(
            folder,
            f"holds two COLMAP models, {read} and {other}, and they disagree: {problem}; "
            f"choose one with --source {read} or --source {other}",
        )
    return f"{other} describes the same cameras as {read}; reading {read}"


def _find_cameras(folder: Path) -> Path:
    models = _colmap_models(folder)
    if models:
        return models[0]
    for candidate in (folder / _TRAIN_SPLIT, folder / "transforms.json", folder / "cameras.json"):
        if candidate.is_file():
            return candidate
    raise InputError(
        folder,
        "no cameras found: expected a COLMAP model (sparse/0/ or sparse/), transforms_train.json, "
        "transforms.json or cameras.json",
    )


def _size_range(cameras: Cameras) -> str:
    def span(values) -> str:
        low, high = int(values.min()), int(values.max())
        return str(low) if low == high else f"{low}-{high}"

    return f"{span(cameras.widths)}×{span(cameras.heights)} px"


def _warn_if_normalized(result_dir: Path, found: list[str]) -> None:
    """With ``--source`` given for a gsplat result folder: say so when its settings file records
    gsplat's normalised world frame (the cameras given must then be in that frame)."""
    config = gsplat_config_file(result_dir)
    if config is None:
        return
    try:
        normalized = read_gsplat_config(config).get("normalize_world_space", True)
    except InputError:
        return
    if normalized is not False:
        line = (
            f"{config} records normalize_world_space: {normalized!r}: the checkpoint's Gaussians "
            "are in gsplat's normalised frame, so the cameras of --source must be too (COLMAP's "
            "own cameras do not fit them)"
        )
        logger.warning("%s", line)
        found.append(line)


def load_scene(
    path: str | os.PathLike[str],
    *,
    source: str | os.PathLike[str] | None = None,
    iteration: int | None = None,
    images: str | None = None,
    scale: float = 1.0,
    undo_applied_transform: bool = False,
) -> Scene:
    """Load a scene from a trained model folder, a gsplat checkpoint or a PLY file.

    Args:
        path: a 3DGS/2DGS model folder (``point_cloud/iteration_*/point_cloud.ply``, usually
            ``cameras.json`` and ``cfg_args``), a ``.ply`` file, a gsplat result folder
            (``ckpts/ckpt_*.pt``) or one gsplat checkpoint ``.pt``
            (:func:`thgs.scene.read_gsplat_checkpoint`; its cameras come from the COLMAP scene
            its ``cfg.yml``/``cfg.json`` names, see
            :func:`thgs.scene.gsplat_config.find_gsplat_source`, or from ``source``).
        source: where the cameras come from: the training data folder (COLMAP ``sparse/0`` +
            ``images/``, ``transforms_train.json`` + its images, or ``transforms.json``) or a
            camera file. See :func:`load_cameras`.
            Default: for a model folder, the training data its ``cfg_args`` names when it is
            found here (:func:`thgs.scene.cfg_args.find_model_source`), else the model's
            ``cameras.json``; for a gsplat result folder (or a checkpoint in its ``ckpts/``),
            the ``data_dir`` of its settings file when found here.
        iteration: which ``iteration_*`` of a model folder, or which step of a gsplat result
            folder; default the newest.
        images: the image folder's name inside ``source`` (e.g. ``images_4``); default
            ``images``, checked when present.
        scale: image size / camera-file size (e.g. 0.25 with ``images_4``); never guessed.
        undo_applied_transform: see :func:`thgs.scene.read_transforms_json`.

    Returns:
        a :class:`Scene`; it logs, and lists in ``found``, what it recognised.

    Raises:
        InputError: nothing recognisable at ``path`` or ``source``, a malformed ``cfg_args``
            or gsplat settings file, two folders that fit its ``source_path``/``data_dir``, a
            gsplat result folder trained in its normalised world frame with no ``source``
            given, or any reader's error.
    """
    path = Path(path)
    found: list[str] = []
    model_cameras: Path | None = None
    model_source: ModelSource | None = None
    result_dir: Path | None = None
    if path.is_dir() and not (path / "point_cloud").is_dir() and (path / "ckpts").is_dir():
        ply_path = find_gsplat_checkpoint(path, iteration)
        found.append(f"gsplat result folder {path}, checkpoint {ply_path.name}")
        result_dir = path
    elif path.is_dir():
        ply_path, chosen = _model_ply(path, iteration)
        found.append(f"trained model folder {path}, iteration {chosen}")
        if (path / "cameras.json").is_file():
            model_cameras = path / "cameras.json"
        if source is None:
            model_source = find_model_source(path)
        if model_source is not None:
            found.append(model_source.describe())
            if model_source.folder is None and model_cameras is not None:
                logger.warning(
                    "cameras from %s: the training data named by %s is not here (pass --source "
                    "with it to read its cameras)",
                    model_cameras,
                    model_source.cfg_args,
                )
            source = model_source.folder
            if source is not None and model_source.images not in (None, "images", images):
                found.append(
                    f"{model_source.cfg_args} trained on the images in "
                    f"{model_source.images!r}; thgs checks the cameras against "
                    f"{images or 'images'!r} (--images and --scale choose)"
                )
    elif path.is_file():
        if path.suffix.lower() not in (".ply", ".pt"):
            raise InputError(
                path, "expected a .ply file, a gsplat checkpoint (.pt) or a trained model folder"
            )
        if iteration is not None:
            raise InputError(path, "iteration is only meaningful for a model folder")
        ply_path = path
        if path.suffix.lower() == ".pt" and path.parent.name == "ckpts":
            result_dir = path.parent.parent
    else:
        raise InputError(path, "no such file or folder")
    if result_dir is not None:
        if source is None:
            model_source = find_gsplat_source(result_dir)
        else:
            _warn_if_normalized(result_dir, found)
        if model_source is not None:
            found.append(model_source.describe())
            source = model_source.folder
            if source is not None and model_source.images not in (None, images):
                factor = model_source.images.removeprefix("images_")
                found.append(
                    f"{model_source.cfg_args}: gsplat trained on {model_source.images!r} "
                    f"(data_factor {factor}); thgs checks the cameras against "
                    f"{images or 'images'!r} (--images {model_source.images} --scale "
                    f"{1 / int(factor):g} choose those)"
                )

    if ply_path.suffix.lower() == ".pt":
        gaussians = read_gsplat_checkpoint(ply_path)
        found.append(
            f"gsplat checkpoint read as {gaussians.kind.upper()}, told by its name "
            "(simple_trainer writes ckpt_<step>_rank<r>.pt, simple_trainer_2dgs ckpt_<step>.pt)"
        )
    else:
        gaussians = read_ply(ply_path)
    found.append(
        f"{len(gaussians):,} {gaussians.kind.upper()} Gaussians, SH degree "
        f"{gaussians.sh_degree} in {ply_path}"
    )
    cameras: Cameras | None = None
    cameras_path: Path | None = None
    camera_source = source if source is not None else model_cameras
    if camera_source is not None:
        try:
            cameras, cameras_path, camera_found = load_cameras(
                camera_source,
                images=images,
                scale=scale,
                undo_applied_transform=undo_applied_transform,
            )
        except InputError as exc:
            if model_source is None or source is None:
                raise
            instead = "" if model_cameras is None else f", e.g. --source {model_cameras}"
            raise InputError(
                exc.source,
                f"{exc.problem} (the source named by {model_source.cfg_args}; --source "
                f"decides{instead})",
            ) from exc
        found.extend(camera_found)
    elif model_source is not None and model_source.named is not None:
        beside = "" if result_dir is not None else "no cameras.json in the model folder and "
        found.append(
            f"no cameras: {beside}its source is not here (pass --source with COLMAP, "
            "transforms.json or cameras.json)"
        )
    else:
        found.append("no cameras (pass a source with COLMAP, transforms.json or cameras.json)")
    for line in found:
        logger.info("%s", line)
    return Scene(
        gaussians,
        cameras,
        ply_path,
        cameras_path,
        tuple(found),
        source=None if source is None else Path(source),
        model_source=model_source,
    )
