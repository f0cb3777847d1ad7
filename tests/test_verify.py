"""detector.geometry.verify: the depth check on exact synthetic frames (a box standing out of a wall; a box with a
hidden arm, where the depth chooses among ICP's results)."""

from dataclasses import replace

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from detector.config import apply_set_options, parse_set_options
from detector.errors import DetectorError
from detector.geometry.icp import chosen_result, refine, turned_poses
from detector.geometry.types import Detection, GeometryConfig, ObjectInfo
from detector.geometry.verify import depth_checked, depth_consistency, pose_consistency, range_image
from detector.infer import geometry_config

K = np.array([[500.0, 0, 160], [0, 500.0, 120], [0, 0, 1]])
SIZE = (0.10, 0.08, 0.05)  # the box, metres: its front face 5 cm in front of a wall 1 m away


def frame_cloud(keep: float, seed: int = 0) -> np.ndarray:
    """(M,3) metres: a 320x240 depth image of the wall with the box's front face, a random ``keep`` share of it."""
    v, u = np.mgrid[0:240, 0:320]
    x, y = (u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1]
    z = np.full(u.shape, 1.0)
    face = (np.abs(x * 0.95) < SIZE[0] / 2) & (np.abs(y * 0.95) < SIZE[1] / 2)
    z[face] = 0.95
    pts = np.stack([x * z, y * z, z], axis=-1).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    return pts[rng.random(len(pts)) < keep]


def box_points(size, n: int = 1000) -> np.ndarray:
    return np.asarray(trimesh.creation.box(extents=size).sample(n, seed=1), np.float64)


def consistency(cloud, size, t, R=np.eye(3)):
    return depth_consistency(range_image(cloud), box_points(size), R[None], np.asarray(t, float)[None], 0.004, 0.008)[0]


@pytest.mark.parametrize("keep", [0.05, 0.3, 1.0])
def test_the_right_pose_is_consistent_at_any_cloud_density(keep):
    cloud = frame_cloud(keep)
    assert consistency(cloud, SIZE, [0, 0, 0.975]) > 0.95
    # the cell follows the points' spacing: every frame point finds a depth no farther than its own
    ri = range_image(cloud)
    z = ri.lookup(cloud)
    assert np.all(np.isfinite(z)) and np.all(z <= cloud[:, 2] + 1e-12)


def test_poses_the_sensor_sees_past_are_not():
    cloud = frame_cloud(0.3)
    right = consistency(cloud, SIZE, [0, 0, 0.975])
    bigger = consistency(cloud, (0.2, 0.16, 0.05), [0, 0, 0.975])  # explains every face point, but the wall shows
    beside = consistency(cloud, SIZE, [0.07, 0, 0.975])  # half of it floats in front of the wall
    assert right > 0.95 and bigger < 0.4 and beside < 0.6
    # hidden behind the wall: no model point is seen or seen past
    assert consistency(cloud, SIZE, [0, 0, 1.2]) == 0.0
    # turned so a 5 cm side faces the camera: its front is 2.5 cm behind the face it claims to be
    turned = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    assert consistency(cloud, SIZE, [0, 0, 0.975], turned) < 0.5


def test_depth_checked_keeps_consistent_scores_and_scales_the_others():
    cloud = frame_cloud(0.3)
    pts = box_points(SIZE)
    objs = ObjectInfo({1: np.zeros((9, 3))}, {1: float(np.linalg.norm(SIZE))}, {1: pts})
    cfg = GeometryConfig(support_distance=0.02, support_floor=0.004, depth_tolerance=2.0, depth_consistent=0.85)
    dets = [Detection(1, 0.8, np.eye(3), np.array(t), 10, np.zeros((9, 3)), np.arange(3))
            for t in ([0, 0, 0.975], [0.07, 0, 0.975])]
    ri = range_image(cloud)
    out = depth_checked(dets, ri, objs, cfg)
    right, beside = (depth_consistency(ri, pts, d.R[None], d.t[None], 0.008, 0.016)[0] for d in dets)
    assert right >= 0.85 and out[0].score == 0.8  # consistent enough: the score stays
    assert beside < 0.85 and out[1].score == pytest.approx(0.8 * beside / 0.85)
    assert np.array_equal(out[1].t, dets[1].t) and out[1].score < 0.6


