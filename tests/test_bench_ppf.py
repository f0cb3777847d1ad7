"""bench/bench_ppf.py: the OpenCV PPF baseline's pipeline recovers a known pose from a render-free synthetic
scene (one built-in object's visible surface samples on a table plane), its scene cloud is the frame in
millimetres with normals toward the camera, and bad input is a one-line error."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from argen.models.objects import builtin_objects
from conftest import load_repo_script
from detector.evaluation.metrics import add

REPO = Path(__file__).resolve().parents[1]

if not hasattr(cv2, "ppf_match_3d_PPF3DDetector"):  # the contrib build is a dependency, but say so plainly
    pytest.skip("OpenCV without the contrib surface_matching module", allow_module_level=True)


bench = load_repo_script("bench/bench_ppf.py")


def _scene(obj, R: np.ndarray, t: np.ndarray, seed: int) -> np.ndarray:
    """The camera-facing surface samples of ``obj`` at pose R (3,3), t (3,) metres on a 30 cm table plane
    touching its lowest point (camera y down), with 1 mm noise: a PPF cloud (N,6) mm."""
    rng = np.random.default_rng(seed)
    pts, nrm = bench.model_surface(obj.mesh, 12000, seed)
    P, N = pts @ R.T + t, nrm @ R.T
    keep = np.einsum("ij,ij->i", N, P) < 0
    P = P[keep] + rng.normal(0, 0.001, (int(keep.sum()), 3))
    g = np.stack(np.meshgrid(np.linspace(-0.15, 0.15, 60), np.linspace(-0.15, 0.15, 60)), -1).reshape(-1, 2)
    plane = np.c_[t[0] + g[:, 0], np.full(len(g), P[:, 1].max()), t[2] + g[:, 1]]
    normals = np.vstack([N[keep], np.tile([0.0, -1.0, 0.0], (len(plane), 1))])
    return bench.ppf_cloud(np.vstack([P, plane]), normals)


def test_ppf_pipeline_recovers_a_known_pose():
    cv2.setNumThreads(1)
    duck = builtin_objects(["duck"])[0]  # no symmetry: ADD is well defined
    s = bench.PPFSettings(sampling_step=0.1, model_points=8000)  # coarser than the bench's default: a fast test
    model_pc = bench.ppf_cloud(*bench.model_surface(duck.mesh, s.model_points, 0))
    det = bench.train_detector(model_pc, s)
    R, _ = cv2.Rodrigues(np.array([0.4, -0.6, 0.9]))
    t = np.array([0.03, -0.02, 0.7])
    scene = _scene(duck, R, t, seed=1)
    found = bench.match_object(det, scene, duck.diameter, 1, s)
    assert len(found) == 1
    R0, t0 = bench.pose_rt(found[0].pose)
    assert np.allclose(R0 @ R0.T, np.eye(3), atol=1e-5)
    pts = bench.model_surface(duck.mesh, 1000, 2)[0]
    assert add(pts, R, t, R0, t0) < 0.2 * duck.diameter  # PPF alone: near (its angle bins are 24 degrees wide)
    (R1, t1), = bench.refine(cv2.ppf_match_3d_ICP(s.icp_iterations), model_pc, scene, found)
    assert add(pts, R, t, R1, t1) < 0.1 * duck.diameter  # ADD@10 %
    assert add(pts, R, t, R1, t1) < add(pts, R, t, R0, t0)


def test_scene_cloud_is_the_frame_in_millimetres_facing_the_camera():
    K = np.array([[500.0, 0, 32], [0, 500.0, 24], [0, 0, 1]])
    depth = np.full((48, 64), 0.8, np.float32)
    depth[:, :8] = 0.0  # missing
    depth[:, -8:] = 3.0  # beyond max_depth
    pc = bench.scene_cloud(depth, K, 2.0)
    assert pc.shape == (48 * 48, 6) and pc.dtype == np.float32
    assert np.allclose(pc[:, 2], 800.0)
    assert np.allclose(pc[:, 3:], [0, 0, -1], atol=1e-4)
    rel = bench.scene_distance(pc, 0.1, bench.PPFSettings(scene_step=0.05))
    assert rel == pytest.approx(0.005 / (np.ptp(pc[:, :3], axis=0).max() / 1000.0))


def test_missing_dataset_is_one_line_error(tmp_path):
    r = subprocess.run([sys.executable, str(REPO / "bench" / "bench_ppf.py"), "--dataset", str(tmp_path / "none")],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [f"error: dataset folder not found: {tmp_path / 'none'}"]
