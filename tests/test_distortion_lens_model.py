"""Strong lens distortion (wide-angle lenses calibrated with OpenCV: k1..k3, p1, p2 and the
rational model's k4..k6): the projection, its Jacobian and the pixels' rays against OpenCV and
finite differences, and past the radius where the lens polynomial turns back."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from quatrack.tracking.camera import PinholeCamera, valid_radius2
from quatrack.tracking.pose import Pose
from quatrack.viewsets.mesh import make_mesh
from quatrack.viewsets.render import pixel_rays, render, undistort_pixels

F = 0.5 * 640 / np.tan(np.radians(28.0))  # the zoo's 640 × 480 camera, 56° across
LENSES = {
    "barrel-k1k2": [-0.35, 0.15, 0.0, 0.0, 0.0],  # never turns back
    "four": [-0.3, 0.1, 0.01, -0.008],
    "turns-k3": [-0.42, 0.2, 0.003, 0.002, -0.05],  # turns back at r = 1.32 (53°)
    "rational": [0.8, -0.2, 0.001, -0.001, 0.01, 1.2, 0.05, 0.02],  # turns back at r = 1.20
    "k1-only": [-0.45, 0.0, 0.0, 0.0],  # turns back at r = 0.86: inside the image's corners
}


def camera(name: str, **kw) -> PinholeCamera:
    return PinholeCamera(F, F, 319.5, 239.5, np.array(LENSES[name], float), width=640, height=480, **kw)


def inside(cam: PinholeCamera, uv: np.ndarray) -> np.ndarray:
    return (uv[:, 0] >= -0.5) & (uv[:, 0] < cam.width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < cam.height - 0.5)


def points(seed: int, n: int, spread: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(-spread, spread, n), rng.uniform(-spread, spread, n), np.ones(n)])
    return X * rng.uniform(0.3, 5.0, (n, 1))


@pytest.mark.parametrize("name", LENSES)
def test_projection_is_opencvs_within_the_lens_models_radius(name):
    """Points over the whole image (corners included), in front of and behind the camera, where
    the lens model still grows outwards: cv2.projectPoints' pixels."""
    cam = camera(name)
    X = points(1, 400, 1.2)
    X[::7] *= -1.0  # behind the camera (x = X/Z as OpenCV divides)
    r2 = (X[:, 0] ** 2 + X[:, 1] ** 2) / X[:, 2] ** 2
    X = X[r2 < cam.valid_r2]
    assert len(X) > 150
    ref, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.matrix, cam.dist_coeffs)
    np.testing.assert_allclose(cam.project(X), ref.reshape(-1, 2), atol=1e-8)


@pytest.mark.parametrize("name", ["turns-k3", "rational", "k1-only"])
def test_a_point_beyond_where_the_lens_turns_back_is_not_projected_into_the_image(name):
    """The polynomial turns back: cv2.projectPoints puts points 60–75° off the axis inside the
    image (turns-k3: (1.5, 1.1, 1) at pixel (202, 154); rational: (3, 2, 1) at (308, 232)).
    The projection grows outwards along every direction instead, continuously."""
    cam = camera(name)
    X = np.array([[1.5, 1.1, 1.0], [3.0, 2.0, 1.0], [-2.5, 0.4, 1.0], [0.3, -6.0, 1.0], [40.0, 30.0, 1.0]])
    assert np.all((X[:, 0] ** 2 + X[:, 1] ** 2) > cam.valid_r2)
    assert not inside(cam, cam.project(X)).any()
    # along a ray from the axis outwards the distance to the principal point only grows
    t = np.linspace(0.0, 6.0, 3001)[:, None]
    for direction in ([1.0, 0.0], [0.6, 0.8], [-0.8, 0.6], [-0.28, -0.96]):
        uv = cam.project(np.column_stack([t * direction, np.ones_like(t)]))
        rd = np.hypot(uv[:, 0] - cam.cx, uv[:, 1] - cam.cy)
        assert np.all(np.diff(rd) > 0), direction


