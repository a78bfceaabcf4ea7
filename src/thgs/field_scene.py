"""A semantic field together with the scene it was built on.

A field file holds labels and features, not geometry; drawing masks, picking pixels or exporting
PLYs also needs the Gaussians and the cameras. ``thgs build`` and ``thgs demo`` record how they
loaded the scene in the field's provenance (:class:`thgs.provenance.SceneRecord`: the path and
the loader's arguments); :func:`open_field_scene` reads the field, reloads that scene (or the one
given) and checks that it is the same scene by its fingerprint.

A field whose features came from a local model folder also records that folder
(:func:`record_text_model`), so that :func:`field_text_encoder` encodes queries with it without
being told again.
"""

from __future__ import annotations

import logging
import os
from dataclasses import replace
from pathlib import Path

import torch

from thgs.device import resolve_device
from thgs.errors import InputError
from thgs.field import SemanticField, load_field, scene_fingerprint
from thgs.provenance import SceneRecord
from thgs.scene import Cameras, Scene, load_scene
from thgs.text import TextEncoder, load_text_encoder

__all__ = [
    "field_text_encoder",
    "find_view",
    "open_field_scene",
    "record_scene",
    "record_text_model",
]

logger = logging.getLogger(__name__)


def record_scene(
    field: SemanticField,
    path: str | os.PathLike[str],
    *,
    source: str | os.PathLike[str] | None = None,
    iteration: int | None = None,
    images: str | None = None,
    scale: float = 1.0,
    field_path: str | os.PathLike[str] | None = None,
) -> SemanticField:
    """``field`` with how to reload its scene in its provenance (``provenance.scene``).

    With ``field_path`` (where the field will be written), the scene's paths are stored relative
    to the field's folder, so that a field and its scene moved or copied together still find
    each other, and the same build in another folder writes the same bytes; without it they are
    stored absolute. Either way the field can be used from any working folder.
    """

    def stored(value: str | os.PathLike[str]) -> str:
        resolved = Path(value).resolve()
        if field_path is None:
            return str(resolved)
        return os.path.relpath(resolved, Path(field_path).resolve().parent)

    record = SceneRecord(
        stored(path),
        source=None if source is None else stored(source),
        iteration=None if iteration is None else int(iteration),
        images=images,
        scale=float(scale),
    )
    return replace(field, provenance=replace(field.provenance, scene=record))


def open_field_scene(
    field_path: str | os.PathLike[str],
    scene: str | os.PathLike[str] | None = None,
    *,
    source: str | os.PathLike[str] | None = None,
    iteration: int | None = None,
    images: str | None = None,
    scale: float = 1.0,
    device: torch.device | str = "cpu",
) -> tuple[SemanticField, Scene]:
    """Load a field and the scene it was built on.

    Args:
        field_path: the field file.
        scene: the scene folder or PLY; default the one recorded in the field. When given, the
            other arguments are :func:`thgs.scene.load_scene`'s; otherwise the recorded ones.
        device: where the scene's Gaussians are put (after the fingerprint check); a name for
            :func:`thgs.device.resolve_device` or a torch device.

    Raises:
        InputError: the field records no scene and none is given, the scene cannot be loaded,
            or its Gaussians are not the ones the field was built on (fingerprint mismatch).
    """
    field_path = Path(field_path)
    field = load_field(field_path)
    if scene is None:
        record = field.provenance.scene
        if record is None:
            raise InputError(
                field_path,
                "records no scene (built by an older thgs?); pass the scene with --scene",
            )
        # relative paths are relative to the field's folder (joining keeps absolute ones)
        folder = field_path.resolve().parent
        scene = folder / record.path
        source = None if record.source is None else folder / record.source
        iteration, images, scale = record.iteration, record.images, record.scale
        if not Path(scene).exists():
            raise InputError(
                field_path,
                f"was built on {scene}, which no longer exists; pass the scene with --scene",
            )
    loaded = load_scene(scene, source=source, iteration=iteration, images=images, scale=scale)
    if len(loaded.gaussians) != len(field):
        raise InputError(
            field_path,
            f"has {len(field)} Gaussians but the scene {loaded.ply_path} has "
            f"{len(loaded.gaussians)}: it was built on another scene",
        )
    if scene_fingerprint(loaded.gaussians) != field.fingerprint:
        raise InputError(
            field_path,
            f"was built on other Gaussians than those in {loaded.ply_path} (fingerprints differ: "
            "moved, reordered or retrained); rebuild the field for this scene",
        )
    logger.info("opened field %s on scene %s", field_path, loaded.ply_path)
    return field, loaded.to(resolve_device(device))


def find_view(cameras: Cameras | None, name: str, source: str | os.PathLike[str]) -> int:
    """Index of the camera whose stem or name is ``name``.

    Raises:
        InputError: no cameras, or no camera of that name (the message lists some).
    """
    if cameras is None:
        raise InputError(source, "the scene has no cameras")
    for i, (stem, full) in enumerate(zip(cameras.stems, cameras.names)):
        if name in (stem, full):
            return i
    shown = ", ".join(cameras.stems[:8]) + (", …" if len(cameras) > 8 else "")
    raise InputError(source, f"no view named {name!r} (views: {shown})")


def record_text_model(field: SemanticField, model: str | os.PathLike[str] | None) -> SemanticField:
    """``field`` with the local folder of its features' model in its provenance
    (``provenance.text_model``) as an absolute path (models stay where they are when fields are
    moved); None stores nothing.

    Raises:
        InputError: ``model`` is not a folder.
    """
    if model is None:
        return field
    folder = Path(model).expanduser().resolve()
    if not folder.is_dir():
        raise InputError(folder, "text model folder not found")
    return replace(field, provenance=replace(field.provenance, text_model=str(folder)))


def field_text_encoder(
    field: SemanticField,
    field_path: str | os.PathLike[str],
    text_model: str | os.PathLike[str] | None = None,
    *,
    device: str = "cpu",
) -> TextEncoder:
    """The text encoder of a field's embedding space.

    The model is read from ``text_model`` if given (``--text-model``), else from the folder the
    field records (:func:`record_text_model`), else from the space's default location
    (:func:`thgs.text.load_text_encoder`: the Hugging Face cache, or the MiniLM package).

    Raises:
        InputError: the recorded folder no longer exists (the message names ``--text-model``),
            or the record is not a path.
        ThgsError: the model cannot be loaded (:func:`thgs.text.load_text_encoder`).
    """
    if text_model is None:
        recorded = field.provenance.text_model
        if recorded is not None:
            if not recorded.strip():
                raise InputError(field_path, f"provenance.text_model is not a path: {recorded!r}")
            if not Path(recorded).is_dir():
                raise InputError(
                    field_path,
                    f"its features came from the text model in {recorded}, which no longer "
                    "exists; pass the model's folder with --text-model DIR",
                )
            text_model = recorded
    logger.info("text model for %s: %s", field_path, text_model or field.space)
    return load_text_encoder(field.space, model_path=text_model, device=device)
