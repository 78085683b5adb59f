"""Many people from the stand-in body: shapes, skin, hair and clothing as vertex colours, random plausible poses,
and a ray caster that renders a vertex-coloured mesh through any pinhole camera (the THUman- and SURREAL-like
stand-ins, ``docs/formats.md §4``).

Clothing is painted on the body's vertices (short or long sleeves and legs, plain or striped tops, and for a share
of the people swimwear: a bare torso and trunks), like the vertex colours of a THUman scan; geometry stays the
body's own. Everything is deterministic under the caller's ``numpy.random.Generator``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import trimesh

from fitting.mesh import vertex_normals
from pipelines.synthetic.scene import LABEL, facing_normals, vertex_regions

_SKIN_TONES = np.array(
    [[0.95, 0.80, 0.69], [0.87, 0.68, 0.55], [0.72, 0.53, 0.40], [0.55, 0.38, 0.27], [0.36, 0.24, 0.17]]
)
SWIMWEAR_SHARE = 0.25  # clothed people drawn in swimwear (bare torso, trunks), so that skin-dominated looks are seen
_HAIR = np.array([[0.08, 0.06, 0.05], [0.25, 0.15, 0.08], [0.55, 0.38, 0.20], [0.80, 0.70, 0.45], [0.5, 0.5, 0.5]])


@dataclass(frozen=True)
class Person:
    """Shape and appearance of one synthetic person.

    Attributes:
        betas: (10,) SMPL shape. gender: ``female`` or ``male`` (names only; the stand-in body is neutral).
        skin, hair, top, bottom, shoes: (3,) RGB in [0, 1].
        sleeve: 0 sleeveless ... 1 long sleeves. legs: 0 shorts ... 1 long trousers. stripes: striped top.
        clothed: False paints skin and underwear only (SURREAL's bodies). bare_torso: no top (swimwear).
    """

    betas: np.ndarray
    gender: str
    skin: np.ndarray
    hair: np.ndarray
    top: np.ndarray
    bottom: np.ndarray
    shoes: np.ndarray
    sleeve: float
    legs: float
    stripes: bool
    clothed: bool = True
    bare_torso: bool = False


def random_person(rng: np.random.Generator, clothed: bool = True, beta_std: float = 1.0) -> Person:
    """A person with betas ~ N(0, beta_std^2) (clipped to +-2.5 std), and random colours and garment lengths.

    A clothed person is in swimwear (bare torso, short trunks) with probability ``SWIMWEAR_SHARE``; that draw comes
    last and only for clothed people, so unclothed (SURREAL-like) people are drawn as before it existed.
    """
    colour = lambda: np.clip(rng.uniform(0.05, 0.95, 3) ** 1.3, 0, 1)  # noqa: E731 - many saturated, some pale
    person = Person(
        betas=np.clip(rng.normal(0, beta_std, 10), -2.5 * beta_std, 2.5 * beta_std),
        gender=("female", "male")[int(rng.integers(2))],
        skin=_SKIN_TONES[rng.integers(len(_SKIN_TONES))] * rng.uniform(0.92, 1.05),
        hair=_HAIR[rng.integers(len(_HAIR))],
        top=colour(),
        bottom=colour() * 0.8,
        shoes=colour() * 0.6,
        sleeve=float(rng.choice([0.0, 0.35, 1.0])),
        legs=float(rng.choice([0.3, 1.0, 1.0])),
        stripes=bool(rng.random() < 0.35),
        clothed=clothed,
    )
    if clothed and rng.random() < SWIMWEAR_SHARE:
        person = replace(person, sleeve=0.0, legs=0.0, stripes=False, bare_torso=True)
    return person


def person_colours(person: Person, rest_vertices: np.ndarray, skinning_weights: np.ndarray) -> np.ndarray:
    """(V, 3) vertex colours of ``person`` from the body's rest vertices (y up, arms along +-x) and weights."""
    regions = vertex_regions(rest_vertices, skinning_weights)
    joint = skinning_weights.argmax(axis=1)
    x_abs, y = np.abs(rest_vertices[:, 0]), rest_vertices[:, 1]
    out = np.tile(person.skin, (len(y), 1))
    out[regions == LABEL["hair"]] = person.hair
    hips = y[np.isin(joint, (1, 2))].max()
    if not person.clothed:  # SURREAL-like: skin and underwear
        brief = np.isin(joint, (0, 1, 2)) & (y > hips - 0.12) & (y < hips + 0.05)
        out[brief] = person.bottom
        return out
    arms = np.isin(joint, (13, 14, 16, 17, 18, 19, 20, 21, 22, 23))
    shoulder_x = x_abs[np.isin(joint, (16, 17))].min()
    hand_x = x_abs.max()
    covered_arm = arms & (x_abs < shoulder_x + person.sleeve * (hand_x - shoulder_x) * 0.82)
    torso = np.isin(joint, (0, 3, 6, 9, 13, 14)) & (y > hips - 0.05)
    top = torso | covered_arm | (regions == LABEL["upper_clothes"])
    top &= ~np.isin(regions, (LABEL["face"], LABEL["hair"], LABEL["torso_skin"])) & (not person.bare_torso)
    stripes = (np.floor((y + 1.0) / 0.05) % 2 == 0) if person.stripes else np.zeros(len(y), bool)
    out[top] = np.where(stripes[top, None], person.top * 0.55 + 0.4, person.top)
    legs = np.isin(joint, (0, 1, 2, 4, 5, 7, 8)) & ~top
    ankle_y = y[np.isin(joint, (7, 8))].max()
    covered_leg = legs & (y > hips - person.legs * (hips - ankle_y) * 0.95 - 0.02)
    out[covered_leg | (np.isin(joint, (0, 1, 2)) & (y > hips - 0.1) & ~top)] = person.bottom
    out[np.isin(regions, (LABEL["left_shoe"], LABEL["right_shoe"]))] = person.shoes
    return out


def random_poses(n: int, rng: np.random.Generator, global_orient: bool = False) -> np.ndarray:
    """(n, 72) plausible SMPL poses: legs standing, walking, squatting or kicking; arms down, out, up or
    crossing; torso and head turns. The global orientation is zero unless ``global_orient``."""
    poses = np.zeros((n, 24, 3))
    u = lambda *shape: rng.uniform(-1, 1, (n, *shape))  # noqa: E731
    stride, squat = u(), np.clip(u() * 1.2, 0, 1)
    poses[:, 1, 0], poses[:, 2, 0] = -0.5 * stride - 0.7 * squat, 0.5 * stride - 0.7 * squat
    poses[:, 1, 2], poses[:, 2, 2] = 0.1 + 0.15 * u(), -0.1 + 0.15 * u()
    poses[:, 4, 0] = np.clip(0.3 * u() + 1.3 * squat + 0.4 * np.maximum(stride, 0), 0, 2.2)
    poses[:, 5, 0] = np.clip(0.3 * u() + 1.3 * squat + 0.4 * np.maximum(-stride, 0), 0, 2.2)
    poses[:, 7, 0], poses[:, 8, 0] = -0.3 * squat + 0.15 * u(), -0.3 * squat + 0.15 * u()
    for shoulder, elbow, wrist, sign in ((16, 18, 20, 1), (17, 19, 21, -1)):
        lift = rng.uniform(-0.4, 1.0, n)  # 1: arm down along the body, -0.4: raised above the shoulder
        poses[:, shoulder, 2] = -sign * 1.2 * lift
        poses[:, shoulder, 1] = -sign * 0.9 * u()
        poses[:, elbow, 1] = sign * np.abs(1.4 * u())
        poses[:, wrist] = 0.3 * u(3)
    poses[:, 3] = 0.15 * u(3)
    poses[:, 6, 1], poses[:, 9, 1] = 0.25 * u(), 0.15 * u()
    poses[:, 12] = 0.15 * u(3)
    poses[:, 15] = 0.3 * u(3)
    if global_orient:
        poses[:, 0] = np.array([0.0, 1.0, 0.0]) * rng.uniform(-np.pi, np.pi, (n, 1))
    return poses.reshape(n, 72)


def pixel_rays(K: np.ndarray, cam_from_world: np.ndarray, width: int, height: int, supersample: int = 1):
    """World origins (N, 3) and unit directions (N, 3) of rays through (sub-)pixel centres, row-major.

    Works for any orthogonal rotation (SURREAL's has det -1). With ``supersample`` s, each pixel gets s x s rays.
    """
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    ys, xs = np.mgrid[0 : height * supersample, 0 : width * supersample].astype(np.float64)
    u = xs // supersample + offsets[(xs % supersample).astype(int)]
    v = ys // supersample + offsets[(ys % supersample).astype(int)]
    cam_dirs = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1).reshape(-1, 3)
    rotation = cam_from_world[:3, :3]
    dirs = cam_dirs @ rotation  # R^T d, row-wise
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    centre = -rotation.T @ cam_from_world[:3, 3]
    return np.broadcast_to(centre, dirs.shape), dirs


