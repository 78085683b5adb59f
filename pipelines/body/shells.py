"""Each part's shell: the cells of its box that lie inside the body or within a margin of its surface (docs/model.md
§1, *Body shells*).

A part box is the bounding box of the part's vertices, so it also holds empty space the body never fills (beside a
thigh, between the legs, under an arm). Training cameras carve that space only where one of their rays sees past the
body; with a few cameras, space that every training ray sees the body in front of or behind stays free to hold
density, and a new camera sees it as a person too wide. The shells keep the field to the body's neighbourhood:

* the cell centres of each part's N^3 grid over box coordinates ``u`` are posed with the part into the world, in the
  rest pose and a few training frames;
* a cell is in the shell when, in any of those frames, the signed distance of its centre to the body (from the
  nearest vertex v: ``|x - v|`` outside, ``(x - v) . n_v`` inside, n_v the outward normal) is below the margin plus
  half the cell's diagonal (the lookup takes the cell of a point, not its centre);
* only vertices on the outside count as nearest: a vertex inside the body (the stand-in's tubes overlap where they
  join; skin pressed against skin) would take a point deep inside for one outside it. Which vertices are inside is
  decided once, on the first body given (the rest pose), by the winding number just outside each vertex.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from fitting.mesh import vertex_normals
from narf.kinematics import N_PARTS


def winding_numbers(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, chunk: int = 64) -> np.ndarray:
    """(N,) generalised winding number of a mesh (vertices (V, 3), faces (F, 3) wound outward) at points (N, 3):
    the triangles' solid angles summed over 4 pi (docs/model.md §1, *Body shells*), tan(Omega / 2) = a . (b x c) /
    (|a||b||c| + (a . b)|c| + (a . c)|b| + (b . c)|a|) with a, b, c the corners relative to the point. 1 inside a
    closed surface, 0 outside, 2 where two overlapping closed pieces hold the point. ``chunk`` points at a time
    (their corners: chunk x F x 9 doubles, 64 MB for SMPL's 13,776 faces)."""
    corners = torch.as_tensor(vertices, dtype=torch.float64)[torch.as_tensor(faces)]  # (F, 3, 3)
    query = torch.as_tensor(points, dtype=torch.float64)
    out = torch.empty(len(points), dtype=torch.float64)
    for start in range(0, len(points), chunk):
        rel = corners[None] - query[start : start + chunk, None, None]  # (n, F, 3, 3)
        a, b, c = rel.unbind(dim=2)
        la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
        numerator = (a * torch.linalg.cross(b, c)).sum(-1)
        denominator = la * lb * lc + (a * b).sum(-1) * lc + (a * c).sum(-1) * lb + (b * c).sum(-1) * la
        out[start : start + chunk] = torch.atan2(numerator, denominator).sum(dim=1) / (2 * math.pi)
    return out.numpy()


def hidden_vertices(vertices: np.ndarray, faces: np.ndarray, offset: float = 0.002, stride: int = 4) -> np.ndarray:
    """(V,) bool: vertices that lie inside the body, where a point ``offset`` out along the vertex normal has a
    winding number above 1/2 (the stand-in's tubes overlap inside the body; skin pressed against skin). The winding
    number is taken at every ``stride``-th vertex (it costs V x F solid angles); every other vertex takes the answer
    of the nearest of those whose normal is within 60 degrees of its own (not one across a thin wall)."""
    normals = vertex_normals(vertices, faces)
    sampled = np.arange(0, len(vertices), stride)
    inside = winding_numbers(vertices[sampled] + offset * normals[sampled], vertices, faces) > 0.5
    neighbours = min(16, len(sampled))
    _, near = cKDTree(vertices[sampled]).query(vertices, k=neighbours)
    near = near.reshape(len(vertices), neighbours)
    alike = np.einsum("vki,vi->vk", normals[sampled][near], normals) > 0.5
    first = np.where(alike.any(axis=1), alike.argmax(axis=1), 0)
    return inside[near[np.arange(len(vertices)), first]]


def signed_distance_to_vertices(
    points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, among: np.ndarray | None = None
) -> np.ndarray:
    """(N,) signed distance of each point x (N, 3) to a mesh (vertices (V, 3), faces (F, 3) wound outward), from its
    nearest vertex v: ``|x - v|`` where ``(x - v) . n_v >= 0`` (n_v the vertex's area-weighted normal), else that
    negative projection (inside). Outside, the distance to the nearest vertex never falls short of the distance to
    the surface by more than the vertex spacing; inside, the projection is the depth below a smooth surface.
    ``among`` (V,) bool: the vertices that may be nearest (default all). The nearest-vertex queries use every core
    (the answers do not depend on how they are split)."""
    normals = vertex_normals(vertices, faces)
    ids = np.arange(len(vertices)) if among is None else np.flatnonzero(among)
    distance, nearest = cKDTree(vertices[ids]).query(points, workers=-1)
    nearest = ids[nearest]
    projection = np.einsum("ni,ni->n", points - vertices[nearest], normals[nearest])
    return np.where(projection < 0, projection, distance)


#: cells measured at a time: bounds the posed centres and the nearest-vertex answers to about 300 MB at any grid size
CHUNK = 2**21


def part_shells(
    bodies: list,
    faces: np.ndarray,
    centres: torch.Tensor,
    half_extents: torch.Tensor,
    resolution: int,
    margin: float,
    frames: int = 8,
) -> torch.Tensor:
    """(P, N, N, N) bool shells of the part boxes (``centres``, ``half_extents`` (P, 3), body units) over up to
    ``frames`` evenly spaced frames of each of ``bodies`` (``PosedBody`` batches: the rest pose first, then the
    training frames), ``margin`` in world units. A shell is the union over the frames, so a frame only measures the
    cells no earlier frame kept (the same cells as measuring every cell in every frame, in under half the time at
    64^3 on the real demo), ``CHUNK`` cells at a time: the cells not yet kept are listed chunk by chunk, so that the
    memory beyond the (P, N^3) bools is the chunk's (two int64 of P N^3 would be 340 MB at 96^3)."""
    n = resolution
    steps = (np.arange(n) + 0.5) * (2.0 / n) - 1.0
    u = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)  # (N^3, 3)
    centres, half_extents = centres.double().cpu().numpy(), half_extents.double().cpu().numpy()
    half_diagonal = np.linalg.norm(half_extents, axis=1) / n  # (P,) body units
    visible = ~hidden_vertices(bodies[0].vertices[0].double().cpu().numpy(), faces)
    chosen = [(b, f) for b in bodies for f in np.unique(np.linspace(0, len(b.reach) - 1, frames).round().astype(int))]
    inside = np.zeros((N_PARTS, n**3), bool)
    for body, f in chosen:
        reach = float(body.reach[f])
        world_from_part = body.world_from_part[f].double().cpu().numpy()
        vertices = body.vertices[f].double().cpu().numpy()
        flat = inside.reshape(-1)
        for start in range(0, flat.size, CHUNK):  # the cells not yet kept, CHUNK cells of P N^3 looked at a time
            index = np.flatnonzero(~flat[start : start + CHUNK]) + start  # grouped by part, in order
            p, c = np.divmod(index, n**3)
            world = _posed_cells(u, centres, half_extents, p, c, world_from_part, reach)
            distance = signed_distance_to_vertices(world, vertices, faces, visible)
            inside[p, c] = distance < margin + half_diagonal[p] * reach
    return torch.from_numpy(inside.reshape(N_PARTS, n, n, n))


def _posed_cells(
    u: np.ndarray,
    centres: np.ndarray,
    half_extents: np.ndarray,
    part: np.ndarray,
    cell: np.ndarray,
    world_from_part: np.ndarray,
    reach: float,
) -> np.ndarray:
    """(K, 3) world places of the cells ``cell`` (K,) of the parts ``part`` (K,), sorted by part: x = R_p (reach (c_p
    + u h_p)) + t_p, with ``u`` (N^3, 3) the cell centres in box coordinates, ``centres`` and ``half_extents`` (P, 3)
    the boxes in body units and ``world_from_part`` (P, 4, 4)."""
    world = np.empty((len(part), 3))
    bounds = np.searchsorted(part, np.arange(len(centres) + 1))
    for p in range(len(centres)):
        a, b = bounds[p], bounds[p + 1]
        if a == b:
            continue
        local = centres[p] + u[cell[a:b]] * half_extents[p]
        world[a:b] = (local * reach) @ world_from_part[p, :3, :3].T + world_from_part[p, :3, 3]
    return world
