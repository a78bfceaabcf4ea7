"""A splat's virtual views on disk: cameras, renders and guidance, kept so that a rerun resumes.

Layout of a views folder (a training-data folder as COLMAP lays it out, so that
:func:`thgs.scene.load_scene` reads it as the scene's source)::

    views.json                        what it was made for: the scene's fingerprint, the
                                      placement settings, the coverage reached
    sparse/0/{cameras,images}.bin     the virtual cameras (PINHOLE, no points)
    images/<stem>.jpg                 the renders (view-dependent colour, over ``background``)
    language_features/<stem>_{s,f}.npy  the guidance (LangSplat layout), + embedding.json

``views.json`` is written last: a folder without it is not (yet) a views folder. A rerun for the
same scene and settings reads the cameras back and skips every finished render and guidance
file (each written atomically); another scene or other settings is an error unless
``overwrite``.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from PIL import Image

from thgs._atomic import atomic_output
from thgs.errors import InputError
from thgs.field import scene_fingerprint
from thgs.render import RasterConfig
from thgs.scene import Cameras, Gaussians, load_cameras, write_colmap
from thgs.splat_views.placement import Placement, PlacementConfig, place_cameras
from thgs.views import scene_image

__all__ = [
    "VIEWS_FORMAT",
    "VIEWS_RECORD",
    "ViewsFolder",
    "open_views_folder",
    "render_view",
    "render_views",
]

logger = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]

VIEWS_RECORD = "views.json"
"""The file that makes a folder a views folder (written last)."""

VIEWS_FORMAT = "thgs.splat_views"
"""``views.json``'s ``"format"``."""

_VERSION = 1

BACKGROUND = (0.5, 0.5, 0.5)
"""Behind the splat in the renders: a neutral grey, which SAM does not take for an object."""


@dataclass(frozen=True)
class ViewsFolder:
    """An opened views folder.

    Attributes:
        path: the folder.
        cameras: its views (the cameras written in ``sparse/0``, names ``<stem>.jpg``).
        record: ``views.json``'s content.
        placed: True when the cameras were placed now, False when read back from the folder.
    """

    path: Path
    cameras: Cameras
    record: dict
    placed: bool

    @property
    def images(self) -> Path:
        """The renders' folder."""
        return self.path / "images"

    @property
    def guidance(self) -> Path:
        """The guidance folder (LangSplat's ``language_features``)."""
        return self.path / "language_features"


def _record(gaussians: Gaussians, ply: Path, config: PlacementConfig, from_model: bool) -> dict:
    return {
        "format": VIEWS_FORMAT,
        "version": _VERSION,
        "scene": str(ply),
        "fingerprint": scene_fingerprint(gaussians),
        "placement": json.loads(json.dumps(asdict(config))),
        "model_cameras": from_model,
    }


