"""detector.geometry: Kabsch, voting, NMS, ICP on exact synthetic data."""

from dataclasses import replace

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from argen.models.objects import builtin_objects
from detector.geometry.icp import (
    distinct_poses,
    fit_residuals,
    fit_rms,
    icp_refine,
    refine,
    refine_pose,
    refine_poses,
    support_radius,
    surface_support,
    turned_poses,
)
from detector.geometry.kabsch import kabsch
from detector.geometry.types import Detection, GeometryConfig, ObjectInfo, half_turns
from detector.geometry.voting import detect, nms, other_classes, robust_control_points, vote_clusters

BOX = np.array([[x, y, z] for x in (-0.04, 0.04) for y in (-0.03, 0.03) for z in (-0.02, 0.02)] + [[0, 0, 0]])
DIAM = float(np.linalg.norm([0.08, 0.06, 0.04]))


def random_pose(rng):
    return Rotation.random(random_state=rng).as_matrix(), rng.uniform([-0.2, -0.2, 0.5], [0.2, 0.2, 1.0])


def rot_err_deg(Ra, Rb):
    return np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1)))


def test_kabsch_exact_random_poses():
    rng = np.random.default_rng(0)
    for _ in range(50):
        R, t = random_pose(rng)
        src = rng.normal(size=(9, 3)) * 0.05
        Re, te = kabsch(src, src @ R.T + t, rng.uniform(0.1, 1, 9))
        assert np.abs(Re - R).max() < 1e-6 and np.abs(te - t).max() < 1e-6
        assert np.linalg.det(Re) == pytest.approx(1.0)


def test_kabsch_never_reflects():
    src = BOX.copy()
    mirrored = src * [1, 1, -1]  # a reflection has no rotation solution
    R, _ = kabsch(src, mirrored)
    assert np.linalg.det(R) == pytest.approx(1.0) and np.allclose(R @ R.T, np.eye(3), atol=1e-9)


def test_robust_aggregate_ignores_ten_percent_outliers():
    rng = np.random.default_rng(1)
    R, t = random_pose(rng)
    true = BOX @ R.T + t
    votes = true + rng.normal(scale=0.002, size=(200, 9, 3))
    bad = rng.choice(200, 20, replace=False)
    votes[bad] += rng.uniform(-0.3, 0.3, size=(20, 1, 3))  # whole-box outliers, up to 30 cm away
    cps, inl = robust_control_points(votes, np.ones(200), DIAM)
    assert not inl[bad].any() and inl.sum() >= 170
    Re, te = kabsch(BOX, cps)
    assert rot_err_deg(Re, R) < 0.5 and np.linalg.norm(te - t) < 0.001
    # the plain mean is visibly worse: the test can fail
    Rm, tm = kabsch(BOX, votes.mean(0))
    assert np.linalg.norm(tm - t) > 5 * np.linalg.norm(te - t)


def test_vote_clusters_separates_two_instances_20cm_apart():
    rng = np.random.default_rng(2)
    a = np.array([0.0, 0.0, 0.8]) + rng.normal(scale=0.005, size=(100, 3))
    b = np.array([0.2, 0.0, 0.8]) + rng.normal(scale=0.005, size=(80, 3))
    labels, counts = vote_clusters(np.concatenate([a, b]), 0.02)
    assert sorted(counts) == [80, 100]
    assert len(set(labels[:100])) == 1 and len(set(labels[100:])) == 1 and labels[0] != labels[100]


def test_vote_modes_keep_two_side_by_side_instances_apart():
    """Two instances of a 10 cm object 7 cm apart (LC-HF scenes put them side by side), votes scattered 1 cm per
    axis: the vote clouds touch, so touching voxels make one cluster; the density modes make two, each around
    its instance. One instance's votes alone stay one cluster, and too few votes make none."""
    from detector.geometry.voting import vote_modes

    rng = np.random.default_rng(9)
    ca, cb = np.array([0.0, 0.0, 0.8]), np.array([0.07, 0.0, 0.8])
    votes = np.concatenate([ca + rng.normal(scale=0.01, size=(150, 3)), cb + rng.normal(scale=0.01, size=(120, 3))])
    assert len(vote_clusters(votes, 0.02)[1]) == 1
    labels, counts = vote_modes(votes, np.ones(len(votes)), 0.035, 3)
    assert len(counts) == 2
    for lab in range(2):
        mine = votes[labels == lab]
        truth = ca if np.linalg.norm(mine.mean(0) - ca) < np.linalg.norm(mine.mean(0) - cb) else cb
        assert np.linalg.norm(np.median(mine, 0) - truth) < 0.006
    assert (labels[:150] == labels[0]).mean() > 0.9 and (labels[150:] == labels[150]).mean() > 0.9
    assert labels[0] != labels[150]
    one_labels, one = vote_modes(votes[:150], np.ones(150), 0.035, 3)
    assert len(one) == 1 and one[0] >= 140 and (one_labels >= 0).sum() == one[0]
    assert len(vote_modes(votes[:2], np.ones(2), 0.035, 3)[1]) == 0
    # detect's centre votes with mode_radius (a fraction of the diameter): the two instances
    box = BOX * (0.1 / DIAM)
    objs = ObjectInfo({7: box}, {7: 0.1}, {7: box})
    cps = np.broadcast_to(box, (len(votes), 9, 3)) + (votes - box[8])[:, None, :]
    xyz, ids, conf = votes.copy(), np.full(len(votes), 7), np.ones(len(votes))
    for radius, found in ((0.0, 1), (0.35, 2)):
        dets = detect(xyz, ids, conf, cps, objs, GeometryConfig(centre_votes=True, tau=0.1, mode_radius=radius))
        assert len(dets) == found
    assert sorted(round(float(d.control_points[8][0]), 2) for d in dets) == [0.0, 0.07]


