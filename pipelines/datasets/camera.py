"""The camera every reader returns and every writer takes: an OpenCV pinhole camera (docs/formats.md §0, §1.3)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np


@dataclass(frozen=True)
class Camera:
    """An OpenCV pinhole camera. ``x_cam = R x_world + t`` with t in metres; pixel centres at integers.

    Attributes:
        name: camera folder name, e.g. ``Camera_B1``.
        K: (3, 3) intrinsics.
        dist: (5,) k1, k2, p1, p2, k3.
        cam_from_world: (4, 4) extrinsics, metres.
        width, height: image size in pixels.
    """

    name: str
    K: np.ndarray
    dist: np.ndarray
    cam_from_world: np.ndarray
    width: int
    height: int

    @property
    def centre(self) -> np.ndarray:
        """Camera centre in world coordinates, ``-R^T t``."""
        return -self.cam_from_world[:3, :3].T @ self.cam_from_world[:3, 3]

    def scaled(self, ratio: float) -> Camera:
        """The camera of the image resized by ``ratio`` to ``round(width * ratio)`` x ``round(height * ratio)``, as
        ``cv2.resize`` resamples it: with pixel centres at integers, pixel u' of the new image is centred on
        u = (u' + 0.5) / s - 0.5 of the old one (s the size's own ratio per axis), so the first two rows of K are
        scaled by s and the principal point becomes (c + 0.5) s - 0.5 (docs/formats.md §0). Scaling the principal
        point like the focal length instead would put every ray (1 / s - 1) / 2 old pixels up and left of its
        pixel's centre: a quarter of a new pixel at half size."""
        width, height = int(round(self.width * ratio)), int(round(self.height * ratio))
        scale = np.array([width / self.width, height / self.height])
        K = self.K.copy()
        K[:2] *= scale[:, None]
        K[:2, 2] = (self.K[:2, 2] + 0.5) * scale - 0.5
        return replace(self, K=K, width=width, height=height)

    def undistorted(self) -> Camera:
        return replace(self, dist=np.zeros(5))


def resized_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W) mask -> (h, w) bool at ``size`` (w, h), each pixel averaging the area of the original that the image's
    pixel averages under ``cv2.resize(..., INTER_AREA)`` (so centred where :meth:`Camera.scaled`'s rays go; docs/
    formats.md §0) and kept where more than half of it is covered. A pixel exactly half covered (an edge through its
    middle, common at a whole ratio) is kept on the squares of one colour of a checkerboard, so that neither side of
    an edge gains: as many pixels as the nearest pixel's value keeps, without its shift up and left."""
    covered = cv2.resize(np.asarray(mask, np.float32), size, interpolation=cv2.INTER_AREA)
    rows, cols = np.indices(covered.shape)
    return (covered > 0.5) | ((covered == 0.5) & ((rows + cols) % 2 == 0))


def project_distorted(camera: Camera, points: np.ndarray) -> np.ndarray:
    """(N, 3) world points -> (N, 2) pixels of the camera with its distortion (OpenCV model)."""
    rvec, _ = cv2.Rodrigues(camera.cam_from_world[:3, :3])
    pixels, _ = cv2.projectPoints(
        np.ascontiguousarray(points, np.float64), rvec, camera.cam_from_world[:3, 3], camera.K, camera.dist
    )
    return pixels[:, 0]


def silhouette(camera: Camera, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels covered by the mesh's projected triangles (triangles behind the camera skipped): those
    :func:`face_ids` gives a face."""
    return face_ids(camera, vertices, faces) >= 0


def face_ids(camera: Camera, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(H, W) int32: the index of the mesh face each pixel shows, -1 where none (docs/model.md §7, *Surfaces the
    training views saw*).

    The faces are drawn far to near by the depth of their centroids (the painter's rule), each over the pixels its
    projected triangle covers (one call a triangle: fillPoly's even-odd rule would cancel overlaps), so a nearer
    face overwrites the faces behind it; for a closed body mesh of small
    triangles this agrees with a depth test except along the edges where two faces meet. Faces with a vertex
    behind the camera are skipped.
    """
    depth = vertices @ camera.cam_from_world[2, :3] + camera.cam_from_world[2, 3]
    pixels = project_distorted(camera, vertices)
    inside = np.isfinite(pixels).all(-1) & (np.abs(pixels) < 1e5).all(-1)
    drawn = np.nonzero((depth[faces] > 1e-3).all(axis=1) & inside[faces].all(axis=1))[0]
    drawn = drawn[np.argsort(-depth[faces[drawn]].mean(axis=1), kind="stable")]
    image = np.full((camera.height, camera.width), -1, np.int32)
    polygons = np.round(pixels[faces[drawn]] * 4).astype(np.int32)  # 2 bits of sub-pixel precision
    for index, polygon in zip(drawn.tolist(), polygons):
        cv2.fillConvexPoly(image, polygon, index, lineType=cv2.LINE_8, shift=2)
    return image
