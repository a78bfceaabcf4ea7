"""Progressive merging of superpoints into sub-parts, parts and objects (design §4.6), and
the one hierarchy type every stage shares.

merged = merge_levels(gaussians, superpoints, lifted, MergeConfig.lerf())
merged.levels.labels     # [N, 4] int32 region per Gaussian at levels 0–3 (RegionLevels)
merged.levels.parents    # per level, the parent region of each region
levels = group_repeated_parts(gaussians, merged.levels, part_features)   # a table's legs: one part
"""

from thgs.hierarchy.adjacency import UnitGraph, coarsened_graph, gaussian_neighbors, unit_graph
from thgs.hierarchy.affinity import MaskEvidence, Source, mask_evidence, pair_affinity
from thgs.hierarchy.coherence import split_incoherent
from thgs.hierarchy.levels import LEVEL_NAMES, RegionLevels
from thgs.hierarchy.merge import MergeConfig, MergeResult, merge_levels, renumber_by_units
from thgs.hierarchy.repeats import (
    RepeatConfig,
    group_repeated_parts,
    repeated_part_pairs,
    residual_part_features,
)

__all__ = [
    "LEVEL_NAMES",
    "MaskEvidence",
    "MergeConfig",
    "MergeResult",
    "RegionLevels",
    "RepeatConfig",
    "Source",
    "UnitGraph",
    "coarsened_graph",
    "gaussian_neighbors",
    "group_repeated_parts",
    "mask_evidence",
    "merge_levels",
    "pair_affinity",
    "renumber_by_units",
    "repeated_part_pairs",
    "residual_part_features",
    "split_incoherent",
    "unit_graph",
]
