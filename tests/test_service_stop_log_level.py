"""A stop whose grace period ends with a request still running is logged as a warning, as the
docs say: uvicorn's own line, "Cancel 1 running task(s), timeout graceful shutdown exceeded",
was an error, and log-based alerting fired at every rollout with a slow upload."""

from __future__ import annotations

import io
import json
import logging

from quatrack.service.logs import JsonFormatter, ServiceLogFilter


def test_uvicorns_cancel_at_the_end_of_the_grace_period_is_a_warning():
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)  # (the service's handler, as logs.configure builds it)
    handler.setFormatter(JsonFormatter())
    handler.addFilter(ServiceLogFilter())
    logger = logging.getLogger("uvicorn.error")
    for args in (("Cancel %s running task(s), timeout graceful shutdown exceeded", 1), ("something else went wrong",)):
        record = logger.makeRecord("uvicorn.error", logging.ERROR, __file__, 1, args[0], args[1:], None)
        handler.handle(record)
    lines = [json.loads(line) for line in stream.getvalue().splitlines()]
    assert [(x["level"], x["msg"]) for x in lines] == [
        ("warning", "Cancel 1 running task(s), timeout graceful shutdown exceeded"),
        ("error", "something else went wrong")]
