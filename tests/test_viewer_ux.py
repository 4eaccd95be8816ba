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
        if token == TOKEN:
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


def _start_webcam(driver, max_frames: int | None = None) -> None:
    if max_frames:
        driver.find_element("id", "max-frames").send_keys(str(max_frames))
    driver.find_element("id", "webcam").click()


def _count(driver) -> int:
    return int(_text(driver, "pose-count"))


def test_a_server_restart_mid_stream_is_a_message_not_a_frozen_page(browser):
    """The server closing the socket (1012, restarting) while the page encoded a frame was never
    seen: the socket's handlers were set only while an answer was awaited, so the page sent into
    the closed socket and waited for ever, still saying "tracking". The encoding of the third
    frame is held here until the socket is closed, so that it happens every time."""
    srv = BackgroundServer(Settings(store=example_store(), api_token=TOKEN)).start()
    try:
        _open(browser, srv.url)
        _js(browser, """window.__blobs = 0;
            const toBlob = HTMLCanvasElement.prototype.toBlob;
            HTMLCanvasElement.prototype.toBlob = function (cb, ...rest) {
              if (++window.__blobs === 3) {
                new Promise((r) => { window.__release = r; }).then(() => toBlob.call(this, cb, ...rest));
                return;
              }
              return toBlob.call(this, cb, ...rest);
            };""")
        _start_webcam(browser)
        _wait(browser, lambda: _js(browser, "return !!window.__release"), "the third frame")
    finally:
        srv.stop()
    _wait(browser, lambda: _js(browser, "return state.ws.readyState === WebSocket.CLOSED"), "the close")
    _js(browser, "window.__release()")
    _wait(browser, lambda: _run_ended(browser), "the run's end", timeout=60)
    assert _text(browser, "status") == "stopped"
    assert "connection closed (1012" in _text(browser, "message"), _text(browser, "message")


def test_two_runs_started_in_a_row_do_not_stop_each_other(server, browser):
    """A run superseded while it waited (here: for the wireframe) went on when the wait ended:
    it reset the newer run's count, replaced its socket and camera, and stopped it ("no pose
    received"). The first run's wireframe request is held until the second run has a pose."""
    _open(browser, server.url)
    _js(browser, COUNT_FRAMES)
    _js(browser, """window.__meshes = 0; const fetch0 = window.fetch;
        window.fetch = function (url, opts) {
          if (String(url).includes("/mesh") && ++window.__meshes === 1)
            return new Promise((r) => { window.__releaseMesh = () => r(fetch0(url, opts)); });
          return fetch0(url, opts);
        };""")
    _start_webcam(browser, 8)
    _wait(browser, lambda: _js(browser, "return !!window.__releaseMesh"), "the first run's wireframe request")
    browser.find_element("id", "webcam").click()
    _wait(browser, lambda: _count(browser) >= 1, "the second run's first pose")
    _js(browser, "window.__releaseMesh()")
    _wait(browser, lambda: _run_ended(browser) and _js(browser, "return state.done === 2"), "the second run's end")
    assert _count(browser) == 8 and _text(browser, "message") == "", _text(browser, "message")
    pairs = _js(browser, "return window.__pairs")
    assert [a for a, b in pairs] == [b for a, b in pairs] == list(range(8)), pairs


def test_stop_says_stopped_by_the_user(server, browser):
    """The stop button's message was replaced by the socket's close a moment later
    ("connection closed (1005)"), as if the connection had failed."""
    _open(browser, server.url)
    _start_webcam(browser)
    _wait(browser, lambda: _count(browser) >= 2, "two poses")
    browser.find_element("id", "stop").click()
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    assert _text(browser, "message") == "stopped by the user"
    assert _text(browser, "status") == "stopped"


