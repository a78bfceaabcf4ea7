"""2D guidance: multi-level masks and per-mask features, in LangSplat's file layout."""

from thgs.guidance.langsplat import (
    EMBEDDING_FILE,
    LEVELS,
    GuidanceFolder,
    ViewGuidance,
    check_masks,
    guidance_folder,
    guidance_space,
    load_guidance,
    read_embedding_model,
    read_embedding_space,
    read_view_guidance,
    resample_segments,
    write_embedding_space,
    write_view_guidance,
)

__all__ = [
    "EMBEDDING_FILE",
    "LEVELS",
    "GuidanceFolder",
    "ViewGuidance",
    "check_masks",
    "guidance_folder",
    "guidance_space",
    "load_guidance",
    "read_embedding_model",
    "read_embedding_space",
    "read_view_guidance",
    "resample_segments",
    "write_embedding_space",
    "write_view_guidance",
]
