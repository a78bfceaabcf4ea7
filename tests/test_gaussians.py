"""Gaussians: accessors against hand computations, check() against broken inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import random_gaussians
from thgs import Gaussians, InputError
from thgs.scene import SH_C0


def one_gaussian(quat, scales) -> Gaussians:
    return Gaussians(
        means=torch.zeros(1, 3),
        quats=torch.tensor([quat], dtype=torch.float32),
        scales=torch.tensor([scales], dtype=torch.float32),
        opacities=torch.zeros(1),
        sh=torch.zeros(1, 1, 3),
    )


def test_activations_by_hand():
    g = Gaussians(
        means=torch.zeros(2, 3),
        quats=torch.tensor([[2.0, 0, 0, 0], [0, 0, 0, 3.0]]),
        scales=torch.tensor([[0.0, math.log(2.0), math.log(0.5)], [1.0, 1.0, 1.0]]),
        opacities=torch.tensor([0.0, math.log(3.0)]),
        sh=torch.tensor([[[0.0, 1.0, -10.0]], [[1.0, 1.0, 1.0]]]),
    ).check()
    assert g.kind == "3dgs" and g.sh_degree == 0 and len(g) == 2
    torch.testing.assert_close(g.activated_opacities(), torch.tensor([0.5, 0.75]))
    torch.testing.assert_close(g.activated_scales()[0], torch.tensor([1.0, 2.0, 0.5]))
    torch.testing.assert_close(g.unit_quats(), torch.tensor([[1.0, 0, 0, 0], [0, 0, 0, 1.0]]))
    torch.testing.assert_close(g.dc_colors()[0], torch.tensor([0.5, 0.5 + SH_C0, 0.0]))


def test_rotation_matrix_90_degrees_about_z():
    half = math.sqrt(0.5)
    g = one_gaussian([half, 0, 0, half], [0.0, 0.0, 0.0])
    expected = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    torch.testing.assert_close(g.rotation_matrices()[0], expected, atol=1e-6, rtol=0)
    # column 0 is where local x goes: x → y under a +90° turn about z
    torch.testing.assert_close(
        g.rotation_matrices()[0] @ torch.tensor([1.0, 0, 0]),
        torch.tensor([0.0, 1, 0]),
        atol=1e-6,
        rtol=0,
    )


def test_rotation_matrices_are_proper_rotations():
    g = random_gaussians(500, seed=3)
    r = g.rotation_matrices().double()
    torch.testing.assert_close(
        r @ r.transpose(1, 2), torch.eye(3).double().expand(500, 3, 3), atol=1e-5, rtol=0
    )
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(500).double(), atol=1e-5, rtol=0)


def test_surfel_normal_is_third_column():
    # 90° about x: local z goes to world −y (third column), the third row would give +y
    half = math.sqrt(0.5)
    g = one_gaussian([half, half, 0, 0], [0.0, 0.0])
    assert g.kind == "2dgs"
    torch.testing.assert_close(
        g.surface_normals()[0], torch.tensor([0.0, -1.0, 0.0]), atol=1e-6, rtol=0
    )


def test_ellipsoid_normal_is_smallest_axis():
    g = one_gaussian([1.0, 0, 0, 0], [0.0, -3.0, -1.0])  # y is the thinnest axis
    torch.testing.assert_close(g.surface_normals()[0], torch.tensor([0.0, 1.0, 0.0]))
    g = random_gaussians(200, seed=1)
    axes = g.scales.argmin(dim=1)
    expected = g.rotation_matrices()[torch.arange(200), :, axes]
    torch.testing.assert_close(g.surface_normals(), expected)


def test_select_keeps_every_field():
    g = random_gaussians(10, sh_degree=2)
    g = Gaussians(
        g.means,
        g.quats,
        g.scales,
        g.opacities,
        g.sh,
        g.normals,
        extras={"label": np.arange(10, dtype=np.int32)},
    )
    picked = g.select(torch.tensor([7, 2]))
    assert len(picked) == 2
    torch.testing.assert_close(picked.sh, g.sh[[7, 2]])
    np.testing.assert_array_equal(picked.extras["label"], [7, 2])
    masked = g.select(torch.arange(10) % 3 == 0)
    torch.testing.assert_close(masked.means, g.means[[0, 3, 6, 9]])


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("means", torch.zeros(4, 2), "means must be"),
        ("scales", torch.zeros(4, 4), "scales must be"),
        ("scales", torch.zeros(4, 1), "scales must be"),
        ("sh", torch.zeros(4, 5, 3), "sh must be"),
        ("opacities", torch.zeros(5), "opacities must be"),
        ("quats", torch.zeros(4, 4), "zero quaternion"),
        ("means", torch.tensor([[0.0, 0, 0]] * 3 + [[0, float("nan"), 0]]), "NaN or infinite"),
        ("sh", torch.full((4, 1, 3), float("inf")), "NaN or infinite"),
        ("opacities", torch.zeros(4, dtype=torch.float64), "dtype"),
    ],
)
def test_check_rejects(field, value, message):
    g = random_gaussians(4, sh_degree=0)
    fields = {name: getattr(g, name) for name in ("means", "quats", "scales", "opacities", "sh")}
    fields[field] = value
    with pytest.raises(InputError, match=message) as info:
        Gaussians(**fields).check(source="my scene")
    assert str(info.value).startswith("my scene: ")


def test_a_passed_check_is_remembered_until_a_tensor_changes_in_place():
    gaussians = random_gaussians(20, seed=3).check()
    key = gaussians.state_key()
    assert gaussians.check() is gaussians and gaussians.state_key() == key
    gaussians.means[4, 1] = float("nan")  # in place: the tensor's version moves on
    assert gaussians.state_key() != key
    with pytest.raises(InputError, match="means has NaN or infinite values in 1 Gaussians"):
        gaussians.check()
    gaussians.means[4, 1] = 0.0
    gaussians.quats[2] = 0.0
    with pytest.raises(InputError, match="zero quaternion"):
        gaussians.check()
