"""Simulated AR capture: orchestrates scene → camera → render → AR step → noise → BOP files.

Per frame, as a real AR capture does it: the background (table, board, clutter) is rendered from the
true camera pose; the markers are detected in that image and the camera pose is estimated from the
board; the virtual objects are rendered from the *estimated* pose and z-composited into the
background, so marker-tracking error shows up as objects slightly off the table. Ground truth is the
object pose in the estimated camera frame, so labels agree exactly with the rendered object pixels.

Frames are numbered by their attempt index ``i`` (scene ``i // frames_per_scene``, image
``i % frames_per_scene``); a rejected frame leaves a gap in the image ids and is logged. Every frame
draws from its own generator seeded by (seed, i), so workers, shards and resumed runs give the same
frames. Progress is committed to ``capture_log.json`` (written last, atomically); a killed run
resumes with the frames not yet in it.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import re
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from argen import __version__, bop
from argen.config import TemplateConfig, simulation_K, to_dict
from argen.errors import ArgenError
from argen.fileio import read_json, remove_stray_temps, write_json
from argen.models.objects import ObjectModel, write_models, write_models_eval
from argen.sim.ar import estimate_board_pose, pose_error
from argen.sim.board import Board
from argen.sim.camera import intrinsics, sample_view
from argen.sim.colour import apply_colour
from argen.sim.noise import apply_noise
from argen.sim.render import get_renderer
from argen.sim.scene import build_scene

STAGES = ("scene", "render", "ar", "noise", "write")


@dataclass
class CaptureRequest:
    """What to capture. frames: number of frame attempts (accepted + rejected); out: dataset root."""

    cfg: TemplateConfig
    objects: list[ObjectModel]
    out: Path
    frames: int
    workers: int = 1
    models_source: str = "builtin"
    overwrite: bool = False
    progress: bool = True
    shard: tuple[int, int] = (0, 1)  # (I, N): this run makes the frames with index % N == I (see argen.merge)


@dataclass
class FrameRecord:
    """What a worker returns for one frame: JSON entries for the scene files and the log."""

    index: int
    scene_id: int
    im_id: int
    accepted: bool
    log: dict
    camera: dict | None = None
    gt: list | None = None
    gt_info: list | None = None
    timing: dict = field(default_factory=dict)


def frame_rngs(seed: int, index: int, n: int = 4) -> list[np.random.Generator]:
    """Independent generators for the stages of frame ``index`` (scene, camera, noise, spare)."""
    return [np.random.default_rng(s) for s in np.random.SeedSequence([seed, index]).spawn(n)]


class FrameMaker:
    """Per-process state: the renderer, the board and the objects; makes and writes one frame."""

    def __init__(self, cfg: TemplateConfig, objects: list[ObjectModel], out: Path):
        self.cfg = cfg
        self.objects = objects
        self.out = Path(out)
        self.board = Board.from_config(cfg.board)
        self.K = intrinsics(cfg.camera)  # written to the files
        self.K_sim = simulation_K(self.K, cfg.output.pixel_centres)  # the images are made with this one
        self.renderer = get_renderer(cfg.camera.width, cfg.camera.height)
        self.renderer.reset()  # the process's renderer may hold other meshes: same seed, same bytes, whatever ran before

    def background(self, index: int, timing: dict | None = None) -> tuple:
        """The scene of frame ``index`` and its background seen from the true camera.

        Returns (scene, T_true (4, 4) world->camera, view dict, RenderOutput of the background).
        """
        cfg, K, cam = self.cfg, self.K_sim, self.cfg.camera
        rng_scene, rng_cam, _, _ = frame_rngs(cfg.seed, index)
        t0 = time.perf_counter()
        scene = build_scene(cfg, self.objects, self.board, rng_scene)
        T_true, view = sample_view(cam, rng_cam)
        t1 = time.perf_counter()
        bg = self.renderer.render(scene.background, K, T_true, lights=scene.lights, ambient=scene.ambient,
                                  znear=cam.z_near, zfar=cam.z_far)
        if timing is not None:
            timing["scene"], timing["render"] = t1 - t0, time.perf_counter() - t1
        return scene, T_true, view, bg

    def simulate(self, index: int) -> tuple[dict, dict]:
        """Simulate frame ``index``: returns (arrays, metadata). Arrays are empty for a rejected frame."""
        cfg, K = self.cfg, self.K_sim
        _, _, rng_noise, rng_colour = frame_rngs(cfg.seed, index)
        timing = {}
        scene, T_true, view, bg = self.background(index, timing)
        t2 = time.perf_counter()
        est = estimate_board_pose(bg.rgb, self.board, K, cfg.ar)
        timing["ar"] = time.perf_counter() - t2
        log = {"index": index, "view": view, "markers": est.n_markers, "reproj_px": finite_or_none(est.reproj_px),
               "placed": scene.info["placed"], "unplaced": scene.info["unplaced"]}
        if est.T_cam_board is not None:
            rot, trans = pose_error(est.T_cam_board, T_true)
            log["board_pose_error"] = {"rot_deg": float(rot), "trans_mm": float(trans * 1000)}
        if not accept(log, est, scene):
            return {}, {"log": log, "timing": timing}
        T_est = est.T_cam_board  # board frame = world frame
        arrays = self.insert(scene, T_est, bg.rgb, bg.depth, rng_noise, timing)
        arrays["rgb"], drawn = apply_colour(arrays["rgb"], cfg.colour, rng_colour)  # the colour camera's artefacts
        if drawn:
            log["colour"] = drawn
        return arrays, {"log": log, "timing": timing, "T_est": T_est}

    def insert(self, scene, T_est: np.ndarray, rgb: np.ndarray, depth: np.ndarray, rng_noise: np.random.Generator,
               timing: dict, margin: float = 0.0, noise_virtual_only: bool = False) -> dict:
        """Render the scene's placed objects from ``T_est`` and z-composite them into (rgb, depth).

        rgb: (H, W, 3) uint8; depth: (H, W) float32 metres, 0 = none. A virtual pixel shows unless the
        background is more than ``margin`` metres in front of it. Sensor noise (if enabled) goes on the
        whole composite, or only on the virtual pixels (``noise_virtual_only``: the background is a real,
        already noisy, measurement). Returns the arrays ``write`` takes: rgb, depth, gts, masks
        (full, visible) and outside ({gt index: what of a silhouette lies beyond the image edge}).
        """
        cfg, K, cam = self.cfg, self.K_sim, self.cfg.camera
        t4 = time.perf_counter()
        items = scene.object_items()
        ob = self.renderer.render(items, K, T_est, lights=scene.lights, ambient=scene.ambient,
                                  znear=cam.z_near, zfar=cam.z_far, seg=True)
        full = self.renderer.full_masks(items, K, T_est, znear=cam.z_near, zfar=cam.z_far)
        beyond = self.renderer.outside_silhouettes(items, K, T_est, full, znear=cam.z_near, zfar=cam.z_far)
        rgb, depth, seg, front = composite(rgb, depth, ob, margin)
        t5 = time.perf_counter()
        timing["render"] = timing.get("render", 0.0) + t5 - t4
        if cfg.noise.enabled:
            noisy = apply_noise(depth, K, cfg.noise, rng_noise, rgb=rgb)
            depth = np.where(front, noisy, depth).astype(np.float32) if noise_virtual_only else noisy
        timing["noise"] = time.perf_counter() - t5
        gts, masks = [], []
        for i, p in enumerate(scene.placements):
            T_cam_obj = T_est @ p.T_world_obj
            gts.append((p.obj.obj_id, T_cam_obj[:3, :3], T_cam_obj[:3, 3]))
            m_full = full.get(i + 1, np.zeros_like(front))
            masks.append((m_full, seg == i + 1))
        outside = {i: beyond[i + 1] for i in range(len(scene.placements)) if i + 1 in beyond}
        return {"rgb": rgb, "depth": depth, "gts": gts, "masks": masks, "outside": outside}

    def make(self, index: int) -> FrameRecord:
        """Simulate frame ``index`` and write its image files; the JSON entries are returned."""
        arrays, meta = self.simulate(index)
        return self.write(index, arrays, meta)

    def write(self, index: int, arrays: dict, meta: dict) -> FrameRecord:
        """Write one frame's image files (nothing for a rejected frame); the JSON entries are returned."""
        cfg = self.cfg
        scene_id, im_id = divmod(index, cfg.output.frames_per_scene)
        log, timing = meta["log"], meta["timing"]
        log.update({"scene_id": scene_id, "im_id": im_id})
        if not log["accepted"]:
            return FrameRecord(index, scene_id, im_id, False, log, timing=timing)
        t0 = time.perf_counter()
        root, split, ds = self.out, cfg.output.split, cfg.output.depth_scale
        depth = arrays["depth"]
        gt_entries, info_entries = [], []
        for g, ((obj_id, R, t), (m_full, m_vis)) in enumerate(zip(arrays["gts"], arrays["masks"])):
            bop.write_mask(bop.mask_path(root, split, scene_id, im_id, g, visib=False), m_full)
            bop.write_mask(bop.mask_path(root, split, scene_id, im_id, g, visib=True), m_vis)
            gt_entries.append(bop.gt_entry(obj_id, R, t))
            info_entries.append(bop.gt_info_entry(m_full, m_vis, depth, arrays.get("outside", {}).get(g)))
        bop.write_depth(bop.image_path(root, split, scene_id, im_id, "depth"), depth, ds)
        bop.write_rgb(root, split, scene_id, im_id, arrays["rgb"])
        timing["write"] = time.perf_counter() - t0
        camera = bop.camera_entry(self.K, ds, meta["T_est"])
        return FrameRecord(index, scene_id, im_id, True, log, camera, gt_entries, info_entries, timing)


