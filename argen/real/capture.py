"""Real AR capture: virtual objects composited into a recorded RGB-D sequence (``argen capture --recording``).

Per recorded frame the objects need a world to stand in (template ``plane.support``):

- *board* (``board``, or ``auto`` where the board is found): detect the printed board's markers in the colour
  image and estimate T_cam_board (argen.sim.ar, the same acceptance checks as capture-sim); draw the frame's
  placements with the same scene code as capture-sim (argen.sim.scene.build_scene: only its placements and
  lights are used, the simulated table and clutter are not, the recording is the background);
- *plane* (``plane``, or ``auto`` where no board is found): no marker at all. The dominant horizontal plane
  near the view's centre is fitted to the depth (argen.real.support) and is the world; the objects are placed
  on its measured extent with capture-sim's placement code (argen.sim.placement: stable resting poses, no
  overlap), and also clear of every real point the depth measured above it (Support.fits). Each frame is
  placed on its own: no odometry carries the objects from frame to frame (see the README for why).

Then the objects are rendered from that pose and z-composited into the real depth and colour
(argen.sim.capture.FrameMaker.insert): a virtual pixel shows unless the real surface is more than
``occlusion_margin`` in front of it (on the support plane's own measured pixels, its depth noise band
``plane_tolerance`` at least, so the sensor's noise on the table top does not eat the objects' bases), so a
real object in front of a virtual one hides it. Sensor noise (template ``noise``) goes on the virtual pixels
only: the real depth already carries the sensor's own. Frame ``i`` of the recording is BOP image ``i`` (a
rejected frame, board not found or no usable plane, leaves a gap and is logged in capture_log.json with its
reason), the output is the BOP layout of capture-sim and a killed run resumes like it.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from pathlib import Path

import numpy as np

from argen.config import TemplateConfig, override
from argen.errors import ArgenError
from argen.models.objects import ObjectModel
from argen.real.recording import RecordingBase
from argen.real.support import Support, find_support, plane_tolerance
from argen.sim.ar import estimate_board_pose
from argen.sim.capture import (
    CaptureRequest,
    CaptureSummary,
    FrameMaker,
    accept,
    accept_world,
    finite_or_none,
    frame_rngs,
    run_capture,
)
from argen.sim.placement import choose_instances, place_instances
from argen.sim.scene import Scene, build_scene, draw_lights

DEFAULT_OCCLUSION_MARGIN = 0.003  # metres: real depth noise on the board must not eat the objects' bases


def recording_config(cfg: TemplateConfig, rec: RecordingBase) -> TemplateConfig:
    """``cfg`` with the recording's image size and intrinsics as its camera, and its depth unit as the output's
    where that is coarser (TUM's 0.2 mm units reach 13 m, the default 0.1 mm only 6.5 m: the real depth must fit)."""
    K = rec.K
    keys = {"camera.width": rec.width, "camera.height": rec.height, "camera.fx": float(K[0, 0]),
            "camera.fy": float(K[1, 1]), "camera.cx": float(K[0, 2]), "camera.cy": float(K[1, 2])}
    if rec.depth_scale > cfg.output.depth_scale:
        keys["output.depth_scale"] = float(rec.depth_scale)
    return override(cfg, keys)


def plane_scene(cfg: TemplateConfig, objects: list[ObjectModel], support: Support, rng: np.random.Generator) -> Scene:
    """The objects placed on a support plane (world = plane frame) and the frame's lights; no background."""
    instances = choose_instances(objects, cfg.placement, rng)
    placements, failed = place_instances(instances, cfg.placement, support.half_extent, rng, fits=support.fits)
    info = {"placed": [p.obj.name for p in placements], "unplaced": [o.name for o in failed]}
    return Scene([], placements, info["unplaced"], draw_lights(cfg, rng), float(rng.uniform(*cfg.scene.ambient)), info)


class RealFrameMaker(FrameMaker):
    """FrameMaker whose background is recording frame ``index`` instead of a simulated scene."""

    def __init__(self, cfg: TemplateConfig, objects: list[ObjectModel], out: Path, recording: RecordingBase,
                 occlusion_margin: float = DEFAULT_OCCLUSION_MARGIN):
        super().__init__(cfg, objects, out)
        self.recording = recording
        self.margin = occlusion_margin
        if cfg.output.pixel_centres != "integer":
            raise ArgenError("output.pixel_centres must stay 'integer' for a real recording: its calibrated K "
                             "puts pixel centres at integer coordinates")
        if not np.allclose(self.K, recording.K):
            raise ArgenError("the template camera differs from the recording's intrinsics (use recording_config)")

    def simulate(self, index: int) -> tuple[dict, dict]:
        """Composite frame ``index``: (arrays, metadata) as FrameMaker.simulate; arrays empty when rejected."""
        cfg, rec = self.cfg, self.recording
        rng_scene, rng_plane, rng_noise, _ = frame_rngs(cfg.seed, index)
        timing = {}
        rgb, depth = rec.read(index)
        log = {"index": index, "source": rec.names[index]}
        if rec.timestamps is not None:
            log["timestamp"] = float(rec.timestamps[index])
        board_reason = None
        if cfg.plane.support != "plane":
            t0 = time.perf_counter()
            scene = build_scene(cfg, self.objects, self.board, rng_scene)
            t1 = time.perf_counter()
            est = estimate_board_pose(rgb, self.board, self.K, cfg.ar)
            timing["scene"], timing["ar"] = t1 - t0, time.perf_counter() - t1
            log.update({"markers": est.n_markers, "reproj_px": finite_or_none(est.reproj_px)})
            if est.accepted or cfg.plane.support == "board":
                log.update({"support": "board", "placed": scene.info["placed"], "unplaced": scene.info["unplaced"]})
                if not accept(log, est, scene):
                    return {}, {"log": log, "timing": timing}
                arrays = self.insert(scene, est.T_cam_board, rgb, depth, rng_noise, timing, margin=self.margin,
                                     noise_virtual_only=True)
                return arrays, {"log": log, "timing": timing, "T_est": est.T_cam_board}
            board_reason = est.reason
            rng_scene = frame_rngs(cfg.seed, index)[0]  # the plane's placements do not depend on the board's
        log["support"] = "plane"
        if board_reason:
            log["board"] = board_reason
        t0 = time.perf_counter()
        support = find_support(depth, self.K, cfg.plane, rng_plane)
        timing["plane"] = time.perf_counter() - t0
        if isinstance(support, str):
            accept_world(log, False, support, None)
            return {}, {"log": log, "timing": timing}
        log["plane"] = support.info()
        t1 = time.perf_counter()
        scene = plane_scene(cfg, self.objects, support, rng_scene)
        timing["scene"] = time.perf_counter() - t1
        log.update({"placed": scene.info["placed"], "unplaced": scene.info["unplaced"]})
        if not accept_world(log, True, "", scene):
            return {}, {"log": log, "timing": timing}
        margin = np.where(support.plane_mask(depth, self.K, cfg.plane),
                          np.maximum(self.margin, plane_tolerance(depth, cfg.plane)), self.margin)
        arrays = self.insert(scene, support.T_cam_world, rgb, depth, rng_noise, timing, margin=margin,
                             noise_virtual_only=True)
        return arrays, {"log": log, "timing": timing, "T_est": support.T_cam_world}


def run_real_capture(req: CaptureRequest, recording: RecordingBase,
                     occlusion_margin: float = DEFAULT_OCCLUSION_MARGIN) -> CaptureSummary:
    """Composite the objects into every frame of ``recording`` and write BOP scenes (resuming).

    req: as for capture-sim (its ``frames`` and ``shard`` are ignored: every recorded frame is made;
    its template camera is replaced by the recording's intrinsics). occlusion_margin: metres.
    """
    if occlusion_margin < 0:
        raise ArgenError(f"--occlusion-margin must be >= 0 metres, got {occlusion_margin:g}")
    rec = recording
    creq = dataclasses.replace(req, cfg=recording_config(req.cfg, rec), frames=len(rec), shard=(0, 1))
    extra = {"recording": str(rec.root.resolve()), "recording_frames": rec.names,
             "depth_scale_in": rec.depth_scale, "occlusion_margin": occlusion_margin}
    maker = functools.partial(RealFrameMaker, recording=rec, occlusion_margin=occlusion_margin)
    return run_capture(creq, maker=maker, kind="capture-real", extra=extra)