def test_detect_two_instances_of_one_object_and_background():
    rng = np.random.default_rng(3)
    objs = ObjectInfo({7: BOX}, {7: DIAM}, {7: BOX})
    poses = [random_pose(rng) for _ in range(2)]
    poses[1] = (poses[1][0], poses[0][1] + [0.2, 0, 0])
    xyz, ids, conf, cps = [], [], [], []
    for (R, t), n in zip(poses, (120, 90)):
        p = t + rng.normal(scale=0.02, size=(n, 3))
        xyz.append(p), ids.append(np.full(n, 7)), conf.append(rng.uniform(0.85, 1, n))
        cps.append(np.broadcast_to(BOX @ R.T + t, (n, 9, 3)) + rng.normal(scale=0.001, size=(n, 9, 3)))
    # background points and low-confidence foreground votes far away must not make detections
    xyz.append(rng.uniform(-1, 1, (200, 3))), ids.append(np.zeros(200, int)), conf.append(np.ones(200))
    cps.append(rng.uniform(-1, 1, (200, 9, 3)))
    xyz.append(rng.uniform(-1, 1, (50, 3))), ids.append(np.full(50, 7)), conf.append(np.full(50, 0.5))
    cps.append(rng.uniform(-1, 1, (50, 9, 3)))
    dets = detect(np.concatenate(xyz), np.concatenate(ids), np.concatenate(conf), np.concatenate(cps), objs,
                  GeometryConfig())
    assert len(dets) == 2
    assert sorted(d.support for d in dets) == [90, 120]
    for d in dets:
        R, t = min(poses, key=lambda p: np.linalg.norm(p[1] - d.t))
        assert rot_err_deg(d.R, R) < 0.3 and np.linalg.norm(d.t - t) < 0.001


def test_nms_keeps_the_most_confident_of_close_detections():
    def det(score, x, oid=1):
        return Detection(oid, score, np.eye(3), np.array([x, 0, 0.8]), 10, np.zeros((9, 3)), np.arange(3))
    kept = nms([det(0.5, 0.0), det(0.9, 0.01), det(0.7, 0.3), det(0.6, 0.0, oid=2)], {1: 0.1, 2: 0.1}, 0.5)
    assert [(d.obj_id, d.score) for d in kept] == [(1, 0.9), (1, 0.7), (2, 0.6)]


def test_nms_across_objects_keeps_one_object_a_place_within_the_smaller_diameter():
    def det(score, x, oid):
        return Detection(oid, score, np.eye(3), np.array([x, 0, 0.8]), 10, np.zeros((9, 3)), np.arange(3))
    diameters = {1: 0.1, 2: 0.3}  # half the smaller: 0.05 m
    dets = [det(0.9, 0.0, 1), det(0.7, 0.04, 2), det(0.8, 0.2, 2), det(0.6, 0.26, 1)]
    kept = nms(dets, diameters, 0.5, across_objects=True)
    # the 0.7 lies 0.04 m from the 0.9 of the other object: one place, the higher score stays; the 0.6 lies 0.06 m
    # from the 0.8 of the other object: apart (half the larger diameter, 0.15 m, would have merged them)
    assert [(d.obj_id, d.score) for d in kept] == [(1, 0.9), (2, 0.8), (1, 0.6)]
    # each object alone: no two of one object within half its diameter (the two of object 2 lie 0.16 m apart)
    assert len(nms(dets, diameters, 0.5)) == 4


def test_nms_across_objects_measures_between_posed_box_centres_not_model_origins():
    """Object 2's mesh has its origin 0.1 m below its box centre (at its base, along its z): posed lying on its side
    (z turned onto x), its box centre stands where object 1's does although the two origins lie 0.1 m apart; and
    two origins 0.02 m apart can belong to boxes that stand apart; and object 2 posed twice at one place, turned
    half way, has origins 0.2 m apart: one detection by its box centres (per object as across objects)."""
    Rz_to_x = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])  # model z -> camera x
    centres = {1: np.zeros(3), 2: np.array([0.0, 0.0, 0.1])}
    diameters = {1: 0.1, 2: 0.3}
    one = Detection(1, 0.9, np.eye(3), np.array([0.1, 0, 0.8]), 10, np.zeros((9, 3)), np.arange(3))
    two = Detection(2, 0.7, Rz_to_x, np.array([0.0, 0, 0.8]), 10, np.zeros((9, 3)), np.arange(3))
    np.testing.assert_allclose(Rz_to_x @ centres[2] + two.t, one.t)
    assert nms([one, two], diameters, 0.5, True, centres) == [one]  # one place
    assert nms([one, two], diameters, 0.5, True) == [one, two]  # by the origins, 0.1 m apart: two places
    near = replace(two, t=np.array([0.12, 0, 0.8]))  # origin 0.02 m from object 1's, box centre 0.12 m away
    assert nms([one, near], diameters, 0.5, True, centres) == [one, near]
    # one object twice at one place, turned half way: origins 0.2 m apart, the same box centre: one detection
    Rz_to_minus_x = np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]])  # model z -> camera -x
    flipped = replace(two, score=0.6, R=Rz_to_minus_x, t=np.array([0.2, 0, 0.8]))
    np.testing.assert_allclose(flipped.R @ centres[2] + flipped.t, two.R @ centres[2] + two.t)
    assert nms([two, flipped], diameters, 0.5, box_centres=centres) == [two]
    assert nms([two, flipped], diameters, 0.5) == [two, flipped]