def raycast(
    vertices: np.ndarray,
    faces: np.ndarray,
    colours: np.ndarray,
    labels: np.ndarray,
    K: np.ndarray,
    cam_from_world: np.ndarray,
    width: int,
    height: int,
    lights: list[tuple[np.ndarray, float]],
    ambient: float = 0.3,
    supersample: int = 2,
) -> dict[str, np.ndarray]:
    """Render a vertex-coloured mesh with Lambertian lights (world directions towards the light, intensity).

    Returns ``rgb`` (H, W, 3) float32 on black and ``alpha`` (H, W) float32, both averaged over the s x s
    sub-pixel rays; ``labels`` (H, W) uint8 (the first hit sub-ray's label) and ``depth`` (H, W) float32 (mean
    depth along the optical axis of the hit sub-rays) where at least half of the sub-rays hit, 0 elsewhere.
    """
    origins, dirs = pixel_rays(K, cam_from_world, width, height, supersample)
    mesh = trimesh.Trimesh(vertices.astype(np.float64), faces, process=False)
    tri, ray, loc = mesh.ray.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    n_sub = origins.shape[0]
    rgb, alpha = np.zeros((n_sub, 3)), np.zeros(n_sub)
    label_sub, depth_sub = np.zeros(n_sub, np.uint8), np.zeros(n_sub)
    if len(ray):
        corners = faces[tri]
        bary = trimesh.triangles.points_to_barycentric(vertices[corners], loc)
        normals = facing_normals(bary, vertex_normals(vertices, faces)[corners], dirs[ray])
        light = np.full(len(ray), ambient)
        for direction, intensity in lights:
            light += intensity * np.clip(normals @ (direction / np.linalg.norm(direction)), 0, None)
        rgb[ray] = np.clip(np.einsum("nk,nkd->nd", bary, colours[corners]) * light[:, None], 0, 1)
        alpha[ray] = 1.0
        label_sub[ray] = labels[corners[np.arange(len(ray)), bary.argmax(1)]]
        depth_sub[ray] = loc @ cam_from_world[2, :3] + cam_from_world[2, 3]
    s = supersample
    shape = (height, s, width, s)
    alpha_px = alpha.reshape(shape).mean(axis=(1, 3))
    covered = alpha_px >= 0.5  # a pixel belongs to the body when at least half of its sub-rays hit it
    sub_labels = label_sub.reshape(shape).transpose(0, 2, 1, 3).reshape(height, width, s * s)
    first_hit = np.argmax(sub_labels > 0, axis=-1)
    labels_px = np.take_along_axis(sub_labels, first_hit[..., None], axis=-1)[..., 0]
    hits = np.maximum(alpha.reshape(shape).sum(axis=(1, 3)), 1)
    depth_px = depth_sub.reshape(shape).sum(axis=(1, 3)) / hits
    return {
        "rgb": rgb.reshape(*shape, 3).mean(axis=(1, 3)).astype(np.float32),
        "alpha": alpha_px.astype(np.float32),
        "labels": np.where(covered, labels_px, 0).astype(np.uint8),
        "depth": np.where(covered, depth_px, 0).astype(np.float32),
    }
