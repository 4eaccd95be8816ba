"""``quatrack serve``: the command-line side of the service (``quatrack demo``, a client of the service, is in :mod:`quatrack.demo`).

``serve`` parses options into :class:`Settings`, prepares the run directory the worker processes
share (:mod:`.workers`) and hands uvicorn the app factory: one worker process per ``--workers``
(default: the number of cores), all accepting on one socket, each with an event loop that
follows the placement rule of :mod:`.placement` (a worker serves a new connection only while its
load is no more than the least-loaded worker's; it passes the others to that one).
"""

from __future__ import annotations

import argparse
import errno


#: the end of ``quatrack serve --help``: where the other settings are and which value wins
SERVE_EPILOG = ("Every setting is also a QUATRACK_* environment variable (QUATRACK_API_TOKEN, QUATRACK_MAX_SESSIONS, "
                "...: `python -m quatrack.service.settings` lists them all, as the README's table). An option given "
                "here wins over its variable, which wins over the default; an empty variable counts as unset. "
                "A variable whose name is no setting (a typo) or whose value is empty is warned of at start.")


def add_serve(parser: argparse.ArgumentParser) -> None:
    parser.epilog = SERVE_EPILOG
    parser.add_argument("--store", metavar="DIR",
                        help="model store (default: $QUATRACK_STORE, else $XDG_DATA_HOME/quatrack/models)")
    parser.add_argument("--host", default=None, help="address to listen on (default: $QUATRACK_HOST, else 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None, help="port (default: $QUATRACK_PORT, else 8000)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="worker processes, each with its own sessions (default: $QUATRACK_WORKERS, else the number of cores)")
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help="CPU threads per worker process (default: $QUATRACK_THREADS, else cores ÷ workers, at least 1)")
    parser.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"],
                        help="least severe log messages written, as JSON lines on stderr (default: info)")


