"""3D-OVS segmentation ground truth (Liu et al., "Weakly Supervised 3D Open-vocabulary
Segmentation", NeurIPS 2023): binary masks per class for a few test views of each scene.

Layout of one scene (from the README and ``dataLoader/llff.py`` of github.com/Kunhao-Liu/3D-OVS)::

    <scene>/
        images/00.png, 01.png, ...          the RGB frames (LLFF-style scene, poses_bounds.npy)
        segmentations/
            classes.txt                      one class (= text query) per line
            <view>/                          one folder per annotated test view, named by the
                <class>.png                  image number ("00", "03", ...); one binary mask per
                ...                          class, white (255) = the class, black (0) = not

How the two reference evaluations read it:

- 3D-OVS (``LLFFDataset.read_classes_names`` / ``read_segmentation_maps``): strips the lines of
  ``classes.txt`` and **sorts** them; takes every sub-folder of ``segmentations`` as a view and
  ``int(folder)`` as its camera index; requires ``<view>/<class>.png`` for every class (raises if
  one is missing); loads it with Pillow ``convert('L')`` and ``(mask / 255).astype(int8)``, so
  only 255 counts as the class.
- THGS / LangSplat follow-ups (``scripts/eval_seg.py``, function ``_3dovs``): takes every entry of
  ``segmentations`` not ending in ``.txt`` as a view and every file in it as a class
  (``name.split('.')[0]``), reads it with OpenCV as grayscale, class = value > 0, and queries
  ``wood wall`` as ``wood`` ("as shown in the appendix of LangSplat"); ``classes.txt`` is not
  read there. :func:`query_text` applies that substitution.

thgs reads the layout strictly: masks must be 0/255 (after Pillow's ``convert('L')``, so mode
``1`` and grey RGB masks work too), so the two rules above agree. A view holds only the classes
whose PNG is present (3D-OVS's loader would refuse a missing one; the THGS evaluation skips it).
Views are kept by folder name, classes in ``classes.txt`` order (not sorted).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from thgs._atomic import atomic_folder
from thgs.errors import InputError

__all__ = [
    "QUERY_SUBSTITUTIONS",
    "SegmentationSet",
    "query_text",
    "read_3dovs_segmentations",
    "write_3dovs_segmentations",
]

logger = logging.getLogger(__name__)

QUERY_SUBSTITUTIONS: dict[str, str] = {"wood wall": "wood"}
"""Class names that the THGS/LangSplat 3D-OVS protocol queries with another text."""

_CLASSES_FILE = "classes.txt"


def query_text(class_name: str) -> str:
    """The text the 3D-OVS protocol queries for ``class_name``: ``"wood wall"`` → ``"wood"``.

    Every other class is queried as written in ``classes.txt``.
    """
    return QUERY_SUBSTITUTIONS.get(class_name, class_name)


@dataclass(frozen=True, eq=False)
class SegmentationSet:
    """The segmentation ground truth of one 3D-OVS scene.

    Attributes:
        classes: the class names (text descriptions) in ``classes.txt`` order.
        views: view name (the folder name, e.g. ``"00"``) → class name → [H, W] bool mask, True
            where the class is. A view holds only the classes with a PNG present; all masks of one
            view share their size. Pixel (x, y) is ``mask[y, x]``, at the PNG's resolution.
    """

    classes: tuple[str, ...]
    views: dict[str, dict[str, np.ndarray]]

    def check(self, source: str = "SegmentationSet") -> SegmentationSet:
        """Verify the invariants above; raise :class:`InputError` naming ``source``.

        Class and view names must be usable as file names (non-empty, no ``/``, ``\\``, NUL or
        line break, not ``.``/``..``, no leading dot) and classes unique.
        """
        for kind, names in (("class", self.classes), ("view", tuple(self.views))):
            for name in names:
                if not isinstance(name, str) or not _valid_name(name):
                    raise InputError(source, f"{kind} name {name!r} is not usable as a file name")
        if len(set(self.classes)) != len(self.classes):
            raise InputError(source, f"classes are not unique: {list(self.classes)}")
        for view, masks in self.views.items():
            shapes = set()
            for class_name, mask in masks.items():
                if class_name not in self.classes:
                    raise InputError(source, f"view {view!r}: class {class_name!r} not in classes")
                if not isinstance(mask, np.ndarray) or mask.ndim != 2 or mask.dtype != np.bool_:
                    raise InputError(
                        source, f"view {view!r}, class {class_name!r}: expected an [H, W] bool mask"
                    )
                shapes.add(mask.shape)
            if len(shapes) > 1:
                raise InputError(
                    source, f"view {view!r}: masks of different sizes {sorted(shapes)}"
                )
        return self


def _valid_name(name: str) -> bool:
    return (
        bool(name)
        and name.strip() == name
        and not name.startswith(".")
        and not any(c in name for c in "/\\\0\n\r")
    )


def _read_classes(path: Path) -> tuple[str, ...]:
    if not path.is_file():
        raise InputError(path, "no such file (3D-OVS lists the scene's classes in classes.txt)")
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not a readable UTF-8 text file ({exc})") from exc
    classes = tuple(line.strip() for line in lines if line.strip())
    if not classes:
        raise InputError(path, "lists no class")
    duplicates = sorted({name for name in classes if classes.count(name) > 1})
    if duplicates:
        raise InputError(path, f"lists classes more than once: {duplicates}")
    return classes


def _read_mask(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as image:
            image.load()
            grey = np.asarray(image.convert("L"))
    except (OSError, UnidentifiedImageError) as exc:
        raise InputError(path, f"not a readable image ({exc})") from exc
    values = np.unique(grey)
    if not np.isin(values, (0, 255)).all():
        shown = values[:8].tolist()
        raise InputError(path, f"not a binary mask: grey values {shown} (expected only 0 and 255)")
    return grey == 255


def read_3dovs_segmentations(folder: str | os.PathLike[str]) -> SegmentationSet:
    """Read a scene's 3D-OVS segmentations.

    Args:
        folder: the ``segmentations`` folder, or the scene folder that contains it.

    Returns:
        :class:`SegmentationSet` with the classes of ``classes.txt`` and every sub-folder as a
        view (sorted by name). Hidden entries are skipped; other non-PNG files in a view folder
        are skipped with a warning.

    Raises:
        InputError: a missing folder or ``classes.txt``; a PNG whose class is not in
            ``classes.txt``; an unreadable image; a mask with values other than 0 and 255; masks
            of different sizes within one view. The message names the file.
    """
    folder = Path(folder)
    if not (folder / _CLASSES_FILE).exists() and (folder / "segmentations").is_dir():
        folder = folder / "segmentations"
    if not folder.is_dir():
        raise InputError(folder, "3D-OVS segmentations folder not found")
    classes_path = folder / _CLASSES_FILE
    classes = _read_classes(classes_path)
    views: dict[str, dict[str, np.ndarray]] = {}
    for view_dir in sorted(folder.iterdir()):
        if view_dir.name.startswith(".") or not view_dir.is_dir():
            continue
        masks: dict[str, np.ndarray] = {}
        first: tuple[Path, tuple[int, ...]] | None = None
        for png in sorted(view_dir.iterdir()):
            if png.name.startswith("."):
                continue
            if png.suffix.lower() != ".png" or not png.is_file():
                logger.warning("%s: not a <class>.png mask, skipped", png)
                continue
            class_name = png.name[: -len(png.suffix)]
            if class_name not in classes:
                raise InputError(png, f"class {class_name!r} is not in {classes_path}")
            mask = _read_mask(png)
            if first is None:
                first = (png, mask.shape)
            elif mask.shape != first[1]:
                raise InputError(
                    png,
                    f"mask is {mask.shape[1]}×{mask.shape[0]} but {first[0].name} in the same "
                    f"view is {first[1][1]}×{first[1][0]}",
                )
            masks[class_name] = mask
        views[view_dir.name] = dict(sorted(masks.items(), key=lambda item: classes.index(item[0])))
    return SegmentationSet(classes, views)


def _write_png(path: Path, mask: np.ndarray) -> None:
    """An 8-bit grey ('L') PNG of 0/255, without metadata: the same mask gives the same bytes."""
    Image.fromarray(mask.astype(np.uint8) * np.uint8(255)).save(path, format="PNG")


def write_3dovs_segmentations(
    folder: str | os.PathLike[str], segmentations: SegmentationSet
) -> None:
    """Write ``segmentations`` as a 3D-OVS ``segmentations`` folder, atomically as a whole.

    Writes ``folder/classes.txt`` (one class per line, UTF-8, LF line ends) and
    ``folder/<view>/<class>.png`` for every mask: 8-bit grey PNG, 255 = the class, 0 = not.
    Everything is written into a temporary sibling folder that is then renamed to ``folder``, so a
    reader sees the complete folder or none; the same input always gives the same bytes.

    Args:
        folder: the ``segmentations`` folder to create (``<scene>/segmentations``). It must not
            exist or be empty.

    Raises:
        InputError: ``folder`` exists and is not an empty folder (nothing is overwritten), or the
            segmentations fail :meth:`SegmentationSet.check` (nothing is written then).
    """
    folder = Path(folder)
    segmentations.check(source=f"segmentations to write to {folder}")
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise InputError(folder, "already exists and is not an empty folder; refusing to overwrite")
    with atomic_folder(folder) as tmp:
        (tmp / _CLASSES_FILE).write_text(
            "".join(f"{name}\n" for name in segmentations.classes), encoding="utf-8"
        )
        for view, masks in segmentations.views.items():
            (tmp / view).mkdir()
            for class_name, mask in masks.items():
                _write_png(tmp / view / f"{class_name}.png", mask)
