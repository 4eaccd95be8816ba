"""Viewsets (Kragic & Kyrki, Sec. 2): the SIFT keypoints of one view of the object, each with
its 3-D point on the model, so that matching a query to a viewset gives 2-D/3-D pairs for PnP."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from quatrack.tracking.camera import PinholeCamera

from .features import RUN_TIME_STRETCH, extract_features
from .mesh import Mesh
from .render import RenderBuffers, lift_keypoints
from quatrack.tracking.pose import Pose


@dataclass(frozen=True)
class ViewsetParams:
    """SIFT and lifting parameters; stored in the manifest so queries use the same ones."""

    max_features: int = 1500
    erode_px: int = 4
    root_sift: bool = False
    contrast_threshold: float = 0.04
    min_cos: float = 0.2
    edge_margin_px: int = 3


@dataclass(frozen=True)
class Viewset:
    """One view's model points. ``keypoints`` (n, 2) px in that view, ``descriptors`` (n, 128)
    float32, ``points3d`` (n, 3) in mesh units (object frame); ``pose`` is object → camera of the
    view; ``bbox`` = (x, y, w, h) of the object's silhouette in the view, pixels.

    ``learned``: the view was learned while tracking a video (:mod:`quatrack.viewsets.learn`),
    not trained from a registered photo; its 3-D points were lifted at the tracked pose.
    ``cooccurrence``: a learned view's RFCH label co-occurrence counts (normalised), folded into
    the model's RFCH histogram when the view joins the model; never stored (None once it has).
    ``relayed``: a learned view lifted at a frame that too few points of the model's own views
    anchored (the track carried itself there): it inherits the track's drift, so a tracker
    measures its points but lets them anchor no frame, and a re-finding on it is second-hand
    (``TrackerParams.relayed_views_anchor``)."""

    label: str
    source_view: int
    synthetic: bool
    camera: PinholeCamera
    pose: Pose
    keypoints: np.ndarray
    descriptors: np.ndarray
    points3d: np.ndarray
    bbox: tuple[int, int, int, int]
    learned: bool = False
    cooccurrence: np.ndarray | None = None
    relayed: bool = False

    def __len__(self) -> int:
        return len(self.keypoints)

    def uncropped(self, camera: PinholeCamera, x0: int, y0: int) -> "Viewset":
        """This viewset, built on a crop whose top-left corner is pixel ``(x0, y0)`` of ``camera``'s
        image (:meth:`PinholeCamera.cropped`), in that whole image: keypoints and box shifted by
        the corner, the camera the whole image's. The 3-D points are the same: so are the rays."""
        bx, by, bw, bh = self.bbox
        return replace(self, camera=camera, keypoints=(self.keypoints + np.array([x0, y0], np.float32)).astype(np.float32),
                       bbox=(bx + x0, by + y0, bw, bh))


def silhouette_bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(x, y, w, h) of the non-zero pixels; zeros if there are none."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return (0, 0, 0, 0)
    return (int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1))


def build_viewset(
    label: str,
    source_view: int,
    synthetic: bool,
    image: np.ndarray,
    feature_mask: np.ndarray,
    camera: PinholeCamera,
    pose: Pose,
    mesh: Mesh,
    buffers: RenderBuffers,
    params: ViewsetParams,
    stretch_to: float | None = None,
) -> Viewset:
    """Extract SIFT inside ``feature_mask`` and keep the keypoints whose rays hit the mesh well.
    ``stretch_to``: as :func:`~.features.extract_features` (views made at run time)."""
    feats = extract_features(
        image, feature_mask, max_features=params.max_features, erode_px=params.erode_px,
        use_root_sift=params.root_sift, contrast_threshold=params.contrast_threshold, stretch_to=stretch_to,
    )
    X, keep = lift_keypoints(mesh, camera, pose, feats.keypoints, params.min_cos, buffers, params.edge_margin_px)
    return Viewset(
        label, source_view, synthetic, camera, pose,
        feats.keypoints[keep].astype(np.float32), feats.descriptors[keep].astype(np.float32),
        X[keep], silhouette_bbox(buffers.face >= 0),
    )


def params_from_manifest(manifest: dict) -> ViewsetParams:
    """The SIFT parameters a model was trained with (so a query is described the same way)."""
    return ViewsetParams(**manifest["parameters"]["viewsets"])


def extract_query_features(image: np.ndarray, mask: np.ndarray | None, params: ViewsetParams):
    """SIFT on a query image as training did (no erosion: a query window is not a silhouette),
    a dim image brightened first (:data:`~.features.RUN_TIME_STRETCH`)."""
    return extract_features(image, mask, max_features=params.max_features, erode_px=0,
                            use_root_sift=params.root_sift, contrast_threshold=params.contrast_threshold,
                            stretch_to=RUN_TIME_STRETCH)
