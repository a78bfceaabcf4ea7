"""The GPU check (scripts/gpu_check.sh, scripts/gpu_check.py): its dry run on the CPU at toy sizes
produces a complete report, the deadline skips what would not fit, bad arguments are refused,
and the full-size models it times have the published sizes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def gpu_check(*arguments: str, tmp_path: Path) -> subprocess.CompletedProcess:
    environment = {**os.environ, "THGS_PYTHON": sys.executable, "OUT": str(tmp_path / "out")}
    return subprocess.run(
        ["bash", str(ROOT / "scripts" / "gpu_check.sh"), *arguments],
        capture_output=True,
        text=True,
        env=environment,
        timeout=600,
    )


@pytest.mark.slow
def test_dry_run_reports_every_step(tmp_path):
    """The tiny run on the CPU: every step ran, gsplat's kernels are skipped for want of CUDA,
    the tests it runs passed, the toy scene was built and scored, and SAM's filter was set so
    that the asked number of masks reached CLIP."""
    run = gpu_check("--tiny", tmp_path=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    report = json.loads((tmp_path / "out" / "gpu_check.json").read_text())
    steps = report["steps"]
    assert list(steps) == ["environment", "kernels", "cuda_tests", "render", "build", "preprocess"]
    assert steps["kernels"] == {"status": "skipped", "why": "the tiny dry run uses the CPU"}
    assert all(steps[name]["status"] == "ok" for name in steps if name != "kernels")
    assert steps["environment"]["mode"] == "tiny"
    assert steps["environment"]["versions"]["torch"] == torch.__version__
    tests = steps["cuda_tests"]
    assert tests["exit_code"] == 0 and tests["failures"] == tests["errors"] == 0
    assert tests["passed"] > 0 and tests["tests"] == tests["passed"] + tests["skipped"]
    render = steps["render"]["runs"]
    assert [(r["kind"], r["backend"]) for r in render] == [("2dgs", "numba"), ("3dgs", "numba")]
    assert all(r[key] > 0 for r in render for key in ("render", "splat_back_20ch"))
    build = steps["build"]
    assert (build["gaussians"], build["views"], build["size"]) == (3000, 4, "96x72")
    counts = build["region_counts"]
    assert counts == sorted(counts, reverse=True) and counts[-1] >= 1
    assert all(0.3 < miou <= 1 for miou in build["miou_subpart_part_object"])
    assert {"lift", "partition", "features"} <= set(build["stages_s"])
    runs = steps["preprocess"]["runs"]
    assert [r["sam"] for r in runs] == ["tiny", "sam2-tiny"]
    assert all(r["masks_to_clip"] == 3 for r in runs)


@pytest.mark.slow
def test_deadline_skips_what_would_not_fit(tmp_path):
    """No time left: every step past the environment is skipped and says how long it needs."""
    out = tmp_path / "report.json"
    command = [sys.executable, str(ROOT / "scripts" / "gpu_check.py"), "--tiny"]
    run = subprocess.run(
        [*command, "--out", str(out), "--deadline-s", "0"], capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr
    steps = json.loads(out.read_text())["steps"]
    assert steps["environment"]["status"] == "ok"
    assert steps["kernels"]["why"] == "the tiny dry run uses the CPU"
    for name in ("cuda_tests", "render", "build", "preprocess"):
        assert steps[name]["status"] == "skipped"
        assert steps[name]["why"].endswith("s needed"), steps[name]


@pytest.mark.slow
def test_bad_arguments_are_refused(tmp_path):
    run = gpu_check("--fast", tmp_path=tmp_path)
    assert run.returncode == 2 and "unknown argument --fast" in run.stderr
    script = str(ROOT / "scripts" / "gpu_check.py")
    out = str(tmp_path / "r.json")
    run = subprocess.run(
        [sys.executable, script, "--tiny", "--out", out, "--steps", "bogus"],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 2 and "unknown steps ['bogus']" in run.stderr
    assert not Path(out).exists()


@pytest.mark.slow
def test_full_size_models_have_the_published_sizes():
    """Built on the meta device (no memory): SAM ViT-H has 641M parameters (the published
    sam_vit_h), SAM 2.1 Hiera-L 224M with the video memory that Sam2Model leaves out (~217M)."""
    transformers = pytest.importorskip("transformers")
    sys.path.insert(0, str(ROOT / "scripts"))
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import gpu_check
    from bench_preprocess import SAM_ENCODERS

    with torch.device("meta"):
        sam = transformers.SamModel(transformers.SamConfig(vision_config=SAM_ENCODERS["vit-h"]))
        sam2 = transformers.Sam2Model(transformers.Sam2Config(**gpu_check.SAM2_HIERA_LARGE))
    millions = [sum(p.numel() for p in model.parameters()) / 1e6 for model in (sam, sam2)]
    assert 640 < millions[0] < 642
    assert 212 < millions[1] < 224


@pytest.mark.slow
@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_full_size_without_cuda_says_so(tmp_path):
    """The full sizes on a machine without CUDA: every GPU step is skipped, saying why."""
    out = tmp_path / "report.json"
    script = str(ROOT / "scripts" / "gpu_check.py")
    steps = ["environment", "kernels", "render", "build", "preprocess"]
    run = subprocess.run(
        [sys.executable, script, "--out", str(out), "--steps", *steps],
        capture_output=True,
        text=True,
    )
    assert run.returncode == 0, run.stderr
    report = json.loads(out.read_text())["steps"]
    assert report["environment"]["mode"] == "full"
    for name in steps[1:]:
        assert report[name] == {"status": "skipped", "why": "torch sees no CUDA device"}
