"""Evaluation data: benchmark label formats (metrics and protocols arrive with the eval stage)."""

from thgs.eval.lerf_ovs import FrameLabels, LabelledObject, read_lerf_labels
from thgs.eval.polygons import rasterize_polygon

__all__ = ["FrameLabels", "LabelledObject", "rasterize_polygon", "read_lerf_labels"]
