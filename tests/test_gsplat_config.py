"""gsplat result folders with their settings file (``cfg.yml`` of simple_trainer, ``cfg.json`` of
simple_trainer_2dgs) load with no ``--source``: the COLMAP scene of ``data_dir`` is found as
cfg_args's ``source_path`` is, and a checkpoint in gsplat's normalised world frame is refused."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from conftest import random_cameras, random_gaussians
from test_gsplat_checkpoint import assert_same, save, splats_of
from thgs import InputError, load_scene
from thgs.provenance import SceneRecord
from thgs.scene import write_colmap
from thgs.scene.gsplat_config import find_gsplat_source, read_gsplat_config


def cfg_yml(data_dir, *, factor=4, normalize="false", result_dir="results/garden", extra=""):
    """A cfg.yml as simple_trainer's ``yaml.dump(vars(cfg))`` writes it: keys sorted, nested
    settings as Python objects and tuples (which plain safe YAML refuses)."""
    normalize_line = "" if normalize is None else f"normalize_world_space: {normalize}\n"
    return (
        "antialiased: false\n"
        "batch_size: 1\n"
        "camera_model: pinhole\n"
        f"data_dir: {data_dir}\n"
        f"data_factor: {factor}\n"
        f"{extra}"
        "eval_steps: !!python/tuple\n- 7000\n- 30000\n"
        "max_steps: 30000\n"
        f"{normalize_line}"
        f"result_dir: {result_dir}\n"
        "sh_degree: 3\n"
        "strategy: !!python/object:gsplat.strategy.default.DefaultStrategy\n"
        "  absgrad: false\n"
        "  prune_opa: 0.005\n"
        "  refine_start_iter: 500\n"
        "test_every: 8\n"
    )


@pytest.fixture
def examples(tmp_path, monkeypatch):
    """gsplat's examples/ folder after ``simple_trainer.py default --data_dir data/garden
    --result_dir results/garden``, with the working folder elsewhere."""
    root = tmp_path / "gsplat" / "examples"
    cameras = random_cameras(4, centred=True, seed=3)
    write_colmap(root / "data" / "garden" / "sparse" / "0", cameras)
    gaussians = random_gaussians(40, sh_degree=1, normals=False, seed=8)
    result = root / "results" / "garden"
    save(result / "ckpts" / "ckpt_29999_rank0.pt", splats_of(gaussians))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    return root, result, cameras, gaussians


def test_cfg_yml_is_read_safely(tmp_path):
    path = tmp_path / "cfg.yml"
    path.write_text(cfg_yml("data/garden"))
    with pytest.raises(yaml.YAMLError):  # the tags a plain safe load refuses
        yaml.safe_load(path.read_text())
    settings = read_gsplat_config(path)
    assert settings["data_dir"] == "data/garden" and settings["data_factor"] == 4
    assert settings["normalize_world_space"] is False and settings["sh_degree"] == 3
    assert settings["strategy"] is None and settings["eval_steps"] is None


def test_result_folder_loads_with_no_source(examples):
    root, result, cameras, gaussians = examples
    data = root / "data" / "garden"
    (result / "cfg.yml").write_text(cfg_yml("data/garden"))
    scene = load_scene(result)
    assert scene.source == data and scene.cameras_path == data / "sparse" / "0"
    assert_same(scene.gaussians, gaussians)
    np.testing.assert_allclose(scene.cameras.viewmats.numpy(), cameras.viewmats.numpy(), atol=1e-9)
    np.testing.assert_allclose(scene.cameras.Ks.numpy(), cameras.Ks.numpy(), atol=1e-9)
    assert scene.model_source.key == "data_dir" and scene.model_source.images == "images_4"
    assert f"found for 'data/garden', named by {result / 'cfg.yml'}" in scene.found[1]
    assert "gsplat trained on 'images_4' (data_factor 4)" in scene.found[2]
    assert "--images images_4 --scale 0.25" in scene.found[2]
    # one checkpoint file inside ckpts/ finds the same scene
    single = load_scene(result / "ckpts" / "ckpt_29999_rank0.pt")
    assert single.source == data and len(single.cameras) == 4
    # data_dir written on another machine: found by its tail
    (result / "cfg.yml").write_text(
        cfg_yml("/home/someone/gsplat/examples/data/garden", factor=1, result_dir="/x/y")
    )
    scene = load_scene(result)
    assert scene.source == data and len(scene.found) > 2
    assert not any("data_factor" in line for line in scene.found)


def test_2dgs_result_folder_reads_cfg_json(tmp_path, monkeypatch):
    cameras = random_cameras(3, centred=True, seed=4)
    write_colmap(tmp_path / "data" / "garden" / "sparse", cameras)  # sparse/ without 0/
    surfels = random_gaussians(30, kind="2dgs", sh_degree=1, normals=False, seed=9)
    result = tmp_path / "results" / "garden_2dgs"
    save(result / "ckpts" / "ckpt_29999.pt", splats_of(surfels, third_scale=-2.0))
    settings = {"data_dir": "data/garden", "data_factor": 1, "normalize_world_space": False}
    (result / "cfg.json").write_text(json.dumps({**settings, "result_dir": "results/garden_2dgs"}))
    monkeypatch.chdir(tmp_path)
    scene = load_scene(result)
    assert scene.gaussians.kind == "2dgs" and scene.source == tmp_path / "data" / "garden"
    np.testing.assert_allclose(scene.cameras.viewmats.numpy(), cameras.viewmats.numpy(), atol=1e-9)


@pytest.mark.parametrize("normalize", ["true", None])
def test_normalised_world_is_refused_unless_source_decides(examples, normalize):
    root, result, _, _ = examples
    config = result / "cfg.yml"
    config.write_text(cfg_yml("data/garden", normalize=normalize))
    with pytest.raises(InputError) as error:
        load_scene(result)
    message = str(error.value)
    assert message.startswith(f"{config}: normalize_world_space is True")
    assert "--no-normalize-world-space" in message and "--source" in message
    # cameras given explicitly are the user's choice; the record is still reported
    scene = load_scene(result, source=root / "data" / "garden")
    assert len(scene.cameras) == 4 and scene.model_source is None
    assert any("records normalize_world_space: True" in line for line in scene.found)


def test_thgs_info_reads_the_result_folder_alone(examples, capsys):
    from thgs.cli import entrypoint

    _, result, _, _ = examples
    (result / "cfg.yml").write_text(cfg_yml("data/garden", factor=1))
    entrypoint(["info", str(result), "--json"])
    document = json.loads(capsys.readouterr().out)
    assert document["count"] == 40 and document["kind"] == "3dgs"
    assert document["cameras"]["count"] == 4


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (cfg_yml("data/garden", extra="data_type: ncore\n"), "data_type is 'ncore'"),
        (cfg_yml("''"), "data_dir must be a folder name, got ''"),
        (cfg_yml("data/garden", factor=0), "data_factor must be a whole number ≥ 1, got 0"),
        ("data_dir: [unclosed\n", "not valid YML"),
        ("- a list\n", "expected the trainer's settings"),
    ],
)
def test_bad_settings_name_the_file(examples, text, message):
    _, result, _, _ = examples
    (result / "cfg.yml").write_text(text)
    with pytest.raises(InputError, match=message) as error:
        find_gsplat_source(result)
    assert str(error.value).startswith(str(result / "cfg.yml"))


def test_cfg_yml_and_cfg_json_must_agree(examples):
    root, result, _, _ = examples
    (result / "cfg.yml").write_text(cfg_yml("data/garden", factor=1))
    same = {"data_dir": "data/garden", "data_factor": 1, "normalize_world_space": False}
    (result / "cfg.json").write_text(json.dumps(same))
    assert find_gsplat_source(result).folder == root / "data" / "garden"
    (result / "cfg.json").write_text(json.dumps({**same, "data_dir": "data/bicycle"}))
    with pytest.raises(InputError) as error:
        find_gsplat_source(result)
    message = str(error.value)
    assert message.startswith(f"{result / 'cfg.yml'}: and {result / 'cfg.json'}")
    assert "differ in data_dir; --source decides" in message


def test_missing_scene_is_said_and_build_names_source(examples, capsys):
    from thgs.cli import entrypoint

    _, result, _, _ = examples
    (result / "cfg.yml").write_text(cfg_yml("data/kitchen", factor=1))
    scene = load_scene(result)
    assert scene.cameras is None and scene.model_source.folder is None
    assert "names the source 'data/kitchen', which is not here" in scene.found[1]
    assert scene.found[-1].startswith("no cameras: its source is not here (pass --source")
    with pytest.raises(SystemExit):
        entrypoint(["build", str(result), "-o", str(result / "a.thgs")])
    err = capsys.readouterr().err
    assert "data/kitchen" in err and "--source" in err


@pytest.mark.slow
def test_build_from_a_gsplat_result_folder_with_no_flags(small_dataset, tmp_path, monkeypatch):
    """The synthetic dataset as gsplat's examples hold a trained scene::

    examples/data/garden/{images, sparse/0, language_features}
    examples/results/garden/{cfg.json or cfg.yml, ckpts/ckpt_29999[_rank0].pt}
    """
    from thgs import read_ply
    from thgs.cli import entrypoint
    from thgs.field import load_field

    root = tmp_path / "examples"
    data = root / "data" / "garden"
    data.mkdir(parents=True)
    for name in ("images", "sparse", "language_features"):
        (data / name).symlink_to(small_dataset / name, target_is_directory=True)
    gaussians = read_ply(small_dataset / "point_cloud" / "iteration_30000" / "point_cloud.ply")
    result = root / "results" / "garden"
    settings = {"data_dir": "data/garden", "data_factor": 1, "normalize_world_space": False}
    if gaussians.kind == "2dgs":  # simple_trainer_2dgs: cfg.json, ckpt_<step>.pt
        save(result / "ckpts" / "ckpt_29999.pt", splats_of(gaussians, third_scale=-4.0))
        (result / "cfg.json").write_text(json.dumps({**settings, "result_dir": "results/garden"}))
    else:
        save(result / "ckpts" / "ckpt_29999_rank0.pt", splats_of(gaussians))
        (result / "cfg.yml").write_text(cfg_yml("data/garden", factor=1))
    monkeypatch.chdir(root)
    try:
        entrypoint(["build", "results/garden", "-o", "garden.thgs"])
    except SystemExit as exc:  # pragma: no cover - the command returns normally
        assert not exc.code
    field = load_field("garden.thgs")
    assert field.provenance.scene == SceneRecord("results/garden", source="data/garden")
    assert field.labels.shape == (len(gaussians), 4) and min(field.region_counts) > 0