def test_a_video_the_browser_cannot_decode_is_a_message(server, browser, tmp_path):
    """A file that is no video (or a codec the browser lacks) never fired "loadeddata": the page
    waited for ever, saying "stopped" and nothing else."""
    bad = tmp_path / "not-a-video.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 40)
    _open(browser, server.url)
    browser.find_element("id", "file").send_keys(str(bad))
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    assert "cannot play this video" in _text(browser, "message"), _text(browser, "message")
    assert _text(browser, "status") == "stopped"


def _webm(path: Path, frames: int) -> Path:
    import cv2

    cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"VP80"), 30, (640, 480))
    for _ in range(frames):
        out.write(cap.read()[1])
    out.release()
    cap.release()
    return path


def test_the_same_file_chosen_again_plays_again(server, browser, tmp_path):
    """The file input kept the chosen file: choosing it again after its run was no change, and
    nothing happened."""
    video = _webm(tmp_path / "box.webm", 20)
    _open(browser, server.url)
    browser.find_element("id", "max-frames").send_keys("2")
    for run in (1, 2):
        browser.find_element("id", "file").send_keys(str(video))
        _wait(browser, lambda: _js(browser, "return state.done") == run, f"run {run}'s end")
        assert _count(browser) == 2 and _text(browser, "source") == "box.webm"


def test_the_webcam_needs_a_secure_page_and_an_object(server, browser):
    """Over plain http from another machine the browser has no navigator.mediaDevices: the page
    said "webcam: Cannot read properties of undefined". And without an object the webcam was
    turned on, then the run refused ("pick an object") with the camera left on."""
    _open(browser, server.url)
    _js(browser, "Object.defineProperty(navigator, 'mediaDevices', {value: undefined, configurable: true})")
    browser.find_element("id", "webcam").click()
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    said = _text(browser, "message")
    assert "https" in said and "localhost" in said, said

    _open(browser, server.url, token=None)  # no token: no objects listed
    _wait(browser, lambda: "unauthorized" in _text(browser, "message"), "the refusal")
    _js(browser, """window.__cams = 0; const gum = navigator.mediaDevices.getUserMedia.bind(navigator.mediaDevices);
        navigator.mediaDevices.getUserMedia = (c) => { window.__cams += 1; return gum(c); };""")
    browser.find_element("id", "webcam").click()
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    # (why there is no object is said, not "pick an object": test_viewer_token_flow.py)
    assert _text(browser, "message") == ("objects: unauthorized: the server has a token; type the server's token in "
                                         "the token field") and _js(browser, "return window.__cams") == 0


def test_the_object_list_offers_what_can_be_tracked(browser, tmp_path):
    """A model that cannot be loaded was offered like the others, and chosen first when its name
    came first (every run then refused with model_unavailable); now it is listed disabled, its
    error in its title and in the message line. An empty store says how to train one. An older
    list answer coming after a newer one is dropped (the token typed while the page's tokenless
    listing was under way showed 'unauthorized' over the objects listed)."""
    import shutil

    from quatrack.viewsets import store as store_mod

    src = example_store() / "cookie-box"
    store = tmp_path / "store"
    for name in ("a-broken", "cookie-box", "z-box"):
        shutil.copytree(src, store / name)
        m = json.loads((store / name / store_mod.MANIFEST).read_text())
        (store / name / store_mod.MANIFEST).write_text(json.dumps({**m, "name": name}))
    arrays = store / "a-broken" / store_mod.ARRAYS
    arrays.write_bytes(arrays.read_bytes()[:1000])
    with BackgroundServer(Settings(store=store, model_poll_s=0)) as srv:
        browser.get(f"{srv.url}/viewer/")
        _wait(browser, lambda: _js(browser, "return document.getElementById('object').options.length") == 3, "the list")
        options = _js(browser, "return [...document.getElementById('object').options]"
                               ".map(o => [o.value, o.textContent, o.disabled, o.title])")
        assert [o[:3] for o in options] == [["a-broken", "a-broken (broken)", True], ["cookie-box", "cookie-box", False],
                                           ["z-box", "z-box", False]]
        assert "a-broken" in options[0][3]
        assert _js(browser, "return document.getElementById('object').value") == "cookie-box"
        assert "1 object(s) cannot be loaded: a-broken" in _text(browser, "message")
    empty = tmp_path / "empty"
    empty.mkdir()
    with BackgroundServer(Settings(store=empty)) as srv:
        browser.get(f"{srv.url}/viewer/")
        _wait(browser, lambda: "no trained object" in _text(browser, "message"), "the message")
        assert "quatrack train" in _text(browser, "message")
        browser.find_element("id", "webcam").click()
        _wait(browser, lambda: _run_ended(browser), "the run's end")
        assert _text(browser, "message") == "pick an object"


