"""The paper's test-scene replacement (``argen replace``): fine-tuning frames made from a BOP test set.

For a random ``fraction`` of the frames with ground truth, the target object (``obj_id``, default each
frame's first GT instance) is taken out of the scene and put back rotated about the working-plane normal
every ``step_deg`` degrees (360 / 30 = 12 copies per frame):

1. Removal. The model is rendered at its GT pose; the pixels of its silhouette (grown by
   ``REMOVE_GROW_PX`` for mixed edge pixels) whose measured depth is not in front of the rendered surface
   (``REMOVE_TOL``) are the object's own points. Real occluders in front of it are kept.
2. Fill. The working plane is fitted (RANSAC, then least squares) to the valid points in a ring around
   the silhouette; a removed pixel gets the depth where its ray meets that plane, when that lies behind the
   removed surface, else it is marked invalid (0). The colour is inpainted (OpenCV Telea). So the hole
   shows the table plane as a depth sensor would have seen it without the object; whatever other surface
   was hidden behind the object (rare on a table top) is not recovered.
3. Insertion. The rotation axis is the working-plane normal through the object's box centre: the world z
   axis of the frame's camera pose when scene_camera.json gives one (board frame, argen datasets), else
   the fitted plane's normal. Each copy is rendered and z-composited into the filled frame (a real surface
   in front hides it), and sensor noise (argen.sim.noise, the template's model) goes on the changed pixels.

Output: BOP layout (same split name), image ``im_id * n + k`` for copy k of input image ``im_id``;
other GT instances keep their poses and have their visible masks reduced by the inserted copy.
``replace_log.json`` says, per output frame, its source, angle, axis source and fill statistics.
"""

from __future__ import annotations

import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from argen import __version__, bop
from argen.config import NoiseConfig
from argen.errors import ArgenError
from argen.fileio import write_json
from argen.models.meshimport import load_any_models
from argen.models.objects import ObjectModel, write_models
from argen.real.support import fit_plane, pixel_rays
from argen.sim.capture import composite
from argen.sim.noise import apply_noise
from argen.sim.render import Light, RenderItem, get_renderer

REMOVE_GROW_PX = 2  # silhouette growth for the removal, pixels
REMOVE_TOL = 0.015  # metres: a measured point this far in front of the rendered object is an occluder, kept
RING_PX = (6, 30)  # plane-fit ring around the silhouette, pixels from it
PLANE_INLIER = 0.005  # metres, RANSAC inlier distance
INSERT_MARGIN = 0.003  # metres: a real surface must be this far in front of the inserted copy to hide it
Z_NEAR, Z_FAR = 0.05, 6.0
_HEADLIGHT = Light("directional", 2.5, np.ones(3), np.diag([1.0, -1.0, -1.0, 1.0]))  # shines along +z_cam


@dataclass
class ReplaceSummary:
    """What a replace run did: source frames used, frames written, wall time (seconds), and notes for the
    user (how a plain mesh folder given as the models was imported)."""

    source_frames: int
    written: int
    seconds: float
    notes: list[str] = field(default_factory=list)

    def line(self) -> str:
        per = self.seconds / self.written if self.written else 0.0
        return (f"{self.written} frames written from {self.source_frames} source frames; "
                f"{per:.3f} s per frame")


# ----------------------------------------------------------------------------------- geometry


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about unit ``axis`` (3,) (Rodrigues)."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def rotated_pose(T_cam_obj: np.ndarray, axis: np.ndarray, centre: np.ndarray, angle: float) -> np.ndarray:
    """(4, 4) pose of the object turned by ``angle`` radians about the camera-frame line (centre (3,), axis (3,))."""
    Rk = rotation_about(axis, angle)
    S = np.eye(4)
    S[:3, :3] = Rk
    S[:3, 3] = centre - Rk @ centre
    return S @ T_cam_obj


def _ring(mask: np.ndarray, inner: int, outer: int) -> np.ndarray:
    k = lambda r: cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))  # noqa: E731
    m = mask.astype(np.uint8)
    return (cv2.dilate(m, k(outer)) > 0) & ~(cv2.dilate(m, k(inner)) > 0)


