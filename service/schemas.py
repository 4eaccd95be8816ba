"""Pydantic models at the service's edge: what clients send and get, with OpenAPI examples.

Units and conventions are the contract's: pose object → camera, ``t`` in mesh units,
``q_wxyz`` scalar first with ``w ≥ 0``, covariances 6×6 over ``[p, δθ]`` row-major.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_core import PydanticCustomError

from quatrack.tracking.camera import PinholeCamera
from quatrack.viewsets.camera import CAMERA_FIELDS, camera_from_dict, misspelt_field
from quatrack.viewsets.errors import SpecError

Vec3 = list[float]


def _strict_bool(v):
    """A JSON boolean only (pydantic's lax mode takes ``"yes"``, ``1``, ``"on"`` as true)."""
    if not isinstance(v, bool):
        raise PydanticCustomError("bool_expected", "expected true or false, got {got}", {"got": repr(v)[:40]})
    return v


CAMERA_EXAMPLE = {"width": 640, "height": 480, "fx": 669.7, "fy": 667.8, "cx": 320.0, "cy": 240.0,
                  "dist_coeffs": [0, 0, 0, 0, 0]}


class ErrorDetail(BaseModel):
    code: str = Field(description="stable machine-readable code, e.g. bad_image, unknown_object")
    message: str = Field(description="what is wrong, for a human")


class ErrorResponse(BaseModel):
    """Every 4xx/5xx body, REST and WebSocket alike."""

    error: ErrorDetail
    model_config = ConfigDict(json_schema_extra={"examples": [
        {"error": {"code": "unknown_object", "message": "no object named 'mug' in the store"}}]})


class CameraIn(BaseModel):
    """A camera as in the contract's camera file. ``width``/``height`` may be left out on the
    REST endpoint (the image's size is used); ``dist_coeffs`` is OpenCV's order."""

    width: int | None = Field(None, gt=0, le=100_000)
    height: int | None = Field(None, gt=0, le=100_000)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    dist_coeffs: list[float] | None = None
    # (WebSocket) the intrinsics are a guess, not a calibration (the viewer's 60° field of view
    # when none is pasted): the session learns no views from it (QUATRACK_LEARN_VIEWS), since
    # views lifted with wrong intrinsics would teach the stored model wrong 3-D points
    guessed: bool = False
    model_config = ConfigDict(extra="ignore", json_schema_extra={"examples": [CAMERA_EXAMPLE]})

    @field_validator("fx", "fy", "cx", "cy", "width", "height", mode="before")
    @classmethod
    def _a_number(cls, v):
        """JSON numbers only: pydantic's lax mode would take ``true`` as 1 and ``"600"`` as 600.
        And finite ones, said before the bounds are checked: ``fx=nan`` (a query's, or Python's
        NaN) was told "Input should be greater than 0", where ``fx=inf`` was told it must be finite."""
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise ValueError(f"must be a number, got {type(v).__name__}")
        if isinstance(v, float) and not math.isfinite(v):
            raise PydanticCustomError("finite_number", "must be finite, got {got}", {"got": repr(v)})
        return v

    _a_bool = field_validator("guessed", mode="before")(_strict_bool)

    @model_validator(mode="before")
    @classmethod
    def _no_misspelt_field(cls, data):
        """A misspelt field (``dist_coeff``, ``fxx``) is refused with a suggestion, not ignored
        (:func:`quatrack.viewsets.camera.misspelt_field`: the distortion was dropped silently)."""
        if isinstance(data, dict) and (msg := misspelt_field(data, (*CAMERA_FIELDS, "guessed", "ack", "type"), "")) is not None:
            raise ValueError(msg.removeprefix(": "))
        return data

    @field_validator("dist_coeffs", mode="before")
    @classmethod
    def _numbers(cls, v):
        if v is not None and (not isinstance(v, list) or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in v)):
            raise ValueError("must be a list of numbers (OpenCV order k1, k2, p1, p2[, k3[, k4, k5, k6]])")
        return v

    def to_camera(self, image_size: tuple[int, int] | None = None) -> PinholeCamera:
        """The project's camera; the image's (width, height) fills a missing size."""
        from .errors import ApiError  # (here: the client imports these schemas, without the server's stack)

        data = self.model_dump(include=set(CameraIn.model_fields) - {"guessed"})
        if data["width"] is None or data["height"] is None:
            if image_size is None:
                raise ApiError(422, "bad_camera", "camera: width and height are required")
            data["width"], data["height"] = image_size
        if data["dist_coeffs"] is None:
            data.pop("dist_coeffs")
        try:
            return camera_from_dict(data, "camera")
        except (SpecError, ValueError) as exc:
            raise ApiError(422, "bad_camera", str(exc)) from None

    @staticmethod
    def error_message(exc: ValidationError) -> str:
        """A refused camera's ``bad_camera`` message, REST field and WebSocket message alike:
        ``camera.FIELD: what is wrong`` (the first problem), ``camera: ...`` when it is not an object."""
        errors = exc.errors()
        e = errors[0]
        missing = [".".join(map(str, m["loc"])) for m in errors if m["type"] == "missing"]
        if e["type"] == "missing" and len(missing) > 1:  # (all of them: "camera.fx: Field required" named one of four)
            return f"camera: fields {', '.join(missing)} are required"
        where = ".".join(map(str, e["loc"]))
        return f"camera{'.' + where if where else ''}: {e['msg']}"


