"""The suite's report: per-scene and mean numbers per benchmark in the paper's table shape, the
field-building time of every scene, the failed scenes and the settings.

:func:`write_suite_report` writes ``report.json`` (everything), ``report.md`` (the tables) and
``report.png`` (a bar chart of each benchmark's headline metric and of the build times; left out,
and said so in the report, when matplotlib is not installed), each atomically.

The tables (values in percent in ``report.md``, in [0, 1] in ``report.json``):

- LERF-OVS (the paper's Table 1): mIoU and localization accuracy under the chosen selection
  (``lerf``), under the paper's rule (``lerf-paper``), and LangSplat's 2D rule;
- 3D-OVS (Table 2): mIoU and accuracy;
- ScanNet (Table 4): mIoU and mAcc over 19, 15 and 10 classes;
- OpenHype's ScanNet++: mIoU over all, object and part prompts under the chosen selection
  (``openhype``), mIoU under the paper's rule (``openhype-paper``), and localization accuracy;
- synthetic: mIoU per hierarchy level, LERF-OVS and 3D-OVS mIoU.

Every timing is kept under ``report.json``'s ``"timings"``, and what ran (which stage ran or was
current, in-process or on Ray) under ``"run"``; :meth:`SuiteReport.comparable` leaves both out,
so that two runs on the same inputs compare equal however they ran.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from thgs._atomic import atomic_output
from thgs.export import write_json
from thgs.suite.discover import BENCHMARKS

__all__ = [
    "HEADLINES",
    "SceneResult",
    "SuiteReport",
    "build_stage_group",
    "write_suite_report",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SceneResult:
    """What became of one scene.

    Attributes:
        benchmark, name: the scene.
        stages: stage → ``"ran"``, ``"current"``, ``"not needed"``, ``"failed"`` or
            ``"not run"``.
        metrics: result name (``lerf``, ``lerf-paper``, ``3dovs``, ``scannet-19`` …) → metric →
            value in [0, 1] (None where a protocol gives none), from ``eval.json``.
        regions: the field's region counts at levels 0–3.
        build_seconds: the field's build time per stage (``lift``, ``knn`` …), as recorded
            when it was built.
        seconds: wall time per stage (preprocess, build, eval), as recorded when it ran.
        error: the one-line reason a failed scene failed; None when it succeeded.
    """

    benchmark: str
    name: str
    stages: dict[str, str]
    metrics: dict[str, dict[str, float | None]] = field(default_factory=dict)
    regions: tuple[int, ...] = ()
    build_seconds: dict[str, float] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    error: str | None = None

    @property
    def key(self) -> str:
        return f"{self.benchmark}/{self.name}"

    @property
    def ok(self) -> bool:
        return self.error is None


HEADLINES: dict[str, tuple[tuple[str, str, str], ...]] = {
    "lerf_ovs": (
        ("lerf", "miou", "mIoU ({selection})"),
        ("lerf", "accuracy", "acc ({selection})"),
        ("lerf-paper", "miou", "mIoU (paper's rule)"),
        ("lerf-paper", "accuracy", "acc (paper's rule)"),
        ("lerf-langsplat", "miou", "mIoU (LangSplat 2D)"),
        ("lerf-langsplat", "localization", "loc (LangSplat 2D)"),
    ),
    "3dovs": (("3dovs", "miou", "mIoU ({selection})"), ("3dovs", "accuracy", "acc")),
    "scannet": tuple(
        (f"scannet-{n}", metric, f"{label} {n}")
        for n in (19, 15, 10, "all")
        for metric, label in (("miou", "mIoU"), ("macc", "mAcc"))
    ),
    "openhype": (
        ("openhype", "miou", "mIoU ({selection})"),
        ("openhype", "miou_objects", "object mIoU ({selection})"),
        ("openhype", "miou_parts", "part mIoU ({selection})"),
        ("openhype-paper", "miou", "mIoU (paper's rule)"),
        ("openhype-paper", "miou_parts", "part mIoU (paper's rule)"),
        ("openhype", "localization", "loc ({selection})"),
    ),
    "synthetic": (
        ("hierarchy", "miou_subpart", "sub-part mIoU"),
        ("hierarchy", "miou_part", "part mIoU"),
        ("hierarchy", "miou_object", "object mIoU"),
        ("lerf", "miou", "LERF mIoU ({selection})"),
        ("lerf-paper", "miou", "LERF mIoU (paper's rule)"),
        ("3dovs", "miou", "3D-OVS mIoU"),
    ),
}
"""Each benchmark's table columns: ``(result, metric, label)``; ``{selection}`` in a label is the
chosen selection mode. A report shows the columns that some scene has a value for (ScanNet's
``scannet-all`` is scored instead of the 19/15/10-class subsets when the labels are not NYU40's,
as in synthetic scenes)."""

_TITLES = {
    "lerf_ovs": "LERF-OVS",
    "3dovs": "3D-OVS",
    "scannet": "ScanNet",
    "openhype": "OpenHype ScanNet++",
    "synthetic": "synthetic",
}

_BUILD_GROUPS = ("lift", "graph", "partition", "merge", "features")


def build_stage_group(stage: str) -> str:
    """The column of the build-time table a field build stage
    (:attr:`thgs.field.SemanticField.timings`) is counted in: ``lift``; ``graph`` (KNN, votes,
    reweighting); ``partition``; ``merge`` (adjacency, levels, absorbing, repeated parts);
    ``features``."""
    if stage in ("knn", "votes", "reweight"):
        return "graph"
    if stage in ("lift", "partition", "features"):
        return stage
    return "merge"


def _mean(values: Sequence[float | None]) -> float | None:
    present = [value for value in values if value is not None and math.isfinite(value)]
    return sum(present) / len(present) if present else None


@dataclass(frozen=True)
class SuiteReport:
    """The results of a suite.

    Attributes:
        scenes: one :class:`thgs.suite.SceneResult` per scene, in suite order.
        settings: :meth:`thgs.suite.SuiteConfig.to_json`.
        field_configs: benchmark → the field config its scenes were built with.
        executor: ``"in-process"`` or ``"ray"``.
        seconds: the suite's wall time.
        notes: lines added below the tables (e.g. why there is no plot).
    """

    scenes: tuple[SceneResult, ...]
    settings: dict[str, Any]
    field_configs: dict[str, Any]
    executor: str
    seconds: float
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def failed(self) -> tuple[SceneResult, ...]:
        """The scenes that failed."""
        return tuple(scene for scene in self.scenes if not scene.ok)

    def benchmarks(self) -> tuple[str, ...]:
        """The benchmarks with scenes, in report order."""
        present = {scene.benchmark for scene in self.scenes}
        return tuple(name for name in BENCHMARKS if name in present)

    def columns(self, benchmark: str) -> list[tuple[str, str, str]]:
        """``(result, metric, label)`` of ``benchmark``'s table, the labels filled in: the
        :data:`HEADLINES` that some scene of the benchmark has a value for (all of them when
        none has any, e.g. every scene failed)."""
        selection = self.settings.get("selection", "auto")
        columns = [
            (result, metric, label.format(selection=selection))
            for result, metric, label in HEADLINES[benchmark]
        ]
        scenes = [scene for scene in self.scenes if scene.benchmark == benchmark]
        present = [
            column
            for column in columns
            if any(scene.metrics.get(column[0], {}).get(column[1]) is not None for scene in scenes)
        ]
        return present or columns

    def table(self, benchmark: str) -> dict[str, Any]:
        """``benchmark``'s table: ``columns`` (labels), ``rows`` (one per scene: name and values,
        None where missing or failed) and ``mean`` (over the scenes that have the value)."""
        columns = self.columns(benchmark)
        rows = []
        for scene in self.scenes:
            if scene.benchmark != benchmark:
                continue
            values = [scene.metrics.get(result, {}).get(metric) for result, metric, _ in columns]
            rows.append({"scene": scene.name, "values": values, "ok": scene.ok})
        mean = [_mean([row["values"][i] for row in rows if row["ok"]]) for i in range(len(columns))]
        return {
            "columns": [label for _, _, label in columns],
            "keys": [[result, metric] for result, metric, _ in columns],
            "rows": [{"scene": row["scene"], "values": row["values"]} for row in rows],
            "mean": mean,
        }

    def build_times(self, scene: SceneResult) -> dict[str, float]:
        """A scene's build time per column of the build-time table (:func:`build_stage_group`)
        and ``total``, in seconds."""
        groups = dict.fromkeys(_BUILD_GROUPS, 0.0)
        for stage, seconds in scene.build_seconds.items():
            groups[build_stage_group(stage)] += seconds
        return {"total": sum(scene.build_seconds.values()), **groups}

    def to_json(self) -> dict[str, Any]:
        """The whole report as JSON values."""
        return {
            "format": "thgs.suite",
            "version": 1,
            "tables": {benchmark: self.table(benchmark) for benchmark in self.benchmarks()},
            "scenes": [
                {
                    "benchmark": scene.benchmark,
                    "name": scene.name,
                    "ok": scene.ok,
                    "error": scene.error,
                    "metrics": scene.metrics,
                    "regions": list(scene.regions),
                }
                for scene in self.scenes
            ],
            "failed": [{"scene": scene.key, "error": scene.error} for scene in self.failed],
            "settings": self.settings,
            "field_configs": self.field_configs,
            "notes": list(self.notes),
            "timings": {
                "suite": self.seconds,
                "scenes": {
                    scene.key: {
                        "stages": scene.seconds,
                        "build": scene.build_seconds,
                        "build_groups": self.build_times(scene),
                    }
                    for scene in self.scenes
                },
            },
            "run": {
                "executor": self.executor,
                "stages": {scene.key: scene.stages for scene in self.scenes},
            },
        }

    def comparable(self) -> dict[str, Any]:
        """:meth:`to_json` without ``"timings"`` and ``"run"``: equal for two runs on the same
        inputs, in-process or on Ray, fresh or resumed."""
        document = self.to_json()
        del document["timings"], document["run"]
        return document

    def markdown(self) -> str:
        """The tables: one per benchmark (rows scenes and the mean, values in percent), the
        build times, the failed scenes, the settings and the notes."""
        lines: list[str] = ["# thgs suite", ""]
        for benchmark in self.benchmarks():
            table = self.table(benchmark)
            lines += [f"## {_TITLES[benchmark]}", ""]
            lines.append("| scene | " + " | ".join(table["columns"]) + " |")
            lines.append("|---" * (len(table["columns"]) + 1) + "|")
            for row in table["rows"]:
                lines.append(
                    f"| {row['scene']} | " + " | ".join(map(_percent, row["values"])) + " |"
                )
            lines.append("| **mean** | " + " | ".join(map(_percent, table["mean"])) + " |")
            lines.append("")
        lines += ["## Times (s): field building by stage, preprocessing, evaluation", ""]
        lines.append("| scene | total | " + " | ".join(_BUILD_GROUPS) + " | preprocess | eval |")
        lines.append("|---" * (len(_BUILD_GROUPS) + 4) + "|")
        for scene in self.scenes:
            if not scene.ok:
                continue
            times = self.build_times(scene)
            cells = [f"{times[name]:.2f}" for name in ("total", *_BUILD_GROUPS)]
            cells += [_seconds(scene.seconds.get(stage)) for stage in ("preprocess", "eval")]
            lines.append(f"| {scene.key} | " + " | ".join(cells) + " |")
        lines.append("")
        if self.failed:
            lines += [f"## Failed ({len(self.failed)} of {len(self.scenes)})", ""]
            lines += [f"- {scene.key}: {scene.error}" for scene in self.failed]
            lines.append("")
        lines += ["## Settings", ""]
        settings = self.settings
        lines.append(f"- field config: {_field_setting(settings)}")
        lines.append(f"- selection: {settings['selection']}; device: {settings['device']}")
        lines.append(
            f"- preprocessing (scenes without language features): SAM {settings['sam']}, "
            f"CLIP {settings['clip']}"
        )
        ran = sum("ran" in scene.stages.values() for scene in self.scenes)
        lines.append(
            f"- run: {self.executor}, {self.seconds:.1f} s; {ran} of {len(self.scenes)} scenes "
            "ran a stage, the others were current"
        )
        lines += [f"- {note}" for note in self.notes]
        return "\n".join(lines) + "\n"


def _field_setting(settings: dict[str, Any]) -> str:
    if settings.get("config") is not None:
        base = "the config given (--config)"
    elif settings.get("preset") is not None:
        base = f"preset {settings['preset']}"
    else:
        base = "each benchmark's preset (3dovs for 3D-OVS, lerf otherwise)"
    changed = settings.get("settings") or []
    return base + (f", --set {' '.join(changed)}" if changed else "")


def _percent(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.1f}"


def _seconds(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        return None
    matplotlib.use("Agg")
    from matplotlib import pyplot

    return pyplot


_NO_PLOT = "report.png not drawn: matplotlib is not installed (pip install 'thgs[bench]')"


def _plot(report: SuiteReport, path: Path, pyplot) -> None:
    benchmarks = report.benchmarks()
    figure, axes = pyplot.subplots(
        1, len(benchmarks) + 1, figsize=(4 * (len(benchmarks) + 1), 3.5), squeeze=False
    )
    for axis, benchmark in zip(axes[0], benchmarks):
        table = report.table(benchmark)
        names = [row["scene"] for row in table["rows"]] + ["mean"]
        values = [row["values"][0] for row in table["rows"]] + [table["mean"][0]]
        axis.bar(names, [0.0 if v is None else 100 * v for v in values], color="tab:blue")
        axis.set_title(f"{_TITLES[benchmark]}: {table['columns'][0]}")
        axis.set_ylim(0, 100)
        axis.tick_params(axis="x", rotation=45)
    axis = axes[0][-1]
    done = [scene for scene in report.scenes if scene.ok]
    bottom = [0.0] * len(done)
    for group in _BUILD_GROUPS:
        heights = [report.build_times(scene)[group] for scene in done]
        axis.bar([scene.key for scene in done], heights, bottom=bottom, label=group)
        bottom = [b + h for b, h in zip(bottom, heights)]
    axis.set_title("field-building time (s)")
    axis.legend(fontsize="small")
    axis.tick_params(axis="x", rotation=45)
    figure.tight_layout()
    with atomic_output(path, "wb") as handle:
        figure.savefig(handle, format="png", dpi=100)
    pyplot.close(figure)


def write_suite_report(
    out: str | os.PathLike[str], report: SuiteReport
) -> tuple[SuiteReport, tuple[Path, ...]]:
    """Write ``report.json``, ``report.md`` and ``report.png`` into ``out``, each atomically.

    Returns:
        the report with a note when the plot could not be drawn (matplotlib missing), and the
        files written.
    """
    out = Path(out)
    pyplot = _pyplot()
    if pyplot is None:
        logger.warning(_NO_PLOT)
        report = replace(report, notes=(*report.notes, _NO_PLOT))
    write_json(out / "report.json", report.to_json())
    with atomic_output(out / "report.md", "w") as handle:
        handle.write(report.markdown())
    paths = [out / "report.json", out / "report.md"]
    if pyplot is not None and report.scenes:
        _plot(report, out / "report.png", pyplot)
        paths.append(out / "report.png")
    return report, tuple(paths)