def remove_object(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, obj_depth: np.ndarray,
                  keep_out: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, dict]:
    """Take an object's points out of a frame and fill the hole from the surrounding plane.

    rgb: (H, W, 3) uint8; depth: (H, W) float32 metres, 0 = none; obj_depth: (H, W) float32 metres, the
    object rendered alone at its GT pose (0 = not hit); keep_out: (H, W) bool pixels not to use for the
    plane fit (other objects). Returns (rgb, depth, info) with info: removed (H, W) bool, plane (n, c)
    or None, filled_px, invalid_px.
    """
    sil = obj_depth > 0
    grow = cv2.dilate(sil.astype(np.uint8), np.ones((2 * REMOVE_GROW_PX + 1,) * 2, np.uint8)) > 0
    near = np.where(sil, obj_depth, np.inf).astype(np.float32)
    near = cv2.erode(near, np.ones((2 * REMOVE_GROW_PX + 1,) * 2, np.uint8))  # nearest object depth around
    removed = grow & (depth > 0) & (depth >= near - REMOVE_TOL)
    ring = _ring(sil, *RING_PX) & (depth > 0) & ~keep_out
    rows, cols = np.nonzero(ring)
    plane = fit_plane(pixel_rays(rows, cols, K) * depth[rows, cols, None], rng, PLANE_INLIER)
    out = depth.copy()
    rr, cc = np.nonzero(removed)
    out[rr, cc] = 0.0
    if plane is not None:
        n, c = plane[0], plane[1]
        denom = pixel_rays(rr, cc, K) @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(np.abs(denom) > 1e-9, -c / denom, 0.0)
        ok = (z > 0) & (z >= depth[rr, cc] - REMOVE_TOL)
        out[rr[ok], cc[ok]] = z[ok]
    rgb = cv2.inpaint(rgb, removed.astype(np.uint8), 5, cv2.INPAINT_TELEA) if removed.any() else rgb.copy()
    filled = int(((out > 0) & removed).sum())
    info = {"removed": removed, "plane": None if plane is None else (plane[0], plane[1]),
            "filled_px": filled, "invalid_px": int(removed.sum()) - filled}
    return rgb, out.astype(np.float32), info


# ------------------------------------------------------------------------------------- frames


def select_frames(frames: list[tuple[int, int]], fraction: float, rng: np.random.Generator) -> list[tuple[int, int]]:
    """A random ``fraction`` of ``frames`` [(scene_id, im_id)] (at least one), in sorted order."""
    if not 0 < fraction <= 1:
        raise ArgenError(f"--fraction must be in (0, 1], got {fraction:g}")
    k = max(1, int(round(fraction * len(frames))))
    pick = rng.choice(len(frames), size=k, replace=False)
    return sorted(frames[int(i)] for i in pick)