COUNT_CAMS = """window.__cams = 0; const gum = navigator.mediaDevices.getUserMedia.bind(navigator.mediaDevices);
navigator.mediaDevices.getUserMedia = (c) => { window.__cams += 1; return gum(c); };"""


@pytest.mark.parametrize("pasted, said", [
    ("fx: 600, fy: 600", "camera: not JSON"),  # (YAML-ish)
    ('{"width": 640, "height": 480, "f": 600}', "camera: fx, fy, cx, cy missing or not a number"),
    ('{"width": 640, "fx": 600, "fy": 600, "cx": 320, "cy": 240}', "width and height must be given together"),
    ('{"fx": 600, "fy": 600, "cx": 320, "cy": 240, "dist_coeffs": [0.1, 0.0, 0.0]}', "dist_coeffs must be 4, 5 or 8"),
])
def test_a_wrong_camera_is_a_clear_message_before_the_webcam_starts(server, browser, pasted, said):
    """A pasted camera that is not the camera JSON was read after the webcam had started, and
    said JSON.parse's "Unexpected token ..." (or, when parsed, drew at NaN)."""
    _open(browser, server.url, camera=pasted)
    _js(browser, COUNT_CAMS)
    _start_webcam(browser)
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    assert said in _text(browser, "message"), _text(browser, "message")
    assert _js(browser, "return window.__cams") == 0


def test_a_camera_of_another_size_is_scaled_or_refused(server, browser):
    """The pasted camera was silently stretched to the video's size, also to another aspect
    ratio (fx and fy scaled apart: every pose wrong). Now the same aspect ratio is scaled and
    said so; another one is refused, naming both sizes. (The fake webcam is 640×480.)"""
    cam = json.loads(CAMERA)
    wide = {**cam, "width": 1280, "height": 720}
    _open(browser, server.url, camera=json.dumps(wide))
    _start_webcam(browser, 1)
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    said = _text(browser, "message")
    assert "the video is 640×480 but the pasted camera is 1280×720" in said and _count(browser) == 0, said

    double = {**cam, "width": 1280, "height": 960, "fx": 2 * cam["fx"], "fy": 2 * cam["fy"], "cx": 640, "cy": 480}
    _open(browser, server.url, camera=json.dumps(double))
    _start_webcam(browser, 1)
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    assert _text(browser, "message") == "the pasted 1280×960 camera is scaled to the video's 640×480"
    used = _js(browser, "return state.camera")
    assert _count(browser) == 1 and [used[k] for k in ("width", "height", "fx", "fy", "cx", "cy")] == \
        [640, 480, cam["fx"], cam["fy"], 320, 240]