def accept(log: dict, est, scene) -> bool:
    """Whether a frame is kept: an accepted board pose and at least one placed object; noted in ``log``."""
    return accept_world(log, est.accepted, est.reason, scene)


def accept_world(log: dict, accepted: bool, reason: str, scene) -> bool:
    """Whether a frame is kept: its world (board or support plane) ``accepted`` (else why not: ``reason``) and at
    least one object placed in ``scene``; noted in ``log``."""
    if accepted and not scene.placements:
        accepted, reason = False, "no object could be placed"
    log["accepted"], log["reason"] = bool(accepted), reason
    return bool(accepted)


def composite(rgb: np.ndarray, depth: np.ndarray, ob, margin: float = 0.0):
    """Z-composite a rendered layer ``ob`` (RenderOutput with seg) into a background image.

    rgb: (H, W, 3) uint8; depth: (H, W) float32 metres, 0 = none. A layer pixel shows where it was hit
    and the background is missing or not more than ``margin`` metres in front of it. Returns
    (rgb, depth float32, seg (H, W) int32 with 0 where the background shows, front (H, W) bool).
    """
    front = (ob.depth > 0) & ((depth == 0) | (ob.depth < depth + margin))
    rgb = np.where(front[..., None], ob.rgb, rgb)
    depth = np.where(front, ob.depth, depth).astype(np.float32)
    seg = np.where(front, ob.seg, 0)
    return rgb, depth, seg, front


