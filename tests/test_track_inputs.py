"""Frame sources of ``quatrack track`` as a phone or a failing disk leaves them: variable frame
rates, rotation metadata, files cut short, folders with glob characters in their names, image
sequences with gaps. Every video is made here, small, in ``tmp_path``."""

from __future__ import annotations

import shutil
import subprocess
import warnings

import cv2
import numpy as np
import pytest

from quatrack.recognition import trackio


def frames(n: int, size: tuple[int, int] = (64, 48)) -> list[np.ndarray]:
    """``n`` distinct frames ``size`` = (width, height) px."""
    rng = np.random.default_rng(7)
    return [rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8) for _ in range(n)]


def write_video(path, images, fps: float = 30.0, fourcc: str = "MJPG") -> str:
    h, w = images[0].shape[:2]
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (w, h))
    assert out.isOpened()
    for image in images:
        out.write(image)
    out.release()
    return str(path)


def ffmpeg(*args: str) -> None:
    if shutil.which("ffmpeg") is None:
        pytest.skip("ffmpeg is not installed")
    subprocess.run(["ffmpeg", "-v", "error", "-y", *args], check=True)


def test_a_variable_frame_rate_video_keeps_its_gap(tmp_path):
    """Frames 5 on come 0.5 s late (a phone's pause): their time_s says so, unless --fps is given."""
    plain = write_video(tmp_path / "cfr.avi", frames(10))
    vfr = str(tmp_path / "vfr.mkv")
    ffmpeg("-i", plain, "-vf", "setpts=PTS+gte(N\\,5)*0.5/TB", "-fps_mode", "passthrough",
           "-c:v", "mjpeg", vfr)
    times = [t for _, t, _ in trackio.open_frames(video=vfr)]
    assert len(times) == 10
    assert times[4] == pytest.approx(4 / 30, abs=2e-3)
    assert times[5] == pytest.approx(5 / 30 + 0.5, abs=2e-3)
    assert times[9] - times[5] == pytest.approx(4 / 30, abs=2e-3)
    given = [t for _, t, _ in trackio.open_frames(video=vfr, fps=10)]  # (the user says the rate)
    assert given == [i / 10 for i in range(10)]


def test_a_video_without_timestamps_is_timed_by_its_rate():
    """A capture whose timestamps do not increase (all 0) is timed index / rate, exactly."""
    source = trackio.FrameSource("--video x", 25.0, _frames=iter(frames(4)), _pos=lambda: 0.0)
    assert [t for _, t, _ in source] == [i / 25 for i in range(4)]


@pytest.mark.parametrize("degrees", [90, 180])
def test_a_rotated_video_is_tracked_as_recorded(tmp_path, degrees):
    """A phone's 64×48 video tagged rotate 90 (or 180): its frames stay 64×48 as the sensor gave
    them (OpenCV turned them: 48×64 was refused by the camera, 180 tracked upside down), warned."""
    plain = write_video(tmp_path / "plain.mp4", frames(3), fourcc="mp4v")
    tagged = str(tmp_path / "tagged.mp4")
    ffmpeg("-i", plain, "-c", "copy", "-metadata:s:v:0", f"rotate={degrees}", tagged)
    if cv2.VideoCapture(tagged).get(cv2.CAP_PROP_ORIENTATION_META) % 360 == 0:
        pytest.skip("this ffmpeg writes no rotation metadata")
    with pytest.warns(trackio.SourceWarning, match=r"the video says rotate \d+°; its frames are tracked as recorded"):
        source = trackio.open_frames(video=tagged)
    got = [image for _, _, image in source]
    assert len(got) == 3 and all(image.shape == (48, 64, 3) for image in got)
    assert np.array_equal(got[0], next(iter(trackio.open_frames(video=plain)))[2])  # (not turned 180°)


def test_a_video_cut_short_is_warned_of(tmp_path):
    """An AVI copied only in part ends after 24-odd of the 40 frames its header counts: said once;
    the whole file and a run stopped by max_frames say nothing."""
    whole = write_video(tmp_path / "whole.avi", frames(40))
    data = open(whole, "rb").read()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) * 6 // 10])
    with pytest.warns(trackio.SourceWarning, match=r"the video ended after \d+ of the 40 frames its header counts") as seen:
        n = len(list(trackio.open_frames(video=str(cut))))
    assert 10 < n < 40 and len(seen) == 1 and f"after {n} of the 40" in str(seen[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(list(trackio.open_frames(video=whole))) == 40
        assert len(list(trackio.open_frames(video=str(cut), max_frames=5))) == 5


def test_the_bundled_video_is_not_called_cut_short():
    """The example's box.mp4 decodes to 455 of the 456 frames its header counts (one damaged slice
    at its start): every `quatrack track` and `demo` of it warned "cut short or damaged?". One frame
    short is tolerated; a copy cut short misses many (above)."""
    from quatrack.examples import example_dir

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(list(trackio.open_frames(video=str(example_dir() / "box.mp4")))) >= 450


def test_images_in_a_folder_named_with_glob_characters(tmp_path):
    """'run[2]/*.png': the folder's name is taken literally when the glob as given matches nothing."""
    folder = tmp_path / "run[2]"
    folder.mkdir()
    for k in (2, 1):
        cv2.imwrite(str(folder / f"f{k}.png"), np.full((8, 8, 3), k, np.uint8))
    source = trackio.open_frames(images=str(folder / "*.png"))
    assert [int(image[0, 0, 0]) for _, _, image in source] == [1, 2]
    assert trackio.image_paths(str(folder / "f?.png")) == [str(folder / "f1.png"), str(folder / "f2.png")]


def test_a_gap_in_an_image_sequence_is_warned_of(tmp_path):
    """frame_0004 then frame_0007: warned once, naming the first gap (times are index / rate);
    a sequence numbered every 5th frame is no gap."""
    for k in (1, 2, 3, 4, 7, 8, 10):
        cv2.imwrite(str(tmp_path / f"frame_{k:04d}.png"), np.zeros((8, 8, 3), np.uint8))
    with pytest.warns(trackio.SourceWarning, match=r"skips from \S*frame_0004.png to \S*frame_0007.png \(2 missing\?\)") as seen:
        assert len(list(trackio.open_frames(images=str(tmp_path / "*.png")))) == 7
    assert len(seen) == 1
    steady = tmp_path / "steady"
    steady.mkdir()
    for k in (0, 5, 10, 15):
        cv2.imwrite(str(steady / f"frame_{k:04d}.png"), np.zeros((8, 8, 3), np.uint8))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(list(trackio.open_frames(images=str(steady / "*.png")))) == 4