def test_the_valid_radius_is_where_the_radial_model_stops_growing():
    """valid_radius2 where OpenCV's model turns back (k1 = −0.35, k2 = 0.05: r_d = r − 0.35 r³ +
    0.05 r⁵ peaks at r² = (1.05 − √0.1025)/0.5); the rational lens's, sampled: cv2.projectPoints'
    radius grows up to it and falls just after."""
    r2 = valid_radius2((-0.35, 0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert r2 == pytest.approx((1.05 - np.sqrt(0.1025)) / 0.5, rel=1e-12)
    cam = PinholeCamera(F, F, 319.5, 239.5, np.array([0.8, -0.2, 0, 0, 0.01, 1.2, 0.05, 0.02]))
    r = np.sqrt(cam.valid_r2) * np.linspace(0.0, 1.02, 5101)
    ref, _ = cv2.projectPoints(np.column_stack([r, np.zeros_like(r), np.ones_like(r)]), np.zeros(3), np.zeros(3),
                               cam.matrix, cam.dist_coeffs)
    grows = np.diff(ref.reshape(-1, 2)[:, 0]) > 0
    assert grows[:4999].all() and not grows[5001:].any()
    assert PinholeCamera(F, F, 320, 240).valid_r2 == np.inf  # no distortion: nothing changes
    assert camera("barrel-k1k2").valid_r2 == np.inf


@pytest.mark.parametrize("name", LENSES)
def test_the_jacobian_is_the_projections_derivative(name):
    """∂uv/∂X against central differences, over and far beyond the image (beyond the valid
    radius the outward continuation's derivative)."""
    cam = camera(name)
    X = points(2, 300, 4.0)
    uv, J = cam.project_with_jacobian(X)
    h = 1e-6
    Jn = np.stack([(cam.project(X + h * e) - cam.project(X - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)
    scale = np.abs(J).max(axis=(1, 2))[:, None, None]
    assert np.max(np.abs(J - Jn) / scale) < 1e-6
    np.testing.assert_array_equal(uv, cam.project(X))


@pytest.mark.parametrize("name", ["barrel-k1k2", "four", "turns-k3", "rational"])
def test_pixel_rays_are_opencvs_where_opencv_inverts_the_model(name):
    """Every 8th pixel of the image, corners included: cv2.undistortPoints' rays, bit for bit."""
    cam = camera(name)
    u, v = np.meshgrid(np.r_[0:640:8, 639], np.r_[0:480:8, 479])
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.matrix, cam.dist_coeffs, None, None, None,
                              (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)).reshape(-1, 2)
    np.testing.assert_array_equal(undistort_pixels(cam, uv), ref)


def test_pixels_beyond_the_lens_models_reach_get_rays_that_project_back_to_them():
    """k1 = −0.45 alone turns back at r_d = 0.574 and the image's corners are at 0.665: OpenCV's
    iteration left their rays ~50 px off. Each pixel's ray projects back onto it, and a crop's
    and a resized camera's rays are the whole image's."""
    cam = camera("k1-only")
    uv = np.array([[0.0, 0.0], [639.0, 479.0], [639.0, 0.0], [0.0, 479.0], [600.0, 30.0], [320.0, 240.0]])
    xy = undistort_pixels(cam, uv)
    assert np.all(np.isfinite(xy))
    np.testing.assert_allclose(cam.project(np.column_stack([xy, np.ones(len(xy))])), uv, atol=1e-6)
    rays = pixel_rays(cam)
    back = cam.project(np.column_stack([rays.reshape(-1, 2), np.ones(640 * 480)]))
    assert np.abs(back - np.stack(np.meshgrid(np.arange(640.0), np.arange(480.0)), -1).reshape(-1, 2)).max() < 1e-6
    crop = cam.cropped(500, 350, 640, 480)
    np.testing.assert_array_equal(pixel_rays(crop), rays[350:, 500:])
    half = cam.scaled(0.5)
    xy_half = undistort_pixels(half, (uv + 0.5) * 0.5 - 0.5)
    np.testing.assert_allclose(xy_half, xy, atol=1e-9)


@pytest.mark.parametrize("half", [2.0, 2.5, 3.0])
def test_a_plane_filling_the_view_through_a_lens_that_turns_back_covers_every_pixel(half):
    """A wall 1 unit ahead reaching past the field of view (63–72° off the axis at its corners):
    each pixel sees it, at depth 1. A triangle's pixel box is found by projecting its edges;
    the rational lens's polynomial put the far corners near the image's centre, and the boxes
    missed up to 30 240 of the 307 200 pixels."""
    cam = camera("rational")
    V = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]])
    mesh = make_mesh(V, np.array([[0, 1, 2], [0, 2, 3]]), "wall")
    buf = render(mesh, cam, Pose(np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])))
    assert (buf.face >= 0).all()
    np.testing.assert_allclose(buf.depth, 1.0, rtol=1e-9)


