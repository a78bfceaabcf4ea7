"""The thgs command line, through its entry point and as an installed console script."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO
from thgs.cli import entrypoint


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        entrypoint(argv)
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_info_on_the_real_sample(shared_data, capsys):
    code, out, _ = run(["info", str(shared_data / "ply_3dgs_train1000.ply")], capsys)
    assert code == 0
    assert "1,000 (3DGS, SH degree 3, normals stored)" in out
    assert "cameras" in out and "none" in out


def test_info_json_with_cameras(shared_data, capsys):
    code, out, _ = run(
        [
            "info",
            str(shared_data / "ply_3dgs_train1000.ply"),
            "--source",
            str(shared_data / "colmap_small"),
            "--scale",
            "0.25",
            "--json",
        ],
        capsys,
    )
    assert code == 0
    document = json.loads(out)
    assert (document["count"], document["kind"], document["sh_degree"]) == (1000, "3dgs", 3)
    assert document["cameras"]["count"] == 23
    assert document["cameras"]["width_range"] == [250, 250]
    assert document["cameras"]["height_range"] == [164, 166]


def test_bad_input_is_one_line_and_status_2(tmp_path, capsys):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\n")
    code, out, err = run(["info", str(bad)], capsys)
    assert code == 2 and out == ""
    assert err.startswith("error: ") and str(bad) in err.replace("\n", "")
    assert "Traceback" not in err


def test_help_lists_info(capsys):
    code, out, _ = run(["--help"], capsys)
    assert code == 0 and "info" in out


def test_console_script_on_bundled_sample():
    """The README's main job: the installed `thgs` on the sample shipped in examples/."""
    executable = shutil.which("thgs", path=str(Path(sys.executable).parent))
    if executable is None:
        pytest.skip("the thgs console script is not installed next to this Python")
    result = subprocess.run(
        [executable, "info", "examples/data/train-1000.ply"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert "1,000 (3DGS, SH degree 3" in result.stdout
