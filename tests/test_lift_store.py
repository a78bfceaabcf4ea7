"""Lifts kept in a temporary file (thgs.lift_store): views read back bit for bit, slices and
iteration read on demand, a build whose lift moves to the file gives the same field, and the
lift cache written view by view is what safetensors itself would store."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file

from test_lift_cache import inputs, same_lifts  # noqa: F401 - the module fixture
from thgs import InputError, ThgsError
from thgs.lift import ViewLift
from thgs.lift_cache import lift_cache_path, lift_key, read_cached_lift, write_lift
from thgs.lift_store import LiftStore, lift_bytes
from thgs.pipeline import FieldConfig, build_field, lift_scene


def random_views(seed: int) -> list[ViewLift]:
    """Views of 0 to 300 Gaussians out of 1000; labels int16 except one int32 view."""
    generator = np.random.default_rng(seed)
    views = []
    for i, n in enumerate([120, 0, 300, 1, 57]):
        gaussians = np.sort(generator.choice(1000, size=n, replace=False)).astype(np.int32)
        dtype = np.int32 if i == 3 else np.int16
        labels = generator.integers(-1, 40000 if i == 3 else 300, size=(n, 4)).astype(dtype)
        depths = generator.uniform(0.1, 9.0, size=n).astype(np.float32)
        weights = generator.uniform(0.0, 1.0, size=n).astype(np.float32)
        views.append(ViewLift(gaussians, labels, depths, weights))
    return views


def test_views_come_back_bit_for_bit():
    views = random_views(0)
    store = LiftStore("cpu")
    for view in views:
        store.append(view)
    assert len(store) == 5
    assert store.nbytes == sum(lift_bytes(view) for view in views)
    same_lifts(list(store), views)
    same_lifts([store[i] for i in (4, 0, 2)], [views[i] for i in (4, 0, 2)])
    same_lifts(list(store[::2]), views[::2])
    same_lifts(list(store[1:][::2]), views[1:][::2])
    assert len(store[::2]) == 3 and store[-1].labels.dtype == torch.int16
    assert store[3].labels.dtype == torch.int32 and int(store[3].labels.max()) >= 32767
    with pytest.raises(IndexError):
        store[5]
    store.close()


@pytest.mark.slow
def test_the_lift_moves_to_the_file_past_its_budget_and_the_field_is_the_same(inputs, caplog):  # noqa: F811
    scene, guidance = inputs
    config = FieldConfig()
    plain = lift_scene(scene, guidance, config.superpoints.lift, memory=None)
    assert isinstance(plain.lifted, list)
    budget = lift_bytes(plain.lifted[0]) + 1  # the second view goes over
    with caplog.at_level(logging.INFO, logger="thgs.pipeline"):
        kept = lift_scene(scene, guidance, config.superpoints.lift, memory=budget)
    assert isinstance(kept.lifted, LiftStore)
    assert "kept in a temporary file" in caplog.text and "after 1 views" in caplog.text
    same_lifts(list(kept.lifted), plain.lifted)
    in_memory = build_field(scene, guidance, config, space="s", lift_memory=None)
    on_disk = build_field(scene, guidance, config, space="s", lift_memory=0)
    np.testing.assert_array_equal(on_disk.labels, in_memory.labels)
    for x, y in zip(on_disk.features, in_memory.features, strict=True):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(InputError, match="memory"):
        lift_scene(scene, guidance, config.superpoints.lift, memory=-1)


def test_the_cache_is_safetensors_and_reads_into_a_store(inputs, tmp_path):  # noqa: F811
    """The streamed cache file holds exactly the tensors safetensors' own writer would, with the
    metadata; a lift over budget is written from its store and read back into one."""
    scene, guidance = inputs
    config = FieldConfig().superpoints.lift
    views = random_views(1)
    path = tmp_path / "lift.safetensors"
    write_lift(path, "k", views)
    tensors = load_file(str(path))
    assert len(tensors) == 4 * len(views)
    for i, view in enumerate(views):
        for name in ("gaussians", "labels", "depths", "max_weights"):
            expected = getattr(view, name)
            got = tensors[f"v{i}.{name}"]
            assert got.dtype == expected.dtype and torch.equal(got, expected), (i, name)
    with safe_open(str(path), framework="pt") as handle:
        header = json.loads(handle.metadata()["thgs"])
    assert (header["key"], header["views"]) == ("k", 5)
    same_lifts(read_cached_lift(path, "k", 5), views)

    first = lift_scene(scene, guidance, config, cache=tmp_path, memory=0)
    assert isinstance(first.lifted, LiftStore)
    again = lift_scene(scene, guidance, config, cache=tmp_path, memory=0)
    assert isinstance(again.lifted, LiftStore)
    same_lifts(list(again.lifted), list(first.lifted))
    key = lift_key(scene.gaussians, scene.cameras, guidance, config)
    cached = read_cached_lift(lift_cache_path(tmp_path, key), key, len(guidance))
    same_lifts(cached, list(first.lifted))


def test_a_folder_that_cannot_hold_the_file_is_named(tmp_path):
    missing = tmp_path / "gone"
    with pytest.raises(ThgsError, match=rf"temporary file in {missing} .*TMPDIR"):
        LiftStore("cpu", folder=missing)
    store = LiftStore("cpu", folder=tmp_path)
    (tmp_path / "read-only").write_bytes(b"")
    store._file = open(tmp_path / "read-only", "rb")  # writes fail, as on a full disk
    with pytest.raises(ThgsError, match=rf"temporary file in {tmp_path} "):
        store.append(random_views(2)[0])
    assert len(store) == 0
    store.close()
