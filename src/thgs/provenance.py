"""Where a semantic field came from, kept beside its build config and read back typed.

A field file's metadata holds the build settings (``config``) and, beside them, its
``provenance``: how to reload the scene it was built on (:class:`SceneRecord`), the local folder
of its features' text model, and the thgs that built it. :func:`thgs.field.load_field` returns
it as a :class:`Provenance`; fields written before the record had its own place (format
versions 1–3 kept the scene and the text model as ``config["scene"]`` and
``config["text_model"]``) are read into the same record, with the thgs version unknown.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from thgs.errors import InputError

__all__ = ["Provenance", "SceneRecord", "installed_version"]


def installed_version() -> str:
    """This thgs's version (``thgs.__version__``): the installed distribution's, or
    ``0.0.0+unknown`` when running from a source tree that was never installed."""
    try:
        return version("thgs")
    except PackageNotFoundError:
        return "0.0.0+unknown"


@dataclass(frozen=True)
class SceneRecord:
    """How to reload the scene a field was built on (:func:`thgs.scene.load_scene`'s arguments).

    Attributes:
        path: the model folder or PLY, relative to the field file's folder (or absolute).
        source: the training data folder or camera file, likewise; None: the model's own.
        iteration: the model's ``iteration_*`` (None: the newest).
        images: the image folder's name inside the source (None: ``images``).
        scale: image size / camera-file size.
    """

    path: str
    source: str | None = None
    iteration: int | None = None
    images: str | None = None
    scale: float = 1.0

    def to_json(self) -> dict[str, Any]:
        """The record as JSON, with only the arguments that are not their default (the layout
        fields have always been written in)."""
        record: dict[str, Any] = {"path": self.path}
        if self.source is not None:
            record["source"] = self.source
        if self.iteration is not None:
            record["iteration"] = self.iteration
        if self.images is not None:
            record["images"] = self.images
        if self.scale != 1.0:
            record["scale"] = self.scale
        return record

    @classmethod
    def from_json(cls, value: Any, where: str) -> SceneRecord:
        """Read :meth:`to_json`'s output.

        Raises:
            InputError: naming ``where`` and the entry that is not what it must be.
        """
        if not isinstance(value, dict) or not isinstance(value.get("path"), str):
            raise InputError(where, "the scene record must be an object with a 'path' string")
        unknown = sorted(set(value) - {"path", "source", "iteration", "images", "scale"})
        if unknown:
            raise InputError(where, f"the scene record has unknown entries {unknown}")
        source, iteration, images = (value.get(key) for key in ("source", "iteration", "images"))
        scale = value.get("scale", 1.0)
        problem = None
        if source is not None and not isinstance(source, str):
            problem = f"source must be a path, got {source!r}"
        elif iteration is not None and (
            isinstance(iteration, bool) or not isinstance(iteration, int)
        ):
            problem = f"iteration must be an integer, got {iteration!r}"
        elif images is not None and not isinstance(images, str):
            problem = f"images must be a folder name, got {images!r}"
        elif isinstance(scale, bool) or not isinstance(scale, (int, float)):
            problem = f"scale must be a number, got {scale!r}"
        elif not (math.isfinite(scale) and scale > 0):
            problem = f"scale must be > 0, got {scale!r}"
        if problem is not None:
            raise InputError(where, f"the scene record's {problem}")
        return cls(value["path"], source, iteration, images, float(scale))


@dataclass(frozen=True)
class Provenance:
    """Where a field came from.

    Attributes:
        scene: how to reload its scene; None: not recorded (a field built in memory and not yet
            given one, or by an old thgs).
        text_model: the absolute path of its features' local model folder; None: the space's
            default location (the Hugging Face cache or the MiniLM package).
        thgs_version: the thgs that built it; None: unknown (fields written before format
            version 4).
    """

    scene: SceneRecord | None = None
    text_model: str | None = None
    thgs_version: str | None = None

    def to_json(self) -> dict[str, Any]:
        """The record as JSON (the field file's ``provenance`` metadata)."""
        return {
            "scene": None if self.scene is None else self.scene.to_json(),
            "text_model": self.text_model,
            "thgs_version": self.thgs_version,
        }

    @classmethod
    def from_json(cls, value: Any, where: str) -> Provenance:
        """Read :meth:`to_json`'s output.

        Raises:
            InputError: naming ``where`` and the entry that is not what it must be.
        """
        if not isinstance(value, dict):
            raise InputError(where, f"provenance must be an object, got {type(value).__name__}")
        unknown = sorted(set(value) - {"scene", "text_model", "thgs_version"})
        if unknown:
            raise InputError(where, f"provenance has unknown entries {unknown}")
        for key in ("text_model", "thgs_version"):
            if value.get(key) is not None and not isinstance(value[key], str):
                raise InputError(where, f"provenance's {key} must be a string, got {value[key]!r}")
        scene = value.get("scene")
        return cls(
            scene=None if scene is None else SceneRecord.from_json(scene, where),
            text_model=value.get("text_model"),
            thgs_version=value.get("thgs_version"),
        )

    @classmethod
    def from_old_config(
        cls, config: dict[str, Any], where: str
    ) -> tuple[Provenance, dict[str, Any]]:
        """Split a format-1–3 field's config into its provenance (``"scene"``,
        ``"text_model"``) and the build config proper.

        Raises:
            InputError: a record that is not what it must be, naming ``where``.
        """
        scene, model = config.get("scene"), config.get("text_model")
        if model is not None and not isinstance(model, str):
            raise InputError(where, f"the recorded text model must be a path, got {model!r}")
        rest = {key: value for key, value in config.items() if key not in ("scene", "text_model")}
        record = cls(
            scene=None if scene is None else SceneRecord.from_json(scene, where), text_model=model
        )
        return record, rest
