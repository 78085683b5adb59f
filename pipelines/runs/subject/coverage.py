"""Surfaces the training views saw (docs/model.md §7, *Surfaces the training views saw*): which faces of the body
model some training view shows inside the person's mask, facing it within 60 degrees, and which pixels of an
evaluated view show a face that none of them did. A held-out camera that sees the person's back, which no training
camera faced, is scored there on colour the fit could only guess; the error breakdown reports those pixels apart."""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from pipelines.datasets.camera import Camera, face_ids
from pipelines.datasets.capture import ZjuCapture

#: a face counts as seen by a view that shows it within 60 degrees of face-on (cosine 0.5): further round, its image
#: is foreshortened more than twice and lies near the outline, where the mask's edge and its band blur its colour
FACE_ON_COS = 0.5


def shown_faces(ids: np.ndarray, where: np.ndarray, n_faces: int) -> np.ndarray:
    """(F,) bool: the faces that ``ids`` (H, W) int, -1 for none (``face_ids``), shows at a pixel of ``where``
    (H, W) bool."""
    shown = np.zeros(n_faces, bool)
    values = ids[where]
    shown[values[values >= 0]] = True
    return shown


def facing_faces(camera: Camera, vertices: np.ndarray, faces: np.ndarray, min_cos: float) -> np.ndarray:
    """(F,) bool: the faces whose outward normal (counter-clockwise order, as SMPL's) makes an angle with the
    direction from their centroid to ``camera``'s centre whose cosine is ``min_cos`` or more."""
    corners = vertices[faces].astype(np.float64)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    to_camera = camera.centre - corners.mean(axis=1)
    lengths = np.linalg.norm(normal, axis=1) * np.linalg.norm(to_camera, axis=1)
    return (normal * to_camera).sum(axis=1) >= min_cos * np.maximum(lengths, 1e-300)


def grown(faces: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(F,) bool: the faces ``seen`` (F,) bool marks and every face that shares a vertex with one of them. At the
    resolution of an evaluated image a face of a few millimetres can fall between pixel centres in every view; its
    neighbours' colour is what the fit learnt for it."""
    vertices = np.zeros(int(faces.max()) + 1, bool)
    vertices[faces[seen].reshape(-1)] = True
    return vertices[faces].any(axis=1)


def training_coverage(
    capture: ZjuCapture, views: list[tuple[int, int]], faces: np.ndarray, progress: bool = False
) -> np.ndarray:
    """(F,) int32: in how many of ``views`` ((frame, camera) pairs, the run's training views) each face of the
    frame's body (``capture.vertices``) is the nearest surface at a pixel of the person's mask, in the image as the
    fit loads it (undistorted, at the capture's ratio), and faces the camera within ``FACE_ON_COS``."""
    counts = np.zeros(len(faces), np.int32)
    for frame, cam in tqdm(views, desc="surfaces the training views saw", unit="view", disable=not progress):
        item = capture.load_frame(frame, cam)
        vertices = capture.vertices(frame)
        ids = face_ids(item.camera, vertices, faces)
        seen = shown_faces(ids, item.mask >= 0.5, len(faces)) & facing_faces(item.camera, vertices, faces, FACE_ON_COS)
        counts += seen
    return counts


def unseen_pixels(camera: Camera, vertices: np.ndarray, faces: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of ``camera`` whose nearest surface of the body ``vertices`` (V, 3) is a face that no
    training view showed (``counts`` (F,) from :func:`training_coverage`, after :func:`grown`); pixels off the body
    are False."""
    ids = face_ids(camera, vertices, faces)
    unseen = ~grown(faces, counts > 0)
    return (ids >= 0) & unseen[np.maximum(ids, 0)]
