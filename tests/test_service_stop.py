"""Stopping the server (SIGTERM: uvicorn's shutdown) while a REST upload is still being read:
after the graceful timeout the request is answered 503 ``shutting_down`` as JSON, with no
traceback in the log (it was uvicorn's plain-text 500 and "Exception in ASGI application")."""

from __future__ import annotations

import json
import logging
import socket
import threading

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store
from test_service_models import Records


def test_a_slow_upload_cut_by_the_stop_gets_a_json_503_and_no_traceback():
    server = BackgroundServer(Settings(store=example_store()))
    logs = Records()
    names = ("uvicorn.error", "quatrack.service")
    with server as srv:
        for name in names:
            logging.getLogger(name).addHandler(logs)
        try:
            with socket.create_connection(("127.0.0.1", srv.port), timeout=30) as s:
                s.sendall(b"POST /v1/objects/cookie-box/pose?fx=600&fy=600&cx=320&cy=240 HTTP/1.1\r\nHost: x\r\n"
                          b"Content-Type: image/jpeg\r\nContent-Length: 100000\r\n\r\n\xff\xd8\xff" + b"a" * 1000)
                stopper = threading.Thread(target=srv.stop)  # as SIGTERM: uvicorn's shutdown, 2 s graceful timeout
                stopper.start()
                answer = b""
                while chunk := s.recv(65536):
                    answer += chunk
                stopper.join()
        finally:
            for name in names:
                logging.getLogger(name).removeHandler(logs)
    head, _, body = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 503"), answer[:300]
    assert json.loads(body)["error"]["code"] == "shutting_down", body
    assert not [r for r in logs.records if r.exc_info], [r.getMessage() for r in logs.records if r.exc_info]
