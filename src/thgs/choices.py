"""The names a user chooses from, in one place: field presets, synthetic scene presets and
devices, as tuples and as the ``Literal`` types the command line offers them with. No heavy
imports, so that every command can type its options with them; the registries that give each
name its meaning (:data:`thgs.pipeline.PRESETS`, :data:`thgs.synthetic.PRESETS`,
:func:`thgs.device.resolve_device`) are tested to hold exactly these names.
"""

from __future__ import annotations

from typing import Literal

__all__ = ["DEVICES", "FIELD_PRESETS", "SCENE_PRESETS", "Device", "FieldPreset", "ScenePreset"]

FIELD_PRESETS = ("lerf", "3dovs")
"""``thgs build --preset`` and ``thgs suite --preset``: the reference's LERF-OVS and 3D-OVS
settings."""

SCENE_PRESETS = ("synth-small", "synth-medium", "synth-large")
"""``thgs synth`` and ``thgs demo --preset``: the synthetic scenes' sizes."""

DEVICES = ("auto", "cpu", "cuda", "mps")
"""The device names the command line offers (``cuda:N`` is accepted too)."""

FieldPreset = Literal[FIELD_PRESETS]  # type: ignore[valid-type]
ScenePreset = Literal[SCENE_PRESETS]  # type: ignore[valid-type]
Device = Literal[DEVICES]  # type: ignore[valid-type]
