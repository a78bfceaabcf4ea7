"""Property-based corruption of every input format (issue 26): truncations, byte changes and, for
JSON formats, missing keys, wrong types and non-finite numbers. Each reader must either read the
file or raise :class:`thgs.errors.InputError` naming it — never another exception — and must
write nothing. Examples per format: ``max_examples`` below (derandomized, so CI is repeatable)."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import random_cameras
from thgs.errors import InputError
from thgs.eval.lerf_ovs import read_lerf_labels
from thgs.eval.openhype import (
    OpenHypeFrame,
    OpenHypeObject,
    read_openhype_frame,
    write_openhype_annotations,
)
from thgs.field import load_field
from thgs.guidance.langsplat import read_view_guidance
from thgs.scene import (
    read_cameras_json,
    read_colmap,
    read_ply,
    read_transforms_json,
    write_cameras_json,
    write_transforms_json,
)

EXAMPLES = 100
SETTINGS = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


def _listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def _check(reader: Callable[[Path], object], path: Path, name: str) -> None:
    """``reader(path)`` reads or raises an InputError naming ``name``; nothing is written."""
    before = _listing(path.parent if path.is_file() else path)
    try:
        reader(path)
    except InputError as error:
        assert name in str(error), str(error)
    after = _listing(path.parent if path.is_file() else path)
    assert after == before


@st.composite
def damaged(draw, original: bytes) -> bytes:
    """The original cut at some byte, or with a few bytes changed, or both."""
    data = bytearray(original)
    if draw(st.booleans()):
        for _ in range(draw(st.integers(1, 8))):
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
    if draw(st.booleans()) or data == bytearray(original):
        data = data[: draw(st.integers(0, len(data) - 1))]
    return bytes(data)


def _json_mutations(document):
    """Strategy: the document with one value removed, replaced by a wrong type or made
    non-finite, anywhere in its tree."""
    paths = []

    def walk(node, trail):
        if isinstance(node, dict):
            for key, value in node.items():
                paths.append((*trail, key))
                walk(value, (*trail, key))
        elif isinstance(node, list):
            for index, value in enumerate(node[:3]):
                paths.append((*trail, index))
                walk(value, (*trail, index))

    walk(document, ())
    replacements = st.sampled_from(
        ["delete", None, "text", [], {}, float("nan"), float("inf"), -1, 1e300, True]
    )

    @st.composite
    def mutated(draw):
        copy = json.loads(json.dumps(document))
        trail = draw(st.sampled_from(paths))
        parent = copy
        for step in trail[:-1]:
            parent = parent[step]
        value = draw(replacements)
        if value == "delete" and isinstance(parent, dict):
            del parent[trail[-1]]
        elif value == "delete":
            parent.pop(trail[-1])
        else:
            parent[trail[-1]] = value
        return json.dumps(copy)

    return mutated()


@pytest.fixture
def samples(shared_data, tmp_path_factory):
    root = tmp_path_factory.mktemp("samples")
    cameras = random_cameras(3, centred=True)
    write_cameras_json(root / "cameras.json", cameras)
    write_transforms_json(root / "transforms.json", cameras)
    return {
        "ply": (shared_data / "ply_3dgs_train1000.ply").read_bytes(),
        "lerf": (
            sorted((shared_data / "lerf_ovs_labels" / "teatime").glob("*.json"))[0]
        ).read_text(),
        "cameras.json": (root / "cameras.json").read_text(),
        "transforms.json": (root / "transforms.json").read_text(),
    }


@SETTINGS
@given(data=st.data())
def test_damaged_ply_files(samples, tmp_path, data):
    path = tmp_path / "scene.ply"
    path.write_bytes(data.draw(damaged(samples["ply"])))
    _check(read_ply, path, "scene.ply")


@pytest.mark.slow
@SETTINGS
@given(data=st.data())
def test_damaged_lerf_label_files(samples, tmp_path, data):
    path = tmp_path / "frame_00002.json"
    if data.draw(st.booleans()):
        path.write_text(data.draw(_json_mutations(json.loads(samples["lerf"]))))
    else:
        path.write_bytes(data.draw(damaged(samples["lerf"].encode())))
    _check(read_lerf_labels, path, "frame_00002.json")


@SETTINGS
@given(data=st.data())
def test_damaged_camera_files(samples, tmp_path, data):
    for name, reader in (
        ("cameras.json", read_cameras_json),
        ("transforms.json", read_transforms_json),
    ):
        path = tmp_path / name
        if data.draw(st.booleans()):
            path.write_text(data.draw(_json_mutations(json.loads(samples[name]))))
        else:
            path.write_bytes(data.draw(damaged(samples[name].encode())))
        _check(reader, path, name)


@SETTINGS
@given(data=st.data())
def test_damaged_colmap_models(shared_data, tmp_path, data):
    model = tmp_path / "sparse"
    shutil.rmtree(model, ignore_errors=True)
    shutil.copytree(shared_data / "colmap_small" / "sparse" / "0", model)
    name = data.draw(st.sampled_from(sorted(p.name for p in model.iterdir())))
    path = model / name
    path.write_bytes(data.draw(damaged(path.read_bytes())))
    _check(read_colmap, model, "sparse")


@SETTINGS
@given(data=st.data())
def test_damaged_field_files(small_field, tmp_path, data):
    path = tmp_path / "field.thgs"
    path.write_bytes(data.draw(damaged(small_field.read_bytes())))
    _check(load_field, path, "field.thgs")


@SETTINGS
@given(data=st.data())
def test_damaged_guidance_files(small_dataset, tmp_path, data):
    folder = tmp_path / "language_features"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir()
    stem = sorted(p.name for p in (small_dataset / "language_features").glob("*_s.npy"))[0][:-6]
    for suffix in ("_s.npy", "_f.npy"):
        shutil.copy(small_dataset / "language_features" / f"{stem}{suffix}", folder)
    name = f"{stem}{data.draw(st.sampled_from(['_s.npy', '_f.npy']))}"
    path = folder / name
    if data.draw(st.booleans()):
        path.write_bytes(data.draw(damaged(path.read_bytes())))
    else:  # a well-formed array with wrong values: NaN, huge, negative, another dtype
        array = np.load(path)
        flat = array.reshape(-1).copy()
        index = data.draw(st.integers(0, flat.size - 1))
        value = data.draw(st.sampled_from([np.nan, np.inf, -7.0, 1e30, 0.5]))
        flat = flat.astype(np.float64)
        flat[index] = value
        np.save(path, flat.reshape(array.shape).astype(data.draw(st.sampled_from(["f4", "f8"]))))
    _check(lambda p: read_view_guidance(p.parent, stem), path, name)


@pytest.fixture
def openhype_folder(tmp_path_factory) -> Path:
    """One OpenHype annotation file with an object and a part prompt and their masks."""
    folder = tmp_path_factory.mktemp("openhype") / "gt"
    masks = np.zeros((2, 6, 8), dtype=bool)
    masks[0, :3], masks[1, 3:, :2] = True, True
    objects = (
        OpenHypeObject("chair", False, masks[0], np.array([[0.0, 0.0, 7.0, 2.0]]), "m/00.png"),
        OpenHypeObject("leg of a chair", True, masks[1], np.array([[0.0, 3, 1, 5]]), "m/01.png"),
    )
    K = np.array([[8.0, 0.0, 4.0], [0.0, 8.0, 3.0], [0.0, 0.0, 1.0]])
    frame = OpenHypeFrame("DSC00001", "DSC00001.JPG", 8, 6, K, np.eye(4), "PINHOLE", objects)
    write_openhype_annotations(folder, [frame])
    return folder


@SETTINGS
@given(data=st.data())
def test_damaged_openhype_annotations(openhype_folder, tmp_path, data):
    folder = tmp_path / "gt"
    shutil.rmtree(folder, ignore_errors=True)
    shutil.copytree(openhype_folder, folder)
    path = folder / "DSC00001.json"
    kind = data.draw(st.sampled_from(["mutated", "damaged", "mask"]))
    if kind == "mutated":
        path.write_text(data.draw(_json_mutations(json.loads(path.read_text()))))
    elif kind == "damaged":
        path.write_bytes(data.draw(damaged(path.read_bytes())))
    else:
        mask = folder / "m" / data.draw(st.sampled_from(["00.png", "01.png"]))
        mask.write_bytes(data.draw(damaged(mask.read_bytes())))
        _check(read_openhype_frame, path, "gt/")
        return
    _check(read_openhype_frame, path, "DSC00001.json")


@st.composite
def altered(draw, original: bytes) -> bytes:
    """The original with one to eight bytes changed, its length kept (a truncation is caught by
    any reader; a change of content under an intact header is what a checksum is for)."""
    data = bytearray(original)
    for _ in range(draw(st.integers(1, 8))):
        data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
    return bytes(data)


@SETTINGS
@given(data=st.data())
def test_an_altered_field_is_refused_or_read_unchanged(small_field, tmp_path, data):
    """Never a different field: every tensor equal to the original's, or an InputError."""
    original = load_field(small_field)
    path = tmp_path / "field.thgs"
    path.write_bytes(data.draw(altered(small_field.read_bytes())))
    try:
        field = load_field(path)
    except InputError as error:
        assert str(path) in str(error)
        return
    np.testing.assert_array_equal(field.labels, original.labels)
    for k in range(3):
        np.testing.assert_array_equal(field.parents[k], original.parents[k])
        np.testing.assert_array_equal(field.features[k], original.features[k])
        np.testing.assert_array_equal(field.seen[k], original.seen[k])


