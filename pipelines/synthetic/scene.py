"""Scene of the synthetic capture: camera rig, taichi-like motion, garments and lights.

World frame as ZJU-MoCap (docs/formats.md §1.4): z points down, the floor is z = 0, cameras stand on a ring of
about 3 m at z about -1.9 and aim at (0, 0, -0.9). Everything is deterministic under the seed.
"""

from __future__ import annotations

import cv2
import numpy as np

from pipelines.datasets.camera import Camera

#: SMPL rest frame (y up, z forward) -> world (z down): x -> x, y -> -z, z -> +y.
WORLD_FROM_SMPL_BASE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
#: CIHP labels used by the generator.
LABEL = {
    "hair": 2,
    "upper_clothes": 5,
    "pants": 9,
    "torso_skin": 10,
    "face": 13,
    "left_arm": 14,
    "right_arm": 15,
    "left_shoe": 18,
    "right_shoe": 19,
}


def look_at(centre: np.ndarray, target: np.ndarray, down: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """(4, 4) ``cam_from_world`` of an OpenCV camera at ``centre`` looking at ``target``, image-down ~ ``down``."""
    down = np.asarray(down, dtype=float)
    forward = target - centre
    forward /= np.linalg.norm(forward)
    y_axis = down - forward * (down @ forward)
    y_axis /= np.linalg.norm(y_axis)
    x_axis = np.cross(y_axis, forward)
    rotation = np.stack([x_axis, y_axis, forward])
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = -rotation @ centre
    return out


def ring_cameras(n_cameras: int, resolution: int, seed: int, radius: float = 3.0) -> list[Camera]:
    """A CoreView-like ring: ``Camera_B1..`` evenly around the subject with small jitter and mild distortion.

    The focal length scales with resolution (about 1100 px at 1024^2, as ZJU-MoCap).
    """
    rng = np.random.default_rng(seed)
    scale = resolution / 1024.0
    cameras = []
    for c in range(n_cameras):
        angle = 2 * np.pi * c / n_cameras + rng.uniform(-0.04, 0.04)
        rad = radius + rng.uniform(-0.15, 0.15)
        centre = np.array([rad * np.sin(angle), -rad * np.cos(angle), -1.9 + rng.uniform(-0.08, 0.08)])
        target = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), -0.9 + rng.uniform(-0.05, 0.05)])
        focal = (1100 + rng.uniform(-40, 40)) * scale
        K = np.array(
            [
                [focal, 0, resolution / 2 + rng.uniform(-12, 12) * scale],
                [0, focal * (1 + rng.uniform(-0.002, 0.002)), resolution / 2 + rng.uniform(-12, 12) * scale],
                [0, 0, 1],
            ]
        )
        dist = np.array(
            [
                rng.uniform(-0.08, 0.02),
                rng.uniform(-0.02, 0.05),
                rng.uniform(-5e-4, 5e-4),
                rng.uniform(-5e-4, 5e-4),
                0.0,
            ]
        )
        cameras.append(Camera(f"Camera_B{c + 1}", K, dist, look_at(centre, target), resolution, resolution))
    return cameras


