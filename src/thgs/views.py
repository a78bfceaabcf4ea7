"""From regions to pixels and back: 2D masks, relevancy maps and picking (design §4.8).

- :func:`selection_opacity` renders a selection's accumulated opacity: every Gaussian carries 1
  if selected and 0 if not, and composites with the usual occlusion, so a selected surface behind
  an unselected one stays hidden. :func:`selection_masks` thresholds it at 0.5 (the paper's 2D
  mask).
- :func:`relevancy_map` renders each Gaussian's region relevancy the same way (LangSplat-style
  per-pixel relevancy, 0 where no Gaussian is).
- :func:`pick` is the paper's interactive segmentation: a pixel → the Gaussian of largest blending
  weight under it → its region at every level. Only the Gaussians near the pixel's ray are
  rasterized (:class:`thgs.pick_index.PickIndex`). ``SemanticField.parent`` and ``children`` move
  between levels from there.

Pixels are ``(x, y)`` = (column, row) from the top-left corner of the image; pixel (x, y) covers
``[x, x + 1) × [y, y + 1)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from thgs.errors import InputError
from thgs.field import SemanticField
from thgs.pick_index import PickIndex, check_pixel
from thgs.render import RasterConfig, render
from thgs.scene import Cameras, Gaussians

__all__ = [
    "HIGHLIGHT",
    "Pick",
    "best_views",
    "highlighted",
    "pick",
    "relevancy_map",
    "scene_image",
    "selection_masks",
    "selection_opacity",
    "visible_pixels",
]


def _columns(values: np.ndarray, n: int, name: str) -> tuple[np.ndarray, bool]:
    values = np.asarray(values)
    if values.ndim not in (1, 2) or values.shape[0] != n:
        raise InputError(name, f"must be [N] or [N, Q] with N = {n}, got {list(values.shape)}")
    single = values.ndim == 1
    return (values[:, None] if single else values), single


def _render_columns(
    gaussians: Gaussians, camera: Cameras, values: np.ndarray, config: RasterConfig
) -> np.ndarray:
    features = torch.from_numpy(np.ascontiguousarray(values, dtype=np.float64))
    out = render(gaussians, camera, features.to(gaussians.device), config=config)
    return out.image.detach().cpu().numpy()


def scene_image(
    gaussians: Gaussians,
    camera: Cameras,
    *,
    background: tuple[float, float, float] = (0.5, 0.5, 0.5),
    config: RasterConfig = RasterConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """The scene as a photo of one view: colours seen from the camera
    (:meth:`thgs.scene.Gaussians.view_colors`) over ``background``.

    Returns:
        ([H, W, 3] float64 RGB in [0, 1], [H, W] int64 index of each pixel's largest-weight
        Gaussian, −1 where none).
    """
    centre = camera.centers()[0].to(device=gaussians.device, dtype=gaussians.means.dtype)
    colors = gaussians.view_colors(centre).to(torch.float64)
    out = render(gaussians, camera, colors, config=config)
    image = out.image.detach().to(torch.float64).cpu().numpy()
    alpha = out.alpha.detach().to(torch.float64).cpu().numpy()
    rgb = image + (1.0 - alpha)[..., None] * np.asarray(background, dtype=np.float64)
    return np.clip(rgb, 0.0, 1.0), out.max_id.detach().cpu().numpy()


HIGHLIGHT = (0.0, 0.9, 1.0)
"""The colour a selection is tinted with in pictures (cyan)."""


def highlighted(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` ([H, W, 3] in [0, 1]) with the ``mask``'s pixels ([H, W] bool) tinted
    :data:`HIGHLIGHT` and the rest dimmed."""
    tint = 0.45 * image + 0.55 * np.asarray(HIGHLIGHT)
    return np.where(mask[..., None], tint, 0.55 * image)


