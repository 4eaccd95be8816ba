"""Parsing of camera files and object specs: good input round-trips, bad input names its culprit."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from quatrack.tracking import quaternion as quat
from quatrack.viewsets.camera import camera_to_dict, load_camera
from quatrack.viewsets.errors import SpecError
from quatrack.viewsets.spec import load_spec, parse_pose

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "cookie-box"


def test_example_spec_parses_with_paths_relative_to_spec():
    spec = load_spec(EXAMPLE / "object.json")
    assert spec.name == "cookie-box"
    assert spec.mesh_path == (EXAMPLE / "box.ply").resolve()
    assert spec.views[0].image_path.is_file()
    assert spec.views[0].camera.width == 718 and spec.views[0].camera.fx > 1000
    assert len(spec.checksum) == 64


def test_three_pose_forms_agree():
    rng = np.random.default_rng(1)
    rvec = rng.normal(size=3)
    t = [1.0, -2.0, 40.0]
    R = cv2.Rodrigues(rvec)[0]
    q = quat.from_rotvec(rvec)
    poses = [
        parse_pose({"rvec": rvec.tolist(), "tvec": t}),
        parse_pose({"R": R.tolist(), "t": t}),
        parse_pose({"q_wxyz": (q * 3.0).tolist(), "t": t}),  # not normalised on purpose
    ]
    for p in poses:
        np.testing.assert_allclose(p.R, R, atol=1e-9)
        np.testing.assert_allclose(p.t, t)


@pytest.mark.parametrize(
    "pose, words",
    [
        ({"euler": [0, 0, 0], "t": [0, 0, 1]}, ["unknown pose format"]),
        ({"rvec": [0, 0], "tvec": [0, 0, 1]}, ["rvec"]),
        ({"R": [[1, 0, 0], [0, 1, 0], [0, 0, 2]], "t": [0, 0, 1]}, ["not a rotation"]),
        ({"q_wxyz": [0, 0, 0, 0], "t": [0, 0, 1]}, ["q_wxyz"]),
    ],
)
def test_bad_poses_are_named(pose, words):
    with pytest.raises(SpecError) as info:
        parse_pose(pose, "view 3: pose")
    for w in ["view 3", *words]:
        assert w in str(info.value)


def test_camera_json_and_yaml(tmp_path):
    cam = {"width": 640, "height": 480, "fx": 600.0, "fy": 610.0, "cx": 320.5, "cy": 239.5,
           "dist_coeffs": [0.1, -0.05, 0.001, 0.002, 0.0]}
    (tmp_path / "c.json").write_text(json.dumps(cam))
    c1 = load_camera(tmp_path / "c.json")
    assert camera_to_dict(c1) == cam
    fs = cv2.FileStorage(str(tmp_path / "c.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", c1.matrix)
    fs.write("distortion_coefficients", np.array(cam["dist_coeffs"]).reshape(1, 5))
    fs.release()
    c2 = load_camera(tmp_path / "c.yml")
    d2 = camera_to_dict(c2)
    assert d2.pop("dist_coeffs") == pytest.approx(cam["dist_coeffs"])
    assert d2 == pytest.approx({k: v for k, v in cam.items() if k != "dist_coeffs"})


def test_a_path_written_relative_to_the_current_folder_is_named_as_such(tmp_path, monkeypatch):
    """The spec in a subfolder, its paths written from where the user stands: training said only
    "<spec folder>/box.ply: mesh file not found" of a file the user sees right there."""
    (tmp_path / "specs").mkdir()
    (tmp_path / "box.ply").write_bytes((EXAMPLE / "box.ply").read_bytes())
    data = json.loads((EXAMPLE / "object.json").read_text())
    data["mesh"] = "box.ply"
    data["views"][0]["image"] = str(EXAMPLE / "resized_IMG_3875.JPG")
    (tmp_path / "specs" / "object.json").write_text(json.dumps(data))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SpecError, match=r"field 'mesh': .*specs/box.ply not found; paths are relative to the "
                                        r"spec's folder.*write '\.\./box.ply'"):
        load_spec("specs/object.json")


def test_fields_a_spec_does_not_know_are_warned_of(tmp_path):
    """A typo (``"mask_path"`` for ``"mask"``) trained silently without the mask: the fields are
    still ignored (a spec may carry more), but the CLI is told, one line per object or view."""
    said = []
    spec = load_spec(_spec(tmp_path, units="cm", view_mask_path="mask.png"), warn=said.append)
    assert spec.views[0].mask_path is None
    assert len(said) == 2
    assert "'units'" in said[0] and "view 0" in said[1] and "'mask_path'" in said[1] and "mask" in said[1]
    said.clear()
    load_spec(EXAMPLE / "object.json", warn=said.append)
    assert said == []


def test_a_spec_and_a_camera_saved_with_a_byte_order_mark_are_read(tmp_path):
    """Windows tools (Notepad, PowerShell's Out-File) save UTF-8 with a BOM, which JSON may carry
    (RFC 8259): both files were refused as "not valid JSON (Unexpected UTF-8 BOM ...)"."""
    cam = {"width": 718, "height": 480, "fx": 1770.0, "fy": 1770.0, "cx": 359.0, "cy": 240.0}
    (tmp_path / "cam.json").write_bytes(b"\xef\xbb\xbf" + json.dumps(cam).encode())
    assert camera_to_dict(load_camera(tmp_path / "cam.json"))["fx"] == 1770.0
    spec = _spec(tmp_path, view_camera="cam.json")
    spec.write_bytes(b"\xef\xbb\xbf" + spec.read_bytes())
    assert load_spec(spec).views[0].camera.fx == 1770.0


def test_an_opencv_yaml_image_size_written_as_text_is_named(tmp_path):
    """``image_width: "718"`` (quoted): OpenCV reads a string's real() as 1.8e308, and the
    message said "'width' must be an integer 1..100000, got 1797693134862315708...": now it
    names the file's own field."""
    fs = cv2.FileStorage(str(tmp_path / "c.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", "718")
    fs.write("image_height", 480)
    fs.write("camera_matrix", np.array([[600.0, 0, 359], [0, 600, 240], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.zeros((1, 5)))
    fs.release()
    with pytest.raises(SpecError, match=r"c\.yml: field 'image_width' must be a number of pixels$"):
        load_camera(tmp_path / "c.yml")


@pytest.mark.parametrize(
    "change, words",
    [
        ({"fx": -5.0}, ["fx=-5"]),
        ({"fy": 0}, ["positive"]),
        ({"width": 0}, ["width"]),
        ({"cx": "a"}, ["cx"]),
        ({"dist_coeffs": [1, 2, 3]}, ["dist_coeffs"]),
        # a JSON integer too large for a float (math.isfinite raised OverflowError: a traceback)
        ({"fx": 10**400}, ["fx", "finite"]),
        ({"width": 10**400}, ["width"]),
        ({"dist_coeffs": [10**400, 0, 0, 0, 0]}, ["dist_coeffs"]),
    ],
)
def test_bad_cameras_are_named(tmp_path, change, words):
    cam = {"width": 640, "height": 480, "fx": 600.0, "fy": 610.0, "cx": 320.0, "cy": 240.0}
    cam.update(change)
    (tmp_path / "bad.json").write_text(json.dumps(cam))
    with pytest.raises(SpecError) as info:
        load_camera(tmp_path / "bad.json")
    assert "bad.json" in str(info.value)
    for w in words:
        assert w in str(info.value)


def _spec(tmp_path, **changes):
    data = json.loads((EXAMPLE / "object.json").read_text())
    data["mesh"] = str(EXAMPLE / "box.ply")
    data["views"][0]["image"] = str(EXAMPLE / "resized_IMG_3875.JPG")
    for k, v in changes.items():
        if k.startswith("view_"):
            data["views"][0][k[5:]] = v
        else:
            data[k] = v
    p = tmp_path / "spec.json"
    p.write_text(json.dumps(data))
    return p


@pytest.mark.parametrize(
    "changes, words",
    [
        ({"name": "../escape"}, ["name"]),
        ({"views": []}, ["views"]),
        ({"view_pose": {"foo": 1}}, ["view 0", "unknown pose format"]),
        ({"view_pose": {"rvec": [0, 0, 0], "tvec": [0, 0, 10**400]}}, ["view 0", "tvec", "finite"]),
        ({"view_camera": "missing_camera.json"}, ["missing_camera.json"]),
        ({"view_camera": {"width": 718, "height": 480, "fx": 0, "fy": 1, "cx": 1, "cy": 1}}, ["view 0", "positive"]),
    ],
)
def test_bad_specs_are_named(tmp_path, changes, words):
    with pytest.raises(SpecError) as info:
        load_spec(_spec(tmp_path, **changes))
    for w in words:
        assert w in str(info.value)


def test_camera_path_and_mask_resolved_relative_to_spec(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "cam.json").write_text(json.dumps(
        {"width": 718, "height": 480, "fx": 1770.0, "fy": 1771.0, "cx": 359.0, "cy": 240.0}))
    p = _spec(tmp_path, view_camera="sub/cam.json", view_mask="sub/m.png")
    spec = load_spec(p)
    assert spec.views[0].camera.fx == 1770.0
    assert spec.views[0].mask_path == (tmp_path / "sub" / "m.png").resolve()


def test_a_deeply_nested_spec_is_not_valid_json(tmp_path):
    from quatrack.viewsets.errors import SpecError
    from quatrack.viewsets.spec import load_spec

    path = tmp_path / "object.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(SpecError, match="nested too deeply"):
        load_spec(path)


def _yaml_camera(path: Path, camera: dict, size: tuple | None) -> Path:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in zip(("image_width", "image_height"), size or ()):
        if value is not None:
            fs.write(key, value)
    K = np.array([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1]], float)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.array(camera["dist_coeffs"], float).reshape(1, -1))
    fs.release()
    return path


def test_an_opencv_yaml_without_its_image_size_is_accepted_and_sized_by_its_images(tmp_path):
    """The shared contract: "An OpenCV YAML with camera_matrix / distortion_coefficients is also
    accepted" — one without image_width / image_height was refused ("fields ... are required").
    It is now a camera sized by its images: training sizes it by its photo (and checks it there),
    ``locate`` by the query, and the model and the pose are those of the sized JSON camera. One
    size without the other is still refused."""
    from quatrack.recognition.locate import locate
    from quatrack.viewsets.train import TrainParams, train_object

    data = json.loads((EXAMPLE / "object.json").read_text())
    cam = data["views"][0]["camera"]
    yml = _yaml_camera(tmp_path / "cam.yml", cam, None)
    sizeless = load_camera(yml)
    assert (sizeless.width, sizeless.height, sizeless.fx, sizeless.cx) == (None, None, cam["fx"], cam["cx"])
    with pytest.raises(SpecError, match="'image_width' and 'image_height' must both be given"):
        load_camera(_yaml_camera(tmp_path / "half.yml", cam, (718, None)))
    with pytest.raises(SpecError, match="not the focal lengths"):
        load_camera(_yaml_camera(tmp_path / "bad.yml", {**cam, "fx": 1.0, "fy": 5000.0}, None))

    data["mesh"] = str(EXAMPLE / data["mesh"])
    data["views"][0]["image"] = str(EXAMPLE / data["views"][0]["image"])
    models = []
    for name, camera in (("json", cam), ("yaml", str(yml))):
        data["views"][0]["camera"] = camera
        (tmp_path / f"{name}.json").write_text(json.dumps(data))
        models.append(train_object(load_spec(tmp_path / f"{name}.json"), TrainParams()))
    a, b = (m.viewsets[0].camera for m in models)
    assert (b.width, b.height) == (a.width, a.height) == (718, 480) and b.fx == a.fx
    # a query with the sizeless camera: sized by the image, the same pose as with the sized one
    video = cv2.VideoCapture(str(EXAMPLE / "box.mp4"))
    ok, frame = video.read()
    video.release()
    query = load_camera(EXAMPLE / "camera.json")
    q_yml = load_camera(_yaml_camera(tmp_path / "q.yml", camera_to_dict(query), None))
    r1, r2 = locate(frame, query, models[0]), locate(frame, q_yml, models[0])
    assert r1.found and r2.found and np.allclose(r1.t, r2.t) and np.allclose(r1.q_wxyz, r2.q_wxyz)


@pytest.mark.parametrize(
    "pose, words",
    [
        ({"rvec": [0, 0, 0], "tvec": [0, 0, 1], "q_wxyz": [1, 0, 0, 0], "t": [0, 0, 2]},
         ["twice", "{rvec, tvec}", "{q_wxyz, t}"]),
        ({"q_wxyz": [1, 0, 0, 0], "t": [0, 0, 2], "rvec": [0, 0, 0]}, ["'rvec'", "{rvec, tvec}", "keep one form"]),
        ({"R": np.eye(3).tolist(), "t": [0, 0, 2], "tvec": [0, 0, 1]}, ["'tvec'", "keep one form"]),
    ],
)
def test_a_pose_with_fields_of_two_forms_is_refused(pose, words):
    """One set of fields was used and the other ignored without a word (user report F3)."""
    with pytest.raises(SpecError) as info:
        parse_pose(pose, "spec.json: view 2: pose")
    for w in ["view 2", *words]:
        assert w in str(info.value)


def test_an_unknown_field_in_a_pose_is_warned_of(tmp_path):
    """``"tvec_mm"`` beside ``rvec``/``tvec`` was ignored silently, while unknown fields of the
    spec and of a view are told (user report F3)."""
    said = []
    pose = parse_pose({"rvec": [0, 0, 0], "tvec": [0, 0, 1], "tvec_mm": [0, 0, 1000]}, "view 0: pose", said.append)
    np.testing.assert_allclose(pose.t, [0, 0, 1])
    assert len(said) == 1 and "view 0: pose" in said[0] and "'tvec_mm'" in said[0] and "ignored" in said[0]
