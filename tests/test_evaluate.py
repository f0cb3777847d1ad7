"""detector eval: the oracle run through the whole pose stage on a real capture-sim + label file; report files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from argen.cli import app as argen_app
from argen.h5 import LabelFile
from argen.label import LabelConfig, LabelRequest, run_label
from detector.evaluate import BOP_CSV, Predictions, evaluate, oracle_predictor
from detector.pose import PoseConfig
from detector.report import read_bop_csv


@pytest.fixture(scope="session")
def label_file(tmp_path_factory):
    """A 3-frame noise-free capture-sim dataset of the built-in objects, labelled (tiny)."""
    d = tmp_path_factory.mktemp("eval")
    r = CliRunner().invoke(argen_app, ["capture-sim", "--frames", "3", "--noise", "none", "--out", str(d / "ds"),
                                       "--seed", "5", "--quiet"])
    assert r.exit_code == 0, r.output
    out = d / "test.h5"
    run_label(LabelRequest(dataset=d / "ds", split="train_pbr", out=out, progress=False,
                           cfg=LabelConfig(max_points=20000)))
    return out


def test_oracle_gives_full_add_accuracy(label_file, tmp_path):
    s = evaluate(oracle_predictor(), label_file, tmp_path, icp=False)
    with LabelFile(label_file) as lf:
        assert s["num_frames"] == lf.num_frames >= 2
    assert sum(o["num_gt"] for o in s["objects"]) >= 3
    for o in s["objects"]:
        assert o["add"]["noicp"]["0.10"] == 1.0, o
    assert s["f1"]["noicp"]["f1"] == 1.0
    # the oracle poses are the ground truth: errors far below 1 mm, and the BOP CSV carries them (mm, row-major)
    assert max(r["noicp"] for r in s["instances"]) < 1e-4
    rows = read_bop_csv(tmp_path / BOP_CSV)
    with LabelFile(label_file) as lf:
        gts = [(f.scene_id, f.im_id, int(o), R, t) for f in lf.frames() for o, R, t in
               zip(f.instances.obj_id, f.instances.R, f.instances.t)]
    for r in rows:
        near = [g for g in gts if g[:3] == (r["scene_id"], r["im_id"], r["obj_id"])]
        assert min(np.abs(g[4] - r["t"]).max() for g in near) < 1e-4
        assert min(np.abs(g[3] - r["R"]).max() for g in near) < 1e-3
    md = (tmp_path / "report.md").read_text()
    assert "| **average** |" in md and "100.0" in md
    js = json.loads((tmp_path / "report.json").read_text())
    assert js["mean"]["noicp"]["0.10"] == 1.0 and js["mean"]["icp"] is None
    assert (tmp_path / "curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_oracle_with_wrong_offsets_is_scored_as_wrong(label_file, tmp_path):
    """Shift every predicted control point by 3 cm: ADD then fails at 10 % for the smaller objects."""
    base = oracle_predictor()

    def shifted(frame):
        p = base(frame)
        return Predictions(p.xyz, p.class_probs, p.class_ids, p.control_points + [0.03, 0, 0], p.confidence,
                           p.point_index)

    s = evaluate(shifted, label_file, tmp_path, icp=False)
    errs = np.array([r["noicp"] for r in s["instances"]])
    assert np.allclose(errs[np.isfinite(errs)], 0.03, atol=1e-4)
    small = [o for o in s["objects"] if o["diameter"] < 0.3]
    assert all(o["add"]["noicp"]["0.10"] == 0.0 for o in small)


def test_oracle_with_icp_and_subsampling(label_file, tmp_path):
    """With ICP on the oracle's exact (subsampled) points the poses stay correct; timings are recorded."""
    s = evaluate(oracle_predictor(num_points=4096, seed=1), label_file, tmp_path, icp=True,
                 cfg=PoseConfig(tau=0.5))
    for o in s["objects"]:
        assert o["add"]["icp"]["0.10"] == 1.0 and o["add"]["noicp"]["0.10"] == 1.0
    assert {"voting", "kabsch", "icp", "total"} <= set(s["timing_ms"])
    assert "with ICP" in (tmp_path / "report.md").read_text()
    assert s["fps"] > 0
