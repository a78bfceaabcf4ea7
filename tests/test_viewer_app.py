"""The viser app on a real server, driven from Python (GUI values set as a browser would), and
``thgs view`` as a process; bad input never stops the server."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest

from thgs.errors import InputError
from thgs.viewer.app import start_viewer, viewer_url
from thgs.viewer.splats import pack_rgba


def _serves(url: str) -> bool:
    with urllib.request.urlopen(url, timeout=10) as response:
        return response.status == 200 and b"<html" in response.read().lower()


@pytest.fixture
def app(small_field, tmp_path):
    app = start_viewer(small_field, port=0, export_root=tmp_path)
    yield app
    app.stop()


def _press(button) -> None:
    button.value = True  # what a click from a browser does; callbacks run with no client


@pytest.mark.slow
def test_search_colours_only_the_chunks_that_change(small_field):
    from thgs.viewer.state import ViewerConfig

    app = start_viewer(small_field, port=0, config=ViewerConfig(chunk_size=500))
    try:
        state = app.state
        assert app.problem is None and state is not None and app.splats.chunk_count == 8
        np.testing.assert_array_equal(app.splats.rgba(), pack_rgba(*state.colors()))
        app.query_text.value = "teddy bear"
        _press(app.search)
        highlight = state.highlight
        assert highlight.kind == "query" and highlight.text == "teddy bear"
        assert "**teddy bear**" in app.results.content
        shown = f"confidence that the scene holds it: {highlight.confidence:.2f}"
        assert highlight.confidence > 0.9 and shown in app.results.content
        assert "| relevancy | confidence | Gaussians |" in app.results.content
        np.testing.assert_array_equal(app.splats.rgba(), pack_rgba(*state.colors()))
        # a pick of another object re-sends only the chunks holding either object
        sent = app.splats.bytes_sent
        objects = state.field.labels[:, 3]
        other = int(objects[~highlight.gaussians][0])
        before = pack_rgba(*state.colors())
        state._select_region(3, other, None)
        app.refresh()
        changed = np.flatnonzero((pack_rgba(*state.colors()) != before).any(axis=1))
        position = np.empty(len(state), np.int64)
        position[app.splats.order] = np.arange(len(state))
        chunks = np.unique(position[changed] // 500)
        assert 0 < chunks.size < app.splats.chunk_count
        assert app.splats.bytes_sent - sent == 32 * 500 * chunks.size
        assert app.hierarchy.content.startswith(f"Selected: **object {other}**")
    finally:
        app.stop()


def test_gui_controls_drive_the_state(app, tmp_path):
    state = app.state
    app.level.value = "2 part"
    assert state.level == 2
    app.mode.value = "threshold"
    app.threshold.value = 0.9
    assert (state.mode, state.threshold) == ("threshold", 0.9)
    app.query_text.value = "mug"
    _press(app.search)
    assert all(level == 2 and score >= 0.9 for level, _, score in state.highlight.regions)
    _press(app.parent)
    assert state.level == 3 and app.level.value == "3 object"
    app.colors.value = "regions"
    assert state.color == "regions"
    np.testing.assert_array_equal(app.splats.rgba(), pack_rgba(*state.colors()))
    app.export_folder.value = str(tmp_path / "out")
    _press(app.export_button)
    assert app.problem is None
    assert sorted(p.name for p in (tmp_path / "out").iterdir())[0].endswith("-indices.npy")
    _press(app.clear)
    assert state.highlight is None
    assert app.views.options[1:] == app.scene.cameras.stems
    app.views.value = app.scene.cameras.stems[2]  # no browser connected: nothing to move
    assert app.problem is None


def test_exports_stay_inside_the_export_root(app, tmp_path):
    app.query_text.value = "mug"
    _press(app.search)
    assert app.export_root == tmp_path.resolve()
    (tmp_path / "inside").mkdir()
    (tmp_path / "inside" / "out").symlink_to(tmp_path.parent)
    for outside in ("/tmp", "..", "inside/../..", str(tmp_path.parent / "x"), "inside/out"):
        app.export_folder.value = outside
        _press(app.export_button)
        assert "is outside" in app.problem and "--export-root" in app.problem, outside
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inside"]
    assert not list(tmp_path.parent.glob("mug*"))
    for inside, folder in ((".", tmp_path), ("a/b", tmp_path / "a" / "b"),
                           (str(tmp_path / "c"), tmp_path / "c")):  # fmt: skip
        app.export_folder.value = inside
        _press(app.export_button)
        assert app.problem is None and (folder / "mug.ply").is_file(), inside


def test_a_problem_clears_when_the_next_action_succeeds(app):
    app.query_text.value = "   "
    _press(app.search)
    assert "type something" in app.problem and "Problem:" in app.status.content
    app.query_text.value = "mug"
    _press(app.search)
    assert app.problem is None and "Problem:" not in app.status.content


def test_an_export_root_that_is_a_file_is_refused_before_the_server_starts(small_field, tmp_path):
    taken = tmp_path / "exports"
    taken.write_text("mine")
    with pytest.raises(InputError, match=rf"{taken}: is a file; the export root is the folder"):
        start_viewer(small_field, port=0, export_root=taken)
    assert taken.read_text() == "mine"


def test_open_field_tells_nothing_about_files_that_are_not_fields(app, tmp_path, small_field):
    secret = tmp_path / "secret.txt"
    secret.write_text("password")
    unreadable = tmp_path / "locked.thgs"
    unreadable.write_bytes(b"not a field")
    answers = set()
    for path in (secret, tmp_path / "missing.txt", tmp_path, unreadable, tmp_path / "no.thgs"):
        app.field_path.value = str(path)
        _press(app.open_button)
        assert app.problem == f"{path}: is not a readable field file (.thgs)", app.problem
        answers.add(app.problem.removeprefix(str(path)))
    assert len(answers) == 1 and len(app.state) == 4000  # one answer; the field stays open
    app.field_path.value = str(small_field)
    _press(app.open_button)
    assert app.problem is None


def test_an_unwritable_export_folder_is_reported_and_the_server_keeps_running(app, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    app.query_text.value = "mug"
    _press(app.search)
    app.export_folder.value = str(blocker / "exports")
    _press(app.export_button)
    assert "cannot write the selection there" in app.problem
    assert str(blocker / "exports") in app.problem and "Problem:" in app.status.content
    assert _serves(viewer_url(app, "127.0.0.1"))
    app.export_folder.value = str(tmp_path / "exports")
    _press(app.export_button)
    assert (tmp_path / "exports" / "mug.ply").is_file()


@pytest.mark.slow
def test_a_field_of_another_scene_is_reported_and_another_field_can_be_opened(
    small_field, tmp_path
):
    from thgs.cli import entrypoint

    other = tmp_path / "other"
    try:
        entrypoint(["synth", "synth-small", str(other), "--gaussians", "2000", "--views", "4"])
    except SystemExit as exc:  # pragma: no cover - the command returns normally
        assert not exc.code
    app = start_viewer(small_field, scene=other, port=0, export_root=tmp_path)
    try:
        assert app.state is None
        assert "4000 Gaussians but the scene" in app.problem and "2000" in app.problem
        assert "Problem:" in app.status.content
        assert _serves(viewer_url(app, "127.0.0.1"))
        app.scene_path = None
        app.field_path.value = str(small_field)
        _press(app.open_button)
        assert app.problem is None and app.state is not None and len(app.state) == 4000
        app.field_path.value = str(tmp_path / "missing.thgs")
        _press(app.open_button)
        assert "missing.thgs" in app.problem and len(app.state) == 4000
    finally:
        app.stop()


def test_a_port_in_use_moves_to_the_next_free_one(small_field):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        app = start_viewer(small_field, port=port)
        try:
            bound = app.server.get_port()
            assert bound != port
            assert app.notes == [f"port {port} is in use; serving on port {bound}"]
            assert f"port {port} is in use" in app.status.content
            assert _serves(viewer_url(app, "127.0.0.1"))
        finally:
            app.stop()


def _interruptible() -> None:
    """In the child before it runs: Ctrl-C delivered and handled as a terminal's would be, even if
    this test process had SIGINT blocked or ignored (libraries loaded by earlier tests may leave
    either, and a child inherits both)."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _ended(process: subprocess.Popen) -> tuple[str, str]:
    """The output of a viewer told to stop; one that has not stopped within 120 s is made to
    dump every thread's stack (faulthandler, on SIGABRT) and the test fails with them."""
    try:
        return process.communicate(timeout=120)  # reads the pipes: a full one would block it
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGABRT)
        _, err = process.communicate(timeout=30)
        pytest.fail(f"the viewer did not stop within 120 s after Ctrl-C; its threads:\n{err}")


