"""thgs.viewer.splats: covariances, hierarchy layout, RGBA packing and chunked viser splat nodes."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch

from conftest import random_gaussians
from thgs import Gaussians
from thgs.errors import InputError
from thgs.viewer.splats import SplatChunks, hierarchy_order, pack_rgba, splat_covariances

viser = pytest.importorskip("viser")
# viser's own float → uint8 colour conversion (private module), the reference for pack_rgba
colors_to_uint8 = pytest.importorskip("viser._assignable_props_api").colors_to_uint8

N = 37  # not a multiple of any chunk size used below except 1 and 37


# ----------------------------------------------------------------------------- helpers


def hand_rotation(quat: np.ndarray) -> np.ndarray:
    """Rotation matrix of one quaternion (w, x, y, z), normalised first, written out by hand."""
    w, x, y, z = quat / np.linalg.norm(quat)
    return np.array(
        [
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
        ]
    )


def brute_force_covariances(gaussians: Gaussians) -> tuple[np.ndarray, np.ndarray]:
    """Per-Gaussian loop in float64: ([N, 3, 3] covariances, [N, 3, 3] rotations)."""
    quats = gaussians.quats.double().numpy()
    scales = np.exp(gaussians.scales.double().numpy())
    covariances, rotations = [], []
    for quat, scale in zip(quats, scales):
        rotation = hand_rotation(quat)
        variances = np.zeros(3)
        variances[: len(scale)] = scale**2  # 2DGS: no extent along the normal (third axis)
        covariances.append(rotation @ np.diag(variances) @ rotation.T)
        rotations.append(rotation)
    return np.array(covariances), np.array(rotations)


def scene_arrays(n: int = N, seed: int = 0) -> dict[str, np.ndarray]:
    """Centres, covariances, colours and opacities of n random Gaussians (NumPy, scene order)."""
    gaussians = random_gaussians(n, seed=seed)
    return {
        "centers": gaussians.means.numpy(),
        "covariances": splat_covariances(gaussians),
        "rgb": gaussians.dc_colors().numpy(),
        "opacity": gaussians.activated_opacities().numpy(),
    }


def layout_positions(order: np.ndarray | None, n: int) -> np.ndarray:
    """[N] layout position of each Gaussian, by search (independent of the implementation)."""
    if order is None:
        return np.arange(n)
    return np.array([int(np.flatnonzero(order == i)[0]) for i in range(n)])


def decode_buffers(chunks: SplatChunks, order: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Centres [N, 3] float32 and upper-triangular covariances [N, 6] float16 read back from the
    handles' buffers, in scene order."""
    buffer = np.concatenate([handle.buffer for handle in chunks.handles])
    centers = np.ascontiguousarray(buffer[:, 0:3]).view(np.float32)
    triu = np.ascontiguousarray(buffer[:, 4:7]).view(np.float16)
    positions = layout_positions(order, len(buffer))
    return centers[positions], triu[positions]


def random_permutation(n: int, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).permutation(n)


def nested_labels(n: int, seed: int = 0) -> np.ndarray:
    """[N, 4] random labels whose levels nest: every region's parent is fixed by its id."""
    rng = np.random.default_rng(seed)
    fine = rng.integers(0, 40, n)
    level1 = rng.integers(0, 12, 40)[fine]
    level2 = np.array([5, 6, 7, 5, 6, 7, 8, 5, 9, 9, 6, 7])[level1]
    level3 = np.array([0, 0, 0, 0, 0, -1, 3, 3, 3, -1])[level2]
    return np.stack([fine, level1, level2, level3], axis=1)


@pytest.fixture
def server():
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield server
    server.stop()


@pytest.fixture
def sent(server, monkeypatch) -> list:
    """Every scene message the server queues from now on, in order."""
    messages = []
    queue = server.scene._queue_scene_message

    def capture(message) -> None:
        messages.append(message)
        queue(message)

    monkeypatch.setattr(server.scene, "_queue_scene_message", capture)
    return messages


def buffer_updates(messages: list) -> list[str]:
    """Names of the nodes that got a buffer update, one entry per message."""
    return [
        message.name
        for message in messages
        if type(message).__name__ == "SceneNodeUpdateMessage" and "buffer" in message.updates
    ]


# ----------------------------------------------------------------------------- covariances


