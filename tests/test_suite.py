"""``thgs suite``: a synthetic suite in the benchmarks' real layouts (2 LERF-OVS scenes, 2 3D-OVS
scenes, 1 synthetic dataset) run in-process and on a local Ray with 2 CPUs — the same report;
every per-scene number equals ``thgs eval`` run by hand; resuming skips what is current (after a
finished run, a deleted eval, a kill in the middle); a broken scene is reported and the others
complete; preprocessing of a scene without language features writes only into the output."""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import run_cli as run
from thgs.cli import entrypoint
from thgs.errors import InputError
from thgs.suite import SuiteConfig, find_suite, plan_scene, run_suite, scene_folder
from thgs.synthetic.layouts import write_3dovs, write_langsplat_lerf, write_opengaussian_scannet

ray = pytest.importorskip("ray")

SCENES = [
    "lerf_ovs/ramen",
    "lerf_ovs/teatime",
    "3dovs/bed",
    "3dovs/sofa",
    "scannet/scene0000_00",
    "synthetic/kitchen",
]


@pytest.fixture(scope="module")
def second_dataset(tmp_path_factory):
    """Another synthetic dataset (seed 1, 3,000 Gaussians, 6 views)."""
    folder = tmp_path_factory.mktemp("synth1") / "scene"
    argv = ["synth", "synth-small", str(folder), "--gaussians", "3000", "--views", "6"]
    entrypoint([*argv, "--seed", "1"])
    return folder


@pytest.fixture(scope="module")
def suite_root(small_dataset, second_dataset, tmp_path_factory):
    """The suite: LangSplat's lerf_ovs/ (one cfg_args naming a path from another machine),
    3D-OVS scenes, OpenGaussian's ScanNet layout, a synthetic dataset; models in
    output/<scene>."""
    root = tmp_path_factory.mktemp("suite") / "root"
    write_langsplat_lerf(small_dataset, root, "teatime", link=True)
    write_langsplat_lerf(
        second_dataset, root, "ramen", source="/home/author/data/lerf_ovs/ramen", link=True
    )
    write_3dovs(small_dataset, root, "bed", link=True)
    write_3dovs(second_dataset, root, "sofa", link=True)
    write_opengaussian_scannet(small_dataset, root, "scene0000_00")
    (root / "synthetic").mkdir()
    (root / "synthetic" / "kitchen").symlink_to(second_dataset, target_is_directory=True)
    return root


def _comparable(path: Path) -> dict:
    document = json.loads(path.read_text())
    del document["timings"], document["run"]
    return document


@pytest.fixture(scope="module")
def in_process(suite_root):
    """The suite run by the CLI, in-process: (out folder, exit code, stdout)."""
    out = suite_root.parent / "out-local"
    try:
        entrypoint(["suite", str(suite_root), "-o", str(out), "--device", "cpu"])
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    return out, code


@pytest.fixture(scope="module")
def on_ray(suite_root, local_ray):
    out = suite_root.parent / "out-ray"
    scenes = find_suite(suite_root)
    return out, run_suite(scenes, out, SuiteConfig(device="cpu"), use_ray=True)


def test_the_suite_is_found_in_its_layouts(suite_root):
    scenes = find_suite(suite_root)
    assert [scene.key for scene in scenes] == SCENES
    by_key = {scene.key: scene for scene in scenes}
    # the model named by cfg_args (a path from another machine, found by its tail)
    assert by_key["lerf_ovs/ramen"].model == suite_root / "output" / "ramen"
    assert by_key["lerf_ovs/ramen"].data == suite_root / "lerf_ovs" / "ramen"
    assert by_key["lerf_ovs/ramen"].protocols == ("lerf", "lerf-langsplat")
    assert by_key["lerf_ovs/ramen"].ground_truth.path("lerf") == (
        suite_root / "lerf_ovs" / "label" / "ramen"
    )
    assert by_key["3dovs/bed"].protocols == ("3dovs",)
    assert by_key["3dovs/bed"].model == suite_root / "output" / "bed"
    scannet = by_key["scannet/scene0000_00"]
    assert scannet.protocols == ("scannet",)
    assert scannet.model == suite_root / "output" / "scene0000_00"
    kitchen = by_key["synthetic/kitchen"]
    assert kitchen.model == kitchen.data  # a synthetic dataset is its own model
    assert kitchen.protocols == (
        "lerf",
        "lerf-langsplat",
        "lerf-opengaussian",
        "3dovs",
        "scannet",
        "hierarchy",
    )
    assert all(scene.problems == () and scene.guidance is not None for scene in scenes)


