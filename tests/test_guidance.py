"""LangSplat-layout guidance: files written as LangSplat does read back right; bad files fail."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from thgs import Cameras, InputError
from thgs.guidance import (
    EMBEDDING_FILE,
    GuidanceFolder,
    ViewGuidance,
    check_masks,
    guidance_space,
    load_guidance,
    read_embedding_model,
    read_embedding_space,
    read_view_guidance,
    resample_segments,
    write_embedding_space,
    write_view_guidance,
)
from thgs.text import LANGSPLAT_SPACE


def langsplat_files(folder, stem, level_maps, features):
    """Write like LangSplat's preprocess: local ids per level, shifted by the previous counts."""
    counts = [int(m.max()) + 1 for m in level_maps]
    segments = np.stack([m.astype(np.float32) for m in level_maps])
    offset = 0
    for level in range(4):
        segments[level][segments[level] != -1] += offset
        offset += counts[level]
    assert offset == len(features)
    np.save(folder / f"{stem}_s.npy", segments)
    np.save(folder / f"{stem}_f.npy", features.astype(np.float32))


def example_levels():
    default = np.array([[0, 0, 1], [-1, 1, 1]])
    small = np.array([[0, 1, 2], [-1, -1, 2]])
    medium = np.array([[0, 0, 0], [-1, 1, 1]])
    large = np.array([[0, 0, 0], [0, 0, 0]])
    return [default, small, medium, large]  # 2 + 3 + 2 + 1 = 8 masks


def features(n, d=6, seed=0):
    rows = np.random.default_rng(seed).normal(size=(n, d))
    return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


def test_reads_langsplat_offsets(tmp_path):
    langsplat_files(tmp_path, "frame_00001", example_levels(), features(8))
    view = read_view_guidance(tmp_path, "frame_00001")
    assert (view.height, view.width) == (2, 3) and view.segments.dtype == np.int32
    # level s, local mask 2 is global row 2 + 2 = 4; level l, local 0 is row 2 + 3 + 2 = 7
    assert view.segments[1, 0, 2] == 4 and view.segments[1, 1, 0] == -1
    assert (view.segments[3] == 7).all()
    assert view.level_ids(2).tolist() == [5, 6]
    np.testing.assert_array_equal(view.features, features(8))


def test_write_read_round_trip(tmp_path):
    langsplat_files(tmp_path, "a", example_levels(), features(8))
    view = read_view_guidance(tmp_path, "a")
    write_view_guidance(tmp_path / "out", view)
    for suffix in ("_s.npy", "_f.npy"):
        assert (tmp_path / "out" / f"a{suffix}").read_bytes() == (
            tmp_path / f"a{suffix}"
        ).read_bytes()


@pytest.mark.parametrize(
    ("segments", "feature_rows", "message"),
    [
        (np.zeros((3, 2, 2)), 1, r"\[4, H, W\]"),
        (np.full((4, 2, 2), 0.5), 1, "whole numbers"),
        (np.full((4, 2, 2), np.nan), 1, "16 mask ids are NaN or infinite"),
        (np.full((4, 2, 2), 3.0), 2, r"mask id 3 has no feature row: the features hold 2 rows"),
        (np.full((4, 2, 2), -5.0), 134, "mask id -5 is invalid: ids are feature rows"),
        (
            np.stack([np.full((2, 2), v, np.float32) for v in (1, 0, 2, 3)]),
            4,
            "level 's' uses mask id 0",
        ),
    ],
)
def test_bad_files(tmp_path, segments, feature_rows, message):
    np.save(tmp_path / "v_s.npy", segments.astype(np.float32))
    np.save(tmp_path / "v_f.npy", features(feature_rows))
    with pytest.raises(InputError, match=message) as info:
        read_view_guidance(tmp_path, "v")
    assert "v_s.npy" in str(info.value)