class CameraMessage(CameraIn):
    """The WebSocket's camera message: the contract's camera object, or the typed
    ``{"type": "camera", "camera": {...}}``; ``"ack": true`` (beside the camera or inside it) asks
    for the ``{"type": "ready"}`` answer. Anything else is ``bad_camera`` with
    :meth:`CameraIn.error_message`'s message."""

    ack: bool = False

    _ack_bool = field_validator("ack", mode="before")(_strict_bool)

    @model_validator(mode="before")
    @classmethod
    def _typed(cls, data):
        if isinstance(data, dict) and data.get("type") == "camera" and "camera" in data:
            cam = data["camera"]
            return {**cam, "ack": data["ack"]} if isinstance(cam, dict) and "ack" in data else cam
        return data


class PoseOut(BaseModel):
    t: Vec3 = Field(description="object origin in the camera frame, mesh units")
    q_wxyz: list[float] = Field(description="unit quaternion, scalar first, w ≥ 0")


class LocateOut(BaseModel):
    """The same JSON object as ``quatrack locate --json``."""

    image: str | None = Field(None, description="the uploaded file's name (multipart); null for a raw body")
    found: bool
    bbox: list[float] | None = Field(None, description="[x, y, w, h] pixels: found, the object's box in the image (the mesh "
                                                         "projected at the pose); not found, the RFCH window searched")
    window: list[float] | None = Field(None, description="[x, y, w, h] of the RFCH window searched, pixels (null: the "
                                                           "whole image was searched without one)")
    chi2: float | None = None
    viewset: str | None = None
    matches: int
    inliers: int
    reprojection_rms_px: float | None = None
    pose: PoseOut | None = None
    covariance: list[list[float]] | None = Field(None, description="6×6 over [p, δθ], row-major")
    time_ms: dict[str, float]
    reason: str | None = None
    searched: str | None = None
    object: str | None = Field(None, description="the object's name")
    verification: dict | None = Field(None, description="the evidence for the pose checked, with its calibrated "
                                      "`confidence` (docs/contract.md, Extensions: issue 13)")
    model_config = ConfigDict(json_schema_extra={"examples": [{
        "found": True, "bbox": [214.3, 131.8, 205.1, 236.4], "window": [201.0, 118.0, 232.0, 260.0], "chi2": 0.41,
        "viewset": "view0",
        "matches": 180, "inliers": 134, "reprojection_rms_px": 1.2,
        "pose": {"t": [-1.9, 3.2, 62.0], "q_wxyz": [0.31, 0.87, -0.26, 0.28]},
        "covariance": [[0.0] * 6 for _ in range(6)],
        "time_ms": {"localise": 40.0, "match": 90.0, "pnp": 10.0, "total": 150.0},
        "reason": None, "searched": "window"}]})


class RivalOut(BaseModel):
    """An object found at the same place as a more confident one, and so reported not found."""

    object: str
    confidence: float = Field(description="its verification's confidence (the found object's is higher)")
    pose: PoseOut = Field(description="its pose (object → camera, its mesh's units): the same print at another "
                                      "size is seen alike at another distance")


