"""The bodies' outline from unseen views (docs/model.md §6): the band by hand, the bank of virtual rays around a
sphere against its analytic outline, the error by hand, and the term in a fit."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh

from fitting.config import load_config
from fitting.data import OutlineRays
from fitting.run_folder import prepare_run_dir
from fitting.unseen import VIRTUAL_DISTANCE, outline_error, outline_terms, terms_rendered_alone
from pipelines.runs.fit import start_run
from pipelines.runs.subject.outlines import HALF_FIELD, RAYS_PER_VIEW, SIZE, outline_band, outline_rays

CENTRE = np.array([0.2, -0.1, 1.0])
RADIUS = 0.3


def test_the_band_by_hand():
    """A 10 x 10 square in a 30 x 30 image, band 2: the pixels of its 14 x 14 dilation not in its 6 x 6 erosion,
    196 - 36 = 160; an empty image has none."""
    inside = np.zeros((30, 30), bool)
    inside[10:20, 10:20] = True
    band = outline_band(inside, 2)
    assert band.sum() == 160 and band[8:22, 8:22].sum() == 160 and not band[12:18, 12:18].any()
    assert not outline_band(np.zeros((30, 30), bool), 2).any()


def sphere_bodies(indices):
    """Every frame's 'body': an icosphere of RADIUS about CENTRE, its pelvis there, reach 1."""
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    world_from_part = torch.eye(4, dtype=torch.float64).repeat(len(indices), 19, 1, 1)
    world_from_part[:, 0, :3, 3] = torch.as_tensor(CENTRE)
    vertices = torch.as_tensor(sphere.vertices + CENTRE).expand(len(indices), -1, -1)
    return SimpleNamespace(vertices=vertices, world_from_part=world_from_part, reach=torch.ones(len(indices)))


def test_the_outline_of_a_sphere():
    """Virtual cameras around a sphere: every ray leaves from VIRTUAL_DISTANCE reaches of its centre; a ray labelled
    as meeting it passes within RADIUS of the centre and one labelled beside it further than the icosphere's
    inscribed radius; every ray lies within the band's 2 pixels of chessboard distance (2 sqrt 2 pixels) plus one
    (the rasteriser draws the polygon's edge pixels) of the outline, a pixel being VIRTUAL_DISTANCE / f at the
    centre's distance; both labels are drawn; the same seed draws
    the same bank. Tolerances: float32 rays of a unit-size scene, 1e-5."""
    faces = trimesh.creation.icosphere(subdivisions=4).faces
    bank = outline_rays(sphere_bodies, 5, faces, seed=3, views=6)
    assert len(bank.inside) == 6 * RAYS_PER_VIEW and set(bank.frames.tolist()) <= set(range(5))
    origins, dirs = bank.origins.double(), bank.dirs.double()
    centre = torch.as_tensor(CENTRE)
    assert torch.allclose(
        (origins - centre).norm(dim=1), torch.full((len(origins),), VIRTUAL_DISTANCE, dtype=torch.float64), atol=1e-5
    )
    to_centre = centre - origins
    miss = (to_centre - (to_centre * dirs).sum(1, keepdim=True) * dirs).norm(dim=1)  # the line's distance
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    inscribed = np.abs((sphere.triangles_center * sphere.face_normals).sum(1)).min()
    inside = bank.inside > 0.5
    assert (miss[inside] <= RADIUS + 1e-5).all() and (miss[~inside] >= inscribed - 1e-5).all()
    pixel = VIRTUAL_DISTANCE / (SIZE / 2 * VIRTUAL_DISTANCE / HALF_FIELD)
    assert ((miss - RADIUS).abs() <= (2 * 2**0.5 + 1) * pixel + (RADIUS - inscribed)).all()
    assert 0.2 < inside.float().mean() < 0.8
    again = outline_rays(sphere_bodies, 5, faces, seed=3, views=6)
    assert torch.equal(again.origins, bank.origins) and torch.equal(again.inside, bank.inside)


def test_the_outline_error_by_hand():
    """Opacities (1, 0.25, 0.5) against (1, 0, 1): (0 + 0.0625 + 0.25) / 3; the ray beside the body weighed 0.5:
    (0 + 0.5 * 0.0625 + 0.25) / 2.5."""
    opacity, inside = torch.tensor([1.0, 0.25, 0.5]), torch.tensor([1.0, 0.0, 1.0])
    # float32 of values <= 1 through a few operations: 1e-7
    assert outline_error(opacity, inside).item() == pytest.approx(0.3125 / 3, abs=1e-7)
    weighed = outline_error(opacity, inside, torch.tensor([1.0, 0.5, 1.0])).item()
    assert weighed == pytest.approx(0.28125 / 2.5, abs=1e-7)


def test_rays_beside_the_body_left_out():
    """With train.outline_beside 0 every ray drawn meets the body; at 1 both kinds are drawn, in proportion."""
    inside = torch.tensor([1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0])
    bank = OutlineRays(torch.arange(30.0).reshape(10, 3), torch.ones(10, 3), torch.zeros(10, dtype=torch.long), inside)
    sets = ["train.outline_weight=1", "train.outline_rays=200"]
    generator = torch.Generator().manual_seed(0)
    through = outline_terms(load_config("tiny", [*sets, "train.outline_beside=0"]), bank, None, generator)
    drawn = through[0].sets[0].origins[:, 0].long() // 3
    assert set(drawn.tolist()) == {0, 3, 7}
    both = outline_terms(load_config("tiny", sets), bank, None, generator)[0].sets[0].origins[:, 0].long() // 3
    assert len(set(both.tolist())) > 3 and 0.15 < inside[both].mean() < 0.45  # 3 of 10; 200 draws: +-0.1 is 3 sigma


def test_the_outline_term_reaches_the_field(data_root_64, tmp_path):
    """In a fit with train.outline_weight the data holds the bank (indices into the training frames), the term
    draws train.outline_rays of it and gives the field's weights a gradient; with the weight at 0 it draws and
    renders nothing (the fit's generator does not move)."""
    sets = [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.steps=3", "train.outline_weight=1.0"]
    sets += ["train.outline_rays=64"]
    trainer = start_run(
        prepare_run_dir(tmp_path / "run", False), torch.device("cpu"), load_config("tiny", sets), progress=False
    )
    trainer.fit()  # the term inside a step, end to end
    bank = trainer.fit_data.outline_rays
    assert isinstance(bank, OutlineRays) and 0 < bank.inside.mean() < 1
    assert bank.frames.max() < len(trainer.fit_data.frames)
    poses = trainer.views.poses
    terms = outline_terms(trainer.config, bank, poses, trainer.generator)
    assert len(terms) == 1 and len(terms[0].sets[0].frames) == 64
    trainer.field.zero_grad()
    terms_rendered_alone(trainer.config, trainer.field, terms).backward()
    grads = [p.grad.abs().sum().item() for p in trainer.field.parameters() if p.grad is not None]
    assert grads and max(grads) > 0
    state = trainer.generator.get_state()
    off = load_config("tiny", [*sets, "train.outline_weight=0"])
    assert outline_terms(off, bank, poses, trainer.generator) == []
    assert torch.equal(trainer.generator.get_state(), state)
