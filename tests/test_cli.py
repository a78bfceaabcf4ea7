"""The thgs command line, through its entry point and as an installed console script."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO
from conftest import run_cli as run
from thgs.errors import InputError


def test_info_on_the_real_sample(shared_data, capsys):
    code, out, _ = run(["info", str(shared_data / "ply_3dgs_train1000.ply")], capsys)
    assert code == 0
    assert "1,000 (3DGS, SH degree 3, normals stored)" in out
    assert "cameras" in out and "none" in out


def test_info_json_with_cameras(shared_data, capsys):
    code, out, _ = run(
        [
            "info",
            str(shared_data / "ply_3dgs_train1000.ply"),
            "--source",
            str(shared_data / "colmap_small"),
            "--scale",
            "0.25",
            "--json",
        ],
        capsys,
    )
    assert code == 0
    document = json.loads(out)
    assert (document["count"], document["kind"], document["sh_degree"]) == (1000, "3dgs", 3)
    assert document["cameras"]["count"] == 23
    assert document["cameras"]["width_range"] == [250, 250]
    assert document["cameras"]["height_range"] == [164, 166]


def test_bad_input_is_one_line_and_status_2(tmp_path, capsys):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\n")
    code, out, err = run(["info", str(bad)], capsys)
    assert code == 2 and out == ""
    assert err.startswith("error: ") and str(bad) in err.replace("\n", "")
    assert "Traceback" not in err


def test_help_lists_info(capsys):
    code, out, _ = run(["--help"], capsys)
    assert code == 0 and "info" in out


@pytest.mark.slow
def test_console_script_on_bundled_sample():
    """The README's main job: the installed `thgs` on the sample shipped in examples/."""
    executable = shutil.which("thgs", path=str(Path(sys.executable).parent))
    if executable is None:
        pytest.skip("the thgs console script is not installed next to this Python")
    result = subprocess.run(
        [executable, "info", "examples/data/train-1000.ply"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert "1,000 (3DGS, SH degree 3" in result.stdout


@pytest.mark.slow
def test_build_writes_a_field_of_the_scene(small_dataset, tmp_path, capsys):
    from thgs import load_scene
    from thgs.field import load_field, scene_fingerprint

    out = tmp_path / "scene.thgs"
    code, stdout, err = run(["build", str(small_dataset), "-o", str(out)], capsys)
    assert code == 0, err
    field = load_field(out)
    assert field.fingerprint == scene_fingerprint(load_scene(small_dataset).gaussians)
    assert field.space == "sentence-transformers/all-MiniLM-L6-v2"
    assert field.config["features"]["mode"] == "shares"
    assert f"wrote {out}" in stdout.replace("\n", "") and "regions" in stdout
    counts = field.region_counts
    assert counts[0] >= counts[1] >= counts[2] >= counts[3] >= 1

    three = tmp_path / "3dovs.thgs"
    code, _, err = run(
        ["build", str(small_dataset), "-o", str(three), "--preset", "3dovs", "--reference"],
        capsys,
    )
    assert code == 0, err
    config = load_field(three).config
    assert config["features"]["mode"] == "centres"
    assert config["merge"]["min_region_gaussians"] == 100
    assert config["superpoints"]["reweight"]["mode"] == "absolute"
    assert config["features"]["visibility_power"] == 0 and not config["repeats"]["enabled"]
    assert field.config["repeats"]["enabled"]

    pieces = tmp_path / "pieces.thgs"
    code, _, err = run(
        ["build", str(small_dataset), "-o", str(pieces), "--no-repeated-parts"], capsys
    )
    assert code == 0, err
    config = load_field(pieces).config
    assert not config["repeats"]["enabled"] and config["features"]["visibility_power"] == 2


@pytest.mark.slow
def test_build_gives_the_same_bytes_with_any_number_of_threads(small_dataset, tmp_path, capsys):
    # blocks of 1,000 Gaussians: the partition's solver processes run side by side
    blocks = ["--set", "superpoints.partition.block_size=1000"]
    fields = []
    for threads in (1, 2, 8):  # each in a fresh process
        out = tmp_path / f"threads{threads}.thgs"
        command = "import sys; from thgs.cli import entrypoint; sys.exit(entrypoint())"
        argv = ["build", str(small_dataset), "-o", str(out), "--threads", str(threads), *blocks]
        subprocess.run(
            [sys.executable, "-c", command, *argv],
            check=True,
            capture_output=True,
            env={**os.environ, "NUMBA_NUM_THREADS": "8"},
        )
        fields.append(out.read_bytes())
    assert fields[0] == fields[1] == fields[2]
    code, _, err = run(
        ["build", str(small_dataset), "-o", str(tmp_path / "x.thgs"), "--threads", "0"], capsys
    )
    assert code == 2 and "--threads" in err and "from 1 to" in err
    assert not (tmp_path / "x.thgs").exists()


def test_build_names_missing_guidance(small_dataset, tmp_path, capsys):
    missing = tmp_path / "nowhere"
    code, out, err = run(
        ["build", str(small_dataset), "-o", str(tmp_path / "f.thgs"), "--guidance", str(missing)],
        capsys,
    )
    assert code == 2 and out == ""
    assert str(missing) in err.replace("\n", "") and "not found" in err
    assert not (tmp_path / "f.thgs").exists()


def test_a_long_path_stays_whole_on_one_error_line(small_dataset, tmp_path, capsys):
    """The console never breaks a message itself (the terminal wraps it): a path of any length
    can be copied from the error as it is."""
    missing = tmp_path / ("a-folder-with-a-long-name-" * 6) / "guidance"
    code, _, err = run(
        ["build", str(small_dataset), "-o", str(tmp_path / "f.thgs"), "--guidance", str(missing)],
        capsys,
    )
    assert code == 2 and len(str(missing)) > 160
    line = err.strip()
    assert line.startswith("error: ") and "\n" not in line and f" {missing}: " in line


@pytest.mark.slow
def test_demo_builds_queries_and_reports(tmp_path, capsys):
    out = tmp_path / "demo"
    argv = ["demo", "-o", str(out), "--cache", str(tmp_path / "cache")]
    argv += ["--gaussians", "4000", "--views", "8", "--query", "mug", "table"]
    code, stdout, err = run(argv, capsys)
    assert code == 0, err
    report = json.loads((out / "report.json").read_text())
    assert report["generated"] is True
    assert [q["text"] for q in report["queries"]] == ["mug", "table"]
    for query in report["queries"]:
        assert (out / query["image"]).is_file() and len(query["regions"]) >= 1
        assert 0.0 <= query["iou"] <= 1.0 and 0.0 <= query["best_iou"] <= 1.0
        assert "reason" not in query
    # the automatic selection answers the objects' names better than the paper's, on average
    # (measured: mug 1.00 against 0.75, table 0.86 against 0.90)
    automatic = np.mean([query["iou"] for query in report["queries"]])
    assert automatic > np.mean([query["paper_iou"] for query in report["queries"]])
    assert [q["level"] for q in report["queries"]] == [3, 3]  # mug and table are objects
    assert set(report["miou"]) == {"subpart", "part", "object"}
    assert all(0.0 < value <= 1.0 for value in report["miou"].values())
    assert (out / "levels.png").is_file() and (out / "field.thgs").is_file()
    assert "matched mIoU" in stdout and "query-*.png" in stdout
    mug = report["queries"][0]
    assert mug["confidence"] > 0.9 and f"mug ({mug['confidence']:.2f})" in stdout
    # each query is drawn in the view that shows most of its selection
    from thgs.field_scene import field_text_encoder, open_field_scene
    from thgs.query import FieldQuery
    from thgs.views import visible_pixels

    field, scene = open_field_scene(out / "field.thgs")
    engine = FieldQuery(field, field_text_encoder(field, out / "field.thgs"))
    for query in report["queries"]:
        counts = visible_pixels(
            scene.gaussians, scene.cameras, engine.select([query["text"]])[0].gaussians
        )
        assert query["view"] == scene.cameras.stems[int(np.argmax(counts))]
    # a second run reuses the cached scene
    code, _, err = run(argv, capsys)
    assert code == 0, err
    assert json.loads((out / "report.json").read_text())["generated"] is False


@pytest.mark.slow
def test_console_script_demo(tmp_path):
    """The README's main job, reduced: the installed `thgs demo` on a small synthetic scene."""
    executable = shutil.which("thgs", path=str(Path(sys.executable).parent))
    if executable is None:
        pytest.skip("the thgs console script is not installed next to this Python")
    result = subprocess.run(
        [executable, "demo", "--gaussians", "3000", "--views", "6", "-o", str(tmp_path / "out")],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        check=False,
        timeout=300,
        env={**os.environ, "THGS_CACHE": str(tmp_path / "cache")},
    )
    assert result.returncode == 0, result.stderr
    assert "text queries" in result.stdout
    assert (tmp_path / "cache" / "synth-small-seed0-3000g-6v" / "synthetic.json").is_file()


@pytest.mark.slow
def test_query_prints_regions_and_writes_masks(small_dataset, small_field, tmp_path, capsys):
    import numpy as np
    from PIL import Image

    from thgs import load_scene
    from thgs.field import load_field
    from thgs.query import FieldQuery
    from thgs.text import load_text_encoder
    from thgs.views import relevancy_map, selection_masks

    scene = load_scene(small_dataset)
    views = list(scene.cameras.stems[:2])
    out = tmp_path / "q"
    argv = ["query", str(small_field), "mug", "teddy bear", "--views", *views, "-o", str(out)]
    code, stdout, err = run([*argv, "--relevancy"], capsys)
    assert code == 0, err
    assert "mug" in stdout and "teddy bear" in stdout
    results = json.loads((out / "results.json").read_text())
    assert [q["text"] for q in results["queries"]] == ["mug", "teddy bear"]
    assert results["config"]["mode"] == "auto"
    field = load_field(small_field)
    fq = FieldQuery(field, load_text_encoder(field.space))
    for entry, selection in zip(results["queries"], fq.select(["mug", "teddy bear"])):
        assert [(r["level"], r["region"]) for r in entry["regions"]] == [
            (k, r) for k, r, _ in selection.regions
        ]
        assert entry["gaussians"] == int(selection.gaussians.sum())
        assert (
            entry["confidence"] == pytest.approx(selection.confidence) and entry["confidence"] > 0.9
        )
        assert [r["confidence"] for r in entry["regions"]] == pytest.approx(
            selection.region_confidence
        )
        assert f"{selection.confidence:.2f}" in stdout
        for i, view in enumerate(views):
            camera = scene.cameras.select([i])
            written = np.asarray(Image.open(out / Path(entry["files"][0]).parent / f"{view}.png"))
            np.testing.assert_array_equal(
                written > 127, selection_masks(scene.gaussians, camera, selection.gaussians)
            )
            relevancy = np.asarray(
                Image.open(out / Path(entry["files"][0]).parent / f"{view}-relevancy-object.png")
            )
            expected = relevancy_map(
                scene.gaussians, camera, fq.gaussian_relevancy(selection.text, 3)
            )
            assert np.abs(relevancy / 255.0 - expected).max() <= 0.5 / 255 + 1e-9
    # threshold mode: a text about nothing in the scene selects nothing
    code, stdout, err = run(
        ["query", str(small_field), "xqzv blorf", "--mode", "threshold"], capsys
    )
    assert code == 0, err
    assert "nothing relevant" in stdout


def test_pick_reports_the_region_chain(small_dataset, small_field, tmp_path, capsys):
    import numpy as np
    import torch

    from thgs import load_scene
    from thgs.field import load_field
    from thgs.render import render
    from thgs.scene import read_ply

    scene = load_scene(small_dataset)
    camera = scene.cameras.select([0])
    zeros = torch.zeros(len(scene.gaussians), 1, dtype=torch.float64)
    ids = render(scene.gaussians, camera, zeros).max_id.numpy()
    rows, cols = np.nonzero(ids >= 0)
    y, x = int(rows[rows.size // 2]), int(cols[rows.size // 2])
    out = tmp_path / "pick"
    argv = ["pick", str(small_field), "--view", camera.stems[0], "--pixel", str(x), str(y)]
    code, stdout, err = run([*argv, "--level", "2", "-o", str(out)], capsys)
    assert code == 0, err
    field = load_field(small_field)
    picked = json.loads((out / "pick.json").read_text())
    assert picked["gaussian"] == ids[y, x]
    assert list(picked["regions"].values()) == field.labels[ids[y, x]].tolist()
    region = picked["region"]
    assert region == field.labels[ids[y, x], 2] and picked["parent"] == field.parent(2, region)
    assert picked["children"] == field.children(2, region).tolist()
    assert (
        len(read_ply(out / f"part-{region}.ply")) == picked["gaussians"] == field.sizes(2)[region]
    )
    assert "← picked" in stdout
    code, _, err = run([*argv[:3], "nope", "--pixel", "0", "0"], capsys)
    assert code == 2 and "no view named 'nope'" in " ".join(err.split())
    code, _, err = run([*argv[:4], "--pixel", "100000", "0"], capsys)
    assert code == 2 and "outside" in err


@pytest.mark.slow
def test_export_selection_regions_and_labels(small_dataset, small_field, tmp_path, capsys):
    import numpy as np

    from thgs import load_scene
    from thgs.field import load_field
    from thgs.scene import read_ply

    out = tmp_path / "export"
    argv = ["export", str(small_field), "-o", str(out), "--query", "mug", "--mode", "level"]
    code, stdout, err = run([*argv, "--color-level", "3", "--labels"], capsys)
    assert "mug" in stdout and "wrote 5 files" in stdout
    assert code == 0, err
    field = load_field(small_field)
    scene = load_scene(small_dataset)
    summary = json.loads((out / "selections.json").read_text())
    (entry,) = summary["queries"]
    level, region = entry["regions"][0]["level"], entry["regions"][0]["region"]
    mug = read_ply(out / "mug.ply")
    members = field.labels[:, level] == region
    assert len(mug) == entry["gaussians"] == members.sum()
    np.testing.assert_array_equal(mug.means.numpy(), scene.gaussians.means[members].numpy())
    assert len(read_ply(out / "regions-object.ply")) == len(field)
    np.testing.assert_array_equal(np.load(out / "labels.npy"), field.labels)
    assert json.loads((out / "labels.json").read_text())["gaussians"] == len(field)
    code, _, err = run(["export", str(small_field), "-o", str(out)], capsys)
    assert code == 2 and "nothing to export" in err


@pytest.mark.slow
def test_export_outputs_never_share_a_name(small_field, tmp_path, capsys):
    """A query named like the whole-scene PLY gets its own name; a set that cannot be written
    whole leaves none of its files."""
    from thgs.field import load_field
    from thgs.scene import read_ply

    out = tmp_path / "export"
    argv = ["export", str(small_field), "-o", str(out), "--query", "regions object"]
    code, _, err = run([*argv, "--mode", "level", "--level", "3", "--color-level", "3"], capsys)
    assert code == 0, err
    (entry,) = json.loads((out / "selections.json").read_text())["queries"]
    assert entry["ply"] == str(out / "regions-object-2.ply")
    assert len(read_ply(out / "regions-object-2.ply")) == entry["gaussians"]
    assert len(read_ply(out / "regions-object.ply")) == len(load_field(small_field))

    blocked = tmp_path / "blocked"
    (blocked / "labels.npy").mkdir(parents=True)  # the last file of the set cannot be written
    argv = ["export", str(small_field), "-o", str(blocked), "--query", "mug", "--color-level", "3"]
    code, _, err = run([*argv, "--labels"], capsys)
    assert code != 0 and "labels.npy:Isadirectory" in "".join(err.split())
    assert sorted(path.name for path in blocked.iterdir()) == ["labels.npy"]


@pytest.mark.slow
def test_field_without_or_with_another_scene_is_refused(small_field, tmp_path, capsys):
    from dataclasses import replace

    from thgs.field import load_field, save_field

    field = load_field(small_field)
    bare = tmp_path / "bare.thgs"
    save_field(bare, replace(field, provenance=replace(field.provenance, scene=None)))
    code, _, err = run(["pick", str(bare), "--view", "x", "--pixel", "0", "0"], capsys)
    assert code == 2 and "records no scene" in err and "--scene" in err
    other = tmp_path / "other"
    code, _, err = run(
        ["synth", "synth-small", str(other), "--gaussians", "4000", "--views", "8", "--seed", "1"],
        capsys,
    )
    assert code == 0, err
    code, _, err = run(
        [
            "query",
            str(small_field),
            "mug",
            "--views",
            "all",
            "-o",
            str(tmp_path / "q"),
            "--scene",
            str(other),
        ],
        capsys,
    )
    assert code == 2 and "fingerprints differ" in " ".join(err.split())
    code, _, err = run(["query", str(small_field), "mug", "--views", "all"], capsys)
    assert code == 2 and "--out" in err


@pytest.mark.slow
def test_eval_runs_every_protocol_of_a_synthetic_dataset(
    small_dataset, small_field, tmp_path, capsys
):
    import numpy as np

    from thgs.eval import matched_miou, read_lerf_labels
    from thgs.eval.ground_truth import read_hierarchy
    from thgs.field import load_field

    out = tmp_path / "eval.json"
    code, stdout, err = run(["eval", str(small_dataset), str(small_field), "-o", str(out)], capsys)
    assert code == 0, err
    report = json.loads(out.read_text())
    protocols = [result["protocol"] for result in report["results"]]
    assert protocols == [
        "lerf",
        "lerf-paper",
        "lerf-langsplat",
        "lerf-opengaussian",
        "3dovs",
        "scannet-all",
        "hierarchy",
    ]
    results = {result["protocol"]: result for result in report["results"]}
    # every (frame, category) of the label files is scored once
    frames = sorted((small_dataset / "label").glob("*.json"))
    expected = [(f.stem, c) for f in frames for c in read_lerf_labels(f).categories]
    for name in ("lerf", "lerf-paper", "lerf-langsplat", "lerf-opengaussian"):
        assert [(i["frame"], i["prompt"]) for i in results[name]["items"]] == expected
        assert all(0.0 <= i["iou"] <= 1.0 for i in results[name]["items"])
    assert results["lerf"]["settings"]["selection"] == "auto"
    # the folder's name is no LERF scene's: OpenGaussian's protocol queries every category
    assert results["lerf-opengaussian"]["notes"] == [
        f"scene name {small_dataset.name!r} is none of OpenGaussian's (figurines, ramen, "
        "teatime, waldo_kitchen): every labelled category is queried"
    ]
    assert "every labelled category is queried" in " ".join(stdout.split())
    assert results["lerf-paper"]["settings"]["selection"] == "paper"
    # the hierarchy protocol is the field's matched mIoU against the ground truth
    field = load_field(small_field)
    truth = read_hierarchy(small_dataset / "ground_truth.safetensors").labels
    for k, name in enumerate(("subpart", "part", "object"), start=1):
        assert results["hierarchy"]["metrics"][f"miou_{name}"] == matched_miou(
            field.labels[:, k], truth[:, k]
        )
    # the THGS mean is over prompts per frame, then frames
    items = results["lerf"]["items"]
    per_frame = [np.mean([i["iou"] for i in items if i["frame"] == f.stem]) for f in frames]
    assert results["lerf"]["metrics"]["miou"] == pytest.approx(np.mean(per_frame))
    assert out.with_suffix(".md").read_text().startswith("| protocol | metric |")
    assert "lerf-langsplat" in stdout and "localization" in stdout

    code, _, err = run(
        ["eval", str(small_dataset), str(small_field), "--protocol", "scannet", "-o", str(out)],
        capsys,
    )
    assert code == 0, err
    assert [r["protocol"] for r in json.loads(out.read_text())["results"]] == ["scannet-all"]

    # eval-mean: the last averaging step, over scenes (here the report and an altered copy)
    first = json.loads(out.read_text())
    second = json.loads(out.read_text())
    second["results"][0]["metrics"]["miou"] = 0.25
    paths = [tmp_path / "a.json", tmp_path / "b.json"]
    for path, document in zip(paths, (first, second)):
        path.write_text(json.dumps(document))
    means = tmp_path / "means.json"
    code, stdout, err = run(["eval-mean", *map(str, paths), "-o", str(means)], capsys)
    assert code == 0, err
    expected = (first["results"][0]["metrics"]["miou"] + 0.25) / 2
    assert json.loads(means.read_text())["means"]["scannet-all"]["miou"] == pytest.approx(expected)
    paths[1].write_text("[1, 2]")
    code, _, err = run(["eval-mean", *map(str, paths)], capsys)
    # rich wraps long lines at spaces (and may split the path anywhere)
    assert code == 2 and "is not a thgs eval report" in " ".join(err.split())
    assert str(paths[1]) in err.replace("\n", "")


def test_eval_refuses_a_dataset_without_ground_truth(small_field, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    code, stdout, err = run(["eval", str(empty), str(small_field)], capsys)
    assert code == 2 and stdout == ""
    assert "holds no benchmark ground truth" in " ".join(err.split())
    assert not list(tmp_path.glob("*.eval.json"))


@pytest.mark.slow
def test_bench_compares_variants_on_a_reduced_scene(tmp_path, capsys):
    out = tmp_path / "bench"
    argv = ["bench", "-o", str(out), "--presets", "synth-small", "--gaussians", "3000"]
    argv += ["--views", "6", "--cache", str(tmp_path / "cache"), "--clip-like"]
    argv += ["--variants", "full", "no progressive merging", "instance level only", "exact lifting"]
    code, stdout, err = run(argv, capsys)
    assert code == 0, err
    assert "Paper orderings" in stdout and "Selection across scenarios" in stdout
    assert (tmp_path / "cache" / "synth-small-seed0-3000g-6v-clip-like").is_dir()
    report = json.loads((out / "bench.json").read_text())
    runs = {entry["variant"]: entry for entry in report["runs"]}
    assert {(e["kind"], e["severity"], e["stand_in"]) for e in report["runs"]} == {
        ("2dgs", 0.5, "clip-like")
    }
    (cell,) = report["selection"]
    assert cell["lerf miou"] == runs["full"]["quality"]["lerf miou"]
    assert cell["lerf-paper miou"] == runs["full"]["quality"]["lerf-paper miou"]
    assert list(runs) == ["full", "no progressive merging", "instance level only", "exact lifting"]
    # the three latent-lifting variants share one lift; exact lifting has its own
    assert [runs[v]["lift_shared"] for v in runs] == [True, True, True, False]
    assert runs["full"]["stages"]["lift"] == runs["instance level only"]["stages"]["lift"]
    for entry in runs.values():
        assert entry["gaussians"] == 3000 and entry["views"] == 6
        assert entry["seconds"] == pytest.approx(sum(entry["stages"].values()))
        assert 0.0 <= entry["quality"]["lerf miou"] <= 1.0
        assert set(entry["quality"]) >= {"hierarchy miou_object", "3dovs miou", "scannet-all miou"}
    # instance level only: one merged level copied to levels 1-3
    counts = runs["instance level only"]["region_counts"]
    assert counts[1] == counts[2] == counts[3]
    assert report["orderings"][0]["variants"] == [
        "full",
        "no progressive merging",
        "instance level only",
    ]
    assert (out / "bench-time.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    markdown = (out / "bench.md").read_text()
    assert "| synth-small | exact lifting |" in markdown and "Paper orderings" in markdown
    code, _, err = run(["bench", "-o", str(out), "--variants", "no such thing"], capsys)
    assert code == 2 and "unknown 'no such thing'" in err
    # stand-ins named by the flag, before any work
    for flags, message in (
        (["--stand-ins", "clip"], "--stand-ins: unknown 'clip' in 'clip'"),
        (["--stand-ins", "clip-like:surroundings=2"], "--stand-ins: 'clip-like:surroundings=2': "),
        (["--clip-like", "--clip-grid"], "--clip-like: and --clip-grid choose different"),
    ):
        code, _, err = run(["bench", "-o", str(tmp_path / "never"), *flags], capsys)
        assert code == 2 and message in " ".join(err.split()), err
        assert not (tmp_path / "never").exists()


# --- guidance guards, the recorded text model, messages in flags ---------------------------------


def _copy_guidance(small_dataset: Path, folder: Path, *, empty: bool = False) -> Path:
    """The small dataset's language_features copied to ``folder``; ``empty``: no mask at all."""
    import numpy as np

    shutil.copytree(small_dataset / "language_features", folder)
    if empty:
        for path in folder.glob("*_s.npy"):
            np.save(path, np.full_like(np.load(path), -1.0))
        for path in folder.glob("*_f.npy"):
            np.save(path, np.load(path)[:0])
    return folder


def test_build_refuses_guidance_without_a_mask(small_dataset, tmp_path, capsys):
    guidance = _copy_guidance(small_dataset, tmp_path / "lf", empty=True)
    out = tmp_path / "f.thgs"
    argv = ["build", str(small_dataset), "-o", str(out), "--guidance", str(guidance)]
    code, stdout, err = run(argv, capsys)
    err = " ".join(err.split())
    assert code == 2 and stdout == "" and not out.exists()
    assert err.startswith(f"error: {guidance}: none of the 8 views has a mask")
    assert "thgs preprocess --pred-iou-threshold, --stability-threshold, --min-region-area" in err


def test_build_refuses_an_embedding_file_that_disagrees(small_dataset, tmp_path, capsys):
    guidance = _copy_guidance(small_dataset, tmp_path / "lf")
    out = tmp_path / "f.thgs"
    base = ["build", str(small_dataset), "-o", str(out), "--guidance", str(guidance)]
    code, _, err = run([*base, "--space", "other/space"], capsys)
    err = " ".join(err.split())
    assert code == 2 and err.startswith("error: --space: 'other/space', but ")
    assert "records 'sentence-transformers/all-MiniLM-L6-v2'" in err
    (guidance / "embedding.json").write_text('{"space": "my/clip", "dim": 512}')
    code, _, err = run(base, capsys)
    err = " ".join(err.split())
    assert code == 2 and not out.exists()
    # rich may wrap anywhere in the long path: compare without white space there
    expected = f"error: {guidance / 'embedding.json'}: records 512-D features of my/clip"
    assert "".join(expected.split()) in "".join(err.split())
    assert "hold 384-D features" in err
    (guidance / "embedding.json").unlink()  # 384-D features without a record: name their space
    code, _, err = run(base, capsys)
    assert code == 2 and "384-D features and no embedding.json" in " ".join(err.split())
    # a --text-model that is not a folder is named before the scene is even loaded
    code, _, err = run([*base, "--text-model", str(tmp_path / "nowhere")], capsys)
    assert code == 2 and "--text-model:" in err
    base += ["--space", "sentence-transformers/all-MiniLM-L6-v2"]
    code, _, err = run([*base, "--text-model", str(tmp_path / "nowhere")], capsys)
    err = " ".join(err.split())
    assert code == 2 and err == f"error: --text-model: {tmp_path / 'nowhere'} is not a folder"


@pytest.mark.slow
def test_build_records_the_preprocess_text_model(small_dataset, tmp_path, capsys):
    from thgs.field import load_field
    from thgs.pipeline import recorded_config

    guidance = _copy_guidance(small_dataset, tmp_path / "lf")
    model = tmp_path / "minilm copy"
    model.mkdir()
    document = json.loads((guidance / "embedding.json").read_text())
    (guidance / "embedding.json").write_text(json.dumps({**document, "model": str(model)}))
    out = tmp_path / "f.thgs"
    argv = ["build", str(small_dataset), "-o", str(out), "--guidance", str(guidance)]
    code, _, err = run(argv, capsys)
    assert code == 0, err
    field = load_field(out)
    assert field.provenance.text_model == str(model.resolve())
    recorded_config(field)  # the record is not a setting: the field can be rebuilt from itself


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory) -> Path:
    pytest.importorskip("transformers")
    import tiny_models

    return tiny_models.tiny_clip(tmp_path_factory.mktemp("models") / "my-clip")


def _clip_field(small_field: Path, model: Path, out: Path) -> None:
    """The small field as if built from features of the CLIP in ``model`` (16-D, preprocessed
    with --space test/tiny-clip), which it records."""
    from dataclasses import replace

    import numpy as np

    from thgs.field import load_field, save_field
    from thgs.field_scene import record_text_model

    field = load_field(small_field)
    rng = np.random.default_rng(0)
    features = []
    for seen in field.seen:
        rows = rng.normal(size=(len(seen), 16)).astype(np.float32)
        rows /= np.linalg.norm(rows, axis=1, keepdims=True)
        features.append(np.where(seen[:, None], rows, 0).astype(np.float32))
    clip = replace(field, features=tuple(features), space="test/tiny-clip")
    save_field(out, record_text_model(clip, model))


def test_query_uses_the_text_model_the_field_records(
    small_field, tiny_clip, tmp_path, monkeypatch, capsys
):
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))  # an empty cache: only the record helps
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    model = tmp_path / "clip"
    shutil.copytree(tiny_clip, model)
    field = tmp_path / "clip.thgs"
    _clip_field(small_field, model, field)
    code, out, err = run(["query", str(field), "mug", "--mode", "level"], capsys)
    assert code == 0, err
    assert "thgs query" in out and "mug" in out
    moved = tmp_path / "moved"
    model.rename(moved)
    code, out, err = run(["query", str(field), "mug"], capsys)
    err = " ".join(err.split())
    assert code == 2 and out == ""
    assert err == (
        f"error: {field}: its features came from the text model in {model.resolve()}, which no "
        "longer exists; pass the model's folder with --text-model DIR"
    )
    code, out, err = run(["query", str(field), "mug", "--text-model", str(moved)], capsys)
    assert code == 0, err
    assert "mug" in out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--top", "0"], "error: --top: must be ≥ 1, got 0"),
        (
            ["--mode", "threshold", "--threshold", "2"],
            "error: --threshold: must be in [0, 1], got 2.0",
        ),
        (["--level", "5"], "error: --level: must be 1 sub-parts, 2 parts or 3 objects, got 5"),
    ],
)
def test_query_names_bad_settings_by_their_flags(small_field, capsys, argv, message):
    code, _, err = run(["query", str(small_field), "mug", *argv], capsys)
    assert code == 2 and " ".join(err.split()) == message


def test_help_speaks_flags(capsys):
    helps = {}
    for command in ("preprocess", "build", "query", "export", "view", "eval", "bench", "info"):
        code, out, _ = run([command, "--help"], capsys)
        assert code == 0
        helps[command] = " ".join(out.split())
        assert "{None}" not in helps[command], command
    assert "[n, 512]" not in helps["preprocess"] and "[n, D] unit features" in helps["preprocess"]
    for flag in ("--pred-iou-threshold", "--stability-threshold", "--min-region-area"):
        assert flag in helps["preprocess"]
    # one vocabulary of selection modes
    for command in ("query", "export", "view"):
        assert "--mode {auto,paper,level,threshold}" in helps[command], command


@pytest.mark.parametrize(
    ("raised", "code", "line"),
    [
        (KeyboardInterrupt(), 130, "error: interrupted"),
        (OSError(28, "No space left on device", "/data/out.thgs"),
         1, "error: /data/out.thgs: No space left on device"),
        (OSError(36, "File name too long"), 1, "error: File name too long"),
    ],
)  # fmt: skip
def test_interrupts_and_system_errors_end_with_one_line(
    shared_data, capsys, monkeypatch, raised, code, line
):
    import thgs.cli.scene

    def fail(*args, **kwargs):
        raise raised

    monkeypatch.setattr(thgs.cli.scene, "load_scene", fail)
    status, out, err = run(["info", str(shared_data / "ply_3dgs_train1000.ply")], capsys)
    assert status == code and err.strip() == line and out == ""


@pytest.mark.slow
def test_interrupted_build_leaves_no_field(small_dataset, tmp_path, capsys, monkeypatch):
    import thgs.pipeline

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(thgs.pipeline, "merge_levels", interrupted)
    out = tmp_path / "field.thgs"
    status, _, err = run(["build", str(small_dataset), "-o", str(out)], capsys)
    assert status == 130 and err.strip().splitlines()[-1] == "error: interrupted"
    assert list(tmp_path.iterdir()) == []


def test_output_paths_are_checked_before_any_work(
    small_dataset, small_field, tmp_path, capsys, monkeypatch
):
    import thgs.pipeline

    def no_work(*args, **kwargs):
        raise AssertionError("the work started before the output path was checked")

    monkeypatch.setattr(thgs.pipeline, "iter_lift_views", no_work)
    folder = tmp_path / "taken"
    folder.mkdir()
    blocker = tmp_path / "file"
    blocker.write_text("")
    long_name = tmp_path / ("q" * 300)
    cases = [
        (["build", str(small_dataset), "-o", str(folder)], f"{folder}: is a folder"),
        (["build", str(small_dataset), "-o", str(blocker / "a.thgs")], f"{blocker}: is a file"),
        (["build", str(small_dataset), "-o", str(long_name)], "has a name longer than"),
        (["eval", str(small_dataset), str(small_field), "-o", str(folder)], "is a folder"),
        (["query", str(small_field), "mug", "-o", str(blocker)], f"{blocker}: is a file;"),
        (
            [
                "pick",
                str(small_field),
                "--view",
                "x",
                "--pixel",
                "1",
                "1",
                "-o",
                str(blocker / "p"),
            ],
            "is a file, so",
        ),
        (["export", str(small_field), "--query", "mug", "-o", str(blocker)], "is a file;"),
        (["demo", "-o", str(blocker)], "is a file;"),
    ]
    for argv, message in cases:
        code, _, err = run(argv, capsys)
        err = " ".join(err.split())
        assert code == 2 and message in err and err.startswith("error:"), (argv, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "taken"]
    assert list(folder.iterdir()) == []


def test_eval_checks_its_default_report_path_before_any_work(
    small_dataset, small_field, tmp_path, capsys, monkeypatch
):
    import thgs.eval.dataset

    def no_work(*args, **kwargs):
        raise AssertionError("the work started before the output path was checked")

    monkeypatch.setattr(thgs.eval.dataset, "find_ground_truth", no_work)
    field = tmp_path / "f.thgs"
    shutil.copy(small_field, field)
    (tmp_path / "f.eval.json").mkdir()  # where the report would go without -o
    code, _, err = run(["eval", str(small_dataset), str(field)], capsys)
    err = " ".join(err.split())
    assert code == 2 and f"{tmp_path / 'f.eval.json'}: is a folder" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.eval.json", "f.thgs"]


@pytest.mark.slow
def test_eval_refuses_ground_truth_of_another_capture(small_dataset, small_field, tmp_path, capsys):
    other = tmp_path / "other"
    code, _, err = run(["synth", "synth-small", str(other), "--gaussians", "4000",
                        "--views", "4", "--seed", "5"], capsys)  # fmt: skip
    assert code == 0, err
    argv = ["eval", str(other), str(small_field), "-o", str(tmp_path / "r.json")]
    code, _, err = run([*argv, "--protocol", "lerf"], capsys)
    err = " ".join(err.split())
    assert code == 2 and "is not the scene the field was built on" in err and "--other-scene" in err
    assert not (tmp_path / "r.json").exists()
    code, _, err = run([*argv, "--protocol", "lerf", "--other-scene"], capsys)
    assert code == 0, err
    # labels drawn on another aspect ratio than their camera's: refused unless asked
    copy = tmp_path / "copy"
    shutil.copytree(small_dataset, copy)
    label = sorted((copy / "label").glob("frame_*.json"))[0]
    document = json.loads(label.read_text())
    document["info"]["width"] = int(document["info"]["width"] * 1.25)
    label.write_text(json.dumps(document))
    argv = [
        "eval",
        str(copy),
        str(small_field),
        "--protocol",
        "lerf",
        "-o",
        str(tmp_path / "c.json"),
    ]
    code, _, err = run(argv, capsys)
    err = " ".join(err.split())
    assert code == 2 and f"label file {label.stem}.json" in err and "--rescale-labels" in err
    assert "another aspect ratio" in err
    code, _, err = run([*argv, "--rescale-labels"], capsys)
    assert code == 0, err


def test_label_sizes_and_camera_subsets():
    from conftest import random_cameras
    from thgs.eval.evaluate import check_label_size
    from thgs.scene.loader import camera_disagreement

    check_label_size("f", (640, 480), (320, 240), False)  # same aspect: scaled
    check_label_size("f", (988, 730), (320, 240), True)  # asked to stretch
    with pytest.raises(InputError, match=r"f: labels are 988×730 but their camera is 320×240"):
        check_label_size("f", (988, 730), (320, 240), False)
    cameras = random_cameras(5, centred=True)
    assert camera_disagreement(cameras, cameras.select([1, 2, 3]), subset=True) is None
    assert "different images" in camera_disagreement(cameras, cameras.select([1, 2, 3]))
    renamed = type(cameras)(
        cameras.viewmats, cameras.Ks, cameras.widths, cameras.heights, ("a", "b", "c", "d", "e")
    )
    assert "no image in common" in camera_disagreement(cameras, renamed, subset=True)


@pytest.mark.slow
@pytest.mark.parametrize(
    "command",
    ["build", "query", "export", "pick", "eval", "synth", "demo"],
)
def test_ctrl_c_while_writing_leaves_nothing(
    command, small_dataset, small_field, tmp_path, capsys, monkeypatch
):
    """Ctrl-C at the moment the first finished output would be moved into place: exit 130, one
    error line, and no file and no hidden temporary left in the output folder."""
    from thgs import load_scene

    camera = load_scene(small_dataset).cameras.stems[0]
    out = tmp_path / "out"
    argv = {
        "build": ["build", str(small_dataset), "-o", str(out / "f.thgs")],
        "query": ["query", str(small_field), "mug", "--views", camera, "-o", str(out)],
        "export": ["export", str(small_field), "--query", "mug", "-o", str(out)],
        "pick": ["pick", str(small_field), "--view", camera, "--pixel", "160", "120", "-o",
                 str(out)],
        "eval": ["eval", str(small_dataset), str(small_field), "--protocol", "hierarchy", "-o",
                 str(out / "r.json")],
        "synth": ["synth", "synth-small", str(out / "d"), "--gaussians", "2000", "--views", "4"],
        "demo": ["demo", "-o", str(out / "demo"), "--cache", str(out / "cache"), "--gaussians",
                 "2000", "--views", "4"],
    }[command]  # fmt: skip
    out.mkdir()
    real = os.replace

    def interrupted(source, target):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted)
    code, _, err = run(argv, capsys)
    monkeypatch.setattr(os, "replace", real)
    assert code == 130 and err.strip().splitlines()[-1] == "error: interrupted", err
    left = [p for p in out.rglob("*") if p.is_file() or p.name.startswith(".")]
    assert left == [], left  # (the demo's cache folder may exist, empty)


