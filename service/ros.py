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
from quatrack.viewsets.names import NAME_RE

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


def ros_units(query: Mapping[str, str]) -> dict[str | None, str] | None:
    """``POST /v1/pose``'s mesh units: ``None`` for the plain JSON, else ``{name: unit}`` with the
    unit of every object not named under the key ``None``. ``mesh_unit=cm`` is every object's
    unit (as before); ``mesh_unit=cookie-box:cm,cube:m`` names each object's (a store mixes
    meshes in mm, cm and m, and one unit made the others' metres silently wrong); a bare unit
    among them is the others'. A bad list is a 422 ``bad_format`` saying the form."""
    fmt = query.get("format", "json")
    text = query.get("mesh_unit")
    if fmt != "ros" or text is None or not (":" in text or "," in text):
        unit = ros_unit(query)
        return None if unit is None else {None: unit}
    units: dict[str | None, str] = {}
    form = "mesh_unit=NAME:UNIT,NAME:UNIT,... (UNIT mm, cm or m; a bare UNIT: every object not named)"
    for item in text.split(","):
        name, sep, unit = (part.strip() for part in item.rpartition(":"))
        key = name if sep else None
        if unit not in UNIT_METRES or (sep and not NAME_RE.fullmatch(name)):
            raise ApiError(422, "bad_format", f"mesh_unit: {item.strip()[:80]!r} is not NAME:UNIT or UNIT; use {form}")
        if key in units:
            raise ApiError(422, "bad_format", f"mesh_unit: {'the bare unit' if key is None else repr(key)} is given twice; "
                                              f"use {form}")
        units[key] = unit
    return units


def unknown_unit_names(units: Mapping[str | None, str] | None, names) -> list[str]:
    """The objects ``units`` names that are not among ``names`` (a typo would leave the object
    meant without ``ros``, answered with a note only)."""
    known = set(names)
    return sorted(n for n in (units or {}) if n is not None and n not in known)


def add_to_found_object(result: dict, units: Mapping[str | None, str] | None) -> dict:
    """One object of a ``POST /v1/pose`` answer with ``"ros"`` added in its own mesh's unit; an
    object whose unit was not given gets no ``"ros"`` but a ``"ros_note"`` saying how to give it
    (its metres cannot be guessed: an answer in the wrong unit is worse than none)."""
    if units is None:
        return result
    unit = units.get(result.get("object"), units.get(None))
    if unit is None:
        name = result.get("object")
        result["ros_note"] = f"no mesh_unit for {name!r}: add {name}:mm, {name}:cm or {name}:m to mesh_unit"
        return result
    return add_to_locate(result, unit)


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
