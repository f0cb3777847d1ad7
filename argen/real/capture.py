"""Real AR capture: virtual objects composited into a recorded RGB-D sequence (``argen capture --recording``).

Per recorded frame: detect the printed board's markers in the colour image and estimate T_cam_board
(argen.sim.ar, the same acceptance checks as capture-sim); draw the frame's placements with the same
scene code as capture-sim (argen.sim.scene.build_scene: only its placements and lights are used, the
simulated table and clutter are not, the recording is the background); render the objects from the
estimated pose and z-composite them into the real depth and colour (argen.sim.capture.FrameMaker.insert):
a virtual pixel shows unless the real surface is more than ``occlusion_margin`` in front of it, so a
real object in front of a virtual one hides it. Sensor noise (template ``noise``) goes on the virtual
pixels only: the real depth already carries the sensor's own. Frame ``i`` of the recording is BOP
image ``i`` (a rejected frame leaves a gap and is logged in capture_log.json with its reason), the
output is the BOP layout of capture-sim and a killed run resumes like it.
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
from argen.real.recording import Recording
from argen.sim.ar import estimate_board_pose
from argen.sim.capture import (
    CaptureRequest,
    CaptureSummary,
    FrameMaker,
    accept,
    finite_or_none,
    frame_rngs,
    run_capture,
)
from argen.sim.scene import build_scene

DEFAULT_OCCLUSION_MARGIN = 0.003  # metres: real depth noise on the board must not eat the objects' bases


def recording_config(cfg: TemplateConfig, rec: Recording) -> TemplateConfig:
    """``cfg`` with the recording's image size and intrinsics as its camera."""
    K = rec.K
    return override(cfg, {"camera.width": rec.width, "camera.height": rec.height, "camera.fx": float(K[0, 0]),
                          "camera.fy": float(K[1, 1]), "camera.cx": float(K[0, 2]), "camera.cy": float(K[1, 2])})


class RealFrameMaker(FrameMaker):
    """FrameMaker whose background is recording frame ``index`` instead of a simulated scene."""

    def __init__(self, cfg: TemplateConfig, objects: list[ObjectModel], out: Path, recording: Recording,
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
        rng_scene, _, rng_noise, _ = frame_rngs(cfg.seed, index)
        timing = {}
        t0 = time.perf_counter()
        rgb, depth = rec.read(index)
        scene = build_scene(cfg, self.objects, self.board, rng_scene)
        t1 = time.perf_counter()
        est = estimate_board_pose(rgb, self.board, self.K, cfg.ar)
        timing["scene"], timing["ar"] = t1 - t0, time.perf_counter() - t1
        log = {"index": index, "source": rec.names[index], "markers": est.n_markers, "reproj_px": finite_or_none(est.reproj_px),
               "placed": scene.info["placed"], "unplaced": scene.info["unplaced"]}
        if rec.timestamps is not None:
            log["timestamp"] = float(rec.timestamps[index])
        if not accept(log, est, scene):
            return {}, {"log": log, "timing": timing}
        arrays = self.insert(scene, est.T_cam_board, rgb, depth, rng_noise, timing, margin=self.margin,
                             noise_virtual_only=True)
        return arrays, {"log": log, "timing": timing, "T_est": est.T_cam_board}


def run_real_capture(req: CaptureRequest, recording: Recording,
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
