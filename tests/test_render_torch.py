"""The torch backend: against the brute-force reference (tiny scenes) and the numba backend (a
larger one), float32 against float64, the step budget, the stop rule, the adjoint identity and
views where nothing is visible."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from test_render import camera, tiny_scene
from thgs import Cameras, Gaussians
from thgs.render import (
    RasterConfig,
    get_backend,
    project,
    render,
    resolve_backend,
    splat_back,
    splat_labels,
)
from thgs.render import _torch as torch_backend
from thgs.render._reference import ReferenceBackend

EXACT = {"atol": 1e-12, "rtol": 1e-10}
"""float64 backends agree to rounding."""


def assert_render_equal(out, expected, **tolerance):
    torch.testing.assert_close(out.image, expected.image, **tolerance)
    torch.testing.assert_close(out.alpha, expected.alpha, **tolerance)
    torch.testing.assert_close(out.depth, expected.depth, **tolerance)
    assert torch.equal(out.max_id, expected.max_id)


def assert_splat_back_equal(out, expected, **tolerance):
    for name in ("feature_sums", "weight_sums", "max_weights", "depths", "centers"):
        torch.testing.assert_close(getattr(out, name), getattr(expected, name), **tolerance)
    assert torch.equal(out.pixel_counts, expected.pixel_counts)


def assert_labels_equal(out, expected, **tolerance):
    for name in ("gaussians", "levels", "labels"):
        assert torch.equal(getattr(out, name), getattr(expected, name)), name
    for name in ("weights", "weight_sums", "max_weights", "depths"):
        torch.testing.assert_close(getattr(out, name), getattr(expected, name), **tolerance)


def label_maps(height: int, width: int, seed: int) -> torch.Tensor:
    """[2, H, W] int64: blocks of a coarse and a fine level, with unlabelled (−1) blocks."""
    rng = np.random.default_rng(seed)
    coarse = rng.integers(-1, 3, size=(-(-height // 6), -(-width // 6))).repeat(6, 0).repeat(6, 1)
    fine = rng.integers(-1, 9, size=(-(-height // 3), -(-width // 3))).repeat(3, 0).repeat(3, 1)
    fine = np.where(fine >= 0, fine * 7, -1)  # labels that are not 0 … k
    maps = np.stack([coarse[:height, :width], fine[:height, :width]])
    return torch.from_numpy(maps)


def inputs(n_gaussians: int, height: int, width: int, seed: int):
    """Features [N, 5], a pixel map [H, W, 3] (float64) and a mask [H, W] keeping ~70 %."""
    generator = torch.Generator().manual_seed(seed)
    features = torch.randn(n_gaussians, 5, dtype=torch.float64, generator=generator)
    pixel_map = torch.randn(height, width, 3, dtype=torch.float64, generator=generator)
    mask = torch.rand(height, width, generator=generator) > 0.3
    return features, pixel_map, mask


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("principal", [None, (20.3, 21.7)])
def test_matches_reference(kind, seed, principal):
    gaussians = tiny_scene(kind, seed=seed)
    cam = camera() if principal is None else camera(cx=principal[0], cy=principal[1])
    features, pixel_map, mask = inputs(len(gaussians), 36, 48, seed)
    maps = label_maps(36, 48, seed)
    reference, dtype = ReferenceBackend(), torch.float64
    expected_render = reference.render(gaussians, cam, features, RasterConfig(), dtype)
    expected_back = reference.splat_back(gaussians, cam, pixel_map, mask, RasterConfig(), dtype)
    expected_labels = reference.label_weights(gaussians, cam, maps, RasterConfig(), dtype)
    assert float(expected_render.alpha.max()) > 0.5, "the scene must actually cover pixels"
    assert int((expected_back.pixel_counts > 0).sum()) > 10
    assert len(expected_labels.weights) > 20

    for tile_size in (1, 5, 8, 16, 64):
        config = RasterConfig(backend="torch", tile_size=tile_size)
        assert_render_equal(
            render(gaussians, cam, features, config=config), expected_render, **EXACT
        )
        back = splat_back(gaussians, cam, pixel_map, mask=mask, config=config)
        assert_splat_back_equal(back, expected_back, **EXACT)
        labels = splat_labels(gaussians, cam, maps, config=config)
        assert_labels_equal(labels, expected_labels, **EXACT)

    projection = project(gaussians, cam, RasterConfig(backend="torch"))
    assert projection.params.dtype == torch.float64
    assert torch.equal(projection.bounds, project(gaussians, cam, RasterConfig()).bounds)


def larger_scene(kind: str) -> tuple[Gaussians, Cameras]:
    """3000 Gaussians over a 160×120 view with an off-centre principal point."""
    return tiny_scene(kind, n=3000, seed=4), camera(160, 120, focal=133.0, cx=77.3, cy=63.1)


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_matches_numba(kind):
    gaussians, cam = larger_scene(kind)
    features, pixel_map, mask = inputs(len(gaussians), 120, 160, seed=5)
    maps = label_maps(120, 160, seed=5)
    numba, ours = RasterConfig(backend="numba"), RasterConfig(backend="torch")
    expected = render(gaussians, cam, features, config=numba)
    assert float((expected.alpha > 0.5).float().mean()) > 0.5
    assert_render_equal(render(gaussians, cam, features, config=ours), expected, **EXACT)
    assert_splat_back_equal(
        splat_back(gaussians, cam, pixel_map, mask=mask, config=ours),
        splat_back(gaussians, cam, pixel_map, mask=mask, config=numba),
        **EXACT,
    )
    assert_labels_equal(
        splat_labels(gaussians, cam, maps, config=ours),
        splat_labels(gaussians, cam, maps, config=numba),
        **EXACT,
    )


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_float32_close_to_float64(kind):
    """float32 rounds differently in the projection, α and the transmittance: an α or a
    transmittance right at alpha_min or transmittance_min can switch a contribution on or off
    (up to alpha_min at the pixel), so most pixels agree to 1e-4, all to 1e-2."""
    gaussians, cam = larger_scene(kind)
    features, pixel_map, _ = inputs(len(gaussians), 120, 160, seed=6)
    single = RasterConfig(backend="torch", precision="float32")
    assert resolve_backend(single, torch.device("cpu"))[1] == torch.float32
    out = render(gaussians, cam, features.float(), config=single)
    expected = render(gaussians, cam, features, config=RasterConfig(backend="torch"))
    assert out.image.dtype == torch.float32
    error = (out.alpha.double() - expected.alpha).abs()
    assert float(error.max()) < 1e-2
    assert float((error < 1e-4).double().mean()) > 0.999
    image_error = (out.image.double() - expected.image).abs().amax(-1)
    assert float((image_error < 1e-3).double().mean()) > 0.999
    assert float((out.max_id == expected.max_id).double().mean()) > 0.99

    back = splat_back(gaussians, cam, pixel_map.float(), config=single)
    expected_back = splat_back(gaussians, cam, pixel_map, config=RasterConfig(backend="torch"))
    assert back.weight_sums.dtype == torch.float32
    scale = float(expected_back.weight_sums.max())
    torch.testing.assert_close(
        back.weight_sums.double(), expected_back.weight_sums, atol=1e-3 * scale, rtol=0
    )
    labels = splat_labels(gaussians, cam, label_maps(120, 160, 6), config=single)
    assert labels.weights.dtype == torch.float32


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_step_size_does_not_change_results(kind, monkeypatch):
    """One tile of 3 Gaussians per step: the transmittance is carried across many steps."""
    gaussians, cam = tiny_scene(kind, seed=1), camera(cx=20.3, cy=21.7)
    features, pixel_map, mask = inputs(len(gaussians), 36, 48, seed=2)
    maps = label_maps(36, 48, seed=2)
    config = RasterConfig(backend="torch", tile_size=8)
    expected = (
        render(gaussians, cam, features, config=config),
        splat_back(gaussians, cam, pixel_map, mask=mask, config=config),
        splat_labels(gaussians, cam, maps, config=config),
    )
    monkeypatch.setattr(torch_backend, "_STEP_BYTES", 1)
    monkeypatch.setattr(torch_backend, "_CPU_STEP_BYTES", 1)
    monkeypatch.setattr(torch_backend, "_BATCH", 3)
    projection = project(gaussians, cam, config)
    steps = list(torch_backend._steps(projection, config))
    assert len(steps) > 50
    assert all(len(ids) == 1 and ids.shape[1] <= 3 for _, ids, _ in steps)
    assert_render_equal(render(gaussians, cam, features, config=config), expected[0], **EXACT)
    back = splat_back(gaussians, cam, pixel_map, mask=mask, config=config)
    assert_splat_back_equal(back, expected[1], **EXACT)
    assert_labels_equal(splat_labels(gaussians, cam, maps, config=config), expected[2], **EXACT)


@pytest.mark.parametrize("batch", [1, 2, 64])
def test_stop_rule_on_opaque_layers(batch, monkeypatch):
    """Three layers of α = 0.99: T goes 1 → 0.01 → 1e-4 → 1e-6 (plus rounding); the layer that
    would bring T to ≤ transmittance_min is not composited, and none after it, whether the layers
    come in one step or in several."""
    monkeypatch.setattr(torch_backend, "_BATCH", batch)
    cam = camera(8, 8, focal=10.0)
    layers = Gaussians(
        means=torch.tensor([[0.0, 0, 3], [0, 0, 4], [0, 0, 5]]),
        quats=torch.tensor([[1.0, 0, 0, 0]] * 3),
        scales=torch.full((3, 2), math.log(100.0)),
        opacities=torch.full((3,), 50.0),
        sh=torch.zeros(3, 1, 3),
    )
    features = torch.eye(3, dtype=torch.float64)

    def composited(transmittance_min):
        config = RasterConfig(backend="torch", transmittance_min=transmittance_min)
        out = render(layers, cam, features, config=config)
        assert bool((out.max_id == 0).all())
        counts = splat_back(layers, cam, torch.ones(8, 8, 1), config=config).pixel_counts
        return out.alpha, counts.tolist()

    def full(value):
        return torch.full((8, 8), value, dtype=torch.float64)

    alpha, counts = composited(0.005)
    torch.testing.assert_close(alpha, full(0.99))
    assert counts == [64, 0, 0]
    alpha, counts = composited(1e-4)
    torch.testing.assert_close(alpha, full(0.9999))
    assert counts == [64, 64, 0]
    alpha, counts = composited(0.0)
    torch.testing.assert_close(alpha, full(0.999999))
    assert counts == [64, 64, 64]


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_adjoint_identity(kind):
    gaussians = tiny_scene(kind, n=60, seed=5)
    cam = camera(40, 30, focal=35.0)
    config = RasterConfig(backend="torch", tile_size=8)
    generator = torch.Generator().manual_seed(11)
    f = torch.randn(60, 4, dtype=torch.float64, generator=generator)
    F = torch.randn(30, 40, 4, dtype=torch.float64, generator=generator)
    lhs = (render(gaussians, cam, f, config=config).image * F).sum()
    rhs = (f * splat_back(gaussians, cam, F, config=config).feature_sums).sum()
    torch.testing.assert_close(lhs, rhs, rtol=1e-12, atol=1e-12)
    ones = splat_back(gaussians, cam, torch.ones(30, 40, 1, dtype=torch.float64), config=config)
    torch.testing.assert_close(ones.feature_sums[:, 0], ones.weight_sums)
    mask = F[..., 0] > 0
    masked = splat_back(gaussians, cam, F, mask=mask, config=config).feature_sums
    unmasked = splat_back(gaussians, cam, F * mask[..., None], config=config).feature_sums
    torch.testing.assert_close(masked, unmasked)


@pytest.mark.parametrize("where", ["behind", "beside"])
def test_nothing_visible(where):
    """All Gaussians behind the camera, or in front of it but outside the image."""
    gaussians = tiny_scene("3dgs", n=10, seed=0)
    offset = torch.tensor([0.0, 0.0, -10.0]) if where == "behind" else torch.tensor([50.0, 0, 0])
    gaussians = Gaussians(
        gaussians.means + offset,
        gaussians.quats,
        gaussians.scales,
        gaussians.opacities,
        gaussians.sh,
    )
    cam, config = camera(), RasterConfig(backend="torch")
    bounds = project(gaussians, cam, config).bounds
    assert bool(((bounds[:, 0] > bounds[:, 1]) | (bounds[:, 2] > bounds[:, 3])).all())
    out = render(gaussians, cam, torch.ones(10, 2, dtype=torch.float64), config=config)
    assert out.image.shape == (36, 48, 2) and not bool(out.image.any())
    assert not bool(out.alpha.any()) and not bool(out.depth.any())
    assert out.max_id.dtype == torch.int64 and bool((out.max_id == -1).all())
    back = splat_back(gaussians, cam, torch.ones(36, 48, 3), config=config)
    assert back.feature_sums.shape == (10, 3) and back.feature_sums.dtype == torch.float32
    assert not bool(back.feature_sums.any()) and not bool(back.max_weights.any())
    assert back.pixel_counts.dtype == torch.int64 and not bool(back.pixel_counts.any())
    labels = splat_labels(gaussians, cam, label_maps(36, 48, seed=0), config=config)
    for name in ("gaussians", "levels", "labels"):
        assert getattr(labels, name).shape == (0,)
        assert getattr(labels, name).dtype == torch.int64
    assert labels.weights.shape == (0,) and labels.weights.dtype == torch.float64
    assert labels.weight_sums.shape == (10,) and not bool(labels.weight_sums.any())


def test_unusable():
    backend = get_backend("torch")
    assert backend.name == "torch"
    cpu, mps = torch.device("cpu"), torch.device("mps")
    assert backend.unusable(cpu, torch.float64) is None
    assert backend.unusable(cpu, torch.float32) is None
    assert backend.unusable(mps, torch.float32) is None
    assert "float64" in backend.unusable(mps, torch.float64)
    assert "float16" in backend.unusable(cpu, torch.float16)


ACCELERATORS = [
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA")),
    pytest.param(
        "mps", marks=pytest.mark.skipif(not torch.backends.mps.is_available(), reason="no MPS")
    ),
]


@pytest.mark.parametrize("device", ACCELERATORS)
@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_accelerator_matches_cpu(device, kind):
    """On an accelerator (float32 by default), the outputs stay on the device and agree with the
    CPU in float64 as float32 does there."""
    gaussians, cam = larger_scene(kind)
    features, pixel_map, mask = inputs(len(gaussians), 120, 160, seed=7)
    config = RasterConfig(backend="torch")
    on_device = gaussians.to(device)
    out = render(on_device, cam, features.float().to(device), config=config)
    assert out.image.device.type == device and out.max_id.device.type == device
    expected = render(gaussians, cam, features, config=config)
    error = (out.alpha.cpu().double() - expected.alpha).abs()
    assert float(error.max()) < 1e-2
    assert float((error < 1e-4).double().mean()) > 0.999
    assert float((out.max_id.cpu() == expected.max_id).double().mean()) > 0.99
    back = splat_back(
        on_device, cam, pixel_map.float().to(device), mask=mask.to(device), config=config
    )
    expected_back = splat_back(gaussians, cam, pixel_map, mask=mask, config=config)
    scale = float(expected_back.weight_sums.max())
    torch.testing.assert_close(
        back.weight_sums.cpu().double(), expected_back.weight_sums, atol=1e-3 * scale, rtol=0
    )
    labels = splat_labels(on_device, cam, label_maps(120, 160, 7).to(device), config=config)
    assert labels.gaussians.device.type == device