def test_the_overlay_projects_as_the_tracker_does(server, browser):
    """The page's projection (the drawn wireframe) is tracking/camera.py's, also with the
    rational model's k4..k6 (8 coefficients, which the service accepts): they were ignored, the
    wireframe drawn off the object near the image's edges."""
    import numpy as np

    from quatrack.tracking.camera import PinholeCamera
    from quatrack.tracking import quaternion as quat

    _open(browser, server.url)
    rng = np.random.default_rng(5)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    t = np.array([3.0, -2.0, 60.0])
    pts = rng.uniform(-25, 25, size=(50, 3))
    for dist in ([0.0] * 5, [-0.3, 0.12, 0.002, -0.001, -0.02], [0.2, -0.1, 0.001, 0.002, 0.03, 0.5, -0.2, 0.1]):
        cam = {"width": 640, "height": 480, "fx": 600.0, "fy": 610.0, "cx": 322.0, "cy": 238.0, "dist_coeffs": dist}
        page = _js(browser, "const R = rotation(arguments[1]);"
                            "return arguments[3].map((X) => project(arguments[0], R, arguments[2], X))",
                   cam, q.tolist(), t.tolist(), pts.tolist())
        ref = PinholeCamera(**{**cam, "dist_coeffs": np.array(dist)}).project(pts @ quat.to_matrix(q).T + t)
        assert np.allclose(np.array(page), ref, atol=1e-6), (dist, np.abs(np.array(page) - ref).max())


def test_every_control_is_labelled_and_the_messages_are_announced():
    """Accessibility basics, read from viewer.html: every form control has a label (a wrapping
    <label>, <label for>, aria-label or aria-labelledby naming an element), the message line is a
    live region (screen readers hear errors), the canvases say what they show. The camera's
    textarea had no label; the messages and canvases were silent."""
    from html.parser import HTMLParser

    class Page(HTMLParser):
        def __init__(self):
            super().__init__()
            self.stack, self.ids, self.label_for, self.controls, self.canvases, self.live = [], set(), set(), [], [], set()

        def handle_starttag(self, tag, attrs):
            a = dict(attrs)
            if "id" in a:
                self.ids.add(a["id"])
            if tag == "label" and "for" in a:
                self.label_for.add(a["for"])
            if tag in ("input", "select", "textarea"):
                self.controls.append((a, "label" in self.stack))
            if tag == "canvas":
                self.canvases.append(a)
            if a.get("role") in ("status", "alert") or "aria-live" in a:
                self.live.add(a.get("id"))
            if tag not in ("input", "meta", "link", "br"):
                self.stack.append(tag)

        def handle_endtag(self, tag):
            if tag in self.stack:
                del self.stack[len(self.stack) - 1 - self.stack[::-1].index(tag):]

    page = Page()
    page.feed((STATIC / "viewer.html").read_text())
    assert len(page.controls) == 5  # token, object, file, max frames, camera
    for a, wrapped in page.controls:
        named = wrapped or a.get("id") in page.label_for or a.get("aria-label") or \
            (a.get("aria-labelledby") and a["aria-labelledby"] in page.ids)
        assert named, f"{a.get('id')} has no label"
    assert "message" in page.live
    assert page.canvases and all(c.get("role") == "img" and c.get("aria-label") for c in page.canvases)


def test_the_page_loads_nothing_from_elsewhere_and_works_by_keyboard(server, browser):
    """Offline: every resource the page loaded during a run came from the server itself. Keyboard:
    Tab reaches every control in order, and Enter on the webcam button starts a run."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    _open(browser, server.url)
    _js(browser, "document.getElementById('max-frames').value = '1'; document.getElementById('token').focus()")
    order = ["token"]
    for _ in range(6):
        ActionChains(browser).send_keys(Keys.TAB).perform()
        order.append(_js(browser, "const e = document.activeElement; return e.id || e.tagName"))
    assert order == ["token", "object", "refresh", "webcam", "file", "max-frames", "camera-label"], order
    _js(browser, "document.getElementById('webcam').focus()")
    ActionChains(browser).send_keys(Keys.ENTER).perform()
    _wait(browser, lambda: _run_ended(browser), "the run's end")
    assert _count(browser) == 1
    urls = _js(browser, "return performance.getEntriesByType('resource').map(e => e.name)")
    assert urls and all(u.startswith(server.url + "/") for u in urls), urls
