"""bench/probe_misses.py: each missed instance gets the first cause that holds, from stage 1's centres to the
score threshold, with the real ADD pose error; the report's misses are read per object in the label file's
order; bad input is a one-line error."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from detector.errors import DetectorError
from detector.evaluation.metrics import add
from detector.geometry.types import Detection

REPO = Path(__file__).resolve().parents[1]


def _det(obj_id: int, R: np.ndarray, t: np.ndarray, score: float, corners: np.ndarray) -> Detection:
    """A detection whose control points are the model's box points (9,3) under (R, t)."""
    return Detection(obj_id=obj_id, score=score, R=R, t=t, support=5, control_points=corners @ R.T + t,
                     members=np.arange(5))


def test_miss_cause_takes_the_first_cause_that_holds(repo_script):
    p = repo_script("bench/probe_misses.py")
    rng = np.random.default_rng(0)
    model = rng.uniform(-0.05, 0.05, (500, 3))  # a 0.1 m box of points; its centre is the origin
    corners = np.concatenate([np.array([[x, y, z] for x in (-.05, .05) for y in (-.05, .05) for z in (-.05, .05)]),
                              np.zeros((1, 3))])
    dia = float(np.linalg.norm(model.max(0) - model.min(0)))
    R, t = Rotation.from_euler("xyz", [20, -30, 50], degrees=True).as_matrix(), np.array([0.1, -0.05, 0.8])
    centre = t.copy()
    error = lambda d: add(model, R, t, d.R, d.t)  # noqa: E731
    right = _det(3, R, t + 0.002, 0.9, corners)
    turned = _det(3, Rotation.from_euler("z", 90, degrees=True).as_matrix() @ R, t, 0.9, corners)
    far = _det(3, R, t + np.array([0.2, 0, 0]), 0.9, corners)
    other = _det(7, R, t, 0.9, corners)

    def cause(stage1, posed, min_score=0.65):
        return p.miss_cause(3, centre, dia, stage1, posed, error, min_score)

    assert cause([], [right]) == "no stage-1 centre"
    assert cause([far], [right]) == "no stage-1 centre"  # its own centre, but not near
    assert cause([other], [right]) == "another object's centre only"
    assert cause([right, other], [other]) == "no stage-2 pose"
    assert cause([right], [turned]) == "wrong pose"
    weak = _det(3, R, t + 0.002, 0.5, corners)
    assert cause([right], [weak]) == "right pose, score under min_score"
    assert cause([right], [weak], min_score=0.4) == "right pose, not chosen"
    # the best-scoring pose near the centre decides
    assert cause([right], [_det(3, turned.R, t, 0.95, corners), weak]) == "wrong pose"
    assert cause([right], [_det(3, turned.R, t, 0.3, corners), right]) == "right pose, not chosen"
    assert set(p.CAUSES) >= {cause([], []), cause([right], [])}


def test_icp_start_errors_tell_a_right_start_from_the_wrong_pose(repo_script):
    """A detection turned far from the truth whose other verified hypothesis lies near it: ICP from that start
    reaches the true pose, from the detection's own pose it does not; too few points for ICP give no errors."""
    from argen.models.objects import builtin_objects
    from test_geometry import visible_surface

    from detector.geometry.icp import icp_starts
    from detector.geometry.types import GeometryConfig, ObjectInfo

    p = repo_script("bench/probe_misses.py")
    rng = np.random.default_rng(3)
    obj = builtin_objects(["drill"])[0]
    model = np.asarray(obj.mesh.sample(1500, seed=4))
    objects = ObjectInfo({5: obj.control_points}, {5: obj.diameter}, {5: model})
    R, t = Rotation.from_euler("xyz", [30, -20, 60], degrees=True).as_matrix(), np.array([0.02, -0.03, 0.75])
    cloud = visible_surface(obj, R, t, 3000, rng)
    error = lambda d: add(model, R, t, d.R, d.t)  # noqa: E731
    wrong = Rotation.from_euler("y", 100, degrees=True).as_matrix() @ R
    near = (Rotation.from_rotvec([0.04, -0.03, 0.02]).as_matrix() @ R, t + np.array([0.004, -0.003, 0.002]))
    d = Detection(obj_id=5, score=0.5, R=wrong, t=t + 0.01, support=5, control_points=obj.control_points @ wrong.T + t,
                  members=np.arange(5), points=np.arange(len(cloud)), alternatives=[near])
    cfg = GeometryConfig(icp=True, icp_half_turns=False)
    errors = p.icp_start_errors(d, cloud, objects, cfg, error)
    assert len(errors) == len(icp_starts(5, d.R, d.t, objects, cfg, d.alternatives)) == 2
    assert errors[0] > 0.1 * obj.diameter  # ICP from the wrong pose stays wrong
    assert errors[1] < 0.02 * obj.diameter < error(replace(d, R=near[0], t=near[1]))  # and from the near one is right
    few = replace(d, points=np.arange(cfg.icp_min_points - 1))
    assert p.icp_start_errors(few, cloud, objects, cfg, error) == []


