"""thgs bench's report across scenarios: the selection table's cells, means and worst cells
against hand-computed values; the scenario grid and its refusals."""

from __future__ import annotations

import pytest

from thgs.bench import BenchConfig, BenchReport, VariantRun
from thgs.errors import InputError


def _run(seed, kind, stand_in, auto, paper, variant="full"):
    return VariantRun(
        preset="synth-small", seed=seed, variant=variant, kind=kind, severity=0.5,
        stand_in=stand_in, gaussians=1, views=1, stages={"lift": 1.0}, lift_shared=False,
        seconds=1.0, peak_gib=0.1, gpu_peak_gib=None, region_counts=(4, 3, 2, 1),
        quality={"lerf miou": auto, "lerf-paper miou": paper, "3dovs miou": 0.9},
        evaluation_seconds=0.0,
    )  # fmt: skip


def test_selection_cells_average_seeds_and_report_mean_and_worst():
    runs = (
        _run(0, "2dgs", "name-perfect", 0.9, 0.5),
        _run(1, "2dgs", "name-perfect", 0.7, 0.5),  # (2dgs, name-perfect): automatic 0.8
        _run(0, "3dgs", "clip-like", 0.4, 0.6),  # (3dgs, clip-like): automatic 0.4 < paper 0.6
        _run(0, "3dgs", "clip-like", 0.1, 0.1, variant="instance level only"),  # not the method
    )
    config = {"seeds": (0, 1), "kinds": ("2dgs", "3dgs"), "severities": (0.5,)}
    report = BenchReport(runs, {"processor": "x", "cpus": 2, "torch_threads": 2, "cuda": None},
                         {**config, "stand_ins": ("name-perfect", "clip-like")})  # fmt: skip
    cells = report.selection_cells()
    assert [(c["kind"], c["stand_in"], c["seeds"]) for c in cells] == [
        ("2dgs", "name-perfect", 2),
        ("3dgs", "clip-like", 1),
    ]
    assert cells[0]["lerf miou"] == pytest.approx(0.8) and cells[1]["lerf-paper miou"] == 0.6
    markdown = report.markdown()
    assert "| synth-small | 2dgs | 0.5 | name-perfect | 0.800 | 0.500 | 0.900 |" in markdown
    assert "stand-ins name-perfect, clip-like" in markdown
    assert "| mean | | | | 0.600 | 0.550 | 0.900 |" in markdown
    assert "| worst cell | | | | 0.400 | 0.500 | 0.900 |" in markdown
    assert "≥ the paper's in 1 of 2 cells" in markdown
    assert report.to_json()["selection"][1]["lerf miou"] == pytest.approx(0.4)


def test_scenarios_are_the_grid_and_bad_axes_are_refused():
    config = BenchConfig(presets=("synth-small",), kinds=("2dgs", "3dgs"), severities=(0, 1.0))
    n, c = "name-perfect", "clip-like"
    assert config.check().scenarios() == [
        ("2dgs", 0, n), ("2dgs", 0, c), ("2dgs", 1.0, n), ("2dgs", 1.0, c),
        ("3dgs", 0, n), ("3dgs", 0, c), ("3dgs", 1.0, n), ("3dgs", 1.0, c),
    ]  # fmt: skip
    bad_axes = (
        ({"kinds": ("4dgs",)}, "^kinds: must be 2dgs or 3dgs"),
        ({"severities": (-1.0,)}, "^severities: must be ≥ 0"),
        ({"stand_ins": ("clip-lik",)}, "^stand_ins: unknown 'clip-lik'"),
        ({"stand_ins": ("clip-like:surroundings=2",)}, r"^stand_ins: 'clip-like:surroundings=2': "),
    )
    for bad, message in bad_axes:
        with pytest.raises(InputError, match=message):
            BenchConfig(presets=("synth-small",), **bad).check()
    with pytest.raises(InputError, match="at least one kind"):
        BenchConfig(presets=("synth-small",), stand_ins=()).check()