def test_estimate_outputs_one_object_a_place_unless_told_otherwise(monkeypatch):
    """A stage-1 detection posed as two objects at one place (other_classes): the output keeps the higher score,
    with ICP and without; ``nms_across_objects`` off keeps both."""
    import detector.infer as infer

    box = np.zeros((9, 3))
    dets = [Detection(1, 0.7, np.eye(3), np.array([0.0, 0.0, 0.8]), 10, box, np.arange(3)),
            Detection(2, 0.9, np.eye(3), np.array([0.01, 0.0, 0.8]), 10, box, np.arange(3)),
            Detection(1, 0.8, np.eye(3), np.array([0.3, 0.0, 0.8]), 10, box, np.arange(3))]
    monkeypatch.setattr(infer, "detect", lambda *a, **k: list(dets))
    monkeypatch.setattr(infer, "refine", lambda ds, *a, **k: [replace(d, refined=True) for d in ds])
    preds = type("P", (), {"xyz": np.zeros((3, 3)), "obj_ids": np.ones(3, int), "confidence": np.ones(3),
                           "control_points": np.zeros((3, 9, 3))})()
    objs = ObjectInfo({1: box, 2: box}, {1: 0.1, 2: 0.2}, {1: box, 2: box})
    cfg = GeometryConfig(icp=True, depth_check=False, colour_check=False, part_check=False, continuation_check=False)
    unrefined, refined = infer.estimate(preds, objs, cfg)
    for out in (unrefined, refined):
        assert [(d.obj_id, d.score) for d in out] == [(2, 0.9), (1, 0.8)]
    unrefined, refined = infer.estimate(preds, objs, replace(cfg, nms_across_objects=False))
    assert sorted(d.score for d in refined) == [0.7, 0.8, 0.9]


def visible_surface(obj, R, t, n, rng):
    """Surface points of ``obj`` under (R, t) facing a camera at the origin, camera frame, metres."""
    pts, faces = obj.mesh.sample(n, return_index=True, seed=int(rng.integers(1 << 31)))
    normals = obj.mesh.face_normals[faces] @ R.T
    cam = pts @ R.T + t
    return cam[np.einsum("ij,ij->i", normals, cam) < 0]


def test_icp_improves_a_perturbed_pose():
    rng = np.random.default_rng(4)
    obj = builtin_objects(["drill"])[0]
    model = np.asarray(obj.mesh.sample(2000, seed=1))
    R, t = Rotation.from_euler("xyz", [30, -20, 60], degrees=True).as_matrix(), np.array([0.05, -0.02, 0.7])
    scene = visible_surface(obj, R, t, 4000, rng)
    dR = Rotation.from_rotvec(np.radians(5) * np.array([1.0, 1.0, 0.0]) / np.sqrt(2)).as_matrix()
    R0, t0 = dR @ R, t + np.array([0.01, 0.0, 0.0])
    Ri, ti = icp_refine(scene, model, R0, t0, max_distance=0.1 * obj.diameter)
    before = np.linalg.norm((model @ R0.T + t0) - (model @ R.T + t), axis=1).mean()
    after = np.linalg.norm((model @ Ri.T + ti) - (model @ R.T + t), axis=1).mean()
    assert after < 0.25 * before and after < 0.003
    assert rot_err_deg(Ri, R) < 1.5


def test_refine_uses_member_points():
    rng = np.random.default_rng(5)
    obj = builtin_objects(["drill"])[0]
    model = np.asarray(obj.mesh.sample(1500, seed=2))
    R, t = Rotation.random(random_state=rng).as_matrix(), np.array([0.0, 0.0, 0.8])
    scene = visible_surface(obj, R, t, 3000, rng)
    objs = ObjectInfo({5: obj.control_points}, {5: obj.diameter}, {5: model})
    R0 = Rotation.from_rotvec([0.0, 0.06, 0.0]).as_matrix() @ R
    d = Detection(5, 1.0, R0, t + [0.0, 0.008, 0.0], len(scene), np.zeros((9, 3)), np.arange(len(scene)))
    timings = {}
    (r,) = refine([d], scene, objs, GeometryConfig(icp=True), timings)
    assert r.refined and timings["icp"] > 0
    assert np.linalg.norm(r.t - t) < 0.3 * np.linalg.norm(d.t - t)


def test_refine_carries_few_members_to_the_full_cloud():
    """20 predicted points are too few for ICP; their nearest cloud points (the whole visible surface) are not."""
    rng = np.random.default_rng(6)
    obj = builtin_objects(["drill"])[0]
    model = np.asarray(obj.mesh.sample(1500, seed=3))
    R, t = Rotation.random(random_state=rng).as_matrix(), np.array([0.05, 0.0, 0.7])
    cloud = visible_surface(obj, R, t, 6000, rng)
    background = rng.uniform([-0.5, -0.5, 1.2], [0.5, 0.5, 1.5], (2000, 3))  # far: owned by no member
    keys = cloud[rng.choice(len(cloud), 20, replace=False)]
    xyz = np.concatenate([keys, background[:50]])
    objs = ObjectInfo({5: obj.control_points}, {5: obj.diameter}, {5: model})
    R0 = Rotation.from_rotvec([0.05, 0.0, 0.03]).as_matrix() @ R
    d = Detection(5, 1.0, R0, t + [0.006, 0.0, 0.0], 20, np.zeros((9, 3)), np.arange(20))
    (same,) = refine([d], xyz, objs, GeometryConfig(icp=True))
    assert not same.refined and same.t is d.t
    (r,) = refine([d], xyz, objs, GeometryConfig(icp=True, propagate=0.03), cloud=np.concatenate([cloud, background]))
    assert r.refined and np.linalg.norm(r.t - t) < 0.2 * np.linalg.norm(d.t - t) and rot_err_deg(r.R, R) < 1.0


