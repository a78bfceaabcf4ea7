"""Progressive merging of superpoints into sub-parts, parts and objects (design §4.6).

merged = merge_levels(gaussians, superpoints, lifted, MergeConfig.lerf())
merged.labels     # [N, 4] int32 region per Gaussian at levels 0–3
merged.parents    # per level, the parent region of each region
"""

from thgs.hierarchy.adjacency import UnitGraph, gaussian_neighbors, unit_graph
from thgs.hierarchy.merge import MergeConfig, MergedLevels, merge_levels, pair_affinity

__all__ = [
    "MergeConfig",
    "MergedLevels",
    "UnitGraph",
    "gaussian_neighbors",
    "merge_levels",
    "pair_affinity",
    "unit_graph",
]