def selection_opacity(
    gaussians: Gaussians,
    camera: Cameras,
    selected: np.ndarray,
    *,
    config: RasterConfig = RasterConfig(),
) -> np.ndarray:
    """Accumulated opacity of the selected Gaussians in one view.

    Args:
        gaussians: the N Gaussians the selection indexes.
        camera: one camera (``cameras.select([i])``).
        selected: [N] bool, or [N, Q] bool for Q selections rendered in one pass.
        config: rasterization settings.

    Returns:
        [H, W] (or [H, W, Q]) float64 in [0, 1]: ``Σ_k w_k(x) · selected_k``.
    """
    columns, single = _columns(selected, len(gaussians), "selected")
    image = _render_columns(gaussians, camera, columns.astype(np.float64), config)
    return image[..., 0] if single else image


def selection_masks(
    gaussians: Gaussians,
    camera: Cameras,
    selected: np.ndarray,
    *,
    threshold: float = 0.5,
    config: RasterConfig = RasterConfig(),
) -> np.ndarray:
    """The selection's 2D mask in one view: :func:`selection_opacity` > ``threshold``.

    Returns:
        [H, W] (or [H, W, Q]) bool.
    """
    if not 0.0 <= threshold < 1.0:
        raise InputError("threshold", f"must be in [0, 1), got {threshold}")
    return selection_opacity(gaussians, camera, selected, config=config) > threshold


def visible_pixels(
    gaussians: Gaussians,
    cameras: Cameras,
    selected: np.ndarray,
    *,
    threshold: float = 0.5,
    config: RasterConfig = RasterConfig(),
) -> np.ndarray:
    """How many pixels of each view each selection covers, what is in front of it included
    (:func:`selection_masks`, one render per view for every selection at once).

    Args:
        cameras: the V views.
        selected: [N] or [N, Q] bool.

    Returns:
        [V, Q] int64 pixel counts ([V] for one selection).
    """
    columns, single = _columns(selected, len(gaussians), "selected")
    if len(cameras) == 0:
        raise InputError("cameras", "no view to look in")
    counts = np.zeros((len(cameras), columns.shape[1]), dtype=np.int64)
    for view in range(len(cameras)):
        masks = selection_masks(
            gaussians, cameras.select([view]), columns, threshold=threshold, config=config
        )
        counts[view] = masks.reshape(-1, columns.shape[1]).sum(axis=0)
    return counts[:, 0] if single else counts


def best_views(
    gaussians: Gaussians,
    cameras: Cameras,
    selected: np.ndarray,
    *,
    threshold: float = 0.5,
    scale: float = 1.0,
    config: RasterConfig = RasterConfig(),
) -> np.ndarray:
    """For each selection, the view that shows most of it (:func:`visible_pixels`): the one to
    draw it in. Ties go to the first such view; −1 when no view shows any of it (an empty
    selection, or one hidden everywhere). ``scale`` < 1 counts the pixels of renders that
    much smaller (0.25: 16 times fewer pixels to render; a selection a few pixels wide may then
    be seen nowhere).

    Returns:
        [Q] int64 view indices into ``cameras`` (a 0-d array for one [N] selection).
    """
    if not 0.0 < scale <= 1.0:
        raise InputError("scale", f"must be in (0, 1], got {scale}")
    if scale < 1.0:
        cameras = cameras.resized(
            [max(1, round(float(w) * scale)) for w in cameras.widths],
            [max(1, round(float(h) * scale)) for h in cameras.heights],
        )
    counts = visible_pixels(gaussians, cameras, selected, threshold=threshold, config=config)
    best = np.argmax(counts, axis=0)
    return np.where(counts.max(axis=0) > 0, best, -1)


