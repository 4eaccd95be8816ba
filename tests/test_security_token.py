"""A token no client can send is refused at start: a non-ASCII ``QUATRACK_API_TOKEN`` was
accepted, and then no request could authenticate (header values travel as bytes: the server reads
them as latin-1, clients encode UTF-8 or refuse). One error line, the token not echoed, as for the
other tokens no client can send (tests/test_serve_settings.py)."""

from __future__ import annotations

import pytest

from quatrack.cli import main
from quatrack.service.settings import Settings
from quatrack.testing.loopback import free_port
from quatrack.testing.scenes import example_store


@pytest.mark.parametrize("token", ["s3cr\u00e9t-tok", "tok\u00e9n", "\u2603snowman", "caf\u00e9 au lait", "abc\u00a0def"])
def test_a_non_ascii_token_is_refused_at_start(not_started, capsys, token):
    env, started = not_started
    env.setenv("QUATRACK_API_TOKEN", token)
    code = main(["serve", "--store", str(example_store()), "--port", str(free_port()), "--workers", "1"])
    lines = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    assert code == 2 and not started, lines
    assert len(lines) == 1 and lines[0].startswith("quatrack serve: error: environment variable "
                                                   "QUATRACK_API_TOKEN=(hidden): "), lines
    assert "not ASCII" in lines[0] and token not in lines[0], lines
    with pytest.raises(ValueError, match="not ASCII"):
        Settings(api_token=token)


def test_ascii_tokens_are_kept():
    for token in ("s3cret", "a.b-c_d~e+f/g=", "s3cret token", "!#$%&'*"):
        assert Settings(api_token=token).api_token == token
