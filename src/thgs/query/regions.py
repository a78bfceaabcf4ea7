"""The regions a query runs on: :class:`Regions` (levels that need not nest, with features),
built from a field or from any other partition, and the field's small-region size.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from thgs._config_json import config_from_json
from thgs.errors import InputError
from thgs.field import SemanticField
from thgs.hierarchy import MergeConfig
from thgs.hierarchy.levels import RegionLevels

__all__ = [
    "Regions",
    "small_region_size",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Regions:
    """What queries read of a segmentation: regions of N Gaussians at levels 1–3 with their
    features; the levels need not nest (the "no progressive merging" ablation's do not).

    Attributes:
        levels: the regions (:class:`thgs.hierarchy.RegionLevels`, nested or not).
        features: level k = 1..3 at index k − 1: [R_k, D] unit features (zero rows unseen).
        seen: level k at index k − 1: [R_k] bool, whether any view saw the region.
        space: the features' embedding space.
        min_region_gaussians: regions with fewer Gaussians are never selected (the field's
            small-region size; 0 selects every region).
    """

    levels: RegionLevels
    features: tuple[np.ndarray, np.ndarray, np.ndarray]
    seen: tuple[np.ndarray, np.ndarray, np.ndarray]
    space: str
    min_region_gaussians: int = 0

    @classmethod
    def from_field(cls, field: SemanticField) -> Regions:
        """A field's regions, with its small-region size (:func:`small_region_size`)."""
        return cls(field.levels, field.features, field.seen, field.space, small_region_size(field))

    def __len__(self) -> int:
        return len(self.levels)

    @property
    def labels(self) -> np.ndarray:
        """[N, 4] int32: ``labels[i, k]`` is the level-k region of Gaussian i."""
        return self.levels.labels

    @property
    def dim(self) -> int:
        """D, the length of a feature vector."""
        return int(self.features[0].shape[1])

    def sizes(self, level: int) -> np.ndarray:
        """[R_level] int64: the number of Gaussians in each region of ``level`` (1..3)."""
        return self.levels.sizes(self.checked_level(level))

    def checked_level(self, level: int) -> int:
        """``level`` as an int after checking that it is 1, 2 or 3 (the levels with features).

        Raises:
            InputError: anything else.
        """
        return self.levels.checked_level(level, range(1, 4))

    def checked_region(self, level: int, region: int) -> int:
        """``region`` as an int after checking that it is a region id of ``level`` (1..3).

        Raises:
            InputError: not an integer, or not in 0..R_level − 1.
        """
        return self.levels.checked_region(self.checked_level(level), region)

    def check(self, source: str = "Regions") -> Regions:
        """Verify the levels (:meth:`RegionLevels.check`) and that every level 1–3 has one
        [R_k, D] feature row and one seen flag per region, with one D; raise
        :class:`InputError` naming ``source``."""
        if not isinstance(self.levels, RegionLevels):
            raise InputError(source, f"levels must be RegionLevels, got {type(self.levels)}")
        self.levels.check(source)
        dims = set()
        for k in (1, 2, 3):
            features, seen = self.features[k - 1], self.seen[k - 1]
            count = self.levels.counts[k]
            if features.ndim != 2 or features.shape[0] != count or seen.shape != (count,):
                raise InputError(
                    source,
                    f"level {k}: features {list(features.shape)} and seen {list(seen.shape)} "
                    f"must be [R, D] and [R] with R = {count} regions",
                )
            dims.add(features.shape[1])
        if len(dims) != 1:
            raise InputError(source, f"levels have different feature dimensions {sorted(dims)}")
        return self


def small_region_size(field: SemanticField) -> int:
    """The field's ``thres_merge`` (its recorded :class:`thgs.hierarchy.MergeConfig`'s
    ``min_region_gaussians``): regions below it are unabsorbed leftovers. 0 (every region
    selectable) when the field records no merge settings or ones this thgs cannot read (logged)."""
    if "merge" not in field.config:
        return 0
    try:
        merge = config_from_json(MergeConfig, field.config["merge"], "field config: merge")
    except InputError as error:
        logger.warning("%s; every region may be selected", error)
        return 0
    return merge.min_region_gaussians
