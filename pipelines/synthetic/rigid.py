"""A rigid-object set for the supplement's Table B (RT-NeRF vs RT-NeRF w/o xi vs RP-NeRF; supplement §B, which
uses a bulldozer): a procedural, textured, vehicle-like mesh of several parts (chassis, cabin with windows, blade
on an arm, four wheels, an exhaust on one side, so that no view is a mirror of another), and per image a random
rigid transform of the object and a random camera aimed at its centre, 200 x 200, 480 train / 20 test.

Written in NARF's render layout (``docs/formats.md §8``): ``<split>/render_200/color/color_%08d.png`` (BGRA,
alpha = mask), ``pose_to_world_%08d.npy`` and ``pose_to_camera_%08d.npy`` (1, 4, 4) (the object frame in the
world and in the camera), ``<split>/render_200/K.npy`` (3, 3), and ``object.ply`` (the true mesh, object frame).
``synthetic.json`` is written last, into a staging folder that is renamed when complete.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import trimesh
from tqdm import tqdm

from fitting.files import write_image, write_npy, writes_folder
from pipelines.synthetic.people import pixel_rays
from pipelines.synthetic.settings import RigidSynthConfig  # noqa: F401 (re-exported)
from pipelines.synthetic.staging import is_finished, publish, start_staging

RIGID_VERSION = 1
#: World lights (direction towards the light, intensity): fixed in the world, so shading changes with the object's
#: pose, which is what RT-NeRF's xi in the colour branch can model (paper Eq. 11).
LIGHTS = [(np.array([0.3, -0.8, -0.5]), 0.6), (np.array([-0.6, -0.2, -0.7]), 0.3)]


def _stripes(points: np.ndarray, axis: np.ndarray, period: float, a, b) -> np.ndarray:
    phase = (points @ np.asarray(axis) / period) % 1.0
    return np.where((phase < 0.5)[:, None], np.asarray(a, float), np.asarray(b, float))


def _checker(points: np.ndarray, size: float, a, b) -> np.ndarray:
    cells = np.floor(points / size).astype(int).sum(axis=1) % 2
    return np.where((cells == 0)[:, None], np.asarray(a, float), np.asarray(b, float))


def _placed(mesh: trimesh.Trimesh, translation, rotation=None) -> trimesh.Trimesh:
    transform = np.eye(4)
    if rotation is not None:
        transform[:3, :3] = cv2.Rodrigues(np.asarray(rotation, float))[0]
    transform[:3, 3] = translation
    return mesh.apply_transform(transform)


def _spokes(centre: np.ndarray):
    def texture(points: np.ndarray) -> np.ndarray:
        angle = np.arctan2(points[:, 1] - centre[1], points[:, 0] - centre[0])
        return np.where((np.cos(6 * angle) > 0.3)[:, None], [0.6, 0.6, 0.6], [0.08, 0.08, 0.08])

    return texture


@dataclass
class Vehicle:
    """The object in its own frame (x forward, y down, z to the right; about 1.45 x 0.95 x 1.0, centred): a
    low-polygon mesh whose colour is a procedural texture per part, evaluated at the hit point (sharp at any
    resolution). ``faces_part`` (F,) gives each triangle's part, ``textures[k]`` maps (N, 3) object-frame points of
    part k to colours (N, 3) in [0, 1]."""

    mesh: trimesh.Trimesh
    faces_part: np.ndarray
    textures: list


def vehicle() -> Vehicle:
    """Chassis (diagonal stripes), cabin (window checker, set back and to the left), blade (ribs) on an arm, an
    exhaust (red and white bands) on the right, four spoked wheels."""
    parts = [
        (
            _placed(trimesh.creation.box([1.2, 0.3, 0.7]), [-0.05, 0.1, 0]),
            lambda p: _stripes(p, [1, 1, 0], 0.2, [0.95, 0.72, 0.1], [0.15, 0.12, 0.1]),
        ),
        (
            _placed(trimesh.creation.box([0.45, 0.4, 0.5]), [-0.3, -0.25, -0.08]),
            lambda p: _checker(p, 0.1, [0.3, 0.55, 0.85], [0.85, 0.85, 0.8]),
        ),
        (
            _placed(trimesh.creation.box([0.08, 0.35, 0.95]), [0.75, 0.1, 0]),
            lambda p: _stripes(p, [0, 0, 1], 0.12, [0.55, 0.55, 0.6], [0.3, 0.3, 0.35]),
        ),
        (
            _placed(trimesh.creation.box([0.3, 0.08, 0.12]), [0.6, -0.05, 0.25], [0, 0, 0.4]),
            lambda p: np.tile([0.9, 0.4, 0.1], (len(p), 1)),
        ),
        (
            _placed(
                trimesh.creation.cylinder(radius=0.04, height=0.35, sections=12), [-0.45, -0.2, 0.25], [np.pi / 2, 0, 0]
            ),
            lambda p: _stripes(p, [0, 1, 0], 0.08, [0.8, 0.1, 0.1], [0.95, 0.95, 0.95]),
        ),
    ]
    for x, z in [(-0.45, -0.42), (-0.45, 0.42), (0.35, -0.42), (0.35, 0.42)]:
        centre = np.array([x, 0.3, z])
        wheel = trimesh.creation.cylinder(radius=0.2, height=0.14, sections=24)  # its axis is z, the object's side
        parts.append((_placed(wheel, centre), _spokes(centre)))
    mesh = trimesh.util.concatenate([m for m, _ in parts])
    faces_part = np.concatenate([np.full(len(m.faces), k) for k, (m, _) in enumerate(parts)])
    return Vehicle(mesh, faces_part, [t for _, t in parts])


def render_vehicle(obj: Vehicle, world_from_object: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray, size: int):
    """RGB (H, W, 3) on black and alpha (H, W), Lambertian under ``LIGHTS`` with flat face normals, 2 x 2 rays per
    pixel averaged (``people.pixel_rays``)."""
    origins, dirs = pixel_rays(K, cam_from_world, size, size, supersample=2)
    object_from_world = np.linalg.inv(world_from_object)
    origins_obj = origins @ object_from_world[:3, :3].T + object_from_world[:3, 3]
    dirs_obj = dirs @ object_from_world[:3, :3].T
    tri, ray, loc = obj.mesh.ray.intersects_id(origins_obj, dirs_obj, multiple_hits=False, return_locations=True)
    rgb, alpha = np.zeros((len(dirs), 3)), np.zeros(len(dirs))
    if len(ray):
        albedo = np.zeros((len(ray), 3))
        for k, texture in enumerate(obj.textures):
            hit = obj.faces_part[tri] == k
            albedo[hit] = texture(loc[hit])
        normals = obj.mesh.face_normals[tri] @ world_from_object[:3, :3].T
        light = np.full(len(ray), 0.3)
        for direction, intensity in LIGHTS:
            light += intensity * np.clip(normals @ (direction / np.linalg.norm(direction)), 0, None)
        rgb[ray], alpha[ray] = np.clip(albedo * light[:, None], 0, 1), 1.0
    shape = (size, 2, size, 2)
    return rgb.reshape(*shape, 3).mean(axis=(1, 3)), alpha.reshape(shape).mean(axis=(1, 3))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation drawn uniformly from SO(3) (a normalised Gaussian quaternion)."""
    q = rng.normal(size=4)
    return trimesh.transformations.quaternion_matrix(q / np.linalg.norm(q))[:3, :3]


