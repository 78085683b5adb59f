"""A detector that swaps one pair of limbs alone in a view (pipelines/prepare/people/targets.py, ``side_swaps``): the
legs as they cross, the arms as they fold. On exact projections of a person striding with one arm raised, the views
whose legs or arms were swapped are found and put right, two views of the same limb included, and nothing is
exchanged where the person stands with the limbs together; through ``triangulate_people`` the legs of a frame where
two of five views swapped them come back where they are, every view counted. (Two of four is a tie that the views
alone cannot break: each pair triangulates its own legs without a disagreement.)"""

import numpy as np
import pytest

from pipelines.datasets.camera import Camera
from pipelines.datasets.keypoints import TARGET_NAMES, mirror_index
from pipelines.prepare.people.multiview import project, projection_matrix
from pipelines.prepare.people.targets import side_swaps, triangulate_people

#: a person striding (left leg forward, right leg back) with the left arm raised: world metres, z up
STRIDE = {
    "pelvis": (0.0, 0.0, 0.95),
    "l_hip": (0.1, 0.0, 0.92),
    "r_hip": (-0.1, 0.0, 0.92),
    "l_knee": (0.15, 0.25, 0.52),
    "r_knee": (-0.12, -0.2, 0.5),
    "l_ankle": (0.18, 0.35, 0.1),
    "r_ankle": (-0.15, -0.45, 0.15),
    "l_foot": (0.2, 0.5, 0.02),
    "r_foot": (-0.15, -0.55, 0.05),
    "neck": (0.0, 0.0, 1.45),
    "head": (0.0, 0.02, 1.65),
    "l_shoulder": (0.2, 0.0, 1.42),
    "r_shoulder": (-0.2, 0.0, 1.42),
    "l_elbow": (0.4, 0.1, 1.6),
    "r_elbow": (-0.3, -0.15, 1.2),
    "l_wrist": (0.45, 0.2, 1.85),
    "r_wrist": (-0.3, -0.05, 0.95),
}
LEGS = ("knee", "ankle", "foot")
ARMS = ("elbow", "wrist")
#: 3 % of the 480-px image: the capture's default (``PrepareRequest.threshold``)
THRESHOLD = 0.03


def _person(places: dict) -> np.ndarray:
    return np.array([places[name] for name in TARGET_NAMES], np.float64)


def _ring(n: int) -> list[Camera]:
    """``n`` cameras on a 4 m circle, 1.2 m up, looking at the person's middle; f = 500 px, 640 x 480."""
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    out = []
    for k, angle in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False) + 0.3):
        centre = np.array([4 * np.cos(angle), 4 * np.sin(angle), 1.2])
        forward = np.array([0, 0, 0.9]) - centre
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([right, np.cross(forward, right), forward])
        pose[:3, 3] = -pose[:3, :3] @ centre
        out.append(Camera(f"cam{k}", K, np.zeros(5), pose, 640, 480))
    return out


def _views(cameras: list[Camera], person: np.ndarray, swaps: dict[int, tuple[str, ...]]) -> np.ndarray:
    """(V, T, 3) exact pixels and confidence 1, with the limbs named in ``swaps[v]`` swapped left for right."""
    P = np.stack([projection_matrix(c) for c in cameras])
    xy = np.concatenate([project(P, person).transpose(1, 0, 2), np.ones((len(P), len(person), 1))], axis=-1)
    for v, limbs in swaps.items():
        order = _order(limbs)
        xy[v] = xy[v, order]
    return xy


def _order(limbs: tuple[str, ...]) -> np.ndarray:
    """The target order that swaps the ``limbs`` (``knee``, ``wrist``, ...) left for right."""
    order = np.arange(len(TARGET_NAMES))
    for limb in limbs:
        for side in "lr":
            t = TARGET_NAMES.index(f"{side}_{limb}")
            order[t] = mirror_index(t)
    return order


@pytest.mark.parametrize(
    "n_views, swaps",
    [(4, {1: LEGS}), (4, {3: ARMS}), (4, {0: LEGS, 2: ARMS}), (5, {1: LEGS, 3: LEGS}), (6, {0: LEGS + ARMS})],
)
def test_swapped_limbs_are_found_in_the_views_that_swapped_them(n_views, swaps):
    cameras = _ring(n_views)
    P = np.stack([projection_matrix(c) for c in cameras])
    xy = _views(cameras, _person(STRIDE), swaps)
    orders = side_swaps(P, xy, np.full(n_views, 480.0), THRESHOLD)
    for v in range(n_views):
        np.testing.assert_array_equal(orders[v], _order(swaps.get(v, ())), err_msg=f"view {v}")


def test_limbs_together_are_left_as_detected():
    # the feet side by side and the arms hanging: a swap moves each target by the width between them, under 3 % of
    # the height from every camera, so the detection as given already agrees and nothing is exchanged
    together = dict(STRIDE)
    for limb, (x, z) in {"knee": (0.01, 0.5), "ankle": (0.01, 0.1), "foot": (0.01, 0.02)}.items():
        together[f"l_{limb}"], together[f"r_{limb}"] = (x, 0.0, z), (-x, 0.0, z)
    for limb, (x, z) in {"elbow": (0.01, 1.15), "wrist": (0.01, 0.9)}.items():
        together[f"l_{limb}"], together[f"r_{limb}"] = (x, 0.0, z), (-x, 0.0, z)
    cameras = _ring(4)
    P = np.stack([projection_matrix(c) for c in cameras])
    xy = _views(cameras, _person(together), {1: LEGS + ARMS})
    orders = side_swaps(P, xy, np.full(4, 480.0), THRESHOLD)
    np.testing.assert_array_equal(orders, np.tile(np.arange(len(TARGET_NAMES)), (4, 1)))


def test_two_of_five_views_with_the_legs_swapped_triangulate_the_legs_where_they_are():
    cameras, person = _ring(5), _person(STRIDE)
    xy = _views(cameras, person, {0: LEGS, 2: LEGS})
    people = [{0: [xy[v]]} for v in range(5)]
    found = triangulate_people(cameras, people, [0], THRESHOLD)
    assert found.frames == [0]
    # exact pixels: the DLT's float64 rounding, some 1e-12 m, far under 1 um
    np.testing.assert_allclose(found.points[0], person, atol=1e-6)
    assert (found.keypoints[0, :, :, 2] > 0).all(), "every view keeps every target"
    legs = [TARGET_NAMES.index(f"{side}_{limb}") for side in "lr" for limb in LEGS]
    truth = _views(cameras, person, {})
    np.testing.assert_allclose(found.keypoints[0][:, legs, :2], truth[:, legs, :2], atol=1e-6)