def test_icp_from_truth_tells_the_points_from_the_starts(repo_script):
    """ICP from the true pose on a detection's points stays right when the points are the object's visible surface,
    and leaves it when they are another surface (the same object's points moved 6 cm); too few points: None."""
    from argen.models.objects import builtin_objects
    from test_geometry import visible_surface

    from detector.geometry.types import GeometryConfig, ObjectInfo

    p = repo_script("bench/probe_misses.py")
    rng = np.random.default_rng(5)
    obj = builtin_objects(["drill"])[0]
    model = np.asarray(obj.mesh.sample(1500, seed=6))
    objects = ObjectInfo({5: obj.control_points}, {5: obj.diameter}, {5: model})
    R, t = Rotation.from_euler("xyz", [-40, 25, 10], degrees=True).as_matrix(), np.array([-0.03, 0.02, 0.7])
    error = lambda d: add(model, R, t, d.R, d.t)  # noqa: E731
    wrong = Rotation.from_euler("x", 120, degrees=True).as_matrix() @ R
    own = visible_surface(obj, R, t, 3000, rng)
    d = Detection(obj_id=5, score=0.5, R=wrong, t=t, support=5, control_points=obj.control_points @ wrong.T + t,
                  members=np.arange(5), points=np.arange(len(own)))
    cfg = GeometryConfig(icp=True)
    assert error(d) > 0.3 * obj.diameter
    assert p.icp_from_truth_error(d, own, objects, cfg, R, t, error) < 0.02 * obj.diameter
    elsewhere = own + np.array([0.06, 0.0, 0.0])  # the points of something else: ICP follows them off the truth
    assert p.icp_from_truth_error(d, elsewhere, objects, cfg, R, t, error) > 0.1 * obj.diameter
    few = replace(d, points=np.arange(cfg.icp_min_points - 1))
    assert p.icp_from_truth_error(few, own, objects, cfg, R, t, error) is None
    assert p.TRUTH_HOLDS in p.COLUMNS and p.TRUTH_HOLDS not in p.CAUSES


def test_missed_instances_follow_the_label_files_order_per_object(repo_script):
    p = repo_script("bench/probe_misses.py")
    rows = [{"frame": f, "obj_id": o, "diameter": d, "icp": e} for f, o, d, e in
            [(0, 5, 0.2, 0.002), (0, 5, 0.2, None), (0, 9, 0.1, 0.03), (0, 5, 0.2, 0.03), (2, 9, 0.1, 0.00999)]]
    # errors are metres, compared with the threshold times each instance's diameter
    assert dict(p.missed_instances({"instances": rows}, 0.1)) == {0: [(5, 1), (9, 0), (5, 2)]}
    assert dict(p.missed_instances({"instances": rows}, 0.05)) == {0: [(5, 1), (9, 0), (5, 2)], 2: [(9, 0)]}
    assert dict(p.missed_instances({"instances": rows}, 0.2)) == {0: [(5, 1), (9, 0)]}
    with pytest.raises(DetectorError, match="--icp"):
        p.missed_instances({"instances": [{"frame": 0, "obj_id": 5, "diameter": 0.1, "noicp": 0.2}]}, 0.1)


@pytest.mark.parametrize("what", ["missing report", "report without ICP", "missing model", "missing labels"])
def test_bad_input_is_a_one_line_error(tmp_path, what):
    report, model = tmp_path / "report.json", tmp_path / "model.pt"
    if what == "report without ICP":
        report.write_text(json.dumps({"instances": [{"frame": 0, "obj_id": 1, "noicp": 0.5}]}))
    elif what != "missing report":
        report.write_text(json.dumps({"instances": [{"frame": 0, "obj_id": 1, "noicp": 0.5, "icp": 0.5}]}))
    if what == "missing labels":
        model = REPO / "checkpoints" / "lm8.pt"
        if not model.is_file():
            pytest.skip("no checkpoints/lm8.pt")
    r = subprocess.run([sys.executable, str(REPO / "bench" / "probe_misses.py"), str(model),
                        str(tmp_path / "labels.h5"), str(report)], capture_output=True, text=True, cwd=REPO)
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and r.stderr.startswith("probe_misses:"), r.stderr