# ------------------------------------------------------------------ ICP keeps a pose only when it fits better


def resting_scene(name, rng, n_obj=4000, plane_margin=0.02):
    """A built-in object standing on a table seen from 50 degrees elevation, 0.7 m away (camera frame).

    Returns the object, a (1000,3) model sample, R, t, its visible surface points and the visible table points
    within ``plane_margin`` metres of them (what a segment that bleeds onto the support plane holds).
    """
    obj = builtin_objects([name])[0]
    zmin = obj.mesh.bounds[0, 2]
    R = Rotation.from_euler("xz", [-140, 25], degrees=True).as_matrix()  # model +z (up) faces the camera
    t = np.array([0.02, -0.01, 0.7])
    surf = visible_surface(obj, R, t, n_obj, rng)
    g = np.arange(-0.2, 0.2, 0.002)
    table = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    table = np.concatenate([table, np.full((len(table), 1), zmin)], 1)
    lo, hi = obj.mesh.bounds
    under = np.all((table[:, :2] > lo[:2]) & (table[:, :2] < hi[:2]), axis=1)  # under the object: not seen
    table = table[~under] @ R.T + t
    from scipy.spatial import cKDTree

    near = cKDTree(surf).query(table)[0] < plane_margin
    return obj, np.asarray(obj.mesh.sample(1000, seed=7)), R, t, surf, table[near]


def add_error(model, R, t, Re, te):
    return float(np.linalg.norm((model @ Re.T + te) - (model @ R.T + t), axis=1).mean())


def trimmed_fit(objs: ObjectInfo, pts: np.ndarray, R, t, cfg: GeometryConfig | None = None) -> float:
    """The measure that decides whether ICP's pose is kept: the trimmed point-to-plane RMS of ``pts`` (object 1)."""
    cfg = cfg or GeometryConfig()
    tree, normals = objs.surface(1)
    return fit_rms(fit_residuals(pts, tree, normals, R, t, cfg.icp_gate * objs.diameters[1]), cfg.icp_trim)


def test_icp_keeps_exact_poses_within_a_millimetre():
    """On noise-free points at the exact pose ICP may slide within the model sample's resolution; the fit
    test refuses that, so the exact pose stays exact (and never moves more than 1 mm)."""
    rng = np.random.default_rng(11)
    for name in ("drill", "duck", "mug"):
        obj, model, R, t, surf, _ = resting_scene(name, rng)
        objs = ObjectInfo({1: obj.control_points}, {1: obj.diameter}, {1: model})
        d = Detection(1, 1.0, R, t, len(surf), np.zeros((9, 3)), np.arange(len(surf)))
        (r,) = refine([d], surf, objs, GeometryConfig(icp=True))
        assert r.icp in ("accepted", "rejected")
        assert add_error(model, R, t, r.R, r.t) < 0.001
        if r.icp == "accepted":
            assert trimmed_fit(objs, surf, r.R, r.t) < trimmed_fit(objs, surf, R, t)


def test_icp_fixes_a_pose_perturbed_by_5_to_10_degrees_and_1_to_2_cm():
    rng = np.random.default_rng(12)
    for k, name in enumerate(("drill", "duck", "mug", "drill")):
        obj, model, R, t, surf, _ = resting_scene(name, rng)
        objs = ObjectInfo({1: obj.control_points}, {1: obj.diameter}, {1: model})
        axis, shift = rng.normal(size=3), rng.normal(size=3)
        R0 = Rotation.from_rotvec(np.radians(5 + 5 * k / 3) * axis / np.linalg.norm(axis)).as_matrix() @ R
        t0 = t + (0.01 + 0.01 * k / 3) * shift / np.linalg.norm(shift)
        noisy = surf + rng.normal(0, 0.001, surf.shape)
        d = Detection(1, 1.0, R0, t0, len(surf), np.zeros((9, 3)), np.arange(len(surf)))
        (r,) = refine([d], noisy, objs, GeometryConfig(icp=True))
        assert r.icp == "accepted" and r.refined
        assert trimmed_fit(objs, noisy, r.R, r.t) < trimmed_fit(objs, noisy, R0, t0)
        assert add_error(model, R, t, r.R, r.t) < 0.1 * add_error(model, R, t, R0, t0)
        assert add_error(model, R, t, r.R, r.t) < 0.003 and rot_err_deg(r.R, R) < 2.0


