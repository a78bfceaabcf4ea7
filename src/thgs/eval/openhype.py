"""OpenHype's ScanNet++ benchmark (Weijler et al., "OpenHype: Hyperbolic Embeddings for
Hierarchical Open-Vocabulary Radiance Fields", NeurIPS 2025): object and part masks on test
frames of 20 ScanNet++ scenes, one JSON file per frame.

Layout of one scene's annotation folder, as OpenHype's evaluator reads it
(github.com/lisaweijler/openhype, ``openhype/openhype_eval/scannetpp_evaluator.py``,
``ScannetppDataEvaluator._get_gt_data``; its ``gt_path`` is
``…/openhype_scannetpp_benchmark/<scene id>``)::

    <gt folder>/
        DSC01752.json       one file per annotated frame, named after its DSLR image
        <masks>.png         wherever each object's "path_to_mask" (relative to the folder) says
        DSC01752.JPG        the test image, copied there by benchmark/scannetpp_preprocess.py

    {"info": {"name": "DSC01752.JPG",              # the frame's image; its stem names the view
              "width": 1752, "height": 1168,       # the masks' (and the rendered view's) size
              "fl_x": …, "fl_y": …, "cx": …, "cy": …,   # pinhole intrinsics in pixels
              "camera_model": "PINHOLE",           # nerfstudio's name of the camera type
              "transform_matrix": [[…4×4…]]},      # camera→world, OpenGL axes (nerfstudio)
     "objects": [{"category": "handle of a cabinet",   # the text prompt
                  "is_part": true,                     # a "[PART] of a [OBJ]" prompt
                  "bbox": [x1, y1, x2, y2],            # pixels; several boxes may be listed
                  "path_to_mask": "…/….png"}, …]}      # relative to the gt folder

How the evaluator reads it (and so does :func:`read_openhype_annotations`):

- the frames are ``sorted(glob(gt_path + "/*.json"))``; frame i is rendered from the camera
  ``info`` states and named ``info["name"].split(".")[0]``;
- a mask is ``np.array(Image.open(path).convert("L")) // 255``: only grey 255 is the object (a
  0/1 PNG would read as empty);
- objects sharing a ``category`` in one frame are one prompt: the **first** one's mask and
  ``is_part`` are kept (later masks are not even opened), and every one's ``bbox`` is appended
  to the prompt's boxes (``reshape(-1)`` then ``reshape(-1, 4)``: any nesting of 4k numbers);
- ``is_part`` separates the object and part scores (``== False`` / truthy).

thgs reads strictly what the evaluator needs, and refuses what would make it fail or score
nonsense: every key above must be there with the right type, every mask file must exist, be
readable, have ``info``'s size and hold at least one 255 pixel (an empty mask would score 0/0);
a ``category`` may not be ``camera_data`` (the key under which the evaluator keeps the camera,
so such a prompt is never scored there). Every object's mask is checked, including those a
repeated category hides; :meth:`OpenHypeFrame.prompts` applies the first-one rule.

The frame-to-view rule of the benchmark's own preprocessing (``scannetpp_preprocess.py``: the
test images are copied into the nerfstudio scene as ``images/frame_eval_00001.JPG`` … in the
sorted order of the annotation files) is :func:`openhype_views`.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np
from PIL import Image, UnidentifiedImageError

from thgs._atomic import atomic_folder
from thgs._json import get_matrix, get_number, load_json
from thgs.errors import InputError
from thgs.field_scene import find_view
from thgs.scene import Cameras
from thgs.scene.cameras import MAX_IMAGE_SIDE, viewmat_from_pose
from thgs.scene.loader import camera_disagreement
from thgs.scene.transforms_json import OPENGL_TO_OPENCV

__all__ = [
    "CAMERA_KEY",
    "EVAL_VIEW_PREFIX",
    "OpenHypeFrame",
    "OpenHypeObject",
    "ViewMatch",
    "openhype_views",
    "part_prompt",
    "read_openhype_annotations",
    "read_openhype_frame",
    "write_openhype_annotations",
]

logger = logging.getLogger(__name__)

CAMERA_KEY = "camera_data"
"""The key under which OpenHype's evaluator keeps a frame's camera beside its prompts (so a
category of that name is never scored there; thgs refuses it)."""

EVAL_VIEW_PREFIX = "frame_eval_"
"""How ``scannetpp_preprocess.py`` renames the annotated test images in the nerfstudio scene:
``frame_eval_00001`` is the first annotation file in sorted order."""

_PERSPECTIVE = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
"""nerfstudio camera models OpenHype renders as plain perspective cameras (it passes no
distortion coefficients, so ``OPENCV`` is a pinhole camera there)."""

_CAMERA_NUMBERS = ("fl_x", "fl_y", "cx", "cy")


@dataclass(frozen=True, eq=False)
class OpenHypeObject:
    """One annotated prompt of a frame.

    Attributes:
        category: the text prompt (``"chair"``, ``"handle of a cabinet"``).
        is_part: a part prompt ("[PART] of a [OBJ]") rather than an object prompt.
        mask: [H, W] bool, True where the mask PNG is grey 255, at the frame's size.
        boxes: [B, 4] float64 (x1, y1, x2, y2) pixel boxes (x = column, y = row), B ≥ 1.
        path_to_mask: the mask's path as the file states it (relative to the annotation folder).
    """

    category: str
    is_part: bool
    mask: np.ndarray
    boxes: np.ndarray
    path_to_mask: str


@dataclass(frozen=True, eq=False)
class OpenHypeFrame:
    """The annotations of one frame.

    Attributes:
        stem: the annotation file's name without ``.json`` (``DSC01752``).
        image_name: ``info.name``, the frame's image (``DSC01752.JPG``).
        width, height: ``info``'s size in pixels: the masks' and the evaluated view's.
        K: [3, 3] float64 pinhole intrinsics (``fl_x``, ``fl_y``, ``cx``, ``cy``) in pixels.
        camtoworld: [4, 4] float64 ``transform_matrix``: camera→world with OpenGL axes (x right,
            y up, z back), nerfstudio's convention, in the capture's world frame.
        camera_model: ``info.camera_model`` (``PINHOLE``, ``SIMPLE_PINHOLE`` or ``OPENCV``).
        objects: every entry of ``objects``, in file order.
        extra: ``info``'s other keys, kept for writing the file back.
    """

    stem: str
    image_name: str
    width: int
    height: int
    K: np.ndarray
    camtoworld: np.ndarray
    camera_model: str
    objects: tuple[OpenHypeObject, ...]
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def view(self) -> str:
        """The view the frame is evaluated in: ``image_name`` without folder and extension."""
        return PurePosixPath(self.image_name.replace("\\", "/")).stem

    def prompts(self) -> tuple[OpenHypeObject, ...]:
        """One object per category, as OpenHype's evaluator scores them: the first entry's mask
        and ``is_part``, the boxes of every entry of that category; in order of first
        appearance."""
        merged: dict[str, OpenHypeObject] = {}
        for entry in self.objects:
            first = merged.get(entry.category)
            if first is None:
                merged[entry.category] = entry
            else:
                boxes = np.concatenate([first.boxes, entry.boxes])
                merged[entry.category] = OpenHypeObject(
                    first.category, first.is_part, first.mask, boxes, first.path_to_mask
                )
        return tuple(merged.values())

    def cameras(self, name: str | None = None) -> Cameras:
        """The camera ``info`` states, as one thgs camera (OpenCV axes) named ``name`` (default
        :attr:`image_name`)."""
        pose = self.camtoworld @ OPENGL_TO_OPENCV
        viewmat = viewmat_from_pose(pose[:3, :3], pose[:3, 3])
        return Cameras.from_lists(
            [viewmat], [self.K], [self.width], [self.height], [name or self.image_name]
        )


def part_prompt(part: str, obj: str) -> str:
    """OpenHype's part prompt "[PART] of a [OBJ]" from a part's and its object's names.

    The part's leading words that are also words of the object's name are dropped
    (``"mug handle"``, ``"mug"`` → ``"handle of a mug"``; ``"bear head"``, ``"teddy bear"`` →
    ``"head of a teddy bear"``); a part name that does not start with one of them, or consists
    of them only, is kept whole (``"light bulb"``, ``"lamp"`` → ``"light bulb of a lamp"``).
    """
    words = part.split()
    object_words = {word.lower() for word in obj.split()}
    start = 0
    while start < len(words) and words[start].lower() in object_words:
        start += 1
    kept = words[start:] if start < len(words) else words
    return f"{' '.join(kept)} of a {obj.strip()}"


def _size(info: dict[str, Any], path: Path) -> tuple[int, int]:
    width = get_number(info, "width", path, "info")
    height = get_number(info, "height", path, "info")
    if width <= 0 or height <= 0 or width != int(width) or height != int(height):
        raise InputError(path, f"info: size {width:g}×{height:g} is not positive integers")
    if max(width, height) > MAX_IMAGE_SIDE:
        raise InputError(path, f"info: size {width:g}×{height:g} exceeds {MAX_IMAGE_SIDE:,} pixels")
    return int(width), int(height)


def _camera(info: dict[str, Any], path: Path) -> tuple[np.ndarray, np.ndarray, str]:
    fx, fy, cx, cy = (get_number(info, key, path, "info") for key in _CAMERA_NUMBERS)
    if fx <= 0 or fy <= 0:
        raise InputError(path, f"info: focal lengths fl_x {fx:g}, fl_y {fy:g} must be positive")
    model = info.get("camera_model")
    if not isinstance(model, str):
        raise InputError(path, "info has no 'camera_model' string")
    if model not in _PERSPECTIVE:
        raise InputError(
            path,
            f"info: camera_model {model!r} is not a perspective model; OpenHype's frames are "
            f"undistorted DSLR images ({', '.join(_PERSPECTIVE)})",
        )
    matrix = info.get("transform_matrix")
    try:
        size = np.asarray(matrix, dtype=np.float64).size if matrix is not None else 0
    except (TypeError, ValueError):
        size = 0
    if size == 16:  # OpenHype reads it with .view(4, 4): any regular nesting of 16 numbers
        info = {**info, "transform_matrix": np.asarray(matrix, dtype=np.float64).reshape(4, 4)}
    camtoworld = get_matrix(info, "transform_matrix", (4, 4), path, "info")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return K, np.asarray(camtoworld, dtype=np.float64), model


def _boxes(value: Any, path: Path, where: str) -> np.ndarray:
    try:
        flat = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise InputError(path, f"{where}: 'bbox' is not numbers [x1, y1, x2, y2]") from exc
    if any(isinstance(v, bool) for v in np.asarray(value, dtype=object).reshape(-1)):
        raise InputError(path, f"{where}: 'bbox' is not numbers [x1, y1, x2, y2]")
    if flat.size == 0 or flat.size % 4:
        raise InputError(
            path, f"{where}: 'bbox' holds {flat.size} numbers; expected [x1, y1, x2, y2] per box"
        )
    if not np.isfinite(flat).all():
        raise InputError(path, f"{where}: 'bbox' has NaN or infinite values")
    return flat.reshape(-1, 4)


def _read_mask(path: Path, source: Path, where: str, size: tuple[int, int]) -> np.ndarray:
    try:
        exists = path.is_file()
    except (OSError, ValueError):  # a name too long, or with a NUL byte
        exists = False
    if not exists:
        raise InputError(source, f"{where}: its mask {path} does not exist")
    try:
        with Image.open(path) as image:
            image.load()
            grey = np.asarray(image.convert("L"))
    except (OSError, UnidentifiedImageError, ValueError, Image.DecompressionBombError) as exc:
        raise InputError(path, f"not a readable image ({exc})") from exc
    width, height = size
    if grey.shape != (height, width):
        raise InputError(
            path,
            f"mask is {grey.shape[1]}×{grey.shape[0]} but {source.name}'s info says "
            f"{width}×{height}",
        )
    mask = grey == 255
    if not mask.any():
        values = np.unique(grey)[:8].tolist()
        raise InputError(
            path,
            f"mask has no pixel of grey 255 (values {values}); OpenHype reads only 255 as the "
            "object (`// 255`), so it would score an empty mask",
        )
    return mask


def _is_part(value: Any, path: Path, where: str) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    raise InputError(path, f"{where}: 'is_part' is {value!r}; expected true or false (or 1 / 0)")


def read_openhype_frame(path: str | os.PathLike[str]) -> OpenHypeFrame:
    """Read one annotation file; its masks are read relative to its folder.

    Raises:
        InputError: unreadable JSON; no ``info`` object or ``objects`` list; an ``info`` without
            a positive integer size, a ``name``, the four intrinsics, a perspective
            ``camera_model`` or a finite 4×4 ``transform_matrix``; an object without a non-empty
            ``category`` string (or named ``camera_data``), a boolean ``is_part``, a ``bbox`` of
            4k finite numbers or a ``path_to_mask`` string; a mask that is missing, unreadable,
            not of ``info``'s size, or without a 255 pixel. The message names the file and the
            object.
    """
    path = Path(path)
    document = load_json(path)
    if not isinstance(document, dict) or not isinstance(document.get("info"), dict):
        raise InputError(
            path, "expected an object with 'info' and 'objects' (OpenHype annotations)"
        )
    info = document["info"]
    width, height = _size(info, path)
    name = info.get("name")
    if not isinstance(name, str) or not name.strip():
        raise InputError(path, "info has no 'name' string (the frame's image)")
    K, camtoworld, model = _camera(info, path)
    entries = document.get("objects")
    if not isinstance(entries, list):
        raise InputError(path, "no 'objects' list")
    objects = []
    for index, entry in enumerate(entries):
        where = f"object {index}"
        if not isinstance(entry, dict) or not isinstance(entry.get("category"), str):
            raise InputError(path, f"{where} has no 'category' string")
        category = entry["category"]
        if not category.strip():
            raise InputError(path, f"{where}: 'category' is empty; it is the text prompt")
        if category == CAMERA_KEY:
            raise InputError(
                path,
                f"{where}: category {CAMERA_KEY!r} is the key under which OpenHype's evaluator "
                "keeps the frame's camera; it would never be scored there",
            )
        for key in ("is_part", "bbox", "path_to_mask"):
            if key not in entry:
                raise InputError(path, f"{where} ({category!r}) has no {key!r}")
        is_part = _is_part(entry["is_part"], path, f"{where} ({category!r})")
        boxes = _boxes(entry["bbox"], path, f"{where} ({category!r})")
        mask_path = entry["path_to_mask"]
        if not isinstance(mask_path, str) or not mask_path.strip():
            raise InputError(path, f"{where} ({category!r}): 'path_to_mask' is not a path string")
        mask = _read_mask(path.parent / mask_path, path, f"{where} ({category!r})", (width, height))
        objects.append(OpenHypeObject(category, is_part, mask, boxes, mask_path))
    categories = [entry.category for entry in objects]
    repeated = sorted({c for c in categories if categories.count(c) > 1})
    if repeated:
        logger.warning(
            "%s: categories %s are annotated more than once; as in OpenHype's evaluator only "
            "the first mask of each is scored (the boxes of all count)",
            path,
            repeated,
        )
    extra = {
        key: value
        for key, value in info.items()
        if key not in ("name", "width", "height", "camera_model", "transform_matrix")
        and key not in _CAMERA_NUMBERS
    }
    return OpenHypeFrame(
        path.stem, name, width, height, K, camtoworld, model, tuple(objects), extra
    )


def read_openhype_annotations(folder: str | os.PathLike[str]) -> list[OpenHypeFrame]:
    """Every ``*.json`` annotation file of one scene's folder, in OpenHype's (sorted) order.

    Raises:
        InputError: the folder is missing or holds no JSON file, or a file is malformed
            (:func:`read_openhype_frame`).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "OpenHype annotation folder not found")
    paths = sorted(
        (
            p
            for p in folder.iterdir()
            if p.name.endswith(".json") and not p.name.startswith(".") and p.is_file()
        ),
        key=lambda p: p.name,
    )
    if not paths:
        raise InputError(folder, "holds no OpenHype annotation files (<image>.json)")
    return [read_openhype_frame(path) for path in paths]


