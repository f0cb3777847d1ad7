"""Markerless `argen capture --recording`: the support plane, placement against real geometry, occlusion, and
the recording readers (argen's folders, TUM, a plain BOP folder, a ROS 1 bag).

The synthetic recording is rendered with argen's renderer: a table plane, a box standing on it and a bar floating
above it nearer the camera, seen from two views; its true camera poses are known, so the fitted plane and the
placed objects can be checked in the world frame.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from pykdtree.kdtree import KDTree
from typer.testing import CliRunner

from argen import bop
from argen.cli.app import app
from argen.config import PlaneConfig, load_template, override
from argen.errors import ArgenError
from argen.features import backproject
from argen.models.objects import builtin_objects, load_models
from argen.real.capture import run_real_capture
from argen.real.readers import open_any
from argen.real.recording import write_recording
from argen.real.support import find_support
from argen.sim.camera import look_at
from argen.sim.capture import CaptureRequest
from argen.sim.placement import convex_hull_2d, separation
from argen.sim.render import RenderItem, get_renderer
from argen.validate import validate_file

W, H = 320, 240
K = np.array([[280.0, 0.0, 159.5], [0.0, 280.0, 119.5], [0.0, 0.0, 1.0]])
TABLE = (0.8, 0.56)  # metres, its top at z = 0; the floor is 0.72 m below
BOX = ((0.22, -0.14), (0.12, 0.10, 0.16))  # centre xy, extents (metres), standing on the table
BAR = ((0.0, -0.04), (1.0, 0.03, 0.02), 0.12)  # centre xy, extents, height of its bottom above the table
VIEWS = [look_at(np.array([0.05, -0.75, 0.6]), np.array([0.0, 0.02, 0.0]), -np.pi / 2),
         look_at(np.array([-0.45, -0.6, 0.55]), np.array([0.0, 0.0, 0.0]), -np.pi / 2 - 0.6)]
FRAMES = 4  # each view twice: new placements every frame
SETS = {"noise.enabled": False, "seed": 5, "placement.objects_per_frame": [3, 4], "plane.support": "plane",
        "camera.z_far": 4.0}
SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def _coloured_box(extents, colour) -> trimesh.Trimesh:
    m = trimesh.creation.box(extents=extents)
    m.visual.vertex_colors = np.tile(np.array([*colour, 255], np.uint8), (len(m.vertices), 1))
    return m


def _translate(x, y, z) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def _world() -> list[RenderItem]:
    (bx, by), be = BOX
    (rx, ry), re_, rz = BAR
    return [RenderItem(("mk-table",), _coloured_box((*TABLE, 0.02), (150, 120, 90)), _translate(0, 0, -0.01)),
            RenderItem(("mk-floor",), _coloured_box((6.0, 6.0, 0.02), (90, 90, 95)), _translate(0, 0, -0.73)),
            RenderItem(("mk-box",), _coloured_box(be, (40, 90, 200)), _translate(bx, by, be[2] / 2)),
            RenderItem(("mk-bar",), _coloured_box(re_, (200, 60, 40)), _translate(rx, ry, rz + re_[2] / 2))]


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    root = tmp_path_factory.mktemp("markerless")
    r = get_renderer(W, H)
    frames = []
    for k in range(FRAMES):
        out = r.render(_world(), K, VIEWS[k % len(VIEWS)], ambient=0.6, znear=0.05, zfar=4.0)
        frames.append((out.rgb, out.depth))
    write_recording(root / "rec", K, frames, depth_scale=0.1)
    cfg = override(load_template("linemod"), SETS)
    objs = builtin_objects()
    s = run_real_capture(CaptureRequest(cfg=cfg, objects=objs, out=root / "out", frames=1, progress=False),
                         open_any(root / "rec"))
    return root, frames, s, objs


def _world_pose(scene: bop.BopScene, im: int, g) -> np.ndarray:
    """T_world_obj of GT instance g of image im, through the true camera pose of that frame."""
    T_cam_obj = np.eye(4)
    T_cam_obj[:3, :3], T_cam_obj[:3, 3] = g.R, g.t
    return np.linalg.inv(VIEWS[im % len(VIEWS)]) @ T_cam_obj


def test_plane_is_found_within_one_degree(synthetic):
    _, frames, _, _ = synthetic
    for k, (_, depth) in enumerate(frames):
        s = find_support(depth, K, PlaneConfig(), np.random.default_rng(k))
        assert not isinstance(s, str), s
        T_true = VIEWS[k % len(VIEWS)]
        n_true = T_true[:3, 2]  # world z in the camera frame
        angle = np.degrees(np.arccos(np.clip(s.T_cam_world[:3, 2] @ n_true, -1, 1)))
        assert angle < 1.0
        height_err = (s.T_cam_world[:3, 3] - T_true[:3, 3]) @ n_true  # origin's height above the true table
        assert abs(height_err) < 0.002


def test_objects_stand_on_the_plane_and_never_inside_real_geometry(synthetic):
    root, _, s, objs = synthetic
    scene = bop.load_scene(root / "out", "train_pbr", 0)
    assert s.written == FRAMES
    by_id = {o.obj_id: o for o in objs}
    (bx, by), be = BOX
    box_fp = convex_hull_2d(np.array([[bx + sx * be[0] / 2, by + sy * be[1] / 2] for sx in (-1, 1) for sy in (-1, 1)]))
    (rx, ry), re_, rz = BAR
    bar_fp = convex_hull_2d(np.array([[rx + sx * re_[0] / 2, ry + sy * re_[1] / 2] for sx in (-1, 1) for sy in (-1, 1)]))
    placed = 0
    for im in scene.im_ids:
        for g in scene.gts[im]:
            T = _world_pose(scene, im, g)
            v = by_id[g.obj_id].hull_vertices @ T[:3, :3].T + T[:3, 3]
            assert abs(v[:, 2].min()) < 0.003  # standing on the table
            fp = convex_hull_2d(v[:, :2])
            assert separation(fp, box_fp) > 0  # never inside (or touching) the box
            assert separation(fp, bar_fp) > 0 or v[:, 2].max() < rz  # never through the bar
            placed += 1
    assert placed >= 3 * FRAMES


def test_real_surface_in_front_hides_and_gt_matches_depth(synthetic):
    root, frames, _, objs = synthetic
    scene = bop.load_scene(root / "out", "train_pbr", 0)
    r = get_renderer(W, H)
    by_id = {o.obj_id: o for o in objs}
    hidden = 0
    for im in scene.im_ids:
        real = frames[im][1]
        out = scene.read_depth(im)
        for k, g in enumerate(scene.gts[im]):
            T_cam_obj = np.eye(4)
            T_cam_obj[:3, :3], T_cam_obj[:3, 3] = g.R, g.t
            item = RenderItem(("obj", by_id[g.obj_id].source, g.obj_id), by_id[g.obj_id].mesh, T_cam_obj, 1)
            virt = r.render_depth([item], K, np.eye(4), znear=0.05, zfar=4.0)
            vis, full = scene.read_mask(im, k), scene.read_mask(im, k, visib=False)
            assert np.array_equal(full, virt > 0)
            # visible pixels: the composited depth is the model's surface (depth-to-model distance, noise off)
            assert vis.sum() > 0 and np.abs(out[vis] - virt[vis]).max() < 0.0005
            # a real surface more than a few mm in front hides the object, and keeps its depth
            front = full & (real > 0) & (real < virt - 0.01)
            assert not (front & vis).any()
            assert np.abs(out[front] - real[front]).max(initial=0) < 0.0005
            hidden += int(front.sum())
    assert hidden > 50  # the bar hides parts of some objects


def test_same_seed_same_output_and_resume(synthetic, tmp_path):
    root, _, _, objs = synthetic
    cfg = override(load_template("linemod"), SETS)
    rec = open_any(root / "rec")
    req = CaptureRequest(cfg=cfg, objects=objs, out=tmp_path / "again", frames=1, progress=False)
    s = run_real_capture(req, rec)
    assert s.written == FRAMES
    for name in ("scene_gt.json", "scene_camera.json"):
        a = (root / "out" / "train_pbr" / "000000" / name).read_bytes()
        assert a == (tmp_path / "again" / "train_pbr" / "000000" / name).read_bytes()
    d = "train_pbr/000000/depth/000002.png"
    assert (root / "out" / d).read_bytes() == (tmp_path / "again" / d).read_bytes()
    assert run_real_capture(req, rec).skipped == FRAMES


def test_frame_without_a_plane_is_rejected_and_logged(tmp_path):
    # a wall facing the camera: a plane, but not a horizontal one
    depth = np.full((H, W), 1.2, np.float32)
    write_recording(tmp_path / "rec", K, [(np.full((H, W, 3), 90, np.uint8), depth)], depth_scale=0.1)
    cfg = override(load_template("linemod"), SETS)
    s = run_real_capture(CaptureRequest(cfg=cfg, objects=builtin_objects(), out=tmp_path / "out", frames=1,
                                        progress=False), open_any(tmp_path / "rec"))
    assert s.written == 0 and s.rejected == 1
    log = json.loads((tmp_path / "out" / "capture_log.json").read_text())["frames"][0]
    assert not log["accepted"] and log["reason"].startswith("no usable plane") and log["support"] == "plane"


# ------------------------------------------------------------------------------------------------ readers


def _write_tum(root: Path, rgb: np.ndarray, depth: np.ndarray) -> None:
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    cv2.imwrite(str(root / "rgb" / "1.000000.png"), rgb[..., ::-1])
    cv2.imwrite(str(root / "depth" / "1.010000.png"), np.round(depth * 5000).astype(np.uint16))
    (root / "rgb.txt").write_text("# color images\n1.000000 rgb/1.000000.png\n")
    (root / "depth.txt").write_text("# depth maps\n1.010000 depth/1.010000.png\n")


def _points(rec) -> np.ndarray:
    _, d = rec.read(0)
    rows, cols = np.nonzero(d > 0)
    return backproject(rows, cols, d[rows, cols].astype(np.float64), rec.K)


def test_tum_and_plain_folder_read_the_same_points(synthetic, tmp_path):
    _, frames, _, _ = synthetic
    rgb, depth = frames[0]
    _write_tum(tmp_path / "tum", rgb, depth)
    plain = tmp_path / "plain"
    plain.mkdir()
    bop.save_camera(plain / "camera.json", K, W, H, 0.1)
    bop.write_png(plain / "000000_color.png", rgb)
    bop.write_depth(plain / "000000_depth.png", depth, 0.1)
    cam = tmp_path / "cam.json"
    bop.save_camera(cam, K, W, H, 1.0)
    tum = open_any(tmp_path / "tum", camera=bop.load_camera(cam))
    assert tum.depth_scale == 0.2  # TUM's own convention: camera.json's depth_scale is for its PNGs, not TUM's
    folder = open_any(plain)
    assert len(tum) == len(folder) == 1 and np.allclose(tum.K, folder.K)
    assert np.array_equal(tum.read(0)[0], folder.read(0)[0])
    a, b = _points(tum), _points(folder)
    assert a.shape == b.shape and np.abs(a - b).max() < 0.00015  # the two PNGs' quantisation: 0.2 and 0.1 mm


def test_tum_without_camera_uses_the_benchmark_default(tmp_path):
    _write_tum(tmp_path / "tum", np.zeros((480, 640, 3), np.uint8), np.full((480, 640), 1.5, np.float32))
    rec = open_any(tmp_path / "tum")
    assert rec.camera_source == "default" and rec.K[0, 0] == 525.0 and rec.K[1, 2] == 239.5


def _write_bag(path: Path, frames, K_: np.ndarray, depth_encoding="16UC1", depth_topic="/camera/aligned_depth_to_color/image_raw"):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    Image, Info, Header = ts.types["sensor_msgs/msg/Image"], ts.types["sensor_msgs/msg/CameraInfo"], ts.types["std_msgs/msg/Header"]
    Time, Float32 = ts.types["builtin_interfaces/msg/Time"], ts.types["std_msgs/msg/Float32"]
    RoI = ts.types["sensor_msgs/msg/RegionOfInterest"]
    with Writer(path) as w:
        c_rgb = w.add_connection("/camera/color/image_raw", Image.__msgtype__, typestore=ts)
        c_d = w.add_connection(depth_topic, Image.__msgtype__, typestore=ts)
        c_info = w.add_connection("/camera/color/camera_info", Info.__msgtype__, typestore=ts)
        c_units = w.add_connection("/device_0/sensor_0/option/Depth Units/value", Float32.__msgtype__, typestore=ts)
        w.write(c_units, 1, ts.serialize_ros1(Float32(data=0.0001), Float32.__msgtype__))
        for k, (rgb, depth) in enumerate(frames):
            ns = 1_000_000_000 + k * 33_333_333
            hdr = Header(seq=k, stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="cam")
            h, w_ = depth.shape
            info = Info(header=hdr, height=h, width=w_, distortion_model="plumb_bob", D=np.zeros(5),
                        K=K_.reshape(-1), R=np.eye(3).reshape(-1), P=np.zeros(12), binning_x=0, binning_y=0,
                        roi=RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
            w.write(c_info, ns, ts.serialize_ros1(info, Info.__msgtype__))
            msg = Image(header=hdr, height=h, width=w_, encoding="rgb8", is_bigendian=0, step=w_ * 3,
                        data=np.ascontiguousarray(rgb).reshape(-1))
            w.write(c_rgb, ns, ts.serialize_ros1(msg, Image.__msgtype__))
            if depth_encoding == "16UC1":
                raw = np.round(depth * 10000).astype("<u2")
                msg = Image(header=hdr, height=h, width=w_, encoding="16UC1", is_bigendian=0, step=w_ * 2,
                            data=raw.view(np.uint8).reshape(-1))
            else:
                raw = depth.astype("<f4")
                msg = Image(header=hdr, height=h, width=w_, encoding="32FC1", is_bigendian=0, step=w_ * 4,
                            data=raw.view(np.uint8).reshape(-1))
            w.write(c_d, ns + 2_000_000, ts.serialize_ros1(msg, Image.__msgtype__))


def test_bag_reads_back_frame_for_frame(synthetic, tmp_path):
    _, frames, _, _ = synthetic
    _write_bag(tmp_path / "rec.bag", frames, K)
    rec = open_any(tmp_path / "rec.bag")
    assert len(rec) == len(frames) and np.allclose(rec.K, K) and rec.depth_scale == pytest.approx(0.1)
    for k, (rgb, depth) in enumerate(frames):
        r, d = rec.read(k)
        assert np.array_equal(r, rgb)
        assert np.abs(d - depth).max() < 0.00006  # 0.1 mm units
    assert np.allclose(np.diff(rec.timestamps), 1 / 30, atol=1e-6)


@pytest.mark.parametrize("case, msg", [
    ("empty", "holds no frames"),
    ("tum8", "not 16-bit"),
    ("tum_unmatched", "no frames"),
    ("plain8", "16-bit"),
    ("bag32", "depth must be 16-bit"),
    ("notbag", "cannot read ROS bag"),
])
def test_bad_inputs_are_one_line_errors(tmp_path, case, msg):
    rec = tmp_path / "rec"
    if case == "empty":
        rec.mkdir()
    elif case.startswith("tum"):
        _write_tum(rec, np.zeros((480, 640, 3), np.uint8), np.full((480, 640), 1.0, np.float32))  # TUM's default size
        if case == "tum8":
            cv2.imwrite(str(rec / "depth" / "1.010000.png"), np.full((480, 640), 90, np.uint8))
        else:
            (rec / "depth.txt").write_text("5.0 depth/1.010000.png\n")
    elif case == "plain8":
        rec.mkdir()
        bop.save_camera(rec / "camera.json", K, W, H, 1.0)
        bop.write_png(rec / "a_color.png", np.zeros((H, W, 3), np.uint8))
        bop.write_png(rec / "a_depth.png", np.full((H, W), 90, np.uint8))
    elif case == "bag32":
        rec = tmp_path / "rec.bag"
        _write_bag(rec, [(np.zeros((H, W, 3), np.uint8), np.full((H, W), 1.0, np.float32))], K,
                   depth_encoding="32FC1", depth_topic="/camera/depth/image_raw")
    else:
        rec = tmp_path / "rec.bag"
        rec.write_bytes(b"not a bag at all")
    with pytest.raises(ArgenError, match=msg):
        open_any(rec)
    r = CliRunner().invoke(app, ["capture", "--recording", str(rec), "--out", str(tmp_path / "o"), "--quiet"])
    assert r.exit_code == 2 and msg in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


# ------------------------------------------------------------------------------------ the real desk frame


@pytest.mark.skipif(not (SHARED / "recordings" / "tum_desk").is_dir() or not (SHARED / "lm" / "models").is_dir(),
                    reason="../shared/data (tum_desk recording, LineMOD models) is not available")
def test_tum_desk_objects_stand_on_the_desk_and_match_the_depth(tmp_path):
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["capture", "--recording", str(SHARED / "recordings" / "tum_desk"), "--models",
                                 str(SHARED / "lm" / "models"), "--out", str(out), "--quiet", "--seed", "1",
                                 "--noise", "none"])
    assert r.exit_code == 0, r.output
    scene = bop.load_scene(out, "train_pbr", 0)
    assert scene.im_ids == [0]
    _, real = open_any(SHARED / "recordings" / "tum_desk").read(0)
    Kc = scene.cameras[0].K
    models = {m.obj_id: m for m in load_models(out / "models")}
    depth = scene.read_depth(0)
    renderer = get_renderer(*real.shape[::-1])
    dists, contact_err = [], []
    for k, g in enumerate(scene.gts[0]):
        m = models[g.obj_id]
        # the object stands on the real desk top: the measured surface at its contact points is where they are
        v = m.hull_vertices @ g.R.T + g.t
        down = -scene.cameras[0].T_cam_world[:3, 2]  # camera frame: the support plane's normal points up
        low = v[v @ down > (v @ down).max() - 0.003]
        px = np.round(low[:, :2] / low[:, 2:] * Kc[[0, 1], [0, 1]] + Kc[:2, 2]).astype(int)
        ok = (px[:, 0] >= 0) & (px[:, 0] < real.shape[1]) & (px[:, 1] >= 0) & (px[:, 1] < real.shape[0])
        zr = real[px[ok, 1], px[ok, 0]]
        contact_err.append(np.abs(zr[zr > 0] - low[ok][zr > 0, 2]))
        # visible virtual pixels: the composited depth lies on the model (depth-to-model distance)
        vis, full = scene.read_mask(0, k), scene.read_mask(0, k, visib=False)
        rows, cols = np.nonzero(vis)
        p = backproject(rows, cols, depth[rows, cols].astype(np.float64), Kc)
        surf = trimesh.sample.sample_surface_even(m.mesh, 50000, seed=0)[0]
        dists.append(KDTree(surf).query((p - g.t) @ g.R)[0])
        # a real surface in front hides the object
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = g.R, g.t
        virt = renderer.render_depth([RenderItem(("obj", m.source, g.obj_id), m.mesh, T, 1)], Kc, np.eye(4),
                                     znear=0.05, zfar=6.0)
        front = full & (real > 0) & (real < virt - 0.03)
        assert not (front & vis).any()
    assert len(scene.gts[0]) >= 3
    c, d = np.concatenate(contact_err), np.concatenate(dists)
    assert len(c) >= 10 and np.median(c) < 0.015  # the desk's measured depth at the contact points (Kinect at 2.4 m)
    assert len(d) >= 100 and np.median(d) < 0.0015 and np.percentile(d, 99) < 0.004
    _, errs = validate_file(_label(out, tmp_path / "l.h5"))
    assert not errs, errs


def _label(out: Path, h5: Path) -> Path:
    r = CliRunner().invoke(app, ["label", str(out), "--out", str(h5), "--quiet"])
    assert r.exit_code == 0, r.output
    return h5