def _written(folder: Path) -> list[Path]:
    """Every file, and every hidden (temporary) name, under ``folder``."""
    return [p for p in folder.rglob("*") if p.is_file() or p.name.startswith(".")]


@pytest.mark.slow
@pytest.mark.parametrize("stage", ["generate", "build"])
def test_ctrl_c_during_bench_leaves_no_report_and_no_half_dataset(
    stage, tmp_path, capsys, monkeypatch
):
    """Ctrl-C while bench generates its synthetic dataset (after the first view is written) or
    builds a variant: exit 130, one error line, no report, and the cache holds the whole dataset
    or none of it."""
    import thgs.bench.run
    import thgs.synthetic.dataset
    from thgs.synthetic.cache import open_synthetic_dataset
    from thgs.text import MINILM_SPACE, load_text_encoder

    real_guidance, calls = thgs.synthetic.dataset.oracle_guidance, []

    def second_view_interrupted(*args, **kwargs):
        calls.append(args[0])
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real_guidance(*args, **kwargs)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    if stage == "generate":
        monkeypatch.setattr(thgs.synthetic.dataset, "oracle_guidance", second_view_interrupted)
    else:
        monkeypatch.setattr(thgs.bench.run, "build_levels", interrupted)
    out, cache = tmp_path / "out", tmp_path / "cache"
    argv = ["bench", "-o", str(out), "--presets", "synth-small", "--gaussians", "2000"]
    argv += ["--views", "4", "--stand-ins", "name-perfect", "--variants", "full"]
    argv += ["--cache", str(cache)]
    code, _, err = run(argv, capsys)
    assert code == 130 and err.strip().splitlines()[-1] == "error: interrupted", err
    assert not out.exists()
    dataset = cache / "synth-small-seed0-2000g-4v"
    if stage == "generate":
        assert len(calls) == 2 and _written(tmp_path) == []
        return
    # the dataset was finished before the build: whole, readable, and nothing hidden beside it
    assert [p.name for p in cache.iterdir()] == [dataset.name]
    assert not [p for p in dataset.rglob(".*")]
    scene, guidance = open_synthetic_dataset(dataset, load_text_encoder(MINILM_SPACE))
    assert (len(scene.gaussians), len(scene.cameras), len(guidance)) == (2000, 4, 4)


