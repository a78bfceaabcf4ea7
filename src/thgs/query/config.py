"""How relevancies become a selection: :class:`QueryConfig`, one setting per selection mode
(the modes: :mod:`thgs.query`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from thgs.choices import SelectionMode
from thgs.errors import InputError

__all__ = [
    "QueryConfig",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class QueryConfig:
    """How relevancies become a selection (see the module docstring).

    Attributes:
        mode: ``"auto"`` (decided per query), ``"paper"`` (the paper's evaluation),
            ``"level"`` or ``"threshold"``.
        levels: auto and paper modes: the levels searched ((1, 2, 3) for auto; the paper pools
            (2, 3): parts and objects).
        per_level: paper mode: regions taken from each pooled level (3).
        keep: paper mode: regions kept from the pool by relevancy (3).
        extent: auto mode: how far below the best region's cosine, as a share of the best's
            lead over the median region (the query's spread), a region may be and still be
            selected (0.1, chosen on synthetic seeds 0–4; docs/query.md).
        hierarchical: auto mode: judge each region against the regions inside it (descend
            from the objects, :func:`select_auto`); False selects every region past the cut
            wherever it is, as thgs did before (nested fields only; others are always flat).
        descend: auto mode: a region past the cut is taken whole unless a region inside it is
            closer to the query by more than this share of the spread.
        siblings: auto mode: when the descent goes into a region's children, those whose best
            cosine (their own or inside them) rises above the region's by at least this share
            of the best child's rise are followed; the others are left out.
        centred: auto mode: read cosines on features centred on the mean feature of the
            scene's selectable regions (renormalized), not on the raw features.
        min_score: auto mode: the query is abstained from when its best region's score, the
            cosine's distance above the scene's null in units of the null's spread (the best
            cosines of the generic :data:`thgs.confidence.NULL_PHRASES`, read the same way), is
            below this. Used when ``min_relevancy`` is None; a scene without a null falls back
            to the space's relevancy threshold (:func:`default_threshold`). 1.3, chosen on
            synthetic seeds 0–4 with ``min_part_score`` and ``part_lead`` (docs/query.md).
        min_part_score: auto mode, hierarchical: the score that is enough (when below
            ``min_score``) for a best region that is a part or sub-part standing out from its
            parent: its cosine above the parent's by at least ``part_lead`` times the null's
            spread. A query matched that specifically is about something there.
        part_lead: see ``min_part_score``.
        level: level and threshold modes: the level searched (1 sub-parts, 2 parts, 3 objects).
        top: level mode: how many regions (1).
        threshold: threshold mode only: the relevancy a region needs (None:
            :func:`default_threshold` of the field's space).
        min_relevancy: auto mode only: if given, the relevancy the best region needs, or the
            query is abstained from, instead of ``min_score``.
        min_gaussians: regions with fewer Gaussians are never selected (0: all may be); None:
            the field's small-region size (``config["merge"]["min_region_gaussians"]``, 20 for
            the LERF preset, 0 if the field does not say). Leftover specks that merging could
            not absorb otherwise win queries on a few lucky views (design §4.6: excluded from
            queries).
        temperature: t of :func:`relevancy` (10).
    """

    mode: SelectionMode = "auto"
    levels: tuple[int, ...] | None = None
    per_level: int = 3
    keep: int = 3
    extent: float = 0.1
    hierarchical: bool = True
    descend: float = 0.05
    siblings: float = 0.6
    centred: bool = True
    min_score: float = 1.3
    min_part_score: float = 1.05
    part_lead: float = 0.5
    level: int = 3
    top: int = 1
    threshold: float | None = None
    min_relevancy: float | None = None
    min_gaussians: int | None = None
    temperature: float = 10.0

    def check(self) -> QueryConfig:
        """Raise :class:`InputError` naming the first invalid setting; return ``self``."""
        if self.mode not in ("auto", "paper", "level", "threshold"):
            raise InputError(
                "QueryConfig.mode",
                f"must be auto, paper, level or threshold, got {self.mode!r}",
            )
        levels = self.searched_levels
        if not levels or any(
            isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k not in (1, 2, 3)
            for k in levels
        ):
            raise InputError("QueryConfig", f"levels must be among 1, 2, 3, got {levels}")
        for name in ("per_level", "keep", "top"):
            if getattr(self, name) < 1:
                raise InputError(f"QueryConfig.{name}", f"must be ≥ 1, got {getattr(self, name)}")
        for name, mode in (("threshold", "threshold"), ("min_relevancy", "auto")):
            value = getattr(self, name)
            if value is None:
                continue
            if not 0.0 <= value <= 1.0:
                raise InputError(f"QueryConfig.{name}", f"must be in [0, 1], got {value}")
            if self.mode != mode:
                raise InputError(
                    f"QueryConfig.{name}",
                    f"only the {mode} mode reads it, not the {self.mode} mode",
                )
        if self.min_gaussians is not None and self.min_gaussians < 0:
            raise InputError("QueryConfig.min_gaussians", f"must be ≥ 0, got {self.min_gaussians}")
        if not self.temperature > 0:
            raise InputError("QueryConfig.temperature", f"must be > 0, got {self.temperature}")
        if not 0.0 <= self.extent < 1.0:
            raise InputError("QueryConfig.extent", f"must be in [0, 1), got {self.extent}")
        if not 0.0 <= self.descend:
            raise InputError("QueryConfig.descend", f"must be ≥ 0, got {self.descend}")
        if not 0.0 <= self.siblings <= 1.0:
            raise InputError("QueryConfig.siblings", f"must be in [0, 1], got {self.siblings}")
        for name in ("min_score", "min_part_score"):
            if not np.isfinite(getattr(self, name)):
                raise InputError(
                    f"QueryConfig.{name}", f"must be a number, got {getattr(self, name)}"
                )
        if not 0.0 <= self.part_lead < np.inf:
            raise InputError("QueryConfig.part_lead", f"must be a number ≥ 0, got {self.part_lead}")
        return self

    @property
    def searched_levels(self) -> tuple[int, ...]:
        """The levels whose relevancies this mode reads."""
        if self.mode in ("level", "threshold"):
            return (self.level,)
        if self.levels is not None:
            return tuple(self.levels)
        return (1, 2, 3) if self.mode == "auto" else (2, 3)
