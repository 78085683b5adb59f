"""The disk-backed training views (fitting.view_store, fitting.data.TrainingSet) against the in-memory sampler they
replace: the same random draws give the same rays and targets, bit for bit, and a view comes back as it went in; the
fast pool draw (fitting.data.pool_pixels) against its reference (pool_pixels_exact): the same distribution."""

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

import fitting.data
from fitting.data import TrainingSet, pool_pixels, pool_pixels_exact
from fitting.view_store import BORDER_PX, ViewStore, sampling_labels


def _view(rng, height, width, body, noisy_background=False):
    """A view with a rectangular 'body' (y0, y1, x0, x1) on black (or noise), a 2-px band and its own camera."""
    image = rng.random((height, width, 3)).astype(np.float32) if noisy_background else np.zeros((height, width, 3))
    mask = np.zeros((height, width), np.float32)
    if body is not None:
        y0, y1, x0, x1 = body
        mask[y0:y1, x0:x1] = 1
        image[y0:y1, x0:x1] = rng.random((y1 - y0, x1 - x0, 3))
    band = (cv2.dilate(mask, np.ones((5, 5))) > 0) & (cv2.erode(mask, np.ones((5, 5))) == 0)
    K = np.array([[50.0 + width, 0, width / 2], [0, 50.0 + width, height / 2], [0, 0, 1]])
    angle = rng.uniform(-0.3, 0.3)
    cam_from_world = np.eye(4)
    cam_from_world[:3, :3] = cv2.Rodrigues(np.array([0.1, angle, 0.0]))[0]
    cam_from_world[:3, 3] = [0.1, -0.2, 3.0]
    return SimpleNamespace(
        image=image.astype(np.float32), mask=mask, band=band, camera=SimpleNamespace(K=K, cam_from_world=cam_from_world)
    )


def _views():
    rng = np.random.default_rng(7)
    return [
        _view(rng, 48, 40, (10, 30, 12, 20)),
        _view(rng, 48, 40, (3, 45, 0, 9)),  # the box touches the top-left corner
        _view(rng, 40, 32, (20, 38, 25, 31), noisy_background=True),  # smaller, and stored whole
        _view(rng, 48, 40, None),  # nobody in view
    ]


