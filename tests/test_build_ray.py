"""A build's per-view and per-block work as Ray tasks (``thgs build --ray``, thgs.build_ray):
the same field bytes as in-process, on the session's local Ray (``local_ray``, conftest.py), which
the command uses as it is and leaves running."""

from __future__ import annotations

import socket

import pytest

ray = pytest.importorskip("ray")

from conftest import run_cli  # noqa: E402
from thgs import build_ray, cluster  # noqa: E402
from thgs.errors import ThgsError  # noqa: E402
from thgs.synthetic import generate_scene, preset  # noqa: E402

BLOCKS = ["--set", "superpoints.partition.block_size=1000"]  # several blocks: solver tasks


def test_ray_must_be_connected_first():
    # not marked ray: the session's Ray, if up, is hidden (conftest.py)
    assert not ray.is_initialized()
    scene = generate_scene(preset("synth-small", gaussians=4000, views=2))
    with pytest.raises(ThgsError, match=r"Ray is not initialised in this process"):
        next(build_ray.ray_lift_views(scene.gaussians, scene.cameras, []))
    with pytest.raises(ThgsError, match=r"Ray is not initialised in this process"):
        build_ray.ray_solve([])


def test_ray_build_gives_the_in_process_bytes(
    small_dataset, tmp_path, capsys, monkeypatch, local_ray
):
    here, there = tmp_path / "here.thgs", tmp_path / "ray.thgs"
    code, _, err = run_cli(["build", str(small_dataset), "-o", str(here), *BLOCKS], capsys)
    assert code == 0, err
    calls = {"lift": 0, "solve": 0}
    lift, solve = build_ray.ray_lift_views, build_ray.ray_solve

    def counted_lift(*args, **kwargs):
        calls["lift"] += 1
        return lift(*args, **kwargs)

    def counted_solve(shares):
        calls["solve"] += len(shares)
        return solve(shares)

    connected, closed = [], []
    connect, shutdown = cluster.connect_ray, cluster.RayConnection.shutdown

    def recorded_connect(*args, **kwargs):
        connected.append((args, kwargs, connection := connect(*args, **kwargs)))
        return connection

    def recorded_shutdown(connection):
        closed.append(connection)
        shutdown(connection)

    monkeypatch.setattr("thgs.pipeline.ray_lift_views", counted_lift)
    monkeypatch.setattr("thgs.build_ray.ray_solve", counted_solve)
    monkeypatch.setattr("thgs.cluster.connect_ray", recorded_connect)
    monkeypatch.setattr("thgs.cluster.RayConnection.shutdown", recorded_shutdown)
    code, _, err = run_cli(
        ["build", str(small_dataset), "-o", str(there), "--ray", *BLOCKS], capsys
    )
    assert code == 0, err
    assert calls["lift"] == 1 and calls["solve"] == 2  # two CPUs: two shares of blocks
    # a bare --ray asks for a local Ray, finds the session's and uses it as it is; the command
    # closes its connection, which shuts down only a Ray it started (connect_ray's own start
    # and shutdown: the local_ray fixture), so the session's Ray runs on
    [(args, kwargs, connection)] = connected
    assert args == (None,) and kwargs == {}
    assert (connection.address, connection.started, connection.cpus) == ("existing", False, 2.0)
    assert closed == [connection] and ray.is_initialized()
    assert there.read_bytes() == here.read_bytes()


def test_a_ray_address_that_does_not_answer(small_dataset, tmp_path, capsys):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    out = tmp_path / "x.thgs"
    argv = ["build", str(small_dataset), "-o", str(out), "--ray", f"127.0.0.1:{port}"]
    code, _, err = run_cli(argv, capsys)
    assert code == 2 and f"127.0.0.1:{port}: no Ray cluster answers there" in err
    assert not out.exists() and not ray.is_initialized()
