"""The settings of a field build, in one typed record: :class:`FieldConfig` (one config per
stage, grouped; :class:`SuperpointConfig` for the four stages that make superpoints), its presets
(:data:`PRESETS`), the one way a build's settings are chosen from a preset or a config file,
``--reference`` and ``--set`` (:func:`chosen_field_config`), and reading them back from a file or
from a field's record (:func:`read_field_config`, :func:`recorded_config`,
:func:`lifted_raster`), older records included.
"""

from __future__ import annotations

import copy
import json
import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from thgs._config_json import config_from_json
from thgs._json import load_json
from thgs.errors import InputError
from thgs.features import FeatureConfig
from thgs.field import SemanticField, load_field
from thgs.graph import (
    GraphConfig,
    PartitionConfig,
    ReweightConfig,
)
from thgs.hierarchy import (
    MergeConfig,
    RepeatConfig,
)
from thgs.lift import LiftConfig
from thgs.render import RasterConfig

__all__ = [
    "PRESETS",
    "FieldConfig",
    "SuperpointConfig",
    "chosen_field_config",
    "lifted_raster",
    "read_field_config",
    "recorded_config",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SuperpointConfig:
    """The configs of the four stages that make level-0 superpoints.

    Attributes:
        lift: how masks become per-Gaussian labels (:class:`thgs.lift.LiftConfig`).
        graph: the KNN graph (:class:`thgs.graph.GraphConfig`).
        reweight: how mask votes change edge distances (:class:`thgs.graph.ReweightConfig`).
        partition: cut pursuit (:class:`thgs.graph.PartitionConfig`).
    """

    lift: LiftConfig = field(default_factory=LiftConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    reweight: ReweightConfig = field(default_factory=ReweightConfig)
    partition: PartitionConfig = field(default_factory=PartitionConfig)

    @classmethod
    def lerf(cls) -> SuperpointConfig:
        """The reference's LERF-OVS numbers (R 0.1, W 0.1, normals up, τ 0.85), our fixes on."""
        return cls(partition=PartitionConfig.lerf())

    @classmethod
    def three_dovs(cls) -> SuperpointConfig:
        """The reference's 3DOVS numbers (R 0.3, W 0.2, lifting τ 0.5), our fixes on."""
        return cls(lift=LiftConfig(cosine_threshold=0.5), partition=PartitionConfig.three_dovs())

    def as_reference(self) -> SuperpointConfig:
        """The same numbers with the authors' behaviour where ours differs: absolute vote
        offsets (0.1 / 0.02 scene units²), edge weights against the reweighted mean, the
        solver's 2 split alternatives on the Gaussians themselves, the solver's superpoints
        unpolished."""
        return replace(
            self,
            reweight=replace(
                self.reweight, mode="absolute", negative_offset=0.1, positive_offset=0.02
            ),
            partition=replace(
                self.partition,
                weight_scale="reweighted",
                split_alternatives=2,
                polish=False,
                coarsen_levels=0,
                threaded_largest=False,
            ),
        )


@dataclass(frozen=True)
class FieldConfig:
    """Everything :func:`build_field` needs: the superpoint stages, merging and features.

    Attributes:
        superpoints: lift, graph, reweighting and partition (:class:`SuperpointConfig`).
        merge: progressive merging (:class:`thgs.hierarchy.MergeConfig`); the ``independent``
            ablation makes levels that need not nest, which a field cannot hold.
        features: region features (:class:`thgs.features.FeatureConfig`).
        repeats: grouping an object's alike, non-touching parts into one level-2 region (ours:
            :class:`thgs.hierarchy.RepeatConfig`); progressive merging only.
    """

    superpoints: SuperpointConfig = field(default_factory=SuperpointConfig)
    merge: MergeConfig = field(default_factory=MergeConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    repeats: RepeatConfig = field(default_factory=RepeatConfig)

    @classmethod
    def lerf(cls) -> FieldConfig:
        """The reference's LERF-OVS preset (our fixes on; see :meth:`as_reference`)."""
        return cls(SuperpointConfig.lerf(), MergeConfig.lerf(), FeatureConfig.lerf())

    @classmethod
    def three_dovs(cls) -> FieldConfig:
        """The reference's 3DOVS preset (our fixes on; see :meth:`as_reference`)."""
        return cls(
            SuperpointConfig.three_dovs(), MergeConfig.three_dovs(), FeatureConfig.three_dovs()
        )

    def as_reference(self) -> FieldConfig:
        """The same numbers with the authors' behaviour where ours differs: absolute vote
        offsets, edge weights against the reweighted mean, the reference's merging (every
        label votes with weight 1, 2-hop members count, one round per pass:
        :meth:`thgs.hierarchy.MergeConfig.as_reference`), its features (the weighted mean
        over views, every labelled Gaussian counting once:
        :meth:`thgs.features.FeatureConfig.as_reference`) and one part per connected piece (no
        grouping of repeated parts)."""
        return replace(
            self,
            superpoints=self.superpoints.as_reference(),
            merge=self.merge.as_reference(),
            features=self.features.as_reference(),
            repeats=replace(self.repeats, enabled=False),
        )

    def to_json(self) -> dict[str, Any]:
        """The config as JSON values (tuples become lists), as stored in the field file.

        The rasterization's ``backend`` and ``precision`` say how the lifting ran, not what it
        computes, and are left out: the same field is written whichever backend built it."""
        document = json.loads(json.dumps(asdict(self)))
        raster = document["superpoints"]["lift"]["raster"]
        for key in ("backend", "precision"):
            raster.pop(key)
        return document

    @classmethod
    def from_json(cls, document: Any, where: str = "FieldConfig") -> FieldConfig:
        """The config :meth:`to_json` wrote: ``FieldConfig.from_json(c.to_json()) == c`` up to
        the rasterization's backend and precision (``"auto"`` again).

        A setting missing from ``document`` takes today's default (a record from an older thgs
        that lacked it).

        Raises:
            InputError: naming ``where`` and the key: an unknown setting, a value of the wrong
                type or outside its choices.
        """
        return config_from_json(cls, document, where)

    def with_settings(self, assignments: Sequence[str]) -> FieldConfig:
        """This config with settings changed by ``"dotted.key=VALUE"`` assignments, e.g.
        ``"merge.min_region_gaussians=30"`` or ``"superpoints.lift.raster.backend=torch"``.

        VALUE is JSON (``30``, ``0.5``, ``true``, ``[0.9, 0.8, 0.7]``); anything that is not
        JSON is taken as a string (``torch``). Every setting of every stage is reachable.

        Raises:
            InputError: an assignment without ``=``, an unknown key, a value of the wrong type.
        """
        document = json.loads(json.dumps(asdict(self)))
        for assignment in assignments:
            key, equals, text = assignment.partition("=")
            if not equals or not key.strip():
                raise InputError("--set", f"expected KEY=VALUE, got {assignment!r}")
            *parents, name = key.strip().split(".")
            node = document
            for i, part in enumerate(parents):
                if not isinstance(node.get(part), dict):
                    raise InputError("--set", f"{'.'.join(parents[: i + 1])!r} is not a stage")
                node = node[part]
            if name not in node:
                raise InputError("--set", f"unknown setting {key!r}; known here: {', '.join(node)}")
            try:
                node[name] = json.loads(text)
            except json.JSONDecodeError:
                node[name] = text
        return FieldConfig.from_json(document, "--set")


def recorded_config(field: SemanticField, source: str = "field") -> FieldConfig:
    """The :class:`FieldConfig` a field was built with, from its record, so that it can be
    rebuilt or its settings read with their types. A setting recorded by no field built before
    it existed takes the value those builds used (:data:`_BEFORE_RECORDED`); a setting that no
    longer exists is dropped (:data:`_RETIRED`).

    Raises:
        InputError: the record is not a valid FieldConfig (named by ``source`` and the key).
    """
    document = copy.deepcopy(field.config)
    for (*stages, name), value in _BEFORE_RECORDED.items():
        node = _stage(document, stages)
        if node is not None and name not in node:
            node[name] = value
    for *stages, name in _RETIRED:
        node = _stage(document, stages)
        if node is not None:
            node.pop(name, None)
    return FieldConfig.from_json(document, f"{source}: config")


def _stage(document: dict, stages: Sequence[str]) -> dict | None:
    """The settings of the stage at the path ``stages`` in a config document, or None when a
    record has no such stage (its error is the config reader's to report)."""
    node: Any = document
    for stage in stages:
        node = node.get(stage) if isinstance(node, dict) else None
    return node if isinstance(node, dict) else None


_BEFORE_RECORDED = {
    ("merge", "min_support"): 0.0,
    ("merge", "split_incoherent"): False,
    ("superpoints", "partition", "split_alternatives"): 2,
    ("superpoints", "partition", "polish"): False,
    ("features", "median_steps"): 0,
    ("features", "fit_power"): 0.0,
    ("superpoints", "partition", "block_size"): 0,
    ("superpoints", "partition", "coarsen_levels"): 0,
    ("superpoints", "partition", "threaded_largest"): False,
}
"""Settings added after fields were first recorded, with the value every earlier build used."""

_RETIRED = (("superpoints", "partition", "max_num_threads"),)
"""Settings earlier fields recorded that no longer exist: the solver's thread count (the
partition's result no longer depends on it)."""


def read_field_config(path: str | os.PathLike[str]) -> FieldConfig:
    """A :class:`FieldConfig` from a JSON file (:meth:`FieldConfig.to_json`'s document) or from
    a field file's record (:func:`recorded_config`), so that a field can be rebuilt as it was.

    Raises:
        InputError: naming the file: missing, not JSON or not a field, or not a valid config.
    """
    path = Path(path)
    if path.suffix.lower() == ".json":
        document = load_json(path)
        config = FieldConfig.from_json(document, str(path))
        missing = _missing_settings(document, config.to_json())
        if missing:
            shown = ", ".join(missing[:8]) + (
                f" and {len(missing) - 8} more" if len(missing) > 8 else ""
            )
            logger.warning("%s does not set %s: thgs's defaults are used there", path, shown)
        return config
    return recorded_config(load_field(path), str(path))


def _missing_settings(document: Any, complete: dict[str, Any], prefix: str = "") -> list[str]:
    """The dotted names of ``complete``'s settings that ``document`` lacks (a whole section
    named once)."""
    missing: list[str] = []
    for key, value in complete.items():
        if not isinstance(document, dict) or key not in document:
            missing.append(prefix + key)
        elif isinstance(value, dict):
            missing += _missing_settings(document[key], value, f"{prefix}{key}.")
    return missing


def lifted_raster(field: SemanticField, source: str = "field") -> RasterConfig:
    """The rasterization settings the field was lifted with, to render its views the same way.

    A record that is not a valid :class:`FieldConfig` (a field from a thgs whose settings had
    other names) gives the default settings, with a logged warning.
    """
    try:
        return recorded_config(field, source).superpoints.lift.raster
    except InputError as error:
        logger.warning("%s; rendering with the default RasterConfig", error)
        return RasterConfig()


PRESETS: dict[str, Callable[[], FieldConfig]] = {
    "lerf": FieldConfig.lerf,
    "3dovs": FieldConfig.three_dovs,
}
"""The named presets of ``thgs build --preset``."""


def chosen_field_config(
    preset: str | None = None,
    config: FieldConfig | None = None,
    settings: Sequence[str] = (),
    *,
    reference: bool = False,
    repeated_parts: bool = True,
) -> FieldConfig:
    """The field config a build asks for, each setting named once: the preset (default
    ``lerf``) or a whole ``config``; then the authors' behaviour (``reference``); then
    ``repeated_parts`` False (no grouping of repeated parts); then the ``"dotted.key=VALUE"``
    ``settings`` (:meth:`FieldConfig.with_settings`), which therefore win over ``reference``.
    What ``thgs build``, ``thgs suite`` and ``thgs bench`` build with.

    Raises:
        InputError: an unknown preset; a preset and a config; a setting named twice (twice in
            ``settings``, or ``repeats.enabled`` with ``repeated_parts`` False), naming both.
    """
    if preset is not None and config is not None:
        raise InputError("--preset", f"{preset!r} and --config both give every setting; pass one")
    if preset is not None and preset not in PRESETS:
        raise InputError("--preset", f"unknown {preset!r}; choose from {', '.join(PRESETS)}")
    named: dict[str, str] = {}
    for assignment in settings:
        key = assignment.partition("=")[0].strip()
        if key in named:
            raise InputError(
                "--set", f"names {key} twice ({named[key]!r} and {assignment!r}); keep one"
            )
        named[key] = assignment
    if not repeated_parts and "repeats.enabled" in named:
        raise InputError(
            "--no-repeated-parts",
            f"and --set {named['repeats.enabled']!r} both name repeats.enabled; keep one",
        )
    chosen = config if config is not None else PRESETS[preset or "lerf"]()
    if reference:
        chosen = chosen.as_reference()
    if not repeated_parts:
        chosen = replace(chosen, repeats=replace(chosen.repeats, enabled=False))
    return chosen.with_settings(list(named.values()))
