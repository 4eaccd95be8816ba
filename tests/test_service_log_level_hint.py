"""``QUATRACK_LOG_LEVEL`` is not a setting: the warning said "did you mean QUATRACK_STORE?" (the
nearest name); it now says the log level is ``quatrack serve --log-level``."""

from __future__ import annotations

import pytest

from quatrack.service.settings import env_warnings


@pytest.mark.parametrize("name", ["QUATRACK_LOG_LEVEL", "quatrack_log_level", "QUATRACK_LOGLEVEL"])
def test_the_log_level_variable_points_to_the_option(name):
    (line,) = env_warnings({name: "verbose"})
    assert line == (f"{name} is not a setting: ignored (the log level is the option --log-level of quatrack serve: "
                    f"debug, info, warning or error)"), line


def test_a_typo_still_gets_the_nearest_setting():
    assert env_warnings({"QUATRACK_API_TOKNE": "x"}) == [
        "QUATRACK_API_TOKNE is not a setting: ignored (did you mean QUATRACK_API_TOKEN?)"]
