"""Refuse websocket connections from pages that are not the app's own.

A browser sends an ``Origin`` header with every websocket handshake; any page the user has open
(another site, a local file) could otherwise connect to the app on 127.0.0.1 and drive it.
viser 1.1.1 has no hook for this, so :func:`install` wraps the ``process_request`` that viser
passes to ``websockets.asyncio.server.serve`` (only for viser's own servers): a websocket
handshake whose Origin is not ``http://<Host>`` — or whose Host is a name other than
``localhost``, which defeats DNS rebinding — gets HTTP 403. Clients that send no Origin (not
browsers: scripts, tests) are let through; plain HTTP requests (the page itself) are unchanged.
"""

from __future__ import annotations

import http
import ipaddress
import threading
from typing import Optional
from urllib.parse import urlsplit

_lock = threading.Lock()
_installed = False


def _host_name(hostport: str) -> Optional[str]:
    try:
        return urlsplit("//" + hostport).hostname
    except ValueError:
        return None


def origin_allowed(origin: Optional[str], host: Optional[str]) -> bool:
    """True if a handshake with these ``Origin`` and ``Host`` headers may open a websocket."""
    if origin is None:
        return True
    if not host:
        return False
    name = _host_name(host)
    if name is None:
        return False
    if name != "localhost":
        try:
            ipaddress.ip_address(name)
        except ValueError:
            return False  # a DNS name pointing at this machine: the rebinding case
    o = urlsplit(origin)
    return o.scheme in ("http", "https") and o.netloc.lower() == host.lower()


def _guard(inner):
    def process_request(connection, request):
        h = request.headers
        if "websocket" in h.get("Upgrade", "").lower() and not origin_allowed(h.get("Origin"), h.get("Host")):
            return connection.respond(http.HTTPStatus.FORBIDDEN, "simgap: websocket from another origin refused\n")
        return inner(connection, request) if inner is not None else None

    return process_request


def install() -> None:
    """Wrap websockets' ``serve`` once so that viser's servers check the Origin (idempotent)."""
    global _installed
    with _lock:
        if _installed:
            return
        import websockets.asyncio.server as wss

        original = wss.serve

        def serve(handler, *args, **kw):
            if getattr(handler, "__module__", "").startswith("viser."):
                kw["process_request"] = _guard(kw.get("process_request"))
            return original(handler, *args, **kw)

        wss.serve = serve
        _installed = True
