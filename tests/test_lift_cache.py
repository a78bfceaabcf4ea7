"""The lift cache: a hit gives the computed lift bit for bit (so the same field), any change to
what a lift depends on misses, a colour change does not, and a broken file is relifted."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging

import numpy as np
import pytest
import torch

from test_cli import run
from thgs.errors import InputError
from thgs.field import load_field
from thgs.guidance import load_guidance
from thgs.lift import LiftConfig
from thgs.lift_cache import lift_cache_path, lift_key, read_cached_lift
from thgs.pipeline import FieldConfig, build_field, lift_scene
from thgs.render import RasterConfig
from thgs.scene import load_scene


@pytest.fixture(scope="module")
def inputs(small_dataset):
    scene = load_scene(small_dataset)
    return scene, load_guidance(small_dataset / "language_features", scene.cameras)


def same_lifts(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        for name in ("gaussians", "labels", "depths", "max_weights"):
            u, v = getattr(x, name), getattr(y, name)
            assert u.dtype == v.dtype and torch.equal(u, v), name


@pytest.mark.slow
def test_a_hit_is_the_computed_lift_and_the_same_field(inputs, tmp_path, caplog):
    scene, guidance = inputs
    config = FieldConfig()
    plain = build_field(scene, guidance, config, space="s")
    first = lift_scene(scene, guidance, config.superpoints.lift, cache=tmp_path)
    assert len(list(tmp_path.glob("lift-*.safetensors"))) == 1
    with caplog.at_level(logging.INFO, logger="thgs.lift_cache"):
        again = lift_scene(scene, guidance, config.superpoints.lift, cache=tmp_path)
    assert "lift read from the cache" in caplog.text
    same_lifts(first.lifted, again.lifted)
    cached = build_field(scene, guidance, config, space="s", lift_cache=tmp_path)
    np.testing.assert_array_equal(cached.labels, plain.labels)
    for x, y in zip(cached.features, plain.features, strict=True):
        np.testing.assert_array_equal(x, y)
    assert len(list(tmp_path.glob("lift-*.safetensors"))) == 1


def test_the_key_follows_what_the_lift_depends_on(inputs):
    scene, guidance = inputs
    gaussians, cameras, config = scene.gaussians, scene.cameras, LiftConfig()
    key = lift_key(gaussians, cameras, guidance, config)
    assert lift_key(gaussians, cameras, guidance, config) == key

    means = gaussians.means.clone()
    means[7, 0] += 1e-4
    assert lift_key(dataclasses.replace(gaussians, means=means), cameras, guidance, config) != key
    recoloured = dataclasses.replace(gaussians, sh=gaussians.sh + 0.5)
    assert lift_key(recoloured, cameras, guidance, config) == key  # colours do not lift

    segments = guidance[3].segments.copy()
    segments[1, 10, 10] = -1 if segments[1, 10, 10] >= 0 else 0
    edited = [*guidance[:3], dataclasses.replace(guidance[3], segments=segments), *guidance[4:]]
    assert lift_key(gaussians, cameras, edited, config) != key
    features = guidance[0].features.copy()
    features[0, 0] += 1e-3
    edited = [dataclasses.replace(guidance[0], features=features), *guidance[1:]]
    assert lift_key(gaussians, cameras, edited, config) != key

    viewmats = cameras.viewmats.clone()
    viewmats[2, 0, 3] += 1e-6
    moved = dataclasses.replace(cameras, viewmats=viewmats)
    assert lift_key(gaussians, moved, guidance, config) != key
    for changed in (
        dataclasses.replace(config, cosine_threshold=config.cosine_threshold + 0.01),
        dataclasses.replace(config, raster=RasterConfig(alpha_min=0.01)),
        dataclasses.replace(config, raster=RasterConfig(precision="float32")),
    ):
        assert lift_key(gaussians, cameras, guidance, changed) != key


def rewrite_tensor(path, name, change, checksum=False):
    """``change`` applied in place to the tensor ``name`` of a cache file, its header intact;
    with ``checksum`` the header's checksum is made to match the new content."""
    data = bytearray(path.read_bytes())
    length = int.from_bytes(data[:8], "little")
    header = json.loads(data[8 : 8 + length])
    begin, end = (8 + length + offset for offset in header[name]["data_offsets"])
    dtype = {"I16": np.int16, "I32": np.int32, "F32": np.float32}[header[name]["dtype"]]
    values = np.frombuffer(bytes(data[begin:end]), dtype=dtype).copy()
    change(values)
    data[begin:end] = values.tobytes()
    if checksum:
        old = json.loads(header["__metadata__"]["thgs"])["checksum"]
        new = hashlib.sha256(bytes(data[8 + length :])).hexdigest()
        data[8 : 8 + length] = data[8 : 8 + length].replace(old.encode(), new.encode())
    path.write_bytes(bytes(data))


