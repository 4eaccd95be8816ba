"""``?format=ros``: the service's poses also as ROS ``geometry_msgs/PoseWithCovarianceStamped`` JSON.

Asked for per request (``POST .../pose?format=ros&mesh_unit=cm``) or per session (the track
WebSocket's URL carries the same query); the answer keeps every usual key and adds ``"ros"``
(``null`` without a pose), so a ROS bridge (see ``examples/ros2_republish.py``) publishes it as is.
ROS wants metres, so the unit of the object's mesh must be named. The conversion itself is
:func:`recognition.trackio.ros_pose_with_covariance`.
"""

from __future__ import annotations

import time
from typing import Mapping

from quatrack.recognition.trackio import UNIT_METRES, ros_pose_with_covariance

from .errors import ApiError


def ros_unit(query: Mapping[str, str]) -> str | None:
    """The mesh unit when ``format=ros`` was asked for, ``None`` for the plain JSON; a bad
    combination is a 422 ``bad_format``."""
    fmt = query.get("format", "json")
    if fmt not in ("json", "ros"):
        raise ApiError(422, "bad_format", f"format={fmt}: use json or ros")
    if fmt == "json":
        return None
    unit = query.get("mesh_unit")
    if unit not in UNIT_METRES:
        raise ApiError(422, "bad_format", "format=ros needs mesh_unit=mm, cm or m (the unit of the object's mesh; ROS uses metres)")
    return unit


def add_to_track_message(msg: dict, unit: str | None) -> dict:
    """A per-frame track message with ``"ros"`` added (stamp = the frame's ``time_s``)."""
    if unit is not None:
        msg["ros"] = ros_pose_with_covariance(msg, unit)
    return msg


def add_to_locate(result: dict, unit: str | None) -> dict:
    """A ``locate`` answer with ``"ros"`` added (stamp = the server's clock at the answer)."""
    if unit is not None:
        msg = {"frame": 0, "time_s": time.time(), "status": "init" if result.get("found") else "lost",
               "pose": result.get("pose"), "covariance": result.get("covariance"), "inliers": result.get("inliers", 0)}
        result["ros"] = ros_pose_with_covariance(msg, unit)
    return result
