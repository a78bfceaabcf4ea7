"""The gsplat backend (thgs.render._gsplat).

On CUDA (skipped without a GPU or without gsplat's kernels): against the torch backend on random
2DGS and 3DGS scenes with gsplat's α cap, the adjoint identity, listing the pairs a few tiles
at a time, and no tile listing more pairs than its bound. Everywhere: backend resolution, the
reasons gsplat refuses a device, a dtype or a missing install, the log of the settings gsplat
cannot honour, the pair weights recomputed in torch against the brute-force reference, and the
sizing of the pair listing (per-tile bounds against a pixel count, blocks, the memory budget).

Tolerances against the torch backend: gsplat bins 2DGS surfels by 3.33× their projected 1σ
ellipse, which drops some contributions with α ≥ 1/255 (thgs.render._gsplat says which; its 3DGS
binning drops none), and both compute in float32 (gsplat with ``__expf``), which can flip the
α ≥ 1/255 test and the stop rule at their thresholds. Simulating gsplat's binning on these
scenes on the CPU (float64) gives at most 0.011 in α (mean 3e-5), 1.3 % in depth and, for the
Gaussians with weight sums above 1, 11 % in a feature sum (of Σ_x w |F|), 4 % in a weight sum
and 9 % in a pixel count; the bounds below leave room for the float32 effects.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from test_render import camera, tiny_scene
from thgs import Cameras, Gaussians, InputError
from thgs.render import (
    RasterConfig,
    _gsplat,
    backends,
    get_backend,
    render,
    resolve_backend,
    splat_back,
    splat_labels,
)
from thgs.render._gsplat import GsplatBackend
from thgs.render._reference import dense_weights

GSPLAT = RasterConfig(alpha_max=0.999, backend="gsplat")
TORCH = RasterConfig(alpha_max=0.999, backend="torch", precision="float32")
"""gsplat's α cap on both; every other setting is the default, which gsplat follows."""

N = 2000
WIDTH, HEIGHT = 160, 120


@pytest.fixture(scope="module")
def cuda() -> torch.device:
    """The CUDA device, or a skip saying why gsplat cannot run on it."""
    device = torch.device("cuda")
    reason = GsplatBackend().unusable(device, torch.float32)
    if reason is None:
        from gsplat.cuda._backend import _C  # compiles gsplat's kernels if they are not built

        if _C is None:
            reason = "gsplat cannot load its CUDA extension"
    if reason is not None:
        pytest.skip(f"gsplat backend unusable here: {reason}")
    return device


def scene(kind: str, seed: int, device: torch.device) -> Gaussians:
    """N Gaussians spread as in test_render's tiny_scene, opacities lowered so that the view
    has pixels that stop early (T ≤ 1e-4) as well as partly covered ones."""
    g = tiny_scene(kind, n=N, seed=seed)
    return Gaussians(g.means, g.quats, g.scales, g.opacities - 2, g.sh).to(device)


def view_camera() -> Cameras:
    return camera(WIDTH, HEIGHT, focal=130.0)