def test_an_empty_cloud_checks_nothing():
    ri = range_image(np.zeros((0, 3)))
    assert depth_consistency(ri, box_points(SIZE), np.eye(3)[None], np.array([[0, 0, 1.0]]), 0.004, 0.008)[0] == 0


def test_refined_poses_can_be_held_to_a_stricter_consistency():
    cloud = frame_cloud(0.3)
    pts = box_points(SIZE)
    objs = ObjectInfo({1: np.zeros((9, 3))}, {1: float(np.linalg.norm(SIZE))}, {1: pts})
    ri = range_image(cloud)
    # a pose 4 mm beside the box: most of it on the face, an edge strip floating in front of the wall
    det = Detection(1, 0.9, np.eye(3), np.array([0.004, 0, 0.975]), 10, np.zeros((9, 3)), np.arange(3))
    c = depth_consistency(ri, pts, det.R[None], det.t[None], 0.008, 0.016)[0]
    assert 0.85 <= c < 0.97
    loose = GeometryConfig(support_distance=0.02, support_floor=0.004, depth_tolerance=2.0, depth_consistent=0.85)
    strict = GeometryConfig(**{**vars(loose), "depth_consistent_refined": 0.97})
    # unset: the refined poses are checked as the others; set: only the refined ones are held to it
    assert depth_checked([det], ri, objs, loose, refined=True)[0].score == 0.9
    assert depth_checked([det], ri, objs, strict)[0].score == 0.9
    assert depth_checked([det], ri, objs, strict, refined=True)[0].score == pytest.approx(0.9 * c / 0.97)
    right = Detection(1, 0.9, np.eye(3), np.array([0, 0, 0.975]), 10, np.zeros((9, 3)), np.arange(3))
    assert depth_checked([right], ri, objs, strict, refined=True)[0].score == 0.9  # the right pose keeps its score


# A box with an arm along its model +x, the arm hidden behind the box in the frame below.
ARM_BOXES = [((-0.03, -0.06, -0.03), (0.03, 0.06, 0.03)), ((0.03, 0.02, -0.01), (0.09, 0.04, 0.01))]


def arm_frame(R, t, w: int = 320, h: int = 240, f: float = 500.0, wall: float = 1.0):
    """An exact depth image of the armed box at pose (R (3,3), t (3,) metres) in front of a wall ``wall`` metres
    away, by ray casting against the two boxes: (the frame's cloud (w*h,3) metres, (w*h,) bool its object rays)."""
    v, u = np.mgrid[0:h, 0:w]
    d = np.stack([(u + 0.5 - w / 2) / f, (v + 0.5 - h / 2) / f, np.ones(u.shape)], -1).reshape(-1, 3)
    z, hit = np.full(len(d), wall), np.zeros(len(d), bool)
    o, dm = -R.T @ t, d @ R  # the rays in the model frame (z along a ray is its parameter: d has z = 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for lo, hi in ARM_BOXES:
            a, b = (np.array(lo) - o) / dm, (np.array(hi) - o) / dm
            near, far = np.nanmax(np.minimum(a, b), 1), np.nanmin(np.maximum(a, b), 1)
            ok = (near <= far) & (near > 0) & (near < z)
            z[ok], hit[ok] = near[ok], True
    return d * z[:, None], hit


