"""thgs: training-free, open-vocabulary, hierarchical scene understanding for Gaussian Splatting.

The public API is what this module exports; submodules starting with an underscore are private.
"""

import importlib
from typing import TYPE_CHECKING

from thgs.errors import InputError, ThgsError
from thgs.provenance import installed_version

if TYPE_CHECKING:
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

_LAZY = {
    **dict.fromkeys(("SemanticField", "load_field", "save_field"), "thgs.field"),
    **dict.fromkeys(("FieldConfig", "build_field"), "thgs.pipeline"),
    **dict.fromkeys(
        (
            "Cameras",
            "Gaussians",
            "Scene",
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
        ),
        "thgs.scene",
    ),
}
"""Public names imported on first use (PEP 562), so that ``import thgs`` and the ``thgs``
command start without torch, and Ctrl-C during start-up is answered as an interruption."""


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'thgs' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})


__version__ = installed_version()

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
