"""``thgs suite``: every scene of every benchmark under a folder — preprocess, build, eval where
needed — and one report in the paper's tables."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Literal

import tyro
from rich.live import Live
from rich.markup import escape
from rich.table import Table

from thgs.choices import Device, FieldPreset
from thgs.cli._console import error, setup_logging, stderr, stdout
from thgs.cli._outputs import check_output_folder
from thgs.guidance.preprocess.sam import DEFAULT_SAM
from thgs.text import LANGSPLAT_SPACE

__all__ = ["suite"]

LOCAL_RAY = "local"
"""The value of ``--ray`` that starts a local Ray (what a bare ``--ray`` means)."""


def bare_ray_flag(argv: Sequence[str]) -> list[str]:
    """``thgs suite`` and ``thgs build`` arguments with a bare ``--ray`` (last, or followed by
    another option) given its value ``local``, so that ``--ray`` and ``--ray ADDRESS`` both
    work."""
    args = list(argv)
    if not args or args[0] not in ("suite", "build"):
        return args
    fixed: list[str] = []
    for i, arg in enumerate(args):
        fixed.append(arg)
        following = args[i + 1] if i + 1 < len(args) else None
        if arg == "--ray" and (following is None or following.startswith("-")):
            fixed.append(LOCAL_RAY)
    return fixed


class _ProgressTable:
    """A live table of the scenes and their states (``progress(scene, state)``)."""

    def __init__(self, keys: Sequence[str]) -> None:
        self.states = dict.fromkeys(keys, "waiting")
        self.live: Live | None = None

    def render(self) -> Table:
        table = Table(title="thgs suite", title_justify="left")
        table.add_column("scene")
        table.add_column("state")
        colours = {"done": "green", "current": "green", "waiting": "dim"}
        for key, state in self.states.items():
            colour = "red" if state.startswith("failed") else colours.get(state, "yellow")
            table.add_row(escape(key), f"[{colour}]{escape(state)}[/]")
        return table

    def __call__(self, key: str, state: str) -> None:
        labels = {"preprocess": "preprocessing", "build": "building", "eval": "evaluating"}
        self.states[key] = labels.get(state, state)
        if self.live is None:  # shown once work starts (after Ray, if wanted, answered)
            self.live = Live(self.render(), console=stderr, refresh_per_second=4)
            self.live.start()
        self.live.update(self.render())

    def stop(self) -> None:
        if self.live is not None:
            self.live.stop()


def _plan_lines(scenes, out, config) -> tuple[list[str], int]:
    """One line per scene: each stage's action and why; and how many scenes cannot run."""
    from thgs.suite import plan_scene

    lines, blocked = [], 0
    for scene in scenes:
        if scene.problems:
            blocked += 1
            lines.append(f"{scene.key}: cannot run: " + "; ".join(scene.problems))
            continue
        plans = plan_scene(scene, out, config)
        lines.append(
            f"{scene.key}: "
            + "; ".join(f"{plan.stage} {plan.action} ({plan.reason})" for plan in plans)
        )
    return lines, blocked


def suite(
    root: Annotated[Path, tyro.conf.arg(metavar="ROOT")],
    /,
    *,
    out: Annotated[Path, tyro.conf.arg(aliases=("-o",))],
    select: tuple[str, ...] = (),
    preset: FieldPreset | None = None,
    config: Path | None = None,
    set: tuple[str, ...] = (),
    selection: Literal["auto", "paper"] = "auto",
    device: Device = "auto",
    sam: str = DEFAULT_SAM,
    clip: str = LANGSPLAT_SPACE,
    ray: Annotated[str | None, tyro.conf.arg(metavar="[ADDRESS]")] = None,
    dry_run: bool = False,
    verbose: bool = False,
) -> None:
    """Run a benchmark suite: every scene under ROOT, each stage only where it is missing or
    stale, and one report.

    Finds LangSplat's LERF-OVS release (lerf_ovs/<scene>, lerf_ovs/label/<scene>), 3D-OVS scenes
    (<scene>/segmentations), ScanNet as OpenGaussian prepares it, OpenHype's ScanNet++ scenes
    (openhype_scannetpp_benchmark/<scene> beside them) and synthetic datasets, with
    their trained models (cfg_args, or ROOT/output/<scene>). For each scene it preprocesses
    (only a scene without language features), builds and evaluates what is not current, into
    OUT/<benchmark>/<scene>/; then writes OUT/report.md, report.json and report.png: per-scene
    and mean numbers per benchmark in the paper's tables, build times, failed scenes, settings.
    A failed scene is reported and the others go on (exit status 1); run the same command again
    to resume (docs/suite.md).

    Args:
        root: the folder holding the benchmarks' data and the trained models.
        out: the folder for the scenes' outputs and the report.
        select: benchmarks (lerf_ovs, 3dovs, scannet, openhype, synthetic), benchmark/scene
            keys or scene names to run; default all.
        preset: one field-building preset for every scene; default each benchmark's (3dovs for
            3D-OVS, lerf otherwise), as in the paper.
        config: every field-building setting from a JSON config or a field file, for every
            scene (instead of a preset).
        set: change single field-building settings, e.g. --set merge.min_region_gaussians=30
            (as thgs build --set); a changed setting rebuilds and re-evaluates every scene.
        selection: the query selection scored: auto (thgs's) or paper (the paper's top-3);
            LERF-OVS also reports the paper's rule either way. A change re-evaluates only.
        device: where to build and evaluate: auto, cpu, cuda or mps.
        sam: SAM for scenes without language features (local folder or Hugging Face id).
        clip: CLIP for them, likewise.
        ray: run scenes as Ray tasks: --ray starts a local Ray, --ray ADDRESS joins a running
            cluster (e.g. 10.0.0.1:6379); needs thgs[cluster].
        dry_run: print what would run for each scene and why, and stop.
        verbose: log every stage.
    """
    from thgs.pipeline import read_field_config
    from thgs.suite import SuiteConfig, find_suite, run_suite, write_suite_report

    setup_logging(verbose)
    check_output_folder(out)
    settings = SuiteConfig(
        preset=preset,
        config=None if config is None else read_field_config(config),
        settings=set,
        selection=selection,
        device=device,
        sam=sam,
        clip=clip,
    ).check()
    scenes = find_suite(root, select, skip=out)
    if dry_run:
        lines, blocked = _plan_lines(scenes, out, settings)
        for line in lines:
            stdout.print(line, soft_wrap=True, highlight=False, markup=False)
        if blocked:
            error(f"{blocked} of {len(scenes)} scenes cannot run (see above)")
            sys.exit(1)
        return
    progress = _ProgressTable([scene.key for scene in scenes])
    try:
        report = run_suite(
            scenes,
            out,
            settings,
            use_ray=ray is not None,
            ray_address=None if ray in (None, LOCAL_RAY) else ray,
            progress=progress,
        )
    finally:
        progress.stop()
    report, paths = write_suite_report(out, report)
    stdout.print(report.markdown(), markup=False, highlight=False, soft_wrap=True)
    stdout.print("wrote " + ", ".join(str(path) for path in paths))
    if report.failed:
        error(
            f"{len(report.failed)} of {len(report.scenes)} scenes failed: "
            + ", ".join(scene.key for scene in report.failed)
            + f" (their tracebacks: {out}/<benchmark>/<scene>/error.log)"
        )
        sys.exit(1)
