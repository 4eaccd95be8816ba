"""``quatrack serve``: the command-line side of the service (``quatrack demo`` is in :mod:`.demo`).

``serve`` only parses options into :class:`Settings` and hands the app to uvicorn.
"""

from __future__ import annotations

import argparse


def add_serve(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--store", metavar="DIR", help="model store (default: $QUATRACK_STORE or the user data directory)")
    parser.add_argument("--host", default=None, help="address to listen on (default 127.0.0.1, or $QUATRACK_HOST)")
    parser.add_argument("--port", type=int, default=None, help="port (default 8000, or $QUATRACK_PORT)")
    parser.add_argument("--workers", type=int, default=None, metavar="N", help="CPU worker threads (default 2)")
    parser.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])


def run_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from .app import create_app
    from .logs import configure
    from .settings import Settings

    settings = Settings.from_env(store=args.store, host=args.host, port=args.port, workers=args.workers)
    if settings.store.exists() and not settings.store.is_dir():
        raise ValueError(f"--store {settings.store}: not a directory")
    app = create_app(settings)
    # frames up to max_body_bytes are answered; up to twice that get a "too_large" error message
    # and the session goes on; beyond, the server closes the socket (1009) without buffering it
    uvicorn.run(app, host=settings.host, port=settings.port, log_config=configure(args.log_level),
                ws_max_size=2 * settings.max_body_bytes, timeout_graceful_shutdown=5, server_header=False)
    return 0
