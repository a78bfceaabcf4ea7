"""thgs: training-free, open-vocabulary, hierarchical scene understanding for Gaussian Splatting.

The public API is what this module exports; submodules starting with an underscore are private.
"""

from importlib.metadata import PackageNotFoundError, version

from thgs.errors import InputError, ThgsError
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
    "Gaussians",
    "InputError",
    "Scene",
    "ThgsError",
    "__version__",
    "load_cameras",
    "load_scene",
    "read_cameras_json",
    "read_colmap",
    "read_ply",
    "read_transforms_json",
    "summarize",
    "write_cameras_json",
    "write_colmap",
    "write_ply",
    "write_transforms_json",
]