def _items(objs: dict[int, ObjectModel], gts, poses) -> list[RenderItem]:
    return [RenderItem(key=("obj", objs[g.obj_id].source, g.obj_id), mesh=objs[g.obj_id].mesh, T_world_obj=T,
                       seg_id=i + 1) for i, (g, T) in enumerate(zip(gts, poses))]


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def replace_frame(renderer, scene: bop.BopScene, im_id: int, target: int, objs: dict[int, ObjectModel],
                  step_deg: float, noise: NoiseConfig | None, rng: np.random.Generator) -> list[dict]:
    """The rotated copies of one frame: one dict per copy with rgb, depth, gts [(obj_id, R, t)], masks (full,
    visible), outside ({gt index: the part of its silhouette beyond the image edge}), log."""
    cam = scene.cameras[im_id]
    K = cam.K
    rgb = scene.read_rgb(im_id)
    if rgb is None:
        raise ArgenError(f"scene {scene.scene_id} image {im_id} has no colour image")
    depth = scene.read_depth(im_id)
    gts = scene.gts[im_id]
    poses = [_pose(g.R, g.t) for g in gts]
    I4 = np.eye(4)
    items = _items(objs, gts, poses)
    alone = renderer.render_depth(items[target:target + 1], K, I4, Z_NEAR, Z_FAR)
    full0 = renderer.full_masks(items, K, I4, Z_NEAR, Z_FAR)
    beyond0 = renderer.outside_silhouettes(items, K, I4, full0, Z_NEAR, Z_FAR)
    others = np.zeros(depth.shape, bool)
    for i in range(len(gts)):
        if i != target:
            others |= full0[i + 1]
    rgb0, depth0, info = remove_object(rgb, depth, K, alone, others, rng)
    if cam.T_cam_world is not None:
        axis, axis_from = cam.T_cam_world[:3, 2], "camera pose"
    elif info["plane"] is not None:
        axis, axis_from = info["plane"][0], "plane fit"
    else:
        raise ArgenError(f"scene {scene.scene_id} image {im_id}: no working plane found around the object "
                         "and no camera pose to take its normal from")
    obj = objs[gts[target].obj_id]
    centre = poses[target][:3, :3] @ obj.control_points[8] + poses[target][:3, 3]
    vis_other = {}  # visible masks of the other instances: the dataset's, else rendered among the GT objects
    seg_others = None
    for i in range(len(gts)):
        if i != target:
            m = scene.read_mask(im_id, i, visib=True)
            if m is None and seg_others is None:
                rest = [it for j, it in enumerate(items) if j != target]
                seg_others = renderer.render(rest, K, I4, znear=Z_NEAR, zfar=Z_FAR, seg=True).seg
            vis_other[i] = m if m is not None else seg_others == i + 1
    n_copies = int(round(360.0 / step_deg))
    out = []
    for k in range(n_copies):
        angle = np.deg2rad(k * step_deg)
        T_k = rotated_pose(poses[target], axis, centre, angle)
        item = RenderItem(items[target].key, obj.mesh, T_k, seg_id=1)
        ob = renderer.render([item], K, I4, lights=[_HEADLIGHT], ambient=0.35, znear=Z_NEAR, zfar=Z_FAR, seg=True)
        rgb_k, depth_k, seg, front = composite(rgb0, depth0, ob, INSERT_MARGIN)
        changed = front | info["removed"]
        if noise is not None and noise.enabled:
            depth_k = np.where(changed, apply_noise(depth_k, K, noise, rng, rgb=rgb_k), depth_k).astype(np.float32)
        masks, gt_out, outside = [], [], {}
        for i, g in enumerate(gts):
            if i == target:
                masks.append((ob.depth > 0, seg == 1))
                gt_out.append((g.obj_id, T_k[:3, :3], T_k[:3, 3]))
                beyond = renderer.outside_silhouettes([item], K, I4, {1: ob.depth > 0}, Z_NEAR, Z_FAR).get(1)
            else:
                masks.append((full0[i + 1], vis_other[i] & ~front))
                gt_out.append((g.obj_id, g.R, g.t))
                beyond = beyond0.get(i + 1)
            if beyond is not None:
                outside[i] = beyond
        log = {"src_scene_id": scene.scene_id, "src_im_id": im_id, "target_gt_index": target,
               "obj_id": gts[target].obj_id, "angle_deg": float(k * step_deg), "axis": axis_from,
               "axis_cam": [float(v) for v in axis], "removed_px": int(info["removed"].sum()),
               "filled_px": info["filled_px"], "invalid_px": info["invalid_px"],
               "fill": "plane" if info["plane"] is not None else "invalid"}
        out.append({"rgb": rgb_k, "depth": depth_k, "gts": gt_out, "masks": masks, "outside": outside, "log": log,
                    "T_cam_world": cam.T_cam_world})
    return out


# -------------------------------------------------------------------------------------- dataset