def finite_or_none(v):
    """``v`` as a float for JSON, or None when it is missing or not finite."""
    return None if v is None or not np.isfinite(v) else float(v)


# --------------------------------------------------------------------------------- dataset files


def dataset_signature(req: CaptureRequest, extra: dict | None = None) -> dict:
    """What must match for a run to resume into an existing output folder (and for shards to merge)."""
    sig = {
        "config": to_dict(req.cfg),
        "models": req.models_source,
        "objects": [o.obj_id for o in req.objects],
    }
    if req.shard[1] > 1:
        sig["shard"] = list(req.shard)
    return {**sig, **(extra or {})}


def shard_indices(frames: int, shard: tuple[int, int]) -> list[int]:
    """Frame indices that shard ``(I, N)`` makes: every N-th frame starting at I (disjoint, covering all)."""
    i, n = shard
    if not (n >= 1 and 0 <= i < n):
        raise ArgenError(f"--shard must be I/N with 0 <= I < N, got {i}/{n}")
    return list(range(i, frames, n))


def prepare_output(req: CaptureRequest, kind: str = "capture-sim", extra: dict | None = None) -> dict[int, dict]:
    """Create or check the output folder; returns the capture log entries already done (by index).

    kind: what made the dataset (argen.json "kind"); extra: more signature entries that must match to resume.
    """
    out = req.out
    meta_p = out / "argen.json"
    sig = dataset_signature(req, extra)
    if out.exists() and not out.is_dir():
        raise ArgenError(f"output path {out} exists and is not a folder")
    if meta_p.is_file():
        old = read_json(meta_p, "argen.json")
        same = all(old.get(k) == v for k, v in json.loads(json.dumps(sig)).items())
        if not same and not req.overwrite:
            raise ArgenError(f"{out} holds a dataset made with other options; use --overwrite to replace it "
                             "or choose another --out")
        if not same or req.overwrite:
            _remove_ours(out, req.cfg.output.split)
    elif out.is_dir() and any(out.iterdir()):
        if not req.overwrite:
            raise ArgenError(f"output folder {out} is not empty and holds no argen.json; use --overwrite "
                             "or choose another --out")
        _remove_ours(out, req.cfg.output.split)
    out.mkdir(parents=True, exist_ok=True)
    for d in (out / req.cfg.output.split, out / "models", out / "models_eval"):
        remove_stray_temps(d)  # what a killed run was writing; its frame is made again below
    for p in out.glob(".tmp-*"):  # top level: argen.json, capture_log.json, camera.json
        p.unlink(missing_ok=True)
    meta = {"argen_version": __version__, "kind": kind, "template": req.cfg.name, "seed": req.cfg.seed,
            "frames": req.frames, "split": req.cfg.output.split, "units": "BOP (mm)", **sig,
            "object_names": {str(o.obj_id): o.name for o in req.objects}}
    write_json(meta_p, meta)  # first: a run stopped while writing the models below resumes (they are rewritten)
    write_models(out / "models", req.objects)
    write_models_eval(out / "models_eval", req.objects)
    cam = req.cfg.camera
    bop.save_camera(out / bop.CAMERA_FILE, intrinsics(cam), cam.width, cam.height, req.cfg.output.depth_scale)
    log_p = out / "capture_log.json"
    if log_p.is_file():
        log = read_json(log_p, "capture_log.json")
        return {int(e["index"]): e for e in log.get("frames", [])}
    return {}


