"""The viewer's door (thgs.viewer.guard): the checks against hand-written requests, and a hostile
client against a running viewer — foreign Origin, foreign Host (DNS rebinding), no token."""

from __future__ import annotations

import urllib.error
import urllib.request

import pytest
import websockets.sync.client as ws_client
from websockets.datastructures import Headers
from websockets.exceptions import InvalidStatus

from thgs.viewer.app import start_viewer, viewer_url
from thgs.viewer.guard import AccessGuard, new_token

TOKEN = "s3cret-token"
LOCAL = ("127.0.0.1", 8080)


def _problem(guard: AccessGuard, path: str = "/", **headers: str) -> str | None:
    return guard.problem(
        Headers(**{k.replace("_", "-"): v for k, v in headers.items()}), path, LOCAL
    )


def test_hosts_and_origins_must_name_this_server():
    guard = AccessGuard("127.0.0.1", None)
    for host in ("127.0.0.1:8080", "localhost:8080", "[::1]:8080", "LOCALHOST:8080", "localhost"):
        assert _problem(guard, Host=host) is None, host
    for host in ("attacker.example.com:8080", "127.0.0.1:9999", "127.0.0.1.nip.io:8080", ""):
        assert "is not this server" in _problem(guard, Host=host), host
    assert "is not this server" in _problem(guard)  # no Host header at all
    same = "http://127.0.0.1:8080"
    assert _problem(guard, Host="127.0.0.1:8080", Origin=same) is None
    assert _problem(guard, Host="127.0.0.1:8080", Origin="http://localhost:8080") is None
    for origin in ("http://evil.example", "http://127.0.0.1:3000", "https://127.0.0.1:8080",
                   "null", "http://127.0.0.1:99999"):  # fmt: skip
        assert "is not this server" in _problem(guard, Host="127.0.0.1:8080", Origin=origin)
    # served on all interfaces: the address a request arrived at is this server too
    everywhere = AccessGuard("0.0.0.0", None)
    assert everywhere.problem(Headers(Host="10.1.2.3:8080"), "/", ("10.1.2.3", 8080)) is None
    assert _problem(everywhere, Host="0.0.0.0:8080") is not None
    named = AccessGuard("viewer.lab", None)
    assert _problem(named, Host="viewer.lab:8080", Origin="http://viewer.lab:8080") is None


def test_the_token_comes_in_the_url_or_its_cookie():
    guard = AccessGuard("127.0.0.1", TOKEN)
    host = "127.0.0.1:8080"
    assert "no valid token" in _problem(guard, Host=host)
    assert "no valid token" in _problem(guard, "/?token=wrong", Host=host)
    assert _problem(guard, f"/?token={TOKEN}", Host=host) is None
    assert _problem(guard, f"/?x=1&token={TOKEN}", Host=host) is None
    cookie, own = f"thgs-viewer-token-8080={TOKEN}", "http://127.0.0.1:8080"
    # the cookie counts on the page's own requests: its Origin, or a same-origin fetch
    assert _problem(guard, Host=host, Origin=own, Cookie=cookie) is None
    assert _problem(guard, Host=host, Sec_Fetch_Site="same-origin", Cookie=cookie) is None
    assert _problem(guard, Host=host, Origin=own, Cookie=f"other=1; {cookie}") is None
    # replayed by another local service, without the page's headers: refused
    assert "no valid token" in _problem(guard, Host=host, Cookie=cookie)
    assert "no valid token" in _problem(
        guard, Host=host, Sec_Fetch_Site="cross-site", Cookie=cookie
    )
    # another viewer's cookie on this host (port 9090) is not this one's
    other_port = f"thgs-viewer-token-9090={TOKEN}"
    assert "no valid token" in _problem(guard, Host=host, Origin=own, Cookie=other_port)
    assert "no valid token" in _problem(
        guard, Host=host, Origin=own, Cookie=f"thgs-viewer-token={TOKEN}"
    )
    assert "no valid token" in _problem(
        guard, Host=host, Origin=own, Cookie="thgs-viewer-token-8080=wrong"
    )
    assert "no valid token" in _problem(guard, Host=host, Origin=own, Cookie='bad"cookie')
    assert guard.set_cookie(8080).startswith(f"{cookie}; HttpOnly; SameSite=Strict")
    assert len(new_token()) == 32 and new_token() != new_token()


def _get(url: str, **headers: str) -> tuple[int, str, str | None]:
    request = urllib.request.Request(url, headers=headers)
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status, response.read(200).decode(), response.headers["Set-Cookie"]
    except urllib.error.HTTPError as error:
        return error.code, error.read().decode(), None


def _websocket(port: int, origin: str, cookie: str | None) -> bool:
    headers = {"Cookie": cookie} if cookie else {}
    try:
        with ws_client.connect(
            f"ws://127.0.0.1:{port}",
            origin=origin,
            additional_headers=headers,
            subprotocols=["viser-v1"],
            open_timeout=10,
        ):
            return True
    except InvalidStatus as error:
        assert error.response.status_code == 403
        return False


@pytest.fixture(scope="module")
def running(small_field):
    app = start_viewer(small_field, port=0)
    yield app
    app.stop()


def test_a_hostile_client_is_refused(running, caplog):
    app = running
    port, url = app.server.get_port(), viewer_url(app, "127.0.0.1")
    assert url == f"http://127.0.0.1:{port}/?token={app.token}"
    # the printed URL opens the page and hands the page its cookie
    status, body, cookie = _get(url)
    assert status == 200 and "<html" in body.lower()
    assert cookie.startswith(f"thgs-viewer-token-{port}={app.token};")
    plain, cookie = f"http://127.0.0.1:{port}/", f"thgs-viewer-token-{port}={app.token}"
    assert _get(plain, Cookie=cookie, **{"Sec-Fetch-Site": "same-origin"})[0] == 200
    assert _get(plain, Cookie=cookie)[0] == 403  # the cookie replayed without the page's headers
    # no token; a rebound host name; another site's page: 403, and the scene is not sent
    for headers in (
        {},
        {"Host": f"attacker.example.com:{port}"},
        {"Origin": "http://evil.example"},
    ):
        status, body, _ = _get(plain if not headers else url, **headers)
        assert status == 403 and "thgs view:" in body and app.token not in body
    # the websocket that carries the scene and the GUI: only the page's own
    own = f"http://127.0.0.1:{port}"
    assert _websocket(port, own, cookie)
    assert not _websocket(port, "http://evil.example", cookie)
    assert not _websocket(port, own, None)
    assert not _websocket(port, own, "thgs-viewer-token=guess")
    assert all(app.token not in record.getMessage() for record in caplog.records)


def test_the_token_can_be_switched_off_but_not_the_host_checks(small_field):
    app = start_viewer(small_field, port=0, token=False)
    try:
        port = app.server.get_port()
        assert app.token is None and viewer_url(app, "127.0.0.1") == f"http://127.0.0.1:{port}"
        assert _get(f"http://127.0.0.1:{port}/")[0] == 200
        assert _get(f"http://127.0.0.1:{port}/", Host=f"evil.example:{port}")[0] == 403
        assert not _websocket(port, "http://evil.example", None)
        assert _websocket(port, f"http://localhost:{port}", None)
    finally:
        app.stop()