def _frame_document(frame: OpenHypeFrame) -> dict[str, Any]:
    fx, fy, cx, cy = frame.K[0, 0], frame.K[1, 1], frame.K[0, 2], frame.K[1, 2]
    info: dict[str, Any] = {
        "name": frame.image_name,
        "width": frame.width,
        "height": frame.height,
        "fl_x": float(fx),
        "fl_y": float(fy),
        "cx": float(cx),
        "cy": float(cy),
        "camera_model": frame.camera_model,
        "transform_matrix": np.asarray(frame.camtoworld, dtype=np.float64).tolist(),
        **frame.extra,
    }
    objects = [
        {
            "category": entry.category,
            "is_part": bool(entry.is_part),
            "bbox": entry.boxes[0].tolist() if len(entry.boxes) == 1 else entry.boxes.tolist(),
            "path_to_mask": entry.path_to_mask,
        }
        for entry in frame.objects
    ]
    return {"info": info, "objects": objects}


def _check_for_writing(frames: list[OpenHypeFrame] | tuple[OpenHypeFrame, ...], source: str):
    stems = [frame.stem for frame in frames]
    if len(set(stems)) != len(stems):
        raise InputError(source, f"two frames share a file name: {sorted(stems)}")
    masks: set[PurePosixPath] = set()
    for frame in frames:
        if not frame.stem or "/" in frame.stem or frame.stem.startswith("."):
            raise InputError(source, f"frame {frame.stem!r} is not usable as a file name")
        for entry in frame.objects:
            relative = PurePosixPath(entry.path_to_mask)
            if (
                relative.is_absolute()
                or ".." in relative.parts
                or relative.suffix.lower() != ".png"
            ):
                raise InputError(
                    source,
                    f"frame {frame.stem}: mask path {entry.path_to_mask!r} must be a relative "
                    ".png path inside the folder",
                )
            if relative in masks:
                raise InputError(source, f"mask path {entry.path_to_mask!r} is used twice")
            masks.add(relative)
            mask = entry.mask
            if mask.dtype != np.bool_ or mask.shape != (frame.height, frame.width):
                raise InputError(
                    source,
                    f"frame {frame.stem}, {entry.category!r}: expected a "
                    f"[{frame.height}, {frame.width}] bool mask",
                )
            if not mask.any():
                raise InputError(source, f"frame {frame.stem}, {entry.category!r}: empty mask")


