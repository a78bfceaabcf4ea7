"""Progressive merging of superpoints into sub-parts, parts and objects (design §4.6).

merged = merge_levels(gaussians, superpoints, lifted, MergeConfig.lerf())
merged.labels     # [N, 4] int32 region per Gaussian at levels 0–3
merged.parents    # per level, the parent region of each region
merged = group_repeated_parts(gaussians, merged, part_features)   # a table's legs: one part
"""

from thgs.hierarchy.adjacency import UnitGraph, coarsened_graph, gaussian_neighbors, unit_graph
from thgs.hierarchy.affinity import MaskEvidence, Source, mask_evidence, pair_affinity
from thgs.hierarchy.merge import (
    MergeConfig,
    MergedLevels,
    merge_levels,
    parents_of,
    renumber_by_units,
)
from thgs.hierarchy.repeats import RepeatConfig, group_repeated_parts, repeated_part_pairs

__all__ = [
    "MaskEvidence",
    "MergeConfig",
    "MergedLevels",
    "RepeatConfig",
    "Source",
    "UnitGraph",
    "coarsened_graph",
    "gaussian_neighbors",
    "group_repeated_parts",
    "mask_evidence",
    "merge_levels",
    "pair_affinity",
    "parents_of",
    "renumber_by_units",
    "repeated_part_pairs",
    "unit_graph",
]
