"""Connecting to Ray (:func:`thgs.cluster.connect_ray`): an address that does not answer, a
malformed one, and errors that cross between processes as themselves."""

from __future__ import annotations

import pickle
import socket

import pytest

from thgs.errors import InputError, ThgsError
from thgs.text import SpaceMismatchError

ray = pytest.importorskip("ray")

from thgs.cluster import connect_ray  # noqa: E402


def _closed_port() -> int:
    """A local port nothing listens on (bound, then released)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.mark.parametrize("scheme", ["", "ray://"])
def test_an_address_that_does_not_answer_is_named(scheme):
    address = f"{scheme}127.0.0.1:{_closed_port()}"
    with pytest.raises(ThgsError, match=r"no Ray cluster answers there") as caught:
        connect_ray(address, timeout=5)
    message = str(caught.value)
    assert message.startswith(f"{address}: ") and "ray start --head" in message
    assert not ray.is_initialized()


@pytest.mark.parametrize("address", ["localhost", "ray://:10001", "host:port"])
def test_a_malformed_address_is_refused(address):
    with pytest.raises(InputError, match=r"not a Ray address: expected host:port"):
        connect_ray(address)


def test_resources_belong_to_a_local_ray_only():
    with pytest.raises(InputError, match=r"give num_cpus/num_gpus only for a local Ray"):
        connect_ray(f"127.0.0.1:{_closed_port()}", num_cpus=2)


@pytest.mark.parametrize(
    "error",
    [
        InputError("/data/frame.png", "not a readable image"),
        SpaceMismatchError("/data/lf", "features are in another space"),
        ThgsError("weights not found"),
    ],
)
def test_errors_cross_processes_as_themselves(error):
    """A Ray worker's error comes back pickled: same type, source and message."""
    copy = pickle.loads(pickle.dumps(error))
    assert type(copy) is type(error) and str(copy) == str(error)
    assert getattr(copy, "source", None) == getattr(error, "source", None)
