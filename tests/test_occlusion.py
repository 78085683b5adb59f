"""People who overlap the followed person in a view (``pipelines.prepare.people.occlusion``), on hand-placed people and
cameras whose figures can be worked out by hand."""

from types import SimpleNamespace

import cv2
import numpy as np

from pipelines.body.silhouettes import distance_to_mask
from pipelines.datasets.camera import Camera
from pipelines.datasets.keypoints import TARGET_NAMES
from pipelines.prepare.people.occlusion import (
    body_region,
    hidden_region,
    leave_out_overlapped,
    overlap_share,
    person_mask,
    without_others,
)
from pipelines.synthetic.scene import look_at

#: a person standing at the origin, facing -y, z up (metres)
STANDING = {
    "pelvis": (0, 0, 1.0),
    "l_hip": (0.1, 0, 0.95),
    "r_hip": (-0.1, 0, 0.95),
    "l_knee": (0.1, 0, 0.5),
    "r_knee": (-0.1, 0, 0.5),
    "l_ankle": (0.1, 0, 0.08),
    "r_ankle": (-0.1, 0, 0.08),
    "l_foot": (0.1, -0.1, 0.02),
    "r_foot": (-0.1, -0.1, 0.02),
    "neck": (0, 0, 1.5),
    "head": (0, 0, 1.7),
    "l_shoulder": (0.2, 0, 1.45),
    "r_shoulder": (-0.2, 0, 1.45),
    "l_elbow": (0.25, 0, 1.2),
    "r_elbow": (-0.25, 0, 1.2),
    "l_wrist": (0.25, 0, 0.95),
    "r_wrist": (-0.25, 0, 0.95),
}


