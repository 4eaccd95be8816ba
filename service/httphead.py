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
    """uvicorn's httptools protocol, refusing a request head longer than :data:`MAX_HEAD_BYTES`.

    The head's bytes are counted before the parser sees them, up to the blank line that ends it,
    so a head over the bound is refused whether it never ends or arrives whole in one read (a
    complete 100 KB head was passed to the app: only the bytes of a head not yet ended counted)."""

    _awaiting_head = True  # from a request's first byte (or the connection's start) to its head's end
    _head_bytes = 0
    _tail = b""  # the head's last 3 bytes so far: its end, CRLF CRLF, may straddle two reads

    def on_message_begin(self) -> None:
        self._awaiting_head = True
        super().on_message_begin()

    def on_headers_complete(self) -> None:
        self._awaiting_head = False
        super().on_headers_complete()

    def on_message_complete(self) -> None:
        # the next bytes on this connection are the next request's head
        self._awaiting_head, self._head_bytes, self._tail = True, 0, b""
        super().on_message_complete()

    def data_received(self, data: bytes) -> None:
        if self._awaiting_head and not self.transport.is_closing():
            seen = self._tail + data
            end = seen.find(b"\r\n\r\n")
            # this read's bytes that belong to the head (a request pipelined behind it in the same
            # read is counted from its own next read on: at most one read more than the bound)
            n = len(data) if end < 0 else end + 4 - len(self._tail)
            self._head_bytes += n
            self._tail = seen[-3:] if end < 0 else b""
            if self._head_bytes > MAX_HEAD_BYTES:
                self._refuse()
                return
        super().data_received(data)

    def _refuse(self) -> None:
        body = json.dumps({"error": {"code": "too_large", "message": f"the request line and headers may have "
                                                                     f"at most {MAX_HEAD_BYTES} bytes"}}).encode()
        self.transport.write(b"HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-type: application/json\r\n"
                             b"content-length: " + str(len(body)).encode() + b"\r\nconnection: close\r\n\r\n" + body)
        self.transport.close()
