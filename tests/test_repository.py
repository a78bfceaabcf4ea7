"""The README's promises: two set-up commands first, and CI running the test one."""

from __future__ import annotations

import re

import pytest

from conftest import REPO


def readme_commands() -> list[str]:
    text = (REPO / "README.md").read_text()
    block = re.search(r"```(?:bash|sh|console)?\n(.*?)```", text, re.S)
    assert block is not None, "the README must open with a code block of commands"
    assert text.index(block.group(0)) < 400, "the commands must be among the README's first lines"
    return [line for line in block.group(1).splitlines() if line.strip()]


def test_readme_opens_with_exactly_two_commands():
    commands = readme_commands()
    assert len(commands) == 2
    main_job, tests = commands
    assert main_job.startswith("bash scripts/setup.sh && ")
    assert tests.startswith("bash scripts/setup.sh && ") and "pytest" in tests


def test_ci_runs_the_readme_test_command():
    _, tests = readme_commands()
    ci = (REPO / ".ci" / "run").read_text()
    assert tests in ci.splitlines()


@pytest.mark.slow
def test_setup_script_second_run_changes_nothing():
    """scripts/setup.sh is idempotent: on the environment it made, it returns at once."""
    import subprocess
    import sys
    from pathlib import Path

    import pytest

    venv = REPO / ".venv"
    if Path(sys.prefix).resolve() != venv.resolve():
        pytest.skip("the tests are not running in the environment scripts/setup.sh made")

    def freeze() -> str:
        return subprocess.run(
            [sys.executable, "-m", "pip", "freeze"], capture_output=True, text=True, check=True
        ).stdout

    before = freeze()
    result = subprocess.run(
        ["bash", str(REPO / "scripts" / "setup.sh")],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    assert "is up to date" in result.stdout
    assert freeze() == before
