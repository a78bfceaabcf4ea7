"""The variants ``thgs bench`` builds: the method and its ablations, as changes of the LERF preset
(:meth:`thgs.pipeline.FieldConfig.lerf`), and the paper's orderings among them."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace
from types import MappingProxyType

from thgs.pipeline import FieldConfig

__all__ = ["ORDERINGS", "VARIANTS"]


def _full(config: FieldConfig) -> FieldConfig:
    return config


def _no_reweighting(config: FieldConfig) -> FieldConfig:
    superpoints = config.superpoints
    return replace(
        config,
        superpoints=replace(superpoints, reweight=replace(superpoints.reweight, mode="none")),
    )


def _no_depth_decay(config: FieldConfig) -> FieldConfig:
    superpoints = config.superpoints
    return replace(
        config,
        superpoints=replace(superpoints, reweight=replace(superpoints.reweight, depth_decay=False)),
    )


def _merge_mode(mode: str) -> Callable[[FieldConfig], FieldConfig]:
    def variant(config: FieldConfig) -> FieldConfig:
        return replace(config, merge=replace(config.merge, mode=mode))

    return variant


def _exact_lifting(config: FieldConfig) -> FieldConfig:
    superpoints = config.superpoints
    return replace(
        config, superpoints=replace(superpoints, lift=replace(superpoints.lift, method="exact"))
    )


def _absolute_reweighting(config: FieldConfig) -> FieldConfig:
    superpoints = config.superpoints
    reweight = replace(
        superpoints.reweight, mode="absolute", negative_offset=0.1, positive_offset=0.02
    )
    return replace(config, superpoints=replace(superpoints, reweight=reweight))


def _authors(config: FieldConfig) -> FieldConfig:
    return config.as_reference()


VARIANTS: Mapping[str, Callable[[FieldConfig], FieldConfig]] = MappingProxyType(
    {
        "full": _full,
        "no edge reweighting": _no_reweighting,
        "no depth decay": _no_depth_decay,
        "no progressive merging": _merge_mode("independent"),
        "instance level only": _merge_mode("instance"),
        "exact lifting": _exact_lifting,
        "absolute reweighting": _absolute_reweighting,
        "authors' code": _authors,
    }
)
"""Variant name → how it changes the LERF preset (:meth:`FieldConfig.lerf`)."""

ORDERINGS: tuple[tuple[str, ...], ...] = (
    ("full", "no depth decay", "no edge reweighting"),
    ("full", "no progressive merging", "instance level only"),
)
"""The paper's Table 3 orderings (best first) on LERF-OVS mIoU."""
