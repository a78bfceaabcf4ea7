"""Evaluation: benchmark label formats and segmentation scores (protocols arrive with the eval
stage)."""

from thgs.eval.lerf_ovs import FrameLabels, LabelledObject, read_lerf_labels, write_lerf_labels
from thgs.eval.metrics import best_iou, matched_miou, purity
from thgs.eval.polygons import mask_to_polygons, rasterize_polygon
from thgs.eval.scannet import (
    SCANNET10_IDS,
    SCANNET15_IDS,
    SCANNET19_IDS,
    SCANNET19_NAMES,
    PointLabels,
    read_scannet_labels,
    scannet_classes_path,
    write_scannet_labels,
)
from thgs.eval.three_dovs import (
    QUERY_SUBSTITUTIONS,
    SegmentationSet,
    query_text,
    read_3dovs_segmentations,
    write_3dovs_segmentations,
)

__all__ = [
    "QUERY_SUBSTITUTIONS",
    "SCANNET10_IDS",
    "SCANNET15_IDS",
    "SCANNET19_IDS",
    "SCANNET19_NAMES",
    "FrameLabels",
    "LabelledObject",
    "PointLabels",
    "SegmentationSet",
    "best_iou",
    "mask_to_polygons",
    "matched_miou",
    "purity",
    "query_text",
    "rasterize_polygon",
    "read_3dovs_segmentations",
    "read_lerf_labels",
    "read_scannet_labels",
    "scannet_classes_path",
    "write_3dovs_segmentations",
    "write_lerf_labels",
    "write_scannet_labels",
]
