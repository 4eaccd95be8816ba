"""A learning WebSocket session's end says how many views it stored (trial report, item 5).

The protocol has no closing message (the client closes; the views are stored after), and the
count was only in the store's own log line. The session's ``session ended`` line now carries
``learned_views_stored`` when its tracker learned (``QUATRACK_LEARN_VIEWS``); other sessions'
lines are unchanged.
"""

from __future__ import annotations

import asyncio
import json
import logging
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import pytest

from quatrack.service import sessions
from quatrack.service.logs import JsonFormatter
from quatrack.service.metrics import Metrics
from quatrack.service.settings import Settings
from test_service_ws import CAMERA
from test_service_ws_sessions import ScriptedSocket  # (the camera, then the client leaves)


def _ended(tmp_path, monkeypatch, tracker) -> dict:
    """The ``session ended`` line (as JSON) of a session whose tracker is ``tracker`` and whose
    end stored 3 views (the store stood in for: what it returns is the count to report)."""
    async def stored(session):
        return 3

    monkeypatch.setattr(sessions, "store_session_views", stored)
    seen: list[logging.LogRecord] = []
    tap = logging.Handler(logging.DEBUG)
    tap.emit = seen.append
    logger = logging.getLogger("quatrack.service")
    logger.addHandler(tap)
    level, disabled = logger.level, logger.disabled
    logger.setLevel(logging.INFO)
    logger.disabled = False
    try:
        with ThreadPoolExecutor(1) as pool:
            session = sessions.TrackSession(ScriptedSocket(json.dumps(CAMERA)), "sid7", "cookie-box", None, Settings(store=tmp_path), pool, Metrics())
            session.tracker = tracker
            asyncio.run(asyncio.wait_for(session.run(), 30))
    finally:
        logger.removeHandler(tap)
        logger.setLevel(level)
        logger.disabled = disabled
    lines = [json.loads(JsonFormatter().format(r)) for r in seen]
    return next(ln for ln in lines if ln["msg"] == "session ended")


def test_a_learning_sessions_end_line_says_how_many_views_it_stored(tmp_path, monkeypatch):
    end = _ended(tmp_path, monkeypatch, SimpleNamespace(params=SimpleNamespace(learn=True)))
    assert end["learned_views_stored"] == 3 and end["session_id"] == "sid7", end


@pytest.mark.parametrize("tracker", [None, SimpleNamespace(params=SimpleNamespace(learn=False))])
def test_other_sessions_end_lines_are_unchanged(tmp_path, monkeypatch, tracker):
    assert "learned_views_stored" not in _ended(tmp_path, monkeypatch, tracker)
