"""What ``quatrack track`` says of frames whose size is not the camera's (user report, F8): frames
a pixel larger than the camera's said "its intrinsics scaled by 1 (a resized video)", and a stray
frame of another size was answered with a Python call, ``camera.scaled(...)``, on the command line."""

from __future__ import annotations

import cv2

from test_track_cli import _box_frames, _track


def test_frames_a_pixel_larger_say_the_real_factors(tmp_path, capsys):
    for k, frame in enumerate(_box_frames(2)):  # 640×480 padded to 641×481
        assert cv2.imwrite(str(tmp_path / f"{k:04d}.png"), cv2.copyMakeBorder(frame, 0, 1, 0, 1, cv2.BORDER_REPLICATE))
    assert _track(tmp_path, "--images", str(tmp_path / "*.png"), "--out", str(tmp_path / "poses.csv")) == 0
    assert capsys.readouterr().err.strip() == (
        "quatrack track: warning: the camera is for 640×480 px images and these are 641×481 px, a few pixels apart: "
        "its intrinsics scaled by 1.0016 wide and 1.0021 tall; if the frames are padded or cropped rather than "
        "resized, give a camera file for 641×481")


def test_a_stray_frame_of_another_size_is_given_the_command_line_s_remedy(tmp_path, capsys):
    frames = _box_frames(3)
    for k, frame in enumerate(frames):
        assert cv2.imwrite(str(tmp_path / f"{k:04d}.png"), cv2.resize(frame, (320, 240)) if k == 1 else frame)
    assert _track(tmp_path, "--images", str(tmp_path / "*.png"), "--out", str(tmp_path / "poses.csv")) == 0
    err = capsys.readouterr().err.strip()
    assert err == (f"quatrack track: frame 1 cannot be read, written as lost: {tmp_path / '0001.png'}: the camera is "
                   f"for 640×480 px images but the frame is 320×240 px (resized by 0.5? the frames of one run must "
                   f"all be 640×480 px: resize it, or track the 320×240 px frames in a run of their own, with a "
                   f"camera file for that size)"), err
    assert "scaled(" not in err


def test_a_camera_stating_the_wrong_size_is_refused_not_scaled(tmp_path, capsys):
    """As ``locate`` refuses it: the 640×480 intrinsics under 1280×960 were scaled by 0.5 (the
    object found nowhere, or at twice its depth) with a warning about a resized video."""
    import json

    from test_track_cli import EXAMPLE, example_store, main

    cam = json.loads((EXAMPLE / "camera.json").read_text()) | {"width": 1280, "height": 960}
    (tmp_path / "cam.json").write_text(json.dumps(cam))
    for k, frame in enumerate(_box_frames(2)):
        assert cv2.imwrite(str(tmp_path / f"{k:04d}.png"), frame)
    code = main(["track", "--object", "cookie-box", "--camera", str(tmp_path / "cam.json"), "--store",
                 str(example_store()), "--quiet", "--images", str(tmp_path / "*.png"), "--out", str(tmp_path / "p.csv")])
    err = capsys.readouterr().err
    assert code == 2 and "are its width and height wrong?" in err and "scaled by" not in err, err
    assert not (tmp_path / "p.csv").exists()