@pytest.mark.parametrize("kind", ["3dgs", "2dgs"])
def test_covariances_match_a_per_gaussian_loop(kind):
    gaussians = random_gaussians(60, kind=kind, seed=3)
    covariances = splat_covariances(gaussians)
    expected, rotations = brute_force_covariances(gaussians)
    assert covariances.dtype == np.float32
    assert covariances.shape == (60, 3, 3)
    size = np.abs(expected).max(axis=(1, 2))
    error = np.abs(covariances - expected).max(axis=(1, 2))
    assert (error <= 1e-5 * size).all()
    np.testing.assert_array_equal(covariances, covariances.transpose(0, 2, 1))
    if kind == "2dgs":
        normals = rotations[:, :, 2]
        residual = np.linalg.norm(np.einsum("nij,nj->ni", covariances, normals), axis=1)
        assert (residual <= 1e-5 * size).all()  # the normal is a null vector
        eigenvalues = np.linalg.eigvalsh(covariances.astype(np.float64))
        assert (np.abs(eigenvalues[:, 0]) <= 1e-5 * size).all()  # rank 2
        assert (eigenvalues[:, 1] > 1e-3 * size).all()


def test_covariances_of_hand_made_gaussians():
    half = math.sqrt(0.5)
    gaussians = Gaussians(
        means=torch.zeros(2, 3),
        # identity (not unit length) and 90° about z: x → y, y → −x
        quats=torch.tensor([[2.0, 0.0, 0.0, 0.0], [half, 0.0, 0.0, half]]),
        scales=torch.log(torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])),
        opacities=torch.zeros(2),
        sh=torch.zeros(2, 1, 3),
    )
    covariances = splat_covariances(gaussians)
    np.testing.assert_allclose(covariances[0], np.diag([1.0, 4.0, 9.0]), atol=1e-5)
    np.testing.assert_allclose(covariances[1], np.diag([4.0, 1.0, 9.0]), atol=1e-5)
    flat = Gaussians(
        means=torch.zeros(1, 3),
        quats=torch.tensor([[half, 0.0, 0.0, half]]),
        scales=torch.log(torch.tensor([[1.0, 2.0]])),
        opacities=torch.zeros(1),
        sh=torch.zeros(1, 1, 3),
    )
    np.testing.assert_allclose(splat_covariances(flat)[0], np.diag([4.0, 1.0, 0.0]), atol=1e-5)


def test_covariances_reject_what_is_not_gaussians():
    with pytest.raises(InputError, match=r"^gaussians:"):
        splat_covariances(np.zeros((3, 3)))


# ----------------------------------------------------------------------------- hierarchy order


def test_hierarchy_order_makes_every_region_contiguous_and_is_stable():
    labels = nested_labels(500)
    order = hierarchy_order(labels)
    assert order.dtype == np.int64
    np.testing.assert_array_equal(np.sort(order), np.arange(500))
    expected = sorted(range(500), key=lambda i: (*labels[i, ::-1].tolist(), i))
    np.testing.assert_array_equal(order, expected)
    laid_out = labels[order]
    for level in range(4):
        for region in np.unique(labels[:, level]):
            positions = np.flatnonzero(laid_out[:, level] == region)
            assert positions[-1] - positions[0] + 1 == len(positions), (level, region)
    # stable: Gaussians with identical labels keep their original order
    for key in np.unique(labels, axis=0):
        members = order[(laid_out == key).all(axis=1)]
        assert (np.diff(members) > 0).all()


def test_hierarchy_order_known_answer_and_inputs():
    labels = np.array([[3, 1], [0, 0], [2, 1], [1, 0], [2, 1], [4, -1]])
    np.testing.assert_array_equal(hierarchy_order(labels), [5, 1, 3, 2, 4, 0])
    np.testing.assert_array_equal(hierarchy_order(torch.from_numpy(labels)), [5, 1, 3, 2, 4, 0])
    np.testing.assert_array_equal(hierarchy_order(np.array([[2], [0], [2], [1]])), [1, 3, 0, 2])
    assert hierarchy_order(np.zeros((0, 4), dtype=np.int32)).shape == (0,)
    for bad in (np.arange(4), np.zeros((4, 0), dtype=int), np.zeros((4, 2)), np.zeros((2, 2, 2))):
        with pytest.raises(InputError, match=r"^labels:"):
            hierarchy_order(bad)