def randn(*shape: int, seed: int, device: torch.device) -> torch.Tensor:
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed)).to(device)


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
@pytest.mark.parametrize("seed", [0, 1])
def test_render_matches_torch(cuda, kind, seed):
    gaussians, cam = scene(kind, seed, cuda), view_camera()
    # 37 channels in [0, 1]: two chunks for gsplat's kernels, the second one padded
    extra = torch.rand(N, 34, generator=torch.Generator().manual_seed(seed)).to(cuda)
    features = torch.cat([gaussians.dc_colors(), extra], dim=1)
    out = render(gaussians, cam, features, config=GSPLAT)
    expected = render(gaussians, cam, features, config=TORCH)
    assert float((expected.alpha > 0.5).float().mean()) > 0.5
    assert float((expected.alpha > 0.999).float().mean()) > 0.02, "the stop rule must matter"

    alpha_error = (out.alpha - expected.alpha).abs()
    assert float(alpha_error.max()) <= 2e-2
    assert float(alpha_error.mean()) < 1e-3
    image_error = (out.image - expected.image).abs()
    assert float(image_error.max()) <= 3e-2  # a dropped contribution also raises later weights
    assert float(image_error.mean()) < 1e-3
    covered = (out.alpha > 0.5) & (expected.alpha > 0.5)
    depth_error = ((out.depth - expected.depth).abs() / expected.depth.abs())[covered]
    assert float(depth_error.max()) <= 5e-2
    assert float(depth_error.mean()) < 2e-3
    assert torch.equal(out.depth[out.alpha == 0], torch.zeros_like(out.depth[out.alpha == 0]))
    assert float((out.max_id == expected.max_id).float().mean()) >= 0.98
    assert torch.equal(out.max_id < 0, out.alpha == 0)


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
@pytest.mark.parametrize("seed", [0, 1])
def test_splat_back_matches_torch(cuda, kind, seed):
    gaussians, cam = scene(kind, seed, cuda), view_camera()
    pixel_map = randn(HEIGHT, WIDTH, 37, seed=seed + 10, device=cuda)
    mask = randn(HEIGHT, WIDTH, seed=seed + 20, device=cuda) > -0.5
    out = splat_back(gaussians, cam, pixel_map, mask=mask, config=GSPLAT)
    expected = splat_back(gaussians, cam, pixel_map, mask=mask, config=TORCH)
    scale = splat_back(gaussians, cam, pixel_map.abs(), mask=mask, config=TORCH).feature_sums
    large = expected.weight_sums > 1  # Gaussians that matter in the view
    assert int(large.sum()) > 100

    # relative to Σ_x w |F|: a few pixels lost at a box edge can move a sum by 10 % of it
    relative = ((out.feature_sums - expected.feature_sums).abs() / scale)[large]
    assert float(relative.max()) <= 0.25
    assert float((relative > 1e-2).float().mean()) <= 0.02
    torch.testing.assert_close(
        out.weight_sums[large], expected.weight_sums[large], rtol=0.1, atol=0
    )
    torch.testing.assert_close(out.max_weights, expected.max_weights, rtol=0, atol=2e-2)
    count_error = (out.pixel_counts - expected.pixel_counts).abs()
    assert bool((count_error[large] <= 0.15 * expected.pixel_counts[large] + 2).all())
    torch.testing.assert_close(out.depths, expected.depths)
    front = expected.depths > GSPLAT.near
    torch.testing.assert_close(out.centers[front], expected.centers[front])


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
@pytest.mark.parametrize("seed", [0, 1])
def test_splat_labels_matches_torch(cuda, kind, seed):
    gaussians, cam = scene(kind, seed, cuda), view_camera()
    rng = np.random.default_rng(seed)
    coarse = rng.integers(-1, 6, size=(HEIGHT // 8, WIDTH // 8)).repeat(8, 0).repeat(8, 1)
    fine = rng.integers(-1, 12, size=(HEIGHT // 4, WIDTH // 4)).repeat(4, 0).repeat(4, 1)
    maps = torch.from_numpy(np.stack([coarse, fine])).to(cuda)
    out = splat_labels(gaussians, cam, maps, config=GSPLAT)
    expected = splat_labels(gaussians, cam, maps, config=TORCH)

    keys = (out.gaussians * 2 + out.levels) * 100 + out.labels
    assert bool((torch.diff(keys) > 0).all()), "rows sorted by Gaussian, level, label"
    assert bool((out.weights > 0).all())
    got = dict(zip(keys.tolist(), out.weights.tolist()))
    expected_keys = (expected.gaussians * 2 + expected.levels) * 100 + expected.labels
    large = expected.weights > 1
    relative = torch.tensor(
        [
            abs(got.get(key, 0.0) - value) / value
            for key, value in zip(expected_keys[large].tolist(), expected.weights[large].tolist())
        ]
    )
    assert len(relative) > 100
    assert float(relative.max()) <= 0.2
    assert float((relative > 1e-2).float().mean()) <= 0.02
    large = expected.weight_sums > 1
    torch.testing.assert_close(
        out.weight_sums[large], expected.weight_sums[large], rtol=0.1, atol=0
    )
    torch.testing.assert_close(out.max_weights, expected.max_weights, rtol=0, atol=2e-2)
    torch.testing.assert_close(out.depths, expected.depths)


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_adjoint_identity(cuda, kind):
    gaussians, cam = scene(kind, 3, cuda), view_camera()
    f = randn(N, 4, seed=11, device=cuda)
    F = randn(HEIGHT, WIDTH, 4, seed=12, device=cuda)
    lhs = (render(gaussians, cam, f, config=GSPLAT).image.double() * F.double()).sum()
    rhs = (f.double() * splat_back(gaussians, cam, F, config=GSPLAT).feature_sums.double()).sum()
    scale = (render(gaussians, cam, f.abs(), config=GSPLAT).image * F.abs()).sum()
    assert abs(float(lhs - rhs)) <= 1e-4 * float(scale)
    # the fused backward pass and the listed pairs give the same weights
    ones = splat_back(gaussians, cam, torch.ones(HEIGHT, WIDTH, 1, device=cuda), config=GSPLAT)
    torch.testing.assert_close(ones.feature_sums[:, 0], ones.weight_sums, rtol=1e-3, atol=1e-4)
    mask = F[..., 0] > 0
    masked = splat_back(gaussians, cam, F, mask=mask, config=GSPLAT)
    unmasked = splat_back(gaussians, cam, F * mask[..., None], config=GSPLAT)
    torch.testing.assert_close(masked.feature_sums, unmasked.feature_sums)


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_pairs_listed_a_few_tiles_at_a_time(cuda, kind, monkeypatch):
    """Listing the composited pairs in many small blocks of tiles gives the same results."""
    gaussians, cam = scene(kind, 4, cuda), view_camera()
    features = gaussians.dc_colors()
    maps = torch.from_numpy(np.random.default_rng(4).integers(-1, 9, size=(1, HEIGHT, WIDTH)))
    maps = maps.to(cuda)
    whole = render(gaussians, cam, features, config=GSPLAT)
    whole_back = splat_back(gaussians, cam, features.new_ones(HEIGHT, WIDTH, 1), config=GSPLAT)
    whole_labels = splat_labels(gaussians, cam, maps, config=GSPLAT)
    monkeypatch.setattr(_gsplat, "_pair_budget", lambda free_bytes: 3000)
    blocks = render(gaussians, cam, features, config=GSPLAT)
    blocks_back = splat_back(gaussians, cam, features.new_ones(HEIGHT, WIDTH, 1), config=GSPLAT)
    blocks_labels = splat_labels(gaussians, cam, maps, config=GSPLAT)
    assert torch.equal(blocks.max_id, whole.max_id)
    for name in ("weight_sums", "max_weights"):
        torch.testing.assert_close(
            getattr(blocks_back, name), getattr(whole_back, name), rtol=1e-5, atol=1e-6
        )
    assert torch.equal(blocks_back.pixel_counts, whole_back.pixel_counts)
    for name in ("gaussians", "levels", "labels"):
        assert torch.equal(getattr(blocks_labels, name), getattr(whole_labels, name))
    torch.testing.assert_close(blocks_labels.weights, whole_labels.weights, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_tile_bounds_hold_every_listed_pair(cuda, kind):
    """No tile lists more pairs than its bound, and the pair memory stays within the budget's
    order (the bound is what sizes the blocks)."""
    gaussians, cam = scene(kind, 5, cuda), view_camera()
    view = _gsplat._view(gaussians, cam, GSPLAT)
    bounds = _gsplat._tile_pair_bounds(view)
    listed = torch.zeros_like(bounds)
    tiles_x = view.offsets.shape[2]
    for _, pixel_ids, _ in _gsplat._pairs(view):
        x = torch.div(pixel_ids % WIDTH, 16, rounding_mode="floor")
        y = torch.div(torch.div(pixel_ids, WIDTH, rounding_mode="floor"), 16, rounding_mode="floor")
        listed += torch.bincount(y * tiles_x + x, minlength=len(listed))
    assert int(listed.sum()) > 1000
    assert bool((listed <= bounds).all())


def binned_view(kind: str, width: int, height: int, seed: int) -> _gsplat._View:
    """A CPU stand-in for gsplat's binning: random centres and box half extents, each Gaussian
    listed in every tile its box touches (gsplat's tile range), tiles in row-major order."""
    generator = torch.Generator().manual_seed(seed)
    n = 60
    means2d = torch.rand(n, 2, generator=generator) * torch.tensor([width + 20.0, height + 20.0])
    means2d -= 10
    radii = torch.randint(0, 30, (n, 2), generator=generator, dtype=torch.int32)
    tiles_x, tiles_y = -(-width // 16), -(-height // 16)
    listed: list[list[int]] = [[] for _ in range(tiles_x * tiles_y)]
    for g in range(n):
        if radii[g].min() <= 0:
            continue
        (cx, cy), (rx, ry) = means2d[g].tolist(), radii[g].tolist()
        for ty in range(
            max(0, math.floor((cy - ry) / 16)), min(tiles_y, math.ceil((cy + ry) / 16))
        ):
            for tx in range(
                max(0, math.floor((cx - rx) / 16)), min(tiles_x, math.ceil((cx + rx) / 16))
            ):
                listed[ty * tiles_x + tx].append(g)
    counts = torch.tensor([len(ids) for ids in listed])
    return _gsplat._View(
        kind=kind,
        width=width,
        height=height,
        means2d=means2d[None],
        params=torch.zeros(1, n, 3),
        normals=None,
        opacities=torch.ones(1, n),
        depths=torch.ones(n),
        radii=radii[None],
        offsets=(torch.cumsum(counts, 0) - counts).int().reshape(1, tiles_y, tiles_x),
        flatten_ids=torch.tensor([g for ids in listed for g in ids], dtype=torch.int32),
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tile_pair_bounds_count_the_pixels_in_each_box(seed):
    """3DGS: per tile, at least the pixels whose centres lie in each listed Gaussian's box and at
    most those of the box widened by one pixel a side; 2DGS: every tile pixel per intersection.
    Edge tiles count only their pixels inside the image (70×50: tiles of 6 and 2 pixels)."""
    width, height = 70, 50
    view = binned_view("3dgs", width, height, seed)
    starts = [*view.offsets.flatten().tolist(), len(view.flatten_ids)]
    tiles_x = view.offsets.shape[2]
    bounds = _gsplat._tile_pair_bounds(view).tolist()
    assert sum(bounds) > 0
    for tile, bound in enumerate(bounds):
        x0, y0 = (tile % tiles_x) * 16, (tile // tiles_x) * 16
        columns = np.arange(x0, min(x0 + 16, width)) + 0.5
        rows = np.arange(y0, min(y0 + 16, height)) + 0.5
        inside = widened = 0
        for g in view.flatten_ids[starts[tile] : starts[tile + 1]].tolist():
            (cx, cy), (rx, ry) = view.means2d[0, g].tolist(), view.radii[0, g].tolist()
            inside += np.sum(np.abs(columns - cx) <= rx) * np.sum(np.abs(rows - cy) <= ry)
            widened += np.sum(np.abs(columns - cx) <= rx + 1) * np.sum(np.abs(rows - cy) <= ry + 1)
        assert inside <= bound <= widened, tile
    surfels = replace(view, kind="2dgs")
    tile_pixels = [
        (min(x0 + 16, width) - x0) * (min(y0 + 16, height) - y0)
        for y0 in range(0, height, 16)
        for x0 in range(0, width, 16)
    ]
    expected = [(starts[t + 1] - starts[t]) * tile_pixels[t] for t in range(len(tile_pixels))]
    assert _gsplat._tile_pair_bounds(surfels).tolist() == expected


def test_tile_pair_bounds_cap_at_the_pairs_a_pixel_can_hold():
    """A tile crowded with more Gaussians than a pixel can composite (α ≥ 1/255 each, stop at
    T ≤ 1e-4: at most 2344, one more for rounding) is bounded per pixel, not per Gaussian."""
    assert _gsplat._MAX_PAIRS_PER_PIXEL == 2345
    assert (1 - 1 / 255) ** 2344 > 1e-4 > (1 - 1 / 255) ** 2345
    n = 3000
    view = _gsplat._View(
        kind="2dgs",
        width=16,
        height=16,
        means2d=torch.full((1, n, 2), 8.0),
        params=torch.zeros(1, n, 3),
        normals=None,
        opacities=torch.ones(1, n),
        depths=torch.ones(n),
        radii=torch.full((1, n, 2), 20, dtype=torch.int32),
        offsets=torch.zeros(1, 1, 1, dtype=torch.int32),
        flatten_ids=torch.arange(n, dtype=torch.int32),
    )
    assert _gsplat._tile_pair_bounds(view).tolist() == [256 * 2345]
    assert _gsplat._tile_pair_bounds(replace(view, kind="3dgs")).tolist() == [256 * 2345]


def test_tile_blocks_fill_the_budget_in_order():
    """Hand cases: consecutive tiles while their bounds fit; a tile over the budget alone; empty
    tiles ride along."""
    assert _gsplat._tile_blocks([5, 3, 0, 7, 2], 8) == [(0, 3), (3, 4), (4, 5)]
    assert _gsplat._tile_blocks([10, 1, 1], 8) == [(0, 1), (1, 3)]
    assert _gsplat._tile_blocks([0, 0, 0], 1) == [(0, 3)]
    assert _gsplat._tile_blocks([4, 4, 4, 4], 100) == [(0, 4)]
    assert _gsplat._tile_blocks([], 5) == []


def test_pair_budget_takes_half_the_free_memory():
    """8 GiB free: 4 GiB for pairs of 400 bytes; nothing free still lists one tile at a time."""
    assert _gsplat._pair_budget(8 * 2**30) == 4 * 2**30 // 400
    assert _gsplat._pair_budget(0) == 1


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_pair_weights_match_brute_force(kind):
    """The weights recomputed in torch from listed pairs, on the CPU: the pairs of a
    brute-force composite (gsplat's cap), pixel by pixel in compositing order."""
    gaussians, cam = tiny_scene(kind, seed=3), camera(cx=20.3, cy=21.7)
    weights, projection = dense_weights(gaussians, cam, RasterConfig(alpha_max=0.999))
    height, width, n = weights.shape
    flat = weights.reshape(-1, n)
    pixel_ids, gaussian_ids = torch.nonzero(flat > 0, as_tuple=True)
    rank = torch.empty(n, dtype=torch.int64)
    rank[torch.argsort(projection.depths, stable=True)] = torch.arange(n)
    order = torch.argsort(pixel_ids * n + rank[gaussian_ids])
    pixel_ids, gaussian_ids = pixel_ids[order], gaussian_ids[order]
    params = projection.params[:, :3] if kind == "3dgs" else projection.params.reshape(-1, 3, 3)
    pair_view = _gsplat._View(
        kind=kind,
        width=width,
        height=height,
        means2d=projection.alpha_centers.float()[None],
        params=params.float()[None],
        normals=None,
        opacities=projection.opacities.float()[None],
        depths=projection.depths.float(),
        radii=torch.zeros(1, n, 2, dtype=torch.int32),
        offsets=torch.zeros(1, 1, 1, dtype=torch.int32),
        flatten_ids=torch.zeros(0, dtype=torch.int32),
    )
    assert len(pixel_ids) > 500
    got = _gsplat._pair_weights(pair_view, gaussian_ids, pixel_ids)
    expected = flat[pixel_ids, gaussian_ids].float()
    torch.testing.assert_close(got, expected, rtol=1e-3, atol=1e-6)


def test_gsplat_needs_cuda_float32():
    cpu = torch.device("cpu")
    with pytest.raises(InputError, match="needs a CUDA"):
        resolve_backend(RasterConfig(backend="gsplat"), cpu)
    backend = GsplatBackend()
    assert "CUDA" in backend.unusable(cpu, torch.float32)
    assert "float32" in backend.unusable(torch.device("cuda"), torch.float64)
    if not torch.cuda.is_available():
        assert "no CUDA device" in backend.unusable(torch.device("cuda"), torch.float32)


def test_float64_on_cuda_is_refused(monkeypatch):
    monkeypatch.setattr(backends, "_installed", lambda module: True)
    config = RasterConfig(backend="gsplat", precision="float64")
    with pytest.raises(InputError, match="gsplat computes in float32 only"):
        resolve_backend(config, torch.device("cuda"))


def test_auto_resolution(monkeypatch, caplog):
    backend, dtype = resolve_backend(RasterConfig(), torch.device("cpu"))
    assert (backend.name, dtype) == ("numba", torch.float64)
    monkeypatch.setattr(backends, "_installed", lambda module: True)
    assert backends._auto_name(torch.device("cuda")) == "gsplat"
    monkeypatch.setattr(backends, "_installed", lambda module: False)
    assert backends._auto_name(torch.device("cuda")) == "torch"
    with caplog.at_level(logging.INFO, logger="thgs.render.backends"):
        backend, dtype = resolve_backend(RasterConfig(), torch.device("cuda"))
    assert (backend.name, dtype) == ("torch", torch.float32)
    assert "gsplat is not installed" in caplog.text
    with pytest.raises(InputError, match=r"pip install 'thgs\[gpu\]'"):
        get_backend("gsplat")


def test_unhonoured_settings_are_logged_once(caplog):
    _gsplat._log_unhonoured.cache_clear()
    with caplog.at_level(logging.INFO, logger="thgs.render._gsplat"):
        _gsplat._check_config(RasterConfig(alpha_max=0.999, filter_inv_square=1.0), "3dgs")
        assert caplog.records == []  # the 2DGS filter does not matter for 3DGS
        _gsplat._check_config(RasterConfig(), "2dgs")
        _gsplat._check_config(RasterConfig(), "2dgs")
        assert len(caplog.records) == 1
        assert "alpha_max=0.99 (gsplat: 0.999)" in caplog.text
        assert "filter_inv_square" not in caplog.text
        _gsplat._check_config(RasterConfig(alpha_max=0.999, filter_inv_square=1.0), "2dgs")
        assert len(caplog.records) == 2
        assert "filter_inv_square=1 (gsplat: 2)" in caplog.records[1].getMessage()
