"""Who may talk to the viewer's server (docs/viewer.md, "Who can connect").

A web page on any site, open in the user's browser, can send requests to ``127.0.0.1`` and open
websockets to it; a site whose name resolves to ``127.0.0.1`` (DNS rebinding) can even read the
answers. The viewer's server therefore answers a request (HTTP or the websocket handshake) only
when:

- its ``Host`` header names this server: a loopback name (``localhost``, ``127.0.0.1``,
  ``[::1]``), the address the server was started on, or the address the request arrived at, with
  the server's port (defeats DNS rebinding: the attacker's page sends its own host name);
- its ``Origin`` header, when present (browsers always send it on websocket handshakes and on
  cross-site requests), is ``http://`` one of those hosts with the same port (defeats other sites'
  pages);
- it carries the secret token made at start-up, as ``?token=…`` in the URL the viewer prints (as
  Jupyter does) or as the cookie the server sets when the page is loaded with it (so the page's
  own websocket is let in) — unless the user opted out (``token=None``). The cookie is named
  after the server's port (``thgs-viewer-token-<port>``: two viewers on one host keep their own)
  and counts only on a request the browser marks as the page's own: this server's ``Origin``
  (every websocket handshake) or ``Sec-Fetch-Site: same-origin`` (the page's files). Browsers
  send a ``127.0.0.1`` cookie to every port, so another local service receives it; replayed
  without those headers it opens nothing.

Anything else gets ``403 Forbidden`` and a logged warning (without the token). viser (1.1) has no
hook for this, so :func:`guarded_websockets` wraps ``websockets.asyncio.server.serve`` while the
viser server starts and passes a checking ``process_request`` in front of viser's own.
"""

from __future__ import annotations

import contextlib
import hmac
import http
import logging
import secrets
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from http.cookies import CookieError, SimpleCookie
from typing import Any
from urllib.parse import parse_qs, urlsplit

__all__ = ["AccessGuard", "guarded_websockets", "new_token"]

logger = logging.getLogger(__name__)

_LOOPBACK = frozenset({"localhost", "127.0.0.1", "::1"})
_COOKIE = "thgs-viewer-token"
"""The cookie's name before ``-<port>``."""
_PATCH = threading.Lock()


def new_token() -> str:
    """A fresh secret (32 URL-safe characters, 192 bits)."""
    return secrets.token_urlsafe(24)


def _host_name(value: str) -> tuple[str, int | None] | None:
    """``(name, port)`` of a ``Host`` header or the network location of a URL (IPv6 brackets
    removed, lower-case); None when it cannot be parsed."""
    try:
        parts = urlsplit(f"//{value}")
        return (parts.hostname or "").lower(), parts.port
    except ValueError:
        return None


@dataclass(frozen=True)
class AccessGuard:
    """The checks of one viewer server (module docstring).

    Attributes:
        host: the address the server was started on (``0.0.0.0`` and ``""`` add no name).
        token: the secret a request must carry, or None (the user opted out).
    """

    host: str
    token: str | None

    def problem(self, headers: Any, path: str, local: tuple[str, int]) -> str | None:
        """Why a request must be refused, or None to let it through.

        Args:
            headers: the request's headers (``get(name)`` and ``get_all(name)``).
            path: the request target (path and query).
            local: ``(address, port)`` the request arrived at.
        """
        address, port = local
        names = set(_LOOPBACK) | {address.lower()}
        if self.host not in ("", "0.0.0.0", "::"):
            names.add(self.host.lower())
        host = _host_name(headers.get("Host") or "")
        if host is None or host[0] not in names or host[1] not in (port, None):
            return f"Host {headers.get('Host')!r} is not this server"
        origin = headers.get("Origin")
        if origin is not None:
            parts = urlsplit(origin)
            try:
                same = (
                    parts.scheme == "http"
                    and (parts.hostname or "").lower() in names
                    and (parts.port or 80) == port
                )
            except ValueError:  # a port out of range
                same = False
            if not same:
                return f"Origin {origin!r} is not this server"
        if self.token is not None and not self._has_token(headers, path, port):
            return "no valid token (open the URL that thgs view printed)"
        return None

    def gave_token_in_url(self, path: str) -> bool:
        """Whether ``path`` carries the token as ``?token=…``."""
        given = parse_qs(urlsplit(path).query).get("token", [])
        return self.token is not None and any(
            hmac.compare_digest(value.encode(), self.token.encode()) for value in given
        )

    def set_cookie(self, port: int) -> str:
        """The ``Set-Cookie`` value that lets the page's later requests to ``port`` in."""
        return f"{_COOKIE}-{port}={self.token}; HttpOnly; SameSite=Strict; Path=/"

    def _has_token(self, headers: Any, path: str, port: int) -> bool:
        assert self.token is not None
        if self.gave_token_in_url(path):
            return True
        # the Origin, when present, was checked to be this server's
        own_page = (
            headers.get("Origin") is not None or headers.get("Sec-Fetch-Site") == "same-origin"
        )
        if not own_page:
            return False
        for line in headers.get_all("Cookie"):
            try:
                cookie = SimpleCookie(line)
            except CookieError:
                continue
            morsel = cookie.get(f"{_COOKIE}-{port}")
            if morsel is not None and hmac.compare_digest(
                morsel.value.encode(), self.token.encode()
            ):
                return True
        return False

    def wrap(self, process_request: Callable | None) -> Callable:
        """A websockets ``process_request`` that checks first, then calls ``process_request``
        (viser's static-file server) and hands the token's cookie to a page loaded with it."""

        def checked(connection: Any, request: Any) -> Any:
            local = connection.local_address[:2]
            reason = self.problem(request.headers, request.path, local)
            if reason is not None:
                logger.warning(
                    "viewer: refused a request for %s: %s", urlsplit(request.path).path, reason
                )
                return connection.respond(http.HTTPStatus.FORBIDDEN, f"thgs view: {reason}\n")
            response = process_request(connection, request) if process_request else None
            if response is not None and self.gave_token_in_url(request.path):
                response.headers["Set-Cookie"] = self.set_cookie(local[1])
            return response

        return checked


@contextlib.contextmanager
def guarded_websockets(guard: AccessGuard) -> Iterator[None]:
    """Within this block, every ``websockets.asyncio.server.serve`` call (the viser server being
    started) puts ``guard``'s checks in front of its ``process_request``."""
    import websockets.asyncio.server as server

    original = server.serve

    def serve(handler: Any, *args: Any, process_request: Any = None, **kwargs: Any) -> Any:
        return original(handler, *args, process_request=guard.wrap(process_request), **kwargs)

    with _PATCH:
        server.serve = serve  # type: ignore[misc]
        try:
            yield
        finally:
            server.serve = original  # type: ignore[misc]
