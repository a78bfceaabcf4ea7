"""thgs.results: the query / pick / export workflows as library calls (the CLI tests check the
same files through the commands; these check the calls and their refusals)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from thgs import load_scene
from thgs.errors import InputError
from thgs.field import load_field
from thgs.query import FieldQuery, QueryConfig
from thgs.render import render
from thgs.results import (
    pick_summary,
    unique_names,
    write_pick_results,
    write_query_results,
    write_query_selections,
)
from thgs.scene import read_ply
from thgs.text import load_text_encoder
from thgs.views import pick


@pytest.fixture(scope="module")
def opened(small_dataset, small_field):
    field = load_field(small_field)
    return field, load_scene(small_dataset), load_text_encoder(field.space)


def test_unique_names_number_repeats():
    assert unique_names(["Mug!", "mug", "a/b", "", "mug"]) == [
        "mug",
        "mug-2",
        "a-b",
        "query",
        "mug-3",
    ]


def test_query_results_without_views_and_with_one(opened, tmp_path):
    field, scene, encoder = opened
    engine = FieldQuery(field, encoder, QueryConfig(mode="threshold", level=3))
    texts = ["mug", "xqzv blorf", "mug"]
    written = write_query_results(tmp_path / "a", engine, texts, field_name="f.thgs")
    results = json.loads(written.results.read_text())
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["results.json"]
    assert results["field"] == "f.thgs" and results["space"] == field.space
    assert results["config"]["threshold"] == engine.threshold
    assert [q["text"] for q in results["queries"]] == texts
    assert results["queries"][1]["regions"] == [] and written.selections[1].empty
    for entry, selection in zip(results["queries"], engine.select(texts)):
        assert entry["gaussians"] == int(selection.gaussians.sum())
        for region in entry["regions"]:
            assert region["gaussians"] == field.sizes(3)[region["region"]]
    camera = scene.cameras.select([1])
    written = write_query_results(
        tmp_path / "b", engine, ["mug"], field_name="f", gaussians=scene.gaussians, cameras=camera
    )
    assert written.files == {"mug": (tmp_path / "b" / "mug" / f"{camera.stems[0]}.png",)}
    assert json.loads(written.results.read_text())["queries"][0]["files"] == [
        str(written.files["mug"][0])
    ]


def test_query_results_refuse_what_cannot_be_drawn(opened, tmp_path):
    field, scene, encoder = opened
    engine = FieldQuery(field, encoder)
    with pytest.raises(InputError, match="at least one query"):
        write_query_results(tmp_path, engine, [], field_name="f")
    with pytest.raises(InputError, match="needs the scene's Gaussians"):
        write_query_results(tmp_path, engine, ["mug"], field_name="f", cameras=scene.cameras)
    with pytest.raises(InputError, match="pass the cameras"):
        write_query_results(tmp_path, engine, ["mug"], field_name="f", relevancy=True)
    assert not any(tmp_path.iterdir())


def test_query_selections_skip_empty_ones(opened, tmp_path):
    field, scene, encoder = opened
    engine = FieldQuery(field, encoder, QueryConfig(mode="threshold", level=3))
    selections, paths = write_query_selections(
        tmp_path, engine, ["mug", "xqzv blorf"], scene.gaussians, field_name="f"
    )
    assert [p.name for p in paths] == ["mug.ply", "selections.json"]
    assert len(read_ply(paths[0])) == int(selections[0].gaussians.sum())
    summary = json.loads(paths[1].read_text())
    assert summary["mode"] == "threshold" and "ply" not in summary["queries"][1]
    with pytest.raises(InputError, match="the field has"):
        write_query_selections(
            tmp_path, engine, ["mug"], scene.gaussians.select(torch.arange(3)), field_name="f"
        )


def test_pick_results_describe_the_region_chain(opened, tmp_path):
    field, scene, _ = opened
    camera = scene.cameras.select([0])
    ids = render(scene.gaussians, camera, torch.zeros(len(field), 1, dtype=torch.float64)).max_id
    rows, cols = np.nonzero(ids.numpy() >= 0)
    x, y = int(cols[rows.size // 2]), int(rows[rows.size // 2])
    picked = pick(field, scene.gaussians, camera, (x, y))
    for level in range(4):
        summary = pick_summary(field, picked, level)
        region = field.labels[picked.gaussian, level]
        assert summary["region"] == region and summary["gaussians"] == field.sizes(level)[region]
        assert summary["parent"] == (field.parent(level, region) if level < 3 else None)
        assert summary["children"] == (field.children(level, region).tolist() if level > 0 else [])
    written = write_pick_results(
        tmp_path, field, scene.gaussians, camera, picked, 1, field_name="f"
    )
    assert json.loads(written.json.read_text()) == written.summary
    assert written.summary["files"] == [str(written.mask), str(written.ply)]
    assert len(read_ply(written.ply)) == written.summary["gaussians"]
    with pytest.raises(InputError, match="must be one view, got 2"):
        write_pick_results(
            tmp_path,
            field,
            scene.gaussians,
            scene.cameras.select([0, 1]),
            picked,
            1,
            field_name="f",
        )
    with pytest.raises(InputError, match=r"level must be in 0\.\.3 here, got 4"):
        pick_summary(field, picked, 4)


def test_query_results_arrive_whole_or_not_at_all(opened, tmp_path, monkeypatch):
    import thgs.results

    field, scene, encoder = opened
    engine = FieldQuery(field, encoder)
    out = tmp_path / "answers"
    out.mkdir()
    (out / "mine.txt").write_text("kept")
    cameras = scene.cameras.select([0, 1, 2])
    real = thgs.results.write_mask_png
    calls = []

    def full_disk(path, mask):
        calls.append(path)
        if len(calls) == 4:
            raise OSError(28, "No space left on device", str(path))
        real(path, mask)

    monkeypatch.setattr(thgs.results, "write_mask_png", full_disk)
    with pytest.raises(OSError, match="No space left"):
        write_query_results(
            out, engine, ["mug", "table"], field_name="f", gaussians=scene.gaussians,
            cameras=cameras,
        )  # fmt: skip
    # three masks were written before the disk filled: none of them reached ``out``
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["answers"]  # no staging left behind
    monkeypatch.setattr(thgs.results, "write_mask_png", real)
    written = write_query_results(
        out, engine, ["mug", "table"], field_name="f", gaussians=scene.gaussians, cameras=cameras
    )
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt", "mug", "results.json", "table"]
    assert all(path.is_file() for paths in written.files.values() for path in paths)
    assert len(written.files["mug"]) == 3


def test_a_very_long_query_still_names_a_file(opened, tmp_path):
    from thgs.export import slug

    field, scene, encoder = opened
    long = "the mug on the table " * 500  # 10,500 characters
    name = slug(long)
    assert len(name) <= 80 and name.startswith("the-mug-on-the-table-the-mug")
    assert slug(long) == name and slug(long + "!") != name  # stable, and texts stay apart
    assert slug("Mug handle") == "mug-handle"  # short names are unchanged
    written = write_query_results(
        tmp_path / "q", FieldQuery(field, encoder), [long], field_name="f",
        gaussians=scene.gaussians, cameras=scene.cameras.select([0]),
    )  # fmt: skip
    assert written.files[name][0].is_file()
