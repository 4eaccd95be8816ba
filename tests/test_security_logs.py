"""Credentials in headers never reach the logs: ``--log-level debug`` made the websockets library
write every handshake header, ``authorization: Bearer TOKEN`` included, although the README says
the header is never logged."""

from __future__ import annotations

import json
import logging

import pytest

from quatrack.service.logs import ServiceLogFilter, redact
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store

SECRET = "s3cr3t-T0KEN"


@pytest.mark.parametrize("msg, args", [
    ("< %s: %s", ("authorization", f"Bearer {SECRET}")),  # websockets' handshake lines
    ("< %s: %s", ("Proxy-Authorization", f"Basic {SECRET}")),
    ("< %s: %s", ("cookie", f"session={SECRET}; theme=dark")),
    ("> %s: %s", ("Set-Cookie", f"session={SECRET}; HttpOnly")),
    ("headers %r", ({"authorization": f"Bearer {SECRET}", "host": "x"},)),
    ("scope headers %r", ([(b"authorization", f"Bearer {SECRET}".encode()), (b"host", b"x")],)),
])
def test_credential_headers_are_redacted_in_every_record(msg, args):
    record = logging.LogRecord("uvicorn.error", logging.DEBUG, __file__, 1, msg, args, None)
    record.headers_seen = f"authorization: Bearer {SECRET}"  # an extra field, as the JSON formatter writes them
    ServiceLogFilter().filter(record)
    assert SECRET not in record.getMessage() and "[redacted]" in record.getMessage(), record.getMessage()
    assert SECRET not in record.headers_seen


def test_other_lines_are_left_alone():
    for text in ("a valid bearer token is required (the Authorization header, or the query parameter token)",
                 "< host: 127.0.0.1:8000", "< sec-websocket-key: +i2bPyuVL2j/Qfj0O4UPPQ==", "cookie-box loaded"):
        assert redact(text) == text


def test_a_debug_log_of_a_session_holds_no_token(capfd):
    """End to end: a session opened with the header, the server at ``--log-level debug``."""
    from websockets.sync.client import connect

    camera = {"width": 640, "height": 480, "fx": 669.7, "fy": 667.8, "cx": 320.0, "cy": 240.0}
    with BackgroundServer(Settings(store=example_store(), api_token=SECRET, model_poll_s=0), log_level="debug") as srv:
        url = srv.url.replace("http://", "ws://") + "/v1/objects/cookie-box/track"
        with connect(url, additional_headers={"Authorization": f"Bearer {SECRET}", "Cookie": f"c={SECRET}"},
                     open_timeout=60) as ws:
            ws.send(json.dumps({**camera, "ack": True}))
            assert json.loads(ws.recv(timeout=60))["type"] == "ready"
    err = capfd.readouterr().err
    assert "authorization: [redacted]" in err.lower(), err[-3000:]  # (the debug lines were written)
    assert SECRET not in err
