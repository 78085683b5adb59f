"""Body shells (docs/model.md §1, *Body shells*): each part's box cut to the body's neighbourhood."""

import numpy as np
import pytest
import torch
import trimesh

from fitting.config import ConfigError, FitConfig, validate_config
from narf.fields import build_field
from narf.fields.common import part_box_coordinates
from narf.kinematics import N_PARTS
from pipelines.body import shells as shells_module
from pipelines.body.model import pose_batch
from pipelines.body.shells import hidden_vertices, part_shells, signed_distance_to_vertices, winding_numbers

MARGIN = 0.03  # metres


@pytest.fixture(scope="module")
def rest(body_model):
    """The stand-in's rest body, its part boxes (padded as a fit pads them), its shells at MARGIN, 32 cells a side,
    and its hidden vertices (inside the body, where its tubes overlap)."""
    with torch.no_grad():
        body = body_model.rest_body(torch.zeros(1, 10))
    boxes = body_model.part_boxes([body])
    shells = part_shells([body], body_model.faces, *boxes, resolution=32, margin=MARGIN)
    return body, boxes, shells, hidden_vertices(body.vertices[0].double().numpy(), body_model.faces)


def _sphere(n_theta=24, n_phi=48, radius=1.0):
    """A UV sphere wound outward: (V, 3), (F, 3)."""
    theta = np.linspace(0, np.pi, n_theta + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    vertices = radius * np.concatenate([[[0, 0, 1]], ring, [[0, 0, -1]]])
    faces, last = [], len(vertices) - 1
    for j in range(n_phi):
        k = (j + 1) % n_phi
        faces.append([0, 1 + j, 1 + k])
        faces.append([last, 1 + (n_theta - 2) * n_phi + k, 1 + (n_theta - 2) * n_phi + j])
        for i in range(n_theta - 2):
            a, b = 1 + i * n_phi, 1 + (i + 1) * n_phi
            faces += [[a + j, b + j, b + k], [a + j, b + k, a + k]]
    return vertices, np.asarray(faces)


def test_signed_distance_to_a_sphere():
    vertices, faces = _sphere()
    directions = np.random.default_rng(0).normal(size=(50, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = np.linspace(0.2, 1.8, 50)
    distance = signed_distance_to_vertices(directions * radii[:, None], vertices, faces)
    inside = radii < 1
    # inside: (x - v) . n_v = r cos(a) - 1 with a, the angle to the nearest vertex, under the grid's 5.3 degree
    # half-diagonal (1 - cos a < 0.0043)
    assert np.abs(distance[inside] - (radii[inside] - 1)).max() < 0.005
    # outside: |x - v|, at least the distance to the sphere (v lies on it) and at most sqrt((r - 1)^2 + 2 r (1 - cos a))
    r = radii[~inside]
    assert (distance[~inside] >= r - 1 - 1e-12).all()
    assert (distance[~inside] <= np.sqrt((r - 1) ** 2 + 2 * r * 0.0043) + 1e-12).all()


def test_winding_numbers_count_the_closed_pieces_around_a_point():
    vertices, faces = _sphere()
    # two unit spheres 1.2 apart in one mesh: they overlap around x = 0.6
    pair = np.concatenate([vertices, vertices + [1.2, 0, 0]])
    faces2 = np.concatenate([faces, faces + len(vertices)])
    points = np.array([[0.0, 0, 0], [0.6, 0, 0], [1.2, 0, 0], [3.0, 0, 0], [0.6, 1.5, 0]])
    # a closed surface's solid angles sum to exactly 4 pi inside and 0 outside; float64 rounding over 2 x 2,208
    # triangles stays far below 1e-9
    assert np.allclose(winding_numbers(points, pair, faces2), [1, 2, 1, 0, 0], atol=1e-9)
    hidden = hidden_vertices(pair, faces2, stride=1)  # every vertex measured
    centres = np.repeat([[0.0, 0, 0], [1.2, 0, 0]], len(vertices), axis=0)
    other = np.repeat([[1.2, 0, 0], [0.0, 0, 0]], len(vertices), axis=0)
    # a vertex of one sphere is hidden exactly when it lies inside the other (2 mm of slack at the seam)
    depth = 1 - np.linalg.norm(pair - other, axis=1)
    assert np.allclose(np.linalg.norm(pair - centres, axis=1), 1)
    assert hidden[depth > 0.003].all() and not hidden[depth < -0.003].any() and hidden.sum() > 100


def test_only_the_outside_vertices_are_nearest(body_model, rest):
    """The stand-in's tubes overlap inside the body: with its hidden vertices counted, points deep in the hips look
    farther than the margin outside; without them, few do (those within a sample spacing of a tube's seam, where
    the hidden set is interpolated)."""
    body, hidden = rest[0], rest[3]
    vertices = body.vertices[0].double().numpy()
    points = np.random.default_rng(0).uniform(vertices.min(0), vertices.max(0), size=(1500, 3))
    inside = winding_numbers(points, vertices, body_model.faces) > 0.5
    every = signed_distance_to_vertices(points, vertices, body_model.faces)
    outer = signed_distance_to_vertices(points, vertices, body_model.faces, ~hidden)
    assert hidden.any() and inside.sum() > 100
    assert (every[inside] > MARGIN).mean() > 0.05
    assert (outer[inside] > MARGIN).mean() < 0.02


def test_shells_keep_the_body_surface_and_cut_the_space_beside_it(rest, body_model):
    body, (centres, half_extents), shells, hidden = rest
    assert shells.shape == (N_PARTS, 32, 32, 32) and shells.dtype == torch.bool
    field = build_field("narf_d", width=16)
    field.set_boxes(centres, half_extents)
    pose = pose_batch(body)
    vertices = body.vertices[0]
    one = torch.zeros(vertices.shape[0], dtype=torch.long)
    u = part_box_coordinates(vertices[:, None], pose.select(one), centres, half_extents)[:, 0]
    whole = field.in_parts(u)
    field.set_shells(shells)
    kept = field.in_parts(u)
    # every vertex of the surface (not the hidden ones, inside the body) stays in every box that holds it
    visible = torch.as_tensor(~hidden)
    assert torch.equal(kept[visible], whole[visible]) and whole.any(dim=1).all()
    # points 10 cm out from the surface along the normal that boxes still hold: cut (the margin is 3 cm, a cell's
    # half-diagonal at most 1.7 cm: a kept point lies within 3 + 2 x 1.7 cm)
    mesh = trimesh.Trimesh(vertices.numpy(), body_model.faces, process=False)
    normals = torch.tensor(mesh.vertex_normals, dtype=vertices.dtype)
    out = vertices + 0.10 * normals
    distance = signed_distance_to_vertices(out.double().numpy(), vertices.double().numpy(), body_model.faces)
    clear = torch.as_tensor(distance > 0.08)  # not near another part of the body (between the legs, at the armpits)
    u_out = part_box_coordinates(out[:, None], pose.select(one), centres, half_extents)[:, 0]
    field.set_shells(torch.ones(N_PARTS, 1, 1, 1, dtype=torch.bool))
    boxed = field.in_parts(u_out).any(dim=1) & clear
    field.set_shells(shells)
    # all but a few: a cell centre beside a sharp edge (a hand, a foot)
    # can take the sign of a vertex whose normal points away, and counts as inside (the error keeps space, never cuts
    # the body)
    assert boxed.sum() > 500
    assert field.in_parts(u_out)[boxed].any(dim=1).float().mean() < 0.01


def _shells_every_cell(bodies, faces, centres, half_extents, n, margin):
    """The reference for :func:`part_shells`: every cell's centre measured in every frame (all of each batch here)."""
    steps = (np.arange(n) + 0.5) * (2.0 / n) - 1.0
    u = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)
    local = centres.double().numpy()[:, None] + u[None] * half_extents.double().numpy()[:, None]
    half_diagonal = np.linalg.norm(half_extents.double().numpy(), axis=1) / n
    visible = ~hidden_vertices(bodies[0].vertices[0].double().numpy(), faces)
    inside = np.zeros((N_PARTS, n**3), bool)
    for body in bodies:
        for f in range(len(body.reach)):
            reach, world_from_part = float(body.reach[f]), body.world_from_part[f].double().numpy()
            world = (
                np.einsum("pij,pnj->pni", world_from_part[:, :3, :3], local * reach) + world_from_part[:, None, :3, 3]
            )
            vertices = body.vertices[f].double().numpy()
            distance = signed_distance_to_vertices(world.reshape(-1, 3), vertices, faces, visible).reshape(N_PARTS, -1)
            inside |= distance < margin + half_diagonal[:, None] * reach
    return torch.from_numpy(inside.reshape(N_PARTS, n, n, n))


def test_shells_measure_each_cell_until_a_frame_keeps_it(body_model, monkeypatch):
    """The shells measure only the cells no earlier frame kept: the same cells as measuring every cell in every frame
    (a union does not depend on its order; both paths compare the same float64 numbers with the same threshold, so
    equality is exact)."""
    poses = torch.zeros(3, 72, dtype=torch.float64)
    poses[1, 3 * 1 : 3 * 1 + 3] = torch.tensor([-1.2, 0.0, 0.3])  # the left hip raised and turned
    poses[2, 3 * 16 : 3 * 16 + 3] = torch.tensor([0.0, 0.0, -1.1])  # the left shoulder lowered
    poses[2, 3 * 18 : 3 * 18 + 3] = torch.tensor([0.0, -1.4, 0.0])  # the left elbow bent
    with torch.no_grad():
        rest = body_model.rest_body(torch.zeros(1, 10))
        posed = body_model.pose_zju(poses, torch.zeros(3, 3), torch.zeros(3, 3), torch.zeros(3, 10))
    boxes = body_model.part_boxes([rest, posed])
    fast = part_shells([rest, posed], body_model.faces, *boxes, resolution=20, margin=MARGIN)
    every = _shells_every_cell([rest, posed], body_model.faces, *boxes, 20, MARGIN)
    assert torch.equal(fast, every)
    # measured in chunks that split the parts (4,001 cells; each part has 8,000), the same cells
    monkeypatch.setattr(shells_module, "CHUNK", 4001)
    assert torch.equal(part_shells([rest, posed], body_model.faces, *boxes, resolution=20, margin=MARGIN), every)
    # the later frames add cells (the limbs moved), so the frames after the first measured some cells and skipped others
    alone = part_shells([rest], body_model.faces, *boxes, resolution=20, margin=MARGIN)
    assert (alone <= fast).all() and (fast & ~alone).sum() > 100


def test_the_shells_memory_beyond_their_bools_is_one_chunks(body_model, monkeypatch):
    """Measured in chunks of 4,096 cells at 48^3 (19 x 110,592 cells): numpy's peak beyond the (P, N^3) bools and
    the (N^3, 3) cell centres stays within a few chunks' worth, where listing every cell not yet kept at once takes
    two int64 arrays of P N^3 (34 MB). (Checked against that listing: the peak was 36 MB.)"""
    import tracemalloc

    with torch.no_grad():
        rest = body_model.rest_body(torch.zeros(1, 10))
    boxes = body_model.part_boxes([rest])
    monkeypatch.setattr(shells_module, "CHUNK", 4096)
    n = 48
    tracemalloc.start()
    part_shells([rest], body_model.faces, *boxes, resolution=n, margin=MARGIN)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    fixed = 19 * n**3 + 2 * n**3 * 3 * 8  # the bools, the centres and a temporary of theirs
    assert peak - fixed < 8 * 2**20  # 4,096-cell chunks' float64 places and distances: well under a megabyte each


def test_a_field_outside_its_shells_has_no_density(rest):
    body, boxes, shells, _ = rest
    field = build_field("narf_d", width=16)
    field.set_boxes(*boxes)
    with torch.no_grad():  # an untrained field with density everywhere in its boxes
        field.head.sigma_out.bias.fill_(5.0)
    pose = pose_batch(body)
    points = torch.rand(512, 8, 3, generator=torch.Generator().manual_seed(0)) * 1.6 - 0.8
    dirs = torch.nn.functional.normalize(torch.ones(512, 3), dim=-1)
    one = pose.select(torch.zeros(512, dtype=torch.long))
    with torch.no_grad():
        before = field(points, dirs, one).sigma
        field.set_shells(shells)
        after = field(points, dirs, one).sigma
    u = part_box_coordinates(points, one, *boxes)
    in_box, in_shell = u.abs().amax(-1).le(1).any(-1), field.in_parts(u).any(-1)
    cut = in_box & ~in_shell
    assert cut.sum() > 20 and (before[cut] > 0).all()
    assert (after[cut] == 0).all() and (after[~in_box] == 0).all()


def test_shells_travel_with_the_weights_and_old_weights_mean_whole_boxes(rest):
    _, boxes, shells, _ = rest
    field = build_field("narf_d", width=16)
    field.set_boxes(*boxes)
    field.set_shells(shells)
    state = field.state_dict()
    loaded = build_field("narf_d", width=16)
    loaded.load_state_dict(state)
    assert torch.equal(loaded.part_shells, shells)
    del state["part_shells"]  # a checkpoint written before the shells
    loaded.load_state_dict(state)
    assert loaded.part_shells.shape == (N_PARTS, 1, 1, 1) and loaded.part_shells.all()
    with pytest.raises(ValueError, match="shells"):
        loaded.set_shells(torch.ones(N_PARTS, 4, 4, 5, dtype=torch.bool))


def test_body_shell_is_for_subject_fits():
    config = FitConfig()
    config.model.body_shell = -0.01
    with pytest.raises(ConfigError, match="model.body_shell"):
        validate_config(config)
    config = FitConfig(kind="autoencoder")
    config.model.latent_dim = 8
    config.model.body_shell = 0.03
    with pytest.raises(ConfigError, match="model.body_shell: only subject"):
        validate_config(config)
    config.model.body_shell, config.model.shell_resolution = 0.0, 16
    with pytest.raises(ConfigError, match="model.shell_resolution: only subject"):
        validate_config(config)
    config = FitConfig()
    config.model.surface_shell = 0.015  # a margin for shells that are off
    with pytest.raises(ConfigError, match="model.surface_shell: shells are off"):
        validate_config(config)
    config.model.surface_shell = -0.01
    with pytest.raises(ConfigError, match="model.surface_shell"):
        validate_config(config)
