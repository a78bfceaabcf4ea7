"""Rasterization and splat-back through the public API, for every CPU backend: against the
brute-force reference (thgs.render._reference), analytic cases, the adjoint identity, gsplat's
pure-torch projection, backend selection and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import numba_threads
from thgs import Cameras, Gaussians, InputError
from thgs.render import RasterConfig, project, render, resolve_backend, splat_back, splat_labels
from thgs.render._reference import ReferenceBackend, dense_weights
from thgs.render.projection import project_centers, project_torch
from thgs.scene.gaussians import quaternions_to_matrices

CPU_BACKENDS = ["numba", "torch"]


def camera(width=48, height=36, focal=40.0, cx=None, cy=None) -> Cameras:
    """A camera at the origin looking along +z (world = camera frame)."""
    K = torch.tensor(
        [
            [focal, 0, width / 2 if cx is None else cx],
            [0, focal, height / 2 if cy is None else cy],
            [0, 0, 1],
        ],
        dtype=torch.float64,
    )
    return Cameras(
        torch.eye(4, dtype=torch.float64)[None],
        K[None],
        torch.tensor([width]),
        torch.tensor([height]),
        ("view.png",),
    ).check()


def tiny_scene(kind: str, n: int = 40, seed: int = 0) -> Gaussians:
    """Random Gaussians in front of `camera()`, some behind it, large and small, tilted."""
    g = torch.Generator().manual_seed(seed)
    z = torch.rand(n, generator=g) * 4 + 2
    z[:3] = torch.tensor([-1.0, 0.1, 0.15])  # behind the camera and closer than the near plane
    xy = (torch.rand(n, 2, generator=g) - 0.5) * 3
    xy[3] = torch.tensor([2.5, 0.0])  # partly outside the image
    means = torch.cat([xy, z[:, None]], dim=1)
    scales = torch.rand(n, 2 if kind == "2dgs" else 3, generator=g) * 2.5 - 3.5
    scales[4] = math.log(1.5)  # a large one covering many tiles
    quats = torch.randn(n, 4, generator=g)
    opacities = torch.randn(n, generator=g) * 2 + 1
    sh = torch.randn(n, 1, 3, generator=g)
    return Gaussians(means, quats, scales, opacities, sh).check()


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("principal", [None, (20.3, 21.7)])
def test_backend_matches_brute_force(backend, kind, seed, principal):
    gaussians = tiny_scene(kind, seed=seed)
    cam = camera() if principal is None else camera(cx=principal[0], cy=principal[1])
    config = RasterConfig(tile_size=8, backend=backend)
    features = torch.randn(
        len(gaussians), 5, dtype=torch.float64, generator=torch.Generator().manual_seed(seed)
    )
    pixel_map = torch.randn(
        36, 48, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(7)
    )
    mask = torch.rand(36, 48, generator=torch.Generator().manual_seed(8)) > 0.3
    reference = ReferenceBackend()
    expected = reference.render(gaussians, cam, features, config)
    expected_back = reference.splat_back(gaussians, cam, pixel_map, mask, config)
    assert float(expected.alpha.max()) > 0.5, "the scene must actually cover pixels"
    assert int((expected_back.pixel_counts > 0).sum()) > 10

    out = render(gaussians, cam, features, config=config)
    torch.testing.assert_close(out.image, expected.image, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(out.alpha, expected.alpha, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(out.depth, expected.depth, atol=1e-10, rtol=1e-10)
    assert torch.equal(out.max_id, expected.max_id)

    back = splat_back(gaussians, cam, pixel_map, mask=mask, config=config)
    for name in ("feature_sums", "weight_sums", "max_weights"):
        torch.testing.assert_close(
            getattr(back, name), getattr(expected_back, name), atol=1e-12, rtol=1e-10
        )
    assert torch.equal(back.pixel_counts, expected_back.pixel_counts)
    torch.testing.assert_close(back.depths, gaussians.means[:, 2].double())


@pytest.mark.parametrize("filter_inv_square", [0.02, 2.0, 50.0])
def test_edge_on_surfels_match_brute_force(filter_inv_square):
    """2DGS surfels seen nearly edge-on, large and small, against the brute force: the numba
    backend visits only the x-span of each row where ρ can be within reach (the ray term's
    quadratic and the screen filter's interval), so a span too narrow would drop weights."""
    g = torch.Generator().manual_seed(11)
    n = 120
    means = torch.cat(
        [(torch.rand(n, 2, generator=g) - 0.5) * 3, torch.rand(n, 1, generator=g) * 3 + 1.5], 1
    )
    # normals nearly perpendicular to the ray to the centre: tilted 80–89.9° away from it
    ray = means / means.norm(dim=1, keepdim=True)
    side = torch.nn.functional.normalize(
        torch.cross(ray, torch.randn(n, 3, generator=g), dim=1), dim=1
    )
    tilt = torch.deg2rad(80 + torch.rand(n, generator=g) * 9.9)[:, None]
    normal = torch.cos(tilt) * ray + torch.sin(tilt) * side
    # the quaternion turning z onto the normal
    axis = torch.cross(torch.tensor([0.0, 0.0, 1.0]).expand(n, 3), normal, dim=1)
    half = 0.5 * torch.acos(normal[:, 2].clamp(-1, 1))[:, None]
    quats = torch.cat(
        [torch.cos(half), torch.sin(half) * torch.nn.functional.normalize(axis, dim=1)], dim=1
    )
    scales = torch.rand(n, 2, generator=g) * 3.5 - 4.0
    opacities = torch.randn(n, generator=g) * 2 + 2
    gaussians = Gaussians(means, quats, scales, opacities, torch.randn(n, 1, 3, generator=g))
    gaussians = gaussians.check()
    cam = camera(cx=20.3, cy=21.7)
    config = RasterConfig(tile_size=8, backend="numba", filter_inv_square=filter_inv_square)
    features = torch.randn(n, 4, dtype=torch.float64, generator=g)
    expected = ReferenceBackend().render(gaussians, cam, features, config)
    assert int((expected.alpha > 0.1).sum()) > 100, "the surfels must cover pixels"
    out = render(gaussians, cam, features, config=config)
    torch.testing.assert_close(out.image, expected.image, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(out.alpha, expected.alpha, atol=1e-12, rtol=1e-10)
    assert torch.equal(out.max_id, expected.max_id)


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_numba_projection_matches_torch(kind, seed):
    """The numba backend's compiled projection against the torch projection (which is tested
    against gsplat's): the same validity and pixel boxes, the same parameters to rounding."""
    gaussians = tiny_scene(kind, n=200, seed=seed)
    cam = camera(cx=20.3, cy=21.7)
    config = RasterConfig(backend="numba")
    ours, expected = project(gaussians, cam, config), project_torch(gaussians, cam, config)
    assert torch.equal(ours.valid, expected.valid)
    assert torch.equal(ours.bounds, expected.bounds)
    valid = expected.valid
    torch.testing.assert_close(ours.depths, expected.depths, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(ours.opacities, expected.opacities, atol=1e-14, rtol=1e-12)
    torch.testing.assert_close(ours.centers[valid], expected.centers[valid], rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(
        ours.alpha_centers[valid], expected.alpha_centers[valid], rtol=1e-10, atol=1e-9
    )
    torch.testing.assert_close(ours.params[valid], expected.params[valid], rtol=1e-9, atol=1e-12)


def test_backends_agree_on_a_larger_scene():
    """numba and torch on 1,500 Gaussians at 96×72: both float64, equal to rounding."""
    gaussians = tiny_scene("2dgs", n=1500, seed=4)
    cam = camera(96, 72, focal=80.0)
    features = gaussians.dc_colors().double()
    maps = np.random.default_rng(4).integers(-1, 5, size=(2, 12, 16)).repeat(6, 1).repeat(6, 2)
    out = {}
    for backend in CPU_BACKENDS:
        config = RasterConfig(backend=backend)
        out[backend] = (
            render(gaussians, cam, features, config=config),
            splat_labels(gaussians, cam, maps, config=config),
        )
    (render_a, labels_a), (render_b, labels_b) = out["numba"], out["torch"]
    torch.testing.assert_close(render_a.image, render_b.image, atol=1e-12, rtol=1e-10)
    assert torch.equal(render_a.max_id, render_b.max_id)
    for name in ("gaussians", "levels", "labels"):
        assert torch.equal(getattr(labels_a, name), getattr(labels_b, name))
    torch.testing.assert_close(labels_a.weights, labels_b.weights, atol=1e-12, rtol=1e-10)


def test_numba_reuses_prepared_gaussians_until_they_change():
    """The numba backend keeps the Gaussians' activated values between views; modifying a tensor
    in place invalidates them."""
    gaussians, cam = tiny_scene("3dgs", seed=2), camera()
    features = torch.ones(len(gaussians), 1, dtype=torch.float64)
    before = render(gaussians, cam, features)
    gaussians.opacities.sub_(2.0)
    gaussians.quats[:, 1:] *= -1
    after = render(gaussians, cam, features)
    expected = ReferenceBackend().render(gaussians, cam, features, RasterConfig())
    torch.testing.assert_close(after.image, expected.image, atol=1e-12, rtol=1e-10)
    assert not torch.allclose(after.image, before.image)


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_numba_outputs_do_not_depend_on_the_order_its_kernels_hold(monkeypatch, kind):
    """The numba kernels hold the Gaussians in Z-order of their centres and map every output back:
    the same bytes as with the Gaussians held in their own order or reversed, equal depths
    included (three Gaussians duplicated at the end, far from their twins in index and with
    other features: the order of a tie shows in the image and in the index of the maximum)."""
    import weakref

    from thgs.render import _numba

    duplicated = torch.cat([torch.arange(60), torch.tensor([4, 20, 33])])
    gaussians, cam = tiny_scene(kind, n=60, seed=7).select(duplicated), camera()
    features = torch.from_numpy(np.random.default_rng(7).random((len(gaussians), 3)))
    pixel_map = torch.from_numpy(np.random.default_rng(8).random((36, 48, 2)))
    maps = np.random.default_rng(9).integers(-1, 4, size=(2, 6, 8)).repeat(6, 1).repeat(6, 2)
    config = RasterConfig(backend="numba")

    def outputs() -> list:
        monkeypatch.setattr(_numba, "_PREPARED", weakref.WeakKeyDictionary())
        return [
            project(gaussians, cam, config),
            render(gaussians, cam, features, config=config),
            splat_back(gaussians, cam, pixel_map, config=config),
            splat_labels(gaussians, cam, maps, config=config),
        ]

    z_order = outputs()
    assert not np.array_equal(_numba._prepared(gaussians).order, np.arange(len(gaussians)))
    # a twin is the largest somewhere: held in reverse, a tie going by that order would make it
    # its duplicate
    assert bool(torch.isin(z_order[1].max_id, torch.tensor([4, 20, 33])).any())
    for held in (np.arange, lambda n: np.arange(n)[::-1].copy()):
        monkeypatch.setattr(_numba, "spatial_order", lambda means, held=held: held(len(means)))
        for expected, got in zip(z_order, outputs(), strict=True):
            for name, value in vars(expected).items():
                if isinstance(value, torch.Tensor):
                    assert torch.equal(value, getattr(got, name)), (type(expected), name)


def test_running_out_of_device_memory_is_an_input_error(monkeypatch):
    from thgs.render import _numba

    def exhausted(*args, **kwargs):
        raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB")

    monkeypatch.setattr(_numba.NumbaBackend, "render", exhausted)
    with pytest.raises(InputError, match=r"cpu: out of memory rasterizing 40 Gaussians at 48×36"):
        render(tiny_scene("2dgs"), camera(), torch.zeros(40, 1))


def test_backend_resolution():
    cpu = torch.device("cpu")
    backend, dtype = resolve_backend(RasterConfig(), cpu)
    assert (backend.name, dtype) == ("numba", torch.float64)
    backend, dtype = resolve_backend(RasterConfig(backend="torch", precision="float32"), cpu)
    assert (backend.name, dtype) == ("torch", torch.float32)
    with pytest.raises(InputError, match="numba cannot render on cpu: it computes in float64"):
        resolve_backend(RasterConfig(backend="numba", precision="float32"), cpu)
    with pytest.raises(InputError, match="numba cannot render on meta: it runs on the CPU only"):
        resolve_backend(RasterConfig(backend="numba"), torch.device("meta"))
    with pytest.raises(InputError, match="MPS has no float64"):
        resolve_backend(RasterConfig(precision="float64"), torch.device("mps"))
    with pytest.raises(InputError, match="backend must be auto, numba, torch or gsplat"):
        RasterConfig(backend="cuda")  # type: ignore[arg-type]


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("tile_size", [1, 5, 16, 64])
def test_tile_size_does_not_change_results(backend, tile_size):
    gaussians = tiny_scene("2dgs", seed=3)
    features = gaussians.dc_colors()
    reference = render(gaussians, camera(), features, config=RasterConfig(tile_size=16))
    config = RasterConfig(tile_size=tile_size, backend=backend)
    out = render(gaussians, camera(), features, config=config)
    torch.testing.assert_close(out.image, reference.image, atol=1e-6, rtol=0)
    assert torch.equal(out.max_id, reference.max_id)


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
@pytest.mark.parametrize("tile_size", [5, 64])
def test_numba_render_is_the_same_with_any_number_of_threads(kind, tile_size):
    """The numba render deals tiles to threads: the same bytes with one thread, with two, and
    with more threads than tiles (one 64-pixel tile covers the whole 48×36 image)."""
    numba = pytest.importorskip("numba")
    gaussians = tiny_scene(kind, seed=5)
    features = gaussians.dc_colors().double()
    config = RasterConfig(tile_size=tile_size, backend="numba")
    outputs = []
    for threads in (1, numba.config.NUMBA_NUM_THREADS):
        with numba_threads(threads):
            outputs.append(render(gaussians, camera(), features, config=config))
    one, many = outputs
    for name in ("image", "alpha", "depth", "max_id"):
        assert torch.equal(getattr(one, name), getattr(many, name)), name
    assert int((one.max_id >= 0).sum()) > 100  # the scene covers much of the image


def single(kind: str, *, z=5.0, scale=0.1, opacity=0.9, quat=(1.0, 0, 0, 0), xy=(0.0, 0.0)):
    n_scales = 2 if kind == "2dgs" else 3
    return Gaussians(
        means=torch.tensor([[xy[0], xy[1], z]]),
        quats=torch.tensor([quat]),
        scales=torch.full((1, n_scales), math.log(scale)),
        opacities=torch.tensor([math.log(opacity / (1 - opacity))]),
        sh=torch.zeros(1, 1, 3),
    )


def pixel_offsets(width=64, height=64, centre=(32.0, 32.0)):
    ys, xs = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    return (xs - centre[0]) ** 2 + (ys - centre[1]) ** 2


@pytest.mark.parametrize(
    ("kind", "scale", "variance"),
    [
        # camera-facing surfel, σ = f·s/z = 100·0.1/5 = 2 px: ρ3d = |d|²/4 < ρ2d = 2|d|²
        ("2dgs", 0.1, 4.0),
        # a tiny surfel: the 2D low-pass wins, ρ2d = 2|d|², i.e. variance ½ px²
        ("2dgs", 0.001, 0.5),
        # a sphere of σ = 2 px plus the 0.3 px² low-pass
        ("3dgs", 0.1, 4.3),
    ],
)
def test_single_gaussian_by_hand(kind, scale, variance):
    cam = camera(64, 64, focal=100.0)
    gaussian = single(kind, scale=scale)
    out = render(gaussian, cam, torch.ones(1, 1))
    d2 = pixel_offsets()
    alpha = np.minimum(0.99, 0.9 * np.exp(-d2 / (2 * variance)))
    expected = np.where(alpha >= 1 / 255, alpha, 0.0)
    np.testing.assert_allclose(out.alpha.numpy(), expected, atol=1e-6)
    back = splat_back(gaussian, cam, torch.ones(64, 64, 1))
    assert int(back.pixel_counts[0]) == int((expected > 0).sum())
    assert float(back.max_weights[0]) == pytest.approx(expected.max(), abs=1e-6)
    assert back.centers[0].tolist() == pytest.approx([32.0, 32.0])
    assert torch.equal(out.max_id == 0, torch.from_numpy(expected > 0))
    np.testing.assert_allclose(out.depth.numpy(), np.where(expected > 0, 5.0, 0.0), atol=1e-6)


def test_rear_gaussian_is_attenuated_by_the_front_one():
    cam = camera(64, 64, focal=100.0)
    front = single("2dgs", z=5.0, scale=0.08, opacity=0.6, xy=(0.05, 0.0))
    rear = single("2dgs", z=6.0, scale=0.12, opacity=0.8, xy=(-0.05, 0.02))
    both = Gaussians(
        *(
            torch.cat([getattr(front, f), getattr(rear, f)])
            for f in ("means", "quats", "scales", "opacities", "sh")
        )
    )
    alpha_front = render(front, cam, torch.ones(1, 1)).alpha
    alpha_rear = render(rear, cam, torch.ones(1, 1)).alpha
    out = render(both, cam, torch.eye(2))
    torch.testing.assert_close(out.image[..., 0], alpha_front)
    torch.testing.assert_close(out.image[..., 1], alpha_rear * (1 - alpha_front))
    # listed rear first, composited in depth order all the same
    swapped = Gaussians(
        *(
            torch.cat([getattr(rear, f), getattr(front, f)])
            for f in ("means", "quats", "scales", "opacities", "sh")
        )
    )
    torch.testing.assert_close(render(swapped, cam, torch.eye(2).flip(0)).image, out.image)


def test_stop_rule_on_opaque_layers():
    """Three layers of α = 0.99: T goes 1 → 0.01 → 1e-4 → 1e-6 (plus rounding)."""
    cam = camera(8, 8, focal=10.0)
    layers = Gaussians(
        means=torch.tensor([[0.0, 0, 3], [0, 0, 4], [0, 0, 5]]),
        quats=torch.tensor([[1.0, 0, 0, 0]] * 3),
        scales=torch.full((3, 2), math.log(100.0)),
        opacities=torch.full((3,), 50.0),
        sh=torch.zeros(3, 1, 3),
    )
    features = torch.eye(3, dtype=torch.float64)

    def alpha(transmittance_min):
        config = RasterConfig(transmittance_min=transmittance_min)
        out = render(layers, cam, features, config=config)
        assert bool((out.max_id == 0).all())
        return out.alpha

    def full(value):
        return torch.full((8, 8), value, dtype=torch.float64)

    # the layer that would bring T to ≤ transmittance_min is not composited, and none after it
    torch.testing.assert_close(alpha(0.005), full(0.99))
    torch.testing.assert_close(alpha(1e-4), full(0.9999))  # T after two = 1e-4 + rounding
    torch.testing.assert_close(alpha(0.0), full(0.999999))


def test_near_plane():
    cam = camera(16, 16, focal=20.0)
    close = single("3dgs", z=0.15, scale=0.01)
    assert float(render(close, cam, torch.ones(1, 1)).alpha.sum()) == 0.0
    visible = render(close, cam, torch.ones(1, 1), config=RasterConfig(near=0.1))
    assert float(visible.alpha.max()) > 0.5


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_adjoint_identity(kind):
    gaussians = tiny_scene(kind, n=60, seed=5)
    cam = camera(40, 30, focal=35.0)
    generator = torch.Generator().manual_seed(11)
    f = torch.randn(60, 4, dtype=torch.float64, generator=generator)
    F = torch.randn(30, 40, 4, dtype=torch.float64, generator=generator)
    lhs = (render(gaussians, cam, f).image * F).sum()
    rhs = (f * splat_back(gaussians, cam, F).feature_sums).sum()
    torch.testing.assert_close(lhs, rhs, rtol=1e-12, atol=1e-12)
    ones = splat_back(gaussians, cam, torch.ones(30, 40, 1, dtype=torch.float64))
    torch.testing.assert_close(ones.feature_sums[:, 0], ones.weight_sums)
    mask = F[..., 0] > 0
    masked = splat_back(gaussians, cam, F, mask=mask).feature_sums
    torch.testing.assert_close(masked, splat_back(gaussians, cam, F * mask[..., None]).feature_sums)


@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
def test_centres_alone_are_the_projections(kind):
    """project_centers gives project_torch's depths and centres, also for points behind the
    camera or past far; a hand-computed point in a moved camera."""
    gaussians, cam = tiny_scene(kind, n=60, seed=4), camera(cx=20.3, cy=15.5)
    config = RasterConfig(near=0.2, far=5.0)
    depths, centers = project_centers(gaussians, cam, config)
    full = project_torch(gaussians, cam, config)
    assert bool((depths <= config.near).any()) and bool((depths >= config.far).any())
    assert torch.equal(depths, full.depths) and torch.equal(centers, full.centers)
    moved = Cameras(
        torch.tensor([[[0.0, -1, 0, 0.5], [1, 0, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]]),
        cam.Ks,
        cam.widths,
        cam.heights,
        cam.stems,
    )
    point = Gaussians(
        torch.tensor([[1.0, 2.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]]), torch.zeros(1, 3),
        torch.zeros(1), torch.zeros(1, 1, 3),
    )  # fmt: skip
    # camera frame: (−2 + 0.5, 1, 2 + 2) = (−1.5, 1, 4); pixels: 40·(−1.5)/4 + 20.3, 40·1/4 + 15.5
    depths, centers = project_centers(point, moved, config)
    torch.testing.assert_close(depths, torch.tensor([4.0], dtype=torch.float64))
    torch.testing.assert_close(centers, torch.tensor([[5.3, 25.5]], dtype=torch.float64))


def test_projection_matches_gsplat_3dgs():
    torch_impl = pytest.importorskip("gsplat.cuda._torch_impl")
    gaussians = tiny_scene("3dgs", n=80, seed=9)
    cam = camera(cx=20.0, cy=15.5)
    config = RasterConfig(near=0.2)
    ours = project_torch(gaussians, cam, config)
    rotations = quaternions_to_matrices(gaussians.quats.double())
    scaled = rotations * torch.exp(gaussians.scales.double())[:, None]
    _, means2d, depths, conics, _ = torch_impl._fully_fused_projection(
        gaussians.means.double(),
        scaled @ scaled.transpose(1, 2),
        cam.viewmats.double(),
        cam.Ks.double(),
        48,
        36,
        eps2d=config.eps2d,
        near_plane=config.near,
    )
    front = ours.depths > config.near
    torch.testing.assert_close(ours.depths, depths[0])
    torch.testing.assert_close(ours.centers[front], means2d[0][front])
    torch.testing.assert_close(ours.params[front, :3], conics[0][front])


def test_projection_matches_gsplat_2dgs():
    torch_impl = pytest.importorskip("gsplat.cuda._torch_impl_2dgs")
    gaussians = tiny_scene("2dgs", n=80, seed=10)
    cam = camera(cx=20.0, cy=15.5)
    ours = project_torch(gaussians, cam, RasterConfig(near=0.2))
    scales3 = torch.cat([torch.exp(gaussians.scales.double()), torch.ones(80, 1).double()], 1)
    _, means2d, depths, ray_transforms, _ = torch_impl._fully_fused_projection_2dgs(
        gaussians.means.double(),
        gaussians.unit_quats().double(),
        scales3,
        cam.viewmats.double(),
        cam.Ks.double(),
        48,
        36,
        near_plane=0.2,
    )
    front = ours.valid
    torch.testing.assert_close(ours.depths, depths[0])
    # near-grazing surfels make the filter centre ill-conditioned: relative tolerance
    torch.testing.assert_close(ours.alpha_centers[front], means2d[0][front], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(
        ours.params.reshape(-1, 3, 3)[front], ray_transforms[0][front], rtol=1e-5, atol=1e-6
    )


def test_bad_input():
    gaussians = tiny_scene("3dgs", n=5)
    cam = camera(8, 6)
    with pytest.raises(InputError, match=r"features: must be \[N, C\] with N = 5, got \[4, 3\]"):
        render(gaussians, cam, torch.zeros(4, 3))
    with pytest.raises(InputError, match="features: must be floating point"):
        render(gaussians, cam, torch.zeros(5, 3, dtype=torch.long))
    with pytest.raises(InputError, match="features: has NaN"):
        render(gaussians, cam, torch.full((5, 1), float("nan")))
    with pytest.raises(InputError, match="features: is on meta"):
        render(gaussians, cam, torch.zeros(5, 1, device="meta"))
    with pytest.raises(InputError, match=r"pixel_map: must be \[H, W, C\] = \[6, 8, C\]"):
        splat_back(gaussians, cam, torch.zeros(8, 6, 1))
    with pytest.raises(InputError, match="mask: must be a bool"):
        splat_back(gaussians, cam, torch.zeros(6, 8, 1), mask=torch.ones(6, 8))
    with pytest.raises(InputError, match="expected one camera"):
        render(
            gaussians,
            Cameras(
                *(
                    torch.cat([getattr(cam, f)] * 2)
                    for f in ("viewmats", "Ks", "widths", "heights")
                ),
                ("a", "b"),
            ),
            torch.zeros(5, 1),
        )
    zero = Cameras(cam.viewmats, cam.Ks, torch.tensor([0]), cam.heights, cam.names)
    with pytest.raises(InputError, match="size 0×6"):
        render(gaussians, zero, torch.zeros(5, 1))
    broken = Gaussians(
        gaussians.means, torch.zeros(5, 4), gaussians.scales, gaussians.opacities, gaussians.sh
    )
    with pytest.raises(InputError, match="zero quaternion"):
        render(broken, cam, torch.zeros(5, 1))
    with pytest.raises(InputError, match="RasterConfig"):
        RasterConfig(near=-1.0)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("kind", ["2dgs", "3dgs"])
@pytest.mark.parametrize("seed", [0, 1])
def test_splat_labels_matches_brute_force(backend, kind, seed):
    gaussians, cam = tiny_scene(kind, seed=seed), camera()
    rng = np.random.default_rng(seed)
    # two levels of blocky labels with unlabelled pixels
    coarse = rng.integers(-1, 3, size=(6, 8)).repeat(6, axis=0).repeat(6, axis=1)
    fine = rng.integers(-1, 7, size=(12, 16)).repeat(3, axis=0).repeat(3, axis=1)
    maps = np.stack([coarse, fine])
    result = splat_labels(gaussians, cam, maps, config=RasterConfig(backend=backend))
    weights = dense_weights(gaussians, cam)[0].numpy()  # [H, W, N], composited by hand
    expected = {}
    for level in range(2):
        for label in range(int(maps[level].max()) + 1):
            sums = weights[maps[level] == label].sum(0)
            for g in np.flatnonzero(sums > 0):
                expected[(int(g), level, label)] = sums[g]
    got = {
        (int(g), int(level), int(label)): float(w)
        for g, level, label, w in zip(
            result.gaussians, result.levels, result.labels, result.weights
        )
    }
    assert got.keys() == expected.keys()
    for key, value in expected.items():
        assert got[key] == pytest.approx(value, rel=1e-9, abs=1e-12)
    np.testing.assert_allclose(result.weight_sums, weights.sum((0, 1)), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.max_weights, weights.max((0, 1)), rtol=1e-9, atol=1e-12)
    keys = torch.stack([result.gaussians, result.levels, result.labels], dim=1)
    assert bool((torch.diff(keys[:, 0] * 100 + keys[:, 1] * 10 + keys[:, 2]) > 0).all())


def test_splat_labels_many_labels_in_a_tile(monkeypatch):
    """A tile with more (Gaussian, level, label) cells than the numba backend's per-tile table
    holds adds every pixel's weight directly: the same sums."""
    from thgs.render import _numba

    gaussians, cam = tiny_scene("2dgs", n=60, seed=6), camera()
    maps = np.arange(2 * 36 * 48).reshape(2, 36, 48) % 997  # a new label on almost every pixel
    expected = splat_labels(gaussians, cam, maps)
    monkeypatch.setattr(_numba, "_LOCAL_SLOTS_MAX", 0)
    direct = splat_labels(gaussians, cam, maps)
    for name in ("gaussians", "levels", "labels"):
        assert torch.equal(getattr(direct, name), getattr(expected, name))
    torch.testing.assert_close(direct.weights, expected.weights, atol=1e-14, rtol=1e-12)
