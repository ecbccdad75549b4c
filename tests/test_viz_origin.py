"""The app's websocket refuses handshakes from pages that are not its own (cross-site, DNS rebinding)."""

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from simgap_viz.origin import origin_allowed


@pytest.mark.parametrize("origin,host,ok", [
    (None, "127.0.0.1:8080", True),                      # not a browser
    ("http://127.0.0.1:8080", "127.0.0.1:8080", True),   # the app's own page
    ("http://localhost:8080", "localhost:8080", True),
    ("http://[::1]:8080", "[::1]:8080", True),
    ("http://evil.example", "127.0.0.1:8080", False),    # another site
    ("null", "127.0.0.1:8080", False),                   # a local file or sandboxed frame
    ("http://127.0.0.1:9999", "127.0.0.1:8080", False),  # another local server
    ("http://evil.example:8080", "evil.example:8080", False),  # DNS rebinding: same origin, but a name
    ("http://127.0.0.1:8080", None, False),
])
def test_origin_rule(origin, host, ok):
    assert origin_allowed(origin, host) is ok


def test_running_app_refuses_foreign_origins():
    from simgap_viz.app import SimgapApp

    app = SimgapApp(port=0, executor="serial")
    try:
        port = app.server.get_port()
        url = f"ws://127.0.0.1:{port}"
        with pytest.raises(InvalidStatus) as e:
            connect(url, origin="http://evil.example", subprotocols=["viser-v1"], open_timeout=10).close()
        assert e.value.response.status_code == 403
        # the app's own page connects (the handshake completes)
        connect(url, origin=f"http://127.0.0.1:{port}", open_timeout=10).close()
    finally:
        app.stop()
