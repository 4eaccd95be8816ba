"""Structured logs: one JSON object per line, with the request or session id when there is one.

Two things every line passes through (a filter on the one handler, so uvicorn's own lines too):

- Secrets are never written: a ``token`` query parameter (WebSocket clients that cannot set a
  header send ``?token=…``; uvicorn logs the path with its query) is replaced by ``[redacted]``.
- Credentials in headers are never written either: the value of an ``Authorization``,
  ``Proxy-Authorization``, ``Cookie`` or ``Set-Cookie`` header, as a header line
  (``authorization: Bearer …``: the websockets library logs every handshake header at debug
  level) or quoted in a repr (``'authorization': '…'``, ``(b'cookie', b'…')``).
- A WebSocket the service refused on purpose (401, 404, 503: see ``routes.deny_websocket``) is logged by
  the service at info level with its reason; uvicorn's error "ASGI callable returned without
  completing handshake", which it writes after every denial response, is dropped for those
  connections only (:func:`mark_refused` sets a context variable in the connection's task, which
  is where uvicorn logs it). Any other connection that ends so is still an error.
- uvicorn's "Cancel N running task(s), timeout graceful shutdown exceeded" is a warning, not an
  error: a stop cutting a slow upload short is routine, and the request is answered 503.
"""

from __future__ import annotations

import contextvars
import json
import logging
import re
import time
from urllib.parse import unquote_plus

_STD = set(vars(logging.makeLogRecord({}))) | {"message", "asctime"}
# a query parameter: its key as written (percent-encoded or not) and its value, up to the next
# separator, space or double quote (uvicorn quotes the request line; a URL's own `"` is always
# encoded, while `'`, `(`, `)` may be left as they are by clients: part of the value)
_PARAM = re.compile(r"([?&;])([^=&;#?\s\"']+)=([^&;#\s\"]*)")
_SECRET_KEYS = {"token", "access_token"}
_HEADER_NAMES = r"(?:proxy-)?authorization|(?:set-)?cookie"
# quoted in a repr: 'authorization': 'Bearer …' (a dict) or b'authorization', b'Bearer …' (ASGI headers)
_QUOTED_HEADER = re.compile(rf"(?i)(\b(?:{_HEADER_NAMES})(['\"])\s*[:,]\s*b?)(['\"])(?:\\.|(?!\3).)*\3")
# a header line: authorization: Bearer … (to the line's end)
_HEADER_LINE = re.compile(rf"(?im)(\b(?:{_HEADER_NAMES})[ \t]*:[ \t]*)\S[^\r\n]*")
_REFUSED: contextvars.ContextVar[bool] = contextvars.ContextVar("quatrack_ws_refused", default=False)
_UVICORN_AFTER_DENIAL = "ASGI callable returned without completing handshake"
# uvicorn's ERROR when a stop's grace period ends with requests still running: the stop is
# routine (every rollout), and those requests are answered 503 shutting_down and logged as a
# warning (``app.StopAnswer``); as an error it woke log-based alerting at every slow upload
_UVICORN_STOP_CANCEL = "timeout graceful shutdown exceeded"


def _secret_key(key: str) -> bool:
    """Whether a query key, as it was written, reads as ``token`` once decoded the way the server
    decodes it (``%74oken``, ``TOKEN``, ``tok%65n``, ``access_token``: all are the token's key
    for someone; the server reads ``token``)."""
    return unquote_plus(key).strip().lower() in _SECRET_KEYS


def redact(text: str) -> str:
    """``text`` with the value of every ``token`` query parameter replaced, however its key is
    written: the service reads ``?%74oken=…`` as ``?token=…`` (the query's keys are
    percent-decoded), so a client that encodes the key must not see its token in the log. And
    the values of credential headers (``Authorization``, ``Cookie``; see the module's note)."""
    if "=" in text:
        text = _PARAM.sub(lambda m: f"{m[1]}{m[2]}=[redacted]" if m[3] and _secret_key(m[2]) else m[0], text)
    low = text.lower()
    if "authorization" in low or "cookie" in low:
        text = _QUOTED_HEADER.sub(lambda m: f"{m[1]}{m[3]}[redacted]{m[3]}", text)
        text = _HEADER_LINE.sub(lambda m: f"{m[1]}[redacted]", text)
    return text


def mark_refused() -> None:
    """Called when the service answers a WebSocket handshake with an HTTP error on purpose."""
    _REFUSED.set(True)


class ServiceLogFilter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        if record.name.startswith("uvicorn") and _UVICORN_AFTER_DENIAL in str(record.msg) and _REFUSED.get():
            return False
        if record.name.startswith("uvicorn") and record.levelno == logging.ERROR \
                and str(record.msg).startswith("Cancel ") and _UVICORN_STOP_CANCEL in str(record.msg):
            record.levelno, record.levelname = logging.WARNING, logging.getLevelName(logging.WARNING)
        try:
            message = record.getMessage()
        except Exception:  # a malformed call: let the formatter report it, as logging does
            return True
        clean = redact(message)
        if clean != message:
            record.msg, record.args = clean, ()
        for key, value in list(vars(record).items()):
            if key not in _STD and isinstance(value, str):
                setattr(record, key, redact(value))
        return True


def install_filters() -> None:
    """Put the filter on uvicorn's own loggers too, whatever logging configuration is in force
    (a handler's filter only sees what reaches that handler). Idempotent."""
    for name in ("uvicorn.error", "uvicorn.access"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, ServiceLogFilter) for f in logger.filters):
            logger.addFilter(ServiceLogFilter())


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        out = {"ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
               "level": record.levelname.lower(), "logger": record.name, "msg": record.getMessage()}
        out.update({k: v for k, v in vars(record).items() if k not in _STD and not k.startswith("_")})
        if record.exc_info:
            out["exc"] = redact(self.formatException(record.exc_info))
        return json.dumps(out, default=str)


def configure(level: str = "info") -> dict:
    """Log config for uvicorn's ``log_config``: our loggers and uvicorn's, all as JSON on stderr."""
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "formatters": {"json": {"()": JsonFormatter}},
        "filters": {"service": {"()": ServiceLogFilter}},
        "handlers": {"stderr": {"class": "logging.StreamHandler", "formatter": "json", "stream": "ext://sys.stderr",
                                "filters": ["service"]}},
        "loggers": {
            "quatrack": {"handlers": ["stderr"], "level": level.upper(), "propagate": False},
            "uvicorn": {"handlers": ["stderr"], "level": level.upper(), "propagate": False},
            "uvicorn.access": {"handlers": [], "level": "WARNING", "propagate": False},  # RequestLog does it
        },
    }
