"""Surface primitives sampled uniformly by area, with outward unit normals.

Every primitive lives in its own frame (z up, metres); :class:`Placed` puts one into a part's
frame with a rotation and a translation. Sampling is exact-area uniform (inverse CDF or rejection
on the area element), so Gaussian density is the same on every surface of a sub-part.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "Box",
    "Disc",
    "Ellipsoid",
    "Frustum",
    "Placed",
    "Rect",
    "TorusArc",
    "rotation_x",
    "rotation_z",
]


def rotation_z(angle: float) -> np.ndarray:
    """[3, 3] rotation by ``angle`` radians about +z."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_x(angle: float) -> np.ndarray:
    """[3, 3] rotation by ``angle`` radians about +x."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


@dataclass(frozen=True)
class Rect:
    """The rectangle ``|x| ≤ sx/2, |y| ≤ sy/2`` in the plane z = 0, normal +z."""

    sx: float
    sy: float

    @property
    def area(self) -> float:
        return self.sx * self.sy

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        u = rng.uniform(-0.5, 0.5, size=(n, 2)) * (self.sx, self.sy)
        points = np.column_stack([u, np.zeros(n)])
        return points, np.tile([0.0, 0.0, 1.0], (n, 1))


@dataclass(frozen=True)
class Disc:
    """The disc of ``radius`` around the origin in the plane z = 0, normal +z (−z if ``down``)."""

    radius: float
    down: bool = False

    @property
    def area(self) -> float:
        return math.pi * self.radius**2

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        r = self.radius * np.sqrt(rng.uniform(size=n))
        theta = rng.uniform(0.0, 2 * math.pi, size=n)
        points = np.column_stack([r * np.cos(theta), r * np.sin(theta), np.zeros(n)])
        normal = [0.0, 0.0, -1.0 if self.down else 1.0]
        return points, np.tile(normal, (n, 1))


@dataclass(frozen=True)
class Box:
    """The surface of the box ``[-sx/2, sx/2] × [-sy/2, sy/2] × [0, sz]``.

    ``faces`` picks which faces exist, from ``+x, -x, +y, -y, +z, -z`` (a box standing on a
    support has no visible bottom).
    """

    sx: float
    sy: float
    sz: float
    faces: tuple[str, ...] = ("+x", "-x", "+y", "-y", "+z", "-z")

    def _face_areas(self) -> np.ndarray:
        areas = {"x": self.sy * self.sz, "y": self.sx * self.sz, "z": self.sx * self.sy}
        return np.array([areas[face[1]] for face in self.faces])

    @property
    def area(self) -> float:
        return float(self._face_areas().sum())

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        areas = self._face_areas()
        face = rng.choice(len(self.faces), size=n, p=areas / areas.sum())
        u = rng.uniform(-0.5, 0.5, size=(n, 3)) * (self.sx, self.sy, self.sz)
        u[:, 2] += 0.5 * self.sz
        half = np.array([self.sx, self.sy, self.sz]) / 2
        normals = np.zeros((n, 3))
        for index, name in enumerate(self.faces):
            rows = face == index
            axis = "xyz".index(name[1])
            sign = 1.0 if name[0] == "+" else -1.0
            u[rows, axis] = (half[axis] * sign) + (half[axis] if axis == 2 else 0.0)
            normals[rows, axis] = sign
        return u, normals


@dataclass(frozen=True)
class Frustum:
    """The side of a truncated cone around +z: radius ``r0`` at z = 0, ``r1`` at z = ``height``.

    ``inward`` flips the normals (the inside wall of a mug or a lamp shade).
    """

    r0: float
    r1: float
    height: float
    inward: bool = False

    @property
    def slant(self) -> float:
        return math.hypot(self.height, self.r1 - self.r0)

    @property
    def area(self) -> float:
        return math.pi * (self.r0 + self.r1) * self.slant

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        # the area element grows with the radius r(t) = r0 + (r1 − r0) t: invert its CDF
        u = rng.uniform(size=n)
        d = self.r1 - self.r0
        if abs(d) < 1e-12 * max(self.r0, self.r1):
            t = u
        else:
            t = (np.sqrt(self.r0**2 + u * (self.r1**2 - self.r0**2)) - self.r0) / d
        theta = rng.uniform(0.0, 2 * math.pi, size=n)
        radius = self.r0 + d * t
        points = np.column_stack([radius * np.cos(theta), radius * np.sin(theta), t * self.height])
        normals = np.column_stack(
            [self.height * np.cos(theta), self.height * np.sin(theta), np.full(n, -d)]
        )
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        return points, -normals if self.inward else normals


@dataclass(frozen=True)
class Ellipsoid:
    """The ellipsoid with semi-axes ``radii`` (x, y, z) centred at the origin."""

    radii: tuple[float, float, float]

    @property
    def area(self) -> float:
        # Knud Thomsen's approximation (relative error below 1.1 %): used only to share samples
        a, b, c = self.radii
        p = 1.6075
        return 4 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        radii = np.asarray(self.radii, dtype=np.float64)
        inverse = 1.0 / radii
        chosen: list[np.ndarray] = []
        count = 0
        while count < n:
            # uniform directions, kept with probability ∝ the area element of the map to the
            # ellipsoid, which makes the kept points uniform in area on it
            directions = rng.normal(size=(2 * (n - count) + 16, 3))
            directions /= np.linalg.norm(directions, axis=1, keepdims=True)
            element = np.linalg.norm(directions * inverse, axis=1) / inverse.min()
            keep = rng.uniform(size=len(directions)) < element
            chosen.append(directions[keep])
            count += int(keep.sum())
        directions = np.concatenate(chosen)[:n]
        normals = directions * inverse
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        return directions * radii, normals


@dataclass(frozen=True)
class TorusArc:
    """Part of a torus around +z (ring radius ``ring``, tube radius ``tube``), ring angles in
    ``[start, stop]`` radians from +x: a mug's handle."""

    ring: float
    tube: float
    start: float
    stop: float

    @property
    def area(self) -> float:
        return (self.stop - self.start) * self.ring * 2 * math.pi * self.tube

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        chosen: list[np.ndarray] = []
        count = 0
        bound = self.ring + self.tube
        while count < n:
            phi = rng.uniform(0.0, 2 * math.pi, size=2 * (n - count) + 16)
            keep = rng.uniform(size=len(phi)) * bound < self.ring + self.tube * np.cos(phi)
            chosen.append(phi[keep])
            count += int(keep.sum())
        phi = np.concatenate(chosen)[:n]
        theta = rng.uniform(self.start, self.stop, size=n)
        radial = np.column_stack([np.cos(theta), np.sin(theta), np.zeros(n)])
        normals = radial * np.cos(phi)[:, None] + np.column_stack(
            [np.zeros(n), np.zeros(n), np.sin(phi)]
        )
        points = radial * self.ring + normals * self.tube
        return points, normals


@dataclass(frozen=True)
class Placed:
    """A primitive moved into its parent's frame: ``p_parent = rotation · p + translation``."""

    surface: Rect | Disc | Box | Frustum | Ellipsoid | TorusArc
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def area(self) -> float:
        return self.surface.area

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        """[n, 3] points and [n, 3] unit normals in the parent frame."""
        points, normals = self.surface.sample(rng, n)
        return points @ self.rotation.T + np.asarray(self.translation), normals @ self.rotation.T
