"""``thgs bench``: the method against its ablations, time, memory and quality in one run."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Annotated, Literal

import tyro

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
    context_mixes: tuple[float, ...] = (0.0, 0.5),
    variants: tuple[str, ...] = (),
    gaussians: int | None = None,
    views: int | None = None,
    cache: Path | None = None,
    device: Literal["auto", "cpu", "cuda", "mps"] = "auto",
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
        context_mixes: the oracle's CLIP-likeness (0 name-perfect features; docs/synthetic.md);
            each kind × severity × context mix is a scenario, and bench.md reports the automatic
            and the paper's selection in every one.
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

    setup_logging(verbose)
    check_output_folder(out)
    require_matplotlib()
    config = BenchConfig(
        seeds=seeds,
        kinds=kinds,
        severities=severities,
        context_mixes=context_mixes,
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
    config.check()
    with stage_progress() as bar:
        report = run_bench(config, progress=StageBars(bar))
    paths = write_bench(out, report)
    stdout.print(report.markdown(), markup=False, highlight=False)
    stdout.print("wrote " + ", ".join(str(p) for p in paths))
