"""What ``thgs bench`` reports: every run, its means over seeds as markdown tables, the
paper's orderings, a plot of the stages, and the three files written together."""

from __future__ import annotations

import itertools
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from thgs._atomic import atomic_files, atomic_output
from thgs.bench.variants import ORDERINGS
from thgs.errors import InputError, ThgsError
from thgs.eval.protocols import get_protocol, protocol_names
from thgs.export import write_json

__all__ = ["BenchReport", "VariantRun", "require_matplotlib", "write_bench"]


@dataclass(frozen=True)
class VariantRun:
    """One variant built and scored on one scene.

    Attributes:
        preset, seed, variant: what was built.
        kind, severity, stand_in: the scene's scenario (:attr:`BenchConfig.scenarios`).
        gaussians, views: scene size.
        stages: seconds per stage, ``lift`` first (see :func:`thgs.pipeline.build_field`).
        lift_shared: the lifting was run once and shared with other variants of this scene.
        seconds: the build's total (sum of ``stages``).
        peak_gib: peak resident memory of the process during lifting or building, GiB.
        gpu_peak_gib: peak allocated CUDA memory, GiB (None on CPU).
        region_counts: regions at levels 0–3.
        quality: ``"<protocol> <metric>"`` → value in [0, 1].
        evaluation_seconds: time spent scoring (not in ``seconds``).
    """

    preset: str
    seed: int
    variant: str
    kind: str
    severity: float
    stand_in: str
    gaussians: int
    views: int
    stages: dict[str, float]
    lift_shared: bool
    seconds: float
    peak_gib: float
    gpu_peak_gib: float | None
    region_counts: tuple[int, int, int, int]
    quality: dict[str, float]
    evaluation_seconds: float


def _stage_mean(group: Sequence[VariantRun], names: Sequence[str]) -> float:
    """Mean over the runs of ``group`` of their seconds summed over the stages ``names``."""
    return float(np.mean([sum(run.stages.get(name, 0.0) for name in names) for run in group]))