def aimed_camera(rng: np.random.Generator, target: np.ndarray, distance: float) -> np.ndarray:
    """(4, 4) cam_from_world of a camera on a random direction at ``distance`` from ``target``, looking at it, with
    a random roll."""
    forward = rng.normal(size=3)
    forward /= np.linalg.norm(forward)
    side = np.cross(forward, rng.normal(size=3))
    side /= np.linalg.norm(side)
    rotation = np.stack([side, np.cross(forward, side), forward])  # rows: camera x, y, z in world coordinates
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = -rotation @ (target - forward * distance)
    return out


def rigid_K(resolution: int) -> np.ndarray:
    """Intrinsics that frame the object (radius about 1.1) from 3.2 units away: f = 1.45 * resolution."""
    c = (resolution - 1) / 2
    return np.array([[1.45 * resolution, 0, c], [0, 1.45 * resolution, c], [0, 0, 1.0]])


def is_rigid_complete(out: Path, config: RigidSynthConfig | None = None) -> bool:
    """True when ``out`` holds a finished rigid-object set (with these settings, if ``config`` is given)."""
    return is_finished(out, "rigid", config, RIGID_VERSION)


@writes_folder()
def generate_rigid(out: str | Path, config: RigidSynthConfig = RigidSynthConfig(), progress: bool = True) -> Path:
    """Generate (or reuse) the rigid-object set at ``out`` (module docstring)."""
    config.validate()
    out = Path(out)
    if is_rigid_complete(out, config):
        return out
    partial = start_staging(out, "rigid", "rigid-object set")
    obj = vehicle()
    obj.mesh.export(partial / "object.ply")
    K = rigid_K(config.resolution)
    for split, count in (("train", config.train), ("test", config.test)):
        folder = partial / split / f"render_{config.resolution}" / "color"
        folder.mkdir(parents=True)
        write_npy(folder.parent / "K.npy", K)
        rng = np.random.default_rng([config.seed, split == "test"])
        for index in tqdm(range(count), desc=f"rigid {split}", unit="image", disable=not progress):
            world_from_object = np.eye(4)
            world_from_object[:3, :3] = random_rotation(rng)
            world_from_object[:3, 3] = rng.uniform(-0.2, 0.2, 3)
            cam_from_world = aimed_camera(rng, world_from_object[:3, 3], rng.uniform(3.0, 3.4))
            rgb, alpha = render_vehicle(obj, world_from_object, K, cam_from_world, config.resolution)
            rgba = np.concatenate([rgb, alpha[..., None]], axis=-1)
            write_image(folder / f"color_{index:08d}.png", np.uint8(rgba * 255 + 0.5)[..., [2, 1, 0, 3]])
            write_npy(folder / f"pose_to_world_{index:08d}.npy", world_from_object[None])
            write_npy(folder / f"pose_to_camera_{index:08d}.npy", (cam_from_world @ world_from_object)[None])
    marker = {"dataset": "rigid", "version": RIGID_VERSION, "config": asdict(config), "object_radius": 1.1}
    return publish(partial, out, marker)