def _read_record(path: Path) -> dict | None:
    record_path = path / VIEWS_RECORD
    if not record_path.is_file():
        return None
    try:
        record = json.loads(record_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputError(record_path, f"unreadable: {error}") from error
    if not isinstance(record, dict) or record.get("format") != VIEWS_FORMAT:
        raise InputError(record_path, f"not a thgs views record (no format {VIEWS_FORMAT!r})")
    return record


def _differences(found: dict, wanted: dict) -> list[str]:
    """What the folder's record says it was made for, where that is not what is wanted."""
    made_for = {
        "fingerprint": "another scene",
        "placement": "other placement settings",
        "model_cameras": "model cameras" if found.get("model_cameras") else "no model cameras",
    }
    return [reason for key, reason in made_for.items() if found.get(key) != wanted[key]]


def _read_cameras(path: Path, record: dict) -> Cameras:
    """The folder's cameras in the order they were placed (``views.json``'s ``stems``; the
    COLMAP reader sorts them by name)."""
    cameras, sparse, _ = load_cameras(path / "sparse" / "0")
    order = {stem: index for index, stem in enumerate(cameras.stems)}
    stems = record.get("stems")
    if not isinstance(stems, list) or sorted(stems) != sorted(order):
        raise InputError(
            path / VIEWS_RECORD,
            f"its stems do not match the cameras in {sparse}; pass --overwrite-views to "
            "place them again",
        )
    return cameras.select([order[stem] for stem in stems])


def open_views_folder(
    path: str | os.PathLike[str],
    gaussians: Gaussians,
    ply: str | os.PathLike[str],
    config: PlacementConfig = PlacementConfig(),
    *,
    model_cameras: Cameras | None = None,
    overwrite: bool = False,
    raster: RasterConfig = RasterConfig(),
    progress: Progress | None = None,
) -> ViewsFolder:
    """The views folder at ``path`` for ``gaussians`` (read from ``ply``): read back when it was
    made for them with the same settings, else made now (cameras placed by
    :func:`thgs.splat_views.place_cameras`, written as a COLMAP model, then ``views.json``).

    Raises:
        InputError: ``path`` is a file; a folder with content but no ``views.json``; a views
            folder made for another scene or other settings (without ``overwrite``); a scene
            cameras cannot be placed around — each naming the file.
    """
    path = Path(path)
    ply = Path(ply)
    if path.exists() and not path.is_dir():
        raise InputError(path, "is a file; name a folder to keep the virtual views in")
    wanted = _record(gaussians, ply, config, model_cameras is not None)
    found = _read_record(path) if path.is_dir() else None
    if found is not None:
        differences = _differences(found, wanted)
        if not differences:
            cameras = _read_cameras(path, found)
            logger.info("reusing the %d virtual views in %s", len(cameras), path)
            return ViewsFolder(path, cameras, found, placed=False)
        if not overwrite:
            raise InputError(
                path / VIEWS_RECORD,
                f"these views were made for {' and '.join(differences)}; pass --overwrite-views "
                "to replace them, or name another folder",
            )
        shutil.rmtree(path)
    elif path.is_dir() and any(path.iterdir()):
        raise InputError(
            path, f"is not empty and holds no {VIEWS_RECORD}; name a new or empty folder"
        )
    placement: Placement = place_cameras(
        gaussians,
        config,
        model_cameras=model_cameras,
        raster=raster,
        source=str(ply),
        progress=progress,
    )
    cameras = placement.cameras
    files = replace(cameras, names=tuple(f"{stem}.jpg" for stem in cameras.stems))
    path.mkdir(parents=True, exist_ok=True)
    write_colmap(path / "sparse" / "0", files)
    record = {
        **wanted,
        "views": len(cameras),
        "base_views": placement.base_views,
        "covered": round(placement.covered, 6),
        "min_views": config.min_views,
        "stems": list(cameras.stems),
    }
    with atomic_output(path / VIEWS_RECORD, "w") as handle:
        json.dump(record, handle, indent=2)
        handle.write("\n")
    return ViewsFolder(path, files, record, placed=True)


def render_view(
    gaussians: Gaussians,
    camera: Cameras,
    *,
    background: tuple[float, float, float] = BACKGROUND,
    raster: RasterConfig = RasterConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """One view of the splat: ([H, W, 3] uint8 RGB with view-dependent colour over
    ``background``, [H, W] int64 index of each pixel's largest-weight Gaussian, −1 where
    none)."""
    image, max_id = scene_image(gaussians, camera, background=background, config=raster)
    return np.floor(image * 255.0 + 0.5).astype(np.uint8), max_id


ViewHook = Callable[[int, str, np.ndarray], None]
"""``hook(view index, stem, max_id)``: called for each view rendered now (e.g. to write the
oracle's guidance from the same render)."""


def render_views(
    views: ViewsFolder,
    gaussians: Gaussians,
    *,
    done: Callable[[str], bool] | None = None,
    on_view: ViewHook | None = None,
    jpeg_quality: int = 95,
    raster: RasterConfig = RasterConfig(),
    progress: Progress | None = None,
) -> int:
    """Render every view of ``views`` whose image is missing (or for which ``done(stem)`` is
    False) to ``images/<stem>.jpg``, atomically, calling ``on_view`` with the render.

    Returns:
        the number of views rendered now (0 when every one was finished).
    """
    rendered = 0
    stems = views.cameras.stems
    for index, stem in enumerate(stems):
        image_path = views.images / f"{stem}.jpg"
        if image_path.is_file() and (done is None or done(stem)):
            if progress is not None:
                progress("render", index + 1, len(stems))
            continue
        rgb, max_id = render_view(gaussians, views.cameras.select([index]), raster=raster)
        if on_view is not None:
            on_view(index, stem, max_id)
        with atomic_output(image_path) as handle:
            Image.fromarray(rgb).save(handle, format="JPEG", quality=jpeg_quality, subsampling=0)
        rendered += 1
        if progress is not None:
            progress("render", index + 1, len(stems))
    return rendered
