"""The viewer as a trial user (an AR engineer) met it: the token typed and webcam clicked at once,
a 401 on the object list, a refused WebSocket, the previous run's numbers, an object deleted
since it was listed, the camera refused. In Debian's headless Chromium, as test_viewer_ux.py
(its fixtures and helpers); every check waits for a state of the page, never for a time.
"""

from __future__ import annotations

import shutil

import pytest

from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store
from quatrack.viewsets import store as store_mod

from test_viewer import _wait
from test_viewer_ux import STATIC, TOKEN, _count, _js, _open, _run_ended, _start_webcam, _text
import test_viewer_ux

server, browser = test_viewer_ux.server, test_viewer_ux.browser  # (that module's fixtures: a server with a token, Chromium)

TOKEN_SAYS = "type the server's token in the token field"


@pytest.mark.parametrize("change", [True, False])
def test_the_token_typed_and_webcam_clicked_at_once_tracks(server, browser, change):
    """The click blurs the token field: its 'change' starts the object list, and the run, started
    in the same moment, found the list still loading ("pick an object"). The run now waits for
    the list; a token typed whose list was never asked for (no 'change' yet) is listed first."""
    _open(browser, server.url, token=None)
    _wait(browser, lambda: "unauthorized" in _text(browser, "message"), "the tokenless list's refusal")
    browser.find_element("id", "max-frames").send_keys("2")
    _js(browser, """const t = document.getElementById('token'); t.value = arguments[0];
        if (arguments[1]) t.dispatchEvent(new Event('change'));
        document.getElementById('webcam').click();""", TOKEN, change)
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    assert _count(browser) == 2, _text(browser, "message")


@pytest.mark.parametrize("typed, said", [(None, "the server has a token"), ("wrong", "the token was refused")])
def test_a_401_on_the_list_says_to_type_the_token_and_a_run_says_it_too(server, browser, typed, said):
    _open(browser, server.url, token=typed)
    _wait(browser, lambda: TOKEN_SAYS in _text(browser, "message"), "the list's refusal")
    assert said in _text(browser, "message")
    _start_webcam(browser)
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    assert said in _text(browser, "message") and TOKEN_SAYS in _text(browser, "message"), _text(browser, "message")


def test_a_refused_socket_says_why(server, browser):
    """A refused handshake reached the page as a bare 1006 ("the server stopped or the network
    failed"): the server now opens a browser's socket to say why (test_service_errors_ws_browser.py)."""
    state = server.app.state.quatrack
    taken = []
    while (sid := state.sessions.try_open()) is not None:
        taken.append(sid)
    try:
        _open(browser, server.url)
        _start_webcam(browser)
        _wait(browser, lambda: _run_ended(browser), "the run's end")
    finally:
        for sid in taken:
            state.sessions.close(sid)
    assert _text(browser, "message").startswith("too_many_sessions: "), _text(browser, "message")


def test_a_socket_that_never_opens_does_not_say_the_server_stopped(server, browser):
    """A socket closed before it opened (what a browser shows of a server not listening, or of a
    proxy refusing the handshake: 1006, no reason) said "1006 connection lost: the server stopped
    or the network failed". The page's WebSocket is replaced by one that closes so."""
    _open(browser, server.url)
    _js(browser, """window.WebSocket = function () {
        const ws = { send() {}, close() {} };
        setTimeout(() => ws.onclose({ code: 1006, reason: "" }), 0);
        return ws;
      };""")
    _start_webcam(browser)
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    said = _text(browser, "message")
    assert said.startswith("cannot open the WebSocket (1006") and "stopped" not in said, said


def test_a_new_run_does_not_show_the_previous_runs_numbers(server, browser):
    _open(browser, server.url)
    _start_webcam(browser, 2)
    _wait(browser, lambda: _run_ended(browser) and _count(browser) == 2, "the first run's end")
    _js(browser, "document.getElementById('camera').value = 'not a camera'")
    browser.find_element("id", "webcam").click()  # refused at once: no pose of its own
    _wait(browser, lambda: _run_ended(browser) and "camera: not JSON" in _text(browser, "message"), "the refusal")
    assert _count(browser) == 0 and _text(browser, "last-pose") == "null"
    assert _js(browser, """const c = document.getElementById('overlay');
        return c.getContext('2d').getImageData(0, 0, c.width, c.height).data.every((v) => v === 0)""")


def test_an_object_gone_since_it_was_listed_reloads_the_list(server, browser):
    _open(browser, server.url)
    browser.find_element("id", "max-frames").send_keys("2")  # (the token field's blur may list the objects again)
    _js(browser, """listLoad.then(() => { const s = document.getElementById('object');
        s.add(new Option('ghost', 'ghost')); s.value = 'ghost'; document.getElementById('webcam').click(); });""")
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    assert _text(browser, "message").startswith("unknown_object: ")  # (the run's reason stays said)
    _wait(browser, lambda: _js(browser, "return [...document.getElementById('object').options].map(o => o.value)")
          == ["cookie-box"], "the list reloaded")


@pytest.mark.parametrize("name, said", [("NotAllowedError", "allow it"), ("NotFoundError", "connect one")])
def test_a_refused_camera_says_what_to_do(server, browser, name, said):
    _open(browser, server.url)
    _js(browser, "navigator.mediaDevices.getUserMedia = () => Promise.reject(new DOMException('refused', arguments[0]))",
        name)
    _start_webcam(browser)
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    assert said in _text(browser, "message") and "choose a video file" in _text(browser, "message")


def test_a_broken_model_is_named_once(browser, tmp_path):
    store = tmp_path / "store"
    shutil.copytree(example_store() / "cookie-box", store / "cookie-box")
    (store / "garbled").mkdir()
    (store / "garbled" / store_mod.MANIFEST).write_text("{not json")
    with BackgroundServer(Settings(store=store, model_poll_s=0)) as srv:
        browser.get(f"{srv.url}/viewer/")
        _wait(browser, lambda: "cannot be loaded" in _text(browser, "message"), "the list")
        said = _text(browser, "message")
    assert "garbled: unreadable manifest" in said and "object 'garbled'" not in said, said


def test_the_page_asks_for_no_favicon():
    """Without an icon of its own the browser asks for /favicon.ico (a 404 in the console; behind
    a prefix, at the host's root). The page's CSP allows data: images."""
    assert '<link rel="icon" href="data:,">' in (STATIC / "viewer.html").read_text()
