"""The service as a user deploys it (token on, behind nginx or exposed): what a security review
found, one test per finding (each failed before its fix). The routes' auth, the constant-time
comparison and the redaction of ``?token=`` are also covered by test_service_http.py and
test_service_ws.py."""

from __future__ import annotations

import logging

import pytest

from quatrack.service.logs import ServiceLogFilter, redact

SECRET = "s3cr3t-T0KEN"


@pytest.mark.parametrize("query", [
    f"token={SECRET}", f"TOKEN={SECRET}", f"%74oken={SECRET}", f"tok%65n={SECRET}", f"%54%4F%4B%45%4E={SECRET}",
    f"a=1&token={SECRET}", f"a=1;token={SECRET}", f"access_token={SECRET}", f"token=wrong&token={SECRET}",
    "token=ab'cd(" + SECRET + ")",
])
def test_a_token_is_redacted_however_its_key_is_written(query):
    """The server reads the query's keys percent-decoded (``?%74oken=`` is ``?token=`` to it), but
    the log filter looked for the literal ``token=``: a client that encoded the key had its token
    written in uvicorn's WebSocket line. A value with a quote or a bracket in it (left as they are
    by encodeURIComponent, which the viewer uses) was cut at the quote."""
    line = f'127.0.0.1:5000 - "WebSocket /v1/objects/cookie-box/track?{query}" [accepted]'
    clean = redact(line)
    assert SECRET not in clean and "[redacted]" in clean, clean
    record = logging.LogRecord("uvicorn.error", logging.INFO, __file__, 1, '%s - "WebSocket %s" [accepted]',
                               ("127.0.0.1:5000", f"/v1/objects/cookie-box/track?{query}"), None)
    ServiceLogFilter().filter(record)
    assert SECRET not in record.getMessage()


def test_redaction_leaves_other_parameters_and_messages_alone():
    assert redact("/v1/objects/cookie-box/pose?fx=1&fy=2&format=ros") == "/v1/objects/cookie-box/pose?fx=1&fy=2&format=ros"
    assert redact("a valid bearer token is required (the Authorization header, or the query parameter token)") == \
        "a valid bearer token is required (the Authorization header, or the query parameter token)"
    assert redact("/track?token=") == "/track?token="  # nothing to hide
