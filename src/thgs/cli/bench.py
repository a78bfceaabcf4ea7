"""``thgs bench``: the method against its ablations, time, memory and quality in one run."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated, Literal

import tyro

from thgs.choices import Device
from thgs.cli._console import StageBars, setup_logging, stage_progress, stdout
from thgs.cli._outputs import check_output_folder

__all__ = ["bench"]


def bench(
    *,
    out: Annotated[Path, tyro.conf.arg(aliases=("-o",))] = Path("thgs-bench"),
    presets: tuple[str, ...] = (),
    seeds: tuple[int, ...] = (0,),
    kinds: tuple[Literal["2dgs", "3dgs"], ...] = ("2dgs",),
    severities: tuple[float, ...] = (0.5,),
    stand_ins: tuple[str, ...] = ("name-perfect", "clip-like"),
    clip_like: bool = False,
    clip_grid: bool = False,
    variants: tuple[str, ...] = (),
    gaussians: int | None = None,
    views: int | None = None,
    cache: Path | None = None,
    device: Device = "auto",
    lift_cache: Path | None = None,
    verbose: bool = False,
) -> None:
    """Build the synthetic scenes with the full method and each ablation; time, memory, scores.

    Variants: full; no edge reweighting; no depth decay; no progressive merging; instance level
    only (the paper's Table 3); exact lifting; absolute reweighting; authors' code. Each is
    scored under every protocol (thgs eval). Writes bench.json, bench.md (tables and the
    paper's orderings) and bench-time.png (seconds per stage) into --out.

    Args:
        out: the folder for the report.
        presets: synthetic presets (default: synth-small and synth-medium; synth-large too on a
            CUDA GPU).
        seeds: scene seeds (results are averaged over them).
        kinds: Gaussian kinds of the scenes, 2dgs and/or 3dgs.
        severities: the oracle's mask-fault severities (0 clean, 0.5 default, 1 heavy).
        stand_ins: how CLIP-like the oracle's features are (docs/synthetic.md): name-perfect,
            clip-like, or a spec such as clip-like:parent_drift=0.8 or
            name-perfect:context_mix=0.8; each kind × severity × stand-in is a scenario, and
            bench.md reports the automatic and the paper's selection in every one.
        clip_like: only the clip-like stand-in (instead of --stand-ins).
        clip_grid: name-perfect and the grid around clip-like (parent drift 0.6 and 0.8 ×
            surroundings 0.1 and 0.3) instead of --stand-ins.
        variants: a subset of the variants, by name (default: all).
        gaussians: override the presets' Gaussian count (quick runs).
        views: override the presets' view count.
        cache: where synthetic datasets are kept (default ~/.cache/thgs).
        device: where to build and score: auto (a CUDA GPU if torch sees one, else MPS, else the
            CPU), cpu, cuda or mps.
        lift_cache: keep each scene's lifts in this folder and reuse them in later runs (quality
            sweeps; the lift's time is then the cache's reading time).
        verbose: log every stage.
    """
    from thgs.bench import BenchConfig, require_matplotlib, run_bench, write_bench
    from thgs.errors import InputError, settings_as_flags
    from thgs.synthetic import CLIP_GRID

    setup_logging(verbose)
    if clip_like and clip_grid:
        raise InputError("--clip-like", "and --clip-grid choose different stand-ins; pick one")
    if clip_like:
        stand_ins = ("clip-like",)
    elif clip_grid:
        stand_ins = ("name-perfect", *CLIP_GRID)
    check_output_folder(out)
    require_matplotlib()
    config = BenchConfig(
        seeds=seeds,
        kinds=kinds,
        severities=severities,
        stand_ins=stand_ins,
        gaussians=gaussians,
        views=views,
        cache=cache,
        device=device,
        lift_cache=lift_cache,
    )
    if presets:
        config = replace(config, presets=presets)
    if variants:
        config = replace(config, variants=variants)
    with settings_as_flags("seeds", "kinds", "severities", "stand_ins", "variants", "presets"):
        config.check()
    with stage_progress() as bar:
        report = run_bench(config, progress=StageBars(bar))
    paths = write_bench(out, report)
    stdout.print(report.markdown(), markup=False, highlight=False)
    stdout.print("wrote " + ", ".join(str(p) for p in paths))
