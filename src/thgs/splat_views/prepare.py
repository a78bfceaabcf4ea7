"""One call from a splat file to a views folder with guidance (the first step of
``thgs build --from-splat``): load the Gaussians, place or read back the cameras, render what is
missing, make the guidance that is missing."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from thgs.splat_views.folder import ViewsFolder, open_views_folder
from thgs.splat_views.guidance import GuidanceSource, ModelGuidance, make_views_guidance
from thgs.splat_views.placement import PlacementConfig

__all__ = ["SplatViews", "SplatViewsRequest", "default_views_folder", "prepare_splat_views"]

logger = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class SplatViewsRequest:
    """How to see a splat that has no photos.

    Attributes:
        folder: the views folder (cameras, renders, guidance; kept so that a rerun resumes).
        guidance: SAM and CLIP on the renders (:class:`ModelGuidance`) or the synthetic oracle
            (:class:`thgs.splat_views.OracleGuidance`).
        placement: where the cameras go.
        model_cameras: start from the model's own cameras (``cameras.json``) when it has them;
            False: always the orbit.
        overwrite: replace a views folder made for another scene or other settings.
    """

    folder: Path
    guidance: GuidanceSource = field(default_factory=ModelGuidance)
    placement: PlacementConfig = field(default_factory=PlacementConfig)
    model_cameras: bool = True
    overwrite: bool = False


@dataclass(frozen=True)
class SplatViews:
    """A views folder ready to build from: ``views`` and how many were ``rendered`` now."""

    views: ViewsFolder
    rendered: int


def default_views_folder(out: Path) -> Path:
    """Where a build writing the field ``out`` keeps its virtual views: ``<out stem>.views``
    beside it."""
    return out.with_name(f"{out.stem}.views")


def prepare_splat_views(
    scene: Path,
    request: SplatViewsRequest,
    *,
    iteration: int | None = None,
    device: str = "auto",
    progress: Progress | None = None,
) -> SplatViews:
    """Make (or resume) the views folder of the splat ``scene`` (a ``.ply``, a model folder or
    a gsplat checkpoint; :func:`thgs.scene.load_scene`).

    Raises:
        InputError: a scene that cannot be read, without usable Gaussians or too degenerate to
            place cameras around; a views folder that is a file, foreign or made for another
            scene; guidance that cannot be made (each naming the file).
    """
    from thgs.device import resolve_device
    from thgs.scene import load_scene

    loaded = load_scene(scene, iteration=iteration)
    gaussians = loaded.gaussians.to(resolve_device(device))
    model_cameras = loaded.cameras if request.model_cameras else None
    views = open_views_folder(
        request.folder,
        gaussians,
        loaded.ply_path,
        request.placement,
        model_cameras=model_cameras,
        overwrite=request.overwrite,
        progress=progress,
    )
    rendered = make_views_guidance(views, gaussians, request.guidance, progress=progress)
    logger.info(
        "views of %s in %s: %d views, %d rendered now",
        scene,
        views.path,
        len(views.cameras),
        rendered,
    )
    return SplatViews(views, rendered)