def test_select_picks_benchmarks_keys_and_names(suite_root):
    keys = [s.key for s in find_suite(suite_root, ["3dovs", "teatime", "synthetic/kitchen"])]
    assert keys == ["lerf_ovs/teatime", "3dovs/bed", "3dovs/sofa", "synthetic/kitchen"]
    with pytest.raises(InputError) as caught:
        find_suite(suite_root, ["replica"])
    assert str(caught.value) == (
        "--select: 'replica' is no benchmark or scene here; benchmarks: 3dovs, lerf_ovs, "
        "scannet, synthetic; scenes: " + ", ".join(SCENES)
    )


@pytest.mark.slow
def test_in_process_and_ray_reports_are_identical(in_process, on_ray):
    out, code = in_process
    assert code == 0
    ray_out, report = on_ray
    assert report.executor == "ray" and not report.failed
    assert report.comparable() == _comparable(out / "report.json")
    assert (out / "report.md").is_file() and (out / "report.png").stat().st_size > 0
    for key in SCENES:
        # the same field, byte for byte, however it ran
        assert (out / key / "field.thgs").read_bytes() == (
            ray_out / key / "field.thgs"
        ).read_bytes()


@pytest.mark.slow
def test_each_number_is_thgs_eval_by_hand(in_process, suite_root, tmp_path, capsys):
    out, _ = in_process
    document = json.loads((out / "report.json").read_text())
    for key, protocol in (("lerf_ovs/teatime", "lerf"), ("3dovs/sofa", "3dovs")):
        data = suite_root / key
        by_hand = tmp_path / f"{key.replace('/', '-')}.json"
        code, _, err = run(
            [
                *("eval", str(data), str(out / key / "field.thgs")),
                *("--protocol", protocol, "--device", "cpu", "-o", str(by_hand)),
            ],
            capsys,
        )
        assert code == 0, err
        expected = {r["protocol"]: r["metrics"] for r in json.loads(by_hand.read_text())["results"]}
        scene = next(s for s in document["scenes"] if f"{s['benchmark']}/{s['name']}" == key)
        for result, metrics in expected.items():
            assert scene["metrics"][result] == metrics
    table = document["tables"]["lerf_ovs"]
    assert table["columns"][:2] == ["mIoU (auto)", "acc (auto)"]
    rows = {row["scene"]: row["values"] for row in table["rows"]}
    scenes = {s["name"]: s["metrics"] for s in document["scenes"]}
    assert rows["teatime"][0] == scenes["teatime"]["lerf"]["miou"]
    assert rows["teatime"][2] == scenes["teatime"]["lerf-paper"]["miou"]
    assert table["mean"][0] == pytest.approx(
        (scenes["teatime"]["lerf"]["miou"] + scenes["ramen"]["lerf"]["miou"]) / 2
    )
    markdown = (out / "report.md").read_text()
    assert f"| teatime | {100 * rows['teatime'][0]:.1f} |" in markdown
    assert "## Times (s): field building by stage, preprocessing, evaluation" in markdown


