"""The body stage of a prepare: the body fitted to the followed person's targets and masks in every camera
(:mod:`pipelines.prepare.body.fit`, the masks by :mod:`pipelines.prepare.body.masks`), or the user's bodies
polished, then the cameras the fit corrected and each camera's distance checked on the masks
(:mod:`pipelines.prepare.body.camera_depth`; docs/guides/real-captures.md, steps 5 and 6)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from pipelines.prepare.body.camera_depth import check_camera_depths
from pipelines.prepare.body.fit import fit_body, fit_steps, fitted_vertices
from pipelines.prepare.body.masks import silhouette_stage
from pipelines.prepare.request import PrepareRequest


def fit_bodies(staging: Path, seen, found, body, request: PrepareRequest):
    """``(seen, fitted, vertices)``: the body fitted in every frame of ``found`` (``request.smpl_params``' bodies
    polished by the silhouette stage alone where given), its (F, N, 3) vertices, and ``seen`` with the cameras the fit
    corrected and moved along their axes where the masks say so."""
    settings, start = request.fit, None
    if request.smpl_params is not None:  # the user's bodies, polished by the silhouette stage only
        start = brought_bodies(request.smpl_params, found.frames, request.person)
        settings = replace(settings, global_iterations=0, iterations=0)
    inputs = _fit_inputs(seen.cameras, found)
    steps = fit_steps(settings, len(found.frames), bool(settings.silhouette_iterations))
    masks = None
    if request.fit.silhouette_iterations:
        masks = silhouette_stage(staging, seen.cameras, found, body.faces, inputs[0])
    rig = (np.stack([c.K for c in seen.cameras]), np.stack([c.cam_from_world for c in seen.cameras]))
    with tqdm(total=steps, desc="fitting the body", disable=not request.progress) as bar:
        fitted = fit_body(body, *inputs, settings, lambda done, total: bar.update(1), masks, rig, start)
    vertices = fitted_vertices(body, fitted)
    if fitted.cam_from_world is not None:  # the capture's cameras are the corrected ones (docs/guides/real-captures.md)
        seen = corrected_cameras(seen, fitted.cam_from_world)
        seen = check_camera_depths(staging, seen, found, vertices, body.faces)
    return seen, fitted, vertices


def brought_bodies(folder: Path, frames: list[int], person: int | None):
    """``fit_body``'s ``start`` from the bodies of ``folder`` (``pipelines.datasets.smpl_params``) for source
    ``frames``: poses with their first three values folded into Rh (R(Rh) R(poses[:3]) is the body's turn), Th, and
    the frames' median shape (the capture keeps one shape)."""
    from pipelines.datasets.smpl_params import bodies_for_frames

    bodies = bodies_for_frames(folder, frames, person)
    poses = np.stack([b.poses for b in bodies]).astype(np.float64)
    turn = Rotation.from_rotvec(np.stack([b.rh for b in bodies])) * Rotation.from_rotvec(poses[:, :3])
    poses[:, :3] = 0
    shapes = np.median(np.stack([b.shapes for b in bodies]), axis=0)
    return poses, turn.as_rotvec(), np.stack([b.th for b in bodies]).astype(np.float64), shapes


def corrected_cameras(seen, cam_from_world: np.ndarray):
    """``seen`` with each camera's extrinsics replaced by the body fit's corrected (V, 3, 4) ones, and how far each
    moved (degrees, centimetres) in ``seen.corrections``."""
    cameras, corrections = [], {}
    for camera, corrected in zip(seen.cameras, cam_from_world):
        pose = np.eye(4)
        pose[:3] = corrected
        moved = replace(camera, cam_from_world=pose)
        turn = Rotation.from_matrix(pose[:3, :3] @ camera.cam_from_world[:3, :3].T).magnitude()
        corrections[camera.name] = (float(np.degrees(turn)), float(100 * np.linalg.norm(moved.centre - camera.centre)))
        cameras.append(moved)
    return replace(seen, cameras=cameras, corrections=corrections)


def _fit_inputs(cameras, found):
    from pipelines.prepare.people.multiview import projection_matrix

    P = np.stack([projection_matrix(c) for c in cameras])
    heights = np.array([c.height for c in cameras], np.float64)
    return P, heights, found.keypoints, found.points