def test_missing_truncated_and_nan(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        read_view_guidance(tmp_path, "nothing")
    langsplat_files(tmp_path, "v", example_levels(), features(8))
    data = (tmp_path / "v_f.npy").read_bytes()
    (tmp_path / "v_f.npy").write_bytes(data[:-20])
    with pytest.raises(InputError, match=r"not a readable \.npy"):
        read_view_guidance(tmp_path, "v")
    bad = features(8)
    bad[3, 1] = np.nan
    bad[5, 0] = np.inf
    np.save(tmp_path / "v_f.npy", bad)
    path = tmp_path / "v_f.npy"
    with pytest.raises(
        InputError,
        match=rf"^{path}: features have NaN or infinite values in 2 of 8 rows \(first: row 3\)",
    ):
        read_view_guidance(tmp_path, "v")
    np.save(tmp_path / "v_f.npy", features(8)[:, 0])
    with pytest.raises(
        InputError,
        match=rf"^{path}: expected an \[n, D\] array of floats \(one feature row per mask\), got "
        r"a 1-D float32 array of shape \[8\]$",
    ):
        read_view_guidance(tmp_path, "v")


def test_failed_write_leaves_nothing(tmp_path):
    broken = ViewGuidance("x", np.full((4, 2, 2), 5, np.int32), features(2))
    with pytest.raises(InputError, match="mask id 5 has no feature row"):
        write_view_guidance(tmp_path, broken)
    assert list(tmp_path.iterdir()) == []


def test_resample_by_hand():
    segments = np.arange(16, dtype=np.int32).reshape(1, 4, 4).repeat(4, axis=0)
    down = resample_segments(segments, 2, 2)
    np.testing.assert_array_equal(down[0], [[5, 7], [13, 15]])  # the pixels under the centres
    up = resample_segments(down, 4, 4)
    np.testing.assert_array_equal(
        up[0], [[5, 5, 7, 7], [5, 5, 7, 7], [13, 13, 15, 15], [13, 13, 15, 15]]
    )


def cameras_for(stems, width, height):
    m = len(stems)
    K = torch.tensor([[10.0, 0, width / 2], [0, 10.0, height / 2], [0, 0, 1]], dtype=torch.float64)
    return Cameras(
        torch.eye(4, dtype=torch.float64).repeat(m, 1, 1),
        K.repeat(m, 1, 1),
        torch.full((m,), width),
        torch.full((m,), height),
        tuple(f"images/{s}.jpg" for s in stems),
    )


def test_load_guidance_matches_cameras(tmp_path):
    for i, stem in enumerate(("b", "a")):
        langsplat_files(tmp_path, stem, example_levels(), features(8, seed=i))
    views = load_guidance(tmp_path, cameras_for(["a", "b"], 3, 2))
    assert [v.stem for v in views] == ["a", "b"]
    np.testing.assert_array_equal(views[0].features, features(8, seed=1))
    with pytest.raises(
        InputError, match=r"masks are 3×2 but the camera is 6×4; resample them with --resize"
    ):
        load_guidance(tmp_path, cameras_for(["a"], 6, 4))
    resized = load_guidance(tmp_path, cameras_for(["a"], 6, 4), resize=True)
    assert resized[0].segments.shape == (4, 4, 6)
    with pytest.raises(InputError, match=r"no guidance for 1 of 2 views .first: \['c'\]"):
        load_guidance(tmp_path, cameras_for(["a", "c"], 3, 2))
    langsplat_files(tmp_path, "d", example_levels(), features(8, d=5))
    with pytest.raises(InputError, match="feature dimension 5, other views have 6"):
        load_guidance(tmp_path, cameras_for(["a", "d"], 3, 2))


def test_lazy_guidance_reads_the_same_views_on_access(tmp_path):
    """lazy=True: the same views (resampled too), read from the files on each access; every
    problem is found when loading, before any view is used."""
    for i, stem in enumerate(("b", "a", "c")):
        langsplat_files(tmp_path, stem, example_levels(), features(8, seed=i))
    for cameras, resize in ((cameras_for(["a", "b", "c"], 3, 2), False),
                            (cameras_for(["c", "a"], 6, 4), True)):  # fmt: skip
        eager = load_guidance(tmp_path, cameras, resize=resize)
        lazy = load_guidance(tmp_path, cameras, resize=resize, lazy=True)
        assert isinstance(lazy, GuidanceFolder) and len(lazy) == len(eager)
        for got in (list(lazy), [lazy[i] for i in range(len(lazy))], lazy[::-1][::-1]):
            for x, y in zip(got, eager, strict=True):
                assert x.stem == y.stem
                np.testing.assert_array_equal(x.segments, y.segments)
                np.testing.assert_array_equal(x.features, y.features)
        for i, view in enumerate(eager):  # the features alone, without the masks
            got = lazy.features(i)
            assert got.dtype == np.float32 and got.shape == view.features.shape
            np.testing.assert_array_equal(got, view.features)
        np.testing.assert_array_equal(lazy.features(-1), eager[-1].features)
        assert lazy[-1].stem == eager[-1].stem
    # a features file damaged after loading is named when its features are read
    lazy = load_guidance(tmp_path, cameras_for(["a", "b"], 3, 2), lazy=True)
    damaged = features(8, seed=1)
    damaged[3, 0] = np.nan
    np.save(tmp_path / "a_f.npy", damaged)
    with pytest.raises(InputError, match=r"a_f\.npy: features have NaN or infinite values in 1 of "
                       r"8 rows \(first: row 3\)"):  # fmt: skip
        lazy.features(0)
    langsplat_files(tmp_path, "a", example_levels(), features(8, seed=1))
    with pytest.raises(InputError, match=r"masks are 3×2 but the camera is 6×4"):
        load_guidance(tmp_path, cameras_for(["a"], 6, 4), lazy=True)
    langsplat_files(tmp_path, "d", example_levels(), features(8, d=5))
    with pytest.raises(InputError, match="feature dimension 5, other views have 6"):
        load_guidance(tmp_path, cameras_for(["a", "d"], 3, 2), lazy=True)
    (tmp_path / "b_s.npy").write_bytes(b"not an array")
    with pytest.raises(InputError, match=r"b_s\.npy: not a readable \.npy file"):
        load_guidance(tmp_path, cameras_for(["a", "b"], 3, 2), lazy=True)


def _views(dims_and_masks):
    """One view per (D, has_masks): a 2 × 3 view with one mask everywhere, or none."""
    views = []
    for i, (dim, masked) in enumerate(dims_and_masks):
        segments = np.full((4, 2, 3), 0 if masked else -1, dtype=np.int32)
        rows = np.eye(1, dim, dtype=np.float32) if masked else np.zeros((0, dim), np.float32)
        views.append(ViewGuidance(f"v{i}", segments, rows))
    return views


def test_embedding_file_must_agree_with_the_features(tmp_path):
    write_embedding_space(tmp_path, "my/space", 6, model=tmp_path / "model" / ".." / "model")
    assert read_embedding_space(tmp_path) == ("my/space", 6)
    assert read_embedding_model(tmp_path) == (tmp_path / "model").resolve()
    assert guidance_space(tmp_path, _views([(6, True)])) == "my/space"
    path = tmp_path / EMBEDDING_FILE
    with pytest.raises(
        InputError,
        match=rf"^{path}: records 6-D features of my/space but the "
        r"folder's _f\.npy files hold 512-D features",
    ):
        guidance_space(tmp_path, _views([(512, True)]))
    write_embedding_space(tmp_path, LANGSPLAT_SPACE, 16)
    assert read_embedding_model(tmp_path) is None
    with pytest.raises(
        InputError, match=rf"records 16-D features of {LANGSPLAT_SPACE}, which is 512"
    ):
        guidance_space(tmp_path, _views([(16, True)]))
    path.write_text('{"space": "x/y", "dim": 4, "model": 3}')
    with pytest.raises(InputError, match="'model' must be a folder path, got 3"):
        read_embedding_model(tmp_path)


def test_guidance_without_any_mask_is_refused():
    assert check_masks(_views([(4, True), (4, False), (4, True)]), "lf") == ["v1"]
    with pytest.raises(InputError) as caught:
        check_masks(_views([(4, False), (4, False)]), "scene/language_features")
    message = str(caught.value)
    assert message.startswith("scene/language_features: none of the 2 views has a mask")
    assert "--pred-iou-threshold" in message and "--min-region-area" in message