# ----------------------------------------------------------------------------- pack_rgba


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_pack_rgba_hand_picked_values(dtype):
    rgb = np.array([[0.0, 1.0, 0.5], [0.999, 0.25, 0.75], [-0.1, 1.5, 0.9999]], dtype=dtype)
    opacity = np.array([0.5, 1.0, 0.0], dtype=dtype)
    rgba = pack_rgba(rgb, opacity)
    assert rgba.dtype == np.uint8
    # truncation, not rounding: 127.5 → 127, 254.745 → 254, 63.75 → 63, 191.25 → 191
    expected = [[0, 255, 127, 127], [254, 63, 191, 255], [0, 255, 254, 0]]
    np.testing.assert_array_equal(rgba, expected)
    np.testing.assert_array_equal(rgba[:, :3], colors_to_uint8(rgb))
    np.testing.assert_array_equal(rgba[:, 3], colors_to_uint8(opacity))


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
def test_pack_rgba_agrees_with_viser_everywhere(dtype):
    rng = np.random.default_rng(0)
    grid = np.arange(256) / 255.0  # k / 255 lands exactly on the truncation edges
    values = np.concatenate([grid, grid + 1e-7, grid - 1e-7, rng.uniform(-0.1, 1.1, 3000)])
    rgb = values[: len(values) // 3 * 3].reshape(-1, 3).astype(dtype)
    opacity = values[: len(rgb)][::-1].astype(dtype)
    rgba = pack_rgba(rgb, opacity)
    np.testing.assert_array_equal(rgba[:, :3], colors_to_uint8(rgb))
    np.testing.assert_array_equal(rgba[:, 3], colors_to_uint8(opacity))
    np.testing.assert_array_equal(pack_rgba(torch.from_numpy(rgb), torch.from_numpy(opacity)), rgba)


def test_pack_rgba_matches_what_viser_packs_from_floats(server):
    data = scene_arrays()
    handle = server.scene.add_gaussian_splats(
        "/reference",
        centers=data["centers"],
        covariances=data["covariances"],
        rgbs=data["rgb"],
        opacities=data["opacity"][:, None],
    )
    rgba = pack_rgba(data["rgb"], data["opacity"])
    np.testing.assert_array_equal(handle.rgbs, rgba[:, :3])
    np.testing.assert_array_equal(handle.opacities[:, 0], rgba[:, 3])


def test_pack_rgba_rejects_bad_input():
    rgb, opacity = np.full((4, 3), 0.5), np.full(4, 0.5)
    cases = [
        (np.full((4, 4), 0.5), opacity, "rgb"),
        (np.full(4, 0.5), opacity, "rgb"),
        (rgb, np.full((4, 1), 0.5), "opacity"),
        (rgb, np.full(3, 0.5), "opacity"),
        (np.full((4, 3), 128), opacity, "rgb"),  # integers would be read as 0–255
        (rgb, np.ones(4, dtype=bool), "opacity"),
    ]
    nan_rgb = rgb.copy()
    nan_rgb[2, 1] = np.nan
    inf_opacity = opacity.copy()
    inf_opacity[3] = np.inf
    cases += [(nan_rgb, opacity, "rgb"), (rgb, inf_opacity, "opacity")]
    for bad_rgb, bad_opacity, argument in cases:
        with pytest.raises(InputError, match=f"^{argument}:"):
            pack_rgba(bad_rgb, bad_opacity)
    with pytest.raises(InputError, match="row 2"):
        pack_rgba(nan_rgb, opacity)


# ----------------------------------------------------------------------------- SplatChunks

ORDERS = {
    "identity": lambda n: None,
    "random": lambda n: random_permutation(n),
    "hierarchy": lambda n: hierarchy_order(nested_labels(n, seed=5)),
}


@pytest.mark.parametrize("chunk_size", [1, 5, 10, 37, 64])
@pytest.mark.parametrize("order_name", sorted(ORDERS))
def test_chunks_hold_the_scene_in_scene_order(server, sent, chunk_size, order_name):
    data = scene_arrays()
    order = ORDERS[order_name](N)
    chunks = SplatChunks(server.scene, "/splats", **data, order=order, chunk_size=chunk_size)
    count = math.ceil(N / chunk_size)
    assert chunks.chunk_count == count == len(chunks.handles)
    assert len(chunks) == N
    assert [handle.name for handle in chunks.handles] == [f"/splats/{i:04d}" for i in range(count)]
    sizes = [len(handle.buffer) for handle in chunks.handles]
    assert sizes == [min(chunk_size, N - i * chunk_size) for i in range(count)]
    expected_order = np.arange(N) if order is None else order
    np.testing.assert_array_equal(chunks.order, expected_order)

    centers, triu = decode_buffers(chunks, order)
    np.testing.assert_array_equal(centers, data["centers"].astype(np.float32))
    expected_triu = data["covariances"].reshape(N, 9)[:, [0, 1, 2, 4, 5, 8]]
    np.testing.assert_array_equal(triu, expected_triu.astype(np.float16))
    full = triu.astype(np.float32)[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(N, 3, 3)
    np.testing.assert_allclose(full, data["covariances"], rtol=1e-3, atol=1e-7)

    np.testing.assert_array_equal(chunks.rgba(), pack_rgba(data["rgb"], data["opacity"]))
    assert chunks.bytes_sent == 0
    assert buffer_updates(sent) == []  # the initial send creates nodes, it updates none


@pytest.mark.parametrize("chunk_size", [1, 4, 7, 16, 37, 100])
@pytest.mark.parametrize("order_name", sorted(ORDERS))
def test_update_resends_exactly_the_chunks_touched(server, sent, chunk_size, order_name):
    data = scene_arrays()
    order = ORDERS[order_name](N)
    chunks = SplatChunks(server.scene, "splats", **data, order=order, chunk_size=chunk_size)
    geometry = [handle.buffer[:, :7].copy() for handle in chunks.handles]
    positions = layout_positions(order, N)
    rng = np.random.default_rng(chunk_size)
    rgb, opacity = data["rgb"].copy(), data["opacity"].copy()
    bytes_before = 0

    for round_ in range(4):
        touched = rng.choice(N, size=int(rng.integers(1, 6)), replace=False)
        old = pack_rgba(rgb, opacity)
        if round_ % 2:
            opacity[touched] = np.where(old[touched, 3] > 127, 0.0, 1.0)
        else:
            rgb[touched, 1] = np.where(old[touched, 1] > 127, 0.0, 1.0)
        new = pack_rgba(rgb, opacity)
        np.testing.assert_array_equal(np.flatnonzero((new != old).any(axis=1)), np.sort(touched))

        expected = sorted({int(positions[i]) // chunk_size for i in touched})
        del sent[:]
        resent = chunks.update(rgb, opacity)
        assert resent == expected
        assert buffer_updates(sent) == [f"/splats/{i:04d}" for i in expected]  # one message each
        lengths = sum(len(chunks.handles[i].buffer) for i in expected)
        assert chunks.bytes_sent == bytes_before + 32 * lengths
        bytes_before = chunks.bytes_sent
        np.testing.assert_array_equal(chunks.rgba(), new)
        for handle, before in zip(chunks.handles, geometry):
            np.testing.assert_array_equal(handle.buffer[:, :7], before)


def test_identical_update_resends_nothing(server, sent):
    data = scene_arrays()
    chunks = SplatChunks(server.scene, "/splats", **data, order=random_permutation(N), chunk_size=8)
    for rgb, opacity in [
        (data["rgb"], data["opacity"]),
        (torch.from_numpy(data["rgb"]), torch.from_numpy(data["opacity"])),
        (data["rgb"].copy(), data["opacity"].copy()),
    ]:
        assert chunks.update(rgb, opacity) == []
    assert chunks.bytes_sent == 0
    assert buffer_updates(sent) == []


def test_update_below_the_byte_resolution_resends_nothing(server, sent):
    data = scene_arrays()
    k = np.random.default_rng(2).integers(0, 255, (N, 3))
    data["rgb"] = (k + 0.25) / 255.0
    chunks = SplatChunks(server.scene, "/splats", **data, chunk_size=8)
    assert chunks.update((k + 0.75) / 255.0, data["opacity"]) == []  # same bytes after truncation
    assert chunks.bytes_sent == 0
    assert buffer_updates(sent) == []
    np.testing.assert_array_equal(chunks.rgba()[:, :3], k)


def test_bytes_sent_counts_32_bytes_per_gaussian_of_each_resent_chunk(server):
    data = scene_arrays()
    chunks = SplatChunks(server.scene, "/splats", **data, chunk_size=10)
    assert chunks.update(1.0 - data["rgb"] + 0.01, data["opacity"]) == [0, 1, 2, 3]
    assert chunks.bytes_sent == 32 * N
    rgb = 1.0 - data["rgb"] + 0.01
    rgb[36] = [0.0, 0.0, 0.0] if rgb[36, 0] > 0.5 else [1.0, 1.0, 1.0]
    assert chunks.update(rgb, data["opacity"]) == [3]  # the last chunk holds 7 Gaussians
    assert chunks.bytes_sent == 32 * N + 32 * 7


def test_remove(server, sent):
    data = scene_arrays()
    chunks = SplatChunks(server.scene, "/splats", **data, chunk_size=10)
    names = {f"/splats/{i:04d}" for i in range(4)}
    assert names | {"/splats"} <= set(server.scene._handle_from_node_name)

    del sent[:]
    chunks.remove()
    removed = {m.name for m in sent if type(m).__name__ == "RemoveSceneNodeMessage"}
    assert removed == names | {"/splats"}
    assert not any(name.startswith("/splats") for name in server.scene._handle_from_node_name)
    chunks.remove()  # a second call does nothing
    with pytest.raises(RuntimeError, match="removed"):
        chunks.update(data["rgb"], data["opacity"])
    with pytest.raises(RuntimeError):
        chunks.handles[0].buffer = chunks.handles[0].buffer.copy()


def test_empty_scene(server):
    data = scene_arrays(0)
    chunks = SplatChunks(server.scene, "/splats", **data, order=np.zeros(0, dtype=int))
    assert chunks.chunk_count == 0
    assert chunks.rgba().shape == (0, 4)
    assert chunks.update(data["rgb"], data["opacity"]) == []


@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")  # viser's cast
def test_covariances_beyond_float16_are_reported(server, caplog):
    data = scene_arrays()
    data["covariances"][3] *= 1e12
    with caplog.at_level(logging.WARNING, logger="thgs.viewer.splats"):
        SplatChunks(server.scene, "/splats", **data)
    assert "Gaussian 3" in caplog.text


def test_bad_chunk_inputs_name_the_argument(server, sent):
    data = scene_arrays()
    nan_centers = data["centers"].copy()
    nan_centers[4, 0] = np.nan
    duplicate = np.arange(N)
    duplicate[5] = 6
    cases = [
        ({"centers": data["centers"][:, :2]}, "centers", r"\[37, 2\]"),
        ({"centers": nan_centers}, "centers", "row 4"),
        ({"covariances": data["covariances"][:, 0]}, "covariances", r"\[37, 3\]"),
        ({"covariances": data["covariances"][:-1]}, "covariances", r"N = 37"),
        ({"rgb": data["rgb"][:-1]}, "rgb", r"\[36, 3\]"),
        ({"opacity": data["opacity"][:, None]}, "opacity", r"\[37, 1\]"),
        ({"order": duplicate}, "order", "permutation"),
        ({"order": np.arange(N - 1)}, "order", r"\[36\]"),
        ({"order": np.arange(N) + 1}, "order", r"\[0, 37\)"),
        ({"order": np.arange(N, dtype=float)}, "order", "float64"),
        ({"chunk_size": 0}, "chunk_size", "≥ 1"),
        ({"chunk_size": 2.5}, "chunk_size", "integer"),
        ({"name": ""}, "name", "''"),
        ({"name": "/splats/"}, "name", "/splats/"),
    ]
    for change, argument, detail in cases:
        arguments = {"name": "/splats", **data, **change}
        with pytest.raises(InputError, match=f"^{argument}:.*{detail}"):
            SplatChunks(server.scene, **arguments)
    assert sent == []  # nothing was sent for a bad input

    chunks = SplatChunks(server.scene, "/splats", **data, chunk_size=10)
    with pytest.raises(InputError, match=r"^rgb:.*\[36, 3\]"):
        chunks.update(data["rgb"][:-1], data["opacity"])
    with pytest.raises(InputError, match=r"^opacity:.*\[36\]"):
        chunks.update(data["rgb"], data["opacity"][:-1])
    assert chunks.bytes_sent == 0
