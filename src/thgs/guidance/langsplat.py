"""2D guidance in LangSplat's layout: multi-level SAM masks and one feature row per mask.

Per view ``<stem>``, in a ``language_features/`` folder::

    <stem>_s.npy   float32 [4, H, W]   mask id per pixel for the levels default, s, m, l; −1 = none
    <stem>_f.npy   float32 [n, D]      one (unit) feature row per mask

Mask ids are global row indices into ``_f.npy``, offset level after level: the ``default`` masks
take rows ``0 … n_default−1``, the ``s`` masks the next ``n_s`` rows, and so on. This is what
LangSplat writes and what THGS, OpenGaussian, Occam's LGS and Dr. Splat read.

thgs adds one file LangSplat lacks, ``embedding.json`` ({"space": ..., "dim": D}, and "model":
the absolute path of the local CLIP folder the features were made with, if any), naming the
embedding space of the features (e.g. ``laion/CLIP-ViT-B-16-laion2B-s34B-b88K``) so that nothing
compares features and queries from different models; a field built from the folder remembers the
model, so queries find it. Folders without the file are taken as they are.
"""

from __future__ import annotations

import json
import logging
import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from thgs._atomic import atomic_output
from thgs._json import load_json
from thgs.errors import InputError
from thgs.scene import Cameras
from thgs.scene.distortion import undistort_labels
from thgs.text import LANGSPLAT_SPACE, known_dim

__all__ = [
    "EMBEDDING_FILE",
    "LEVELS",
    "GuidanceFolder",
    "ViewGuidance",
    "check_masks",
    "load_guidance",
    "read_embedding_model",
    "read_embedding_space",
    "read_view_guidance",
    "resample_segments",
    "write_embedding_space",
    "write_view_guidance",
]

logger = logging.getLogger(__name__)

LEVELS = ("default", "s", "m", "l")
"""Mask levels in file order: SAM's pooled masks, then its small, medium and large outputs."""


@dataclass(frozen=True, eq=False)
class ViewGuidance:
    """The masks and mask features of one view.

    Attributes:
        stem: the view's image stem.
        segments: [4, H, W] int32 global mask id per pixel and level (``LEVELS`` order); −1 = none.
            ``segments[k, y, x] = i`` means pixel (x, y) lies in mask i at level k, whose feature
            is ``features[i]``.
        features: [n, D] float32 mask features (CLIP or the synthetic oracle's text space).
    """

    stem: str
    segments: np.ndarray
    features: np.ndarray

    @property
    def height(self) -> int:
        return int(self.segments.shape[1])

    @property
    def width(self) -> int:
        return int(self.segments.shape[2])

    def level_ids(self, level: int) -> np.ndarray:
        """The sorted mask ids present at ``level`` (0–3)."""
        ids = np.unique(self.segments[level])
        return ids[ids >= 0]

    def check(
        self, source: str = "ViewGuidance", features_source: str | None = None
    ) -> ViewGuidance:
        """Verify the layout; raise :class:`InputError` naming ``source`` (``features_source``,
        if given, for problems of the features alone).

        Invariants: segments [4, H, W] integer-valued ≥ −1 and < n; features [n, D] finite; the
        ids of each level come after those of the previous levels (LangSplat's offsets).
        """
        if self.segments.ndim != 3 or self.segments.shape[0] != 4:
            raise InputError(source, f"segments must be [4, H, W], got {list(self.segments.shape)}")
        if self.features.ndim != 2:
            raise InputError(source, f"features must be [n, D], got {list(self.features.shape)}")
        n = self.features.shape[0]
        _check_finite(self.features, features_source or source)
        low, high = int(self.segments.min()), int(self.segments.max())
        if low < -1:
            raise InputError(
                source,
                f"mask id {low} is invalid: ids are feature rows (≥ 0), or −1 for no mask",
            )
        if high >= n:
            raise InputError(
                source,
                f"mask id {high} has no feature row: the features hold {n} rows (ids 0 … {n - 1})",
            )
        previous_max = -1
        for level, name in enumerate(LEVELS):
            ids = self.segments[level]
            ids = ids[ids >= 0]
            if not ids.size:
                continue
            lowest = int(ids.min())
            if lowest <= previous_max:
                raise InputError(
                    source,
                    f"level {name!r} uses mask id {lowest}, not after the previous levels' "
                    f"ids (up to {previous_max}); expected LangSplat's level offsets",
                )
            previous_max = int(ids.max())
        return self


