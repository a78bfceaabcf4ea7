"""Real on-disk layouts with no extra flags: a trained model folder whose ``cfg_args`` names its
training data (3DGS, 2DGS, THGS), and LangSplat's LERF-OVS release with its labels beside the
scenes (``lerf_ovs/<scene>``, ``lerf_ovs/label/<scene>``); and the errors when a layout is
ambiguous or points nowhere."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from conftest import run_cli as run
from thgs import InputError, load_scene
from thgs.eval import find_ground_truth, read_lerf_labels
from thgs.eval.rules import OPENGAUSSIAN_LERF_PROMPTS
from thgs.field import load_field
from thgs.provenance import SceneRecord
from thgs.scene.cfg_args import find_model_source, read_cfg_args
from thgs.synthetic.layouts import write_langsplat_lerf

CFG_ARGS = (
    "Namespace(sh_degree=3, source_path={source!r}, model_path={model!r}, images='images', "
    "resolution=-1, white_background=False, data_device='cuda', eval=True, "
    "render_items=['RGB', 'Alpha', 'Normal', 'Depth'], depth_ratio=0.0, debug=False)\n"
)


def one_line(text: str) -> str:
    """Rich wraps long lines at spaces: undo it (for text without long words)."""
    return " ".join(text.split())


def squeezed(text: str) -> str:
    """The text without whitespace: rich also splits a long path anywhere."""
    return "".join(text.split())


def write_cfg_args(model: Path, source: str, model_path: str = "output/teatime") -> None:
    model.mkdir(parents=True, exist_ok=True)
    (model / "cfg_args").write_text(CFG_ARGS.format(source=source, model=model_path))


def source_folder(folder: Path) -> Path:
    """A folder that looks like training data (a COLMAP model folder)."""
    (folder / "sparse" / "0").mkdir(parents=True)
    return folder


# cfg_args: parsed, never executed


def test_read_cfg_args_parses_what_the_trainers_write(tmp_path):
    write_cfg_args(tmp_path, "/data/lerf_ovs/teatime")
    settings = read_cfg_args(tmp_path / "cfg_args")
    assert settings["source_path"] == "/data/lerf_ovs/teatime"
    assert settings["model_path"] == "output/teatime"
    assert (settings["resolution"], settings["eval"], settings["depth_ratio"]) == (-1, True, 0.0)
    assert settings["render_items"] == ["RGB", "Alpha", "Normal", "Depth"]


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("Namespace(source_path=__import__('os').getcwd())", "source_path= is not a literal"),
        ("__import__('os').getcwd()", "expected the text Namespace"),
        ("Namespace('/data', sh_degree=3)", "expected the text Namespace"),
        ("Namespace(**{'source_path': '/data'})", "expected the text Namespace"),
        ("Namespace(source_path='/data'", "expected the text Namespace"),
        ("", "expected the text Namespace"),
    ],
)
def test_read_cfg_args_refuses_anything_else(tmp_path, text, problem):
    path = tmp_path / "cfg_args"
    path.write_text(text)
    with pytest.raises(InputError, match=problem) as caught:
        read_cfg_args(path)
    assert str(path) in str(caught.value)


# where the source is


def test_source_as_written(tmp_path):
    data = source_folder(tmp_path / "data" / "teatime")
    write_cfg_args(tmp_path / "output" / "teatime", str(data))
    found = find_model_source(tmp_path / "output" / "teatime", cwd=tmp_path / "output")
    assert found is not None and found.folder == data and found.named == str(data)
    assert found.describe() == f"source {data} (named by {tmp_path / 'output/teatime/cfg_args'})"


def test_relative_source_from_where_training_ran(tmp_path):
    """model_path 'output/teatime' puts training in tmp_path: 'data/teatime' is there, from any
    working folder."""
    data = source_folder(tmp_path / "data" / "teatime")
    write_cfg_args(tmp_path / "output" / "teatime", "data/teatime", "./output/teatime")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    found = find_model_source(tmp_path / "output" / "teatime", cwd=elsewhere)
    assert found is not None and found.folder == data


def test_source_from_another_machine_found_by_its_tail(tmp_path):
    data = source_folder(tmp_path / "work" / "lerf_ovs" / "teatime")
    source_folder(tmp_path / "work" / "ramen")  # another scene, not a candidate
    model = tmp_path / "work" / "output" / "teatime"
    write_cfg_args(model, "/home/author/data/lerf_ovs/teatime")
    found = find_model_source(model, cwd=tmp_path)
    assert found is not None and found.folder == data
    assert "found for '/home/author/data/lerf_ovs/teatime'" in found.describe()


def test_the_model_folder_itself_is_never_the_source(tmp_path):
    model = tmp_path / "output" / "teatime"
    write_cfg_args(model, "/elsewhere/output/teatime")
    (model / "images").mkdir()  # looks like training data, but it is the model
    found = find_model_source(model, cwd=tmp_path)
    assert found is not None and found.folder is None
    assert found.tails == ("elsewhere/output/teatime", "output/teatime", "teatime")
    assert found.describe() == (
        f"{model / 'cfg_args'} names the source '/elsewhere/output/teatime', which is not here "
        f"(looked for 'elsewhere/output/teatime', 'output/teatime', 'teatime' under "
        f"{tmp_path}, {tmp_path / 'output'})"
    )


def test_two_folders_fitting_the_source_are_an_error(tmp_path):
    first = source_folder(tmp_path / "work" / "teatime")
    second = source_folder(tmp_path / "cwd" / "teatime")
    model = tmp_path / "work" / "output" / "teatime"
    write_cfg_args(model, "/data/teatime")
    with pytest.raises(InputError) as caught:
        find_model_source(model, cwd=tmp_path / "cwd")
    message = str(caught.value)
    assert message.startswith(f"{model / 'cfg_args'}: names the source '/data/teatime'")
    assert f"2 folders fit it: {first}, {second}; choose one with --source" in message


def test_a_malformed_cfg_args_names_the_flag(tmp_path):
    (tmp_path / "cfg_args").write_text("Namespace(source_path=open('x'))")
    with pytest.raises(InputError) as caught:
        find_model_source(tmp_path)
    assert str(caught.value) == (
        f"{tmp_path / 'cfg_args'}: source_path= is not a literal value; --source decides instead"
    )
    (tmp_path / "cfg_args").write_text("Namespace(source_path=3)")
    with pytest.raises(InputError, match="source_path must be a folder name, got 3; --source"):
        find_model_source(tmp_path)


def test_no_cfg_args_or_no_source_path(tmp_path):
    assert find_model_source(tmp_path) is None
    (tmp_path / "cfg_args").write_text("Namespace(sh_degree=3)")
    found = find_model_source(tmp_path)
    assert found is not None and found.named is None and found.folder is None
    assert found.describe() == f"{tmp_path / 'cfg_args'} names no source_path"


# the commands on the real layouts, with no extra flags


@pytest.mark.slow
def test_build_and_eval_on_the_real_layouts_with_no_flags(
    small_dataset, tmp_path, monkeypatch, capsys
):
    root = tmp_path / "work"
    write_langsplat_lerf(
        small_dataset, root, "teatime", source="/home/author/data/lerf_ovs/teatime", link=True
    )
    monkeypatch.chdir(root)
    data = root / "lerf_ovs" / "teatime"

    scene = load_scene("output/teatime")
    assert scene.source == data and scene.model_source is not None
    assert scene.cameras_path == data / "sparse" / "0"  # COLMAP of the source, not cameras.json

    code, out, err = run(["info", "output/teatime", "--json"], capsys)
    assert code == 0, err
    document = json.loads(out)
    assert document["cameras"]["source"] == str(data / "sparse" / "0")
    assert any(line.startswith(f"source {data} (found for") for line in document["found"])

    code, out, err = run(["build", "output/teatime", "-o", "teatime.thgs"], capsys)
    assert code == 0, err
    assert "wrote teatime.thgs" in one_line(out)
    record = load_field("teatime.thgs").provenance.scene
    assert record == SceneRecord("output/teatime", source="lerf_ovs/teatime")

    # labels in LangSplat's sibling folder lerf_ovs/label/teatime, found with no flag
    code, out, err = run(["eval", "lerf_ovs/teatime", "teatime.thgs"], capsys)
    assert code == 0, err
    report = json.loads(Path("teatime.eval.json").read_text())
    assert report["info"]["ground_truth"]["lerf"] == str(root / "lerf_ovs" / "label" / "teatime")
    results = {result["protocol"]: result for result in report["results"]}
    frames = sorted((small_dataset / "label").glob("*.json"))
    pairs = [(f.stem, c) for f in frames for c in read_lerf_labels(f).categories]
    assert [(i["frame"], i["prompt"]) for i in results["lerf"]["items"]] == pairs
    # the scene's name chose OpenGaussian's teatime prompts, and the report says so
    prompts = OPENGAUSSIAN_LERF_PROMPTS["teatime"]
    outside = sum(category not in prompts for _, category in pairs)
    note = (
        "lerf-opengaussian: scene name 'teatime' → OpenGaussian's fixed prompt list for "
        f"teatime (14 prompts); {outside} labelled (frame, category) pairs outside it score 0"
    )
    assert note in one_line(out)
    assert Path("teatime.eval.md").read_text().endswith(f"\n\n- {note}\n")
    assert results["lerf-opengaussian"]["notes"] == [note.removeprefix("lerf-opengaussian: ")]

    # --labels with the folder of every scene's labels, as LangSplat's and THGS's scripts take
    code, _, err = run(
        [
            *("eval", "lerf_ovs/teatime", "teatime.thgs", "--labels", "lerf_ovs/label"),
            *("--protocol", "lerf", "-o", "parent.json"),
        ],
        capsys,
    )
    assert code == 0, err
    again = json.loads(Path("parent.json").read_text())["results"][0]
    assert again["metrics"] == results["lerf"]["metrics"]


def test_source_flag_decides_over_cfg_args(small_dataset, tmp_path, monkeypatch):
    root = tmp_path / "work"
    write_langsplat_lerf(small_dataset, root, "teatime", source="/nowhere/teatime", link=True)
    monkeypatch.chdir(root)
    scene = load_scene("output/teatime", source="lerf_ovs/teatime")
    assert scene.model_source is None and scene.source == Path("lerf_ovs/teatime")
    assert scene.cameras_path == Path("lerf_ovs/teatime/sparse/0")


# bad input: a cfg_args pointing nowhere, ambiguous folders


def test_cfg_args_pointing_nowhere(small_dataset, tmp_path, monkeypatch, capsys, caplog):
    root = tmp_path / "work"
    write_langsplat_lerf(
        small_dataset, root, "teatime", source="/home/author/data/lerf_ovs/teatime", link=True
    )
    shutil.rmtree(root / "lerf_ovs")
    monkeypatch.chdir(root)
    named = "output/teatime/cfg_args names the source '/home/author/data/lerf_ovs/teatime', "
    looked = (
        "which is not here (looked for 'data/lerf_ovs/teatime', 'lerf_ovs/teatime', 'teatime' "
        f"under {root}, {root / 'output'})"
    )

    # the scene still loads, with the model's cameras.json, and says why
    scene = load_scene("output/teatime")
    assert scene.source is None and scene.cameras_path == Path("output/teatime/cameras.json")
    assert named + looked in scene.found
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == [
        "cameras from output/teatime/cameras.json: the training data named by "
        "output/teatime/cfg_args is not here (pass --source with it to read its cameras)"
    ]

    code, out, err = run(["build", "output/teatime", "-o", "f.thgs"], capsys)
    assert code == 2 and out == ""
    assert squeezed(err).startswith("warning:camerasfromoutput/teatime/cameras.json")
    assert squeezed(err.split("error:")[1]) == squeezed(
        "output/teatime/language_features: language features folder not found; "
        + named
        + looked
        + "; pass --source with the training data folder that holds language_features/, or "
        "--guidance, or make guidance on renders of the splat with --from-splat"
    )
    assert not Path("f.thgs").exists()

    (root / "output" / "teatime" / "cameras.json").unlink()
    code, out, err = run(["build", "output/teatime", "-o", "f.thgs"], capsys)
    assert code == 2 and out == ""
    assert squeezed(err) == squeezed(
        "error: output/teatime: no cameras; "
        + named
        + looked
        + "; pass --source with COLMAP or transforms.json, or build from the splat alone with "
        "--from-splat"
    )


def test_cfg_args_source_without_cameras_names_the_flag(small_dataset, tmp_path, monkeypatch):
    root = tmp_path / "work"
    write_langsplat_lerf(small_dataset, root, "teatime", source="lerf_ovs/teatime", link=True)
    (root / "lerf_ovs" / "teatime" / "sparse").unlink()
    monkeypatch.chdir(root)
    with pytest.raises(InputError) as caught:
        load_scene("output/teatime")
    assert str(caught.value) == (
        f"{root / 'lerf_ovs' / 'teatime'}: no cameras found: expected a COLMAP model (sparse/0/ "
        "or sparse/), transforms_train.json, transforms.json or cameras.json (the source named by "
        "output/teatime/cfg_args; --source decides, e.g. --source output/teatime/cameras.json)"
    )


def test_two_sources_fitting_cfg_args_stop_the_build(small_dataset, tmp_path, monkeypatch, capsys):
    """'teatime' fits the dataset linked beside the model and a folder in the working folder."""
    root = tmp_path / "work"
    write_langsplat_lerf(
        small_dataset, root, "teatime", source="/home/author/data/teatime", link=True
    )
    (root / "teatime").symlink_to(root / "lerf_ovs" / "teatime", target_is_directory=True)
    other = source_folder(root / "output" / "copy" / "teatime")
    monkeypatch.chdir(root / "output" / "copy")
    model = root / "output" / "teatime"
    code, out, err = run(["build", str(model), "-o", str(tmp_path / "f.thgs")], capsys)
    assert code == 2 and out == ""
    assert squeezed(f"2 folders fit it: {root / 'teatime'}, {other}; choose one with --source") in (
        squeezed(err)
    )
    assert not (tmp_path / "f.thgs").exists()


def test_two_label_folders_are_an_error_naming_both(small_dataset, small_field, tmp_path, capsys):
    root = tmp_path / "work"
    write_langsplat_lerf(small_dataset, root, "teatime", source="lerf_ovs/teatime", link=True)
    data = root / "lerf_ovs" / "teatime"
    (data / "label").symlink_to(small_dataset / "label", target_is_directory=True)
    # the same folder reached twice is one folder
    assert find_ground_truth(data).path("lerf") == data / "label"
    (data / "label").unlink()
    shutil.copytree(small_dataset / "label", data / "label")
    code, out, err = run(["eval", str(data), str(small_field)], capsys)
    assert code == 2 and out == ""
    assert squeezed(err) == squeezed(
        f"error: {data}: LERF-OVS labels (frame_*.json) in two places: {data / 'label'} and "
        f"{root / 'lerf_ovs' / 'label' / 'teatime'}; choose one with --labels (lerf= in Python)"
    )
    chosen = find_ground_truth(data, lerf=root / "lerf_ovs" / "label")
    assert chosen.path("lerf") == root / "lerf_ovs" / "label" / "teatime"


def test_labels_parent_without_the_scene(small_dataset, tmp_path):
    root = tmp_path / "work"
    write_langsplat_lerf(small_dataset, root, "teatime", source="lerf_ovs/teatime", link=True)
    (root / "lerf_ovs" / "label" / "ramen").mkdir()
    ramen = root / "lerf_ovs" / "ramen"
    ramen.mkdir()
    with pytest.raises(InputError) as caught:
        find_ground_truth(ramen, lerf=root / "lerf_ovs" / "label")
    assert str(caught.value) == (
        f"{root / 'lerf_ovs' / 'label'}: holds no LERF-OVS label files (frame_*.json), nor "
        "ramen/ or label/ramen/ with them (its folders: ramen, teatime; 'ramen' is the dataset "
        "folder's name); pass the folder of the scene's frame_*.json with --labels"
    )
    # the dataset root (lerf_ovs) works too: its label/<scene>
    found = find_ground_truth(root / "lerf_ovs" / "teatime", lerf=root / "lerf_ovs")
    assert found.path("lerf") == root / "lerf_ovs" / "label" / "teatime"


def test_the_scene_name_is_the_folder_as_named(small_dataset, tmp_path):
    """A link named teatime to a folder named otherwise is the scene teatime (its labels and
    OpenGaussian's prompts)."""
    (tmp_path / "lerf_ovs" / "label").mkdir(parents=True)
    (tmp_path / "lerf_ovs" / "teatime").symlink_to(small_dataset, target_is_directory=True)
    truth = find_ground_truth(tmp_path / "lerf_ovs" / "teatime")
    assert truth.scene_name == "teatime" and small_dataset.name != "teatime"