def taichi_motion(n_frames: int, seed: int) -> dict[str, np.ndarray]:
    """A slow, smooth taichi-like sequence: ZJU parameters per frame (poses, Rh, Th before floor contact).

    Arms rise and circle, knees sink and rise, weight shifts side to side, the torso turns, and the body slowly
    turns about the vertical. Returns ``poses`` (F, 72), ``Rh`` (F, 3), ``Th`` (F, 3), ``shapes`` (F, 10).
    """
    rng = np.random.default_rng(seed + 1)
    t = np.arange(n_frames) / 30.0  # seconds at 30 fps
    phase = rng.uniform(0, 2 * np.pi, size=8)
    w = 2 * np.pi / np.array([7.0, 5.0, 9.0, 11.0, 6.0, 13.0, 8.0, 17.0])
    s = [np.sin(w[k] * t + phase[k]) for k in range(8)]
    poses = np.zeros((n_frames, 24, 3))
    sink = 0.5 + 0.5 * s[0]  # 0..1 knee bend
    for hip, knee, ankle, sign in ((1, 4, 7, 1), (2, 5, 8, -1)):
        shift = 0.5 + 0.5 * sign * s[2]
        poses[:, hip, 0] = -(0.15 + 0.45 * sink) * (0.7 + 0.6 * shift)
        poses[:, hip, 2] = sign * (0.12 + 0.06 * s[2])
        poses[:, knee, 0] = (0.25 + 0.8 * sink) * (0.7 + 0.6 * shift)
        poses[:, ankle, 0] = -(0.1 + 0.35 * sink) * (0.7 + 0.6 * shift)
    raise_ = 0.5 + 0.5 * s[1]
    for shoulder, elbow, wrist, collar, sign in ((16, 18, 20, 13, 1), (17, 19, 21, 14, -1)):
        circle = s[4] if sign > 0 else np.sin(w[4] * t + phase[4] + 1.2)
        poses[:, shoulder, 2] = -sign * (1.25 - 1.0 * raise_ + 0.15 * circle)
        poses[:, shoulder, 1] = -sign * (0.3 + 0.5 * raise_ + 0.25 * s[5])
        poses[:, elbow, 1] = sign * (0.5 + 0.6 * (0.5 + 0.5 * circle))
        poses[:, wrist, 2] = -sign * 0.3 * s[6]
        poses[:, collar, 2] = -sign * 0.08 * raise_
    poses[:, 3, 1] = 0.25 * s[3]
    poses[:, 6, 1] = 0.15 * s[3]
    poses[:, 9, 0] = 0.05 * s[0]
    poses[:, 12, 1] = 0.2 * s[5]
    poses[:, 15, 0] = 0.1 * s[6]
    poses[:, 15, 1] = 0.25 * s[5]
    yaw = 0.6 * s[7] + 2 * np.pi * t / (n_frames / 30.0) * 0.5  # half a turn over the sequence
    rh = np.zeros((n_frames, 3))
    import cv2

    for f in range(n_frames):
        turn = cv2.Rodrigues(np.array([0.0, 0.0, yaw[f]]))[0]
        rh[f] = cv2.Rodrigues(turn @ WORLD_FROM_SMPL_BASE)[0].ravel()
    th = np.stack([0.08 * s[2], 0.05 * s[3], np.zeros(n_frames)], axis=1)
    shapes = np.tile(np.array([0.4, -0.3, 0.5, 0.2, 0.3, -0.2, 0.1, 0.0, -0.3, 0.2]), (n_frames, 1))
    return {"poses": poses.reshape(n_frames, 72), "Rh": rh, "Th": th, "shapes": shapes}


def vertex_regions(rest_vertices: np.ndarray, skinning_weights: np.ndarray) -> np.ndarray:
    """CIHP label of every vertex from its dominant joint and rest position (works for any SMPL-format body)."""
    joint = skinning_weights.argmax(axis=1)
    y, z = rest_vertices[:, 1], rest_vertices[:, 2]
    x_abs = np.abs(rest_vertices[:, 0])
    left = rest_vertices[:, 0] > 0
    labels = np.full(len(joint), LABEL["upper_clothes"], np.uint8)
    head_top = y.max()
    labels[np.isin(joint, (1, 2, 4, 5)) | (np.isin(joint, (0, 3)) & (y < -0.17))] = LABEL["pants"]
    labels[np.isin(joint, (7, 8, 10, 11))] = np.where(left, LABEL["left_shoe"], LABEL["right_shoe"])[
        np.isin(joint, (7, 8, 10, 11))
    ]
    labels[joint == 12] = LABEL["torso_skin"]
    head = joint == 15
    hair = head & ((y > head_top - 0.09) | ((z < 0.02) & (y > head_top - 0.22)))
    labels[head] = LABEL["face"]
    labels[hair] = LABEL["hair"]
    bare_arm = (np.isin(joint, (16, 17)) & (x_abs > 0.3)) | np.isin(joint, (18, 19, 20, 21, 22, 23))
    labels[bare_arm] = np.where(left, LABEL["left_arm"], LABEL["right_arm"])[bare_arm]
    return labels


_SKIN = np.array([0.87, 0.68, 0.55])