def _reference_sample(views, frame_of_view, n_images, rays_per_image, body_fraction, border_fraction, generator):
    """The sampler as it was with every view in memory: pools of flat indices into the views padded to one size."""
    height, width = max(v.mask.shape[0] for v in views), max(v.mask.shape[1] for v in views)
    pad = lambda a: np.pad(a, [(0, height - a.shape[0]), (0, width - a.shape[1])] + [(0, 0)] * (a.ndim - 2))  # noqa: E731
    images = np.stack([pad((v.image * 255 + 0.5).astype(np.uint8)) for v in views])
    masks, bands = np.stack([pad(v.mask > 0.5) for v in views]), np.stack([pad(v.band) for v in views])
    pools = []
    for v, mask in zip(views, masks):
        dilated = cv2.dilate(mask.astype(np.uint8), np.ones((BORDER_PX, BORDER_PX), np.uint8)) > 0
        dilated[v.mask.shape[0] :], dilated[:, v.mask.shape[1] :] = False, False
        ys, xs = np.nonzero(dilated) if dilated.any() else ([0, v.mask.shape[0] - 1], [0, v.mask.shape[1] - 1])
        ys, xs = np.asarray(ys), np.asarray(xs)
        pad_y, pad_x = int(0.1 * (ys.max() - ys.min() + 1)), int(0.1 * (xs.max() - xs.min() + 1))
        box = np.zeros_like(mask)
        box[max(ys.min() - pad_y, 0) : ys.max() + pad_y + 1, max(xs.min() - pad_x, 0) : xs.max() + pad_x + 1] = True
        box[v.mask.shape[0] :], box[:, v.mask.shape[1] :] = False, False
        pools.append([np.flatnonzero(m) for m in (mask, dilated & ~mask, box & ~dilated)])
    chosen = torch.randint(0, len(views), (n_images,), generator=generator).tolist()
    n_body, n_border = int(round(rays_per_image * body_fraction)), int(round(rays_per_image * border_fraction))
    picked = []
    for image in chosen:
        for pool, count in zip(pools[image], (n_body, n_border, rays_per_image - n_body - n_border)):
            pool = pool if pool.size else pools[image][0]
            pick = torch.randint(0, pool.size, (count,), generator=generator).numpy()
            picked += [(image, flat // width, flat % width) for flat in pool[pick]]
    index = tuple(np.array(picked).T)
    rgb, mask, band = images[index] / 255.0, masks[index], bands[index]
    return index, rgb, mask, ~band, np.asarray(frame_of_view)[index[0]]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sampling_from_disk_draws_what_the_in_memory_sampler_drew(seed, tmp_path, monkeypatch):
    """With the reference draw (pools listed in full), the store's rays are the in-memory sampler's, bit for bit."""
    monkeypatch.setattr(fitting.data, "pool_pixels", pool_pixels_exact)
    views, frames = _views()[:3], [2, 0, 1]  # the empty view is left out: the reference drew from padding there
    training = TrainingSet(iter(views), frames, SimpleNamespace(to=lambda device: None), "cpu", store_dir=tmp_path)
    batch = training.sample(6, 20, 0.5, 0.25, torch.Generator().manual_seed(seed))
    (images, rows, cols), rgb, mask, weight, frame = _reference_sample(
        views, frames, 6, 20, 0.5, 0.25, torch.Generator().manual_seed(seed)
    )
    # the targets are the same bytes; float32 of a uint8 / 255 either way
    assert np.array_equal(batch.rgb.numpy(), rgb.astype(np.float32))
    assert np.array_equal(batch.mask.numpy(), mask.astype(np.float32))
    assert np.array_equal(batch.mask_weight.numpy(), weight.astype(np.float32))
    assert np.array_equal(batch.frames.numpy(), frame)
    # the ray through pixel (col, row) of its view's camera: K^-1 (u, v, 1) turned into the world, unit length
    for i in range(0, len(images), 7):
        camera = views[images[i]].camera
        direction = camera.cam_from_world[:3, :3].T @ np.linalg.solve(camera.K, [cols[i], rows[i], 1.0])
        # float32 solve and rotation of O(1) numbers: a few float32 ulps
        np.testing.assert_allclose(batch.dirs[i].numpy(), direction / np.linalg.norm(direction), atol=1e-6)
        centre = -camera.cam_from_world[:3, :3].T @ camera.cam_from_world[:3, 3]
        np.testing.assert_allclose(batch.origins[i].numpy(), centre, atol=1e-6)


def test_a_view_comes_back_as_it_went_in(tmp_path):
    views = _views()
    training = TrainingSet(views, [0, 1, 2, 3], SimpleNamespace(to=lambda device: None), "cpu", store_dir=tmp_path)
    assert (training.height, training.width) == (48, 40)
    for index, view in enumerate(views):
        image, mask, band = training.full_view(index)
        h, w = view.mask.shape
        assert np.array_equal(image[:h, :w], (view.image * 255 + 0.5).astype(np.uint8))
        assert np.array_equal(mask[:h, :w], view.mask > 0.5) and np.array_equal(band[:h, :w], view.band)
        assert not image[h:].any() and not mask[:, w:].any(), "padded with zeros"
    # the black-background views are kept cropped to their boxes, the noisy one whole
    assert training.store.box(0) != (0, 0, 48, 40) and training.store.box(2) == (0, 0, 40, 32)
    assert not list(tmp_path.iterdir()), "the store's file has no name: nothing is left behind"


def test_an_empty_view_draws_from_its_whole_image(tmp_path):
    view = _views()[3]
    training = TrainingSet([view], [0], SimpleNamespace(to=lambda device: None), "cpu", store_dir=tmp_path)
    batch = training.sample(4, 50, 0.5, 0.25, torch.Generator().manual_seed(0))
    assert len(batch.rgb) == 200 and not batch.mask.any()
    labels, box = sampling_labels(view.mask > 0.5, view.band)
    assert box == (0, 48, 0, 40) and (labels == 3).all()


def test_a_view_of_the_wrong_type_is_refused(tmp_path):
    store = ViewStore(tmp_path)
    with pytest.raises(ValueError, match="uint8"):
        store.add(np.zeros((4, 4, 3), np.float32), np.zeros((4, 4), bool), np.zeros((4, 4), bool))


def test_views_per_frame_draws_several_views_of_each_frame(tmp_path):
    """k views each of n / k frames, no view twice within a frame (a frame with fewer views gives all it has); k = 1
    draws exactly as ``torch.randint`` over the images does, so a fit that does not ask keeps its batches."""
    rng = np.random.default_rng(3)
    views = [_view(rng, 48, 40, (10, 30, 12, 20)) for _ in range(7)]
    frames = [0, 0, 0, 1, 1, 1, 2]  # frame 2 has one view
    training = TrainingSet(views, frames, SimpleNamespace(to=lambda device: None), "cpu", store_dir=tmp_path)
    for seed in range(20):
        chosen, groups = training.choose_images(6, 3, torch.Generator().manual_seed(seed)), 0
        while chosen:  # the frames' groups, one after the other
            size = 1 if frames[chosen[0]] == 2 else 3
            group, chosen, groups = chosen[:size], chosen[size:], groups + 1
            assert len({frames[i] for i in group}) == 1 and len(set(group)) == size, group
        assert groups == 2
    plain = training.choose_images(5, 1, torch.Generator().manual_seed(1))
    assert plain == torch.randint(0, 7, (5,), generator=torch.Generator().manual_seed(1)).tolist()


def test_no_ray_is_drawn_where_the_owner_is_unknown(tmp_path):
    """Pixels of unknown owner (a prepared capture's ``mask_unknown/``: somebody in front of the person) lie in no
    pool: painted pure red here, over half the body and its border, no drawn ray has their colour."""
    rng = np.random.default_rng(3)
    view = _view(rng, 48, 40, (10, 30, 12, 20))
    view.image = np.minimum(view.image, 0.9).astype(np.float32)  # nothing else is pure red
    view.unknown = np.zeros((48, 40), bool)
    view.unknown[20:34, 8:24] = True
    view.image[view.unknown] = (1.0, 0.0, 0.0)
    view.mask[view.unknown] = 0.0
    training = TrainingSet([view], [0], SimpleNamespace(to=lambda device: None), "cpu", store_dir=tmp_path)
    batch = training.sample(8, 200, 0.5, 0.25, torch.Generator().manual_seed(0))
    assert len(batch.rgb) == 1600 and batch.mask.any() and not (batch.rgb == torch.tensor([1.0, 0, 0])).all(-1).any()
    image, mask, band = training.full_view(0)
    assert not mask[view.unknown].any() and band[view.unknown].all()  # the evaluation's band, the mask loss's skip
    assert np.array_equal(
        training.store.mask_and_unknown(0)[1], view.unknown
    )  # the subject fit's body refinement reads them
    assert (
        not TrainingSet(_views(), [0, 1, 2, 3], SimpleNamespace(to=lambda device: None), "cpu")
        .store.mask_and_unknown(1)[1]
        .any()
    )


def _labels(height=30, width=20, body=(5, 25, 4, 16), border=2):
    """A crop's pool labels (fitting.view_store): a rectangular body, a ``border``-px ring, background elsewhere."""
    labels = np.full((height, width), 3, np.uint8)
    y0, y1, x0, x1 = body
    labels[max(y0 - border, 0) : y1 + border, max(x0 - border, 0) : x1 + border] = 2
    labels[y0:y1, x0:x1] = 1
    return labels


@pytest.mark.parametrize(
    "labels",
    [_labels(), _labels(body=(0, 30, 0, 17), border=1)],  # the second: a border of 30 pixels, a 20th of the crop
    ids=["ring", "thin-border"],
)
def test_the_fast_pool_draw_has_the_references_distribution(labels):
    """Every pixel drawn lies in its pool, and over 4,000 draws of (14, 4, 2) rays each pool's pixels are drawn
    uniformly: a chi-square against the uniform per pool, for the fast draw and, as a check of the check, for the
    reference. A draw that favoured some pixels of a pool (say the first hits of a fixed scan) fails it."""
    from scipy.stats import chi2

    counts, flat = (14, 4, 2), labels.reshape(-1)
    for draw in (pool_pixels, pool_pixels_exact):
        generator, tallies = torch.Generator().manual_seed(3), [np.zeros(flat.size) for _ in counts]
        for _ in range(4000):
            for pool, (pixels, count) in enumerate(zip(draw(labels, counts, generator), counts)):
                assert len(pixels) == count and (flat[pixels] == pool + 1).all(), (draw.__name__, pool)
                np.add.at(tallies[pool], pixels, 1)
        for pool, tally in enumerate(tallies):
            observed = tally[flat == pool + 1]
            expected = observed.sum() / observed.size
            statistic = ((observed - expected) ** 2 / expected).sum()
            # a false alarm once in a million runs for a uniform draw (the seed is fixed: the same every run)
            assert statistic < chi2.ppf(1 - 1e-6, observed.size - 1), (draw.__name__, pool, statistic)


def test_the_fast_pool_draw_falls_back_where_a_pool_is_small_or_empty():
    """A pool of one pixel has too few candidates' hits: the reference draws it (every ray on that pixel); an empty
    border draws from the body and a crop without a body from all of it, as the reference does."""
    labels = _labels()
    labels[labels == 2] = 3
    labels[(labels == 3).nonzero()[0][0], (labels == 3).nonzero()[1][0]] = 2  # one border pixel
    border = pool_pixels(labels, (14, 4, 2), torch.Generator().manual_seed(0))[1]
    assert (border == np.flatnonzero(labels == 2)[0]).all()
    no_border = np.where(labels == 2, 3, labels).astype(np.uint8)
    for generator in (torch.Generator().manual_seed(s) for s in range(5)):
        assert (no_border.reshape(-1)[pool_pixels(no_border, (14, 4, 2), generator)[1]] == 1).all()
    nobody = np.full((6, 5), 3, np.uint8)
    drawn = pool_pixels(nobody, (14, 4, 2), torch.Generator().manual_seed(0))
    assert [len(d) for d in drawn] == [14, 4, 2] and all(((d >= 0) & (d < 30)).all() for d in drawn)