def test_icp_refuses_a_pose_the_support_plane_drags_away():
    """The segment holds table points around the object's foot: plain ICP slides the object toward the plane
    (checked), the trimmed fit of the object's own points says that is worse, and the pose is kept."""
    rng = np.random.default_rng(13)
    dragged = 0
    for name in ("drill", "duck", "mug"):
        obj, model, R, t, surf, table = resting_scene(name, rng)
        objs = ObjectInfo({1: obj.control_points}, {1: obj.diameter}, {1: model})
        obj_pts = surf[::4]
        n_table = min(len(table), int(0.3 * len(obj_pts)))
        pts = np.concatenate([obj_pts, table[rng.choice(len(table), n_table, replace=False)]])
        assert 0.15 < n_table / len(pts) < 0.25  # about a fifth of the segment is table
        Ri, ti = icp_refine(pts, model, R, t, 0.2 * obj.diameter, 30, objs.cloud(1))
        dragged += add_error(model, R, t, Ri, ti) > 0.003
        d = Detection(1, 1.0, R, t, len(pts), np.zeros((9, 3)), np.arange(len(pts)))
        (r,) = refine([d], pts, objs, GeometryConfig(icp=True))
        assert r.icp == "rejected" and not r.refined
        assert np.array_equal(r.R, R) and np.array_equal(r.t, t)
        _, _, ok, (before, after) = refine_pose(pts, 1, R, t, objs, GeometryConfig(icp=True))
        assert not ok and after >= before  # ICP's best pose fits the object's points worse
    assert dragged >= 2  # the plane really pulls plain ICP away


def test_icp_points_leave_out_background_and_other_detections():
    """A cloud point joins a detection only when all its nearest predicted points are that detection's."""
    from detector.geometry.icp import nearest_owner, owned_points

    xyz = np.array([[0.0, 0, 1], [0.01, 0, 1], [0.02, 0, 1],  # detection A
                    [0.03, 0, 1],  # background
                    [0.06, 0, 1], [0.07, 0, 1]])  # detection B
    cloud = np.array([[0.005, 0, 1], [0.024, 0, 1], [0.045, 0, 1], [0.065, 0, 1], [0.5, 0, 1]])
    owners = nearest_owner(xyz, cloud, 0.012, k=2)
    a = owned_points(owners, np.array([0, 1, 2]), len(xyz))
    b = owned_points(owners, np.array([4, 5]), len(xyz))
    assert a.tolist() == [True, False, False, False, False]  # 0.024 is next to the background point
    assert b.tolist() == [False, False, False, True, False]  # 0.045 has background within reach; 0.5 has no owner
    assert not np.any(a & b)


def test_report_counts_icp_decisions():
    from detector.geometry.icp import icp_counts

    d = Detection(1, 1.0, np.eye(3), np.zeros(3), 3, np.zeros((9, 3)), np.arange(3))
    from dataclasses import replace

    dets = [replace(d, icp="accepted"), replace(d, icp="rejected"), replace(d, icp="rejected"), replace(d, icp="skipped")]
    assert icp_counts(dets) == {"accepted": 1, "rejected": 2, "skipped": 1}


def test_surface_support_is_high_for_the_right_pose_only():
    from detector.geometry.icp import surface_support

    rng = np.random.default_rng(21)
    obj, model, R, t, surf, table = resting_scene("drill", rng)
    objs = ObjectInfo({1: obj.control_points}, {1: obj.diameter}, {1: model})
    tree, normals = objs.surface(1)
    d = 0.02 * obj.diameter
    assert surface_support(surf, tree, normals, R, t, d) > 0.9
    R_off = Rotation.from_rotvec([0.0, 0.0, np.radians(30)]).as_matrix() @ R
    assert surface_support(surf, tree, normals, R_off, t, d) < 0.6
    assert surface_support(table, tree, normals, R, t, d) < 0.3  # the table is not the drill
    assert surface_support(np.zeros((0, 3)), tree, normals, R, t, d) == 0.0


def test_support_floor_keeps_right_poses_of_small_objects_under_sensor_noise():
    """With the depth error of a Kinect v1 near 1 m (a median 2.4 mm off the surface), 2 % of a 12 cm object's
    diameter (2.5 mm) explains only about half of its points under the right pose, below the score threshold; a
    floor of 4 mm explains most of them, and a pose turned by 30 degrees still scores low."""
    from detector.geometry.icp import support_radius, surface_support

    rng = np.random.default_rng(22)
    obj, model, R, t, surf, _ = resting_scene("duck", rng)
    objs = ObjectInfo({1: obj.control_points}, {1: obj.diameter}, {1: model})
    tree, normals = objs.surface(1)
    # noise off the surface as a Kinect v1's near 1 m: its depth lies a median 2.4 mm from the model surface
    n_cam = normals[tree.query((surf - t) @ R)[1]] @ R.T
    noisy = surf + n_cam * rng.normal(0.0, 0.0036, (len(surf), 1))
    assert np.median(np.abs(np.einsum("ij,ij->i", noisy - surf, n_cam))) == pytest.approx(0.0024, abs=0.0003)
    cfg = GeometryConfig()
    assert support_radius(cfg.support_distance, 0.0, obj.diameter) == pytest.approx(0.02 * obj.diameter)
    assert support_radius(cfg.support_distance, cfg.support_floor, 0.5) == pytest.approx(0.01)  # large: the fraction
    without = surface_support(noisy, tree, normals, R, t, support_radius(cfg.support_distance, 0.0, obj.diameter))
    floor = support_radius(cfg.support_distance, cfg.support_floor, obj.diameter)
    assert floor == cfg.support_floor
    right = surface_support(noisy, tree, normals, R, t, floor)
    R_off = Rotation.from_rotvec([0.0, 0.0, np.radians(30)]).as_matrix() @ R
    wrong = surface_support(noisy, tree, normals, R_off, t, floor)
    assert without < 0.6 < 0.7 < right
    assert wrong < 0.5