def _interrupt_at_rename(monkeypatch, call: int) -> list[str]:
    """Ctrl-C at the ``call``-th ``os.replace`` (the renames before and after it happen): the
    renamed targets' names, in order, as they come."""
    real, calls = os.replace, []

    def interrupted(source, target):
        calls.append(Path(target).name)
        if len(calls) == call:
            raise KeyboardInterrupt
        real(source, target)

    monkeypatch.setattr(os, "replace", interrupted)
    return calls


@pytest.mark.parametrize("replace_call", range(1, 7))
def test_ctrl_c_while_bench_writes_its_report_leaves_none_of_it(
    replace_call, tmp_path, capsys, monkeypatch
):
    """bench's three report files are written to a hidden folder (renames 1–3) and then moved
    in (renames 4–6): Ctrl-C at any of them leaves no report file and no temporary; a rerun
    writes all three."""
    from dataclasses import asdict

    import thgs.bench
    from thgs.bench import BenchConfig, BenchReport, VariantRun

    run_ = VariantRun(
        preset="synth-small", seed=0, variant="full", kind="2dgs", severity=0.5,
        stand_in="name-perfect", gaussians=2000, views=4, stages={"lift": 1.5, "partition": 0.5},
        lift_shared=False, seconds=2.0, peak_gib=0.5, gpu_peak_gib=None,
        region_counts=(60, 40, 20, 10), quality={"lerf miou": 0.6, "lerf-paper miou": 0.5},
        evaluation_seconds=1.0,
    )  # fmt: skip
    machine = {"processor": "x86_64", "cpus": 2, "torch_threads": 2, "cuda": None}
    report = BenchReport((run_,), machine, asdict(BenchConfig(presets=("synth-small",))))
    monkeypatch.setattr(thgs.bench, "run_bench", lambda *args, **kwargs: report)
    out = tmp_path / "out"
    argv = ["bench", "-o", str(out), "--presets", "synth-small", "--variants", "full"]
    calls = _interrupt_at_rename(monkeypatch, replace_call)
    code, _, err = run(argv, capsys)
    assert code == 130 and err.strip().splitlines()[-1] == "error: interrupted", err
    assert len(calls) == replace_call and _written(tmp_path) == []
    if replace_call >= 4:
        assert calls[3:] == ["bench.json", "bench.md", "bench-time.png"][: replace_call - 3]
    code, _, err = run(argv, capsys)
    assert code == 0, err
    assert sorted(p.name for p in _written(tmp_path)) == [
        "bench-time.png",
        "bench.json",
        "bench.md",
    ]
    assert json.loads((out / "bench.json").read_text()) == json.loads(json.dumps(report.to_json()))
    assert (out / "bench.md").read_text() == report.markdown()


