"""quatrack as a robotics/AR engineer's Python library: what such a user passes (cameras built in
code, frames from numpy in odd layouts, a tracker reused, results copied) is either used as meant
or refused naming the argument — never a traceback from deep inside numpy or OpenCV."""

from __future__ import annotations

import numpy as np
import pytest

from quatrack.tracking.camera import PinholeCamera


def _camera(**kw) -> PinholeCamera:
    return PinholeCamera(**{"fx": 669.7, "fy": 667.8, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480, **kw})


def test_a_camera_size_given_as_floats_or_numpy_ints_is_kept_as_ints():
    # width=640.0 was kept as a float: Tracker.step ended in OpenCV's "Can't parse 'dsize'"
    for w, h in ((640.0, 480.0), (np.int64(640), np.int32(480)), (np.float32(640), 480)):
        cam = _camera(width=w, height=h)
        assert (cam.width, cam.height) == (640, 480)
        assert type(cam.width) is int and type(cam.height) is int
    assert _camera(width=None, height=None).width is None


@pytest.mark.parametrize("bad", ["640", 640.5, 0, -3, True, float("nan"), float("inf"), [640]])
def test_a_camera_size_that_is_no_whole_number_is_refused_naming_it(bad):
    # "640" passed float() and failed later with "'<=' not supported between instances of 'str' and 'int'"
    with pytest.raises(ValueError, match="width must be a whole number of pixels"):
        _camera(width=bad)


def test_a_rig_transform_of_the_wrong_shape_or_not_a_rotation_is_refused_naming_it():
    with pytest.raises(ValueError, match="R_rig must be a 3×3 matrix"):  # (numpy: "cannot reshape array of size 4")
        _camera(R_rig=np.eye(2))
    with pytest.raises(ValueError, match="t_rig must be 3"):
        _camera(t_rig=[1.0, 2.0])
    with pytest.raises(ValueError, match="R_rig is not a rotation"):  # (a reflection was used as given)
        _camera(R_rig=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="R_rig must be numbers"):
        _camera(R_rig="identity")
    c, s = np.cos(0.3), np.sin(0.3)
    cam = _camera(R_rig=[[c, 0, s], [0, 1, 0], [-s, 0, c]], t_rig=[-100, 0, 0])
    assert cam.R_rig.shape == (3, 3) and not cam.is_reference


@pytest.mark.parametrize("field, bad", [("min_points", "5"), ("max_points", 2.5), ("refresh_every", -1),
                                        ("audit_every_anchored", "6"), ("min_inliers", True)])
def test_tracker_settings_that_are_no_whole_numbers_are_refused_naming_them(field, bad):
    # min_points="5" ended in "'<' not supported between instances of 'int' and 'str'" at the
    # first refresh; refresh_every=2.5 and -1 were run as given
    from quatrack.recognition.video import TrackerParams

    with pytest.raises(ValueError, match=f"{field} must be a whole number >= 0"):
        TrackerParams(**{field: bad})


def test_tracker_settings_of_the_wrong_kind_are_refused_naming_them():
    from quatrack.recognition.video import TrackerParams

    with pytest.raises(ValueError, match="gate_chi2 must be a finite number"):  # (a numpy UFuncTypeError in the step)
        TrackerParams(gate_chi2="13")
    with pytest.raises(ValueError, match="systematic_px must be a finite number"):
        TrackerParams(systematic_px=float("nan"))
    with pytest.raises(ValueError, match="keyframe_synthetic_deg must be a tuple of numbers"):
        TrackerParams(keyframe_synthetic_deg=20.0)
    with pytest.raises(TypeError, match="klt: a KLTParams"):
        TrackerParams(klt={"win": 17})
    with pytest.raises(ValueError, match="motion_noise must be a dict"):
        TrackerParams(motion_noise=[("a", 1.0)])


def test_tracker_settings_in_other_number_types_are_read_as_meant():
    from quatrack.recognition.video import TrackerParams

    p = TrackerParams(max_points=150.0, refresh_every=np.int64(5), systematic_px=None, motion_noise=None)
    assert p == TrackerParams(max_points=150, refresh_every=5, systematic_px=None)
    assert type(p.max_points) is int and type(p.refresh_every) is int and p.motion_noise == {}
    assert TrackerParams().for_live_streams().anchor_max_side == 320


