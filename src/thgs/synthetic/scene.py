"""Procedural scenes: a floor, a table, objects on it and a chair beside it, as Gaussians.

World frame: metres, z up, the floor at z = 0, the table centred on the z axis. Gaussians are
sampled uniformly on every sub-part's surfaces and shaped like a trained scene's: 2DGS surfels (or
flat 3DGS ellipsoids) aligned with the surface, sizes from the local sample spacing, mostly opaque
with a tail of faint ones, colours jittered around the sub-part's palette colour; optionally a few
floaters with no ground truth. Same config (seed included) → the same scene, bit for bit.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from thgs.errors import InputError
from thgs.eval.ground_truth import Hierarchy
from thgs.scene import Cameras, Gaussians
from thgs.scene.cameras import viewmat_from_pose
from thgs.scene.gaussians import SH_C0
from thgs.synthetic.catalog import (
    FLOOR_OBJECTS,
    PALETTE,
    TABLE_OBJECTS,
    ObjectModel,
    build_floor,
    build_table,
)
from thgs.synthetic.shapes import rotation_z

__all__ = ["PRESETS", "PlacedObject", "SceneConfig", "SyntheticScene", "generate_scene", "preset"]

logger = logging.getLogger(__name__)

_FLOOR_SIZE = 3.6
_MIN_GAUSSIANS_PER_SUBPART = 30


@dataclass(frozen=True)
class SceneConfig:
    """What to generate.

    Attributes:
        gaussians: total number of Gaussians (floaters included).
        views: number of cameras.
        width, height: image size in pixels.
        kind: "2dgs" surfels or "3dgs" flat ellipsoids.
        table_objects: how many objects stand on the table (at least 4 distinct types when there
            is room; the rest may repeat a type, so categories can be shared).
        floaters: fraction of Gaussians floating in the air, with no ground truth.
        sh_degree: spherical-harmonics degree written to the PLY (colours are view-independent:
            higher bands are zero).
        seed: every random draw derives from it.
    """

    gaussians: int = 50_000
    views: int = 24
    width: int = 320
    height: int = 240
    kind: Literal["2dgs", "3dgs"] = "2dgs"
    table_objects: int = 6
    floaters: float = 0.002
    sh_degree: int = 0
    seed: int = 0

    def check(self) -> SceneConfig:
        if self.gaussians < 1000:
            raise InputError(
                "SceneConfig.gaussians", f"must be at least 1000, got {self.gaussians}"
            )
        if self.views < 1 or self.width < 16 or self.height < 16:
            raise InputError("SceneConfig", "needs at least one view of at least 16×16 pixels")
        if self.kind not in ("2dgs", "3dgs"):
            raise InputError("SceneConfig.kind", f"must be '2dgs' or '3dgs', got {self.kind!r}")
        if not 1 <= self.table_objects <= 10:
            raise InputError("SceneConfig.table_objects", "must be between 1 and 10")
        if not 0.0 <= self.floaters < 0.5:
            raise InputError("SceneConfig.floaters", "must be a fraction in [0, 0.5)")
        if not 0 <= self.sh_degree <= 3:
            raise InputError("SceneConfig.sh_degree", "must be 0, 1, 2 or 3")
        return self


PRESETS: dict[str, SceneConfig] = {
    "synth-small": SceneConfig(gaussians=50_000, views=24, width=320, height=240),
    "synth-medium": SceneConfig(gaussians=300_000, views=60, width=640, height=480),
    "synth-large": SceneConfig(gaussians=1_000_000, views=200, width=986, height=728),
}
"""Named scene sizes; synth-large matches a LERF scene (about 1M Gaussians, 986×728 views)."""


def preset(name: str, **overrides) -> SceneConfig:
    """The config of preset ``name`` with fields replaced by ``overrides`` (e.g. ``seed=3``).

    Raises:
        InputError: unknown preset name.
    """
    if name not in PRESETS:
        raise InputError(name, f"unknown preset (choose from {', '.join(PRESETS)})")
    return replace(PRESETS[name], **overrides).check()


@dataclass(frozen=True)
class PlacedObject:
    """An object and its pose: ``p_world = R_z(yaw) · p_object + position``."""

    model: ObjectModel
    position: tuple[float, float, float]
    yaw: float


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """A generated scene.

    Attributes:
        gaussians: N Gaussians, world frame (metres).
        cameras: the views, OpenCV axes, looking at the table.
        hierarchy: per-Gaussian sub-part / part / object ids and names (floaters: −1).
        objects: the placed objects; object id i is ``objects[i]``.
        config: what it was generated from.
    """

    gaussians: Gaussians
    cameras: Cameras
    hierarchy: Hierarchy
    objects: tuple[PlacedObject, ...]
    config: SceneConfig


def _layout(rng: np.random.Generator, config: SceneConfig) -> tuple[list[PlacedObject], float]:
    """The floor, the table, a chair and the table's objects, placed without overlap."""
    table, (length, width, height) = build_table(rng)
    placed = [
        PlacedObject(build_floor(rng, _FLOOR_SIZE), (0.0, 0.0, 0.0), 0.0),
        PlacedObject(table, (0.0, 0.0, 0.0), 0.0),
    ]
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    chair = FLOOR_OBJECTS["chair"](rng)
    chair_at = (rng.uniform(-0.25, 0.25) * length, side * (width / 2 + 0.3), 0.0)
    placed.append(PlacedObject(chair, chair_at, -side * math.pi / 2))

    types = list(TABLE_OBJECTS)
    order = [types[i] for i in rng.permutation(len(types))]
    chosen = order[: min(config.table_objects, 4)]
    chosen += [
        types[int(i)] for i in rng.integers(len(types), size=max(0, config.table_objects - 4))
    ]
    footprints: list[tuple[float, float, float]] = []
    for name in chosen:
        model = TABLE_OBJECTS[name](rng)
        margin_x = length / 2 - model.footprint - 0.04
        margin_y = width / 2 - model.footprint - 0.04
        for _ in range(200):
            x, y = rng.uniform(-margin_x, margin_x), rng.uniform(-margin_y, margin_y)
            if all(math.hypot(x - u, y - v) > r + model.footprint + 0.03 for u, v, r in footprints):
                footprints.append((x, y, model.footprint))
                placed.append(PlacedObject(model, (x, y, height), rng.uniform(0, 2 * math.pi)))
                break
        else:
            logger.info("no room left on the table for a %s; skipped", name)
    return placed, height


