"""A clean close on SIGTERM: every open WebSocket session gets close code 1012 (service restart)
*and* its closing handshake completes before the connection is closed.

Why: uvicorn's shutdown (stop accepting, then ``shutdown()`` on every connection, then wait for
the connections to end) writes the 1012 close frame and closes the socket in the same breath.
A streaming client keeps sending frames meanwhile, so the socket usually has unread data when
it is closed, and then the kernel resets the connection (RST) and discards what was not yet
sent — often the close frame itself: the client, or nginx in front of the replica, sees the
connection drop (1006), about one stop in five under load.

:class:`GracefulWebSocketProtocol` is uvicorn's own WebSocket protocol (websockets, sans-I/O)
with two changes: on shutdown it sends 1012 and keeps the connection open until the client's
close frame comes back (frames still in flight are read and dropped meanwhile), so the socket
is closed with nothing unread (FIN, not RST). uvicorn's shutdown order is kept: the listening
socket is closed first (a balancer's next connect fails and goes to another replica), and
uvicorn already waits up to ``timeout_graceful_shutdown`` for the connections to end; a client
that never answers is cut after :data:`CLOSE_WAIT_S`. ``quatrack serve`` and
:class:`~quatrack.service.server.BackgroundServer` pass it to uvicorn as ``ws=``.
"""

from __future__ import annotations

from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol

SERVICE_RESTART = 1012  # RFC 6455 registry: "the server is restarting"
CLOSE_WAIT_S = 3.0  # a client's closing reply is awaited this long (below uvicorn's graceful timeout)


class GracefulWebSocketProtocol(WebSocketsSansIOProtocol):
    """uvicorn's WebSocket protocol whose shutdown completes the closing handshake."""

    def shutdown(self) -> None:
        if not self.handshake_complete or self.close_sent or self.transport.is_closing():
            return super().shutdown()  # not a session yet, or already closing: uvicorn's way
        self.stop_keepalive()
        # what uvicorn's shutdown does, minus closing the transport now: the app hears the
        # disconnect (its session ends), the client gets 1012
        self.queue.put_nowait({"type": "websocket.disconnect", "code": SERVICE_RESTART})
        self.conn.send_close(SERVICE_RESTART, "service restart")
        self.transport.write(b"".join(self.conn.data_to_send()))
        self.close_sent = True
        if self.read_paused:  # the client's close frame must be read
            self.read_paused = False
            self.transport.resume_reading()
        # the client's close frame ends the connection (handle_close); if none comes, cut it
        self.close_timer = self.loop.call_later(CLOSE_WAIT_S, self.transport.close)

    def handle_parser_exception(self) -> None:
        """A frame the parser refuses — over ``ws_max_size`` (1009, twice
        ``QUATRACK_MAX_BODY_BYTES``) or malformed (1002) — closed as :meth:`shutdown` closes: the
        close frame is written and the connection stays open (what the client still sends is read
        and discarded) until it ends or :data:`CLOSE_WAIT_S` passes. uvicorn closed the socket at
        once, while the client was still sending the oversized frame: the kernel reset the
        connection and the close frame was lost (the client saw 1006 for a 30 MB frame, 1009 for
        25 MB)."""
        if self.close_sent:  # (later data of a connection already closing: discarded)
            return
        assert self.conn.close_sent is not None
        code, reason = self.conn.close_sent.code, self.conn.close_sent.reason
        self.queue.put_nowait({"type": "websocket.disconnect", "code": code, "reason": reason})
        self.transport.write(b"".join(self.conn.data_to_send()))
        self.close_sent = True
        if self.read_paused:
            self.read_paused = False
            self.transport.resume_reading()
        self.close_timer = self.loop.call_later(CLOSE_WAIT_S, self.transport.close)
