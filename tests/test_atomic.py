"""The atomic writers: results appear whole or not at all, with the permissions of a plainly
created file or folder, and the process's umask is never touched; what a writer killed outright
leaves is removed by the next writer of the same target, never what a running one is writing."""

from __future__ import annotations

import errno
import os
import signal
import stat
import subprocess
import sys
import threading

import pytest

from thgs._atomic import (
    _HOST,
    atomic_files,
    atomic_folder,
    atomic_output,
    remove_stale_temporaries,
    staging_folder,
)
from thgs.errors import InputError


@pytest.fixture(autouse=True)
def no_umask_calls(monkeypatch):
    """os.umask sets the mask process-wide even to read it: the writers must never call it."""

    def forbidden(mask):
        raise AssertionError("os.umask called")

    monkeypatch.setattr(os, "umask", forbidden)


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def hidden(folder) -> list[str]:
    return sorted(name for name in os.listdir(folder) if name.startswith("."))


def test_file_is_written_whole_with_plain_permissions(tmp_path):
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    with atomic_output(tmp_path / "sub" / "out.txt", "w") as handle:
        handle.write("hello")
        assert not (tmp_path / "sub" / "out.txt").exists()
    assert (tmp_path / "sub" / "out.txt").read_text() == "hello"
    assert mode(tmp_path / "sub" / "out.txt") == mode(plain)
    assert hidden(tmp_path / "sub") == []


@pytest.mark.parametrize("error", [RuntimeError, KeyboardInterrupt])
def test_file_failure_keeps_the_old_content(tmp_path, error):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with pytest.raises(error), atomic_output(target) as handle:
        handle.write(b"new, half")
        raise error
    assert target.read_bytes() == b"old"
    assert hidden(tmp_path) == []


def test_system_errors_name_the_target_not_the_temporary(tmp_path):
    """A folder in the target's place (the rename fails on the temporary's name) and a full
    disk (an error naming no file) are raised naming the target; other files' errors stay."""
    taken = tmp_path / "taken.npy"
    taken.mkdir()
    with pytest.raises(IsADirectoryError) as raised, atomic_output(taken) as handle:
        handle.write(b"data")
    assert raised.value.filename == str(taken) and raised.value.strerror == "Is a directory"
    full = tmp_path / "full.bin"
    with pytest.raises(OSError) as raised, atomic_output(full):
        raise OSError(errno.ENOSPC, "No space left on device")
    assert (raised.value.errno, raised.value.filename) == (errno.ENOSPC, str(full))
    other = tmp_path / "elsewhere"
    with pytest.raises(FileNotFoundError) as raised, atomic_output(tmp_path / "x.bin"):
        open(other)
    assert raised.value.filename == str(other)
    assert hidden(tmp_path) == [] and not full.exists()


def test_folder_errors_name_the_folder_and_the_file_inside(tmp_path):
    """A full disk while a folder is filled: the error names the folder being written and the
    file inside the hidden one; NumPy's short write is called what it is."""
    target = tmp_path / "dataset"
    with pytest.raises(OSError) as raised, atomic_folder(target) as staging:
        (staging / "label").mkdir()
        raise OSError(errno.ENOSPC, "No space left on device", str(staging / "label" / "a.json"))
    assert raised.value.filename == str(target) and raised.value.errno == errno.ENOSPC
    assert raised.value.strerror == "No space left on device (writing label/a.json)"
    with pytest.raises(OSError) as raised, atomic_folder(target):
        raise OSError("307200 requested and 141280 written")
    assert raised.value.filename == str(target)
    assert raised.value.strerror.startswith("No space left on device? (307200 requested")
    assert not target.exists() and hidden(tmp_path) == []


def test_folder_is_moved_in_whole_with_plain_permissions(tmp_path):
    plain = tmp_path / "plain"
    plain.mkdir()
    target = tmp_path / "out"
    with atomic_folder(target) as folder:
        (folder / "a.txt").write_text("a")
        assert not target.exists()
    assert (target / "a.txt").read_text() == "a"
    assert mode(target) == mode(plain)
    assert hidden(tmp_path) == []