@pytest.mark.parametrize("dist", [[-50.0, 0.0, 0.0, 0.0], [-3.0, 0.0, 0.0, 0.0, 0.0], [0.0, -40.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
def test_a_lens_model_turning_back_inside_the_image_is_refused_naming_it(dist, tmp_path):
    """Coefficients that turn back before the image's nearest side (a typo, the wrong order) are
    refused where cameras are read, naming dist_coeffs; they were accepted, and every search
    said "not found". One turning back only near the corners (k1 = −0.45) is a lens."""
    from quatrack.viewsets.camera import camera_from_dict, load_camera
    from quatrack.viewsets.errors import SpecError

    base = {"width": 640, "height": 480, "fx": F, "fy": F, "cx": 319.5, "cy": 239.5}
    with pytest.raises(SpecError, match=r"camera: field 'dist_coeffs' .* turns back .* inside the 640×480 image"):
        camera_from_dict({**base, "dist_coeffs": dist})
    yml = tmp_path / "cam.yml"
    fs = cv2.FileStorage(str(yml), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array([[F, 0, 319.5], [0, F, 239.5], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array(dist, float).reshape(1, -1))
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.release()
    with pytest.raises(SpecError, match="dist_coeffs"):
        load_camera(yml)
    for name in LENSES:
        assert camera_from_dict({**base, "dist_coeffs": LENSES[name]}).has_distortion


def test_a_camera_sized_by_its_images_has_its_lens_checked_at_their_size():
    """An OpenCV YAML with camera_matrix / distortion_coefficients alone takes its images' size;
    a lens model turning back inside them is then refused as a sized camera's is (it went on,
    and the search said "not found")."""
    from quatrack.recognition.images import ImageError, prepare_image

    img = np.zeros((480, 640, 3), np.uint8)
    bad = PinholeCamera(F, F, 319.5, 239.5, np.array([-50.0, 0.0, 0.0, 0.0]))
    with pytest.raises(ImageError, match=r"dist_coeffs.*turns back .* inside the 640×480 image"):
        prepare_image(img, bad)
    good = PinholeCamera(F, F, 319.5, 239.5, np.array(LENSES["rational"]))
    assert prepare_image(img, good).camera.width == 640


def test_the_tracker_and_training_check_a_sized_by_images_camera_too(tmp_path):
    """The tracker sizes such a camera from its first frame, training from its photo: the same
    lens check (a track with k1 = -50 was lost at every frame, training learned through it)."""
    import json

    from conftest import EXAMPLE
    from quatrack.recognition.images import ImageError
    from quatrack.recognition.video import Tracker
    from quatrack.testing.scenes import example_store
    from quatrack.viewsets.spec import load_spec
    from quatrack.viewsets.errors import SpecError
    from quatrack.viewsets.store import load_model
    from quatrack.viewsets.train import TrainParams, train_object

    model = load_model(example_store(), "cookie-box")
    bad = PinholeCamera(F, F, 319.5, 239.5, np.array([-50.0, 0.0, 0.0, 0.0]))
    with pytest.raises(ImageError, match="dist_coeffs"):
        Tracker(model, bad).step(np.zeros((480, 640, 3), np.uint8), 0.0)

    spec = json.loads((EXAMPLE / "object.json").read_text())
    cam = spec["views"][0]["camera"]
    yml = tmp_path / "camera.yml"
    fs = cv2.FileStorage(str(yml), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[-50.0, 0.0, 0.0, 0.0, 0.0]]))
    fs.release()
    spec["views"][0]["camera"] = str(yml)
    spec["views"][0]["image"] = str(EXAMPLE / spec["views"][0]["image"])
    spec["mesh"] = str(EXAMPLE / spec["mesh"])
    (tmp_path / "object.json").write_text(json.dumps(spec))
    with pytest.raises(SpecError, match=r"view 0: camera: field 'dist_coeffs'"):
        train_object(load_spec(tmp_path / "object.json"), TrainParams(novel=None))


def test_the_service_refuses_such_a_lens_as_bad_camera():
    """The REST and WebSocket cameras are read by camera_from_dict: 422 bad_camera naming the
    field, also when the image's size fills a camera given without one."""
    from quatrack.service.errors import ApiError
    from quatrack.service.schemas import CameraIn

    cam = CameraIn(fx=F, fy=F, cx=319.5, cy=239.5, dist_coeffs=[-50.0, 0.0, 0.0, 0.0])
    with pytest.raises(ApiError) as err:
        cam.to_camera((640, 480))
    assert (err.value.status_code, err.value.code) == (422, "bad_camera")
    assert "field 'dist_coeffs'" in err.value.message and "turns back" in err.value.message


@pytest.mark.parametrize("dist", [[0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, -5.0, 0.0, 0.0],
                                  [-1e8, 0.0, 0.0, 0.0]])
def test_degenerate_lens_models_project_without_raising(dist):
    """A rational denominator reaching 0 (1 − r² at r = 1), points at infinity or on the camera
    plane: the compiled projection raises no ZeroDivisionError (numba raises where numpy gives
    inf; `track` with k4 = −5 stopped on a traceback), and equals the numpy one bit for bit."""
    cam = PinholeCamera(F, F, 319.5, 239.5, np.array(dist), width=640, height=480)
    X = np.vstack([[[1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [1e200, 0.0, 1.0], [np.inf, 0.0, 1.0], [0.0, 0.0, 0.0],
                    [1.0, 0.0, 0.0], [np.sqrt(cam.valid_r2), 0.0, 1.0]], points(3, 500, 3.0)])
    with np.errstate(all="ignore"):
        iz = 1.0 / X[:, 2]
        x, y = X[:, 0] * iz, X[:, 1] * iz
        uv, J = cam._project_distorted(x, y, iz, True)
        uv_ref, J_ref = cam._project_distorted_numpy(x, y, iz, True)
        rays = undistort_pixels(cam, np.array([[0.0, 0.0], [639.0, 479.0], [320.0, 240.0]]))
    np.testing.assert_array_equal(uv, uv_ref)
    np.testing.assert_array_equal(J, J_ref)
    assert np.isfinite(uv[:2]).all() and np.isfinite(rays[2]).all()


def _covered(cam: PinholeCamera, V: np.ndarray) -> np.ndarray:
    """Pixels whose ray lies inside the camera-frame triangle ``V`` (the render's own test, over
    every pixel of the image: no box)."""
    r = pixel_rays(cam)
    p = V[:, :2] / V[:, 2:3]
    e = [(p[(i + 1) % 3, 0] - p[i, 0]) * (r[..., 1] - p[i, 1]) - (p[(i + 1) % 3, 1] - p[i, 1]) * (r[..., 0] - p[i, 0])
         for i in range(3)]
    return (np.minimum(np.minimum(e[0], e[1]), e[2]) >= 0) | (np.maximum(np.maximum(e[0], e[1]), e[2]) <= 0)


@pytest.mark.parametrize("name", ["barrel-k1k2", "rational", "turns-k3", "k1-only"])
def test_a_triangle_reaching_out_of_the_view_draws_every_pixel_it_covers(name):
    """Triangles with corners far outside the view (seeded, up to 50 units off a depth of 1):
    render draws each pixel whose ray falls in the triangle. Their pixel boxes came from nine
    samples per edge, which left out the lens's curve of an edge between them: the triangle
    (−47, −0.4, 1), (33, −0.4, 1), (0, 40, 1) lost tens of thousands of its pixels."""
    cam = camera(name)
    rng = np.random.default_rng(7)
    tris = [np.array([[-47.0, -0.4, 1.0], [33.0, -0.4, 1.0], [0.0, 40.0, 1.0]])]
    for _ in range(12):
        V = np.column_stack([rng.uniform(-1, 1, (3, 2)) * rng.choice([0.8, 3.0, 50.0], (3, 1)), np.ones(3)])
        tris.append(V * rng.uniform(0.5, 2.0, (3, 1)))
    for V in tris:
        mesh = make_mesh(V, np.array([[0, 1, 2]]), "triangle")
        drawn = render(mesh, cam, Pose(np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3))).face >= 0
        want = _covered(cam, V)
        assert not (want & ~drawn).any(), (V.tolist(), int((want & ~drawn).sum()))
        assert not (drawn & ~want).any()
