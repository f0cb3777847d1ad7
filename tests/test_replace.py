"""`argen replace`: remove the target object from BOP frames and insert it rotated about the plane normal."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from argen import bop
from argen.cli.app import app
from argen.config import NoiseConfig, load_template, override
from argen.errors import ArgenError
from argen.models.objects import builtin_objects, load_models
from argen.real.replace import fit_plane, pixel_rays, replace_dataset, rotation_about, select_frames
from argen.sim.capture import CaptureRequest, run_capture
from argen.sim.render import RenderItem, get_renderer

SETS = {"camera.width": 320, "camera.height": 240, "camera.fx": 286.2, "camera.fy": 286.8, "camera.cx": 162.6,
        "camera.cy": 121.0, "camera.distance": [0.5, 0.7], "camera.elevation_deg": [50.0, 85.0],
        "noise.enabled": False, "seed": 11, "placement.objects_per_frame": [2, 2]}
SPLIT = "train_pbr"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("replace")
    cfg = override(load_template("linemod"), SETS)
    run_capture(CaptureRequest(cfg=cfg, objects=builtin_objects(), out=root / "src", frames=2, progress=False))
    s = replace_dataset(root / "src", root / "out", split=SPLIT, fraction=0.5, step_deg=30, seed=1, noise=None,
                        progress=False)
    return root, s


def _angle_axis(R: np.ndarray) -> tuple[float, np.ndarray]:
    ang = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    ax = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(ang), ax / (np.linalg.norm(ax) + 1e-12)


def test_twelve_copies_rotated_about_the_plane_normal(data):
    root, s = data
    src, out = bop.load_scene(root / "src", SPLIT, 0), bop.load_scene(root / "out", SPLIT, 0)
    log = json.loads((root / "out" / "replace_log.json").read_text())["frames"]
    assert s.source_frames == 1 and s.written == 12 == len(out.im_ids) == len(log)
    im = log[0]["src_im_id"]
    assert [e["im_id"] for e in log] == [im * 12 + k for k in range(12)]
    g0 = src.gts[im][0]
    n = src.cameras[im].T_cam_world[:3, 2]  # board normal in the camera frame
    centre0 = None
    obj = {o.obj_id: o for o in load_models(root / "src" / "models")}[g0.obj_id]
    for k in range(12):
        g = out.gts[im * 12 + k][0]
        assert g.obj_id == g0.obj_id and log[k]["angle_deg"] == 30 * k and log[k]["axis"] == "camera pose"
        dR = g.R @ g0.R.T
        ang, ax = _angle_axis(dR)
        assert ang == pytest.approx(min(30 * k, 360 - 30 * k), abs=1e-3)
        if 0 < k < 12 and k != 6:
            assert abs(abs(ax @ n) - 1) < 1e-6
        assert np.allclose(dR, rotation_about(n, np.deg2rad(30 * k)), atol=1e-6)
        centre = g.R @ obj.control_points[8] + g.t  # the box centre stays put, so the object stays on the board
        centre0 = centre if centre0 is None else centre0
        assert np.allclose(centre, centre0, atol=1e-6)
        # the other instance is untouched
        assert np.allclose(out.gts[im * 12 + k][1].t, src.gts[im][1].t, atol=1e-6)


def test_inserted_depth_agrees_with_its_gt_pose(data):
    root, _ = data
    out = bop.load_scene(root / "out", SPLIT, 0)
    objs = {o.obj_id: o for o in load_models(root / "out" / "models")}
    r = get_renderer(320, 240)
    for im in out.im_ids[::4]:
        g = out.gts[im][0]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = g.R, g.t
        ref = r.render_depth([RenderItem(("chk", g.obj_id), objs[g.obj_id].mesh, T, 1)], out.cameras[im].K, np.eye(4))
        vis = out.read_mask(im, 0)
        d = out.read_depth(im)
        assert vis.sum() > 100 and (ref[vis] > 0).all()
        assert np.median(np.abs(d[vis] - ref[vis])) < 0.001
        assert np.array_equal(out.read_mask(im, 0, visib=False), ref > 0)


def test_removed_object_leaves_the_board_plane(data):
    root, _ = data
    src, out = bop.load_scene(root / "src", SPLIT, 0), bop.load_scene(root / "out", SPLIT, 0)
    for im in out.im_ids[1:12:5]:
        sim = im // 12
        old = src.read_mask(sim, 0)
        new = out.read_mask(im, 0, visib=False) | out.read_mask(im, 1, visib=False)
        hole = old & ~new
        assert hole.sum() > 30
        rows, cols = np.nonzero(hole)
        d = out.read_depth(im)[rows, cols]
        assert (d > 0).mean() > 0.95
        p = pixel_rays(rows, cols, out.cameras[im].K)[d > 0] * d[d > 0, None]
        T = out.cameras[im].T_cam_world
        z_board = (p - T[:3, 3]) @ T[:3, :3][:, 2]  # height above the board top, metres
        assert np.abs(z_board).max() < 0.006  # 3 mm board thickness, 1 mm PNG rounding, plane fit
        # the object's old depth (well above the board) is gone
        assert np.median(src.read_depth(sim)[rows, cols] - out.read_depth(im)[rows, cols]) < -0.005


def test_plane_fit_recovers_the_board_normal(data):
    root, _ = data
    src = bop.load_scene(root / "src", SPLIT, 0)
    im = src.im_ids[0]
    d, K, T = src.read_depth(im), src.cameras[im].K, src.cameras[im].T_cam_world
    rows, cols = np.nonzero(d > 0)
    p = pixel_rays(rows, cols, K) * d[rows, cols, None]
    n, c, inl = fit_plane(p, np.random.default_rng(0))
    assert np.degrees(np.arccos(abs(n @ T[:3, 2]))) < 1.0 and n @ T[:3, 2] > 0 and inl.mean() > 0.5


def test_noise_goes_on_the_changed_pixels_only(data, tmp_path):
    root, _ = data
    replace_dataset(root / "src", tmp_path / "n", split=SPLIT, fraction=0.5, step_deg=120, seed=1,
                    noise=NoiseConfig(), progress=False)
    clean, noisy = bop.load_scene(root / "out", SPLIT, 0), bop.load_scene(tmp_path / "n", SPLIT, 0)
    im_c, im_n = clean.im_ids[4], noisy.im_ids[1]  # both 120 degrees
    assert np.allclose(clean.gts[im_c][0].R, noisy.gts[im_n][0].R)
    dc, dn = clean.read_depth(im_c), noisy.read_depth(im_n)
    vis = clean.read_mask(im_c, 0) & (dn > 0)
    diff = np.abs(dc[vis] - dn[vis])
    assert 0.0003 < np.median(diff) < 0.005
    src = bop.load_scene(root / "src", SPLIT, 0)
    touched = clean.read_mask(im_c, 0, visib=False) | src.read_mask(im_c // 12, 0, visib=False)
    far = cv2.dilate(touched.astype(np.uint8), np.ones((9, 9), np.uint8)) == 0
    assert far.mean() > 0.8
    assert np.array_equal(dc[far], dn[far])


def test_fraction_and_step_checks(tmp_path):
    rng = np.random.default_rng(0)
    frames = [(0, i) for i in range(50)]
    pick = select_frames(frames, 0.1, rng)
    assert len(pick) == 5 and pick == sorted(set(pick))
    with pytest.raises(ArgenError, match="fraction"):
        select_frames(frames, 0.0, rng)
    r = CliRunner().invoke(app, ["replace", str(tmp_path), "--out", str(tmp_path / "o"), "--step-deg", "25"])
    assert r.exit_code == 2 and "divide 360" in r.stderr
    r = CliRunner().invoke(app, ["replace", str(tmp_path / "none"), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "not found" in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_without_camera_pose_the_axis_is_the_fitted_plane_normal(data, tmp_path):
    root, _ = data
    import shutil

    src = tmp_path / "src"
    shutil.copytree(root / "src", src)
    p = src / SPLIT / "000000" / "scene_camera.json"
    cams = json.loads(p.read_text())
    truth = {k: np.array(v["cam_R_w2c"]).reshape(3, 3)[:, 2] for k, v in cams.items()}
    p.write_text(json.dumps({k: {"cam_K": v["cam_K"], "depth_scale": v["depth_scale"]} for k, v in cams.items()}))
    replace_dataset(src, tmp_path / "o", split=SPLIT, fraction=0.5, step_deg=90, seed=1, progress=False)
    log = json.loads((tmp_path / "o" / "replace_log.json").read_text())["frames"]
    assert len(log) == 4
    for e in log:
        assert e["axis"] == "plane fit" and e["fill"] == "plane"
        n = truth[str(e["src_im_id"])]
        assert np.degrees(np.arccos(np.clip(np.dot(e["axis_cam"], n), -1, 1))) < 1.5


def test_replace_takes_a_plain_mesh_folder_as_models(data, tmp_path):
    """--models with plain meshes named obj_NNNNNN (no models_info.json): imported on the fly, same frames."""
    root, _ = data
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    for p in (root / "src" / "models").glob("obj_*.ply"):
        bop.read_mesh(p).export(meshes / f"{p.stem}.stl")  # STL in metres, no colours
    s = replace_dataset(root / "src", tmp_path / "o", split=SPLIT, models=meshes, fraction=0.5, step_deg=120,
                        seed=1, noise=None, progress=False)
    assert "imported" in s.notes[0] and s.written == 3
    ref = bop.load_scene(root / "out", SPLIT, 0)
    new = bop.load_scene(tmp_path / "o", SPLIT, 0)
    im_r, im_n = ref.im_ids[4], new.im_ids[1]  # both 120 degrees
    assert np.array_equal(ref.read_mask(im_r, 0, visib=False), new.read_mask(im_n, 0, visib=False))
