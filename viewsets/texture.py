"""The object's texture as trusted views saw it: what the model keeps of its training photos.

SIFT keypoints describe a photo at a few hundred points; a wrong pose can gather a consensus of
them where faces share texture. The photo's pixels over the whole object are evidence it cannot
fake (:func:`quatrack.recognition.appearance.texture_agreement`), so training keeps each
registered photo's crop of the object, grey, with its camera, pose and mask.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.pose import Pose

from .mesh import Mesh
from .render import RenderBuffers, render


@dataclass(frozen=True)
class TextureReference:
    """A trusted view of the object: ``image`` (grey or BGR) seen by ``camera`` (any crop's camera,
    :meth:`PinholeCamera.cropped`) at ``pose`` (object → camera); ``mask`` (same size, non-zero:
    the object is seen there, not covered; None: wherever the mesh is) — a training photo's or a
    keyframe's crop. ``buffers``: its z-buffer at ``pose`` (rendered when None; keep it to render
    a reference more than once)."""

    image: np.ndarray
    camera: PinholeCamera
    pose: Pose
    mask: np.ndarray | None = None
    buffers: RenderBuffers | None = None

    def rendered(self, mesh: Mesh) -> "TextureReference":
        """This reference with its z-buffer."""
        if self.buffers is not None:
            return self
        return replace(self, buffers=render(mesh, self.camera, self.pose))


def crop_reference(image: np.ndarray, camera: PinholeCamera, pose: Pose, mask: np.ndarray,
                   margin_px: int = 8) -> TextureReference | None:
    """The reference of a photo: its grey crop round ``mask`` (non-zero: the object, seen) grown
    by ``margin_px``, with the crop's camera and mask; None when the mask is empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None
    h, w = mask.shape
    x0, y0 = max(int(xs.min()) - margin_px, 0), max(int(ys.min()) - margin_px, 0)
    x1, y1 = min(int(xs.max()) + 1 + margin_px, w), min(int(ys.max()) + 1 + margin_px, h)
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    return TextureReference(np.ascontiguousarray(grey[y0:y1, x0:x1]), camera.cropped(x0, y0, x1, y1), pose,
                            np.where(mask[y0:y1, x0:x1] > 0, 255, 0).astype(np.uint8))
