"""`argen capture --recording`: compositing into a recording agrees with rendering the full scene directly.

The recording is made with capture-sim's own machinery (FrameMaker.background: table, board and clutter
from the true camera, no objects), so with the same seed the composited frames must equal capture-sim's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from argen import bop
from argen.cli.app import app
from argen.config import load_template, override
from argen.errors import ArgenError
from argen.models.objects import builtin_objects
from argen.real.capture import run_real_capture
from argen.real.recording import open_recording, write_recording
from argen.sim.capture import CaptureRequest, FrameMaker, composite, run_capture
from argen.sim.render import RenderOutput

SETS = {"camera.width": 320, "camera.height": 240, "camera.fx": 286.2, "camera.fy": 286.8, "camera.cx": 162.6,
        "camera.cy": 121.0, "camera.distance": [0.5, 0.7], "camera.elevation_deg": [45.0, 85.0],
        "noise.enabled": False, "seed": 3, "plane.support": "board"}
N = 3  # frames made by both; the recording has one more, with the board hidden


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("realcap")
    cfg = override(load_template("linemod"), SETS)
    objs = builtin_objects()
    run_capture(CaptureRequest(cfg=cfg, objects=objs, out=root / "sim", frames=N, progress=False))
    maker = FrameMaker(cfg, objs, root / "unused")
    frames = [(bg.rgb, bg.depth) for bg in (maker.background(i)[3] for i in range(N))]
    frames.append((np.full_like(frames[0][0], 128), frames[0][1]))  # markers invisible
    write_recording(root / "rec", maker.K, frames, depth_scale=0.1, timestamps=np.arange(N + 1) / 30.0)
    rec = open_recording(root / "rec")
    s = run_real_capture(CaptureRequest(cfg=cfg, objects=objs, out=root / "real", frames=1, progress=False), rec)
    return root, rec, s, cfg, objs


def _scene(out: Path):
    return bop.load_scene(out, "train_pbr", 0)


def test_composite_equals_direct_rendering(runs):
    root, _, s, _, _ = runs
    sim, real = _scene(root / "sim"), _scene(root / "real")
    assert s.written == len(sim.im_ids) >= 2 and set(real.im_ids) == set(sim.im_ids)
    compared = 0
    for im in sim.im_ids:
        assert len(real.gts[im]) == len(sim.gts[im])
        d_sim, d_real = sim.read_depth(im), real.read_depth(im)
        for g, (a, b) in enumerate(zip(sim.gts[im], real.gts[im])):
            assert a.obj_id == b.obj_id
            assert np.allclose(a.R, b.R, atol=1e-6) and np.allclose(a.t, b.t, atol=1e-6)
            m_sim, m_real = sim.read_mask(im, g), real.read_mask(im, g)
            assert np.array_equal(sim.read_mask(im, g, visib=False), real.read_mask(im, g, visib=False))
            if m_sim.sum() <= 50:  # hidden behind a distractor: nothing to compare
                assert m_real.sum() <= 50 + 0.02 * sim.read_mask(im, g, visib=False).sum()
                continue
            compared += 1
            iou = (m_sim & m_real).sum() / (m_sim | m_real).sum()
            assert iou > 0.98
            both = m_sim & m_real
            assert np.median(np.abs(d_sim[both] - d_real[both])) < 0.001
            assert np.array_equal(sim.read_mask(im, g, visib=False), real.read_mask(im, g, visib=False))
        # away from the objects the output is the recording itself
        bg = ~np.any([sim.read_mask(im, g, visib=False) for g in range(len(sim.gts[im]))], axis=0)
        assert np.abs(d_sim[bg] - d_real[bg]).max() < 1e-4
    assert compared >= 3


def test_hidden_board_is_rejected_and_logged(runs):
    root, rec, s, _, _ = runs
    log = json.loads((root / "real" / "capture_log.json").read_text())["frames"]
    assert [e["source"] for e in log] == rec.names
    last = log[-1]
    assert not last["accepted"] and "markers" in last["reason"] and last["timestamp"] == pytest.approx(N / 30)
    assert s.rejected >= 1 and N not in _scene(root / "real").im_ids
    assert json.loads((root / "real" / "argen.json").read_text())["kind"] == "capture-real"


def test_without_the_board_auto_falls_back_to_the_plane(runs, tmp_path):
    root, rec, _, cfg, objs = runs
    write_recording(tmp_path / "rec", rec.K, [rec.read(N)], depth_scale=0.1)  # the frame whose board is hidden
    auto = override(cfg, {"plane.support": "auto"})
    s = run_real_capture(CaptureRequest(cfg=auto, objects=objs, out=tmp_path / "o", frames=1, progress=False),
                         open_recording(tmp_path / "rec"))
    log = json.loads((tmp_path / "o" / "capture_log.json").read_text())["frames"][0]
    assert s.written == 1 and log["support"] == "plane" and "markers" in log["board"]
    assert log["plane"]["tilt_deg"] <= auto.plane.max_tilt_deg


def test_rerun_resumes_without_redoing(runs):
    root, rec, _, cfg, objs = runs
    before = (root / "real" / "train_pbr" / "000000" / "scene_gt.json").read_bytes()
    s = run_real_capture(CaptureRequest(cfg=cfg, objects=objs, out=root / "real", frames=1, progress=False), rec)
    assert s.skipped == len(rec) and s.written == 0
    assert (root / "real" / "train_pbr" / "000000" / "scene_gt.json").read_bytes() == before


def test_real_surface_in_front_hides_the_virtual_object():
    rgb = np.zeros((4, 4, 3), np.uint8)
    real = np.full((4, 4), 2.0, np.float32)
    real[:, :2] = 0.5  # a real surface at 0.5 m in front of the virtual object at 1.0 m
    real[0, 3] = 0.0  # no measurement: the virtual object shows
    ob = RenderOutput(np.full((4, 4, 3), 200, np.uint8), np.full((4, 4), 1.0, np.float32), np.ones((4, 4), np.int32))
    out_rgb, depth, seg, front = composite(rgb, real, ob, margin=0.003)
    assert not front[:, :2].any() and front[:, 2:].all()
    assert np.allclose(depth[:, :2], 0.5) and np.allclose(depth[:, 2:], 1.0) and (seg[:, :2] == 0).all()
    assert (out_rgb[:, 2:] == 200).all() and (out_rgb[:, :2] == 0).all()


def _recording(tmp: Path, n_rgb=1, n_depth=1, depth_value=7000, camera=True, depth_scale=0.1):
    if camera:
        (tmp).mkdir(parents=True, exist_ok=True)
        (tmp / "camera.json").write_text(json.dumps({"fx": 50.0, "fy": 50.0, "cx": 16.0, "cy": 12.0,
                                                     "depth_scale": depth_scale}))
    for i in range(n_rgb):
        bop.write_png(tmp / "rgb" / f"{i:06d}.png", np.zeros((24, 32, 3), np.uint8))
    for i in range(n_depth):
        bop.write_png(tmp / "depth" / f"{i:06d}.png", np.full((24, 32), depth_value, np.uint16))
    return tmp


@pytest.mark.parametrize("kw, msg", [
    ({"camera": False}, "no camera.json"),
    ({"n_rgb": 3, "n_depth": 2}, "3 colour and 2 depth frames"),
    ({"depth_scale": 10.0}, "wrong depth units"),
    ({"depth_value": 7}, "wrong depth units"),
])
def test_bad_recordings_are_one_line_errors(tmp_path, kw, msg):
    rec = _recording(tmp_path / "rec", **kw)
    with pytest.raises(ArgenError, match=msg):
        open_recording(rec)
    r = CliRunner().invoke(app, ["capture", "--recording", str(rec), "--out", str(tmp_path / "o"), "--quiet"])
    assert r.exit_code == 2 and msg in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_eight_bit_depth_is_refused(tmp_path):
    rec = _recording(tmp_path / "rec", n_depth=0)
    bop.write_png(rec / "depth" / "000000.png", np.full((24, 32), 70, np.uint8))
    with pytest.raises(ArgenError, match="not 16-bit"):
        open_recording(rec)


def test_noise_goes_on_the_virtual_pixels_only(runs, tmp_path):
    root, rec, _, cfg, objs = runs
    noisy_cfg = override(cfg, {"noise.enabled": True})
    run_real_capture(CaptureRequest(cfg=noisy_cfg, objects=objs, out=tmp_path / "n", frames=1, progress=False), rec)
    clean, noisy = _scene(root / "real"), _scene(tmp_path / "n")
    assert noisy.im_ids == clean.im_ids
    for im in clean.im_ids:
        dc, dn = clean.read_depth(im), noisy.read_depth(im)
        virt = np.any([clean.read_mask(im, g) for g in range(len(clean.gts[im]))], axis=0)
        assert np.array_equal(dc[~virt], dn[~virt])  # the recording already holds its sensor's noise
        both = virt & (dn > 0)
        assert 0.0002 < np.median(np.abs(dc[both] - dn[both])) < 0.005