@pytest.mark.slow
@pytest.mark.parametrize(
    "damage",
    [
        "truncated",
        "garbage",
        "other key",
        "fewer views",
        "zeroed labels",
        "index out of range",
        "nan depths",
    ],
)
def test_a_broken_or_foreign_file_is_lifted_again(inputs, tmp_path, caplog, damage):
    scene, guidance = inputs
    config = LiftConfig()
    first = lift_scene(scene, guidance, config, cache=tmp_path)
    key = lift_key(scene.gaussians, scene.cameras, guidance, config)
    path = lift_cache_path(tmp_path, key)
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(b"not safetensors")
    elif damage == "zeroed labels":  # header intact: only the checksum can tell
        for i in range(len(guidance)):
            rewrite_tensor(path, f"v{i}.labels", lambda values: values.fill(0))
    elif damage == "index out of range":  # the checksum made to match: the indices tell
        rewrite_tensor(path, "v1.gaussians", lambda values: values.__setitem__(-1, 10**9), True)
    elif damage == "nan depths":
        rewrite_tensor(path, "v2.depths", lambda values: values.__setitem__(0, np.nan), True)
    elif damage == "other key":
        assert read_cached_lift(path, "0" * 64, len(guidance)) is None
        return
    else:
        assert read_cached_lift(path, key, len(guidance) - 1) is None
        return
    with caplog.at_level(logging.WARNING, logger="thgs.lift_cache"):
        again = lift_scene(scene, guidance, config, cache=tmp_path)
    assert f"lift cache {path} unusable" in caplog.text
    same_lifts(first.lifted, again.lifted)
    assert read_cached_lift(path, key, len(guidance)) is not None  # rewritten whole


@pytest.mark.slow
def test_build_reuses_the_lift_from_the_command_line(small_dataset, tmp_path, capsys):
    cache = tmp_path / "lifts"
    first, second = tmp_path / "a.thgs", tmp_path / "b.thgs"
    for out, extra in ((first, []), (second, ["--set", "merge.rounds=1"])):
        argv = ["build", str(small_dataset), "-o", str(out), "--lift-cache", str(cache), *extra]
        code, _, err = run(argv, capsys)
        assert code == 0, err
    assert len(list(cache.glob("lift-*.safetensors"))) == 1  # the merge setting reused the lift
    assert load_field(second).config["merge"]["rounds"] == 1


def test_a_cache_that_is_a_file_stops_before_any_work(inputs, small_dataset, tmp_path, capsys):
    scene, guidance = inputs
    taken = tmp_path / "lifts"
    taken.write_text("mine")
    out = tmp_path / "a.thgs"
    argv = ["build", str(small_dataset), "-o", str(out), "--lift-cache", str(taken)]
    code, _, err = run(argv, capsys)
    assert code == 2 and "--lift-cache" in err and f"{taken} is a file" in err
    assert not out.exists() and taken.read_text() == "mine"
    progress = []
    with pytest.raises(InputError, match=rf"{taken}: is a file; the lift cache is a folder"):
        lift_scene(scene, guidance, cache=taken, progress=lambda *step: progress.append(step))
    assert progress == []