def _prepare(out: Path, overwrite: bool, split: str) -> None:
    if out.exists() and not out.is_dir():
        raise ArgenError(f"output path {out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise ArgenError(f"output folder {out} is not empty; use --overwrite or choose another --out")
        for name in ("argen.json", "replace_log.json", bop.CAMERA_FILE):
            (out / name).unlink(missing_ok=True)
        for name in ("models", split):
            if (out / name).is_dir():
                shutil.rmtree(out / name)
    out.mkdir(parents=True, exist_ok=True)


def replace_dataset(dataset: str | Path, out: str | Path, split: str = "test", models: str | Path | None = None,
                    obj_id: int | None = None, fraction: float = 0.1, step_deg: float = 30.0, seed: int = 0,
                    noise: NoiseConfig | None = None, overwrite: bool = False, progress: bool = True,
                    depth_scale: float = 0.1) -> ReplaceSummary:
    """Write the rotated-copy frames of a random ``fraction`` of ``dataset``'s frames to ``out`` (BOP).

    obj_id: target object (frames without it are skipped); None = each frame's first GT instance.
    step_deg: rotation step (360 / step_deg copies). noise: sensor model for the changed pixels, None = off.
    depth_scale: BOP depth_scale of the written depth PNGs (mm per unit).
    """
    t_start = time.perf_counter()
    dataset, out = Path(dataset), Path(out)
    if not 0 < step_deg <= 360 or abs(360.0 / step_deg - round(360.0 / step_deg)) > 1e-6:
        raise ArgenError(f"--step-deg must divide 360, got {step_deg:g}")
    if not dataset.is_dir():
        raise ArgenError(f"dataset folder not found: {dataset}")
    models_list, notes = load_any_models(Path(models) if models else dataset / "models")
    objs = {o.obj_id: o for o in models_list}
    scenes = {sid: bop.load_scene(dataset, split, sid) for sid in bop.list_scenes(dataset, split)}
    candidates, targets = [], {}
    for sid, sc in scenes.items():
        for im in sc.im_ids:
            ids = [g.obj_id for g in sc.gts[im]]
            t = 0 if obj_id is None and ids else (ids.index(obj_id) if obj_id in ids else None)
            if t is None:
                continue
            missing = [i for i in ids if i not in objs]
            if missing:
                raise ArgenError(f"no model for object {missing[0]} (scene {sid} image {im}); give --models")
            candidates.append((sid, im))
            targets[(sid, im)] = t
    if not candidates:
        raise ArgenError(f"no frame of {dataset / split} has ground truth" + (f" for object {obj_id}" if obj_id else ""))
    rng = np.random.default_rng(seed)
    chosen = select_frames(candidates, fraction, rng)
    _prepare(out, overwrite, split)
    write_models(out / "models", list(objs.values()))
    if (dataset / bop.CAMERA_FILE).is_file():
        shutil.copyfile(dataset / bop.CAMERA_FILE, out / bop.CAMERA_FILE)
    write_json(out / "argen.json", {"argen_version": __version__, "kind": "replace", "source": str(dataset.resolve()),
                                    "split": split, "fraction": fraction, "step_deg": step_deg, "seed": seed,
                                    "noise": noise is not None and noise.enabled, "obj_id": obj_id,
                                    "units": "BOP (mm)", "frames": [list(c) for c in chosen]})
    n = int(round(360.0 / step_deg))
    log, written = [], 0
    jsons = bop.SceneJsons(out, split)

    for sid, im in tqdm(chosen, desc="replace", unit="frame", disable=not progress, file=sys.stderr):
        sc = scenes[sid]
        h, w = sc.read_depth(im).shape
        renderer = get_renderer(w, h)
        frng = np.random.default_rng(np.random.SeedSequence([seed, sid, im]))
        copies = replace_frame(renderer, sc, im, targets[(sid, im)], objs, step_deg, noise, frng)
        for k, c in enumerate(copies):
            oim = im * n + k
            _write_frame(out, split, sid, oim, c, depth_scale)
            jsons.add(sid, oim, bop.camera_entry(sc.cameras[im].K, depth_scale, c["T_cam_world"]),
                      [bop.gt_entry(o, R, t) for o, R, t in c["gts"]],
                      [bop.gt_info_entry(mf, mv, c["depth"], c["outside"].get(g)) for g, (mf, mv) in enumerate(c["masks"])])
            log.append({"scene_id": sid, "im_id": oim, **c["log"]})
            written += 1
    jsons.flush()
    write_json(out / "replace_log.json", {"frames": log}, indent=1)
    return ReplaceSummary(len(chosen), written, time.perf_counter() - t_start, notes)


def _write_frame(root: Path, split: str, sid: int, im: int, c: dict, depth_scale: float) -> None:
    for g, (m_full, m_vis) in enumerate(c["masks"]):
        bop.write_mask(bop.mask_path(root, split, sid, im, g, visib=False), m_full)
        bop.write_mask(bop.mask_path(root, split, sid, im, g, visib=True), m_vis)
    bop.write_depth(bop.image_path(root, split, sid, im, "depth"), c["depth"], depth_scale)
    bop.write_rgb(root, split, sid, im, c["rgb"])
