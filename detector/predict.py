"""`detector predict`: poses for one input - a BOP frame, a depth PNG with intrinsics, or a PLY point cloud.

Inputs become the network's per-point features ``[X, Y, Z, R, G, B, Nx, Ny, Nz]`` exactly as ``argen label``
makes them (same back-projection, grid normals and subsampling; colour in [0, 1], zeros without an image).
Writes ``poses.json`` (metres, T_cam_model) and ``poses.png`` (3D boxes over the image, or over a splat of
the cloud seen from its own camera).
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

from argen import bop
from argen.features import BOX_EDGES, frame_points, palette, project
from detector.errors import DetectorError, argen_errors
from detector.geometry.types import Detection, GeometryConfig, ObjectInfo
from detector.infer import estimate

MAX_POINTS = 30000  # as argen label's default max_points
PLY_VIEW = (480, 640)  # (h, w) of the virtual camera a PLY cloud is drawn with


@dataclass
class PointInput:
    """One frame to predict on.

    features: (N,9) float32 [X,Y,Z metres, R,G,B in [0,1], unit normals]; K: (3,3) pixels; image: (H,W,3) uint8
    RGB to draw on, or None (the cloud is splatted); image_size: (h, w); name: for messages and the JSON.
    """

    features: np.ndarray
    K: np.ndarray
    image: np.ndarray | None
    image_size: tuple[int, int]
    name: str


def depth_features(depth: np.ndarray, K: np.ndarray, rgb: np.ndarray | None, max_points: int = MAX_POINTS,
                   max_depth: float | None = None, seed: int = 0) -> np.ndarray:
    """Per-point features of a depth image as ``argen label`` computes them.

    depth: (H,W) float32 metres, 0 = missing; K: (3,3); rgb: (H,W,3) uint8 or None. Returns (N,9) float32.
    """
    features = frame_points(depth, K, rgb, max_points, 0.0, np.random.default_rng(seed), max_depth).features
    if len(features) == 0:
        raise DetectorError("the depth image has no valid pixels"
                            + (f" within {max_depth:g} m (--max-depth)" if max_depth is not None else ""))
    return features


def parse_K(text: str) -> np.ndarray:
    """Intrinsics from "fx,fy,cx,cy" or 9 comma/space separated row-major values: (3,3) float64."""
    try:
        v = [float(x) for x in re.split(r"[,\s]+", text.strip()) if x]
    except ValueError:
        raise DetectorError(f"--K: cannot parse '{text}' (give fx,fy,cx,cy or 9 values)") from None
    if len(v) == 4:
        return np.array([[v[0], 0, v[2]], [0, v[1], v[3]], [0, 0, 1]], np.float64)
    if len(v) == 9:
        return np.array(v, np.float64).reshape(3, 3)
    raise DetectorError(f"--K: expected 4 (fx,fy,cx,cy) or 9 values, got {len(v)}")


def load_bop_frame(split_dir: Path, scene_id: int, im_id: int, **kw) -> PointInput:
    """A BOP frame ``SPLIT_DIR/scene_id/im_id`` (e.g. ``ds/test/000001`` + image 3)."""
    split_dir = Path(split_dir)
    scene = bop.load_scene(split_dir.parent, split_dir.name, scene_id)
    if im_id not in scene.cameras:
        raise DetectorError(f"{split_dir}/{scene_id:06d}: the scene has no camera for image {im_id}")
    depth = scene.read_depth(im_id)
    rgb = scene.read_rgb(im_id)
    rgb = rgb if rgb is not None and rgb.shape[:2] == depth.shape else None
    K = scene.cameras[im_id].K
    return PointInput(depth_features(depth, K, rgb, **kw), K, rgb, depth.shape, f"{split_dir}/{scene_id}/{im_id}")


def load_depth_png(path: Path, K: np.ndarray, depth_scale: float, rgb_path: Path | None = None, **kw) -> PointInput:
    """A depth PNG (value x depth_scale = millimetres, BOP convention) with intrinsics K (3,3), optional RGB."""
    depth = bop.read_depth(path, depth_scale)
    rgb = bop.read_rgb(rgb_path) if rgb_path else None
    if rgb is not None and rgb.shape[:2] != depth.shape:
        raise DetectorError(f"{rgb_path} is {rgb.shape[1]}x{rgb.shape[0]} but the depth is "
                            f"{depth.shape[1]}x{depth.shape[0]}")
    return PointInput(depth_features(depth, K, rgb, **kw), K, rgb, depth.shape, str(path))


def view_camera(xyz: np.ndarray, size: tuple[int, int] = PLY_VIEW) -> np.ndarray:
    """A pinhole K (3,3) at the origin (OpenCV axes) whose image of size (h, w) holds the points (N,3) metres."""
    h, w = size
    z = np.maximum(xyz[:, 2], 1e-3)
    u, v = xyz[:, 0] / z, xyz[:, 1] / z
    f = 0.45 * min(w / max(np.abs(u).max(), 1e-6), h / max(np.abs(v).max(), 1e-6))
    return np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], np.float64)


def load_ply(path: Path, max_points: int = MAX_POINTS, seed: int = 0, max_depth: float | None = None) -> PointInput:
    """A PLY point cloud in camera coordinates, metres (OpenCV axes); colours and normals when present,
    else normals estimated (open3d) and turned toward the camera. max_depth: keep points with 0 < z <= it."""
    # lazy: open3d loads in about a second; only PLY input needs it
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(path))
    xyz = np.asarray(pc.points)
    if len(xyz) == 0:
        raise DetectorError(f"{path}: no points (not a PLY point cloud?)")
    if np.median(xyz[:, 2]) > 20:
        raise DetectorError(f"{path}: points are expected in metres in the camera frame (median z "
                            f"{np.median(xyz[:, 2]):.0f}: millimetres?)")
    if not pc.has_normals():
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(16))
        pc.orient_normals_towards_camera_location(np.zeros(3))
    normals = np.asarray(pc.normals)
    colour = np.asarray(pc.colors) if pc.has_colors() else np.zeros_like(xyz)
    if max_depth is not None:
        near = (xyz[:, 2] > 0) & (xyz[:, 2] <= max_depth)
        if not near.any():
            raise DetectorError(f"{path}: no point within {max_depth:g} m (--max-depth)")
        xyz, normals, colour = xyz[near], normals[near], colour[near]
    keep = np.sort(np.random.default_rng(seed).choice(len(xyz), max_points, replace=False)) \
        if len(xyz) > max_points else np.arange(len(xyz))
    feats = np.concatenate([xyz, colour, normals], axis=1)[keep].astype(np.float32)
    return PointInput(feats, view_camera(feats[:, :3]), None, PLY_VIEW, str(path))


def load_input(spec: str, K: str | None = None, depth_scale: float | None = None, camera: Path | None = None,
               rgb: Path | None = None, max_points: int = MAX_POINTS, seed: int = 0,
               max_depth: float | None = None) -> PointInput:
    """The input named on the command line: ``*.ply``, a depth ``*.png`` (intrinsics from --K, --camera, the
    image's own camera in its BOP scene, or a camera.json found near it: :mod:`argen.bop`), or a BOP frame
    ``SPLIT_DIR/SCENE_ID/IM_ID``; its points within ``max_depth`` metres along z (None: all), as ``argen label``'s
    ``--max-depth`` keeps them."""
    p = Path(spec)
    if p.suffix.lower() == ".ply":
        if not p.is_file():
            raise DetectorError(f"point cloud not found: {p}")
        return load_ply(p, max_points, seed, max_depth)
    if p.suffix.lower() == ".png":
        if not p.is_file():
            raise DetectorError(f"depth image not found: {p}")
        scale = 1.0
        with argen_errors():
            frame_cam = bop.depth_image_camera(p) if K is None and camera is None else None
        if K is not None:
            Km = parse_K(K)
        elif frame_cam is not None:
            Km, scale = frame_cam.K, frame_cam.depth_scale
        else:
            cam = camera or bop.camera_file_near(p)
            if cam is None:
                raise DetectorError(f"{p}: give the intrinsics with --K fx,fy,cx,cy or --camera camera.json")
            with argen_errors():
                c = bop.load_camera(cam)
            Km, scale = c.K, (c.depth_scale if c.depth_scale is not None else 1.0)
        return load_depth_png(p, Km, depth_scale if depth_scale is not None else scale, rgb,
                              max_points=max_points, seed=seed, max_depth=max_depth)
    parts = p.parts
    if len(parts) >= 3 and parts[-1].isdigit() and parts[-2].isdigit():
        return load_bop_frame(Path(*parts[:-2]), int(parts[-2]), int(parts[-1]), max_points=max_points, seed=seed,
                              max_depth=max_depth)
    raise DetectorError(f"cannot tell what {spec} is: give a .ply cloud, a depth .png or a BOP frame "
                        "SPLIT_DIR/SCENE_ID/IM_ID")


def splat_cloud(features: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H,W,3) uint8 view of the points (N,9) through K (3,3), size (h, w): colour when present, else grey shading
    by normal; nearer points drawn over farther ones."""
    h, w = size
    uv = np.round(project(features[:, :3], K)).astype(np.int64)
    ok = (features[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    col = features[:, 3:6]
    if not np.any(col > 0):
        col = np.repeat(0.25 + 0.7 * np.abs(features[:, 8:9]), 3, axis=1)
    order = np.argsort(-features[ok, 2])  # far first, near overwrites
    img = np.zeros((h, w, 3), np.uint8)
    idx = np.flatnonzero(ok)[order]
    img[uv[idx, 1], uv[idx, 0]] = np.clip(col[idx] * 255 + 0.5, 0, 255).astype(np.uint8)
    k = int(np.clip(np.sqrt(h * w / max(len(idx), 1)), 3, 9))  # dots about as wide as the point spacing
    return cv2.dilate(img, np.ones((k, k), np.uint8))


def draw_detections(image: np.ndarray, K: np.ndarray, detections: list[Detection], objects: ObjectInfo,
                    names: dict[int, str] | None = None) -> np.ndarray:
    """The image (H,W,3) uint8 with each detection's 3D box (model control points under its pose) drawn."""
    img = image.copy()
    cols = palette(max(len(detections), 1))
    for k, d in enumerate(detections):
        cps = objects.control_points[d.obj_id] @ d.R.T + d.t
        if np.any(cps[:, 2] <= 0.01):
            continue
        uv = np.round(project(cps, K) * 16).astype(np.int64)
        colour = tuple(int(v) for v in cols[k])
        for a, b in BOX_EDGES:
            cv2.line(img, tuple(map(int, uv[a])), tuple(map(int, uv[b])), colour, 2, cv2.LINE_AA, shift=4)
        label = f"{(names or {}).get(d.obj_id, d.obj_id)} {d.score:.2f}"
        cv2.putText(img, label, (int(uv[8][0] / 16) + 5, int(uv[8][1] / 16) - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    colour, 1, cv2.LINE_AA)
    return img


def detection_json(d: Detection, name: str) -> dict:
    """One detection for poses.json: R (3,3), t (3,) metres, T_cam_model (4,4), score, support, refined (the ICP
    pose was kept) and icp ("accepted", "rejected", "skipped"; "" without --icp)."""
    return {"obj_id": int(d.obj_id), "name": name, "score": float(d.score), "R": d.R.tolist(), "t": d.t.tolist(),
            "T_cam_model": d.pose.tolist(), "support": int(d.support), "refined": bool(d.refined), "icp": d.icp}


def predict(predictor, inp: PointInput, objects: ObjectInfo, out_dir: Path, cfg: GeometryConfig | None = None,
            names: dict[int, str] | None = None, poser=None, max_depth: float | None = None,
            net_dtype: str | None = None) -> dict:
    """Run ``predictor`` (see :mod:`detector.infer`) and the geometry (with a two-stage model's ``poser``)
    on ``inp``; write poses.json and poses.png into ``out_dir``. Returns the JSON content. max_depth: the working
    volume ``inp`` was read with (metres, None: all points), recorded in the JSON; net_dtype: the networks' number
    format the predictor and poser were made with (:mod:`detector.net_dtype`), recorded (None: not said)."""
    cfg = cfg or GeometryConfig()
    t0 = time.perf_counter()
    preds = predictor(SimpleNamespace(features=inp.features, scene_id=0, im_id=0))
    timings = dict(preds.timings)
    dets, refined = estimate(preds, objects, cfg, timings, inp.features[:, :3], poser, inp.features)
    final = refined if refined is not None else dets
    timings["total"] = time.perf_counter() - t0
    names = names or {}
    out = {"input": inp.name, "units": "metres; R, t and T_cam_model map model points into the camera frame",
           "icp": bool(cfg.icp), "tau": cfg.tau, "max_depth": max_depth, "net_dtype": net_dtype,
           "K": np.asarray(inp.K).tolist(),
           "detections": [detection_json(d, names.get(d.obj_id, str(d.obj_id))) for d in final],
           "timing_ms": {k: 1000 * v for k, v in timings.items()}}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "poses.json").write_text(json.dumps(out, indent=2) + "\n")
    base = inp.image if inp.image is not None else splat_cloud(inp.features, inp.K, inp.image_size)
    img = draw_detections(base, inp.K, final, objects, names)
    if not cv2.imwrite(str(out_dir / "poses.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
        raise DetectorError(f"cannot write {out_dir / 'poses.png'}")
    return out