class FoundObjectOut(LocateOut):
    """One object of ``POST /v1/pose``'s answer: the per-object answer plus its ``rivals``."""

    rivals: list[RivalOut] = Field(default_factory=list, description=(
        "objects found at the same place (projected boxes overlapping by more than half) with less confidence, "
        "reported not found in its place: one answer per place"))
    ros: dict | None = Field(None, description="with ?format=ros and this object's mesh_unit: "
                                               "geometry_msgs/PoseWithCovarianceStamped (metres, x,y,z,w)")
    ros_note: str | None = Field(None, description="with ?format=ros: why there is no `ros` (no mesh_unit for this object)")


class LocateAllOut(BaseModel):
    """``POST /v1/pose``: the objects found in one image (each as ``POST /v1/objects/{name}/pose``
    answers, with its ``object`` name and ``rivals``); ``searched``: the objects searched;
    ``not_found``: each object searched and not found, with its reason; ``failed``: models that
    cannot be loaded."""

    found: bool
    objects: list[FoundObjectOut]
    searched: list[str]
    not_found: dict[str, str] = Field(default_factory=dict, description=(
        "each object searched and not found: why (as POST /v1/objects/{name}/pose's `reason`)"))
    failed: dict[str, str] = Field(default_factory=dict)
    time_ms: dict[str, float]


class ObjectSummary(BaseModel):
    name: str
    created: str | None = None
    viewsets: int | None = Field(None, description="viewsets made by training")
    points3d: int | None = Field(None, description="3-D points of the viewsets made by training (learned views' points: "
                                                  "`learned_points3d`)")
    learned_viewsets: int = Field(0, description="viewsets learned while tracking since (track --learn, the service)")
    learned_points3d: int = Field(0, description="3-D points of the viewsets learned while tracking")
    loaded: bool = Field(description="already in memory (first request needs no loading)")
    error: str | None = Field(None, description="why the model cannot be loaded (corrupt files): requests for it get 503")


class ObjectList(BaseModel):
    objects: list[ObjectSummary]
    model_config = ConfigDict(json_schema_extra={"examples": [{"objects": [
        {"name": "cookie-box", "created": "2025-01-01T00:00:00Z", "viewsets": 19, "points3d": 9000, "loaded": True}]}]})


class ObjectDetail(BaseModel):
    name: str
    created: str | None = None
    training_summary: dict = Field(description="the manifest's training summary, as `quatrack models show` prints it")
    parameters: dict | None = None
    error: str | None = Field(None, description="why the model cannot be loaded, if it cannot")


class Health(BaseModel):
    status: Literal["ok"] = "ok"


class Ready(BaseModel):
    ready: bool = Field(description="start-up loading is done (objects that failed are listed, the others served)")
    models: list[str]
    tracker: str = Field(description="which tracker drives WebSocket sessions")
    failed: dict[str, str] = Field({}, description="objects of the store that cannot be loaded, with the reason")
    error: str | None = Field(None, description="why start-up loading failed (the server stays not ready; "
                                                "the log has the traceback); absent while it runs or once it succeeded")


class ReloadOut(BaseModel):
    """What ``POST /v1/objects/{name}/reload`` did."""

    name: str
    status: Literal["loaded", "unchanged", "removed", "failed"] = Field(
        description="loaded: the store's (new) model now serves new sessions; unchanged: it already did; "
                    "removed: gone from the store, out of service; failed: unreadable (see message)")
    message: str | None = None


# --- WebSocket messages (documented here; the socket itself is not in OpenAPI) -----------------

class VelocityOut(BaseModel):
    v: Vec3 = Field(description="linear velocity, mesh units/s, camera frame")
    omega: Vec3 = Field(description="angular velocity, rad/s, camera frame")


class TrackMessage(BaseModel):
    """One server message per processed frame."""

    frame: int = Field(description="0-based index of the frame in the order the server received it")
    time_s: float
    status: Literal["init", "tracking", "lost"]
    pose: PoseOut | None
    velocity: VelocityOut | None
    covariance: list[list[float]] | None
    inliers: int
    latency_ms: float = Field(description="from the frame's arrival to this message")
    skipped: int = Field(description="frames dropped (newer ones arrived) since the previous message")
    reason: str | None = Field(None, description="why lost, or how (re)initialised")
    timings_ms: dict[str, float] = {}
    ros: dict | None = Field(None, description="with ?format=ros: geometry_msgs/PoseWithCovarianceStamped (metres, x,y,z,w)")
    id: int | str | None = Field(None, description="the frame's id as its header gave it "
                                 "({\"type\": \"frame\", \"id\"}); absent when the client gave none")
