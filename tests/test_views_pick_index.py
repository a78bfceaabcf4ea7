"""The pick index: its candidates hold every Gaussian that can reach the pixel, an indexed pick is
exactly the full one-pixel render's max-weight Gaussian, a spread-out scene gives few candidates,
and bad input is refused."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from thgs import Cameras, Gaussians, InputError
from thgs.field import SemanticField
from thgs.hierarchy import RegionLevels
from thgs.pick_index import PickIndex
from thgs.render import RasterConfig, render
from thgs.render._reference import dense_alpha
from thgs.scene.gaussians import quaternions_to_matrices
from thgs.views import pick

CONFIGS = {
    "default": RasterConfig(),
    "wide filters": RasterConfig(eps2d=3.0, filter_inv_square=0.25, alpha_min=0.002),
    "narrow filters": RasterConfig(eps2d=0.0, filter_inv_square=8.0, alpha_min=0.05, near=0.5),
    "far plane": RasterConfig(near=0.05, far=6.0),
}


def camera(width=48, height=36, *, focal=(40.0, 46.0), principal=(21.3, 19.1), turn=0.0):
    """A pinhole camera at (0.3, −0.2, −0.5) turned by ``turn`` radians about a tilted axis."""
    axis = torch.tensor([0.3, 1.0, 0.2], dtype=torch.float64)
    quat = torch.cat([torch.tensor([math.cos(turn / 2)]), math.sin(turn / 2) * axis / axis.norm()])
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = quaternions_to_matrices(quat[None])[0]
    viewmat[:3, 3] = torch.tensor([0.3, -0.2, -0.5], dtype=torch.float64)
    K = torch.tensor(
        [[focal[0], 0, principal[0]], [0, focal[1], principal[1]], [0, 0, 1]], dtype=torch.float64
    )
    return Cameras(
        viewmat[None], K[None], torch.tensor([width]), torch.tensor([height]), ("view.png",)
    ).check()


def scene(kind: str, n: int = 300, seed: int = 0, cam: Cameras | None = None) -> Gaussians:
    """Random Gaussians seen by ``cam``: mostly in front of it, some behind it, at the near plane
    and beside the image; tiny, large and huge, tilted, of high and low opacity."""
    cam = camera() if cam is None else cam
    g = torch.Generator().manual_seed(seed)
    z = torch.rand(n, generator=g).double() * 5 + 1
    z[:10] = torch.tensor([-1.0, -0.3, 0.0, 0.03, 0.1, 0.19, 0.21, 0.3, 0.49, 0.51])
    xy = (torch.rand(n, 2, generator=g).double() - 0.5) * 1.6 * z[:, None].abs().clamp_min(0.5)
    xy[10:20] *= 2.5  # partly or wholly beside the image
    points = torch.cat([xy, z[:, None]], dim=1)
    rotation, translation = cam.viewmats[0, :3, :3], cam.viewmats[0, :3, 3]
    means = (points - translation) @ rotation  # camera frame → world
    scales = torch.rand(n, 2 if kind == "2dgs" else 3, generator=g) * 4 - 6  # 0.0025 … 0.14
    scales[20:30] = torch.rand(10, scales.shape[1], generator=g) * 1.5 - 0.5  # large: 0.6 … 2.7
    scales[30:35] = -9.0  # tiny
    scales[3:8] = 0.2  # as large as their distance, or larger
    quats = torch.randn(n, 4, generator=g)
    opacities = torch.randn(n, generator=g) * 3
    opacities[35:45] = -6.0  # below 1/255
    return Gaussians(
        means.float(), quats, scales, opacities, torch.randn(n, 1, 3, generator=g)
    ).check()


def identity_field(n: int) -> SemanticField:
    """A field where every Gaussian is its own region at every level (all that pick reads)."""
    ids = np.arange(n, dtype=np.int32)
    return SemanticField(
        levels=RegionLevels(np.repeat(ids[:, None], 4, axis=1), (ids, ids, ids), (n,) * 4),
        features=(np.zeros((n, 1), np.float32),) * 3,
        seen=(np.zeros(n, bool),) * 3,
        space="none",
        fingerprint="",
        config={},
        timings={},
    )


def one_pixel(cam: Cameras, x: int, y: int) -> Cameras:
    """The 1×1 camera through pixel (x, y), as :func:`thgs.views.pick` renders it."""
    Ks = cam.Ks.clone()
    Ks[0, 0, 2] -= x
    Ks[0, 1, 2] -= y
    ones = torch.ones(1, dtype=torch.int64)
    return Cameras(cam.viewmats, Ks, ones, ones.clone(), cam.names)


def full_max_id(gaussians: Gaussians, cam: Cameras, x: int, y: int, config: RasterConfig) -> int:
    """The max-weight Gaussian at (x, y) from a render of all N Gaussians (pick without index)."""
    zeros = torch.zeros(len(gaussians), 1, dtype=torch.float64)
    return int(render(gaussians, one_pixel(cam, x, y), zeros, config=config).max_id[0, 0])


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
@pytest.mark.parametrize("config_name", list(CONFIGS))
@pytest.mark.parametrize(("seed", "turn"), [(0, 0.0), (1, 0.7)])
def test_candidates_hold_every_reaching_gaussian_and_pick_is_exact(kind, config_name, seed, turn):
    config = CONFIGS[config_name]
    cam = camera(turn=turn)
    gaussians = scene(kind, seed=seed, cam=cam)
    field = identity_field(len(gaussians))
    index = PickIndex.build(gaussians, cell_size=16)
    rng = np.random.default_rng(seed)
    picked, reaching, sizes = 0, 0, []
    for x, y in zip(rng.integers(0, 48, 60), rng.integers(0, 36, 60)):
        x, y = int(x), int(y)
        candidates = index.candidates(gaussians, cam, (x, y), config=config)
        assert np.all(np.diff(candidates) > 0)
        alpha, projection = dense_alpha(gaussians, one_pixel(cam, x, y), config)
        needed = np.flatnonzero((projection.valid & (alpha[0] >= config.alpha_min)).numpy())
        missing = np.setdiff1d(needed, candidates)
        assert missing.size == 0, f"pixel ({x}, {y}) misses Gaussians {missing.tolist()}"
        expected = full_max_id(gaussians, cam, x, y, config)
        result = pick(field, gaussians, cam, (x, y), config=config, index=index)
        assert (None if result is None else result.gaussian) == (None if expected < 0 else expected)
        picked += result is not None
        reaching += needed.size
        sizes.append(candidates.size)
    # the scene covers most pixels, and the index still leaves most Gaussians out
    assert picked >= 30 and reaching >= 60
    assert np.mean(sizes) < 0.5 * len(gaussians)


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_cell_size_does_not_change_the_candidates(kind):
    # the members of a cell are tested one by one, so the cells may only skip what that test drops
    cam = camera(turn=0.3)
    gaussians = scene(kind, seed=4, cam=cam)
    indexes = [PickIndex.build(gaussians, cell_size=size) for size in (1, 7, 64, 10_000)]
    for x, y in [(0, 0), (47, 35), (20, 18), (5, 30), (40, 3)]:
        sets = [index.candidates(gaussians, cam, (x, y)) for index in indexes]
        for other in sets[1:]:
            np.testing.assert_array_equal(other, sets[0])


def spread_out(kind: str, n: int = 20_000) -> Gaussians:
    """A 100 × 100 floor of small Gaussians 2 units below the camera."""
    g = torch.Generator().manual_seed(9)
    means = torch.rand(n, 3, generator=g) * torch.tensor([100.0, 0.2, 100.0]) - torch.tensor(
        [50.0, -2.0, 10.0]
    )
    scales = torch.full((n, 2 if kind == "2dgs" else 3), math.log(0.4))
    quats = torch.tensor([[math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0]]).repeat(n, 1)
    return Gaussians(means, quats, scales, torch.full((n,), 2.0), torch.zeros(n, 1, 3)).check()


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_a_spread_out_scene_gives_few_candidates(kind):
    gaussians = spread_out(kind)
    cam = camera(320, 240, focal=(300.0, 300.0), principal=(160.0, 120.0))
    index = PickIndex.build(gaussians)
    field = identity_field(len(gaussians))
    for x, y in [(160, 200), (30, 230), (300, 150)]:
        candidates = index.candidates(gaussians, cam, (x, y))
        assert 0 < candidates.size < 0.05 * len(gaussians), candidates.size
        expected = full_max_id(gaussians, cam, x, y, RasterConfig())
        assert expected >= 0
        assert pick(field, gaussians, cam, (x, y), index=index).gaussian == expected
    # a pixel above the horizon sees nothing; only surfels as large as their distance from the
    # camera (whose 2D filter may land anywhere) are candidates there
    sky = index.candidates(gaussians, cam, (160, 10))
    assert sky.size < 0.005 * len(gaussians)
    assert pick(field, gaussians, cam, (160, 10), index=index) is None


def test_pick_without_an_index_tests_every_gaussian():
    cam = camera()
    gaussians = scene("3dgs", seed=2, cam=cam)
    field = identity_field(len(gaussians))
    for x, y in [(10, 10), (24, 18), (40, 30)]:
        expected = full_max_id(gaussians, cam, x, y, RasterConfig())
        result = pick(field, gaussians, cam, (x, y))
        assert (None if result is None else result.gaussian) == (None if expected < 0 else expected)


def test_bad_input():
    cam = camera()
    gaussians = scene("2dgs", n=60, cam=cam)
    index = PickIndex.build(gaussians)
    with pytest.raises(InputError, match=r"view: pixel \(48, 0\) is outside the 48×36 image"):
        index.candidates(gaussians, cam, (48, 0))
    with pytest.raises(InputError, match=r"view: pixel \(3, -1\) is outside"):
        pick(identity_field(60), gaussians, cam, (3, -1), index=index)
    other = gaussians.select(torch.arange(50))
    with pytest.raises(InputError, match="PickIndex: built for 60 2DGS Gaussians but given 50"):
        index.candidates(other, cam, (3, 3))
    with pytest.raises(InputError, match="built for 60 2DGS Gaussians but given 60 3DGS"):
        index.candidates(scene("3dgs", n=60, cam=cam), cam, (3, 3))
    with pytest.raises(InputError, match="built for 60 2DGS Gaussians but given 50"):
        pick(identity_field(50), other, cam, (3, 3), index=index)
    with pytest.raises(InputError, match="expected one camera"):
        index.candidates(gaussians, cam.select([0, 0]), (3, 3))
    with pytest.raises(InputError, match=r"PickIndex.cell_size: must be ≥ 1, got 0"):
        PickIndex.build(gaussians, cell_size=0)


def test_an_empty_scene_has_no_candidates():
    empty = scene("3dgs", n=60).select(torch.zeros(0, dtype=torch.int64))
    index = PickIndex.build(empty)
    assert index.candidates(empty, camera(), (3, 3)).size == 0