# --- the tracker on the bundled example's video ------------------------------------------------

@pytest.fixture(scope="module")
def box():
    """(model, camera, the video's first 6 frames) of the bundled example."""
    import cv2

    from quatrack.testing.scenes import EXAMPLE, example_model
    from quatrack.viewsets.camera import load_camera

    cap = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
    frames = [cap.read()[1] for _ in range(6)]
    cap.release()
    return example_model(), load_camera(EXAMPLE / "camera.json"), frames


def test_a_track_step_gives_its_pose_as_a_pose_and_survives_pickling(box):
    import copy
    import pickle

    from quatrack.recognition.video import Tracker

    model, camera, frames = box
    tracker = Tracker(model, camera)
    steps = [tracker.step(f, k / 30) for k, f in enumerate(frames[:3])]
    s = steps[-1]
    assert s.status == "tracking" and s.has_pose
    np.testing.assert_array_equal(s.pose.t, s.t)
    np.testing.assert_allclose(s.pose.q_wxyz, s.q_wxyz, rtol=0, atol=1e-12)  # (Pose renormalises)
    T = s.pose.as_matrix()  # (object → camera, as Located.pose)
    np.testing.assert_allclose(T[:3, :3] @ [1.0, 2.0, 3.0] + T[:3, 3], s.pose.apply([1.0, 2.0, 3.0]))
    C = s.covariance
    assert C.shape == (6, 6) and np.allclose(C, C.T, rtol=0, atol=1e-15) and np.linalg.eigvalsh(C).min() > 0
    again = pickle.loads(pickle.dumps(s))
    assert again.pose.allclose(s.pose, atol=0) and copy.deepcopy(s).status == "tracking"
    lost = tracker.skip(0.2, "unreadable")
    assert lost.pose is None and not lost.has_pose


def test_a_skipped_frame_may_not_go_back_in_time_as_a_stepped_one_may_not(box):
    # skip(0.0) after a frame at 0.1 s was answered, a step earlier than the one before it
    from quatrack.recognition.video import Tracker

    model, camera, frames = box
    tracker = Tracker(model, camera)
    tracker.step(frames[0], 0.1)
    with pytest.raises(ValueError, match="time goes backwards"):
        tracker.skip(0.0, "unreadable")
    assert tracker.skip(0.1, "unreadable").frame == 1  # (a repeated time is no step back)
    with pytest.raises(ValueError, match="time goes backwards"):
        tracker.step(frames[1], 0.05)
    tracker.reset()  # (a new stream: its clock may start again)
    assert tracker.skip(0.0, "unreadable").time_s == 0.0


def test_a_tracker_refuses_to_be_copied_or_pickled_saying_why(box):
    # (copy.deepcopy and pickle said "cannot pickle '_thread._local' object")
    import copy
    import pickle

    from quatrack.recognition.video import Tracker

    model, camera, _ = box
    tracker = Tracker(model, camera)
    for how in (copy.copy, copy.deepcopy, pickle.dumps):
        with pytest.raises(TypeError, match="a Tracker cannot be copied or pickled.*make another Tracker"):
            how(tracker)


def test_a_step_while_another_thread_is_inside_step_is_refused(box, monkeypatch):
    # two threads stepping one tracker (a ROS multi-threaded executor's callbacks) interleaved
    # their frames in one filter without a word
    import threading

    from quatrack.recognition.tracker import machine
    from quatrack.recognition.video import Tracker

    model, camera, frames = box
    tracker = Tracker(model, camera)
    inside, go_on = threading.Event(), threading.Event()
    convert = machine.to_bgr8

    def slow_convert(image):
        inside.set()
        go_on.wait(30)
        return convert(image)

    monkeypatch.setattr(machine, "to_bgr8", slow_convert)
    answers: list = []
    first = threading.Thread(target=lambda: answers.append(tracker.step(frames[0], 0.0)))
    first.start()
    assert inside.wait(30)
    with pytest.raises(RuntimeError, match="another call of it"):
        tracker.step(frames[1], 1 / 30)
    go_on.set()
    first.join(60)
    monkeypatch.setattr(machine, "to_bgr8", convert)
    assert answers[0].frame == 0 and tracker.step(frames[1], 1 / 30).frame == 1  # (the refused call counted nothing)