@pytest.mark.slow
def test_resume_skips_what_is_current(in_process, suite_root, capsys):
    out, _ = in_process
    before = _comparable(out / "report.json")
    code, _, err = run(["suite", str(suite_root), "-o", str(out), "--device", "cpu"], capsys)
    assert code == 0, err
    document = json.loads((out / "report.json").read_text())
    assert all(
        stages == {"preprocess": "not needed", "build": "current", "eval": "current"}
        for stages in document["run"]["stages"].values()
    )
    assert _comparable(out / "report.json") == before
    # build times are those recorded when the fields were built
    assert all(t["build"] for t in document["timings"]["scenes"].values())

    (out / "lerf_ovs" / "ramen" / "eval.json").unlink()
    code, _, err = run(["suite", str(suite_root), "-o", str(out), "--device", "cpu"], capsys)
    assert code == 0, err
    stages = json.loads((out / "report.json").read_text())["run"]["stages"]
    assert {key for key, s in stages.items() if "ran" in s.values()} == {"lerf_ovs/ramen"}
    assert stages["lerf_ovs/ramen"]["build"] == "current"
    assert _comparable(out / "report.json") == before

    # what a change of settings reruns, planned
    scene = find_suite(suite_root, ["ramen"])[0]
    actions = {p.stage: p.action for p in plan_scene(scene, out, SuiteConfig(device="cpu"))}
    assert actions == {"preprocess": "not needed", "build": "current", "eval": "current"}
    paper = SuiteConfig(device="cpu", selection="paper")
    assert [p.action for p in plan_scene(scene, out, paper)][1:] == ["current", "run"]
    changed = SuiteConfig(device="cpu", settings=("merge.min_region_gaussians=30",))
    assert [p.action for p in plan_scene(scene, out, changed)][1:] == ["run", "run"]

    # a field damaged after its stamp was written is built again, not trusted
    field = out / "lerf_ovs" / "ramen" / "field.thgs"
    whole = field.read_bytes()
    field.write_bytes(whole[: len(whole) // 2])
    plans = plan_scene(scene, out, SuiteConfig(device="cpu"))
    assert (plans[1].action, plans[1].reason) == (
        "run",
        "its output changed since it was written (damaged?)",
    )
    code, _, err = run(["suite", str(suite_root), "-o", str(out), "--device", "cpu"], capsys)
    assert code == 0, err
    stages = json.loads((out / "report.json").read_text())["run"]["stages"]["lerf_ovs/ramen"]
    assert (stages["build"], stages["eval"]) == ("ran", "ran")
    assert field.read_bytes() == whole and _comparable(out / "report.json") == before


@pytest.mark.slow
def test_dry_run_prints_the_plan_and_writes_nothing(in_process, suite_root, tmp_path, capsys):
    out, _ = in_process
    code, printed, err = run(["suite", str(suite_root), "-o", str(out), "--dry-run"], capsys)
    assert code == 0, err
    assert printed.count("build current (output current); eval current") == len(SCENES)
    fresh = tmp_path / "fresh"
    code, printed, err = run(["suite", str(suite_root), "-o", str(fresh), "--dry-run"], capsys)
    assert code == 0, err
    assert printed.count("build run (no output yet); eval run") == len(SCENES)
    assert not fresh.exists()


@pytest.mark.slow
def test_a_kill_mid_suite_resumes_past_the_finished_scenes(
    small_dataset, tmp_path, monkeypatch, capsys
):
    root = tmp_path / "root"
    for name in ("a", "b", "c"):
        write_3dovs(small_dataset, root, name, link=True)
    out = tmp_path / "out"
    import thgs.pipeline

    real = thgs.pipeline.build_field
    calls = []

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(thgs.pipeline, "build_field", interrupted)
    code, _, err = run(["suite", str(root), "-o", str(out), "--device", "cpu"], capsys)
    assert code == 130 and "interrupted" in err
    assert (out / "3dovs" / "b" / "eval.json").is_file()
    assert not (out / "3dovs" / "c" / "field.thgs").exists()
    assert not (out / "report.json").exists()
    assert [p.name for p in (out / "3dovs" / "c").iterdir()] == []  # nothing half-written

    monkeypatch.setattr(thgs.pipeline, "build_field", real)
    code, _, err = run(["suite", str(root), "-o", str(out), "--device", "cpu"], capsys)
    assert code == 0, err
    stages = json.loads((out / "report.json").read_text())["run"]["stages"]
    assert stages["3dovs/a"]["build"] == stages["3dovs/b"]["build"] == "current"
    assert stages["3dovs/c"] == {"preprocess": "not needed", "build": "ran", "eval": "ran"}


@pytest.mark.slow
def test_broken_and_incomplete_scenes_are_reported_and_the_rest_complete(
    small_dataset, tmp_path, capsys
):
    root = tmp_path / "root"
    write_3dovs(small_dataset, root, "good", link=True)
    write_3dovs(small_dataset, root, "broken")  # a copy, to break
    ply = root / "output" / "broken" / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    ply.write_bytes(ply.read_bytes()[:2000])
    write_langsplat_lerf(small_dataset, root, "nolabels", link=True)
    (root / "lerf_ovs" / "label" / "nolabels").unlink()
    out = tmp_path / "out"
    code, _, err = run(["suite", str(root), "-o", str(out), "--device", "cpu"], capsys)
    assert code == 1
    assert "2 of 3 scenes failed: lerf_ovs/nolabels, 3dovs/broken" in " ".join(err.split())
    document = json.loads((out / "report.json").read_text())
    failed = {item["scene"]: item["error"] for item in document["failed"]}
    assert failed["lerf_ovs/nolabels"] == (
        "missing its ground truth: LERF-OVS labels (label/frame_*.json, or LangSplat's "
        "../label/<scene>/frame_*.json)"
    )
    assert failed["3dovs/broken"].startswith(str(ply))
    assert "Traceback" in (out / "3dovs" / "broken" / "error.log").read_text()
    good = next(s for s in document["scenes"] if s["name"] == "good")
    assert good["ok"] and good["metrics"]["3dovs"]["miou"] > 0.5
    assert "## Failed (2 of 3)" in (out / "report.md").read_text()


def test_a_root_without_scenes_is_an_error(tmp_path, capsys):
    (tmp_path / "empty" / "photos").mkdir(parents=True)
    code, printed, err = run(["suite", str(tmp_path / "empty"), "-o", str(tmp_path / "o")], capsys)
    assert code == 2 and printed == ""
    message = " ".join(err.split())
    assert message.startswith(f"error: {tmp_path / 'empty'}: holds no recognisable scene")
    assert "lerf_ovs/label/<scene>/frame_*.json" in message and "synthetic.json" in message


def test_two_models_naming_one_scene_are_a_problem(small_dataset, tmp_path):
    root = tmp_path / "root"
    data = write_langsplat_lerf(small_dataset, root, "teatime", link=True)
    shutil.copytree(root / "output" / "teatime", root / "runs" / "again", symlinks=True)
    (scene,) = find_suite(root)
    assert scene.model is None
    assert scene.problems == (
        f"2 model folders name this data folder in their cfg_args: {root / 'output' / 'teatime'}"
        f", {root / 'runs' / 'again'}; keep one under the root",
    )
    assert data == scene.data


def test_scannet_scenes_are_found_by_their_label_ply(small_dataset, tmp_path):
    """OpenGaussian's ScanNet folder: <scene>_vh_clean_2.labels.ply beside the cameras."""
    data = tmp_path / "root" / "scannet" / "scene0000_00"
    data.mkdir(parents=True)
    for name in ("images", "sparse", "language_features"):
        (data / name).symlink_to(small_dataset / name, target_is_directory=True)
    labels = small_dataset / "scannet" / "synthetic_vh_clean_2.labels.ply"
    (data / "scene0000_00_vh_clean_2.labels.ply").symlink_to(labels)
    write_model = tmp_path / "root" / "output" / "scene0000_00"
    write_model.mkdir(parents=True)
    (write_model / "point_cloud").symlink_to(small_dataset / "point_cloud")
    (scene,) = find_suite(tmp_path / "root")
    assert (scene.key, scene.protocols, scene.problems) == (
        "scannet/scene0000_00",
        ("scannet",),
        (),
    )
    assert scene.model == write_model


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    pytest.importorskip("transformers")
    import tiny_models

    root = tmp_path_factory.mktemp("models")
    return {"sam": tiny_models.tiny_sam(root / "sam"), "clip": tiny_models.tiny_clip(root / "clip")}


@pytest.mark.slow
@pytest.mark.parametrize("executor", ["in-process", pytest.param("ray", marks=pytest.mark.ray)])
def test_a_scene_without_features_is_preprocessed_into_the_output(
    small_dataset, tmp_path, models, executor, request, monkeypatch
):
    from thgs.guidance.preprocess import (
        MaskGeneratorConfig,
        PreprocessConfig,
        image_jobs,
        load_preprocess_models,
        preprocess_images,
    )
    from thgs.scene import load_cameras

    root = tmp_path / "root"
    data = write_3dovs(small_dataset, root, "bed", link=True)
    (data / "language_features").unlink()
    permissive = PreprocessConfig(
        masks=MaskGeneratorConfig(
            points_per_side=4, pred_iou_threshold=0.0, stability_threshold=0.0, crop_layers=0
        )
    )
    config = SuiteConfig(
        device="cpu", sam=str(models["sam"]), clip=str(models["clip"]), preprocess=permissive
    )
    (scene,) = find_suite(root)
    assert scene.guidance is None and scene.images == data / "images"
    assert [p.action for p in plan_scene(scene, tmp_path / "out", config)] == ["run"] * 3
    # CLIP's sums depend on torch's thread count in the last bit; Ray's actors run on one thread
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    request.addfinalizer(lambda: torch.set_num_threads(threads))
    use_ray = executor == "ray"
    if use_ray:
        request.getfixturevalue("local_ray")
    report = run_suite([scene], tmp_path / "out", config, use_ray=use_ray)
    assert report.executor == executor
    assert not report.failed, report.failed
    assert report.scenes[0].stages == dict.fromkeys(("preprocess", "build", "eval"), "ran")
    assert not (data / "language_features").exists()  # the dataset is never written into

    # the same features as preprocessing by hand
    by_hand = tmp_path / "by-hand"
    segmenter, encoder = load_preprocess_models(str(models["sam"]), str(models["clip"]))
    jobs = image_jobs(data / "images", cameras=load_cameras(data)[0])
    preprocess_images(jobs, by_hand, segmenter, encoder, permissive)
    made = scene_folder(tmp_path / "out", scene) / "language_features"
    assert sorted(os.listdir(made)) == sorted(os.listdir(by_hand))
    for job in jobs:
        for suffix in ("_s.npy", "_f.npy"):
            np.testing.assert_array_equal(
                np.load(made / f"{job.stem}{suffix}"), np.load(by_hand / f"{job.stem}{suffix}")
            )
    again = run_suite([scene], tmp_path / "out", config, use_ray=use_ray)
    assert again.scenes[0].stages == dict.fromkeys(("preprocess", "build", "eval"), "current")


@pytest.mark.slow
def test_an_unreadable_image_on_ray_fails_its_scene_only(
    small_dataset, tmp_path, models, local_ray
):
    from thgs.guidance.preprocess import MaskGeneratorConfig, PreprocessConfig

    root = tmp_path / "root"
    for name in ("bed", "sofa"):
        data = write_3dovs(small_dataset, root, name)
        shutil.rmtree(data / "language_features")
    broken = sorted((root / "3dovs" / "sofa" / "images").iterdir())[1]
    broken.write_bytes(b"not an image")
    config = SuiteConfig(
        device="cpu",
        sam=str(models["sam"]),
        clip=str(models["clip"]),
        preprocess=PreprocessConfig(
            masks=MaskGeneratorConfig(
                points_per_side=4, pred_iou_threshold=0.0, stability_threshold=0.0, crop_layers=0
            )
        ),
    )
    report = run_suite(find_suite(root), tmp_path / "out", config, use_ray=True)
    results = {scene.name: scene for scene in report.scenes}
    assert results["bed"].ok and results["bed"].stages["preprocess"] == "ran"
    assert not results["sofa"].ok and results["sofa"].stages == {
        "preprocess": "failed", "build": "not run", "eval": "not run"
    }  # fmt: skip
    assert str(broken) in results["sofa"].error
    assert not (tmp_path / "out" / "3dovs" / "sofa" / "field.thgs").exists()


def test_a_ray_address_that_does_not_answer_is_an_error(suite_root, tmp_path, capsys):
    import socket

    with socket.socket() as probe:  # a port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    argv = ["suite", str(suite_root), "-o", str(tmp_path / "o"), "--ray", f"127.0.0.1:{port}"]
    code, printed, err = run(argv, capsys)
    assert code == 2 and printed == ""
    assert " ".join(err.split()).startswith(
        f"error: 127.0.0.1:{port}: no Ray cluster answers there"
    )
    assert not (tmp_path / "o" / "report.json").exists()


def test_a_bare_ray_flag_means_a_local_ray():
    from thgs.cli.suite import bare_ray_flag

    assert bare_ray_flag(["suite", "R", "--ray"]) == ["suite", "R", "--ray", "local"]
    assert bare_ray_flag(["suite", "R", "--ray", "-o", "O"]) == [
        *("suite", "R", "--ray", "local", "-o", "O")
    ]
    assert bare_ray_flag(["suite", "R", "--ray", "h:1"]) == ["suite", "R", "--ray", "h:1"]
    assert bare_ray_flag(["build", "S", "--ray"]) == ["build", "S", "--ray", "local"]
    assert bare_ray_flag(["query", "--ray"]) == ["query", "--ray"]


def test_what_the_walk_cannot_use_is_named(second_dataset, tmp_path, caplog, capsys):
    """A link to itself under the root is left out with a warning, LERF-OVS labels whose scene
    folder is a file are warned of (the mean covers one scene fewer), a root that is a file or
    the output folder itself is an error naming it."""
    root = tmp_path / "root"
    (root / "output").mkdir(parents=True)
    (root / "output" / "loop").symlink_to(root / "output" / "loop")
    (root / "lerf_ovs" / "label" / "kitchen").mkdir(parents=True)
    (root / "lerf_ovs" / "label" / "kitchen" / "frame_00001.json").write_text("{}")
    (root / "lerf_ovs" / "kitchen").write_text("not a scene")
    (root / "synthetic").mkdir()
    (root / "synthetic" / "kitchen").symlink_to(second_dataset, target_is_directory=True)
    with caplog.at_level(logging.WARNING, logger="thgs.suite.discover"):
        (scene,) = find_suite(root)
    assert scene.key == "synthetic/kitchen"
    assert f"{root / 'output' / 'loop'}: not searched for scenes" in caplog.text
    assert (
        f"{root / 'lerf_ovs' / 'label' / 'kitchen'} has LERF-OVS labels but its scene folder "
        f"{root / 'lerf_ovs' / 'kitchen'} is not a folder: not run" in caplog.text
    )
    code, _, err = run(["suite", str(root / "lerf_ovs" / "kitchen"), "-o", "x"], capsys)
    assert code == 2 and "is a file; the suite root is the folder" in " ".join(err.split())
    code, _, err = run(["suite", str(root), "-o", str(root)], capsys)
    assert code == 2 and "is also the output folder (-o)" in " ".join(err.split())