def test_icp_starts_from_alternatives_and_keeps_the_best_fit():
    """A wrong-way first pose (turned 120 degrees) is a local minimum ICP cannot leave; with a near-right
    alternative among the starting poses, refine keeps the alternative's ICP result, since it fits better."""
    rng = np.random.default_rng(21)
    for name in ("drill", "duck"):
        obj, model, R, t, surf, _ = resting_scene(name, rng)
        objs = ObjectInfo({1: obj.control_points}, {1: obj.diameter}, {1: model})
        noisy = surf + rng.normal(0, 0.001, surf.shape)
        wrong = Rotation.from_rotvec(np.radians(120) * np.array([0.0, 0.6, 0.8])).as_matrix() @ R
        near = Rotation.from_rotvec(np.radians(8) * np.array([1.0, 0.0, 0.0])).as_matrix() @ R
        bad = Rotation.from_rotvec(np.radians(90) * np.array([1.0, 0.0, 0.0])).as_matrix() @ R
        d = Detection(1, 1.0, wrong, t, len(surf), np.zeros((9, 3)), np.arange(len(surf)),
                      alternatives=[(bad, t), (near, t + 0.01)])
        (one,), (two,), (three,) = (refine([d], noisy, objs, GeometryConfig(icp=True, icp_starts=n,
                                                                         icp_half_turns=False)) for n in (1, 2, 3))
        assert add_error(model, R, t, one.R, one.t) > 0.1 * obj.diameter  # ICP from the wrong pose stays wrong
        assert add_error(model, R, t, two.R, two.t) > 0.1 * obj.diameter  # the near pose is the third start
        assert three.icp == "accepted"
        assert trimmed_fit(objs, noisy, three.R, three.t) < trimmed_fit(objs, noisy, wrong, t)
        assert add_error(model, R, t, three.R, three.t) < 0.003


def test_half_turns_are_turns_about_the_model_axes_that_keep_the_object_in_place():
    """Each of the three transforms is a proper rotation by 180 degrees about one of the model's x, y and z axes
    that maps the centroid of the model points onto itself: the turned object stays where it was, wherever the
    mesh's origin lies."""
    obj = builtin_objects(["duck"])[0]
    pts = np.asarray(obj.mesh.sample(3000, seed=3))
    for model in (pts, pts + [0.3, -0.2, 0.05]):  # the same shape with its origin elsewhere
        c = model.mean(axis=0)
        turns = half_turns(model)
        assert turns.shape == (3, 4, 4)
        for k, T in enumerate(turns):
            F = T[:3, :3]
            np.testing.assert_allclose(F @ F.T, np.eye(3), atol=1e-12)
            assert np.linalg.det(F) == pytest.approx(1.0)
            assert np.trace(F) == pytest.approx(-1.0)  # 1 + 2 cos(180 degrees)
            np.testing.assert_allclose(F[:, k], np.eye(3)[k])  # the axis of the turn: model axis k
            turned = model @ F.T + T[:3, 3]
            np.testing.assert_allclose(turned.mean(axis=0), c, atol=1e-12)
            assert np.abs(turned - model).max() > 0.5 * obj.diameter  # a turn, not the identity


def test_icp_also_starts_from_half_turns_and_leaves_the_other_side():
    """A pose that shows the object's other side (turned half way about its upright axis) is a local
    minimum that ICP from that pose alone cannot leave; with ``icp_half_turns`` ICP also starts from the pose turned
    back, which fits better, and ends on the right pose."""
    rng = np.random.default_rng(5)
    for name in ("duck", "drill"):
        obj, model, R, t, surf, _ = resting_scene(name, rng)
        objs = ObjectInfo({1: obj.control_points}, {1: obj.diameter}, {1: model})
        noisy = surf + rng.normal(0, 0.001, surf.shape)
        Rk, tk = turned_poses(R, t, objs.half_turns(1)[2:])  # about the model's z: its upright
        d = Detection(1, 1.0, Rk[1], tk[1], len(surf), np.zeros((9, 3)), np.arange(len(surf)))
        assert add_error(model, R, t, d.R, d.t) > 0.2 * obj.diameter
        (alone,) = refine([d], noisy, objs, GeometryConfig(icp=True, icp_half_turns=False))
        (turned,) = refine([d], noisy, objs, GeometryConfig(icp=True))
        assert add_error(model, R, t, alone.R, alone.t) > 0.1 * obj.diameter
        assert turned.icp == "accepted"
        assert add_error(model, R, t, turned.R, turned.t) < 0.003


def test_icp_keeps_the_way_round_of_an_object_whose_turns_fit_alike():
    """A box turned half way about any of its axes is the same shape: from its half-turned starts ICP ends on a fit
    as good as from its own pose, and the sensor's noise makes one of them a little better by chance. With
    ``icp_own_margin`` the result from the detection's own pose stays unless another fits clearly better: over 12
    views (random poses, 2 mm noise, the detection 3 degrees and 3 mm off) the box keeps its way round in at least
    10, and more often than the fit alone keeps it."""
    mesh = trimesh.creation.box(extents=(0.10, 0.06, 0.04))
    model = np.asarray(mesh.sample(1000, seed=3), np.float64)
    objs = ObjectInfo({1: np.zeros((9, 3))}, {1: float(np.linalg.norm([0.10, 0.06, 0.04]))}, {1: model})
    turned = {0.0: 0, 0.05: 0}
    for seed in range(12):
        rng = np.random.default_rng(seed)
        R, t = Rotation.random(random_state=seed).as_matrix(), np.array([0.0, 0.0, 0.8])
        pts, face = trimesh.sample.sample_surface(mesh, 3000, seed=seed)
        x = pts @ R.T + t
        seen = np.einsum("ij,ij->i", mesh.face_normals[face] @ R.T, x) < 0  # faces towards the camera
        x = x[seen] + rng.normal(0, 0.002, (int(seen.sum()), 3))
        R0 = Rotation.from_rotvec(rng.normal(0, 0.05, 3)).as_matrix() @ R
        d = Detection(1, 1.0, R0, t + rng.normal(0, 0.003, 3), len(x), np.zeros((9, 3)), np.arange(len(x)))
        for own in turned:
            (r,) = refine([d], x, objs, GeometryConfig(icp=True, icp_points=256, icp_own_margin=own))
            assert r.icp == "accepted"
            turned[own] += np.trace(r.R.T @ R) < 1  # more than 90 degrees from the true pose (1 + 2 cos)
    assert turned[0.05] <= 2 and turned[0.05] < turned[0.0]


