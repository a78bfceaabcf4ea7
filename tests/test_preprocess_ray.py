"""Preprocessing through Ray Data (:func:`preprocess_with_ray`) on a local Ray with the small random
models: the same files as in-process, byte for byte; resuming; an unreadable image named as in
process; Ray not initialised."""

from __future__ import annotations

import contextlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from thgs.errors import InputError, ThgsError

ray = pytest.importorskip("ray")
pytest.importorskip("ray.data")
pytest.importorskip("transformers")

import tiny_models  # noqa: E402  (needs transformers)
from thgs.cluster import connect_ray  # noqa: E402
from thgs.guidance.preprocess import (  # noqa: E402
    MANIFEST_FILE,
    MaskGeneratorConfig,
    PreprocessConfig,
    PreprocessTarget,
    image_jobs,
    load_preprocess_models,
    preprocess_images,
    preprocess_with_ray,
)

PERMISSIVE = PreprocessConfig(
    masks=MaskGeneratorConfig(
        points_per_side=4, pred_iou_threshold=0.0, stability_threshold=0.0, min_region_area=20
    ),
    clip_batch_size=5,
)


@contextlib.contextmanager
def one_thread():
    """Torch on one thread, as each Ray actor (1 CPU) runs: on a CPU, features depend on the
    thread count in their last bit (and numba's parallel loops elsewhere in the test session
    raise this process's OpenMP thread count)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, str]:
    root = tmp_path_factory.mktemp("models")
    return {
        "sam": str(tiny_models.tiny_sam(root / "sam")),
        "clip": str(tiny_models.tiny_clip(root / "clip")),
    }


def _scene(root: Path, name: str, count: int, seed: int) -> Path:
    """A scene folder with ``count`` random 56 × 40 images in ``images/``."""
    folder = root / name / "images"
    folder.mkdir(parents=True)
    generator = np.random.default_rng(seed)
    for i in range(count):
        pixels = generator.integers(0, 256, (40, 56, 3), dtype=np.uint8)
        Image.fromarray(pixels).save(folder / f"frame_{i:03d}.png")
    return folder


def _targets(root: Path, folder: str) -> list[PreprocessTarget]:
    return [
        PreprocessTarget(tuple(image_jobs(root / "a" / "images")), root / "a" / folder),
        PreprocessTarget(tuple(image_jobs(root / "b" / "images")), root / "b" / folder),
    ]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory, models) -> Path:
    """Two scenes (3 and 2 images) and their in-process results in ``<scene>/reference``."""
    root = tmp_path_factory.mktemp("scenes")
    _scene(root, "a", 3, seed=0)
    _scene(root, "b", 2, seed=1)
    segmenter, encoder = load_preprocess_models(models["sam"], models["clip"])
    with one_thread():
        for target in _targets(root, "reference"):
            preprocess_images(target.jobs, target.output, segmenter, encoder, PERMISSIVE)
    return root


def _assert_same_files(folder: Path, reference: Path) -> None:
    assert sorted(path.name for path in folder.iterdir()) == sorted(
        path.name for path in reference.iterdir()
    )
    for path in reference.iterdir():
        assert (folder / path.name).read_bytes() == path.read_bytes(), path


def test_ray_not_initialised_is_a_clear_error(tmp_path, models):
    # not marked ray: the session's Ray, if up, is hidden (conftest.py)
    assert not ray.is_initialized()
    with pytest.raises(
        ThgsError, match=r"Ray is not initialised in this process: .*connect_ray\(\)"
    ):
        preprocess_with_ray([], sam=models["sam"], clip=models["clip"])


@pytest.mark.slow
def test_ray_writes_the_in_process_files_byte_for_byte(scenes, models, local_ray):
    # the session's Ray (conftest.py), started by connect_ray: a local one with 2 CPUs
    assert (local_ray.address, local_ray.started, local_ray.cpus) == ("local", True, 2.0)
    seen = []
    summaries = preprocess_with_ray(
        _targets(scenes, "ray"),
        sam=models["sam"],
        clip=models["clip"],
        config=PERMISSIVE,
        actors=2,
        on_image=lambda stem, seconds: seen.append((stem, seconds)),
    )
    assert [list(summary.done) for summary in summaries] == [
        ["frame_000", "frame_001", "frame_002"],
        ["frame_000", "frame_001"],
    ]
    assert sorted(stem for stem, _ in seen) == sorted(
        ["frame_000"] * 2 + ["frame_001"] * 2 + ["frame_002"]
    )
    assert all(seconds > 0 for _, seconds in seen)
    for name in ("a", "b"):
        _assert_same_files(scenes / name / "ray", scenes / name / "reference")
    # the summaries count the masks in the files
    for name, summary in zip("ab", summaries):
        counts = np.zeros(4, dtype=int)
        for stem in summary.done:
            segments = np.load(scenes / name / "ray" / f"{stem}_s.npy")
            counts += [len(np.unique(level[level >= 0])) for level in segments]
        assert summary.masks == tuple(counts) and sum(counts) > 0 and summary.skipped == []


@pytest.mark.slow
def test_ray_resumes_and_skips_finished_views(scenes, models, local_ray):
    targets = _targets(scenes, "resumed")
    # scene a's first two views finished in an earlier, in-process run
    segmenter, encoder = load_preprocess_models(models["sam"], models["clip"])
    with one_thread():
        preprocess_images(targets[0].jobs[:2], targets[0].output, segmenter, encoder, PERMISSIVE)
    seen = []
    summaries = preprocess_with_ray(
        targets,
        sam=models["sam"],
        clip=models["clip"],
        config=PERMISSIVE,
        on_image=lambda stem, seconds: seen.append((stem, seconds)),
    )
    assert summaries[0].skipped == ["frame_000", "frame_001"]
    assert list(summaries[0].done) == ["frame_002"]
    assert list(summaries[1].done) == ["frame_000", "frame_001"] and summaries[1].skipped == []
    assert seen[:2] == [("frame_000", None), ("frame_001", None)]
    for name in ("a", "b"):
        _assert_same_files(scenes / name / "resumed", scenes / name / "reference")
    # all done: nothing runs, everything is skipped
    again = preprocess_with_ray(targets, sam=models["sam"], clip=models["clip"], config=PERMISSIVE)
    assert [summary.done for summary in again] == [{}, {}]
    assert [len(summary.skipped) for summary in again] == [3, 2]


@pytest.mark.slow
def test_an_unreadable_image_is_named_and_the_others_are_done(tmp_path, scenes, models, local_ray):
    for name in ("a", "b"):
        shutil.copytree(scenes / name / "images", tmp_path / name / "images")
    broken = tmp_path / "b" / "images" / "frame_000.png"
    broken.write_bytes(b"not a png")
    with pytest.raises(InputError, match="not a readable image") as caught:
        preprocess_with_ray(
            _targets(tmp_path, "out"), sam=models["sam"], clip=models["clip"], config=PERMISSIVE
        )
    # the error as the worker raised it: its type, file and message, not Ray's wrapping
    assert type(caught.value) is InputError and caught.value.source == str(broken)
    assert "ray" not in str(caught.value).lower()
    _assert_same_files(tmp_path / "a" / "out", scenes / "a" / "reference")
    assert sorted(path.name for path in (tmp_path / "b" / "out").iterdir()) == [
        "embedding.json",
        "frame_001_f.npy",
        "frame_001_s.npy",
        MANIFEST_FILE,
    ]


@pytest.mark.slow
def test_other_settings_are_refused_before_any_work(scenes, models, local_ray):
    other = PreprocessConfig(masks=MaskGeneratorConfig(points_per_side=8))
    with pytest.raises(InputError, match=r"preprocess\.json: this folder was preprocessed with"):
        preprocess_with_ray(
            _targets(scenes, "reference"), sam=models["sam"], clip=models["clip"], config=other
        )
    manifest = json.loads((scenes / "a" / "reference" / MANIFEST_FILE).read_text())
    assert manifest["config"]["masks"]["points_per_side"] == 4


def test_bad_arguments_are_named(scenes, models, local_ray):
    targets = _targets(scenes, "reference")
    with pytest.raises(InputError, match=r"is the output of targets 0 and 1"):
        preprocess_with_ray([targets[0], targets[0]], sam=models["sam"], clip=models["clip"])
    with pytest.raises(InputError, match=r"dtype: must be one of float32, bfloat16, float16"):
        preprocess_with_ray(targets, sam=models["sam"], clip=models["clip"], dtype="int8")
    with pytest.raises(InputError, match=r"gpus_per_actor: is 0; device 'cuda' needs a GPU"):
        preprocess_with_ray(targets, sam=models["sam"], clip=models["clip"], device="cuda")
    with pytest.raises(InputError, match=r"actors: must be at least 1, not 0"):
        preprocess_with_ray(targets, sam=models["sam"], clip=models["clip"], actors=0)


def test_a_missing_model_is_named_from_the_worker(tmp_path, scenes, models, local_ray):
    with pytest.raises(InputError, match="not a Hugging Face model folder") as caught:
        preprocess_with_ray(
            _targets(scenes, "reference"), sam=models["sam"], clip=str(tmp_path), config=PERMISSIVE
        )
    assert caught.value.source == str(tmp_path) and "Traceback" not in str(caught.value)


def test_connect_ray_uses_a_ray_already_running(local_ray):
    connection = connect_ray(None)
    assert (connection.address, connection.started) == ("existing", False)
    connection.shutdown()
    assert ray.is_initialized()