def _person(offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    return np.array([STANDING[name] for name in TARGET_NAMES], np.float64) + np.asarray(offset)


def _camera(name: str, centre, target=(0.0, 0.0, 1.0)) -> Camera:
    K = np.array([[1000.0, 0, 500], [0, 1000.0, 500], [0, 0, 1]])
    return Camera(name, K, np.zeros(5), look_at(np.asarray(centre, float), np.asarray(target, float)), 1000, 1000)


def test_a_bone_is_a_capsule_of_its_radius_at_its_depth():
    # only the left forearm: from (0.25, 0, 1.2) to (0.25, 0, 0.95), 4 m in front of the camera, radius 0.05 m:
    # 2 r f / z = 25 px wide and 0.25 f / z = 62.5 px long, with round caps: 25 x 62.5 + pi 12.5^2 = 2,053 px
    points = np.full((len(TARGET_NAMES), 3), np.nan)
    for name in ("l_elbow", "l_wrist"):
        points[TARGET_NAMES.index(name)] = STANDING[name]
    region = body_region(_camera("front", (0, -4, 1.0), (0, 0, 1.0)), points)
    rows, cols = np.nonzero(region)
    # a 25-px band gains or loses up to a pixel along each edge (2 of 25 px, 8 %), its caps a pixel around
    assert abs(region.sum() - 2053) < 0.08 * 2053
    assert abs((cols.max() - cols.min() + 1) - 25) <= 2 and abs((rows.max() - rows.min() + 1) - (62.5 + 25)) <= 2


def test_the_share_covered_by_somebody_in_front_or_behind():
    camera = _camera("front", (0, -5, 1.0))
    person = _person()
    # the same body 2 m nearer the camera covers the person's (it projects 5/3 as large about the image centre) but
    # for the tips of the feet, whose bones point at the camera and so do not grow like the rest (1.5 % measured)
    assert overlap_share(camera, person, [_person((0, -2, 0))]) > 0.95
    # 2 m behind, it projects 5/7 as large about the image centre, inside the person: the share is its own area
    behind = body_region(camera, _person((0, 2, 0)))
    expected = (behind & body_region(camera, person)).sum() / body_region(camera, person).sum()
    assert overlap_share(camera, person, [_person((0, 2, 0))]) == expected and 0.3 < expected < 0.7
    assert overlap_share(camera, person, [_person((2, -2, 0))]) == 0.0  # in front, 2 m aside
    assert overlap_share(camera, person, []) == 0.0


def test_the_mask_loses_the_others_outside_the_body_only():
    camera = _camera("front", (0, -5, 1.0))
    body = body_region(camera, _person())
    other = body_region(camera, _person((0.6, 0, 0)))  # beside the person, overlapping an arm's width
    mask = body | other
    cut = without_others(mask, body, camera, [_person((0.6, 0, 0))])
    assert (cut == body).all() and (body & other).any()  # what the body covers stays, whoever else is there
    assert (without_others(mask, body, camera, []) == mask).all()


def test_what_the_mask_holds_beside_somebody_elses_capsules_is_theirs():
    # real people are wider than their capsules (hair, clothes): the segmenter's one mask holds both people widened by
    # a few pixels; each pixel outside the body goes to whoever's region is nearer
    camera = _camera("front", (0, -5, 1.0))
    body = body_region(camera, _person())
    other = body_region(camera, _person((0.6, 0, 0)))
    ring = lambda region, px: cv2.dilate(region.astype(np.uint8), np.ones((2 * px + 1,) * 2, np.uint8)) > 0  # noqa: E731
    clothes, theirs = ring(body, 3) & ~body, ring(other, 8) & ~other & ~ring(body, 8)
    cut = without_others(body | clothes | other | theirs, body, camera, [_person((0.6, 0, 0))])
    assert theirs.sum() > 1000 and not (cut & theirs).any()  # all of their ring, which the capsules alone left
    # the person's own clothes stay where they are nearer the person than the other's region (every pixel of the
    # 3-px ring except where the two regions touch: the pixels there are within 3 px of both)
    far = clothes & (distance_to_mask(other) > 3)
    assert far.sum() > 1000 and (cut & far).sum() == far.sum()


def test_the_boxed_distances_give_the_whole_images_owners():
    # the reference: both distance fields over the whole image; the function's boxes must give the same pixels,
    # bit for bit (distance_to_mask is exact in its integer squared distances), with the other person beside,
    # behind, touching or far, and a mask reaching 60 px past the body
    camera = _camera("front", (0, -5, 1.0))
    body = body_region(camera, _person())
    mask = cv2.dilate(body.astype(np.uint8), np.ones((121, 121), np.uint8)) > 0
    # (1.0-1.1 m aside: the other's arm starts 20-40 px past the mask, nearer its edge than the body is)
    for offset in ((0.6, 0, 0), (0.3, 1.0, 0), (-0.5, -0.5, 0.2), (2.0, 0, 0), (1.0, 0, 0), (1.1, 0, 0)):
        covered = body_region(camera, _person(offset))
        reference = mask & ~((distance_to_mask(covered) < distance_to_mask(body)) & ~body)
        assert (without_others(mask, body, camera, [_person(offset)]) == reference).all(), offset


def test_somebody_in_front_makes_the_owner_unknown_and_somebody_behind_does_not():
    camera = _camera("front", (0, -5, 1.0))
    person, body = _person(), body_region(camera, _person())
    near = np.ones_like(body)
    in_front, behind = _person((0.4, -1, 0)), _person((0.4, 1, 0))  # 40 cm aside, 1 m nearer or farther
    hidden = hidden_region(camera, person, [in_front], near)
    assert (hidden == body_region(camera, in_front)).all() and (hidden & body).any()
    assert not hidden_region(camera, person, [behind], near).any()
    assert not hidden_region(camera, person, [in_front], np.zeros_like(near)).any()  # only within ``near``
    # the segmenter's one mask for both: the person keeps their own pixels that nobody hides, the one in front is
    # either unknown (near the person) or cut (farther than the neighbourhood, 4 % of the height = 40 px)
    raw = body | body_region(camera, in_front)
    mask, unknown = person_mask(raw, body, camera, person, [in_front])
    assert not (mask & unknown).any() and (mask | unknown | ~raw).sum() < raw.size
    assert (mask == (body & ~unknown)).all() and unknown.any()
    mask, unknown = person_mask(body | body_region(camera, behind), body, camera, person, [behind])
    assert (mask == body).all() and not unknown.any()


def test_a_limb_behind_somebody_who_stands_behind_the_person_is_hidden_by_them():
    # the other stands 40 cm behind the person and 45 cm aside, and the person's left leg reaches back past them:
    # where the other's capsules cover the part of the leg behind them the owner is unknown, not elsewhere
    camera = _camera("front", (0, -5, 1.0))
    person = _person()
    person[TARGET_NAMES.index("l_knee")] = (0.35, 0.6, 0.5)
    person[TARGET_NAMES.index("l_ankle")] = (0.5, 0.9, 0.2)
    person[TARGET_NAMES.index("l_foot")] = (0.5, 0.8, 0.15)
    other = _person((0.45, 0.4, 0))
    shin = np.full_like(person, np.nan)
    for name in ("l_knee", "l_ankle", "l_foot"):  # 60-90 cm behind the person's centre, behind the other (40 cm)
        shin[TARGET_NAMES.index(name)] = person[TARGET_NAMES.index(name)]
    theirs = body_region(camera, other)
    shin_behind = body_region(camera, shin) & theirs & ~body_region(camera, _person())
    hidden = hidden_region(camera, person, [other], np.ones_like(theirs))
    # (not all of it: each quarter of a bone holds one depth, and the thigh's quarter before the knee, at 5.375 m,
    # in front of the other's 5.4 m, still covers the knee's end of the shin: 45 of 1,090 pixels)
    assert shin_behind.sum() > 500 and (hidden & shin_behind).sum() >= 0.9 * shin_behind.sum()
    # above the hips (image rows above the centre, 1 m high at the person) the other stands behind the person's
    # torso and arms: those pixels stay the person's
    upper = body_region(camera, _person()) & theirs & (np.arange(1000)[:, None] < 500)
    assert upper.sum() > 100 and not (hidden & upper).any()  # 480 pixels: the other's shoulder and arm


def test_overlapped_views_are_left_out_with_their_keypoints():
    cameras = [_camera("front", (0, -5, 1.0)), _camera("side", (-5, 0, 1.0))]
    person, other = _person(), _person((0, 2, 0))  # behind the person for the front camera, 2 m aside for the side
    found = SimpleNamespace(
        frames=[7, 8],
        points=np.stack([person, person]),
        used=np.ones((2, 2), bool),
        keypoints=np.ones((2, 2, len(TARGET_NAMES), 3)),
        others={7: [other]},
        view_notes=[{"overlapped": 0}, {"overlapped": 0}],
    )
    counts = leave_out_overlapped(cameras, found)
    assert counts == [1, 0] and [n["overlapped"] for n in found.view_notes] == [1, 0]
    assert found.used.tolist() == [[False, True], [True, True]]
    assert (found.keypoints[0, 0, :, 2] == 0).all() and (found.keypoints[found.used][..., 2] == 1).all()
