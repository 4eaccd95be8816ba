"""A bound on an HTTP request's head (request line and headers), which uvicorn does not set.

Why: with httptools (uvicorn's default HTTP parser where installed) the parser buffers a header
value until its line ends, however long: one connection sending ``X: aaaa…`` without an end of
line made a worker hold every byte (200 MB sent, +313 MB of RSS), so a single client could push a
worker — and every session on it — out of memory. The body has its limit
(``QUATRACK_MAX_BODY_BYTES``, ``app.BodyLimit``); the head now has one too: more than
:data:`MAX_HEAD_BYTES` before the head ends is answered ``431`` with the contract's JSON error and
the connection is closed. ``quatrack serve`` and :class:`~quatrack.service.server.BackgroundServer`
pass :class:`BoundedHttpToolsProtocol` to uvicorn as ``http=``.
"""

from __future__ import annotations

import json

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

MAX_HEAD_BYTES = 64 * 1024  # nginx's default allows 4 × 8 KiB header lines; browsers send a few KiB


class BoundedHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol, refusing a request head longer than :data:`MAX_HEAD_BYTES`."""

    _awaiting_head = True  # from a request's first byte (or the connection's start) to its head's end
    _head_bytes = 0

    def on_message_begin(self) -> None:
        self._awaiting_head, self._head_bytes = True, 0
        super().on_message_begin()

    def on_headers_complete(self) -> None:
        self._awaiting_head = False
        super().on_headers_complete()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if not self._awaiting_head or self.transport.is_closing():
            return
        # the head has not ended after these bytes: all of them belong to it (nearly: the end of a
        # request pipelined before it may share the chunk, which only counts it early)
        self._head_bytes += len(data)
        if self._head_bytes > MAX_HEAD_BYTES:
            body = json.dumps({"error": {"code": "too_large", "message": f"the request line and headers may have "
                                                                         f"at most {MAX_HEAD_BYTES} bytes"}}).encode()
            self.transport.write(b"HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-type: application/json\r\n"
                                 b"content-length: " + str(len(body)).encode() + b"\r\nconnection: close\r\n\r\n" + body)
            self.transport.close()
