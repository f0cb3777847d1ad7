"""ADD / ADD-S, thresholds, greedy matching and F1."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from argen.models.objects import builtin_objects, load_objects
from detector.evaluation.metrics import (
    accuracy,
    accuracy_curve,
    add,
    adds,
    greedy_match,
    match_frame,
    pose_error,
    prf,
    top_k,
)

LM = Path(__file__).resolve().parents[2] / "shared/data/lm"


def symmetric_objects():
    objs = [builtin_objects(["eggcrate"])[0]]
    if (LM / "models").is_dir():
        objs += load_objects(LM / "models", ["eggbox"])
    return objs


def test_add_zero_for_true_pose_and_equal_to_offset_for_translation():
    obj = builtin_objects(["drill"])[0]
    pts = np.asarray(obj.mesh.sample(500, seed=0))
    R, t = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix(), np.array([0.1, 0, 0.8])
    assert add(pts, R, t, R, t) == 0.0 and adds(pts, R, t, R, t) == 0.0
    assert add(pts, R, t, R, t + [0, 0.01, 0]) == pytest.approx(0.01)


@pytest.mark.parametrize("obj", symmetric_objects(), ids=lambda o: o.name)
def test_adds_zero_under_a_symmetry_while_add_is_not(obj):
    assert obj.symmetric and obj.info.symmetries_discrete
    pts = np.asarray(obj.mesh.vertices)  # the vertex set maps onto itself under an exact symmetry
    S = np.asarray(obj.info.symmetries_discrete[0])
    R, t = Rotation.from_euler("xyz", [40, -10, 70], degrees=True).as_matrix(), np.array([0.0, 0.05, 0.7])
    R2, t2 = R @ S[:3, :3], R @ S[:3, 3] + t  # same appearance, different pose
    tol = 1e-6 if obj.source == "builtin" else 0.01 * obj.diameter  # a scanned eggbox is only nearly symmetric
    assert adds(pts, R, t, R2, t2) < tol
    assert add(pts, R, t, R2, t2) > 0.2 * obj.diameter
    assert pose_error(pts, True, R, t, R2, t2) < tol and pose_error(pts, False, R, t, R2, t2) > 0.2 * obj.diameter


def test_accuracy_thresholds_and_curve():
    d = np.full(4, 0.2)
    err = np.array([0.01, 0.025, 0.05, np.inf])  # 5 %, 12.5 %, 25 %, missed
    assert [accuracy(err, d, k) for k in (0.10, 0.15, 0.30)] == [0.25, 0.5, 0.75]
    ks, acc = accuracy_curve(err, d)
    assert acc[0] == 0 and acc[-1] == 0.75 and np.all(np.diff(acc) >= 0)


def test_greedy_matching_each_gt_once_by_score():
    # two detections of the same object, one GT: the higher score wins even if the other is closer
    err = np.array([[0.02], [0.001]])
    assert greedy_match(np.array([0.9, 0.5]), err).tolist() == [0, -1]
    # limit: a far first pick leaves the GT to the next detection
    assert greedy_match(np.array([0.9, 0.5]), np.array([[0.5], [0.001]]), np.array([0.03])).tolist() == [-1, 0]
    # inf (another object) never matches
    assert greedy_match(np.array([1.0]), np.array([[np.inf, 0.01]])).tolist() == [1]


def test_match_frame_f1_counts():
    # 3 GT (diameter 0.1), 4 detections: two correct, one duplicate, one wrong object
    err = np.array([[0.005, np.inf, 0.3], [0.004, np.inf, 0.3], [np.inf, 0.2, np.inf], [0.3, np.inf, 0.01]])
    m = match_frame(np.array([0.9, 0.8, 0.7, 0.6]), err, np.full(3, 0.1))
    assert m.tp == 2 and m.num_det == 4 and m.num_gt == 3
    # ADD takes the 3 best-scoring detections only (3 instances): the duplicate uses up a place, 0.2 is beyond half
    # the diameter, and the right detection of instance 2 is the fourth
    assert m.gt_error.tolist() == [0.005, np.inf, np.inf]
    r = prf(m.tp, m.num_det, m.num_gt)
    assert r["precision"] == 0.5 and r["recall"] == pytest.approx(2 / 3)
    assert r["f1"] == pytest.approx(2 * 0.5 * (2 / 3) / (0.5 + 2 / 3))
    assert prf(0, 0, 3) == {"precision": 0.0, "recall": 0.0, "f1": 0.0}


def test_match_frame_ignores_invalid_instances_and_their_detections():
    err = np.array([[0.001, np.inf], [np.inf, 0.002], [np.inf, 0.5]])
    m = match_frame(np.array([0.9, 0.8, 0.7]), err, np.full(2, 0.1), valid=np.array([True, False]))
    assert (m.tp, m.num_det, m.num_gt) == (1, 2, 1)  # the hit on the ignored instance is neither TP nor FP


def test_match_frame_detections_of_an_object_with_no_instance_in_the_frame():
    m = match_frame(np.array([0.9, 0.5]), np.zeros((2, 0)), np.zeros(0), valid=np.zeros(0, bool))
    assert (m.tp, m.num_det, m.num_gt) == (0, 2, 0) and m.gt_error.shape == (0,)


def test_add_counts_the_top_scoring_pose_only_while_f1_keeps_every_detection():
    """BOP19's n_top rule: per object and frame the k best-scoring poses (k instances) are the answer. A
    higher-scoring pose 0.8 diameters off makes the instance wrong although a lower-scoring right one lies on it."""
    dia = np.array([0.1])
    err = np.array([[0.08], [0.002]])  # detection 0: far off, scored higher; detection 1: right
    m = match_frame(np.array([0.9, 0.5]), err, dia)
    assert m.gt_error.tolist() == [np.inf]  # was 0.002: the far one used to be skipped
    assert (m.tp, m.num_det, m.num_gt) == (1, 2, 1)  # F1 still sees both: one TP, one FP
    # scored the other way round, the right pose is the answer
    assert match_frame(np.array([0.5, 0.9]), err, dia).gt_error.tolist() == [0.002]
    # two instances: the two best detections are matched greedily by score; the third (right on instance 1) is out
    err2 = np.array([[0.001, 0.2], [0.3, 0.09], [0.5, 0.001]])
    m2 = match_frame(np.array([0.9, 0.8, 0.1]), err2, np.full(2, 0.2))
    assert m2.gt_error.tolist() == [0.001, 0.09] and m2.tp == 2 and m2.num_det == 3
    # k counts the valid instances only; an ignored instance gets no ADD error
    m3 = match_frame(np.array([0.9, 0.8]), np.array([[0.001, 0.5], [0.5, 0.001]]), np.full(2, 0.1),
                     valid=np.array([False, True]))
    assert m3.gt_error.tolist() == [np.inf, np.inf] and (m3.tp, m3.num_det, m3.num_gt) == (1, 1, 1)
    assert top_k(np.array([0.5, 0.9, 0.5, 0.7]), 3).tolist() == [1, 3, 0]  # ties keep their order (stable)
