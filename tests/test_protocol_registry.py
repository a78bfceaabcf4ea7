"""The protocol registry: a protocol added in one place (here, in a test) is found in a dataset,
offered by `thgs eval`, run by evaluate_dataset and tabulated by `thgs bench`, and the built-in
protocols are registered in report order with sources that find their ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

import thgs.eval.protocols as registry
from test_cli import run
from thgs.bench import BenchReport, VariantRun
from thgs.errors import InputError
from thgs.eval import ProtocolResult, evaluate_dataset, find_ground_truth
from thgs.eval.protocols import GroundTruthSource, Protocol, protocol_names
from thgs.field_scene import open_field_scene
from thgs.query import FieldQuery
from thgs.text import load_text_encoder


def _count_selected(context):
    """The toy protocol: the share of Gaussians each listed text selects."""
    texts = context.ground_truth.read_text().split()
    selected = context.engine.selected(texts)
    items = [{"prompt": t, "share": float(selected[:, q].mean())} for q, t in enumerate(texts)]
    if context.progress is not None:
        context.progress(1, 1)
    return [ProtocolResult("toy", {"share": float(selected.mean())}, items, {})]


@pytest.fixture
def toy(monkeypatch):
    """A fresh copy of the registry with a toy source and protocol added, as a new module would."""
    monkeypatch.setattr(registry, "_SOURCES", dict(registry._SOURCES))
    monkeypatch.setattr(registry, "_PROTOCOLS", dict(registry._PROTOCOLS))
    registry.register_source(
        GroundTruthSource("toy", lambda d: d / "toy.txt" if (d / "toy.txt").is_file() else None, "")
    )
    return registry.register_protocol(
        Protocol("toy", "a test", "toy", False, (("toy", "share"),), _count_selected)
    )


def test_built_ins_in_report_order():
    assert protocol_names() == (
        "lerf",
        "lerf-langsplat",
        "lerf-opengaussian",
        "3dovs",
        "scannet",
        "openhype",
        "hierarchy",
    )
    assert registry.source_names() == ("lerf", "three_dovs", "scannet", "openhype", "hierarchy")
    needs_cameras = [registry.get_protocol(n).needs_cameras for n in protocol_names()]
    assert needs_cameras == [True, True, True, True, False, True, False]


def test_sources_find_a_synthetic_datasets_ground_truth(small_dataset):
    found = find_ground_truth(small_dataset)
    assert found.paths == {
        "lerf": small_dataset / "label",
        "three_dovs": small_dataset / "segmentations",
        "scannet": small_dataset / "scannet" / "synthetic_vh_clean_2.labels.ply",
        "hierarchy": small_dataset / "ground_truth.safetensors",
    }
    assert found.available() == tuple(name for name in protocol_names() if name != "openhype")
    with pytest.raises(InputError, match="unknown kind 'labels'"):
        find_ground_truth(small_dataset, labels=small_dataset)


@pytest.mark.slow
def test_a_registered_protocol_runs_everywhere(toy, small_dataset, small_field, tmp_path, capsys):
    dataset = tmp_path / "toyset"
    dataset.mkdir()
    (dataset / "toy.txt").write_text("table chair")
    ground_truth = find_ground_truth(dataset)
    assert ground_truth.available() == ("toy",)

    field, scene = open_field_scene(small_field)
    engine = FieldQuery(field, load_text_encoder(field.space))
    report = evaluate_dataset(ground_truth, engine, scene.gaussians, None)
    expected = engine.selected(["table", "chair"])
    assert report.metric("toy", "share") == pytest.approx(float(expected.mean()))
    assert [item["prompt"] for item in report.results[0].items] == ["table", "chair"]
    assert report.info["ground_truth"]["toy"] == str(dataset / "toy.txt")

    out = tmp_path / "toy.json"
    code, _, err = run(
        ["eval", str(dataset), str(small_field), "--protocol", "toy", "-o", str(out)], capsys
    )
    assert code == 0, err
    results = json.loads(out.read_text())["results"]
    assert [r["protocol"] for r in results] == ["toy"]
    assert results[0]["metrics"]["share"] == pytest.approx(float(expected.mean()))

    # thgs bench's table takes its columns from the registry's headline metrics
    bench = BenchReport(
        runs=(
            VariantRun(
                preset="p", seed=0, variant="full", kind="2dgs", severity=0.5,
                stand_in="name-perfect",
                gaussians=1, views=1, stages={"lift": 1.0},
                lift_shared=False, seconds=1.0, peak_gib=0.1, gpu_peak_gib=None,
                region_counts=(1, 1, 1, 1), quality={"toy share": 0.25}, evaluation_seconds=0.0,
            ),
        ),
        machine={"processor": "x", "cpus": 2, "torch_threads": 2, "cuda": None},
        config={},
    )  # fmt: skip
    assert "| toy share |" in bench.markdown() and "| 0.250 |" in bench.markdown()


def test_unknown_protocols_are_refused_before_loading(small_dataset, tmp_path, capsys):
    argv = ["eval", str(small_dataset), str(tmp_path / "missing.thgs"), "--protocol", "lerff"]
    code, _, err = run(argv, capsys)
    assert code == 2 and "unknown 'lerff'; choose from lerf, lerf-langsplat" in err
    with pytest.raises(InputError, match="unknown 'nope'"):
        evaluate_dataset(
            find_ground_truth(small_dataset), None, np.zeros(1), None, protocols=["nope"]
        )


def test_registering_twice_or_without_a_source_fails(toy):
    with pytest.raises(ValueError, match="already registered"):
        registry.register_protocol(toy)
    with pytest.raises(ValueError, match="unknown source 'nowhere'"):
        registry.register_protocol(Protocol("x", "", "nowhere", False, (), _count_selected))
