"""The settings of a suite run: how every scene is preprocessed, built and evaluated
(:class:`SuiteConfig`)."""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

from thgs.choices import DEVICES
from thgs.errors import InputError
from thgs.guidance.preprocess.run import PreprocessConfig
from thgs.guidance.preprocess.sam import DEFAULT_SAM
from thgs.pipeline import FieldConfig, chosen_field_config
from thgs.text import LANGSPLAT_SPACE

__all__ = [
    "SuiteConfig",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SuiteConfig:
    """How every scene of a suite is preprocessed, built and evaluated.

    Attributes:
        preset: the field-building preset of every scene (:data:`thgs.pipeline.PRESETS`);
            None: each benchmark's own, as in the paper (``3dovs`` for 3D-OVS scenes, ``lerf``
            for the others).
        config: a whole field config for every scene instead of a preset (``--config``).
        settings: single settings changed on top, ``"dotted.key=VALUE"``
            (:meth:`thgs.pipeline.FieldConfig.with_settings`).
        selection: the query selection scored as the headline: ``"auto"`` (thgs's) or
            ``"paper"`` (the paper's top-3); LERF-OVS reports the paper's rule beside it either
            way (``lerf-paper``).
        device: where to build and evaluate: ``auto``, ``cpu``, ``cuda`` or ``mps``.
        sam: SAM for scenes without language features (a local folder or a Hugging Face id).
        clip: CLIP for them, likewise.
        preprocess: the preprocessing settings (:class:`thgs.guidance.preprocess.PreprocessConfig`).
        scannet_level: the field level whose features classify ScanNet points.
    """

    preset: str | None = None
    config: FieldConfig | None = None
    settings: tuple[str, ...] = ()
    selection: Literal["auto", "paper"] = "auto"
    device: str = "cpu"
    sam: str = DEFAULT_SAM
    clip: str = LANGSPLAT_SPACE
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    scannet_level: int = 3

    def check(self) -> SuiteConfig:
        """Refuse an unknown preset or selection, a preset together with a config, or a bad
        ``--set``; returns ``self``.

        Raises:
            InputError: naming the option.
        """
        if self.selection not in ("auto", "paper"):
            raise InputError("--selection", f"must be auto or paper, got {self.selection!r}")
        if self.device not in DEVICES:
            raise InputError("--device", f"must be auto, cpu, cuda or mps, got {self.device!r}")
        for benchmark in ("lerf_ovs", "3dovs"):  # the preset, the config and --set
            self.field_config(benchmark)
        return self

    def field_config(self, benchmark: str) -> FieldConfig:
        """The field config of a scene of ``benchmark``."""
        preset = self.preset
        if preset is None and self.config is None:
            preset = "3dovs" if benchmark == "3dovs" else "lerf"
        return chosen_field_config(preset, self.config, self.settings)

    def to_json(self) -> dict[str, Any]:
        """The settings as JSON (the report's "settings")."""
        return {
            "preset": self.preset,
            "config": None if self.config is None else self.config.to_json(),
            "settings": list(self.settings),
            "selection": self.selection,
            "device": self.device,
            "sam": self.sam,
            "clip": self.clip,
            "preprocess": json.loads(json.dumps(asdict(self.preprocess))),
            "scannet_level": self.scannet_level,
        }
