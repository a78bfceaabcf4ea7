"""What the viewer shows and does, without a browser.

:class:`ViewerState` holds one semantic field with its scene and the current *highlight*: the
regions a text query selected, or the region a click picked. It answers everything the GUI asks
through the library's public API (:class:`thgs.query.FieldQuery`, :func:`thgs.views.pick` with
the scene's :class:`thgs.pick_index.PickIndex`, :func:`thgs.render.render`,
:func:`thgs.export.write_selection`) and never touches viser, so it is unit-tested on its own.

Levels are the field's: 1 sub-parts, 2 parts, 3 objects (0, superpoints, is not shown). A
highlight has a *primary* region (its most relevant, or the picked one) from which
:meth:`ViewerState.parent`, :meth:`~ViewerState.child` and :meth:`~ViewerState.sibling` move.
A pick remembers the Gaussian under the click (its *anchor*), so climbing from sub-part to part
to object and back down returns through the regions that contain the clicked point.

Display colours (:meth:`ViewerState.colors`) are the scene's view-independent colours (the SH
DC term), each region's colour, or the last query's relevancy; with a highlight, the Gaussians
outside it are dimmed (colour and opacity scaled down by :class:`ViewerConfig`'s factors) and
those inside keep their colour.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from thgs.choices import SelectionMode
from thgs.errors import InputError
from thgs.export import region_colors, slug, write_selection
from thgs.field import SemanticField
from thgs.hierarchy.levels import LEVEL_NAMES
from thgs.pick_index import PickIndex
from thgs.query import FieldQuery, QueryConfig
from thgs.render import render
from thgs.scene import Cameras, Gaussians
from thgs.views import pick

__all__ = [
    "COLOR_MODES",
    "QUERY_MODES",
    "Highlight",
    "ViewMask",
    "ViewerConfig",
    "ViewerState",
    "relevancy_colors",
]

logger = logging.getLogger(__name__)

QueryMode = SelectionMode
ColorMode = Literal["scene", "regions", "relevancy"]

QUERY_MODES: dict[str, str] = {
    "auto": "the regions named like the query, at their own level, or nothing",
    "paper": "the paper's: top 3 of parts and objects",
    "level": "the best region of the level",
    "threshold": "every region of the level above the threshold",
}
"""The viewer's query modes and what each selects: :class:`thgs.query.QueryConfig`'s modes of
the same names (``thgs query --mode``), ``level`` with ``top=1``."""

COLOR_MODES: dict[str, str] = {
    "scene": "the scene's colours",
    "regions": "one colour per region of the level",
    "relevancy": "the last query's relevancy at the level",
}

# LERF's relevancy colouring: 0.5 (no more like the query than like a generic phrase) and below
# dark blue, 1 dark red, through a turbo-like ramp.
_RAMP = np.array(
    [
        [0.19, 0.07, 0.23],
        [0.12, 0.56, 0.95],
        [0.46, 0.99, 0.35],
        [0.98, 0.73, 0.22],
        [0.48, 0.02, 0.01],
    ]
)


def relevancy_colors(relevancy: np.ndarray) -> np.ndarray:
    """[N, 3] float32 RGB in [0, 1] for [N] relevancies: values ≤ 0.5 the ramp's first colour,
    1 its last, linear in between."""
    t = np.clip((np.asarray(relevancy, dtype=np.float64) - 0.5) / 0.5, 0.0, 1.0)
    stops = np.linspace(0.0, 1.0, len(_RAMP))
    return np.stack([np.interp(t, stops, _RAMP[:, c]) for c in range(3)], axis=1).astype(np.float32)


@dataclass(frozen=True)
class ViewerConfig:
    """Settings of ``thgs view``.

    Attributes:
        level: the level shown first (1 sub-parts, 2 parts, 3 objects).
        mode: how a query selects (:data:`QUERY_MODES`).
        threshold: the relevancy the ``threshold`` mode needs; None: the embedding space's
            default (:func:`thgs.query.default_threshold`).
        color: the colouring shown first (:data:`COLOR_MODES`).
        dim_color: factor on the colour of Gaussians outside a highlight (0 black, 1 unchanged).
        dim_opacity: factor on their opacity, so that the highlight shows through.
        ranking: how many regions a query lists with their relevancy.
        mask_height: the 2D mask of a view is rendered at most this many pixels tall (the
            viewport's aspect kept).
        chunk_size: Gaussians per splat node; a colour change re-sends only the nodes whose
            colours changed (docs/viewer.md).
        seed: of the region colours (as ``thgs export --color-level``).
    """

    level: int = 3
    mode: QueryMode = "auto"
    threshold: float | None = None
    color: ColorMode = "scene"
    dim_color: float = 0.3
    dim_opacity: float = 0.1
    ranking: int = 5
    mask_height: int = 480
    chunk_size: int = 65536
    seed: int = 0

    def check(self) -> ViewerConfig:
        """Raise :class:`InputError` naming the first invalid setting; return ``self``."""
        if self.level not in (1, 2, 3):
            raise InputError("ViewerConfig.level", f"must be 1, 2 or 3, got {self.level}")
        if self.mode not in QUERY_MODES:
            raise InputError("ViewerConfig.mode", f"must be one of {list(QUERY_MODES)}")
        if self.color not in COLOR_MODES:
            raise InputError("ViewerConfig.color", f"must be one of {list(COLOR_MODES)}")
        if self.threshold is not None and not 0.0 <= self.threshold <= 1.0:
            raise InputError("ViewerConfig.threshold", f"must be in [0, 1], got {self.threshold}")
        for name in ("dim_color", "dim_opacity"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InputError(f"ViewerConfig.{name}", "must be in [0, 1]")
        for name in ("ranking", "mask_height", "chunk_size"):
            if getattr(self, name) < 1:
                raise InputError(f"ViewerConfig.{name}", f"must be ≥ 1, got {getattr(self, name)}")
        return self


@dataclass(frozen=True, eq=False)
class Highlight:
    """What is highlighted.

    Attributes:
        kind: ``"query"`` (a text query's selection) or ``"pick"`` (a clicked region, or one
            reached from it through the hierarchy).
        text: the query ("" for picks).
        regions: ``(level, region, relevancy)`` triples, the primary region first; relevancy is
            None for picks. Empty when a query found nothing relevant enough.
        gaussians: [N] bool, the highlighted Gaussians.
        anchor: the picked Gaussian, while the primary region contains it; else None.
        ranking: queries: the ``ViewerConfig.ranking`` most relevant regions of the level shown,
            ``(level, region, relevancy)``, whether selected or not.
        reason: queries that selected nothing in auto mode: why
            (:attr:`thgs.query.Selection.reason`).
        confidence: queries: the calibrated probability that the scene holds what was asked
            (:attr:`thgs.query.Selection.confidence`); None for picks or when unknown.
        region_confidence: queries: ``(level, region)`` → the calibrated probability that the
            region belongs to what was asked, for every ranked or selected region.
    """

    kind: Literal["query", "pick"]
    text: str
    regions: tuple[tuple[int, int, float | None], ...]
    gaussians: np.ndarray
    anchor: int | None = None
    ranking: tuple[tuple[int, int, float], ...] = ()
    reason: str | None = None
    confidence: float | None = None
    region_confidence: Mapping[tuple[int, int], float] = dataclass_field(default_factory=dict)

    @property
    def primary(self) -> tuple[int, int] | None:
        """``(level, region)`` navigation starts from; None when nothing is selected."""
        return self.regions[0][:2] if self.regions else None


@dataclass(frozen=True, eq=False)
class ViewMask:
    """A highlight's 2D mask in one view.

    Attributes:
        mask: [H, W] bool, the highlight's rendered opacity > 0.5, as
            :func:`thgs.views.selection_masks` draws it.
        picture: [H, W, 3] float64 RGB in [0, 1]: the scene's colours over a white background,
            the mask tinted red.
        camera: the one camera it was rendered from.
    """

    mask: np.ndarray
    picture: np.ndarray
    camera: Cameras


class ViewerState:
    """One field and its scene, and what the viewer currently highlights.

    The scene's :class:`PickIndex` (``pick_index``) is built here, once, so that every click
    rasterizes only the Gaussians near the clicked ray (about 0.35 s per million Gaussians on
    2 CPU cores, docs/viewer.md).

    Args:
        field: the semantic field.
        gaussians: the N Gaussians it was built on.
        query: text queries of ``field``; None when no text model is available (picking,
            navigation, colours and exports still work).
        config: the viewer's settings.

    Raises:
        InputError: a field of another size than the scene, or an invalid config.
    """

    def __init__(
        self,
        field: SemanticField,
        gaussians: Gaussians,
        query: FieldQuery | None = None,
        config: ViewerConfig = ViewerConfig(),
    ):
        if len(field) != len(gaussians):
            raise InputError(
                "viewer", f"the field has {len(field)} Gaussians, the scene {len(gaussians)}"
            )
        self.config = config.check()
        self.field = field
        self.gaussians = gaussians
        self.query = query
        self.level = config.level
        self.mode: QueryMode = config.mode
        self.threshold = config.threshold
        self.color: ColorMode = config.color
        self.highlight: Highlight | None = None
        self.last_text: str | None = None
        self._scene_rgb = gaussians.dc_colors().detach().cpu().numpy().astype(np.float32)
        self._opacity = gaussians.activated_opacities().detach().cpu().numpy().astype(np.float32)
        self.pick_index = PickIndex.build(gaussians)

    def __len__(self) -> int:
        return len(self.field)

    # Queries ------------------------------------------------------------------------------------

    def query_config(self) -> QueryConfig:
        """The :class:`QueryConfig` of the current mode, level and threshold."""
        if self.mode in ("auto", "paper"):
            return QueryConfig(mode=self.mode)
        if self.mode == "threshold":
            return QueryConfig(mode="threshold", level=self.level, threshold=self.threshold)
        return QueryConfig(mode="level", level=self.level, top=1)

    def ask(self, text: str) -> Highlight:
        """Highlight what ``text`` selects in the current mode.

        Raises:
            InputError: no text model, or an empty text.
        """
        if self.query is None:
            raise InputError("query", "no text model is loaded, so text queries are off")
        text = text.strip()
        if not text:
            raise InputError("query", "type something to look for")
        config = self.query_config()
        selection = self.query.select([text], config)[0]
        scores = self.query.relevancy([text], self.level)[0]
        top = np.lexsort((np.arange(scores.size), -scores))[: self.config.ranking]
        ranking = tuple((self.level, int(r), float(scores[r])) for r in top)
        self.last_text = text
        listed = [(level, region) for level, region, _ in (*ranking, *selection.regions)]
        by_level = {k: self.query.confidence([text], k)[0] for k in {k for k, _ in listed}}
        region_confidence = {
            (k, region): float(by_level[k][region])
            for k, region in listed
            if not np.isnan(by_level[k][region])
        }
        self.highlight = Highlight(
            "query",
            text,
            selection.regions,
            selection.gaussians,
            None,
            ranking,
            selection.reason,
            selection.confidence,
            region_confidence,
        )
        logger.info(
            "query %r: %d regions, %d Gaussians",
            text,
            len(selection.regions),
            int(selection.gaussians.sum()),
        )
        return self.highlight

    # Picking and the hierarchy ------------------------------------------------------------------

    def _select_region(self, level: int, region: int, anchor: int | None) -> Highlight:
        if anchor is not None and self.field.labels[anchor, level] != region:
            anchor = None
        self.level = level
        gaussians = self.field.labels[:, level] == region
        self.highlight = Highlight("pick", "", ((level, int(region), None),), gaussians, anchor)
        return self.highlight

    def pick(self, camera: Cameras, pixel: tuple[int, int]) -> Highlight | None:
        """Highlight the region at the current level under ``pixel`` of ``camera``.

        Returns:
            the new highlight, or None (and the highlight unchanged) where no Gaussian is.
        """
        picked = pick(self.field, self.gaussians, camera, pixel, index=self.pick_index)
        if picked is None:
            return None
        return self._select_region(self.level, picked.region(self.level), picked.gaussian)

    def _primary(self, action: str) -> tuple[int, int]:
        primary = self.highlight.primary if self.highlight is not None else None
        if primary is None:
            raise InputError(action, "nothing is selected: ask a query or click on the scene")
        return primary

    def parent(self) -> Highlight:
        """Highlight the region one level up that contains the primary region."""
        level, region = self._primary("parent")
        if level == 3:
            raise InputError("parent", "an object is the top of the hierarchy")
        anchor = self.highlight.anchor if self.highlight is not None else None
        return self._select_region(level + 1, self.field.parent(level, region), anchor)

    def child(self) -> Highlight:
        """Highlight a region one level down inside the primary region: the one containing the
        picked point if there is one, else the largest (lowest id on ties)."""
        level, region = self._primary("child")
        if level == 1:
            raise InputError("child", "sub-parts are the finest level shown")
        children = self.field.children(level, region)
        anchor = self.highlight.anchor if self.highlight is not None else None
        if anchor is not None and self.field.labels[anchor, level - 1] in children:
            chosen = int(self.field.labels[anchor, level - 1])
        else:
            sizes = self.field.sizes(level - 1)[children]
            chosen = int(children[np.lexsort((children, -sizes))[0]])
        return self._select_region(level - 1, chosen, anchor)

    def sibling(self, step: int = 1) -> Highlight:
        """Highlight the region ``step`` places after the primary one among the regions with the
        same parent (among all objects at level 3), in id order, wrapping around."""
        level, region = self._primary("sibling")
        if level == 3:
            siblings = np.arange(self.field.region_counts[3])
        else:
            siblings = self.field.children(level + 1, self.field.parent(level, region))
        position = int(np.searchsorted(siblings, region))
        return self._select_region(level, int(siblings[(position + step) % siblings.size]), None)

    def set_level(self, level: int) -> Highlight | None:
        """Show ``level``; a highlight follows: a query is asked again at that level, a picked
        region becomes its ancestor or descendant there (through the picked point if known)."""
        if level not in (1, 2, 3):
            raise InputError("level", f"must be 1, 2 or 3, got {level}")
        self.level = level
        highlight = self.highlight
        if highlight is None:
            return None
        if highlight.kind == "query":
            return self.ask(highlight.text)
        current = highlight.primary[0]
        while current != level:
            current = (self.parent() if current < level else self.child()).primary[0]
        return self.highlight

    def set_mode(self, mode: QueryMode, threshold: float | None = None) -> Highlight | None:
        """Change how queries select (and the threshold mode's relevancy); a query highlight is
        asked again."""
        replace(self.config, mode=mode, threshold=threshold).check()
        self.mode, self.threshold = mode, threshold
        if self.highlight is not None and self.highlight.kind == "query":
            return self.ask(self.highlight.text)
        return self.highlight

    def set_color(self, color: ColorMode) -> None:
        """Choose the colouring (:data:`COLOR_MODES`)."""
        replace(self.config, color=color).check()
        self.color = color

    def clear(self) -> None:
        """Highlight nothing."""
        self.highlight = None

    # What is drawn ------------------------------------------------------------------------------

    def colors(self) -> tuple[np.ndarray, np.ndarray]:
        """The colours to draw: ``(rgb, opacity)``, [N, 3] and [N] float32 in [0, 1], in the
        scene's order."""
        if self.color == "regions":
            rgb = region_colors(self.field.labels[:, self.level], self.config.seed)
        elif self.color == "relevancy" and self.query is not None and self.last_text is not None:
            rgb = relevancy_colors(self.query.gaussian_relevancy(self.last_text, self.level))
        else:
            rgb = self._scene_rgb
        rgb = np.asarray(rgb, dtype=np.float32).copy()
        opacity = self._opacity.copy()
        if self.highlight is not None:
            outside = ~self.highlight.gaussians
            rgb[outside] *= self.config.dim_color
            opacity[outside] *= self.config.dim_opacity
        return rgb, opacity

    def view_mask(self, camera: Cameras) -> ViewMask:
        """The highlight's 2D mask in ``camera`` (one camera) and a picture of it.

        Raises:
            InputError: nothing is selected.
        """
        if self.highlight is None or not self.highlight.gaussians.any():
            raise InputError("2D mask", "nothing is selected: ask a query or click on the scene")
        features = np.concatenate(
            [self._scene_rgb, self.highlight.gaussians[:, None]], axis=1, dtype=np.float64
        )
        out = render(self.gaussians, camera, torch.from_numpy(features).to(self.gaussians.device))
        image = out.image.detach().cpu().numpy()
        alpha = out.alpha.detach().cpu().numpy()[..., None]
        mask = image[..., 3] > 0.5
        picture = image[..., :3] + (1.0 - alpha)
        tint = np.array([1.0, 0.1, 0.1])
        picture[mask] = 0.45 * picture[mask] + 0.55 * tint
        return ViewMask(mask, np.clip(picture, 0.0, 1.0), camera)

    # Export -------------------------------------------------------------------------------------

    def selection_name(self) -> str:
        """A file name for the highlight: the query's slug, or ``<level>-<region>``."""
        primary = self._primary("export")
        if self.highlight is not None and self.highlight.kind == "query":
            return slug(self.highlight.text)
        return f"{LEVEL_NAMES[primary[0]]}-{primary[1]}"

    def export(self, folder: str | os.PathLike[str]) -> list[Path]:
        """Write the highlighted Gaussians to ``folder`` (:func:`thgs.export.write_selection`):
        ``<name>.ply``, ``<name>-labels.npy``, ``<name>-indices.npy``, ``<name>.json``.

        Raises:
            InputError: nothing selected, or a folder that cannot be written.
        """
        name = self.selection_name()
        highlight = self.highlight
        assert highlight is not None
        description = {
            "kind": highlight.kind,
            "text": highlight.text,
            "regions": [
                {"level": level, "name": LEVEL_NAMES[level], "region": region, "relevancy": score}
                for level, region, score in highlight.regions
            ],
            "space": self.field.space,
        }
        paths = write_selection(
            folder, name, self.gaussians, self.field, highlight.gaussians, description
        )
        logger.info("exported %d Gaussians to %s", int(highlight.gaussians.sum()), folder)
        return paths
