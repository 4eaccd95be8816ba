"""`quatrack serve` as an operator configures it: `QUATRACK_*` variables told apart from typos and
empty values, and every bad value a one-line error naming the variable (no server is started)."""

from __future__ import annotations

import pytest

from quatrack.cli import main
from quatrack.service.settings import Settings, env_warnings


@pytest.fixture
def clean_env(monkeypatch):
    import os

    for key in list(os.environ):
        if key.upper().startswith("QUATRACK_"):
            monkeypatch.delenv(key)
    return monkeypatch


def _serve(capsys, tmp_path, *extra) -> tuple[int, list[str]]:
    code = main(["serve", "--store", str(tmp_path), *extra])
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return code, err.strip().splitlines()


def test_a_misspelt_variable_is_warned_of(clean_env, capsys, tmp_path):
    # QUATRACK_API_TOKNE: the server started without a token and said nothing, its operator
    # believing every route needed one
    assert env_warnings({"QUATRACK_API_TOKNE": "s3cret", "QUATRACK_PORT": "8000", "HOME": "/"}) == [
        "QUATRACK_API_TOKNE is not a setting: ignored (did you mean QUATRACK_API_TOKEN?)"]
    assert env_warnings({"QUATRACK_NO_SUCH_THING_AT_ALL": "1"})[0].startswith("QUATRACK_NO_SUCH_THING_AT_ALL is not a setting")
    # told before the values are checked, so also when the start then fails
    clean_env.setenv("QUATRACK_API_TOKNE", "s3cret")
    clean_env.setenv("QUATRACK_MAX_FPS", "abc")
    code, lines = _serve(capsys, tmp_path)
    assert code == 2 and len(lines) == 2, lines
    assert lines[0] == "quatrack serve: warning: QUATRACK_API_TOKNE is not a setting: ignored (did you mean QUATRACK_API_TOKEN?)"
    assert lines[1].startswith("quatrack serve: error: environment variable QUATRACK_MAX_FPS='abc'")


def test_an_empty_token_is_warned_of(clean_env):
    # `QUATRACK_API_TOKEN=${TOKEN}` with TOKEN unset: empty counts as unset, so no token is required
    assert env_warnings({"QUATRACK_API_TOKEN": ""}) == ["QUATRACK_API_TOKEN is empty: ignored, no token is required"]
    assert env_warnings({"QUATRACK_MAX_FPS": ""}) == ["QUATRACK_MAX_FPS is empty: ignored, the default is used"]
    clean_env.setenv("QUATRACK_API_TOKEN", "")
    assert Settings.from_env().api_token is None
    assert env_warnings({"QUATRACK_API_TOKEN": "x", "QUATRACK_LEARN_VIEWS": "*"}) == []


@pytest.mark.parametrize("env, names", [
    ({"QUATRACK_MAX_FPS": "abc"}, "QUATRACK_MAX_FPS='abc'"),
    ({"QUATRACK_MAX_BODY_BYTES": "-1"}, "QUATRACK_MAX_BODY_BYTES='-1'"),
    ({"QUATRACK_PORT": "70000"}, "QUATRACK_PORT='70000'"),
    ({"QUATRACK_HOST": "  "}, "QUATRACK_HOST='  '"),  # was "settings: Value error, host must not be empty"
    ({"QUATRACK_RUN_DIR": "FILE"}, "QUATRACK_RUN_DIR="),  # was "[Errno 17] File exists: ..."
])
def test_a_bad_value_is_one_line_naming_the_variable(clean_env, capsys, tmp_path, env, names):
    (tmp_path / "file").write_text("")
    for key, value in env.items():
        clean_env.setenv(key, str(tmp_path / "file") if value == "FILE" else value)
    code, lines = _serve(capsys, tmp_path)
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith(f"quatrack serve: error: environment variable {names}"), lines


@pytest.mark.parametrize("args, line", [
    (["--host", " "], "--host ' ': Value error, the address must not be blank"),
    (["--threads", "0"], "--threads 0: Input should be greater than or equal to 1"),  # was "threads=0: ..."
    (["--port", "70000"], "--port 70000: Input should be less than or equal to 65535"),
])
def test_a_bad_option_is_named_as_given(clean_env, capsys, tmp_path, args, line):
    if args[0] == "--port":
        clean_env.setenv("QUATRACK_PORT", "abc")  # (an option given wins: its variable is not read)
    code, lines = _serve(capsys, tmp_path, *args)
    assert code == 2 and lines == [f"quatrack serve: error: {line}"], lines


