"""Build from the splat alone: virtual cameras placed around a Gaussian Splatting scene that came
without its photos, their renders, and guidance made on the renders (docs/build.md, "From the
splat alone").

- :mod:`thgs.splat_views.placement` — where the cameras go (the model's own cameras or an orbit,
  then close-ups of what they leave unseen);
- :mod:`thgs.splat_views.folder` — the views folder on disk (cameras, renders), resumable;
- :mod:`thgs.splat_views.guidance` — SAM and CLIP on the renders, or the synthetic oracle;
- :mod:`thgs.splat_views.prepare` — all of it in one call, before a build.
"""

from thgs.splat_views.folder import (
    VIEWS_RECORD,
    ViewsFolder,
    open_views_folder,
    render_view,
    render_views,
)
from thgs.splat_views.guidance import (
    GuidanceSource,
    ModelGuidance,
    OracleGuidance,
    make_views_guidance,
    read_dataset_oracle,
)
from thgs.splat_views.placement import (
    Placement,
    PlacementConfig,
    SceneFrame,
    close_up_cameras,
    look_at,
    orbit_cameras,
    place_cameras,
    scene_frame,
    visibility_counts,
)
from thgs.splat_views.prepare import (
    SplatViews,
    SplatViewsRequest,
    default_views_folder,
    prepare_splat_views,
)

__all__ = [
    "VIEWS_RECORD",
    "GuidanceSource",
    "ModelGuidance",
    "OracleGuidance",
    "Placement",
    "PlacementConfig",
    "SceneFrame",
    "SplatViews",
    "SplatViewsRequest",
    "ViewsFolder",
    "close_up_cameras",
    "default_views_folder",
    "look_at",
    "make_views_guidance",
    "open_views_folder",
    "orbit_cameras",
    "place_cameras",
    "prepare_splat_views",
    "read_dataset_oracle",
    "render_view",
    "render_views",
    "scene_frame",
    "visibility_counts",
]