def arm_scene():
    """The armed box posed with its arm away from the camera, 0.85 m off, and its exact frame: R (3,3), t (3,)
    metres, the frame's cloud (M,3) metres and its object rays (M,) bool, a (1000,3) model sample, its diameter in
    metres and its :class:`ObjectInfo` (object 1)."""
    R = Rotation.from_euler("xyz", [-30, -90, 0], degrees=True).as_matrix()  # model +x (the arm) away from the camera
    t = np.array([0.01, 0.0, 0.85])
    cloud, hit = arm_frame(R, t)
    mesh = trimesh.util.concatenate([trimesh.creation.box(bounds=np.array(b)) for b in ARM_BOXES])
    model = np.asarray(mesh.sample(1000, seed=3), np.float64)
    dia = float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]))
    return R, t, cloud, hit, model, dia, ObjectInfo({1: np.zeros((9, 3))}, {1: dia}, {1: model})


def test_the_depth_chooses_among_icp_results_that_fit_alike():
    """The arm points away from the camera, so the frame shows the box alone. Turned half way about its upright
    axis, the pose puts the arm in front of the box: its fit to the box's points is as good, and ICP from that
    start ends there when the fit chooses. The frame's depth sees the box's face behind the arm, so with it
    (``icp_depth_margin``) ICP ends on the right pose from every half-turned start."""
    R, t, cloud, hit, model, dia, objs = arm_scene()
    assert np.all((cloud[hit] - t) @ R[:, 0] < 0.031)  # no point of the arm is in the frame
    frame = range_image(cloud)
    cfg = GeometryConfig(icp=True, icp_points=256, icp_depth_margin=0.1)

    def consistency(oid, Rs, ts):
        return pose_consistency(frame, objs, cfg, oid, Rs, ts)

    def add(r):
        return float(np.linalg.norm(model @ r.R.T + r.t - (model @ R.T + t), axis=1).mean())

    Rk, tk = turned_poses(R, t, objs.half_turns(1))
    assert consistency(1, R[None], t[None])[0] > 0.99
    assert np.all(consistency(1, Rk[1:], tk[1:]) < 0.8)
    fit_alone = []
    for k in (1, 2, 3):
        d = Detection(1, 1.0, Rk[k], tk[k], int(hit.sum()), np.zeros((9, 3)), np.arange(int(hit.sum())),
                      points=np.flatnonzero(hit))
        (by_fit,) = refine([d], cloud, objs, replace(cfg, icp_depth_margin=None), cloud=cloud,
                           consistency_of=consistency)
        (by_depth,) = refine([d], cloud, objs, cfg, cloud=cloud, consistency_of=consistency)
        fit_alone.append(add(by_fit))
        assert by_depth.icp == "accepted" and add(by_depth) < 0.05 * dia
    assert max(fit_alone) > 0.3 * dia  # the fit alone keeps a wrong pose from some start


def test_the_choice_among_icp_results():
    """The best fit among the results within the margin of the most consistent one; the first of equal fits; the
    best fit of all without a consistency or a margin."""
    fits = [0.001, 0.002, 0.003, 0.002]
    assert chosen_result(fits, None, 0.1) == 0
    assert chosen_result(fits, [0.5, 0.95, 1.0, 0.95], None) == 0
    assert chosen_result(fits, [0.5, 0.95, 1.0, 0.95], 0.1) == 1
    assert chosen_result(fits, [0.5, 0.95, 1.0, 0.95], 0.0) == 2
    assert chosen_result(fits, [0.95, 0.95, 1.0, 0.95], 0.1) == 0
    # the first result, from the detection's own pose, unless another fits better by more than ``own`` of its RMS
    near = [0.00104, 0.001, 0.003]
    assert chosen_result(near, None, None) == 1
    assert chosen_result(near, None, None, own=0.05) == 0
    assert chosen_result(near, None, None, own=0.03) == 1
    assert chosen_result(near, [0.5, 1.0, 1.0], 0.1, own=0.05) == 1  # not where the depth ruled the first out


