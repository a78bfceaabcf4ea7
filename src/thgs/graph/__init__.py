"""The superpoint graph: KNN edges, SAM-guided reweighting, cut-pursuit partition (design §4.3–4.5).

graph = knn_graph(gaussians, GraphConfig())
pos, neg = edge_counts(graph, views, ReweightConfig())
distances = reweight(graph, pos, neg, ReweightConfig())
superpoints = partition(gaussians, graph, distances, PartitionConfig.lerf())
"""

from thgs.graph.knn import GraphConfig, KnnGraph, knn_graph, nearest_neighbors, search_points
from thgs.graph.partition import PartitionConfig, partition
from thgs.graph.reweight import ReweightConfig, ReweightMode, edge_counts, reweight

__all__ = [
    "GraphConfig",
    "KnnGraph",
    "PartitionConfig",
    "ReweightConfig",
    "ReweightMode",
    "edge_counts",
    "knn_graph",
    "nearest_neighbors",
    "partition",
    "reweight",
    "search_points",
]
