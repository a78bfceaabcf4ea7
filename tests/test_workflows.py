"""The library's user actions (:mod:`thgs.workflows`): the same files as the commands that call
them, written whole or not at all, and the query options checked together."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

import thgs
from conftest import run_cli
from thgs.errors import InputError
from thgs.eval.dataset import find_ground_truth
from thgs.field import load_field
from thgs.pipeline import FieldConfig
from thgs.query import QueryConfig
from thgs.workflows import (
    BuildRequest,
    EvalRequest,
    ExportRequest,
    build_field_file,
    evaluate_field_file,
    export_field_file,
    query_config,
)


@pytest.mark.slow
def test_the_library_build_writes_the_commands_bytes(small_dataset, small_field, tmp_path):
    out = tmp_path / "library.thgs"
    built = build_field_file(BuildRequest(small_dataset, out, FieldConfig.lerf(), device="cpu"))
    assert built.path == out and built.space == load_field(small_field).space
    assert built.field.region_counts == load_field(out).region_counts
    assert sum(built.field.timings.values()) > 0  # the build's own timer, not in the file
    assert load_field(out).provenance == built.field.provenance
    assert built.field.provenance.thgs_version == thgs.__version__
    assert built.field.provenance.scene.path == os.path.relpath(small_dataset, tmp_path)
    # the same inputs and settings as `thgs build` (the fixture): the same field, its scene
    # recorded relative to the file, so a copy beside the command's is byte-identical
    copy = small_field.with_name("library-copy.thgs")
    build_field_file(BuildRequest(small_dataset, copy, FieldConfig.lerf(), device="cpu"))
    assert copy.read_bytes() == small_field.read_bytes()
    copy.unlink()


def test_a_build_request_is_refused_before_any_work(small_dataset, tmp_path):
    def request(**options) -> BuildRequest:
        return BuildRequest(small_dataset, tmp_path / "f.thgs", FieldConfig.lerf(), **options)

    (tmp_path / "cache-file").write_text("x")
    with pytest.raises(InputError, match=r"^--lift-cache: .*cache-file is a file"):
        build_field_file(request(lift_cache=tmp_path / "cache-file"))
    with pytest.raises(InputError, match=r"^--text-model: .*nowhere is not a folder"):
        build_field_file(request(text_model=tmp_path / "nowhere"))
    with pytest.raises(InputError, match="language features folder not found"):
        build_field_file(request(guidance=tmp_path / "none"))
    assert sorted(os.listdir(tmp_path)) == ["cache-file"]


def test_the_evaluation_writes_its_report_and_table_together(
    small_dataset, small_field, tmp_path, capsys
):
    out = tmp_path / "library.json"
    request = EvalRequest(small_dataset, small_field, out, protocols=("hierarchy",), device="cpu")
    outcome = evaluate_field_file(request, find_ground_truth(small_dataset))
    assert (outcome.json_path, outcome.table_path) == (out, tmp_path / "library.md")
    document = json.loads(out.read_text())
    assert document["info"]["field"] == str(small_field)
    assert document["info"]["dataset"] == str(small_dataset)
    assert outcome.table_path.read_text() == outcome.report.table() + "\n"

    command = tmp_path / "command.json"
    argv = ["eval", str(small_dataset), str(small_field), "--protocol", "hierarchy"]
    code, _, _ = run_cli([*argv, "-o", str(command), "--device", "cpu"], capsys)
    assert code == 0
    assert command.with_suffix(".md").read_bytes() == outcome.table_path.read_bytes()
    assert {**json.loads(command.read_text()), "seconds": None} == {**document, "seconds": None}

    # the table cannot be written (a folder holds its name): neither file is
    blocked = tmp_path / "blocked.json"
    (tmp_path / "blocked.md").mkdir()
    with pytest.raises(OSError):
        evaluate_field_file(
            EvalRequest(small_dataset, small_field, blocked, protocols=("hierarchy",)),
            find_ground_truth(small_dataset),
        )
    assert not blocked.exists()


def test_an_export_is_whole_or_absent(small_field, tmp_path, monkeypatch):
    request = ExportRequest(small_field, tmp_path / "x", color_level=2, labels=True)
    outcome = export_field_file(request)
    assert [p.name for p in outcome.files] == ["regions-part.ply", "labels.npy", "labels.json"]
    labels = np.load(tmp_path / "x" / "labels.npy")
    assert np.array_equal(labels, outcome.field.labels)

    import thgs.export

    def fail(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(thgs.export, "write_labels", fail)
    with pytest.raises(OSError):
        export_field_file(ExportRequest(small_field, tmp_path / "y", color_level=1, labels=True))
    assert not (tmp_path / "y").exists()  # the region PLY written first is gone, and the folder


def test_nothing_to_export_and_a_bad_level_are_named(small_field, tmp_path):
    with pytest.raises(InputError, match="nothing to export"):
        export_field_file(ExportRequest(small_field, tmp_path / "x"))
    with pytest.raises(InputError, match=r"^--color-level: must be 0, 1, 2 or 3, got 4"):
        export_field_file(ExportRequest(small_field, tmp_path / "x", color_level=4))
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(
    ("options", "expected"),
    [
        ({}, QueryConfig(mode="auto")),
        ({"level": 2}, QueryConfig(mode="level", level=2)),
        ({"mode": "threshold", "threshold": 0.6}, QueryConfig(mode="threshold", threshold=0.6)),
        ({"mode": "paper"}, QueryConfig(mode="paper")),
        ({"mode": "level", "top": 3}, QueryConfig(mode="level", level=3, top=3)),
        ({"threshold": 0.7}, QueryConfig(mode="auto", min_relevancy=0.7)),
    ],
)
def test_query_options_become_a_query_config(options, expected):
    assert query_config(**options) == expected


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"level": 4}, "--level: must be 1 sub-parts, 2 parts or 3 objects, got 4"),
        ({"mode": "auto", "level": 2}, "--level: the auto mode searches levels 1–3"),
        ({"mode": "paper", "level": 2}, "--level: the paper mode searches levels 2 and 3"),
        ({"top": 0}, "--top: must be ≥ 1, got 0"),
        ({"mode": "threshold", "threshold": 2.0}, "--threshold: must be in [0, 1], got 2.0"),
        ({"min_gaussians": -1}, "--min-gaussians: must be ≥ 0, got -1"),
        ({"mode": "paper", "threshold": 0.5}, "--threshold: the paper mode uses no threshold"),
        ({"level": 2, "threshold": 0.5}, "--threshold: the level mode uses no threshold"),
        ({"threshold": 1.5}, "--threshold: must be in [0, 1], got 1.5"),
    ],
)
def test_contradicting_query_options_are_named(options, message):
    with pytest.raises(InputError) as caught:
        query_config(**options)
    assert str(caught.value).startswith(message)