@pytest.mark.slow
def test_thgs_view_serves_until_interrupted(small_field):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    executable = shutil.which("thgs", path=str(Path(sys.executable).parent))
    if executable is None:
        pytest.skip("the thgs console script is not installed next to this Python")
    process = subprocess.Popen(
        [executable, "view", str(small_field), "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONFAULTHANDLER": "1"},
        preexec_fn=_interruptible,
    )
    second = None
    try:
        line = process.stdout.readline()
        assert line.startswith(f"thgs view: http://127.0.0.1:{port}/?token="), (
            line + process.stderr.read() if process.poll() is not None else line
        )
        assert line.split()[3:5] == ["(4,000", "Gaussians);"], line
        assert _serves(line.split()[2])
        # a second viewer on the same port, of a field that does not exist: both say so, and
        # it serves anyway
        missing = small_field.parent / "missing.thgs"
        second = subprocess.Popen(
            [executable, "view", str(missing), "--port", str(port)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=_interruptible,
            env={
                **os.environ,
                "PYTHONUNBUFFERED": "1",
                "PYTHONFAULTHANDLER": "1",
                "COLUMNS": "200",
            },
        )
        line = second.stdout.readline()
        assert line.startswith("thgs view: http://127.0.0.1:") and "(no field open)" in line
        moved = urlsplit(line.split()[2]).port
        assert moved != port and _serves(line.split()[2])
        second.send_signal(signal.SIGINT)
        _, err = _ended(second)
        assert second.returncode == 0, err
        err = " ".join(err.split())
        assert f"port {port} is in use; serving on port {moved}" in err
        assert f"{missing}: semantic field file not found" in err
        process.send_signal(signal.SIGINT)
        printed, err = _ended(process)
        assert process.returncode == 0, err
        assert "viser" not in printed
    finally:
        for running in (process, second):
            if running is not None and running.poll() is None:
                running.kill()