def _paths(folder: Path, stem: str) -> tuple[Path, Path]:
    return folder / f"{stem}_s.npy", folder / f"{stem}_f.npy"


_NPY_HEADER_LOCK = threading.Lock()
"""NumPy parses a .npy header with ``ast.literal_eval``, which CPython's AST constructor can
fail on when threads call it at once ("AST constructor recursion depth mismatch", CPython
gh-106905); the lift's threads read guidance files lazily, so reads take turns."""


def _load(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InputError(path, "no such file")
    try:
        with _NPY_HEADER_LOCK:
            return np.load(path, allow_pickle=False)
    except Exception as exc:  # numpy's header parser raises ValueError, SyntaxError, TokenError…
        raise InputError(path, f"not a readable .npy file ({exc})") from exc


def read_view_guidance(folder: str | os.PathLike[str], stem: str) -> ViewGuidance:
    """Read ``<stem>_s.npy`` and ``<stem>_f.npy`` from ``folder`` (LangSplat's layout).

    Raises:
        InputError: a missing, truncated or malformed file, non-integer ids, ids outside the
            feature rows, levels out of LangSplat's order.
    """
    folder = Path(folder)
    segments_path, features_path = _paths(folder, stem)
    segments = _load(segments_path)
    if segments.ndim != 3 or segments.shape[0] != 4:
        raise InputError(
            segments_path, f"expected [4, H, W] masks, got shape {list(segments.shape)}"
        )
    if not np.issubdtype(segments.dtype, np.number):
        raise InputError(segments_path, f"expected numbers, got dtype {segments.dtype}")
    if not np.isfinite(segments).all():
        count = int((~np.isfinite(segments)).sum())
        raise InputError(segments_path, f"{count} mask ids are NaN or infinite")
    if not np.array_equal(segments, np.round(segments)):
        raise InputError(segments_path, "mask ids must be whole numbers")
    limits = np.iinfo(np.int32)
    if segments.size and (segments.min() < limits.min or segments.max() > limits.max):
        raise InputError(
            segments_path,
            f"mask ids range over [{segments.min():g}, {segments.max():g}]: ids are feature rows "
            "(≥ 0), or −1 for no mask",
        )
    guidance = ViewGuidance(stem, segments.astype(np.int32), _checked_features(features_path))
    return guidance.check(source=str(segments_path), features_source=str(features_path))


def _checked_features(path: Path) -> np.ndarray:
    """[n, D] float32 finite mask features read from ``path`` (``<stem>_f.npy``)."""
    features = _load(path)
    if features.ndim != 2 or not np.issubdtype(features.dtype, np.floating):
        raise InputError(
            path,
            f"expected an [n, D] array of floats (one feature row per mask), got a "
            f"{features.ndim}-D {features.dtype} array of shape {list(features.shape)}",
        )
    _check_finite(features, path)
    return features.astype(np.float32, copy=False)


def _check_finite(features: np.ndarray, source: str | os.PathLike[str]) -> None:
    """Raise an :class:`InputError` naming ``source`` if a row of the [n, D] ``features`` holds
    NaN or infinity."""
    bad = ~np.isfinite(features).all(axis=1)
    if bad.any():
        raise InputError(
            source,
            f"features have NaN or infinite values in {int(bad.sum())} of {len(features)} "
            f"rows (first: row {int(np.flatnonzero(bad)[0])})",
        )


def write_view_guidance(folder: str | os.PathLike[str], guidance: ViewGuidance) -> None:
    """Write one view in LangSplat's layout (float32 files), each file atomically.

    The feature file is written first, so a reader never finds masks without their features.

    Raises:
        InputError: the guidance fails :meth:`ViewGuidance.check` (nothing is written then).
    """
    folder = Path(folder)
    segments_path, features_path = _paths(folder, guidance.stem)
    guidance.check(source=f"guidance to write to {segments_path}")
    with atomic_output(features_path) as handle:
        np.save(handle, guidance.features.astype(np.float32))
    with atomic_output(segments_path) as handle:
        np.save(handle, guidance.segments.astype(np.float32))


EMBEDDING_FILE = "embedding.json"
"""The file in a ``language_features`` folder that names the features' embedding space."""


def write_embedding_space(
    folder: str | os.PathLike[str],
    space: str,
    dim: int,
    *,
    model: str | os.PathLike[str] | None = None,
) -> None:
    """Record that the features in ``folder`` are ``dim``-D vectors of embedding space ``space``,
    made with the local model folder ``model`` (stored absolute) if given."""
    document: dict[str, object] = {"space": space, "dim": int(dim)}
    if model is not None:
        document["model"] = str(Path(model).expanduser().resolve())
    with atomic_output(Path(folder) / EMBEDDING_FILE, "w") as handle:
        json.dump(document, handle, indent=2)
        handle.write("\n")


def _embedding_document(folder: str | os.PathLike[str]) -> tuple[Path, dict | None]:
    path = Path(folder) / EMBEDDING_FILE
    if not path.is_file():
        return path, None
    document = load_json(path)
    if not isinstance(document, dict) or not isinstance(document.get("space"), str):
        raise InputError(path, 'expected {"space": <name>, "dim": <int>}')
    if not document["space"].strip():
        raise InputError(path, "'space' is empty")
    dim = document.get("dim")
    if isinstance(dim, bool) or not isinstance(dim, int) or dim < 1:
        raise InputError(path, f"'dim' must be a positive integer, got {dim!r}")
    model = document.get("model")
    if model is not None and (not isinstance(model, str) or not model.strip()):
        raise InputError(path, f"'model' must be a folder path, got {model!r}")
    return path, document


def read_embedding_space(folder: str | os.PathLike[str]) -> tuple[str, int] | None:
    """The (space, dim) recorded in ``folder``, or None if it records none.

    Raises:
        InputError: the file exists but is malformed.
    """
    _, document = _embedding_document(folder)
    if document is None:
        return None
    return document["space"], document["dim"]


def read_embedding_model(folder: str | os.PathLike[str]) -> Path | None:
    """The local model folder the features in ``folder`` were made with (``embedding.json``'s
    ``model``), or None where it records none (a Hugging Face id from the cache, or no file).

    Raises:
        InputError: the file exists but is malformed.
    """
    _, document = _embedding_document(folder)
    if document is None or document.get("model") is None:
        return None
    return Path(document["model"])


def guidance_folder(
    scene: str | os.PathLike[str], source: str | os.PathLike[str] | None = None
) -> Path:
    """Where a scene's guidance is by default: ``language_features`` in the source folder
    (COLMAP / transforms.json, LangSplat's layout) when one is given, else beside the model
    (in its folder, or the PLY's folder)."""
    root = Path(source) if source is not None and Path(source).is_dir() else Path(scene)
    return (root if root.is_dir() else root.parent) / "language_features"


def guidance_space(folder: str | os.PathLike[str], views: Sequence[ViewGuidance]) -> str:
    """The embedding space of the features in ``folder``: the one its ``embedding.json``
    records, else LangSplat's OpenCLIP ViT-B/16 for 512-D features (what LangSplat writes
    without recording it).

    Raises:
        InputError: no ``embedding.json`` and features that are not 512-D (their space cannot
            be guessed); a malformed ``embedding.json``, or one whose dimension is not the
            features' (or not its space's, for a space thgs knows).
    """
    path, document = _embedding_document(folder)
    dim = int(views[0].features.shape[1]) if views else 0
    if document is not None:
        space, recorded = document["space"], document["dim"]
        expected = known_dim(space)
        if expected is not None and recorded != expected:
            raise InputError(
                path, f"records {recorded}-D features of {space}, which is {expected}-D"
            )
        if views and recorded != dim:
            raise InputError(
                path,
                f"records {recorded}-D features of {space} but the folder's _f.npy files "
                f"hold {dim}-D features: it belongs to other features; correct or delete it "
                "(thgs build --space then names their space)",
            )
        return space
    if dim == 512:
        return LANGSPLAT_SPACE
    raise InputError(
        folder, f"{dim}-D features and no {EMBEDDING_FILE}; name their space (thgs build --space)"
    )


def check_masks(views: Sequence[ViewGuidance], source: str | os.PathLike[str]) -> list[str]:
    """Refuse guidance without a single mask; name the views without masks.

    A field takes its regions' features from masks, so guidance with no mask in any view cannot
    give one (SAM's score thresholds were too strict for these images, or the masks were made
    for other images).

    Args:
        views: the views' guidance.
        source: the guidance folder (or its name), for the message.

    Returns:
        the stems of the views with no mask at any level, in view order.

    Raises:
        InputError: no view has a mask (the message names ``source`` and the
            ``thgs preprocess`` thresholds to lower).
    """
    empty = [view.stem for view in views if not (view.segments >= 0).any()]
    if views and len(empty) == len(views):
        raise InputError(
            source,
            f"none of the {len(views)} views has a mask, so no region can get a feature; make "
            "the masks again with lower SAM thresholds (thgs preprocess --pred-iou-threshold, "
            "--stability-threshold, --min-region-area) or check that they belong to these images",
        )
    return empty


def resample_segments(segments: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-neighbour resize of [4, H, W] mask ids to [4, height, width].

    Output pixel (x, y) takes the input pixel under its centre: ``floor((x + 0.5) · W / width)``,
    the same pixel-centre convention as the cameras (docs/conventions.md).
    """
    _, src_h, src_w = segments.shape
    rows = np.minimum(((np.arange(height) + 0.5) * src_h / height).astype(np.int64), src_h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * src_w / width).astype(np.int64), src_w - 1)
    return segments[:, rows[:, None], cols[None, :]]


def _load_view(
    folder: Path, cameras: Cameras, i: int, resize: bool, file_size: tuple[int, int]
) -> tuple[ViewGuidance, bool]:
    """View ``i``'s guidance at its camera's resolution (``file_size``: its image file's width
    and height), and whether it was undistorted."""
    stem = cameras.stems[i]
    view = read_view_guidance(folder, stem)
    height, width = int(cameras.heights[i]), int(cameras.widths[i])
    mapping = cameras.undistortion_map(i)
    if mapping is not None and (view.height, view.width) != (height, width):
        file_width, file_height = file_size
        if (view.height, view.width) != (file_height, file_width):
            if not resize:
                raise InputError(
                    folder / f"{stem}_s.npy",
                    f"masks are {view.width}×{view.height} but the image file is "
                    f"{file_width}×{file_height} (its undistorted camera {width}×{height}); "
                    "resample them with --resize (load_guidance(resize=True); nearest "
                    "neighbour)",
                )
            view = ViewGuidance(
                stem, resample_segments(view.segments, file_height, file_width), view.features
            )
        return ViewGuidance(stem, undistort_labels(view.segments, mapping), view.features), True
    if (view.height, view.width) != (height, width):
        if not resize:
            raise InputError(
                folder / f"{stem}_s.npy",
                f"masks are {view.width}×{view.height} but the camera is {width}×{height}; "
                "resample them with --resize (load_guidance(resize=True); nearest "
                "neighbour), or make the masks at the cameras' size (thgs preprocess "
                "--cameras)",
            )
        view = ViewGuidance(stem, resample_segments(view.segments, height, width), view.features)
    return view, False


class GuidanceFolder(Sequence[ViewGuidance]):
    """The guidance of a ``language_features`` folder, each view read (and undistorted or
    resampled) when accessed, as :func:`load_guidance` with ``lazy=True`` returns it."""

    def __init__(self, folder: Path, cameras: Cameras, resize: bool):
        self.folder, self.cameras, self.resize = folder, cameras, resize
        widths, heights = cameras.file_sizes()
        self._file_sizes = [(int(w), int(h)) for w, h in zip(widths, heights)]

    def __len__(self) -> int:
        return len(self.cameras)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(len(self))[index]]
        i = range(len(self))[index]
        return _load_view(self.folder, self.cameras, i, self.resize, self._file_sizes[i])[0]

    def features(self, index: int) -> np.ndarray:
        """View ``index``'s [n, D] float32 mask features alone (``<stem>_f.npy``): what
        ``self[index].features`` holds, without reading, checking and resampling its masks
        (a tenth of a view's bytes at 986×728)."""
        i = range(len(self))[index]
        return _checked_features(_paths(self.folder, self.cameras.stems[i])[1])


def load_guidance(
    folder: str | os.PathLike[str], cameras: Cameras, *, resize: bool = False, lazy: bool = False
) -> list[ViewGuidance] | GuidanceFolder:
    """The guidance of every camera, matched by image stem, at the cameras' resolution.

    Masks are made on the image files. Where the files have lens distortion
    (:attr:`thgs.Cameras.distortion`), masks at the size of the image file are warped into the
    camera's undistorted pinhole image (nearest neighbour,
    :func:`thgs.scene.distortion.undistort_labels`; pixels whose ray leaves the file get −1), and
    masks already at the pinhole camera's size are taken as undistorted.

    Args:
        folder: the ``language_features`` folder.
        cameras: :class:`thgs.Cameras`; view i's files are ``<cameras.stems[i]>_{s,f}.npy``.
        resize: if a view's masks are not at its camera's size (or its image file's, with
            distortion), resample them (nearest neighbour, :func:`resample_segments`) to that
            size instead of raising. The reference code silently assumes equal sizes; thgs
            never does.
        lazy: keep no view in memory: every view is read and checked once here, and then read
            again (and undistorted or resampled again) each time it is used. A build reads the
            guidance a few times; this saves holding it whole (11.5 MB a view at 986×728, 2.3 GB
            for 200 views).

    Returns:
        one :class:`ViewGuidance` per camera, in camera order: a list, or with ``lazy`` a
        :class:`GuidanceFolder` reading them on access.

    Raises:
        InputError: a view's files are missing or malformed, sizes differ without ``resize``,
            or views disagree on the feature dimension.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "language features folder not found")
    missing = [stem for stem in cameras.stems if not (folder / f"{stem}_s.npy").is_file()]
    if missing:
        raise InputError(
            folder,
            f"no guidance for {len(missing)} of {len(cameras)} views (first: {missing[:5]}); "
            "files must be named <image stem>_s.npy / _f.npy",
        )
    lazily = GuidanceFolder(folder, cameras, resize)
    views, dim, undistorted = [], None, 0
    for i, stem in enumerate(cameras.stems):
        view, was_undistorted = _load_view(folder, cameras, i, resize, lazily._file_sizes[i])
        undistorted += was_undistorted
        if dim is not None and view.features.shape[1] != dim:
            raise InputError(
                folder / f"{stem}_f.npy",
                f"feature dimension {view.features.shape[1]}, other views have {dim}",
            )
        dim = view.features.shape[1]
        if not lazy:
            views.append(view)
    if undistorted:
        logger.info("undistorted the masks of %d views (lens distortion)", undistorted)
    logger.info("read guidance for %d views from %s", len(cameras), folder)
    return lazily if lazy else views