def _remove_ours(out: Path, split: str) -> None:
    """Remove what a capture wrote (never other files the user keeps there)."""
    for name in ("argen.json", "capture_log.json", bop.CAMERA_FILE):
        (out / name).unlink(missing_ok=True)
    for name in ("models", "models_eval", split):
        if (out / name).is_dir():
            shutil.rmtree(out / name)


# ------------------------------------------------------------------------------------- running

_worker: FrameMaker | None = None


def _init_worker(maker, cfg, objects, out, threads):
    global _worker
    # llvmpipe (OSMesa) renders with all cores by default; share them between the workers
    os.environ.setdefault("LP_NUM_THREADS", str(threads))
    _worker = maker(cfg, objects, out)


def _work(index: int) -> FrameRecord:
    return _worker.make(index)


@dataclass
class CaptureSummary:
    written: int
    rejected: int
    skipped: int
    seconds: float
    stage_seconds: dict
    rejected_reasons: dict
    unplaced: int

    def line(self) -> str:
        n = self.written + self.rejected
        spf = self.seconds / n if n else 0.0
        reasons = ", ".join(f"{k}: {v}" for k, v in self.rejected_reasons.items())
        s = (f"{self.written} frames written, {self.rejected} rejected"
             + (f" ({reasons})" if reasons else "")
             + (f", {self.skipped} already done" if self.skipped else "")
             + f"; {spf:.3f} s per frame ({n / self.seconds if self.seconds else 0:.2f} frames/s)")
        if self.unplaced:
            s += f"; {self.unplaced} object instances could not be placed (see capture_log.json)"
        return s


def run_capture(req: CaptureRequest, maker=None, kind: str = "capture-sim", extra: dict | None = None) -> CaptureSummary:
    """Capture ``req.frames`` frames into ``req.out`` (resuming), returning a summary.

    maker: picklable callable (cfg, objects, out) -> an object with ``make(index) -> FrameRecord``
    (default FrameMaker, the simulated capture); kind, extra: see ``prepare_output``.
    """
    maker = maker or FrameMaker
    if req.frames < 1:
        raise ArgenError("--frames must be at least 1")
    if req.workers < 1:
        raise ArgenError("--workers must be at least 1")
    mine = shard_indices(req.frames, req.shard)
    done = prepare_output(req, kind, extra)
    todo = [i for i in mine if i not in done]
    jsons = bop.SceneJsons(req.out, req.cfg.output.split)
    log_entries = dict(done)
    stage = {k: 0.0 for k in STAGES}
    t_start = time.perf_counter()
    written = rejected = unplaced = 0
    reasons: dict[str, int] = {}

    def commit():
        jsons.flush()
        write_json(req.out / "capture_log.json",
                   {"frames": [log_entries[k] for k in sorted(log_entries)]}, indent=1)

    bar = tqdm(total=len(todo), desc=kind, unit="frame", disable=not req.progress, file=sys.stderr)
    last_commit = time.perf_counter()
    try:
        for rec in _records(req, todo, maker):
            log_entries[rec.index] = rec.log
            for k, v in rec.timing.items():
                stage[k] = stage.get(k, 0.0) + v
            unplaced += len(rec.log.get("unplaced", []))
            if rec.accepted:
                jsons.add(rec.scene_id, rec.im_id, rec.camera, rec.gt, rec.gt_info)
                written += 1
            else:
                rejected += 1
                key = re.sub(r"\d+(\.\d+)?", "N", rec.log["reason"]).split(" (")[0]
                reasons[key] = reasons.get(key, 0) + 1
            bar.update(1)
            bar.set_postfix(written=written, rejected=rejected)
            if time.perf_counter() - last_commit > 5.0:
                commit()
                last_commit = time.perf_counter()
        commit()
        bop.save_test_targets(req.out, req.cfg.output.split)  # BOP19 targets of all frames written so far
    finally:
        bar.close()
    return CaptureSummary(written, rejected, len(mine) - len(todo), time.perf_counter() - t_start, stage,
                          reasons, unplaced)


def _records(req: CaptureRequest, todo: list[int], maker):
    if req.workers == 1 or len(todo) <= 1:
        m = maker(req.cfg, req.objects, req.out)
        for i in todo:
            yield m.make(i)
        return
    ctx = mp.get_context("spawn")
    with ctx.Pool(req.workers, initializer=_init_worker, initargs=(maker, req.cfg, req.objects, req.out, max(1, (os.cpu_count() or 1) // req.workers))) as pool:
        yield from pool.imap(_work, todo, chunksize=1)
