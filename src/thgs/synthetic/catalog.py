"""The object catalog: objects made of named parts made of named sub-parts.

Each builder draws an object's sizes and colours from a random generator and returns it in its
own frame (metres, z up, origin at the centre of its footprint on the supporting surface). Names
are what the oracle's text model embeds and what queries match, so they read like things a person
would type ("mug handle", "bear nose"). A part with no finer division has one sub-part of the
same name; several sub-parts may share a name (a chair's four "chair leg"s).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from thgs.synthetic.shapes import (
    Box,
    Disc,
    Ellipsoid,
    Frustum,
    Placed,
    Rect,
    TorusArc,
    rotation_x,
    rotation_z,
)

__all__ = [
    "CONFUSABLE_NAMES",
    "FLOOR_OBJECTS",
    "PALETTE",
    "TABLE_OBJECTS",
    "ObjectModel",
    "Part",
    "SubPart",
    "build_floor",
    "build_table",
]

PALETTE: dict[str, tuple[float, float, float]] = {
    "red": (0.80, 0.12, 0.10),
    "orange": (0.95, 0.50, 0.10),
    "yellow": (0.95, 0.85, 0.20),
    "green": (0.20, 0.60, 0.25),
    "blue": (0.15, 0.30, 0.80),
    "purple": (0.50, 0.20, 0.60),
    "pink": (0.95, 0.60, 0.70),
    "brown": (0.50, 0.30, 0.15),
    "white": (0.92, 0.92, 0.90),
    "black": (0.10, 0.10, 0.10),
    "grey": (0.55, 0.55, 0.55),
    "beige": (0.85, 0.75, 0.60),
}
"""Named colours (linear RGB in [0, 1]) that parts are painted with."""

_BRIGHT = ("red", "orange", "yellow", "green", "blue", "purple", "pink")


@dataclass(frozen=True)
class SubPart:
    """The finest ground-truth unit: a name, a palette colour and the surfaces it covers."""

    name: str
    color: str
    surfaces: tuple[Placed, ...]

    @property
    def area(self) -> float:
        return sum(surface.area for surface in self.surfaces)


@dataclass(frozen=True)
class Part:
    name: str
    subparts: tuple[SubPart, ...]


@dataclass(frozen=True)
class ObjectModel:
    """One object in its own frame.

    Attributes:
        name: the object's text name (its category; two mugs share "mug").
        parts: its parts, each made of sub-parts.
        footprint: radius in metres of a disc around the origin that holds the object's base
            (used to place objects without overlap).
        density: relative Gaussian density (trained scenes spend more Gaussians on detailed
            objects than on floors).
    """

    name: str
    parts: tuple[Part, ...]
    footprint: float
    density: float = 1.0


def _pick(rng: np.random.Generator, names: tuple[str, ...]) -> str:
    return names[int(rng.integers(len(names)))]


def _single(name: str, color: str, *surfaces: Placed) -> Part:
    return Part(name, (SubPart(name, color, surfaces),))


def build_mug(rng: np.random.Generator) -> ObjectModel:
    radius = rng.uniform(0.04, 0.055)
    height = rng.uniform(0.09, 0.12)
    color = _pick(rng, (*_BRIGHT, "white", "black"))
    handle_color = color if rng.uniform() < 0.7 else _pick(rng, _BRIGHT)
    wall = 0.06 * radius
    body = [
        SubPart(
            "mug body",
            color,
            (
                Placed(Frustum(radius, radius, height)),
                Placed(Frustum(radius - wall, radius - wall, height, inward=True)),
            ),
        )
    ]
    if rng.uniform() < 0.5:
        coffee = Placed(Disc(radius - wall), translation=(0.0, 0.0, 0.8 * height))
        body.append(SubPart("coffee", "brown", (coffee,)))
    else:
        inside = Placed(Disc(radius - wall), translation=(0.0, 0.0, 0.05 * height))
        body[0] = SubPart("mug body", color, (*body[0].surfaces, inside))
    ring = 0.28 * height
    handle = Placed(
        TorusArc(ring, rng.uniform(0.007, 0.011), -math.pi / 2, math.pi / 2),
        rotation=rotation_x(math.pi / 2),
        translation=(radius, 0.0, 0.5 * height),
    )
    parts = (Part("mug body", tuple(body)), _single("mug handle", handle_color, handle))
    return ObjectModel("mug", parts, footprint=radius + ring + 0.01, density=1.5)


def build_lamp(rng: np.random.Generator) -> ObjectModel:
    base_radius = rng.uniform(0.07, 0.10)
    base_height = rng.uniform(0.02, 0.03)
    pole_height = rng.uniform(0.25, 0.40)
    shade_height = rng.uniform(0.10, 0.14)
    metal = _pick(rng, ("black", "grey", "white", "brown"))
    shade_color = _pick(rng, ("white", "beige", "yellow", "red", "green"))
    base = (
        Placed(Frustum(base_radius, base_radius, base_height)),
        Placed(Disc(base_radius), translation=(0.0, 0.0, base_height)),
    )
    pole = Placed(Frustum(0.01, 0.01, pole_height), translation=(0.0, 0.0, base_height))
    shade_bottom = base_height + pole_height - 0.6 * shade_height
    shade = (
        Placed(Frustum(0.12, 0.07, shade_height), translation=(0.0, 0.0, shade_bottom)),
        Placed(
            Frustum(0.118, 0.068, shade_height, inward=True),
            translation=(0.0, 0.0, shade_bottom),
        ),
    )
    bulb = Placed(Ellipsoid((0.03, 0.03, 0.04)), translation=(0.0, 0.0, base_height + pole_height))
    parts = (
        _single("lamp base", metal, *base),
        _single("lamp pole", metal, pole),
        Part(
            "lamp shade",
            (SubPart("lamp shade", shade_color, shade), SubPart("light bulb", "white", (bulb,))),
        ),
    )
    return ObjectModel("lamp", parts, footprint=0.125, density=1.5)


def build_teddy_bear(rng: np.random.Generator) -> ObjectModel:
    size = rng.uniform(0.85, 1.15)
    fur = _pick(rng, ("brown", "beige", "white", "pink"))
    ear_color = fur if rng.uniform() < 0.6 else _pick(rng, ("brown", "beige", "pink"))

    def blob(radii: tuple[float, float, float], centre: tuple[float, float, float]) -> Placed:
        return Placed(
            Ellipsoid(tuple(r * size for r in radii)),  # type: ignore[arg-type]
            translation=tuple(c * size for c in centre),  # type: ignore[arg-type]
        )

    body = Part(
        "bear body",
        (
            SubPart("bear body", fur, (blob((0.07, 0.06, 0.085), (0.0, 0.0, 0.085)),)),
            SubPart("bear arm", fur, (blob((0.022, 0.022, 0.05), (0.0, 0.075, 0.10)),)),
            SubPart("bear arm", fur, (blob((0.022, 0.022, 0.05), (0.0, -0.075, 0.10)),)),
        ),
    )
    head = Part(
        "bear head",
        (
            SubPart("bear head", fur, (blob((0.055, 0.055, 0.05), (0.0, 0.0, 0.215)),)),
            SubPart("bear ear", ear_color, (blob((0.012, 0.022, 0.022), (0.0, 0.04, 0.26)),)),
            SubPart("bear ear", ear_color, (blob((0.012, 0.022, 0.022), (0.0, -0.04, 0.26)),)),
            SubPart("bear nose", "black", (blob((0.015, 0.012, 0.01), (0.05, 0.0, 0.21)),)),
        ),
    )
    return ObjectModel("teddy bear", (body, head), footprint=0.09 * size, density=1.5)


def build_chair(rng: np.random.Generator) -> ObjectModel:
    width = rng.uniform(0.40, 0.48)
    seat_height = rng.uniform(0.42, 0.48)
    back_height = rng.uniform(0.35, 0.50)
    leg = 0.035
    wood = _pick(rng, ("brown", "black", "white", "red", "blue", "green"))
    back_color = wood if rng.uniform() < 0.6 else _pick(rng, _BRIGHT)
    seat = Placed(Box(width, width, 0.04), translation=(0.0, 0.0, seat_height - 0.04))
    back = Placed(
        Box(0.03, width, back_height), translation=(-(width - 0.03) / 2, 0.0, seat_height)
    )
    offset = (width - leg) / 2
    legs = tuple(
        SubPart(
            "chair leg",
            wood,
            (
                Placed(
                    Box(leg, leg, seat_height - 0.04, faces=("+x", "-x", "+y", "-y")),
                    translation=(sx * offset, sy * offset, 0.0),
                ),
            ),
        )
        for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1))
    )
    parts = (
        _single("chair seat", wood, seat),
        _single("chair back", back_color, back),
        Part("chair legs", legs),
    )
    return ObjectModel("chair", parts, footprint=width * 0.71, density=0.6)


def build_stack_of_books(rng: np.random.Generator) -> ObjectModel:
    books = []
    z = 0.0
    count = int(rng.integers(2, 5))
    for _ in range(count):
        width, depth = rng.uniform(0.15, 0.22), rng.uniform(0.11, 0.16)
        thickness = rng.uniform(0.02, 0.04)
        turn = rotation_z(rng.uniform(-0.25, 0.25))
        cover = Placed(Box(width, depth, thickness, faces=("+z", "-z", "-x")), turn, (0, 0, z))
        pages = Placed(Box(width, depth, thickness, faces=("+x", "+y", "-y")), turn, (0, 0, z))
        books.append(
            Part(
                "book",
                (
                    SubPart("book cover", _pick(rng, (*_BRIGHT, "black", "brown")), (cover,)),
                    SubPart("book pages", "white", (pages,)),
                ),
            )
        )
        z += thickness
    return ObjectModel("stack of books", tuple(books), footprint=0.14, density=1.2)


def build_potted_plant(rng: np.random.Generator) -> ObjectModel:
    pot_height = rng.uniform(0.08, 0.12)
    r0, r1 = rng.uniform(0.04, 0.05), rng.uniform(0.06, 0.075)
    stem_height = rng.uniform(0.12, 0.20)
    pot_color = _pick(rng, ("orange", "brown", "white", "grey", "blue"))
    pot = Part(
        "flower pot",
        (
            SubPart("flower pot", pot_color, (Placed(Frustum(r0, r1, pot_height)),)),
            SubPart(
                "soil",
                "brown",
                (Placed(Disc(r1 * 0.95), translation=(0.0, 0.0, 0.9 * pot_height)),),
            ),
        ),
    )
    stem = SubPart(
        "plant stem",
        "green",
        (Placed(Frustum(0.006, 0.005, stem_height), translation=(0, 0, 0.9 * pot_height)),),
    )
    leaves = []
    top = 0.9 * pot_height + stem_height
    for k in range(int(rng.integers(3, 6))):
        angle = 2 * math.pi * k / 5 + rng.uniform(-0.3, 0.3)
        leaf = Placed(
            Ellipsoid((0.055, 0.022, 0.004)),
            rotation_z(angle),
            (0.045 * math.cos(angle), 0.045 * math.sin(angle), top - 0.02 * k),
        )
        leaves.append(SubPart("leaf", "green", (leaf,)))
    plant = Part("plant", (stem, *leaves))
    return ObjectModel("potted plant", (pot, plant), footprint=r1 + 0.05, density=1.5)


def build_bottle(rng: np.random.Generator) -> ObjectModel:
    radius = rng.uniform(0.03, 0.04)
    height = rng.uniform(0.14, 0.19)
    glass = _pick(rng, ("green", "blue", "white", "brown"))
    label_color = _pick(rng, (*_BRIGHT, "white"))
    low, high = 0.3 * height, 0.7 * height
    body = Part(
        "bottle body",
        (
            SubPart(
                "bottle body",
                glass,
                (
                    Placed(Frustum(radius, radius, low)),
                    Placed(Frustum(radius, radius, height - high), translation=(0, 0, high)),
                ),
            ),
            SubPart(
                "bottle label",
                label_color,
                (Placed(Frustum(radius, radius, high - low), translation=(0, 0, low)),),
            ),
        ),
    )
    neck = Placed(Frustum(radius, 0.013, 0.05), translation=(0.0, 0.0, height))
    cap = (
        Placed(Frustum(0.014, 0.014, 0.02), translation=(0.0, 0.0, height + 0.05)),
        Placed(Disc(0.014), translation=(0.0, 0.0, height + 0.07)),
    )
    parts = (
        body,
        _single("bottle neck", glass, neck),
        _single("bottle cap", _pick(rng, ("red", "black", "white", "yellow")), *cap),
    )
    return ObjectModel("bottle", parts, footprint=radius + 0.01, density=1.5)


def build_table(rng: np.random.Generator) -> tuple[ObjectModel, tuple[float, float, float]]:
    """The table and its top's (length, width, height above the floor) in metres."""
    length, width = rng.uniform(1.4, 1.8), rng.uniform(0.8, 1.0)
    height, thickness, leg = 0.75, 0.04, 0.06
    wood = _pick(rng, ("brown", "beige", "white", "black"))
    top = Placed(Box(length, width, thickness), translation=(0.0, 0.0, height - thickness))
    legs = tuple(
        SubPart(
            "table leg",
            wood,
            (
                Placed(
                    Box(leg, leg, height - thickness, faces=("+x", "-x", "+y", "-y")),
                    translation=(sx * (length - leg) / 2.2, sy * (width - leg) / 2.2, 0.0),
                ),
            ),
        )
        for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1))
    )
    parts = (_single("table top", wood, top), Part("table legs", legs))
    return ObjectModel("table", parts, footprint=0.0, density=0.6), (length, width, height)