def test_icp_gives_the_same_pose_every_time():
    """The same points and starts give bit for bit the same pose: open3d's threaded sums inside ICP added in a varying
    order, and about one call in ten ended elsewhere (a few hundredths of a millimetre, or another start's fit)."""
    rng = np.random.default_rng(5)
    obj, model, R, t, surf, table = resting_scene("duck", rng)
    objs = ObjectInfo({1: obj.control_points}, {1: obj.diameter}, {1: model})
    pts = np.concatenate([surf, table]) + rng.normal(0, 0.002, (len(surf) + len(table), 3))
    pts = pts[rng.choice(len(pts), 256, replace=False)]
    alts = [(Rotation.from_rotvec(rng.normal(0, 0.4, 3)).as_matrix() @ R, t + rng.normal(0, 0.01, 3)) for _ in range(7)]
    R0 = Rotation.from_rotvec([0.3, 0.2, 0.1]).as_matrix() @ R
    cfg = GeometryConfig(icp=True, icp_iterations=20)
    first = refine_pose(pts, 1, R0, t + 0.01, objs, cfg, alts)
    for _ in range(40):
        again = refine_pose(pts, 1, R0, t + 0.01, objs, cfg, alts)
        np.testing.assert_array_equal(again[0], first[0])
        np.testing.assert_array_equal(again[1], first[1])
        assert again[3] == first[3]


def test_icp_of_several_detections_at_once_is_each_alone():
    """refine_poses runs the ICP starts of every detection of a frame in one thread pool: each detection's result
    is bit for bit what refine_pose gives it alone (the results go back to their own detections)."""
    rng = np.random.default_rng(9)
    cps, dias, models, jobs = {}, {}, {}, []
    for i, name in enumerate(("duck", "drill", "mug"), start=1):
        obj, model, R, t, surf, table = resting_scene(name, rng)
        cps[i], dias[i], models[i] = obj.control_points, obj.diameter, model
        pts = np.concatenate([surf, table]) + rng.normal(0, 0.002, (len(surf) + len(table), 3))
        pts = pts[rng.choice(len(pts), 256, replace=False)]
        alts = [(Rotation.from_rotvec(rng.normal(0, 0.4, 3)).as_matrix() @ R, t + rng.normal(0, 0.01, 3))
                for _ in range(3)]
        jobs.append((pts, i, Rotation.from_rotvec(rng.normal(0, 0.2, 3)).as_matrix() @ R, t + rng.normal(0, 0.01, 3),
                     alts))
    objs = ObjectInfo(cps, dias, models)
    cfg = GeometryConfig(icp=True, icp_iterations=20)
    together = refine_poses(jobs, objs, cfg)
    assert len(together) == 3
    for job, got in zip(jobs, together):
        alone = refine_pose(*job[:4], objs, cfg, job[4])
        np.testing.assert_array_equal(got[0], alone[0])
        np.testing.assert_array_equal(got[1], alone[1])
        assert got[2:] == alone[2:]
    assert sum(ok for _, _, ok, _ in together) >= 2  # ICP moved the perturbed poses: not a comparison of inputs


def test_near_copies_of_a_start_are_refined_once():
    """ICP from two starts 2 degrees and 1 mm apart ends in the same fit: only the first of them is kept; a start
    turned 10 degrees, or moved 5 % of the diameter, is another start. The order stays."""
    dia = 0.1
    R0 = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    t0 = np.array([0.01, 0.02, 0.7])
    turn = lambda deg: Rotation.from_rotvec(np.radians(deg) * np.array([0.0, 0.6, 0.8])).as_matrix() @ R0  # noqa: E731
    poses = [(R0, t0), (turn(2), t0 + [0.001, 0, 0]), (turn(10), t0), (R0, t0 + [0, 0, 0.05 * dia]), (R0, t0)]
    kept = distinct_poses(poses, dia)
    assert len(kept) == 3
    for (Ra, ta), k in zip(kept, (0, 2, 3)):
        np.testing.assert_array_equal(Ra, poses[k][0])
        np.testing.assert_array_equal(ta, poses[k][1])
    assert len(distinct_poses(poses, 10 * dia)) == 2  # 5 mm is a near copy for a 1 m object


