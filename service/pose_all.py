"""``POST /v1/pose``: which trained objects are in the image, and where (issue 13).

Every model the store holds (and that can be loaded) is searched in the image, as
``quatrack locate --object all`` does (:func:`quatrack.recognition.locate.locate_all`); each one
found is returned with its pose and its verification. Objects that are not in the image are not
listed. The request is the same as ``POST /v1/objects/{name}/pose`` (multipart ``image`` +
``camera``, or the raw image with the camera in the query).
"""

from __future__ import annotations

import functools
import time
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request

from quatrack.recognition.images import ImageError
from quatrack.recognition.locate import LocateParams, locate_all, not_found

from .errors import ApiError
from . import ros
from .routes import (ERRORS, CameraQuery, FormatQuery, ServiceState, decode_with_camera, get_state, require_token,
                     serve_pose)
from .schemas import CameraIn, LocateAllOut

__all__ = ["LocateAllOut", "router"]  # (LocateAllOut was defined here; service.schemas holds it now)

MeshUnitsQuery = Annotated[str | None, Query(description=(
    "with format=ros: the meshes' units, one for all (mm, cm or m) or per object: NAME:UNIT,NAME:UNIT "
    "(a bare UNIT among them: every object not named); an object found without a unit gets `ros_note`, no `ros`"))]


ObjectsQuery = Annotated[str | None, Query(description=(
    "comma-separated names of the objects to search (default: every object of the store); "
    "an object the store does not hold is a 422"))]


router = APIRouter(prefix="/v1", tags=["pose"], dependencies=[Depends(require_token)], responses=ERRORS)


@router.post("/pose", response_model=LocateAllOut, response_model_exclude_unset=True,
             summary="search every trained object in one image (as `quatrack locate --object all --json`)")
async def pose_all(
    request: Request, state: Annotated[ServiceState, Depends(get_state)], query_camera: CameraQuery,
    format: FormatQuery = "json", mesh_unit: MeshUnitsQuery = None, objects: ObjectsQuery = None,
) -> dict:
    """With ``format=ros`` each object found also carries ``"ros"``, as the per-object endpoint's
    answer does, in its own mesh's unit (``mesh_unit``: one unit for all, or ``NAME:UNIT,...``);
    an object found whose unit was not given carries ``"ros_note"`` instead (metres from a
    guessed unit would be silently wrong). Naming an object the store does not hold is a 422.

    ``objects``: only these are searched (each costs ~40–60 ms on a 640×480 image where it is found,
    ~1.5–2.5× that where it is not, since its whole image is searched too; a store of many objects,
    of which a camera sees a few, had to be searched whole or object by object).

    Each object searched and not found is in ``not_found`` with its reason. A store with no
    object, or none that can be loaded, is a 503 (``no_objects``, ``model_unavailable``): a 200
    "nothing found" from a server that searched nothing reads as an empty scene."""
    units = ros.ros_units({"format": format, "mesh_unit": mesh_unit})
    if unknown := ros.unknown_unit_names(units, state.registry.names()):
        raise ApiError(422, "bad_format", f"mesh_unit names {', '.join(map(repr, unknown[:5]))}: no such object in the "
                                          f"store (GET /v1/objects lists them)")
    names = _chosen(objects, state.registry.names())
    if not names:  # (a 200 "nothing found" read as an empty shelf from a server with no model: the CLI refuses it)
        raise ApiError(503, "no_objects", "the server's store holds no trained object: train one into it "
                                          "(quatrack train SPEC --store DIR), then POST /v1/objects/NAME/reload")
    image_name, out = await serve_pose(state, request, query_camera, functools.partial(_locate_all, state, names=names))
    out["objects"] = [ros.add_to_found_object({"image": image_name, **o}, units) for o in out["objects"]]
    return out


def _chosen(objects: str | None, stored: list[str]) -> list[str]:
    """The store's objects to search: all (``objects`` not given), or those ``objects`` names
    (comma-separated, each once, in the store's order); a name the store does not hold, or an
    empty list, is a 422 ``invalid_input``."""
    if objects is None:
        return list(stored)
    asked = [n.strip() for n in objects.split(",")]
    if not all(asked):
        raise ApiError(422, "invalid_input", f"objects={objects[:80]!r}: comma-separated object names, none empty")
    if missing := [n for n in dict.fromkeys(asked) if n not in stored]:
        raise ApiError(422, "invalid_input", f"objects names {', '.join(repr(n[:80]) for n in missing[:5])}: no such "
                                             f"object in the store (GET /v1/objects lists them)")
    return [n for n in stored if n in asked]


def _locate_all(state: ServiceState, data: bytes, camera: CameraIn, names: list[str]) -> dict:
    """Worker thread: decode, check the camera, search every loadable model of ``names`` (:func:`_chosen`)."""
    t0 = time.perf_counter()
    image, cam = decode_with_camera(state, data, camera)
    models, failed = [], {}
    for name in names:
        try:
            models.append(state.registry.get(name)[0])
        except ApiError as exc:  # a broken model: the others are still searched
            failed[name] = exc.message
        except Exception as exc:  # noqa: BLE001 - a model that cannot be loaded is reported, not fatal
            failed[name] = state.registry.public(str(exc))
    if not models:  # (every model broken: nothing was searched, which is no "not found")
        raise ApiError(503, "model_unavailable", "no object can be searched: " + "; ".join(
            f"{n}: {why}" for n, why in failed.items()))
    try:
        results = locate_all(image, cam, models, LocateParams(max_pixels=state.settings.locate_max_pixels))
    except ImageError as exc:
        raise ApiError(422, "bad_image", str(exc)) from None
    for r in results:
        state.metrics.observe_stages(state.metrics.locate_stages, r.time_ms)
    found = [r.to_json() for r in results if r.found]
    return {"found": bool(found), "objects": found, "searched": [m.name for m in models],
            "not_found": not_found(results), "failed": failed,
            "time_ms": {"total": round((time.perf_counter() - t0) * 1e3, 3)}}
