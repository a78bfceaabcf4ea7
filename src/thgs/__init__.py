"""thgs: training-free, open-vocabulary, hierarchical scene understanding for Gaussian Splatting.

The public API is what this module exports; submodules starting with an underscore are private.
"""

from importlib.metadata import PackageNotFoundError, version

from thgs.errors import InputError, ThgsError
from thgs.field import SemanticField, load_field, save_field
from thgs.pipeline import FieldConfig, build_field
from thgs.scene import (
    Cameras,
    Gaussians,
    Scene,
    load_cameras,
    load_scene,
    read_cameras_json,
    read_colmap,
    read_ply,
    read_transforms_json,
    summarize,
    write_cameras_json,
    write_colmap,
    write_ply,
    write_transforms_json,
)

try:
    __version__ = version("thgs")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

__all__ = [
    "Cameras",
    "FieldConfig",
    "Gaussians",
    "InputError",
    "Scene",
    "SemanticField",
    "ThgsError",
    "__version__",
    "build_field",
    "load_cameras",
    "load_field",
    "load_scene",
    "read_cameras_json",
    "read_colmap",
    "read_ply",
    "read_transforms_json",
    "save_field",
    "summarize",
    "write_cameras_json",
    "write_colmap",
    "write_ply",
    "write_transforms_json",
]