def relevancy_map(
    gaussians: Gaussians,
    camera: Cameras,
    relevancy: np.ndarray,
    *,
    config: RasterConfig = RasterConfig(),
) -> np.ndarray:
    """Per-pixel relevancy in one view: ``Σ_k w_k(x) · rel_k``.

    Args:
        relevancy: [N] (or [N, Q]) per-Gaussian relevancy, e.g.
            :meth:`thgs.query.FieldQuery.gaussian_relevancy`.

    Returns:
        [H, W] (or [H, W, Q]) float64; 0 where no Gaussian is, and lowered where the scene is
        not opaque.
    """
    columns, single = _columns(relevancy, len(gaussians), "relevancy")
    if not np.isfinite(columns).all():
        raise InputError("relevancy", "has NaN or infinite values")
    image = _render_columns(gaussians, camera, columns, config)
    return image[..., 0] if single else image


@dataclass(frozen=True)
class Pick:
    """What lies under one pixel.

    Attributes:
        view: the camera's image stem.
        pixel: ``(x, y)``, column and row.
        gaussian: index of the Gaussian with the largest blending weight at that pixel.
        regions: its region id at levels 0..3 (superpoint, sub-part, part, object).
    """

    view: str
    pixel: tuple[int, int]
    gaussian: int
    regions: tuple[int, int, int, int]

    def region(self, level: int) -> int:
        """The picked region at ``level`` (0..3)."""
        if level not in (0, 1, 2, 3):
            raise InputError("Pick.region", f"level must be in 0..3, got {level}")
        return self.regions[level]


def _pixel_camera(camera: Cameras, x: int, y: int) -> Cameras:
    """A 1×1 camera that sees exactly pixel (x, y) of ``camera``: the principal point moves by
    (−x, −y), so every ray, and hence every blending weight, is the same."""
    Ks = camera.Ks.clone()
    Ks[0, 0, 2] -= x
    Ks[0, 1, 2] -= y
    ones = torch.ones(1, dtype=camera.widths.dtype)
    return Cameras(camera.viewmats, Ks, ones, ones.clone(), camera.names)


def pick(
    field: SemanticField,
    gaussians: Gaussians,
    camera: Cameras,
    pixel: tuple[int, int],
    *,
    config: RasterConfig = RasterConfig(),
    index: PickIndex | None = None,
) -> Pick | None:
    """The Gaussian and regions under ``pixel`` of one view; None where no Gaussian is.

    Only that pixel is rasterized (a 1×1 camera through it), and only the Gaussians that can
    reach it (:meth:`thgs.pick_index.PickIndex.candidates`, a conservative superset), so a pick
    with a prebuilt index costs about the Gaussians near the pixel's ray, not all N. The answer
    is exactly the ``max_id`` of that pixel rendered from all N Gaussians.

    Args:
        field: the semantic field of ``gaussians``.
        gaussians: its N Gaussians.
        camera: one camera (``cameras.select([i])``).
        pixel: ``(x, y)`` integer pixel, inside the image.
        config: rasterization settings.
        index: :meth:`PickIndex.build` of ``gaussians``, kept by callers that pick repeatedly
            (the viewer); None tests every Gaussian against the pixel's ray (O(N), vectorized)
            before rasterizing the few that pass.

    Raises:
        InputError: a field of another size, an index of other Gaussians, several cameras, or a
            pixel outside the image.
    """
    if len(field) != len(gaussians):
        raise InputError(
            "pick", f"the field has {len(field)} Gaussians, the scene {len(gaussians)}"
        )
    x, y = check_pixel(camera, pixel)
    if index is None:
        index = PickIndex.build(gaussians, cell_size=max(len(gaussians), 1))
    candidates = index.candidates(gaussians, camera, (x, y), config=config)
    if candidates.size == 0:
        return None
    near = gaussians.select(torch.from_numpy(candidates).to(gaussians.device))
    zeros = torch.zeros(len(near), 1, dtype=torch.float64, device=gaussians.device)
    out = render(near, _pixel_camera(camera, x, y), zeros, config=config)
    local = int(out.max_id[0, 0])
    if local < 0:
        return None
    gaussian = int(candidates[local])
    regions = tuple(int(v) for v in field.labels[gaussian])
    return Pick(camera.stems[0], (x, y), gaussian, regions)  # type: ignore[arg-type]