@pytest.fixture(scope="module")
def cached_lift(small_dataset, tmp_path_factory):
    """A lift cache file of the small dataset, its key, view count and lifts."""
    from thgs.guidance import load_guidance
    from thgs.lift import LiftConfig
    from thgs.lift_cache import lift_cache_path, lift_key
    from thgs.pipeline import lift_scene
    from thgs.scene import load_scene

    scene = load_scene(small_dataset)
    guidance = load_guidance(small_dataset / "language_features", scene.cameras)
    folder = tmp_path_factory.mktemp("lift-cache")
    lifted = lift_scene(scene, guidance, LiftConfig(), cache=folder).lifted
    key = lift_key(scene.gaussians, scene.cameras, guidance, LiftConfig())
    return lift_cache_path(folder, key), key, len(guidance), list(lifted)


@SETTINGS
@given(data=st.data())
def test_an_altered_lift_cache_is_refused_or_read_unchanged(cached_lift, tmp_path, data):
    """Never a different lift: read_cached_lift gives every tensor bit for bit, or None (the
    build lifts again)."""
    import torch

    from thgs.lift_cache import read_cached_lift

    original_path, key, views, lifted = cached_lift
    path = tmp_path / original_path.name
    path.write_bytes(data.draw(altered(original_path.read_bytes())))
    read = read_cached_lift(path, key, views)
    if read is None:
        return
    for got, expected in zip(read, lifted, strict=True):
        for name in ("gaussians", "labels", "depths", "max_weights"):
            assert torch.equal(getattr(got, name), getattr(expected, name)), name