@dataclass(frozen=True)
class BenchReport:
    """Every :class:`VariantRun` of one ``thgs bench``, and the machine it ran on."""

    runs: tuple[VariantRun, ...]
    machine: dict[str, Any]
    config: dict[str, Any]

    def groups(self) -> dict[tuple[str, str], list[VariantRun]]:
        """The runs of each (preset, variant) — one per seed — in the order they ran."""
        groups: dict[tuple[str, str], list[VariantRun]] = {}
        for run in self.runs:
            groups.setdefault((run.preset, run.variant), []).append(run)
        return groups

    def mean(self, preset: str, variant: str, key: str) -> float:
        """Mean over seeds of a quality value (``"lerf miou"``) or ``"seconds"``/``"peak_gib"``."""
        values = [
            float(getattr(run, key))
            if key in ("seconds", "peak_gib", "evaluation_seconds")
            else run.quality.get(key, float("nan"))
            for run in self.groups().get((preset, variant), [])
        ]
        return float(np.mean(values)) if values else float("nan")

    def orderings(self) -> list[tuple[str, tuple[str, ...], tuple[float, ...], bool]]:
        """Per preset and paper ordering: (preset, variants, their mean LERF mIoU, holds)."""
        checks = []
        presets = list(dict.fromkeys(run.preset for run in self.runs))
        variants = {run.variant for run in self.runs}
        for preset in presets:
            for chain in ORDERINGS:
                if not all(v in variants for v in chain):
                    continue
                scores = tuple(self.mean(preset, v, "lerf-paper miou") for v in chain)
                holds = all(a > b for a, b in itertools.pairwise(scores))
                checks.append((preset, chain, scores, holds))
        return checks

    def selection_cells(self, variant: str = "full") -> list[dict[str, Any]]:
        """Per (preset, kind, severity, stand-in), the means over seeds of ``variant``'s
        LERF mIoU under the automatic selection (``lerf``) and the paper's (``lerf-paper``),
        and its 3D-OVS mIoU: the selection rule measured across scenarios."""
        cells: dict[tuple[str, str, float, str], list[VariantRun]] = {}
        for run in self.runs:
            if run.variant == variant:
                key = (run.preset, run.kind, run.severity, run.stand_in)
                cells.setdefault(key, []).append(run)
        rows = []
        for (preset, kind, severity, spec), group in cells.items():
            row: dict[str, Any] = {
                "preset": preset,
                "kind": kind,
                "severity": severity,
                "stand_in": spec,
                "seeds": len(group),
            }
            for key in ("lerf miou", "lerf-paper miou", "3dovs miou"):
                row[key] = float(np.mean([r.quality.get(key, float("nan")) for r in group]))
            rows.append(row)
        return rows

    def to_json(self) -> dict[str, Any]:
        def finite(values: Mapping[str, Any]) -> dict[str, Any]:
            return {
                k: None if isinstance(v, float) and not np.isfinite(v) else v
                for k, v in values.items()
            }

        return {
            "machine": self.machine,
            "config": json.loads(json.dumps(self.config, default=str)),
            "runs": [
                {**asdict(run), "quality": finite(run.quality), "region_counts": run.region_counts}
                for run in self.runs
            ],
            "orderings": [
                {"preset": p, "variants": list(c), "lerf_miou": list(s), "holds": h}
                for p, c, s, h in self.orderings()
            ],
            "selection": [finite(cell) for cell in self.selection_cells()],
        }

    def markdown(self) -> str:
        """Two tables (time and memory; quality), means over seeds, and the ordering checks."""
        seeds = len(self.config.get("seeds", (0,)))
        lines = [
            f"Machine: {self.machine['processor']}, {self.machine['cpus']} CPUs, torch threads "
            f"{self.machine['torch_threads']}, CUDA: {self.machine['cuda'] or 'none'}. "
            f"Means over {seeds} seed(s) and every scenario (kinds "
            f"{', '.join(self.config.get('kinds', ('2dgs',)))}, severities "
            f"{', '.join(f'{v:g}' for v in self.config.get('severities', (0.5,)))}, stand-ins "
            f"{', '.join(self.config.get('stand_ins', ('name-perfect',)))}).",
            "",
            "| preset | variant | total s | lift s | partition s | merge s | features s "
            "| peak GiB | regions L0 / L1 / L2 / L3 |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        groups = self.groups()
        for (preset, variant), group in groups.items():
            stages = group[0].stages
            merge = [
                s for s in stages if s in ("adjacency", "split", "absorb") or s.startswith("level")
            ]
            lift = f"{_stage_mean(group, ['lift']):.1f}"
            lift += " (shared)" if group[0].lift_shared else ""
            partition = _stage_mean(group, ["knn", "votes", "reweight", "partition"])
            counts = " / ".join(
                f"{np.mean([r.region_counts[k] for r in group]):.0f}" for k in range(4)
            )
            lines.append(
                f"| {preset} | {variant} | {self.mean(preset, variant, 'seconds'):.1f} "
                f"| {lift} | {partition:.1f} | {_stage_mean(group, merge):.1f} "
                f"| {_stage_mean(group, ['features']):.2f} "
                f"| {self.mean(preset, variant, 'peak_gib'):.2f} | {counts} |"
            )
        headline = [pair for name in protocol_names() for pair in get_protocol(name).headline]
        keys = [f"{p} {m}" for p, m in headline if any(f"{p} {m}" in r.quality for r in self.runs)]
        lines += [
            "",
            "| preset | variant | " + " | ".join(keys) + " |",
            "|---|---|" + "---|" * len(keys),
        ]
        for preset, variant in groups:
            values = " | ".join(f"{self.mean(preset, variant, key):.3f}" for key in keys)
            lines.append(f"| {preset} | {variant} | {values} |")
        cells = self.selection_cells()
        if cells:
            lines += [
                "",
                "Selection across scenarios (full method; LERF mIoU, THGS protocol; means over "
                "seeds):",
                "",
                "| preset | kind | severity | stand-in | automatic | paper's | 3dovs |",
                "|---|---|---|---|---|---|---|",
            ]
            for cell in cells:
                lines.append(
                    f"| {cell['preset']} | {cell['kind']} | {cell['severity']:g} "
                    f"| {cell['stand_in']} | {cell['lerf miou']:.3f} "
                    f"| {cell['lerf-paper miou']:.3f} | {cell['3dovs miou']:.3f} |"
                )
            auto = [cell["lerf miou"] for cell in cells]
            paper = [cell["lerf-paper miou"] for cell in cells]
            wins = sum(a >= b for a, b in zip(auto, paper))
            lines += [
                f"| mean | | | | {np.mean(auto):.3f} | {np.mean(paper):.3f} "
                f"| {np.mean([cell['3dovs miou'] for cell in cells]):.3f} |",
                f"| worst cell | | | | {np.min(auto):.3f} | {np.min(paper):.3f} "
                f"| {np.min([cell['3dovs miou'] for cell in cells]):.3f} |",
                "",
                f"The automatic selection ≥ the paper's in {wins} of {len(cells)} cells.",
            ]
        checks = self.orderings()
        if checks:
            lines += ["", "Paper orderings (LERF mIoU, THGS protocol, paper's selection):", ""]
            for preset, chain, scores, holds in checks:
                shown = " > ".join(f"{v} {s:.3f}" for v, s in zip(chain, scores))
                lines.append(f"- {preset}: {shown}: {'holds' if holds else 'does not hold'}")
        return "\n".join(lines) + "\n"

    def plot(self, path: str | os.PathLike[str]) -> None:
        """A PNG of seconds per stage (stacked bars, one per preset and variant), atomically.

        Raises:
            ThgsError: matplotlib is not installed (``pip install 'thgs[bench]'``).
        """
        pyplot = require_matplotlib()
        groups = self.groups()
        stages = list(dict.fromkeys(s for run in self.runs for s in run.stages))
        figure, axis = pyplot.subplots(figsize=(11, 0.45 * len(groups) + 1.8))
        labels = [f"{preset}: {variant}" for preset, variant in groups]
        left = np.zeros(len(groups))
        colors = pyplot.get_cmap("tab20")
        for i, stage in enumerate(stages):
            widths = np.array([_stage_mean(group, [stage]) for group in groups.values()])
            axis.barh(labels, widths, left=left, label=stage, color=colors(i % 20))
            left += widths
        axis.invert_yaxis()
        axis.set_xlabel("seconds")
        axis.set_title("build time per stage")
        axis.legend(fontsize="small", loc="center left", bbox_to_anchor=(1.01, 0.5))
        figure.tight_layout()
        with atomic_output(path, "wb") as handle:
            figure.savefig(handle, format="png", dpi=120)
        pyplot.close(figure)


def require_matplotlib():
    """matplotlib's ``pyplot`` on the Agg backend.

    Raises:
        ThgsError: matplotlib is not installed (``pip install 'thgs[bench]'``).
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        from matplotlib import pyplot
    except ImportError as error:
        raise ThgsError(
            "thgs bench draws its plot with matplotlib: pip install 'thgs[bench]'"
        ) from error
    return pyplot


def write_bench(out: str | os.PathLike[str], report: BenchReport) -> tuple[Path, Path, Path]:
    """Write ``bench.json``, ``bench.md`` and ``bench-time.png`` into ``out``: all three or none
    (:func:`thgs._atomic.atomic_files`)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    paths = (out / "bench.json", out / "bench.md", out / "bench-time.png")
    with atomic_files(paths) as (json_path, markdown_path, plot_path):
        write_json(json_path, report.to_json())
        with atomic_output(markdown_path, "w") as handle:
            handle.write(report.markdown())
        report.plot(plot_path)
    return paths