def albedo(rest_points: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Procedural albedo (N, 3) in [0, 1] of points given in the rest (T-pose) frame: striped shirt with a chest
    print, twill trousers, white shoes with a stripe, skin, hair, and a face with eyes, brows and mouth."""
    x, y, z = rest_points[:, 0], rest_points[:, 1], rest_points[:, 2]
    out = np.tile(_SKIN, (len(labels), 1))
    shirt = labels == LABEL["upper_clothes"]
    stripes = (np.floor((y + 0.5) / 0.045) % 2 == 0)[:, None]
    shirt_col = np.where(stripes, [0.80, 0.22, 0.18], [0.95, 0.92, 0.85])
    star = (np.hypot(x - 0.0, y - 0.13) < 0.06) & (z > 0.05)
    ring = (np.abs(np.hypot(x, y - 0.13) - 0.085) < 0.012) & (z > 0.05)
    shirt_col[star] = [0.15, 0.35, 0.80]
    shirt_col[ring] = [0.98, 0.80, 0.10]
    out[shirt] = shirt_col[shirt]
    pants = labels == LABEL["pants"]
    twill = (np.floor((y + 2 * x + 2) / 0.02) % 2)[:, None]
    out[pants] = (np.array([0.12, 0.16, 0.32]) + 0.06 * twill)[pants]
    shoes = np.isin(labels, (LABEL["left_shoe"], LABEL["right_shoe"]))
    shoe_stripe = (np.abs(y + 1.12) < 0.012)[:, None]
    out[shoes] = np.where(shoe_stripe, [0.1, 0.6, 0.3], [0.92, 0.92, 0.9])[shoes]
    out[labels == LABEL["hair"]] = [0.18, 0.11, 0.06]
    face = labels == LABEL["face"]
    eyes = face & (np.hypot(np.abs(x) - 0.035, y - 0.46) < 0.013) & (z > 0.05)
    brows = face & (np.abs(np.abs(x) - 0.037) < 0.02) & (np.abs(y - 0.485) < 0.005) & (z > 0.05)
    mouth = face & (np.abs(x) < 0.025) & (np.abs(y - 0.395) < 0.007) & (z > 0.05)
    out[eyes | brows] = [0.08, 0.06, 0.05]
    out[mouth] = [0.70, 0.25, 0.25]
    return out


#: Fixed world lights (direction towards the light, intensity); z is down, so "above" is -z.
LIGHTS = ((np.array([0.4, -0.6, -0.7]), 0.75), (np.array([-0.7, 0.5, -0.3]), 0.35))
AMBIENT = 0.25


def facing_normals(bary: np.ndarray, corner_normals: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Shading normals at ray hits: the hit triangle's vertex normals blended with the barycentric weights, unit
    length, turned to face the incoming ray (so the inside of a thin part is lit like its outside).

    Args:
        bary: (N, 3) barycentric weights of the hits.
        corner_normals: (N, 3, 3) the vertex normals of each hit triangle's corners.
        dirs: (N, 3) ray directions.

    Returns:
        (N, 3) unit normals with n . d <= 0.
    """
    normals = np.einsum("nk,nkd->nd", bary, corner_normals)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-9)
    normals[np.einsum("nd,nd->n", normals, dirs) > 0] *= -1
    return normals


def shade(albedo_rgb: np.ndarray, normals_world: np.ndarray) -> np.ndarray:
    """Lambertian shading under the fixed world lights: (N, 3) albedo, (N, 3) unit normals -> (N, 3) RGB."""
    light = np.full(len(normals_world), AMBIENT)
    for direction, intensity in LIGHTS:
        light += intensity * np.clip(normals_world @ (direction / np.linalg.norm(direction)), 0, None)
    return np.clip(albedo_rgb * light[:, None], 0, 1)


def studio_background(camera: Camera, pixel_dirs_world: np.ndarray) -> np.ndarray:
    """(H, W, 3) static background: a checkered grey floor (z = 0) and a graded wall, per camera."""
    dirs = pixel_dirs_world.reshape(-1, 3)
    centre = camera.centre
    t_floor = np.where(dirs[:, 2] > 1e-6, -centre[2] / np.maximum(dirs[:, 2], 1e-6), np.inf)
    hit = centre + np.where(np.isfinite(t_floor), t_floor, 0.0)[:, None] * dirs
    on_floor = np.isfinite(t_floor) & (np.hypot(hit[:, 0], hit[:, 1]) < 6)
    checker = (np.floor(hit[:, 0] / 0.5) + np.floor(hit[:, 1] / 0.5)) % 2
    wall = 0.35 + 0.25 * (-dirs[:, 2]).clip(-1, 1)
    colour = np.tile(wall[:, None], (1, 3)) * np.array([0.9, 0.95, 1.0])
    colour[on_floor] = (0.45 + 0.12 * checker[on_floor])[:, None] * np.array([0.85, 0.8, 0.7])
    return colour.reshape(camera.height, camera.width, 3)


def pixel_directions(camera: Camera) -> np.ndarray:
    """(H, W, 3) unit world directions of the rays through every (distorted) pixel centre."""
    ys, xs = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    pixels = np.stack([xs.ravel(), ys.ravel()], axis=1)[:, None]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
    normalised = cv2.undistortPoints(pixels, camera.K, camera.dist, None, None, None, criteria)[:, 0]
    dirs_cam = np.concatenate([normalised, np.ones((len(normalised), 1))], axis=1)
    dirs_world = dirs_cam @ camera.cam_from_world[:3, :3]
    dirs_world /= np.linalg.norm(dirs_world, axis=1, keepdims=True)
    return dirs_world.reshape(camera.height, camera.width, 3).astype(np.float32)