@pytest.mark.parametrize("replace_call", range(1, 5))
def test_ctrl_c_at_any_rename_of_eval_leaves_no_report(
    replace_call, small_dataset, small_field, tmp_path, capsys, monkeypatch
):
    """eval's report and its table are written to a hidden folder (renames 1–2) and moved in
    together (3–4): Ctrl-C at any of them leaves neither and no temporary."""
    out = tmp_path / "out"
    argv = ["eval", str(small_dataset), str(small_field), "--protocol", "hierarchy"]
    argv += ["-o", str(out / "r.json")]
    calls = _interrupt_at_rename(monkeypatch, replace_call)
    code, _, err = run(argv, capsys)
    assert code == 130 and err.strip().splitlines()[-1] == "error: interrupted", err
    assert len(calls) == replace_call and _written(tmp_path) == []
    code, _, err = run(argv, capsys)
    assert code == 0, err
    assert sorted(p.name for p in _written(tmp_path)) == ["r.json", "r.md"]


def test_eval_mean_checks_its_output_first_and_leaves_nothing_when_interrupted(
    tmp_path, capsys, monkeypatch
):
    reports = [tmp_path / "a.json", tmp_path / "b.json"]
    for path, miou in zip(reports, (0.25, 0.75)):
        path.write_text(json.dumps({"results": [{"protocol": "lerf", "metrics": {"miou": miou}}]}))
    folder = tmp_path / "taken"
    folder.mkdir()
    code, out, err = run(["eval-mean", *map(str, reports), "-o", str(folder)], capsys)
    err = " ".join(err.split())
    assert (
        code == 2
        and out == ""
        and err == f"error: {folder}: is a folder; -o names the file to write"
    )

    def interrupted(source, target):
        raise KeyboardInterrupt

    means = tmp_path / "out" / "means.json"
    monkeypatch.setattr(os, "replace", interrupted)
    code, _, err = run(["eval-mean", *map(str, reports), "-o", str(means)], capsys)
    monkeypatch.undo()
    assert code == 130 and err.strip().splitlines()[-1] == "error: interrupted", err
    assert _written(tmp_path / "out") == [] and list(folder.iterdir()) == []
    code, _, err = run(["eval-mean", *map(str, reports), "-o", str(means)], capsys)
    assert code == 0, err
    assert json.loads(means.read_text())["means"] == {"lerf": {"miou": 0.5}}


