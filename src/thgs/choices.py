"""The names a user chooses from, in one place: field presets, synthetic scene presets,
devices and query selection modes, as tuples and as the ``Literal`` types the command line
offers them with. No heavy imports, so that every command can type its options with them; the
registries that give each name its meaning (:data:`thgs.pipeline.PRESETS`,
:data:`thgs.synthetic.PRESETS`, :func:`thgs.device.resolve_device`,
:class:`thgs.query.QueryConfig`) are tested to hold exactly these names.
"""

from __future__ import annotations

from typing import Literal

__all__ = [
    "DEVICES",
    "FIELD_PRESETS",
    "SCENE_PRESETS",
    "SELECTION_MODES",
    "Device",
    "FieldPreset",
    "ScenePreset",
    "SelectionMode",
]

FIELD_PRESETS = ("lerf", "3dovs")
"""``thgs build --preset`` and ``thgs suite --preset``: the reference's LERF-OVS and 3D-OVS
settings."""

SCENE_PRESETS = ("synth-small", "synth-medium", "synth-large")
"""``thgs synth`` and ``thgs demo --preset``: the synthetic scenes' sizes."""

DEVICES = ("auto", "cpu", "cuda", "mps")
"""The device names the command line offers (``cuda:N`` is accepted too)."""

SELECTION_MODES = ("auto", "paper", "level", "threshold")
"""How a query's relevancies become a selection (:class:`thgs.query.QueryConfig`'s ``mode``)."""

FieldPreset = Literal[FIELD_PRESETS]  # type: ignore[valid-type]
ScenePreset = Literal[SCENE_PRESETS]  # type: ignore[valid-type]
Device = Literal[DEVICES]  # type: ignore[valid-type]
SelectionMode = Literal[SELECTION_MODES]  # type: ignore[valid-type]