def check_address(host: str, port: int) -> None:
    """Raise ValueError (one line for the user) unless the service can listen on ``host:port``:
    the name resolves and nothing else listens there. Why here: uvicorn finds out only after the
    models are loaded, logs one JSON line and exits 3, the last lines printed being the models
    loaded, as if the server had started. Bound (with SO_REUSEADDR, as uvicorn binds) and closed
    at once: another process may still take the port in between, and uvicorn then reports it."""
    import socket

    # the family uvicorn binds (IPv6 for a host with ':', else IPv4), then any the name has
    found, why = None, None
    for family in (socket.AF_INET6 if ":" in host else socket.AF_INET, socket.AF_UNSPEC):
        try:
            found = socket.getaddrinfo(host, port, family, socket.SOCK_STREAM)[0]
            break
        except (socket.gaierror, UnicodeError) as exc:
            why = getattr(exc, "strerror", None) or exc
    if found is None:
        raise ValueError(f"--host {host}: cannot resolve it ({why})")
    family, kind, proto, _, address = found
    with socket.socket(family, kind, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(address)
        except OSError as exc:
            hint = " (is another server running there?)" if exc.errno == errno.EADDRINUSE else ""
            raise ValueError(f"--host {host} --port {port}: cannot listen there: {exc.strerror or exc}{hint}") from None


def exposed_without_token(host: str, token: str | None) -> str | None:
    """The warning for a server that listens beyond this machine without a token, else None:
    every endpoint (the objects, pose, tracking sessions, reload, metrics) is then open to
    whoever reaches the port. Loopback addresses and ``localhost`` are quiet."""
    import ipaddress

    if token is not None or host.strip().lower() == "localhost":
        return None
    try:
        if ipaddress.ip_address(host.strip().strip("[]")).is_loopback:
            return None
    except ValueError:
        pass  # a name other than localhost: it resolves to an address others may reach
    return (f"listening on {host} without a token: anyone who can reach the port may use every endpoint "
            f"(set QUATRACK_API_TOKEN, or listen on 127.0.0.1)")


def unlearned_objects(learn_views, store) -> list[str]:
    """One line per object named in ``QUATRACK_LEARN_VIEWS`` that the store does not hold (a
    typo, another case): its sessions would never learn, in silence, since the names are compared
    whole (``service/learning.py``). With the nearest name and the objects held
    (:func:`~quatrack.viewsets.store.names_hint`). An object trained into the store later is
    learned from, so this is a warning. Nothing for ``*`` or a store that does not exist (warned
    of already)."""
    from pathlib import Path

    from quatrack.viewsets.store import list_models, names_hint

    if "*" in learn_views or not Path(store).is_dir():
        return []
    held = list_models(store)
    return [f"QUATRACK_LEARN_VIEWS names {name!r}, which the store does not hold{names_hint(name, held)}: "
            f"its sessions learn no views until an object of that name is trained"
            for name in learn_views if name not in held]


def run_serve(args: argparse.Namespace) -> int:
    import os
    import shutil

    import sys

    from quatrack.viewsets.store import store_note

    from .settings import Settings, env_warnings

    # before the settings are checked, so that a misspelt name is told even when a value is refused
    for line in env_warnings():
        print(f"quatrack serve: warning: {line}", file=sys.stderr, flush=True)
    options = {"store": args.store, "host": args.host, "port": args.port, "workers": args.workers, "threads": args.threads}
    try:
        settings = Settings.from_env(**options)
    except ValueError as exc:  # "threads=0: ..." names the option as the other errors of the command do: "--threads 0: ..."
        text = str(exc)
        for name, value in options.items():
            if value is not None and text.startswith(f"{name}={value!r}: "):
                shown = value if str(value).strip() else repr(value)  # (a blank one quoted)
                text = f"--{name} {shown}: " + text[len(f"{name}={value!r}: "):]
        raise ValueError(text) from None
    if settings.store.exists() and not settings.store.is_dir():
        raise ValueError(f"--store {settings.store}: not a directory")
    if not settings.store.exists():  # (a typo in --store or QUATRACK_STORE: ready, with no object, in silence)
        print(f"quatrack serve: warning: the store {settings.store} does not exist: no object to serve until "
              f"one is trained into it (quatrack train --store {settings.store} ...)", file=sys.stderr, flush=True)
    elif note := store_note(settings.store):  # (a model's own folder: served as an empty store, in silence)
        print(f"quatrack serve: warning: the store {settings.store} holds no object{note}", file=sys.stderr, flush=True)
    for line in unlearned_objects(settings.learn_views, settings.store):
        print(f"quatrack serve: warning: {line}", file=sys.stderr, flush=True)
    check_address(settings.host, settings.port)
    exposed = exposed_without_token(settings.host, settings.api_token)
    if exposed:
        print(f"quatrack serve: warning: {exposed}", file=sys.stderr, flush=True)
    from .workers import prepare_run_dir

    settings, run_dir, made, run_lock = prepare_run_dir(settings)  # before uvicorn (and prometheus-client) start
    os.environ.update(settings.to_env())  # the workers rebuild the settings from these
    # uvicorn re-raises the SIGTERM it caught once it has shut down; with the default handler that
    # killed the process before the finally below, and every 1-worker run left its run directory
    # in the temp dir (quatrack-run-*; `bench serve`'s 1-worker setups too). Exit status stays 143.
    import signal
    import threading

    previous = None
    if threading.current_thread() is threading.main_thread():
        def _terminated(signum, frame):
            raise SystemExit(128 + signum)

        previous = signal.signal(signal.SIGTERM, _terminated)
    try:
        import uvicorn

        from .httphead import BoundedHttpToolsProtocol
        from .logs import configure
        from .shutdown import GracefulWebSocketProtocol

        # frames up to max_body_bytes are answered; up to twice that get a "too_large" error message
        # and the session goes on; beyond, the server closes the socket (1009) without buffering it.
        # On SIGTERM every open session is closed with code 1012 (service restart), and its
        # closing handshake completes before the connection is closed (service/shutdown.py).
        # With several workers, each one's event loop comes from service/placement.py: a worker
        # holding more sessions than the least-loaded one stops accepting connections meanwhile,
        # and passes those it accepted in a burst to the least-loaded one before reading them.
        loop = "quatrack.service.placement:loop_factory" if settings.workers > 1 else "auto"
        # No permessage-deflate: the frames are JPEG/PNG/WebP, which deflate cannot shrink, and each
        # one was compressed by the client and inflated on the worker's event loop for nothing.
        uvicorn.run("quatrack.service.workers:app_from_env", factory=True, workers=settings.workers,
                    ws=GracefulWebSocketProtocol, loop=loop, ws_per_message_deflate=False,
                    http=BoundedHttpToolsProtocol,  # a request head of at most 64 KiB (service/httphead.py)
                    limit_concurrency=settings.max_connections,  # per worker: uvicorn's plain-text 503 beyond
                    host=settings.host, port=settings.port, log_config=configure(args.log_level),
                    ws_max_size=2 * settings.max_body_bytes, timeout_graceful_shutdown=5, server_header=False)
    finally:
        os.close(run_lock)  # (the run directory free for the next server, in this process too)
        if made:
            shutil.rmtree(run_dir, ignore_errors=True)
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return 0