def test_frames_from_numpy_in_other_layouts_give_the_same_track_and_the_rest_say_what_is_expected(box):
    # float 0..1, 16-bit, strided views and Fortran order are the same frame as OpenCV's uint8 BGR;
    # an int64 array (np.array of a nested list) or channels-first said only "unsupported pixel
    # type int64" / "unsupported image shape (3, 480, 640)"
    from quatrack.recognition.images import ImageError
    from quatrack.recognition.video import Tracker

    model, camera, frames = box

    def track(convert):
        tracker = Tracker(model, camera)
        return [tracker.step(convert(f), k / 30) for k, f in enumerate(frames[:3])]

    ref = track(lambda f: f)
    assert ref[-1].status == "tracking"
    for convert in (lambda f: f.astype(np.float32) / 255, lambda f: f.astype(np.uint16) * 257,
                    lambda f: np.ascontiguousarray(f[..., ::-1])[..., ::-1], np.asfortranarray,
                    lambda f: np.pad(f, ((0, 0), (0, 0), (0, 1)))[..., :3]):
        got = track(convert)
        assert [s.status for s in got] == [s.status for s in ref]
        np.testing.assert_array_equal(got[-1].t, ref[-1].t)
        np.testing.assert_array_equal(got[-1].q_wxyz, ref[-1].q_wxyz)
    tracker = Tracker(model, camera)
    with pytest.raises(ImageError, match="int64: expected uint8, uint16, or float32/float64 in 0..1"):
        tracker.step(frames[0].astype(np.int64), 0.0)
    with pytest.raises(ImageError, match=r"channels first\? image.transpose\(1, 2, 0\)"):
        tracker.step(frames[0].transpose(2, 0, 1), 0.0)


LIBRARY_MODULES = ["quatrack.viewsets.train", "quatrack.viewsets.store", "quatrack.viewsets.camera",
                   "quatrack.viewsets.spec", "quatrack.recognition.tracker.params",
                   "quatrack.recognition.tracker.machine", "quatrack.recognition.video", "quatrack.tracking.camera"]


@pytest.mark.parametrize("name", LIBRARY_MODULES)
def test_the_library_modules_say_what_is_public_and_document_it(name):
    # (none but recognition.video had __all__; store.model_path and load_manifest had no docstring)
    import importlib
    import inspect

    module = importlib.import_module(name)
    assert isinstance(getattr(module, "__all__", None), list), f"{name} has no __all__"
    for public in module.__all__:
        obj = getattr(module, public)
        if inspect.isfunction(obj) or inspect.isclass(obj):
            assert inspect.getdoc(obj), f"{name}.{public} has no docstring"
    own = {n for n, o in vars(module).items() if not n.startswith("_") and (inspect.isfunction(o) or inspect.isclass(o))
           and o.__module__ == module.__name__}
    assert own <= set(module.__all__) | {"isfinite"}, f"{name}: public but not in __all__: {own - set(module.__all__)}"


def test_training_settings_of_the_wrong_kind_are_refused_naming_them():
    # min_keypoints="20" trained every viewset and then failed with "'<' not supported between
    # instances of 'int' and 'str'"; jobs=2.5 was truncated without a word
    from quatrack.viewsets.train import TrainParams

    for field, bad in (("min_keypoints", "20"), ("jobs", 2.5), ("jobs", -1)):
        with pytest.raises(ValueError, match=f"{field} must be a whole number"):
            TrainParams(**{field: bad})
    with pytest.raises(ValueError, match="min_contrast_threshold must be a number above 0"):
        TrainParams(min_contrast_threshold=0)
    with pytest.raises(TypeError, match="rfch: a RFCHParams"):
        TrainParams(rfch={"n_clusters": 16})
    with pytest.raises(TypeError, match="novel: a NovelViewParams or None"):
        TrainParams(novel=False)
    p = TrainParams(jobs=np.int64(2), min_keypoints=20.0, novel=None)
    assert p == TrainParams(jobs=2, novel=None) and type(p.jobs) is int and type(p.min_keypoints) is int