def test_serve_help_tells_the_precedence_and_the_real_defaults(clean_env, capsys):
    # "(default 8000, or $QUATRACK_PORT)" read as if 8000 came first; --log-level had no help; the
    # other settings (the token among them) were not mentioned at all
    with pytest.raises(SystemExit):
        main(["serve", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    fields = Settings.model_fields
    assert f"(default: $QUATRACK_PORT, else {fields['port'].default})" in out
    assert f"(default: $QUATRACK_HOST, else {fields['host'].default})" in out
    assert "(default: info)" in out and "QUATRACK_API_TOKEN" in out and "python -m quatrack.service.settings" in out
    assert "An option given here wins over its variable, which wins over the default" in out


def test_an_option_wins_over_its_variable_which_wins_over_the_default(clean_env):
    assert Settings.from_env().port == Settings.model_fields["port"].default
    clean_env.setenv("QUATRACK_PORT", "9000")
    clean_env.setenv("QUATRACK_HOST", "0.0.0.0")
    assert Settings.from_env().port == 9000 and Settings.from_env(port=None).port == 9000
    s = Settings.from_env(port=9001, host="127.0.0.2")
    assert (s.port, s.host) == (9001, "127.0.0.2")


def test_the_readme_lists_every_serve_option_and_tells_the_precedence():
    # --log-level was missing from the README's heading of `quatrack serve`, and "CLI options win"
    # said nothing of what an empty or misspelt variable does
    import argparse
    from pathlib import Path

    from quatrack.service.cli import add_serve

    readme = " ".join((Path(__file__).parents[1] / "README.md").read_text().split())
    head = next(line for line in readme.split("### ") if line.startswith("Serve: `quatrack serve"))
    parser = argparse.ArgumentParser()
    add_serve(parser)
    for action in parser._actions:
        for opt in action.option_strings:
            assert opt in ("-h", "--help") or opt in head.split("`")[1], opt
    assert "an option of `quatrack serve` wins over its variable" in readme
    assert "QUATRACK_API_TOKNE is not a setting: ignored (did you mean QUATRACK_API_TOKEN?)" in readme


def _options(parser, path=()):
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _options(sub, (*path, name))
        elif action.option_strings:
            yield " ".join(path), action


# options whose help tells their default in other words than the value (none now: `demo --out`,
# `--overlay` and `--plot` were excused, and `demo --help` showed none of their defaults)
_TOLD_ELSEWHERE: set[tuple[str, str]] = set()


def test_every_option_with_a_default_has_help_that_tells_it():
    # `bench serve --object` (cookie-box), `--rest-concurrency` (4) and `serve --log-level` (info)
    # had no help at all
    import argparse

    from quatrack.cli import build_parser

    missing = []
    for command, action in _options(build_parser()):
        d = action.default
        if d in (None, False, "", argparse.SUPPRESS) or (command, action.option_strings[-1]) in _TOLD_ELSEWHERE:
            continue
        told = [str(d)] + ([f"{d:g}"] if isinstance(d, float) else [])
        if not action.help or not any(t in action.help for t in told):
            missing.append(f"{command} {action.option_strings[-1]} (default {d!r})")
    assert not missing, missing


_FLOATS = [name for name, f in Settings.model_fields.items() if f.annotation is float]


@pytest.fixture
def no_server(clean_env):
    """A value wrongly accepted fails the test instead of starting a server that never returns
    (and the variables ``serve`` exports for its workers are taken back)."""
    import os

    import uvicorn

    def started(*args, **kwargs):
        raise AssertionError("the settings were accepted: the server was started")

    clean_env.setattr(uvicorn, "run", started)
    before = dict(os.environ)
    yield clean_env
    os.environ.clear()
    os.environ.update(before)


@pytest.mark.parametrize("name", _FLOATS)
@pytest.mark.parametrize("value", ["inf", "nan", "-inf", "Infinity"])
def test_a_float_setting_must_be_finite(no_server, capsys, tmp_path, name, value):
    """``QUATRACK_MAX_FPS=inf`` and ``QUATRACK_IDLE_TIMEOUT_S=inf`` started a server (whose token
    bucket then computed ``0 × inf``); ``QUATRACK_MODEL_POLL_S=inf`` started one whose store
    watcher died at its first wait (OverflowError). Refused at start, naming the variable."""
    no_server.setenv(f"QUATRACK_{name.upper()}", value)
    code, lines = _serve(capsys, tmp_path)
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith(f"quatrack serve: error: environment variable QUATRACK_{name.upper()}={value!r}: "), lines


@pytest.mark.parametrize("env, why", [
    ({"QUATRACK_MODEL_POLL_S": "1e10"}, "less than or equal to"),  # above threading.TIMEOUT_MAX: OverflowError in the watcher
    ({"QUATRACK_MAX_SESSIONS": "1000000"}, "less than or equal to 10000"),  # a million slot files probed per /metrics
    ({"QUATRACK_MAX_FPS": "0"}, "greater than 0"),
    ({"QUATRACK_IDLE_TIMEOUT_S": "-1"}, "greater than 0"),
])
def test_a_setting_out_of_its_range_is_refused(no_server, capsys, tmp_path, env, why):
    for key, value in env.items():
        no_server.setenv(key, value)
    code, lines = _serve(capsys, tmp_path)
    assert code == 2 and len(lines) == 1 and why in lines[0], lines


def test_large_finite_values_and_zero_where_it_means_off_are_kept(clean_env):
    for key, value, field, expected in [("QUATRACK_MAX_FPS", "1e6", "max_fps", 1e6),
                                        ("QUATRACK_IDLE_TIMEOUT_S", "86400", "idle_timeout_s", 86400.0),
                                        ("QUATRACK_MODEL_POLL_S", "0", "model_poll_s", 0.0),
                                        ("QUATRACK_MODEL_POLL_S", "3600", "model_poll_s", 3600.0),
                                        ("QUATRACK_RELOCATE_INTERVAL_S", "0", "relocate_interval_s", 0.0),
                                        ("QUATRACK_MAX_SESSIONS", "10000", "max_sessions", 10000)]:
        clean_env.setenv(key, value)
        assert getattr(Settings.from_env(), field) == expected, key
        clean_env.delenv(key)


@pytest.mark.parametrize("value, message", [
    ("   ", "the token must not be blank"),
    ("\t\n", "the token must not be blank"),
    ("abc\ndef", "the token has a control character"),
])
def test_a_token_no_client_can_send_is_refused_without_echoing_it(no_server, capsys, tmp_path, value, message):
    """A whitespace-only token started a server that refused every request (HTTP strips a
    header's surrounding whitespace, so no client could send it). The error line, which goes to
    logs, does not echo the token."""
    no_server.setenv("QUATRACK_API_TOKEN", value)
    code, lines = _serve(capsys, tmp_path)
    assert code == 2 and len(lines) == 1, lines
    assert lines[0].startswith("quatrack serve: error: environment variable QUATRACK_API_TOKEN=(hidden): ")
    assert message in lines[0] and "def" not in lines[0], lines
    with pytest.raises(ValueError, match="api_token=\\(hidden\\)"):
        Settings.from_env(api_token=value)


def test_a_token_s_surrounding_whitespace_is_removed(clean_env):
    """A secret file's line end (``kubectl create secret --from-file``) made the token one no
    client could match: the header's value arrives stripped. It is removed; what is inside stays."""
    clean_env.setenv("QUATRACK_API_TOKEN", "  s3cret token\n")
    s = Settings.from_env()
    assert s.api_token == "s3cret token"
    assert s.to_env()["QUATRACK_API_TOKEN"] == "s3cret token"  # what the worker processes get
    assert Settings(api_token="s3cret").api_token == "s3cret"


@pytest.mark.parametrize("host, token, warned", [
    ("0.0.0.0", None, True), ("::", None, True), ("192.168.1.20", None, True), ("0.0.0.0", "s3cret", False),
    ("127.0.0.1", None, False), ("127.0.0.2", None, False), ("::1", None, False), ("localhost", None, False),
])
def test_listening_beyond_loopback_without_a_token_is_warned_of(no_server, capsys, tmp_path, host, token, warned):
    """``--host 0.0.0.0`` (the image's default) without ``QUATRACK_API_TOKEN`` started in silence,
    every endpoint open to the network. The server still starts."""
    import uvicorn

    from quatrack.service.cli import exposed_without_token

    assert (exposed_without_token(host, token) is not None) == warned
    if host in ("0.0.0.0", "127.0.0.1"):  # addresses this machine surely has: through `quatrack serve`
        from quatrack.testing.loopback import free_port

        started = []
        no_server.setattr(uvicorn, "run", lambda *a, **k: started.append(k["host"]))
        if token:
            no_server.setenv("QUATRACK_API_TOKEN", token)
        code = main(["serve", "--store", str(tmp_path), "--host", host, "--port", str(free_port()), "--workers", "1"])
        err = capsys.readouterr().err
        assert code == 0 and started == [host], err
        assert ("quatrack serve: warning: listening on 0.0.0.0 without a token" in err) == warned, err


def test_an_ipv6_host_written_as_in_a_url_is_taken_bare(clean_env):
    """``--host [::1]`` (as in ``http://[::1]:8000``) was ``cannot resolve it``."""
    assert Settings.from_env(host="[::1]").host == "::1"
    clean_env.setenv("QUATRACK_HOST", "[::]")
    assert Settings.from_env().host == "::"
    assert Settings.from_env(host="127.0.0.1").host == "127.0.0.1"


def test_a_store_that_does_not_exist_is_warned_of(no_server, capsys, tmp_path):
    """``--store /data/modles`` (a typo) started a server ready with no object, in silence; it
    still starts (a store trained into later is picked up), with a warning."""
    import uvicorn

    from quatrack.testing.loopback import free_port

    no_server.setattr(uvicorn, "run", lambda *a, **k: None)
    for store, warned in ((tmp_path / "modles", True), (tmp_path, False)):
        code = main(["serve", "--store", str(store), "--port", str(free_port()), "--workers", "1"])
        err = capsys.readouterr().err
        assert code == 0, err
        assert (f"quatrack serve: warning: the store {store} does not exist" in err) == warned, err