def test_ctrl_c_while_the_command_starts_is_an_interruption():
    """A KeyboardInterrupt while ``thgs`` imports its modules (seconds: torch, numba): exit 130
    and one line, no traceback; ``import thgs`` itself does not import torch."""
    code = (
        "import builtins, sys\n"
        "real = builtins.__import__\n"
        "def refuse(name, *args, **kwargs):\n"
        "    if name == 'thgs.cli':\n"
        "        raise KeyboardInterrupt\n"
        "    return real(name, *args, **kwargs)\n"
        "builtins.__import__ = refuse\n"
        "import thgs\n"
        "assert 'torch' not in sys.modules\n"
        "from thgs._main import main\n"
        "main()\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert (done.returncode, done.stderr) == (130, "error: interrupted\n")


def test_a_repeated_list_option_keeps_every_value():
    from thgs.cli import COMMANDS, joined_list_options, list_options

    assert list_options(COMMANDS["build"]) == {"--set", "--orbit-views", "--orbit-spheres"}
    assert list_options(COMMANDS["pick"]) == set()  # --pixel X Y has two values, always
    argv = ["build", "S", "--set", "a=1", "-o", "x", "--set", "b=2", "c=3", "--verbose"]
    assert joined_list_options(argv) == [
        *("build", "S", "--set", "a=1", "b=2", "c=3", "-o", "x", "--verbose")
    ]
    assert joined_list_options(["build", "S", "--set=a=1", "--set", "b=2"]) == [
        *("build", "S", "--set", "a=1", "b=2")
    ]
    argv = ["suite", "R", "--select", "x", "--ray", "local", "--select", "y", "-h"]
    assert joined_list_options(argv) == [
        *("suite", "R", "--select", "x", "y", "--ray", "local", "-h")
    ]
    argv = ["query", "F", "a mug", "--views", "v1", "--views", "v2"]
    assert joined_list_options(argv) == ["query", "F", "a mug", "--views", "v1", "v2"]
    assert joined_list_options(["pick", "F", "--pixel", "1", "2"]) == [
        *("pick", "F", "--pixel", "1", "2")
    ]
    assert joined_list_options(["nope", "--set", "a", "--set", "b"]) == [
        *("nope", "--set", "a", "--set", "b")
    ]
