"""Benchmark suites: every scene of LERF-OVS, 3D-OVS, ScanNet and synthetic datasets under one
folder, preprocessed, built and evaluated where needed, and one report in the paper's tables.

- :func:`find_suite` — the scenes under a folder, in the benchmarks' release layouts;
- :func:`run_suite` — run each scene's missing stages, in-process or as Ray tasks;
- :func:`write_suite_report` — ``report.json``, ``report.md``, ``report.png``.

``thgs suite ROOT -o OUT`` does all three (docs/suite.md).
"""

from thgs.suite.config import SuiteConfig
from thgs.suite.discover import BENCHMARK_PROTOCOLS, BENCHMARKS, SuiteScene, find_suite
from thgs.suite.plan import STAGES, StagePlan, plan_scene, scene_folder
from thgs.suite.report import (
    HEADLINES,
    SceneResult,
    SuiteReport,
    build_stage_group,
    write_suite_report,
)
from thgs.suite.run import run_scene, run_suite

__all__ = [
    "BENCHMARKS",
    "BENCHMARK_PROTOCOLS",
    "HEADLINES",
    "STAGES",
    "SceneResult",
    "StagePlan",
    "SuiteConfig",
    "SuiteReport",
    "SuiteScene",
    "build_stage_group",
    "find_suite",
    "plan_scene",
    "run_scene",
    "run_suite",
    "scene_folder",
    "write_suite_report",
]