def test_icp_keeps_a_right_pose_unless_it_fits_clearly_better():
    """ICP on noisy points always finds some pose that fits them a little better than the right one; on a smooth
    surface (here a sphere, which every rotation about its centre fits as well) that pose may lie anywhere along
    the surface. A gain within the sensor's and the model sampling's own noise is not taken (``icp_min_gain``),
    while a pose that is really off (1 cm) is still corrected."""
    rng = np.random.default_rng(3)
    v = rng.normal(size=(3000, 3))
    model = 0.05 * v / np.linalg.norm(v, axis=1, keepdims=True)  # a sphere of 10 cm diameter, centred at 0
    R, t = np.eye(3), np.array([0.0, 0.0, 0.8])
    w = rng.normal(size=(400, 3))
    cap = 0.05 * w / np.linalg.norm(w, axis=1, keepdims=True)
    scene = cap[cap[:, 2] < -0.01] @ R.T + t  # the part facing the camera
    scene = scene + rng.normal(0, 0.0005, scene.shape)
    objs = ObjectInfo({1: np.zeros((9, 3))}, {1: 0.1}, {1: model})
    d = Detection(1, 1.0, R, t, len(scene), np.zeros((9, 3)), np.arange(len(scene)))
    (slid,) = refine([d], scene, objs, GeometryConfig(icp=True, icp_min_gain=0.0))
    _, _, ok, (before, after) = refine_pose(scene, 1, R, t, objs, GeometryConfig(icp=True, icp_min_gain=0.0))
    assert slid.icp == "accepted" and ok and before - after < 0.001 * 0.1  # a gain below 0.1 mm
    (kept,) = refine([d], scene, objs, GeometryConfig(icp=True))
    assert kept.icp == "rejected" and np.array_equal(kept.R, R) and np.array_equal(kept.t, t)
    off = replace(d, t=t + [0.01, 0.0, 0.0])
    (fixed,) = refine([off], scene, objs, GeometryConfig(icp=True))
    assert fixed.icp == "accepted" and np.linalg.norm(fixed.t - t) < 0.002


def test_icp_on_a_spread_subset_of_many_points_still_fixes_the_pose():
    """icp_points caps the points ICP and its acceptance test use (a stage 2 pooling several crop samples hands
    over hundreds): the capped ICP still fixes a 6 degree / 1.5 cm error, and the score after ICP is the support
    of all the detection's points."""
    rng = np.random.default_rng(22)
    obj, model, R, t, surf, _ = resting_scene("drill", rng)
    objs = ObjectInfo({1: obj.control_points}, {1: obj.diameter}, {1: model})
    noisy = surf + rng.normal(0, 0.001, surf.shape)
    assert len(noisy) > 1000
    R0 = Rotation.from_rotvec(np.radians(6) * np.array([0.6, 0.0, 0.8])).as_matrix() @ R
    d = Detection(1, 1.0, R0, t + [0.015, 0.0, 0.0], 10, np.zeros((9, 3)), np.arange(3),
                  points=np.arange(len(noisy)))
    cfg = GeometryConfig(icp=True, icp_points=150)
    (r,) = refine([d], noisy[:3], objs, cfg, cloud=noisy)
    assert r.icp == "accepted" and add_error(model, R, t, r.R, r.t) < 0.003
    tree, normals = objs.surface(1)
    dist = support_radius(cfg.support_distance, cfg.support_floor, obj.diameter)
    assert r.score == surface_support(noisy, tree, normals, r.R, r.t, dist)
    spread = noisy[np.linspace(0, len(noisy) - 1, 150).round().astype(np.int64)]  # ICP and its test ran on these
    R1, t1, ok, _ = refine_pose(spread, 1, d.R, d.t, objs, cfg)
    assert ok and np.allclose(R1, r.R, atol=1e-9) and np.allclose(t1, r.t, atol=1e-12)
    (full,) = refine([d], noisy[:3], objs, GeometryConfig(icp=True), cloud=noisy)
    assert add_error(model, R, t, full.R, full.t) < 0.003


def test_other_classes_adds_each_likely_object_at_the_same_centre():
    box2 = BOX * 1.5
    objs = ObjectInfo({7: BOX, 8: box2, 9: BOX}, {7: DIAM, 8: 1.5 * DIAM, 9: DIAM}, {7: BOX, 8: box2, 9: BOX})
    t = np.array([0.1, 0.0, 0.8])
    d = Detection(7, 0.9, np.eye(3), t, 4, BOX + t, np.arange(4))
    probs = np.array([[0.1, 0.6, 0.3, 0.0]] * 2 + [[0.0, 0.8, 0.1, 0.1]] * 2)  # mean: bg .05, 7 .7, 8 .2, 9 .05
    out = other_classes([d], probs, [7, 8, 9], objs, 0.1, 0.5)
    assert [k.obj_id for k in out] == [7, 8]
    assert np.allclose(out[1].control_points[8], d.control_points[8])  # the same box centre
    assert np.allclose(out[1].control_points, box2 + out[1].t) and out[1].score == pytest.approx(0.9 * 0.2)
    assert [k.obj_id for k in other_classes([d], probs, [7, 8, 9], objs, 0.05, 0.5)] == [7, 8, 9]
    assert [k.obj_id for k in other_classes([d], probs, [7, 8, 9], objs, 1.5, 0.5)] == [7]
    # an object already detected there is not added again; one detected elsewhere is
    near = Detection(8, 0.5, np.eye(3), out[1].t + 0.01, 4, box2 + out[1].t, np.arange(4))
    far = replace(near, t=out[1].t + 0.3)
    assert [k.obj_id for k in other_classes([d, near], probs, [7, 8, 9], objs, 0.1, 0.5)] == [7, 8]
    assert [k.obj_id for k in other_classes([d, far], probs, [7, 8, 9], objs, 0.1, 0.5)] == [7, 8, 8]
