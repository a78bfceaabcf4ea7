"""2D guidance: multi-level masks and per-mask features, in LangSplat's file layout."""

from thgs.guidance.langsplat import (
    LEVELS,
    ViewGuidance,
    load_guidance,
    read_view_guidance,
    resample_segments,
    write_view_guidance,
)

__all__ = [
    "LEVELS",
    "ViewGuidance",
    "load_guidance",
    "read_view_guidance",
    "resample_segments",
    "write_view_guidance",
]