@pytest.mark.parametrize("margin", ["-0.1", "1.5", "x", ".nan"])
def test_a_bad_depth_margin_is_refused(margin):
    """eval's and predict's --set geometry.icp_depth_margin=M: a margin outside [0, 1] or not a number is a
    one-line error; null and a margin within are taken."""
    with pytest.raises(DetectorError, match="icp_depth_margin"):
        geometry_config(0.5, True, apply_set_options(GeometryConfig(), parse_set_options([f"icp_depth_margin={margin}"])))
    for ok, want in (("null", None), ("0.1", 0.1)):
        cfg = apply_set_options(GeometryConfig(), parse_set_options([f"icp_depth_margin={ok}"]))
        assert geometry_config(0.5, True, cfg).icp_depth_margin == want


@pytest.mark.parametrize("own", ["-0.1", "1.5", ".nan"])
def test_a_bad_own_margin_is_refused(own):
    """--set geometry.icp_own_margin=M: a share outside [0, 1] is a one-line error; 0 and 0.1 are taken."""
    with pytest.raises(DetectorError, match="icp_own_margin"):
        geometry_config(0.5, True, apply_set_options(GeometryConfig(), parse_set_options([f"icp_own_margin={own}"])))
    for ok in (0.0, 0.1):
        cfg = apply_set_options(GeometryConfig(), parse_set_options([f"icp_own_margin={ok}"]))
        assert geometry_config(0.5, True, cfg).icp_own_margin == ok



@pytest.mark.parametrize("setting", ["continuation_limit=0", "continuation_limit=-0.03", "continuation_tolerance=0",
                                     "continuation_reach=.nan", "continuation_gap=-0.01"])
def test_a_bad_continuation_setting_is_refused(setting):
    """--set geometry.continuation_*: a limit, tolerance or reach not above 0, or a negative gap, is a one-line
    error (a negative limit would turn scores into NaN, which every threshold then drops silently)."""
    with pytest.raises(DetectorError, match=setting.split("=")[0]):
        geometry_config(0.5, True, apply_set_options(GeometryConfig(), parse_set_options([setting])))
    assert geometry_config(0.5, True, GeometryConfig()).continuation_gap == 0.01

def test_without_the_settings_the_choice_is_the_best_fit():
    """With no depth margin and no own margin the candidate is the first best fit, as before the settings existed;
    a NaN margin or consistency measures nothing and leaves the fits to choose."""
    rng = np.random.default_rng(2)
    for _ in range(200):
        fits = rng.random(rng.integers(1, 12)) * 1e-3
        fits[rng.random(len(fits)) < 0.3] = fits.min()  # ties: the first of them
        assert chosen_result(fits, None, None) == int(np.argmin(fits))
        assert chosen_result(fits, rng.random(len(fits)), None) == int(np.argmin(fits))
        assert chosen_result(fits, rng.random(len(fits)), float("nan")) == int(np.argmin(fits))


def test_the_depth_accepts_a_result_over_the_unrefined_pose_only_beyond_the_margin():
    """A detection already at the true pose: ICP cannot fit its points better, so by the fits it is rejected.
    A frame's depth that finds the results more consistent than the unrefined pose by less than the margin
    changes nothing; by more, the candidate is accepted whatever the fits."""
    R, t, cloud, hit, _, _, objs = arm_scene()
    cfg = GeometryConfig(icp=True, icp_points=256, icp_depth_margin=0.1, icp_half_turns=False)
    d = Detection(1, 1.0, R, t, int(hit.sum()), np.zeros((9, 3)), np.arange(int(hit.sum())),
                  points=np.flatnonzero(hit))

    def flat(gain):  # the unrefined pose (first) at 0.5, every ICP result at 0.5 + gain
        return lambda oid, Rs, ts: np.r_[0.5, np.full(len(Rs) - 1, 0.5 + gain)]

    (alone,) = refine([d], cloud, objs, cfg, cloud=cloud)
    (within,) = refine([d], cloud, objs, cfg, cloud=cloud, consistency_of=flat(0.05))
    (beyond,) = refine([d], cloud, objs, cfg, cloud=cloud, consistency_of=flat(0.2))
    assert alone.icp == "rejected" and within.icp == "rejected" and beyond.icp == "accepted"
    assert np.array_equal(within.R, R) and np.array_equal(within.t, t)
