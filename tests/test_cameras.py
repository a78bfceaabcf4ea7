"""Cameras: projection by hand, resizing, check() against broken inputs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import random_cameras
from thgs import Cameras, InputError

# A camera at (−5, 0, 0) looking along world +x; camera right = world −y, camera down = world −z.
HAND_ROTATION = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
HAND_CENTRE = np.array([-5.0, 0.0, 0.0])
HAND_POINTS = np.array([[0.0, 0.0, 0.0], [1.0, -1.0, 2.0], [-2.0, 3.0, -1.5]])
# cam = R p + (0, 0, 5): (0,0,5), (1,−2,6), (−3,1.5,3); pixel = (100 x/z + 160, 110 y/z + 120)
HAND_PIXELS = np.array([[160.0, 120.0], [160 + 100 / 6, 120 - 220 / 6], [160 - 100, 120 + 55]])
HAND_DEPTHS = np.array([5.0, 6.0, 3.0])


def hand_camera() -> Cameras:
    viewmat = np.eye(4)
    viewmat[:3, :3] = HAND_ROTATION
    viewmat[:3, 3] = -HAND_ROTATION @ HAND_CENTRE
    return Cameras(
        viewmats=torch.tensor(viewmat[None]),
        Ks=torch.tensor([[[100.0, 0, 160], [0, 110, 120], [0, 0, 1]]], dtype=torch.float64),
        widths=torch.tensor([320]),
        heights=torch.tensor([240]),
        names=("hand.png",),
    ).check()


def test_project_by_hand():
    pixels, depths = hand_camera().project(torch.tensor(HAND_POINTS))
    np.testing.assert_allclose(pixels[0].numpy(), HAND_PIXELS, atol=1e-12)
    np.testing.assert_allclose(depths[0].numpy(), HAND_DEPTHS, atol=1e-12)


def test_centres_and_inverse():
    cameras = random_cameras(6)
    eye = torch.eye(4, dtype=torch.float64).expand(6, 4, 4)
    torch.testing.assert_close(cameras.camtoworlds() @ cameras.viewmats, eye)
    torch.testing.assert_close(cameras.camtoworlds()[:, :3, 3], cameras.centers())
    np.testing.assert_allclose(hand_camera().centers()[0].numpy(), HAND_CENTRE, atol=1e-12)


def test_resize_keeps_pixel_edges():
    """Halving the image maps the continuous pixel coordinate x to x / 2 (edges to edges)."""
    camera = hand_camera()
    half = camera.scaled(0.5)
    assert (int(half.widths[0]), int(half.heights[0])) == (160, 120)
    pixels, _ = camera.project(torch.tensor(HAND_POINTS))
    half_pixels, _ = half.project(torch.tensor(HAND_POINTS))
    torch.testing.assert_close(half_pixels, pixels / 2)
    odd = camera.resized([250], [165])
    torch.testing.assert_close(
        odd.Ks[0, 0, 2], torch.tensor(160.0 * 250 / 320, dtype=torch.float64)
    )
    torch.testing.assert_close(
        odd.Ks[0, 1, 1], torch.tensor(110.0 * 165 / 240, dtype=torch.float64)
    )
    assert camera.scaled(0.25).heights.tolist() == [60]
    # 658 · 0.25 = 164.5 rounds half up, as the resizers do
    assert Cameras.scaled(camera.resized([1000], [658]), 0.25).heights.tolist() == [165]


def test_select_and_stems():
    cameras = random_cameras(5)
    picked = cameras.select([4, 1])
    assert picked.names == ("view_004.png", "view_001.png")
    torch.testing.assert_close(picked.Ks, cameras.Ks[[4, 1]])
    named = Cameras(
        cameras.viewmats[:2],
        cameras.Ks[:2],
        cameras.widths[:2],
        cameras.heights[:2],
        ("images/a.b.jpg", "c"),
    )
    assert named.stems == ("a.b", "c")


def broken(**changes) -> Cameras:
    camera = hand_camera()
    fields = {
        name: getattr(camera, name) for name in ("viewmats", "Ks", "widths", "heights", "names")
    }
    fields.update(changes)
    return Cameras(**fields)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        (
            {"viewmats": torch.diag(torch.tensor([2.0, 2, 2, 1], dtype=torch.float64))[None]},
            "not a proper rotation",
        ),
        ({"viewmats": torch.ones(1, 4, 4, dtype=torch.float64)}, "last row"),
        (
            {"viewmats": torch.diag(torch.tensor([1.0, 1, -1, 1], dtype=torch.float64))[None]},
            "not a proper rotation",
        ),
        ({"viewmats": torch.full((1, 4, 4), float("nan"), dtype=torch.float64)}, "not finite"),
        ({"viewmats": torch.eye(4)[None]}, "must be float64"),
        ({"Ks": torch.tensor([[[100.0, 0, 160], [0, -110, 120], [0, 0, 1]]]).double()}, "focal"),
        (
            {"Ks": torch.tensor([[[100.0, 0, 160], [0, 110, 120], [0, 0, 2]]]).double()},
            "not a pinhole",
        ),
        ({"widths": torch.tensor([0])}, "size 0×240"),
        ({"names": ("a", "b")}, "2 names for 1 cameras"),
        ({"names": ("",)}, "empty image name"),
        ({"Ks": torch.eye(3, dtype=torch.float64)}, r"Ks must be \[1, 3, 3\]"),
    ],
)
def test_check_rejects(changes, message):
    with pytest.raises(InputError, match=message):
        broken(**changes).check(source="cams")


def test_check_rejects_duplicate_stems():
    cameras = random_cameras(3)
    duplicated = Cameras(
        cameras.viewmats,
        cameras.Ks,
        cameras.widths,
        cameras.heights,
        ("a/x.png", "b/x.jpg", "y.png"),
    )
    with pytest.raises(InputError, match=r"not unique per stem: \['x'\]"):
        duplicated.check()
