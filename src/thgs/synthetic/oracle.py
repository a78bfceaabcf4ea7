"""Oracle guidance: SAM-like multi-level masks and CLIP-like features from the ground truth.

The masks are :mod:`thgs.synthetic.sam_masks`'s: each view's ground-truth components at
SAM's levels s, m and l with SAM's faults applied, each at a rate scaled by one ``severity`` knob
(0 = clean), and LangSplat's ``default`` level pooled from them.

Each mask's feature is the text embedding of its name plus Gaussian noise, renormalized: a
stand-in for the CLIP embedding of the mask's crop. Real crops are not name-perfect, and four
effects of CLIP on LangSplat-style crops (the mask cut out, the rest blacked out) can be mixed in,
each with its own setting (:class:`OracleConfig`, :func:`mask_embeddings`):

- *parent drift* — a part cut out of its object still looks like the object (a mug's handle like a
  mug, a table leg like a table): a part's embedding drifts towards its object's name, a
  sub-part's towards its part as the part looks (so, through it, towards the object too);
  objects have no parent;
- *surroundings* — what borders the mask leaks in a little (the crop's box holds some of it, and
  the mask's edge shows it), although the background is blacked out;
- *confusion* — things that look alike share names (:data:`thgs.synthetic.catalog.
  CONFUSABLE_NAMES`: a mug and a bottle, a table top and a chair seat);
- *compression* — CLIP's image–text cosines live in a narrow band (about 0.15–0.35 for
  ViT-B/16) because image embeddings share a direction text embeddings lack; every feature is
  pulled towards one fixed direction, which shrinks every cosine with a query.

:data:`STAND_INS` names settings of them (``name-perfect``, ``clip-like``) and
:func:`stand_in` reads a setting from its spec (``clip-like:parent_drift=0.8``);
:data:`CLIP_GRID` is the grid around ``clip-like`` every synthetic benchmark reports.
``context_mix``, an older single knob mixing the parent's and the surroundings' names with one
weight, stays for comparison.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from types import MappingProxyType

import numpy as np
from scipy import ndimage

from thgs.errors import InputError
from thgs.eval.ground_truth import Hierarchy
from thgs.guidance import ViewGuidance
from thgs.synthetic.catalog import CONFUSABLE_NAMES
from thgs.synthetic.sam_masks import (
    FaultRates,
    LevelMasks,
    MaskFaults,
    apply_faults,
    clean_masks,
    disk,
    ground_truth_maps,
    grown_box,
    pool_default,
)
from thgs.text import TextEncoder

__all__ = [
    "CLIP_GRID",
    "STAND_INS",
    "MaskContext",
    "OracleConfig",
    "compression_direction",
    "mask_context",
    "mask_contexts",
    "mask_embeddings",
    "mask_features",
    "oracle_guidance",
    "stand_in",
    "stand_in_spec",
]


_STAND_IN_FIELDS = (
    "subpart_drift",
    "part_drift",
    "surroundings",
    "confusion",
    "compression",
    "context_mix",
)


@dataclass(frozen=True)
class OracleConfig:
    """Settings of the oracle guidance.

    Attributes:
        severity: multiplies every fault rate; 0 gives the clean ground-truth components.
        rates: the fault rates at severity 1.
        max_jitter: largest boundary shift in pixels.
        spurious_radius: range of the spurious ellipses' semi-axes in pixels.
        min_split_pixels: masks smaller than this are never split.
        min_pixels: masks smaller than this are removed, clean or faulty (SAM's minimum region;
            1 keeps every ground-truth component).
        feature_noise: standard deviation of the noise added to a mask's embedding (as a
            vector norm: ``f = normalize(e + feature_noise · g / √D)``, g standard normal).
        subpart_drift: share of a sub-part mask's embedding that is its part's (the part's
            own mixture, which drifts towards the object in turn); in [0, 1]. 0: name-perfect.
        part_drift: share of a part mask's embedding that is its object's name; in [0, 1].
        surroundings: share of a mask's embedding that is the name of the object bordering
            it (the object other than its own under most of a ``context_radius``-pixel ring
            around it); in [0, 1].
        confusion: share of a name's embedding that is its look-alike's
            (:data:`thgs.synthetic.catalog.CONFUSABLE_NAMES`); in [0, 0.5] (0.5 makes the two
            names one).
        compression: pull of every feature towards one fixed direction
            (:func:`compression_direction`) after the noise, ``f ← normalize((1 − κ) f + κ u)``:
            every cosine with a text shrinks by about ``(1 − κ) / √((1 − κ)² + κ²)`` (0.85
            gives 0.17: MiniLM's 0.9 for a match and ~0.1 otherwise become ~0.16 and ~0.02,
            a band as narrow as CLIP's); in [0, 1).
        context_mix: the older single knob: ``e = (1 − c) · e(name) + c · e(context)``, with
            ``e(context)`` the normalized mean of the embeddings of the mask's parent and its
            surroundings (an object has no parent, so its context is its neighbour); in
            [0, 1]. Not combined with the four settings above.
        context_radius: width in pixels of the ring that defines a mask's surroundings.
        seed: base of every random draw (view i uses ``[seed, i]``).

    The four stand-in settings mix unit embeddings: for a mask named n whose ancestors are a₁
    (parent) and a₂ (grandparent), ``chain = (1 − d₁) b(n) + d₁ ((1 − d₂) b(a₁) + d₂ b(a₂))``
    with the drifts of the mask's level and the next and ``b(x) = (1 − c) e(x) + c e(look-alike
    of x)``, then ``e = (1 − s) chain + s b(surroundings)`` (see :func:`mask_embeddings`).
    """

    severity: float = 0.5
    rates: FaultRates = field(default_factory=FaultRates)
    max_jitter: int = 3
    spurious_radius: tuple[int, int] = (2, 8)
    min_split_pixels: int = 64
    min_pixels: int = 10
    feature_noise: float = 0.5
    subpart_drift: float = 0.0
    part_drift: float = 0.0
    surroundings: float = 0.0
    confusion: float = 0.0
    compression: float = 0.0
    context_mix: float = 0.0
    context_radius: int = 6
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("severity", "feature_noise"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise InputError(f"OracleConfig.{name}", f"must be a number ≥ 0, got {value}")
        for name, value in asdict(self.rates).items():
            if not (math.isfinite(value) and value >= 0.0):
                raise InputError(f"OracleConfig.rates.{name}", f"must be ≥ 0, got {value}")
        ranges = {
            "subpart_drift": (1.0, "[0, 1]"),
            "part_drift": (1.0, "[0, 1]"),
            "surroundings": (1.0, "[0, 1]"),
            "confusion": (0.5, "[0, 0.5]"),
            "context_mix": (1.0, "[0, 1]"),
        }
        for name, (high, text) in ranges.items():
            value = getattr(self, name)
            if not 0.0 <= value <= high:
                raise InputError(f"OracleConfig.{name}", f"must be in {text}, got {value}")
        if not 0.0 <= self.compression < 1.0:
            raise InputError(
                "OracleConfig.compression", f"must be in [0, 1), got {self.compression}"
            )
        if self.context_mix > 0 and self.clip_like_effects:
            raise InputError(
                "OracleConfig.context_mix",
                "is the older single knob and is not combined with subpart_drift, part_drift, "
                "surroundings or confusion; set it alone",
            )
        if self.context_radius < 1:
            raise InputError(
                "OracleConfig.context_radius", f"must be ≥ 1 pixel, got {self.context_radius}"
            )

    def faults(self) -> MaskFaults:
        """The fault rates at this severity and the masks' sizes, as :func:`apply_faults` takes
        them."""
        return MaskFaults(
            FaultRates(**{name: rate * self.severity for name, rate in asdict(self.rates).items()}),
            max_jitter=self.max_jitter,
            spurious_radius=self.spurious_radius,
            min_split_pixels=self.min_split_pixels,
            min_pixels=self.min_pixels,
        )

    @property
    def clip_like_effects(self) -> bool:
        """Whether any of parent drift, surroundings or confusion is set (they need each
        mask's context)."""
        return any(
            getattr(self, name) > 0
            for name in ("subpart_drift", "part_drift", "surroundings", "confusion")
        )

    @property
    def stand_in(self) -> dict[str, float]:
        """The settings that make the features CLIP-like (``subpart_drift`` …
        ``context_mix``), by name."""
        return {name: getattr(self, name) for name in _STAND_IN_FIELDS}

    def with_stand_in(self, spec: str) -> OracleConfig:
        """This config with the stand-in settings of ``spec`` (:func:`stand_in`); every
        stand-in setting the spec does not give is reset to 0."""
        return replace(self, **stand_in(spec))


STAND_INS: Mapping[str, Mapping[str, float]] = MappingProxyType(
    {
        "name-perfect": MappingProxyType({}),
        "clip-like": MappingProxyType(
            {
                "subpart_drift": 0.6,
                "part_drift": 0.6,
                "surroundings": 0.1,
                "confusion": 0.25,
                "compression": 0.85,
            }
        ),
    }
)
"""Named settings of the CLIP stand-in (docs/synthetic.md): ``name-perfect`` (every setting 0:
each mask's feature is its name's embedding plus noise) and ``clip-like``, one reasoned point:
a part or sub-part crop is 60 % its parent (a handle cut out of a mug still looks like a mug;
a sub-part's parent as the part itself looks), the blacked-out background leaks 10 %, a
look-alike's name 25 %, and cosines are compressed into CLIP's band."""

CLIP_GRID: tuple[str, ...] = (
    "clip-like",
    "clip-like:parent_drift=0.8",
    "clip-like:surroundings=0.3",
    "clip-like:parent_drift=0.8,surroundings=0.3",
)
"""The grid around ``clip-like`` that the synthetic benchmarks report: parent drift 0.6 and 0.8
× surroundings 0.1 and 0.3."""


def stand_in(spec: str) -> dict[str, float]:
    """The stand-in settings (``OracleConfig`` fields) of a spec ``NAME[:KEY=VALUE,...]``.

    NAME is one of :data:`STAND_INS`; each KEY=VALUE changes one setting: ``subpart_drift``,
    ``part_drift``, ``parent_drift`` (both drifts), ``surroundings``, ``confusion``,
    ``compression`` or ``context_mix``. Settings neither the name nor a key gives are 0.
    E.g. ``"clip-like:parent_drift=0.8,surroundings=0.3"``, ``"name-perfect:context_mix=0.8"``.

    Raises:
        InputError: an unknown name or key, a value that is not a number, or one out of its
            range (the message names the spec).
    """
    name, _, changes = str(spec).partition(":")
    if name not in STAND_INS:
        raise InputError(
            "stand-in", f"unknown {name!r} in {spec!r}; choose from {', '.join(STAND_INS)}"
        )
    settings = {key: 0.0 for key in _STAND_IN_FIELDS}
    settings.update(STAND_INS[name])
    for item in filter(None, (part.strip() for part in changes.split(","))):
        key, equals, text = item.partition("=")
        key = key.strip()
        keys = ("subpart_drift", "part_drift") if key == "parent_drift" else (key,)
        if not equals or any(k not in _STAND_IN_FIELDS for k in keys):
            raise InputError(
                "stand-in",
                f"{item!r} in {spec!r} is not KEY=VALUE with KEY one of parent_drift, "
                + ", ".join(_STAND_IN_FIELDS),
            )
        try:
            value = float(text)
        except ValueError:
            raise InputError(
                "stand-in", f"{key} in {spec!r} must be a number, got {text!r}"
            ) from None
        settings.update(dict.fromkeys(keys, value))
    try:
        OracleConfig(**settings)
    except InputError as error:
        setting = str(error.source).rpartition(".")[2]
        raise InputError("stand-in", f"{spec!r}: {setting} {error.problem}") from error
    return settings


def stand_in_spec(config: OracleConfig) -> str:
    """The shortest spec of ``config``'s stand-in settings (:func:`stand_in` reads it back):
    a named setting as it is, else the named setting it differs least from plus the keys
    that differ."""
    settings = config.stand_in
    best: tuple[int, str] | None = None
    for name in STAND_INS:
        base = stand_in(name)
        changed = {k: v for k, v in settings.items() if v != base[k]}
        if changed.keys() >= {"subpart_drift", "part_drift"} and (
            changed["subpart_drift"] == changed["part_drift"]
        ):
            changed = {"parent_drift": changed.pop("subpart_drift")} | changed
            del changed["part_drift"]
        text = ",".join(f"{key}={value:g}" for key, value in changed.items())
        if best is None or len(changed) < best[0]:
            best = (len(changed), f"{name}:{text}" if text else name)
    assert best is not None
    return best[1]


_COMPRESSION_SEED = 20250419


def compression_direction(dim: int) -> np.ndarray:
    """[dim] float64 unit vector: the fixed direction :attr:`OracleConfig.compression` pulls
    every feature towards (CLIP's image embeddings share one that its text embeddings lack).
    The same for every scene and seed, as it belongs to the model, not the scene."""
    direction = np.random.default_rng(_COMPRESSION_SEED).normal(size=dim)
    return direction / np.linalg.norm(direction)


@dataclass(frozen=True)
class MaskContext:
    """What a mask's crop shows besides its own name (:func:`mask_contexts`).

    Attributes:
        ancestors: the names of the nodes above the mask, nearest first: for a sub-part mask
            its part's and its object's, for a part mask its object's, none for an object
            mask (each the node under most of the mask's pixels at that level; the chain
            stops where no node is).
        surroundings: the name of the object under most of a ring around the mask, other than
            the mask's own object; None when the ring shows no other object.
    """

    ancestors: tuple[str, ...]
    surroundings: str | None


def mask_contexts(
    masks: LevelMasks, level: int, maps: np.ndarray, hierarchy: Hierarchy, radius: int
) -> tuple[MaskContext, ...]:
    """Per mask of ``masks`` (SAM level index ``level``: 0 s, 1 m, 2 l), its ancestors and its
    surroundings (:class:`MaskContext`; the ring is ``radius`` pixels wide)."""
    count = len(masks)
    above = [_majority(masks.ids, maps[k], count) for k in range(level + 1, 3)]
    own = _majority(masks.ids, maps[2], count)
    ring_disk = disk(radius)
    contexts = []
    shape = masks.ids.shape
    for index, box in enumerate(ndimage.find_objects(masks.ids + 1, max_label=count)):
        ancestors = []
        for offset, nodes in enumerate(above):
            if nodes[index] < 0:
                break
            ancestors.append(hierarchy.names[level + 2 + offset][nodes[index]])
        surroundings = None
        if box is not None:
            window = grown_box(box, radius, shape)
            inside = masks.ids[window] == index
            ring = ndimage.binary_dilation(inside, structure=ring_disk) & ~inside
            around = maps[2][window][ring]
            around = around[(around >= 0) & (around != own[index])]
            if around.size:
                surroundings = hierarchy.names[3][int(np.bincount(around).argmax())]
        contexts.append(MaskContext(tuple(ancestors), surroundings))
    return tuple(contexts)


def mask_context(
    masks: LevelMasks, level: int, maps: np.ndarray, hierarchy: Hierarchy, radius: int
) -> tuple[tuple[str, ...], ...]:
    """Per mask of ``masks`` (SAM level index ``level``: 0 s, 1 m, 2 l), the names of its
    context for :attr:`OracleConfig.context_mix`: its parent (the level-above node under most of
    its pixels; none for objects) and its surroundings (:func:`mask_contexts`)."""
    return tuple(
        (*context.ancestors[:1], *(() if context.surroundings is None else (context.surroundings,)))
        for context in mask_contexts(masks, level, maps, hierarchy, radius)
    )


_LOOK_ALIKES = {a: b for pair in CONFUSABLE_NAMES for a, b in (pair, pair[::-1])}
"""Each confusable name's look-alike, both ways."""


def mask_embeddings(
    names: tuple[str, ...],
    level: int,
    contexts: tuple[MaskContext, ...],
    encoder: TextEncoder,
    config: OracleConfig,
) -> np.ndarray:
    """[len(names), D] float64 embeddings (not unit) of masks named ``names`` at SAM level
    index ``level`` (0 s, 1 m, 2 l), before the noise, with the stand-in's parent drift,
    surroundings and confusion (:class:`OracleConfig`).

    With ``b(x) = (1 − c) e(x) + c e(x')`` (x' the look-alike of x, :data:`thgs.synthetic.
    catalog.CONFUSABLE_NAMES`; ``e(x)`` where x has none): the chain of the mask's name and
    its ancestors ``n, a₁, a₂`` gives ``(1 − d_ℓ) b(n) + d_ℓ ((1 − d_ℓ₊₁) b(a₁) + d_ℓ₊₁ b(a₂))``
    (d₀ the sub-part drift, d₁ the part drift; the last name of a chain takes the remaining
    weight): a sub-part drifts towards its part as the part itself looks. Mixing names alone
    (``(1 − d) b(n) + d b(a₁)`` for a sub-part too) would make a bear's ear more like "bear
    head" than the bear's head is, which no crop does. A mask named like its parent (a part
    with one sub-part, or a part-sized mask among the sub-parts) is the parent's crop and starts
    the chain there. Then ``e = (1 − s) chain + s b(surroundings)`` where the mask has
    surroundings.
    """
    drifts = (config.subpart_drift, config.part_drift)
    wanted = set(names)
    for context in contexts:
        wanted.update(context.ancestors)
        if context.surroundings is not None:
            wanted.add(context.surroundings)
    wanted.update(_LOOK_ALIKES[name] for name in list(wanted) if name in _LOOK_ALIKES)
    order = sorted(wanted)
    vectors = dict(zip(order, encoder.encode(order).astype(np.float64))) if order else {}

    def blurred(name: str) -> np.ndarray:
        if config.confusion > 0 and name in _LOOK_ALIKES:
            other = vectors[_LOOK_ALIKES[name]]
            return (1.0 - config.confusion) * vectors[name] + config.confusion * other
        return vectors[name]

    out = np.zeros((len(names), encoder.dim), dtype=np.float64)
    for i, (name, context) in enumerate(zip(names, contexts)):
        chain, start = [name, *context.ancestors], level
        while len(chain) > 1 and chain[0] == chain[1]:
            chain, start = chain[1:], start + 1
        weight = 1.0
        for j, link in enumerate(chain):
            drift = drifts[start + j] if j < len(chain) - 1 else 0.0
            out[i] += weight * (1.0 - drift) * blurred(link)
            weight *= drift
        if context.surroundings is not None and config.surroundings > 0:
            out[i] = (1.0 - config.surroundings) * out[i] + config.surroundings * blurred(
                context.surroundings
            )
    return out


def mask_features(
    names: tuple[str, ...],
    encoder: TextEncoder,
    noise: float,
    rng: np.random.Generator,
    context: tuple[tuple[str, ...], ...] | None = None,
    mix: float = 0.0,
    embeddings: np.ndarray | None = None,
    compression: float = 0.0,
) -> np.ndarray:
    """[len(names), D] float32 unit rows: ``normalize(e + noise · g / √D)``, then pulled
    towards :func:`compression_direction` by ``compression``.

    ``e`` is ``embeddings`` when given (:func:`mask_embeddings`), else
    ``(1 − mix) · embed(name) + mix · normalize(mean(embed(c) for c in context))`` (just
    ``embed(name)`` where a mask has no context or ``mix`` is 0).

    Args:
        names: each mask's name.
        encoder: the text model.
        noise: the noise's norm (:attr:`OracleConfig.feature_noise`).
        rng: the view's random generator (one [len(names), D] normal draw).
        context: per mask, the names of its context (:func:`mask_context`).
        mix: :attr:`OracleConfig.context_mix`.
        embeddings: [len(names), D] the masks' embeddings before the noise, if computed already.
        compression: :attr:`OracleConfig.compression`.
    """
    if embeddings is None:
        embeddings = encoder.encode(list(names)).astype(np.float64)
        if len(names) and mix > 0.0 and context is not None:
            for i, words in enumerate(context):
                if words:
                    around = encoder.encode(list(words)).astype(np.float64).mean(axis=0)
                    around /= np.linalg.norm(around)
                    embeddings[i] = (1.0 - mix) * embeddings[i] + mix * around
    if len(names) == 0:
        return np.zeros((0, encoder.dim), dtype=np.float32)
    dim = embeddings.shape[1]
    noisy = embeddings + noise * rng.normal(size=embeddings.shape) / math.sqrt(dim)
    features = noisy / np.linalg.norm(noisy, axis=1, keepdims=True)
    if compression > 0.0:
        features = (1.0 - compression) * features + compression * compression_direction(dim)
        features /= np.linalg.norm(features, axis=1, keepdims=True)
    return features.astype(np.float32)


def _majority(ids: np.ndarray, nodes: np.ndarray, count: int) -> np.ndarray:
    """[count] int: the most common node ≥ 0 under each id ≥ 0 (−1 where none)."""
    keep = (ids >= 0) & (nodes >= 0)
    if not keep.any():
        return np.full(count, -1, dtype=np.int64)
    pairs, votes = np.unique(np.stack([ids[keep], nodes[keep]], axis=1), axis=0, return_counts=True)
    order = np.lexsort((-votes, pairs[:, 0]))  # per id, most votes first (lowest node on ties)
    pairs = pairs[order]
    first = np.concatenate([[True], pairs[1:, 0] != pairs[:-1, 0]])
    out = np.full(count, -1, dtype=np.int64)
    out[pairs[first, 0]] = pairs[first, 1]
    return out


def _level_features(
    masks: LevelMasks,
    level: int,
    maps: np.ndarray,
    hierarchy: Hierarchy,
    encoder: TextEncoder,
    config: OracleConfig,
    rng: np.random.Generator,
) -> np.ndarray:
    """[len(masks), D] float32 features of one level's masks (module docstring)."""
    embeddings = context = None
    if config.clip_like_effects:
        contexts = mask_contexts(masks, level, maps, hierarchy, config.context_radius)
        embeddings = mask_embeddings(masks.names, level, contexts, encoder, config)
    elif config.context_mix > 0:
        context = mask_context(masks, level, maps, hierarchy, config.context_radius)
    return mask_features(
        masks.names,
        encoder,
        config.feature_noise,
        rng,
        context,
        config.context_mix,
        embeddings=embeddings,
        compression=config.compression,
    )


def oracle_guidance(
    stem: str,
    max_id: np.ndarray,
    hierarchy: Hierarchy,
    encoder: TextEncoder,
    config: OracleConfig,
    view_index: int,
) -> ViewGuidance:
    """One view's guidance in LangSplat's layout (levels default, s, m, l).

    Args:
        stem: the view's image stem.
        max_id: [H, W] index of each pixel's max-weight Gaussian (−1 where none), from
            :func:`thgs.render.render`.
        hierarchy: the per-Gaussian ground truth.
        encoder: the text model whose space the features live in.
        config: fault severity and rates, feature noise, seed.
        view_index: the view's position (seeds its random draws with ``[config.seed, i]``).
    """
    rng = np.random.default_rng([config.seed, view_index])
    maps = ground_truth_maps(max_id, hierarchy)
    clean = clean_masks(maps, hierarchy, config.min_pixels)
    levels = apply_faults(clean, maps, hierarchy, config.faults(), rng)
    level_features = [
        _level_features(masks, level, maps, hierarchy, encoder, config, rng)
        for level, masks in enumerate(levels)
    ]
    pooled, sources = pool_default(levels)
    pooled_features = (
        np.stack([level_features[level][index] for level, index in sources])
        if sources
        else np.zeros((0, encoder.dim), dtype=np.float32)
    )
    segments = []
    offset = 0
    for masks in (pooled, *levels):
        segments.append(np.where(masks.ids >= 0, masks.ids + offset, -1))
        offset += len(masks)
    features = np.concatenate([pooled_features, *level_features])
    return ViewGuidance(stem, np.stack(segments).astype(np.int32), features).check(
        source=f"oracle guidance for {stem}"
    )