def build_floor(rng: np.random.Generator, size: float) -> ObjectModel:
    color = _pick(rng, ("grey", "beige", "brown", "white"))
    return ObjectModel(
        "floor", (_single("floor", color, Placed(Rect(size, size))),), footprint=0.0, density=0.2
    )


TABLE_OBJECTS: dict[str, Callable[[np.random.Generator], ObjectModel]] = {
    "mug": build_mug,
    "lamp": build_lamp,
    "teddy bear": build_teddy_bear,
    "stack of books": build_stack_of_books,
    "potted plant": build_potted_plant,
    "bottle": build_bottle,
}
"""Objects that stand on the table, by type name."""

FLOOR_OBJECTS: dict[str, Callable[[np.random.Generator], ObjectModel]] = {"chair": build_chair}
"""Objects that stand on the floor beside the table."""

CONFUSABLE_NAMES: tuple[tuple[str, str], ...] = (
    ("mug", "bottle"),  # drinking vessels on a table
    ("mug body", "bottle body"),  # a glazed or glass cylinder
    ("table", "chair"),  # wooden furniture of the same colours
    ("table top", "chair seat"),  # a flat horizontal board
    ("table leg", "chair leg"),  # a square wooden post
    ("table legs", "chair legs"),
    ("lamp shade", "flower pot"),  # a truncated cone, open at the top
    ("lamp pole", "plant stem"),  # a thin vertical rod
    ("coffee", "soil"),  # a dark brown disc inside a container
)
"""Pairs of catalog names that look alike in a crop, across objects: what an image model
confuses (as CLIP confuses a cup with a mug). The oracle's ``confusion`` mixes each name's
partner into its features (:class:`thgs.synthetic.OracleConfig`)."""
