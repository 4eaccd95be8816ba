"""The browser viewer (``/viewer``) as a user meets it: what breaks or misleads, each case checked
in Debian's headless Chromium (one browser for the module, a fresh page per test; helpers from
``test_viewer.py``). Every check waits for a state of the page (a message, a count, the run's
end), never for an amount of time; hooks installed in the page (a wrapped ``WebSocket.send``,
a held ``fetch`` or ``toBlob``) make the orders of events that matter happen every time.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from quatrack.service import codes
from quatrack.service.server import BackgroundServer
from quatrack.service.settings import Settings
from quatrack.testing.scenes import example_store

from test_viewer import EXAMPLE, _driver, _wait, write_y4m

TOKEN = "viewer-ux-token"
STATIC = Path(__file__).resolve().parent.parent / "service" / "static"
CAMERA = (EXAMPLE / "camera.json").read_text()


def test_the_pages_refused_frame_codes_are_the_servers():
    """viewer.js's REFUSED_FRAME (errors without "frame" that answer the frame just sent) is
    service/codes.py's: a code added on one side only would shift every later pose by a frame."""
    js = (STATIC / "viewer.js").read_text()
    found = re.search(r"const REFUSED_FRAME = new Set\(\[([^\]]*)\]\)", js)
    assert found, "viewer.js has no REFUSED_FRAME list"
    assert set(json.loads(f"[{found.group(1)}]")) == codes.REFUSED_FRAME


@pytest.fixture(scope="module")
def server():
    with BackgroundServer(Settings(store=example_store(), api_token=TOKEN)) as srv:
        yield srv


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("chromium")
    y4m = tmp / "box.y4m"
    write_y4m(EXAMPLE / "box.mp4", y4m, 30)
    driver = _driver(tmp, y4m)
    yield driver
    driver.quit()


def _open(driver, url: str, token: str | None = TOKEN, camera: str | None = CAMERA) -> None:
    """A fresh page, the token typed (objects listed), the camera pasted."""
    driver.get(f"{url}/viewer/")
    if token is not None:
        driver.find_element("id", "token").send_keys(token)
        driver.execute_script("document.getElementById('token').dispatchEvent(new Event('change'))")
        _wait(driver, lambda: driver.execute_script("return document.getElementById('object').value") == "cookie-box",
              "the objects")
    if camera is not None:
        driver.execute_script("document.getElementById('camera').value = arguments[0]", camera)


def _js(driver, script: str, *args):
    return driver.execute_script(script, *args)


def _text(driver, el: str) -> str:
    return _js(driver, f"return document.getElementById('{el}').textContent")


def _run_ended(driver) -> bool:
    return bool(_js(driver, "return state.done === state.run"))


# Counts every binary frame the page sends, and pairs each drawn answer's frame number with the
# number of the frame just sent (they must be equal: lock-step draws a pose on its own frame).
COUNT_FRAMES = """
window.__sent = 0; window.__headers = 0; window.__pairs = [];
const send = WebSocket.prototype.send;
WebSocket.prototype.send = function (data) {
  if (typeof data === "string" && data.includes('"type":"frame"')) {
    window.__headers += 1;
    const extra = (window.__extra || {})[window.__headers];
    if (extra) send.call(this, extra);
  } else if (typeof data !== "string") window.__sent += 1;
  return send.call(this, data);
};
const draw = drawFrame;
drawFrame = function (frame, msg, rtt) { window.__pairs.push([msg.frame, window.__sent - 1]); return draw(frame, msg, rtt); };
"""


def test_an_error_that_answers_no_frame_does_not_shift_the_poses(server, browser):
    """A refused frame header (bad_message, out_of_order: errors without "frame" and not a
    refused frame's code) was taken as the answer to the frame just sent: every later pose was
    drawn on the next frame, and the last frame's answer never read. The page now shows such an
    error and waits for the frame's own answer."""
    _open(browser, server.url)
    _js(browser, COUNT_FRAMES)
    _js(browser, """window.__extra = {3: JSON.stringify({type: "frame", time_s: -1}),
                                      5: JSON.stringify({type: "frame", time_s: 0})}""")
    browser.find_element("id", "max-frames").send_keys("6")
    browser.find_element("id", "webcam").click()
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    pairs = _js(browser, "return window.__pairs")
    last = json.loads(_text(browser, "last-pose"))
    assert _text(browser, "pose-count") == "6", _text(browser, "message")
    assert [a for a, b in pairs] == [b for a, b in pairs] == list(range(6)), pairs
    assert last["frame"] == 5 and _js(browser, "return window.__sent") == 6
    assert "out_of_order" in _text(browser, "message")  # (the latest one is shown)