def test_folder_onto_an_empty_folder(tmp_path):
    (tmp_path / "out").mkdir()
    with atomic_folder(tmp_path / "out") as folder:
        (folder / "a.txt").write_text("a")
    assert os.listdir(tmp_path / "out") == ["a.txt"]


def test_folder_failure_leaves_nothing(tmp_path):
    with pytest.raises(KeyboardInterrupt), atomic_folder(tmp_path / "out") as folder:
        (folder / "a.txt").write_text("a")
        raise KeyboardInterrupt
    assert os.listdir(tmp_path) == []


def test_folder_refuses_a_filled_target_and_cleans_up(tmp_path):
    target = tmp_path / "out"
    target.mkdir()
    (target / "theirs.txt").write_text("theirs")
    with pytest.raises(InputError, match="could not move the new folder"):
        with atomic_folder(target) as folder:
            (folder / "mine.txt").write_text("mine")
    assert os.listdir(target) == ["theirs.txt"]
    assert hidden(tmp_path) == []


def test_folder_replace_swaps_the_whole_folder(tmp_path):
    target = tmp_path / "out"
    target.mkdir()
    (target / "old.txt").write_text("old")
    with atomic_folder(target, replace=True) as folder:
        (folder / "new.txt").write_text("new")
        assert (target / "old.txt").exists()  # the old one stays until the new one is whole
    assert os.listdir(target) == ["new.txt"]
    assert hidden(tmp_path) == []


def test_folder_replace_failure_keeps_the_old_folder(tmp_path):
    target = tmp_path / "out"
    target.mkdir()
    (target / "old.txt").write_text("old")
    with pytest.raises(RuntimeError), atomic_folder(target, replace=True) as folder:
        (folder / "new.txt").write_text("new")
        raise RuntimeError
    assert os.listdir(target) == ["old.txt"]
    assert hidden(tmp_path) == []


def test_staging_folder_is_always_removed(tmp_path):
    with staging_folder(tmp_path / "x") as folder:
        (folder / "f").write_text("f")
        kept = folder
    assert not kept.exists()
    with pytest.raises(ValueError), staging_folder(tmp_path / "x") as folder:
        raise ValueError
    assert os.listdir(tmp_path) == []


def test_files_are_moved_in_together(tmp_path):
    (tmp_path / "b.md").write_text("old b")
    with atomic_files([tmp_path / "a.json", tmp_path / "b.md"]) as (a, b):
        a.write_text("a")
        b.write_text("b")
        assert sorted(os.listdir(tmp_path)) == [hidden(tmp_path)[0], "b.md"]
    assert sorted(os.listdir(tmp_path)) == ["a.json", "b.md"]
    assert (tmp_path / "a.json").read_text() == "a" and (tmp_path / "b.md").read_text() == "b"
    for paths in ([], [tmp_path / "a", tmp_path / "x" / "b"], [tmp_path / "a", tmp_path / "a"]):
        with pytest.raises(ValueError), atomic_files(paths):
            pass


@pytest.mark.parametrize("interrupted_move", [None, 1, 2])
def test_files_failure_leaves_none_of_them(tmp_path, monkeypatch, interrupted_move):
    """Ctrl-C while the files are written (None) or at the first or second move: none of the
    new files is left, nor any temporary; a file it did not reach keeps its old content."""
    (tmp_path / "b.md").write_text("old b")
    real, moves = os.replace, []

    def replace(source, target):
        moves.append(target)
        if len(moves) == interrupted_move:
            raise KeyboardInterrupt
        real(source, target)

    monkeypatch.setattr(os, "replace", replace)
    files = [tmp_path / "a", tmp_path / "b.md"]
    with pytest.raises(KeyboardInterrupt), atomic_files(files) as (a, b):
        a.write_text("a")
        b.write_text("b")
        if interrupted_move is None:
            raise KeyboardInterrupt
    # at the second move, the first file moved in is removed again
    assert len(moves) == (interrupted_move or 0)
    assert os.listdir(tmp_path) == ["b.md"] and (tmp_path / "b.md").read_text() == "old b"