def write_openhype_annotations(
    folder: str | os.PathLike[str], frames: list[OpenHypeFrame] | tuple[OpenHypeFrame, ...]
) -> None:
    """Write ``frames`` as one scene's OpenHype annotation folder, atomically as a whole.

    Writes ``folder/<stem>.json`` per frame (``json``, indent 4) and each object's mask at
    ``folder/<path_to_mask>`` as an 8-bit grey PNG, 255 = the object, 0 = not; a ``bbox`` of
    one box is written flat ``[x1, y1, x2, y2]``, several as a list of boxes. Everything is
    written into a temporary sibling folder renamed into place at the end; the same frames give
    the same bytes.

    Raises:
        InputError: ``folder`` exists and is not an empty folder, two frames share a stem, a
            mask path is not a relative ``.png`` inside the folder or is used twice, or a mask
            is not a non-empty bool mask of its frame's size (nothing is written then).
    """
    folder = Path(folder)
    _check_for_writing(frames, f"annotations to write to {folder}")
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise InputError(folder, "already exists and is not an empty folder; refusing to overwrite")
    with atomic_folder(folder) as tmp:
        for frame in frames:
            for entry in frame.objects:
                target = tmp / PurePosixPath(entry.path_to_mask)
                target.parent.mkdir(parents=True, exist_ok=True)
                image = Image.fromarray(entry.mask.astype(np.uint8) * np.uint8(255))
                image.save(target, format="PNG")
            with open(tmp / f"{frame.stem}.json", "w", encoding="utf-8") as handle:
                json.dump(_frame_document(frame), handle, indent=4)
                handle.write("\n")


