"""Service settings, read once from the environment (``QUATRACK_*``) and overridable in code.

A plain frozen dataclass rather than pydantic-settings: one dependency fewer, and every limit is
visible here with its unit. ``quatrack serve`` builds one from the environment and its options.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from quatrack.viewsets.store import resolve_store


def _env(name: str, default, cast):
    raw = os.environ.get(name)
    if raw is None or raw.strip() == "":
        return default
    try:
        return cast(raw)
    except ValueError:
        raise ValueError(f"environment variable {name}={raw!r}: expected {cast.__name__}") from None


def _origins(raw: str) -> tuple[str, ...]:
    return tuple(o.strip() for o in raw.split(",") if o.strip())


@dataclass(frozen=True)
class Settings:
    """Everything an operator may tune. Sizes in bytes/pixels, times in seconds."""

    store: Path = field(default_factory=lambda: resolve_store(None))
    host: str = "127.0.0.1"
    port: int = 8000
    api_token: str | None = None  # bearer token for everything but /healthz and /readyz
    cors_origins: tuple[str, ...] = ()  # e.g. ("https://example.org",); "*" allows any
    workers: int = 2  # threads doing the CPU work (the machine has 2 cores)
    max_body_bytes: int = 10 * 1024 * 1024  # REST body and one WebSocket frame
    max_image_pixels: int = 20_000_000  # refused before decoding (decompression bombs)
    locate_max_pixels: int = 4_000_000  # larger images are downscaled for recognition
    max_pending_requests: int = 8  # REST pose requests queued or running; then 503
    max_sessions: int = 4  # concurrent WebSocket sessions; then 503 + Retry-After
    max_fps: float = 60.0  # frames a session may send per second (token bucket); above: dropped
    idle_timeout_s: float = 60.0  # a session with no message for this long is closed
    retry_after_s: int = 5
    preload: bool = True  # load every model of the store at start-up (readyz waits for it)

    @classmethod
    def from_env(cls, **overrides) -> "Settings":
        """Settings from ``QUATRACK_*`` variables; explicit ``overrides`` (CLI options) win."""
        s = cls(
            store=resolve_store(None),
            host=_env("QUATRACK_HOST", cls.host, str),
            port=_env("QUATRACK_PORT", cls.port, int),
            api_token=_env("QUATRACK_API_TOKEN", None, str),
            cors_origins=_env("QUATRACK_CORS_ORIGINS", (), _origins),
            workers=_env("QUATRACK_WORKERS", cls.workers, int),
            max_body_bytes=_env("QUATRACK_MAX_BODY_BYTES", cls.max_body_bytes, int),
            max_image_pixels=_env("QUATRACK_MAX_IMAGE_PIXELS", cls.max_image_pixels, int),
            locate_max_pixels=_env("QUATRACK_LOCATE_MAX_PIXELS", cls.locate_max_pixels, int),
            max_pending_requests=_env("QUATRACK_MAX_PENDING_REQUESTS", cls.max_pending_requests, int),
            max_sessions=_env("QUATRACK_MAX_SESSIONS", cls.max_sessions, int),
            max_fps=_env("QUATRACK_MAX_FPS", cls.max_fps, float),
            idle_timeout_s=_env("QUATRACK_IDLE_TIMEOUT_S", cls.idle_timeout_s, float),
        )
        known = {f.name for f in fields(cls)}
        return replace(s, **{k: v for k, v in overrides.items() if k in known and v is not None}).checked()

    def checked(self) -> "Settings":
        """Refuse settings that cannot work, with the variable's meaning in the message."""
        if self.workers < 1:
            raise ValueError("workers must be at least 1")
        if not 0 < self.port < 65536:
            raise ValueError(f"port must be 1-65535, got {self.port}")
        for name in ("max_body_bytes", "max_image_pixels", "locate_max_pixels", "max_pending_requests", "max_sessions"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be positive")
        if self.max_fps <= 0 or self.idle_timeout_s <= 0:
            raise ValueError("max_fps and idle_timeout_s must be positive")
        return replace(self, store=Path(self.store).expanduser())