def _tables(objects: list[PlacedObject]) -> tuple[tuple, list, list, list]:
    """Flatten objects → node names per level, parents, and (sub-part, object index) pairs."""
    subpart_names, part_names, object_names = [], [], []
    subpart_parent, part_parent, subparts = [], [], []
    for o, placed in enumerate(objects):
        object_names.append(placed.model.name)
        for part in placed.model.parts:
            part_parent.append(o)
            part_names.append(part.name)
            for subpart in part.subparts:
                subpart_parent.append(len(part_names) - 1)
                subpart_names.append(subpart.name)
                subparts.append((subpart, o))
    names = (subpart_names, part_names, object_names)
    return names, subpart_parent, part_parent, subparts


def _allocate(weights: np.ndarray, total: int, minimum: int) -> np.ndarray:
    """Integer counts ∝ weights summing to ``total``, none below ``minimum`` (largest remainder)."""
    counts = np.maximum(minimum, np.floor(weights / weights.sum() * total)).astype(np.int64)
    surplus = int(counts.sum()) - total
    largest = int(np.argmax(counts))
    counts[largest] -= surplus
    if counts[largest] < minimum:
        raise InputError("SceneConfig.gaussians", f"too few Gaussians ({total}) for this scene")
    return counts


def _frames(normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """[n, 3, 3] right-handed frames [t1, t2, normal] (columns) with a random in-plane turn."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    angle = rng.uniform(0.0, 2 * math.pi, size=(len(normals), 1))
    u = np.cos(angle) * t1 + np.sin(angle) * t2
    v = np.cross(normals, u)
    return np.stack([u, v, normals], axis=2)


def _cameras(rng: np.random.Generator, config: SceneConfig, table_height: float) -> Cameras:
    viewmats, Ks, names = [], [], []
    focal = 0.8 * config.width
    K = [[focal, 0.0, config.width / 2], [0.0, focal, config.height / 2], [0.0, 0.0, 1.0]]
    for i in range(config.views):
        azimuth = 2 * math.pi * (i + rng.uniform(-0.3, 0.3)) / config.views
        elevation = math.radians(rng.uniform(25.0, 65.0))
        distance = rng.uniform(1.1, 1.8)
        target = np.array(
            [rng.normal(0, 0.1), rng.normal(0, 0.08), table_height + rng.uniform(0.0, 0.1)]
        )
        eye = target + distance * np.array(
            [
                math.cos(elevation) * math.cos(azimuth),
                math.cos(elevation) * math.sin(azimuth),
                math.sin(elevation),
            ]
        )
        forward = (target - eye) / np.linalg.norm(target - eye)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        # columns: the camera's x (right), y (down) and z (forward) axes in world coordinates
        camera_to_world = np.stack([right, np.cross(forward, right), forward], axis=1)
        viewmats.append(viewmat_from_pose(camera_to_world, eye))
        Ks.append(K)
        names.append(f"frame_{i + 1:05d}")
    widths, heights = [config.width] * config.views, [config.height] * config.views
    return Cameras.from_lists(viewmats, Ks, widths, heights, names).check(source="synthetic")


def generate_scene(config: SceneConfig) -> SyntheticScene:
    """Generate the scene ``config`` describes (deterministic in ``config.seed``)."""
    config.check()
    layout_rng, sample_rng, camera_rng = (
        np.random.default_rng([config.seed, stream]) for stream in range(3)
    )
    objects, table_height = _layout(layout_rng, config)
    names, subpart_parent, part_parent, subparts = _tables(objects)

    n_floaters = round(config.floaters * config.gaussians)
    weights = np.array([sub.area * objects[o].model.density for sub, o in subparts])
    counts = _allocate(weights, config.gaussians - n_floaters, _MIN_GAUSSIANS_PER_SUBPART)

    means, normals, colors, spacing, sub_ids = [], [], [], [], []
    for index, ((subpart, o), count) in enumerate(zip(subparts, counts)):
        pose = objects[o]
        rotation = rotation_z(pose.yaw)
        areas = np.array([surface.area for surface in subpart.surfaces])
        shares = sample_rng.multinomial(count, areas / areas.sum())
        for surface, n in zip(subpart.surfaces, shares):
            points, surface_normals = surface.sample(sample_rng, int(n))
            means.append(points @ rotation.T + np.asarray(pose.position))
            normals.append(surface_normals @ rotation.T)
        base = np.asarray(PALETTE[subpart.color])
        colors.append(np.clip(base + sample_rng.normal(0, 0.03, size=(count, 3)), 0.01, 0.99))
        spacing.append(np.full(count, math.sqrt(subpart.area / count)))
        sub_ids.append(np.full(count, index))
    means_np = np.concatenate(means)
    normals_np = np.concatenate(normals)
    frames = _frames(normals_np, sample_rng)
    spacing_np = np.concatenate(spacing)
    sub_np = np.concatenate(sub_ids)
    n = len(means_np)
    scale_1 = spacing_np * sample_rng.uniform(0.55, 0.95, size=n)
    scale_2 = scale_1 * sample_rng.uniform(0.6, 1.0, size=n)
    scales = [scale_1, scale_2] if config.kind == "2dgs" else [scale_1, scale_2, scale_1 * 0.05]
    opaque = sample_rng.uniform(size=n) < 0.85
    opacity = np.where(
        opaque, sample_rng.uniform(0.75, 0.99, size=n), sample_rng.uniform(0.1, 0.75, size=n)
    )
    color_np = np.concatenate(colors)
    quats = Rotation.from_matrix(frames).as_quat()[:, [3, 0, 1, 2]]

    if n_floaters:
        floater_rng = np.random.default_rng([config.seed, 3])
        low, high = np.array([-1.2, -1.2, 0.2]), np.array([1.2, 1.2, 1.8])
        means_np = np.concatenate([means_np, floater_rng.uniform(low, high, (n_floaters, 3))])
        size = floater_rng.uniform(0.01, 0.04, size=n_floaters)
        scales = [np.concatenate([s, size * f]) for s, f in zip(scales, (1.0, 0.8, 0.6))]
        opacity = np.concatenate([opacity, floater_rng.uniform(0.05, 0.4, size=n_floaters)])
        color_np = np.concatenate([color_np, floater_rng.uniform(0.1, 0.9, (n_floaters, 3))])
        random_quats = floater_rng.normal(size=(n_floaters, 4))
        quats = np.concatenate(
            [quats, random_quats / np.linalg.norm(random_quats, axis=1)[:, None]]
        )
        sub_np = np.concatenate([sub_np, np.full(n_floaters, -1)])

    # trained PLYs are not grouped by object: shuffle so that order carries no ground truth
    order = np.random.default_rng([config.seed, 4]).permutation(len(means_np))
    subpart_parent_np = np.asarray(subpart_parent, dtype=np.int32)
    part_parent_np = np.asarray(part_parent, dtype=np.int32)
    hierarchy = Hierarchy.from_subparts(
        sub_np[order], subpart_parent_np, part_parent_np, names, source="synthetic"
    )

    k = (config.sh_degree + 1) ** 2
    sh = np.zeros((len(order), k, 3), dtype=np.float32)
    sh[:, 0] = (color_np[order] - 0.5) / SH_C0
    opacity = np.clip(opacity[order], 1e-4, 1 - 1e-4)

    def tensor(array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))

    gaussians = Gaussians(
        means=tensor(means_np[order]),
        quats=tensor(quats[order]),
        scales=tensor(np.log(np.column_stack(scales)[order])),
        opacities=tensor(np.log(opacity / (1 - opacity))),
        sh=torch.from_numpy(sh),
        normals=torch.zeros(len(order), 3),
    ).check(source="synthetic")
    cameras = _cameras(camera_rng, config, table_height)
    logger.info(
        "generated %d objects, %d parts, %d sub-parts, %d Gaussians (%d floaters), %d views",
        len(names[2]),
        len(names[1]),
        len(names[0]),
        len(gaussians),
        n_floaters,
        len(cameras),
    )
    return SyntheticScene(gaussians, cameras, hierarchy, tuple(objects), config)