@dataclass(frozen=True)
class ViewMatch:
    """Which camera of the scene each annotation frame is evaluated in.

    Attributes:
        indices: one camera index per frame, in the frames' order.
        rule: ``"name"`` (the camera whose image stem is the frame's :attr:`OpenHypeFrame.view`)
            or ``"frame_eval"`` (the preprocessing's renaming: the k-th annotation file in
            sorted order is ``frame_eval_0000k``).
        note: what a reader of the numbers must know about the matching ('' for ``name``).
    """

    indices: tuple[int, ...]
    rule: str
    note: str = ""


def _has_view(cameras: Cameras, name: str) -> bool:
    return name in cameras.stems or name in cameras.names


def openhype_views(
    cameras: Cameras | None, frames: list[OpenHypeFrame] | tuple[OpenHypeFrame, ...], source: str
) -> ViewMatch:
    """The camera of each annotation frame.

    A frame is the camera whose image stem is its :attr:`~OpenHypeFrame.view` (``DSC01752`` for
    ``info.name`` ``DSC01752.JPG``), as LERF-OVS frames are. When no frame's image is a camera of
    the scene but the scene holds the preprocessed test views ``frame_eval_00001`` …
    (``scannetpp_preprocess.py`` copies the annotated images under these names, in the sorted
    order of ``<annotation stem>.JPG``), frame k of that order is ``frame_eval_0000k``; there
    must be as many such views as frames, and the cameras the frames state must agree with
    them (intrinsics within 0.1 %, camera centres up to a similarity within 0.1 % of their
    spread when there are 3 or more: :func:`thgs.scene.loader.camera_disagreement`).

    Args:
        cameras: the scene's cameras.
        frames: the annotation frames (:func:`read_openhype_annotations`).
        source: the annotation folder, for messages.

    Raises:
        InputError: no cameras; a frame with no camera of its image's name (naming the frame
            and some views) while others have one; the ``frame_eval`` views are not one per
            frame, or their cameras are not the frames'.
    """
    if cameras is None:
        raise InputError(source, "the scene has no cameras")
    found = [_has_view(cameras, frame.view) for frame in frames]
    evaluated = sorted(stem for stem in cameras.stems if stem.startswith(EVAL_VIEW_PREFIX))
    if any(found) or not evaluated or not frames:
        indices = tuple(
            find_view(cameras, frame.view, f"{source}/{frame.stem}.json") for frame in frames
        )
        return ViewMatch(indices, "name")
    order = sorted(range(len(frames)), key=lambda i: f"{frames[i].stem}.JPG")
    names = {i: f"{EVAL_VIEW_PREFIX}{rank + 1:05d}" for rank, i in enumerate(order)}
    expected = sorted(names.values())
    if evaluated != expected:
        raise InputError(
            source,
            f"no annotated image ({frames[0].view}, …) is a view of the scene, whose test views "
            f"are {evaluated[0]} … {evaluated[-1]} ({len(evaluated)}) as scannetpp_preprocess.py "
            f"names them, but there are {len(frames)} annotation files: they are not this "
            "scene's (or the scene was processed from other annotations)",
        )
    stated = Cameras.from_lists(
        [frame.cameras().viewmats[0].numpy() for frame in frames],
        [frame.K for frame in frames],
        [frame.width for frame in frames],
        [frame.height for frame in frames],
        [f"{names[i]}.JPG" for i in range(len(frames))],
    )
    problem = camera_disagreement(stated, cameras, subset=True)
    if problem is not None:
        raise InputError(
            source,
            f"the annotation files' cameras are not the scene's views {expected[0]} … "
            f"{expected[-1]} they were renamed to: {problem}",
        )
    indices = tuple(cameras.stems.index(names[i]) for i in range(len(frames)))
    note = (
        f"annotation frames matched to the preprocessed test views {expected[0]} … "
        f"{expected[-1]} by the sorted order of their file names (scannetpp_preprocess.py's "
        "renaming); the cameras the frames state agree with those views"
    )
    return ViewMatch(indices, "frame_eval", note)
