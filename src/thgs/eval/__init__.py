"""Evaluation: benchmark label formats, scoring rules, and the protocols run on a scene
(``thgs eval``; docs/eval.md)."""

from thgs.eval.dataset import (
    EvalReport,
    GroundTruth,
    evaluate_dataset,
    find_ground_truth,
    mean_over_scenes,
)
from thgs.eval.evaluate import (
    ProtocolResult,
    evaluate_3dovs,
    evaluate_hierarchy,
    evaluate_lerf,
    evaluate_lerf_langsplat,
    evaluate_lerf_opengaussian,
    evaluate_openhype,
    evaluate_scannet,
    read_lerf_frames,
)
from thgs.eval.ground_truth import Hierarchy, read_hierarchy
from thgs.eval.lerf_ovs import FrameLabels, LabelledObject, read_lerf_labels, write_lerf_labels
from thgs.eval.metrics import best_iou, matched_miou, purity
from thgs.eval.openhype import (
    OpenHypeFrame,
    OpenHypeObject,
    read_openhype_annotations,
    write_openhype_annotations,
)
from thgs.eval.polygons import mask_to_polygons, rasterize_polygon
from thgs.eval.protocols import Protocol, protocol_names, register_protocol
from thgs.eval.rules import (
    OPENGAUSSIAN_LERF_PROMPTS,
    OPENGAUSSIAN_THRESHOLD,
    ClassScores,
    langsplat_level,
    langsplat_localized,
    langsplat_mask,
    mask_iou,
    openhype_localized,
    pixel_accuracy,
    scannet_scores,
)
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
    "OPENGAUSSIAN_LERF_PROMPTS",
    "OPENGAUSSIAN_THRESHOLD",
    "QUERY_SUBSTITUTIONS",
    "SCANNET10_IDS",
    "SCANNET15_IDS",
    "SCANNET19_IDS",
    "SCANNET19_NAMES",
    "ClassScores",
    "EvalReport",
    "FrameLabels",
    "GroundTruth",
    "Hierarchy",
    "LabelledObject",
    "OpenHypeFrame",
    "OpenHypeObject",
    "PointLabels",
    "Protocol",
    "ProtocolResult",
    "SegmentationSet",
    "best_iou",
    "evaluate_3dovs",
    "evaluate_dataset",
    "evaluate_hierarchy",
    "evaluate_lerf",
    "evaluate_lerf_langsplat",
    "evaluate_lerf_opengaussian",
    "evaluate_openhype",
    "evaluate_scannet",
    "find_ground_truth",
    "langsplat_level",
    "langsplat_localized",
    "langsplat_mask",
    "mask_iou",
    "mask_to_polygons",
    "matched_miou",
    "mean_over_scenes",
    "openhype_localized",
    "pixel_accuracy",
    "protocol_names",
    "purity",
    "query_text",
    "rasterize_polygon",
    "read_3dovs_segmentations",
    "read_hierarchy",
    "read_lerf_frames",
    "read_lerf_labels",
    "read_openhype_annotations",
    "read_scannet_labels",
    "register_protocol",
    "scannet_classes_path",
    "scannet_scores",
    "write_3dovs_segmentations",
    "write_lerf_labels",
    "write_openhype_annotations",
    "write_scannet_labels",
]