def test_concurrent_writers_to_one_target(tmp_path):
    target = tmp_path / "out.txt"

    def write(i):
        with atomic_output(target, "w") as handle:
            handle.write(str(i) * 1000)

    threads = [threading.Thread(target=write, args=(i,)) for i in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    content = target.read_text()
    assert len(content) == 1000 and len(set(content)) == 1
    assert hidden(tmp_path) == []


# --- temporaries of writers killed outright ------------------------------------------------------

_WRITER = """
import os, signal, sys
from pathlib import Path
from thgs._atomic import atomic_folder, atomic_output

folder, file = Path(sys.argv[1]), Path(sys.argv[2])
with atomic_folder(folder) as staging, atomic_output(file) as handle:
    (staging / "half.txt").write_text("half")
    handle.write(b"half")
    print("writing", flush=True)
    if sys.argv[3] == "die":
        os.kill(os.getpid(), signal.SIGKILL)
    sys.stdin.read()
"""


def writer(tmp_path, mode: str) -> subprocess.Popen:
    """A process halfway through writing ``out`` (a folder) and ``out.bin``."""
    process = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(tmp_path / "out"), str(tmp_path / "out.bin"), mode],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert process.stdout.readline() == "writing\n"
    return process


def test_a_killed_writers_temporaries_go_with_the_next_write_of_the_same_target(tmp_path):
    killed = writer(tmp_path, "die")
    assert killed.wait() == -signal.SIGKILL
    (file,) = [name for name in hidden(tmp_path) if name.startswith(".out.bin.")]
    (folder,) = [name for name in hidden(tmp_path) if name != file]
    assert name_pid(folder) == name_pid(file) == killed.pid
    (tmp_path / f".other.{_HOST}-{killed.pid}-{'a' * 12}.tmp").mkdir()  # another target's

    with atomic_output(tmp_path / "out.bin") as handle:
        handle.write(b"whole")
    assert hidden(tmp_path) == sorted([folder, f".other.{_HOST}-{killed.pid}-{'a' * 12}.tmp"])
    with atomic_folder(tmp_path / "out") as staging:
        (staging / "whole.txt").write_text("whole")
    assert hidden(tmp_path) == [f".other.{_HOST}-{killed.pid}-{'a' * 12}.tmp"]
    assert os.listdir(tmp_path / "out") == ["whole.txt"]


def name_pid(name: str) -> int:
    return int(name.rsplit(".", 2)[1].split("-")[1])


def test_a_running_writers_temporaries_are_kept(tmp_path):
    running = writer(tmp_path, "wait")
    try:
        before = hidden(tmp_path)
        assert len(before) == 2
        assert remove_stale_temporaries(tmp_path / "out") == []
        assert remove_stale_temporaries(tmp_path / "out.bin") == []
        assert hidden(tmp_path) == before
    finally:
        running.kill()
        running.wait()
    assert len(remove_stale_temporaries(tmp_path / "out")) == 1
    assert len(remove_stale_temporaries(tmp_path / "out.bin")) == 1
    assert hidden(tmp_path) == []


def test_other_machines_and_this_process_open_temporaries_are_kept(tmp_path):
    other_host = "0" * 8 if _HOST != "0" * 8 else "1" * 8
    elsewhere = tmp_path / f".out.{other_host}-1-{'b' * 12}.tmp"
    elsewhere.mkdir()  # pid 1 means nothing on another machine
    recycled = tmp_path / f".out.{_HOST}-{os.getpid()}-{'c' * 12}.tmp"
    recycled.mkdir()  # this pid, but not a temporary this process has open: a recycled pid
    not_ours = tmp_path / f".out.notes-{'d' * 12}.tmp"
    not_ours.write_text("a user's file that only looks like a temporary")
    with staging_folder(tmp_path / "out") as open_now:
        assert not recycled.exists()  # removed when this writer started
        assert remove_stale_temporaries(tmp_path / "out") == []  # its own is not stale
        assert open_now.is_dir()
    assert hidden(tmp_path) == sorted([elsewhere.name, not_ours.name])
