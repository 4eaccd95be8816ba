"""Service settings: one pydantic-settings class, read from ``QUATRACK_*`` environment variables.

Why pydantic-settings: types, bounds, defaults and the documentation of every variable live on
the field (the README's settings table is generated from these descriptions and a test checks it
lists every field). Precedence, highest first: values passed in code (``Settings(port=1)``, CLI
options through :meth:`Settings.from_env`), then ``QUATRACK_<FIELD>``, then the default. Empty
variables count as unset. ``quatrack serve --workers N`` hands its settings to the worker
processes through the same variables (:meth:`Settings.to_env`).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Annotated

from pydantic import Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from quatrack.recognition.tracker.params import TrackerParams
from quatrack.viewsets.store import resolve_store

ENV_PREFIX = "QUATRACK_"
# Bounds that are not the type's. Every float setting is also finite (``allow_inf_nan=False``):
# ``QUATRACK_MAX_FPS=inf`` was accepted, and the token bucket then added ``0 × inf`` (NaN);
# ``QUATRACK_MODEL_POLL_S=inf`` (or above ``threading.TIMEOUT_MAX``) killed the store's watcher
# thread with an OverflowError at its first wait, after a clean start.
SECRET_FIELDS = frozenset({"api_token"})  # never echoed in an error line
MAX_SESSIONS = 10_000  # the slots are files: /metrics probes each of them at every scrape (70 ms for 10 000)


def usable_cores() -> int:
    """CPUs this process may use: its affinity mask, capped by a cgroup v2 CPU quota (a container's
    ``--cpus`` or Kubernetes limit), which ``os.cpu_count()`` ignores. Quota q µs per period p µs
    gives ceil(q / p) CPUs."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()[:2]
        if quota != "max":
            n = min(n, max(1, -(-int(quota) // int(period))))
    except (OSError, ValueError):
        pass
    return max(1, n)


class Settings(BaseSettings):
    """Everything an operator may tune. Sizes in bytes/pixels, times in seconds."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, frozen=True, extra="ignore", env_ignore_empty=True,
                                      validate_default=True)

    store: Path = Field(default_factory=lambda: resolve_store(None),
                        description="model store directory (default: `$XDG_DATA_HOME/quatrack/models`)")
    host: str = Field("127.0.0.1", description="address to listen on (`0.0.0.0` in containers)")
    port: int = Field(8000, ge=1, le=65535, description="TCP port")
    api_token: str | None = Field(None, description="bearer token required on everything but `/healthz`, `/readyz`, "
                                                     "the API's description (`/docs`, `/redoc`, `/openapi.json`) "
                                                     "and the viewer's page (`/viewer`)")
    cors_origins: Annotated[tuple[str, ...], NoDecode] = Field(
        (), description="comma-separated origins allowed by CORS, e.g. `https://example.org`; `*` allows any")
    allowed_hosts: Annotated[tuple[str, ...], NoDecode] = Field(
        (), description="comma-separated host names the server answers to (the request's `Host`, without its port), "
                        "e.g. `localhost,127.0.0.1,::1`; `*.example.org`: its subdomains. Another `Host` is refused, "
                        "400 `invalid_host`, except on `/healthz` and `/readyz` (DNS rebinding; see Security). "
                        "Default: any")
    workers: int = Field(default_factory=usable_cores, ge=1, le=256,
                         description="worker processes, each with its own models and sessions (default: the number of cores)")
    threads: int | None = Field(None, ge=1, le=64, description="CPU threads per worker process doing recognition and "
                                "tracking (default: the number of cores ÷ workers, at least 1)")
    thread_nice: int = Field(5, ge=0, le=19, description="nice value of those threads (Linux, per thread), "
                                                         "so that the event loop (probes, frames in, poses "
                                                         "out) gets a core first; 0: off")
    switch_interval_ms: float = Field(1.0, gt=0, le=100, allow_inf_nan=False, description="the interpreter's switch interval in worker "
                                                                     "processes: how long a thread running Python keeps "
                                                                     "the lock while the event loop waits for it")
    max_body_bytes: int = Field(10 * 1024 * 1024, ge=1, description="largest REST body and WebSocket frame, bytes")
    max_image_pixels: int = Field(20_000_000, ge=1, description="larger images are refused before decoding (decompression bombs)")
    locate_max_pixels: int = Field(4_000_000, ge=1, description="larger images are downscaled for recognition")
    max_pending_requests: int = Field(8, ge=1, description="REST pose requests being received, queued or running "
                                      "**per worker process**; then 503 `busy` before the body is read")
    body_timeout_s: float = Field(60.0, gt=0, le=threading.TIMEOUT_MAX, allow_inf_nan=False,
                                  description="a REST pose request's whole body must arrive within this many seconds "
                                              "of its headers; else 408 `body_timeout` (a slow upload holds a "
                                              "pending slot that long at most)")
    max_sessions: int = Field(4, ge=1, le=MAX_SESSIONS, description="concurrent WebSocket sessions **for the whole server** (all workers); then 503 + Retry-After")
    max_connections: int | None = Field(
        None, ge=1, description="open connections **per worker process** (WebSocket sessions, keep-alive, uploads, "
                                "probes) beyond which a new HTTP request is answered uvicorn's plain-text 503 "
                                "(uvicorn's `limit_concurrency`; default: `QUATRACK_MAX_SESSIONS` + "
                                "`QUATRACK_MAX_PENDING_REQUESTS` + 64)")
    max_fps: float = Field(60.0, gt=0, allow_inf_nan=False, description="frames a session may send per second (token bucket); above: refused while an earlier frame is unanswered, a lock-step frame waits for its turn")
    idle_timeout_s: float = Field(60.0, gt=0, allow_inf_nan=False, description="a session with no message for this long is closed")
    retry_after_s: int = Field(5, ge=0, description="`Retry-After` seconds sent with 503 answers")
    preload: bool = Field(True, description="load every model of the store at start-up (`/readyz` waits for it)")
    model_poll_s: float = Field(2.0, ge=0, le=threading.TIMEOUT_MAX, allow_inf_nan=False, description="how often the store is checked for retrained, new and deleted models "
                                                      "(new sessions get them; 0: never, `POST /v1/objects/{name}/reload` still works)")
    learn_views: Annotated[tuple[str, ...], NoDecode] = Field(
        (), description="comma-separated objects whose tracking sessions learn views of the sides their photos do not "
                        "show, added to the stored model when the session ends (`*`: every object; default: none)")
    tracker_sources: Annotated[tuple[str, ...], NoDecode] = Field(
        TrackerParams().sources,
        description="comma-separated measurement sources of the tracker (some of `trained`, `mesh`, `edges`, `contour`): "
                    "without `contour` (the outline by colour) a step costs about a fifth less and is less accurate")
    relocate_interval_s: float = Field(0.0, ge=0, allow_inf_nan=False, description="while a session's object is lost, search for it at "
                                       "most once per this many seconds of the frames' time (0: every frame). A failed "
                                       "search costs 0.1-0.6 s of CPU, so a stream whose object is out of view holds a "
                                       "thread that the other sessions wait for; e.g. 0.25 frees most of it and finds "
                                       "the object again up to that much later")
    run_dir: Path | None = Field(None, description="directory the worker processes share (session slots, Prometheus "
                                                    "multiprocess files); `quatrack serve` makes a fresh one and wipes it on start. One "
                                                    "server per directory: a second `quatrack serve` given one a live server holds "
                                                    "(`server.lock`) is refused (exit 2)")

    @field_validator("cors_origins", "learn_views", "tracker_sources", "allowed_hosts", mode="before")
    @classmethod
    def _split_origins(cls, v):
        if isinstance(v, str):
            return tuple(o.strip() for o in v.split(",") if o.strip())
        return v

    @field_validator("threads", mode="after")
    @classmethod
    def _threads_per_core(cls, v: int | None, info) -> int:
        """Default: the cores shared out between the workers. Why: on 2 cores, 2 workers of 2
        threads each (4 threads) processed 87.7 frames/s from 16 streams and 1 worker of 2
        threads 62.1 (×1.41); 2 workers of 1 thread 92.2 against 1 worker of 1 thread 45.8
        (×2.01), with a lower p99 (bench/RESULTS.md, serving, session 26). One worker still gets
        every core."""
        if v is not None:
            return v
        return max(1, usable_cores() // max(1, int(info.data.get("workers") or 1)))

    @field_validator("max_connections", mode="after")
    @classmethod
    def _connections_for_the_limits(cls, v: int | None, info) -> int:
        """Default: every session and pending request (a worker may hold all of the server's
        sessions), and 64 more for probes, scrapes and a balancer's idle keep-alive connections.
        Why a cap at all: uvicorn has none, and every connection a client opens and holds costs
        the worker memory and a file descriptor until it runs out."""
        if v is not None:
            return v
        return int(info.data.get("max_sessions") or 0) + int(info.data.get("max_pending_requests") or 0) + 64

    @field_validator("store", mode="after")
    @classmethod
    def _expand(cls, v: Path) -> Path:
        return Path(v).expanduser()

    @field_validator("tracker_sources", mode="after")
    @classmethod
    def _known_sources(cls, v):
        # (raises ValueError naming what is unknown; checked on the field, so that the one-line
        # error names QUATRACK_TRACKER_SOURCES, not "settings")
        TrackerParams(sources=v)
        return v

    @field_validator("cors_origins", mode="after")
    @classmethod
    def _origins(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        """Origins as browsers send them (``Origin: https://example.org``, compared whole by the
        CORS middleware and the WebSocket's origin check): ``https://example.org/`` (a trailing
        slash, as copied from the address bar), ``https://Example.org`` or ``https://example.org:443``
        never matched, silently; they are normalised. A name without a scheme or a URL with a path
        matches nothing: refused, naming the entry. ``*`` and ``null`` stay as they are."""
        from urllib.parse import urlsplit

        out = []
        for entry in v:
            if entry in ("*", "null"):
                out.append(entry)
                continue
            try:
                u = urlsplit(entry)
                port = u.port
            except ValueError:
                u, port = None, None
            if u is None or not u.scheme or not u.hostname or u.path not in ("", "/") or u.query or u.fragment \
                    or u.username is not None:
                raise ValueError(f"{entry!r} is not an origin (scheme://host[:port], e.g. https://example.org)")
            host = f"[{u.hostname}]" if ":" in u.hostname else u.hostname
            default = {"http": 80, "https": 443}.get(u.scheme.lower())
            out.append(f"{u.scheme.lower()}://{host}" + (f":{port}" if port is not None and port != default else ""))
        return tuple(out)

    @field_validator("allowed_hosts", mode="after")
    @classmethod
    def _host_names(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        """Names as they are compared (lower case, an IPv6 address without brackets, no final
        dot); a URL or a port is refused, naming the entry: ``Host`` is compared without its port."""
        out = []
        for entry in v:
            name = entry.lower().rstrip(".")
            if name.startswith("[") and name.endswith("]"):
                name = name[1:-1]
            if "/" in name or name.count(":") == 1 or not name:
                raise ValueError(f"{entry!r} is not a host name (give names or addresses without a scheme or port, "
                                 f"e.g. localhost,127.0.0.1)")
            out.append(name)
        return tuple(out)

    @field_validator("host", mode="after")
    @classmethod
    def _host_not_blank(cls, v: str) -> str:
        # (on the field, so that the one-line error names QUATRACK_HOST or --host, not "settings")
        if not v.strip():
            raise ValueError("the address must not be blank")
        # an IPv6 address as URLs write it ([::1]): uvicorn and getaddrinfo want it bare ("cannot resolve it")
        return v[1:-1] if v.startswith("[") and v.endswith("]") else v

    @field_validator("api_token", mode="after")
    @classmethod
    def _token_sendable(cls, v: str | None) -> str | None:
        """Surrounding whitespace is removed (a secret file's line end, ``kubectl create secret
        --from-file``): HTTP strips it from a header's value, so a token ending in ``\\n`` refused
        every client. A token of whitespace only was accepted the same way, and one with a control
        character inside (a line break) cannot be sent in a header at all: both are refused."""
        if v is None:
            return None
        v = v.strip()
        if not v:
            raise ValueError("the token must not be blank (it is whitespace only)")
        if any(ord(c) < 32 or ord(c) == 127 for c in v):
            raise ValueError("the token has a control character (a line break?): "
                             "an Authorization header cannot carry it")
        # A non-ASCII token (``tökén``, an emoji) was accepted, and no client could ever send it:
        # HTTP header values travel as bytes, read by the server as latin-1, while clients encode
        # them as UTF-8 (or refuse to send them), so the header never matched.
        if not v.isascii():
            raise ValueError("the token has a character that is not ASCII: an Authorization header cannot carry it "
                             "as every client sends it (use letters, digits and ASCII punctuation)")
        return v

    @field_validator("run_dir", mode="after")
    @classmethod
    def _run_dir_is_a_directory(cls, v: Path | None) -> Path | None:
        if v is not None and Path(v).expanduser().exists() and not Path(v).expanduser().is_dir():
            raise ValueError("not a directory")
        return None if v is None else Path(v).expanduser()

    @classmethod
    def from_env(cls, **overrides) -> "Settings":
        """Settings from ``QUATRACK_*`` variables; explicit, non-None ``overrides`` (CLI options) win.
        A bad value is one line naming the variable (or option), as a ``ValueError``."""
        given = {k: v for k, v in overrides.items() if k in cls.model_fields and v is not None}
        try:
            return cls(**given)
        except ValidationError as exc:
            raise ValueError(describe(exc, given)) from None

    def checked(self) -> "Settings":
        """Kept for callers of the former dataclass: validation now happens on construction."""
        return self

    def replace(self, **changes) -> "Settings":
        """A copy with ``changes``, validated like a new instance (``model_copy`` does not validate)."""
        try:
            return type(self).model_validate({**self.model_dump(), **changes})
        except ValidationError as exc:
            raise ValueError(describe(exc, changes)) from None

    def to_env(self) -> dict[str, str]:
        """The ``QUATRACK_*`` variables that rebuild these settings in another process."""
        out = {}
        for name, value in self.model_dump().items():
            if value is None:
                continue
            if isinstance(value, (tuple, list)):
                value = ",".join(value)
            out[env_name(name)] = str(value)
        return out


def env_name(field: str) -> str:
    return ENV_PREFIX + field.upper()


# variables an operator may look for that are options of ``quatrack serve``, not settings: the
# nearest setting's name was no help (QUATRACK_LOG_LEVEL -> "did you mean QUATRACK_STORE?")
COMMAND_OPTIONS = {
    **dict.fromkeys((ENV_PREFIX + "LOG_LEVEL", ENV_PREFIX + "LOGLEVEL", ENV_PREFIX + "LOG"),
                    "the log level is the option --log-level of quatrack serve: debug, info, warning or error"),
}


def env_warnings(environ=None) -> list[str]:
    """One line per ``QUATRACK_*`` variable the settings will not use as the operator may think:
    a name no setting has (``QUATRACK_API_TOKNE``: the server would start without a token), with
    the setting it is nearest to, and an empty value, which counts as unset (the default is used;
    for ``QUATRACK_API_TOKEN``: no token is required). Names are matched as pydantic-settings
    matches them, whatever their case."""
    import difflib

    environ = os.environ if environ is None else environ
    known = {env_name(f) for f in Settings.model_fields}
    out = []
    for key in sorted(environ):
        name = key.upper()
        if not name.startswith(ENV_PREFIX):
            continue
        if name not in known:
            near = difflib.get_close_matches(name, sorted(known), n=1, cutoff=0.6)
            hint = f" (did you mean {near[0]}?)" if near else " (the settings are listed by `python -m quatrack.service.settings`)"
            if name in COMMAND_OPTIONS:  # (QUATRACK_LOG_LEVEL: "did you mean QUATRACK_STORE?")
                hint = f" ({COMMAND_OPTIONS[name]})"
            out.append(f"{key} is not a setting: ignored{hint}")
        elif environ[key] == "":
            what = "no token is required" if name == env_name("api_token") else "the default is used"
            out.append(f"{key} is empty: ignored, {what}")
    return out


def describe(exc: ValidationError, given: dict) -> str:
    """The first error of ``exc`` as one line: ``QUATRACK_PORT='x': Input should be ...``."""
    e = exc.errors()[0]
    field = str(e["loc"][0]) if e["loc"] else ""
    secret = field in SECRET_FIELDS  # its value is not echoed: the error line goes to logs
    if field and field not in given and env_name(field) in os.environ:
        value = "(hidden)" if secret else repr(os.environ[env_name(field)])
        where = f"environment variable {env_name(field)}={value}"
    elif field:
        where = f"{field}={'(hidden)' if secret else repr(given.get(field))}"
    else:
        where = "settings"
    return f"{where}: {e['msg']}"


def settings_table() -> str:
    """The README's table of variables, from the field descriptions (``python -m quatrack.service.settings``)."""
    rows = ["| variable | default | meaning |", "| --- | --- | --- |"]
    for name, f in Settings.model_fields.items():
        if f.default_factory is not None:
            default = "(see meaning)"
        elif f.default is None:
            default = "unset"
        elif isinstance(f.default, tuple):
            default = ",".join(f.default) or "(none)"
        else:
            default = f"`{f.default}`"
        rows.append(f"| `{env_name(name)}` | {default} | {f.description} |")
    return "\n".join(rows)


if __name__ == "__main__":
    print(settings_table())
