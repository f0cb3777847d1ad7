"""detector eval: the oracle run through the whole geometry on a real capture-sim + label file; report files."""

from __future__ import annotations

import hashlib
import json
import os

import numpy as np
import pytest
import torch
from test_data import TINY_MODEL
from typer.testing import CliRunner

from argen.cli.app import app as argen_app
from argen.errors import ArgenError
from argen.h5 import LabelFile
from argen.label import LabelConfig, LabelRequest, run_label
from detector.data.augment import NORMALISATION
from detector.data.frames import object_table_dict
from detector.evaluate import bop19_summary, evaluate
from detector.geometry.types import GeometryConfig
from detector.report import read_bop_csv
from detector.stage1 import network as model
from detector.stage1.predictor import Predictions, oracle_predictor
from detector.training.checkpoint_file import save_checkpoint


@pytest.fixture(scope="session")
def dataset(tmp_path_factory):
    """A 3-frame noise-free capture-sim dataset of the built-in objects and its label file (tiny); no distractors
    on the board and the objects apart, so that an offset never lands a detection on another instance."""
    d = tmp_path_factory.mktemp("eval")
    r = CliRunner().invoke(argen_app, ["capture-sim", "--frames", "3", "--noise", "none", "--out", str(d / "ds"),
                                       "--seed", "5", "--set", "clutter.on_board=[0,0]", "--set", "placement.beside=0",
                                       "--quiet"])
    assert r.exit_code == 0, r.output
    out = d / "test.h5"
    run_label(LabelRequest(dataset=d / "ds", split="train_pbr", out=out, progress=False,
                           cfg=LabelConfig(max_points=20000)))
    return d / "ds", out


@pytest.fixture(scope="session")
def label_file(dataset):
    return dataset[1]


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
    assert s["bop_csv"] == "argen_ds-train-pbr.csv"  # METHOD_DATASET-SPLIT-SPLITTYPE.csv
    rows = read_bop_csv(tmp_path / s["bop_csv"])
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
    # BOP19 on the labelled dataset: the ground truth scores 1 in every figure, in the toolkit's file too
    b = json.loads((tmp_path / "scores_bop19.json").read_text())
    assert set(b) == {"bop19_average_recall", "bop19_average_recall_vsd", "bop19_average_recall_mssd",
                      "bop19_average_recall_mspd", "bop19_average_time_per_image"}
    assert all(v == 1.0 for k, v in b.items() if k != "bop19_average_time_per_image")
    assert s["bop19"]["num_targets"] == len(s["instances"]) and "## BOP19 Average Recall" in md
    assert js["bop19"]["pixel_centres"] == "integer" and "errors" not in js["bop19"]


def test_oracle_with_wrong_offsets_is_scored_as_wrong(label_file, tmp_path):
    """Shift every predicted control point by 3 cm: the ADD error is then 3 cm (at most that for ADD-S: a shifted
    symmetric object partly maps onto itself), so ADD fails at 10 % for the smaller objects."""
    base = oracle_predictor()

    def shifted(frame):
        p = base(frame)
        return Predictions(p.xyz, p.class_probs, p.class_ids, p.control_points + [0.03, 0, 0], p.confidence)

    s = evaluate(shifted, label_file, tmp_path, icp=False)
    sym = {o["obj_id"] for o in s["objects"] if o["symmetric"]}
    errs = np.array([r["noicp"] for r in s["instances"] if r["obj_id"] not in sym])
    assert len(errs) >= 3 and np.allclose(errs[np.isfinite(errs)], 0.03, atol=1e-4)
    assert all(r["noicp"] <= 0.03 + 1e-4 for r in s["instances"] if r["obj_id"] in sym and r["noicp"] is not None)
    small = [o for o in s["objects"] if o["diameter"] < 0.3 and not o["symmetric"]]
    assert all(o["add"]["noicp"]["0.10"] == 0.0 for o in small)


def test_oracle_with_icp_and_subsampling(label_file, tmp_path):
    """With ICP on the oracle's exact (subsampled) points the poses stay correct; timings are recorded."""
    s = evaluate(oracle_predictor(num_points=4096, seed=1), label_file, tmp_path, icp=True,
                 cfg=GeometryConfig(tau=0.5))
    for o in s["objects"]:
        assert o["add"]["icp"]["0.10"] == 1.0 and o["add"]["noicp"]["0.10"] == 1.0
    # exact poses stay exact: ICP never moves one by 1 mm or more (it is refused unless it fits better)
    assert max(r["icp"] for r in s["instances"]) < 1e-3
    r = s["icp_refinement"]
    assert sum(r.values()) == sum(o["f1"]["icp"]["num_det"] for o in s["objects"]) > 0
    assert {"voting", "kabsch", "icp", "total"} <= set(s["timing_ms"])
    md = (tmp_path / "report.md").read_text()
    assert "with ICP" in md and f"ICP refinement: {r['accepted']} of {sum(r.values())} detections" in md
    assert s["fps"] > 0


# ------------------------------------------------------------------------------------------------ predict


def gt_predictor(ds, scene_id, im_id):
    """Labels each input point with the ground-truth instance whose surface it lies on (within 3 mm)."""
    from scipy.spatial import cKDTree

    from argen import bop
    from argen.models.objects import load_models

    models = {o.obj_id: o for o in load_models(ds / "models")}
    gts = bop.load_scene(ds, "train_pbr", scene_id).gts[im_id]

    def predict(frame):
        xyz = frame.features[:, :3].astype(np.float64)
        best = np.full(len(xyz), np.inf)
        cps = np.zeros((len(xyz), 9, 3))
        obj = np.zeros(len(xyz), np.int64)
        for g in gts:
            o = models[g.obj_id]
            d, _ = cKDTree(np.asarray(o.mesh.sample(20000, seed=0)) @ g.R.T + g.t).query(xyz)
            take = (d < 0.003) & (d < best)
            best[take], obj[take], cps[take] = d[take], g.obj_id, o.control_points @ g.R.T + g.t
        ids = sorted(models)
        probs = np.eye(len(ids) + 1)[np.searchsorted(ids, obj) + 1]
        probs[obj == 0] = np.eye(len(ids) + 1)[0]
        return Predictions(xyz, probs, ids, cps, np.ones(len(xyz)))

    return predict, models, gts


def check_poses(out, gts, tol_t=1e-3, tol_deg=1.0):
    found = {d["obj_id"]: d for d in out["detections"]}
    visible = [g for g in gts if g.obj_id in found]
    assert len(visible) >= 2
    for g in visible:
        d = found[g.obj_id]
        assert np.abs(np.array(d["t"]) - g.t).max() < tol_t
        cos = (np.trace(np.array(d["R"]).T @ g.R) - 1) / 2
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < tol_deg
        assert np.allclose(np.array(d["T_cam_model"])[:3, 3], d["t"])


def test_predict_on_bop_frame_depth_png_and_ply(dataset, tmp_path):
    import open3d as o3d

    from argen import bop
    from detector.geometry.types import ObjectInfo
    from detector.predict import load_input, predict

    ds, _ = dataset
    scene = bop.load_scene(ds, "train_pbr", 0)
    im_id = scene.im_ids[0]
    predictor, models, gts = gt_predictor(ds, 0, im_id)
    objects = ObjectInfo({i: o.control_points for i, o in models.items()}, {i: o.diameter for i, o in models.items()},
                         {i: np.asarray(o.mesh.sample(500, seed=1)) for i, o in models.items()})
    inp = load_input(str(ds / "train_pbr" / "000000" / str(im_id)))
    assert inp.image is not None and inp.features.shape[1] == 9
    out = predict(predictor, inp, objects, tmp_path / "bop", names={i: o.name for i, o in models.items()})
    check_poses(out, gts)
    assert json.loads((tmp_path / "bop" / "poses.json").read_text()) == json.loads(json.dumps(out))
    png = (tmp_path / "bop" / "poses.png").read_bytes()
    assert png[:4] == b"\x89PNG"

    # the same frame as a depth PNG with explicit intrinsics gives the same points
    cam = scene.cameras[im_id]
    K = cam.K
    depth_png = bop.image_path(ds, "train_pbr", 0, im_id, "depth")
    inp2 = load_input(str(depth_png), K=f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}", depth_scale=cam.depth_scale,
                      rgb=bop.rgb_path(ds, "train_pbr", 0, im_id))
    np.testing.assert_allclose(inp2.features, inp.features, atol=1e-6)
    # ... and without intrinsics: a depth PNG inside a BOP scene takes its image's entry of scene_camera.json
    inp4 = load_input(str(depth_png))
    np.testing.assert_allclose(inp4.K, K)
    np.testing.assert_allclose(inp4.features[:, [0, 1, 2, 6, 7, 8]], inp.features[:, [0, 1, 2, 6, 7, 8]], atol=1e-6)
    # ... and within a working volume, the points argen label keeps with that --max-depth
    from argen.features import frame_points
    from detector.predict import MAX_POINTS

    near = float(np.median(inp.features[:, 2]))
    inp5 = load_input(str(ds / "train_pbr" / "000000" / str(im_id)), max_depth=near)
    want = frame_points(scene.read_depth(im_id), K, scene.read_rgb(im_id), MAX_POINTS, 0.0, np.random.default_rng(0),
                        near).features
    assert inp5.features[:, 2].max() <= near < inp.features[:, 2].max()
    np.testing.assert_array_equal(inp5.features, want)

    # ... and as a PLY cloud (metres, camera frame), drawn over a splat of the cloud
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(inp.features[:, :3].astype(np.float64)))
    pc.colors = o3d.utility.Vector3dVector(inp.features[:, 3:6].astype(np.float64))
    pc.normals = o3d.utility.Vector3dVector(inp.features[:, 6:9].astype(np.float64))
    o3d.io.write_point_cloud(str(tmp_path / "cloud.ply"), pc)
    inp3 = load_input(str(tmp_path / "cloud.ply"))
    assert inp3.image is None
    np.testing.assert_allclose(np.sort(inp3.features[:, 2]), np.sort(inp.features[:, 2]), atol=1e-6)
    out3 = predict(predictor, inp3, objects, tmp_path / "ply")
    check_poses(out3, gts)
    inp6 = load_input(str(tmp_path / "cloud.ply"), max_depth=near)
    assert inp6.features[:, 2].max() <= near and len(inp6.features) == int((inp.features[:, 2] <= near).sum())
    import cv2
    img = cv2.imread(str(tmp_path / "ply" / "poses.png"))
    assert img.shape[:2] == (480, 640) and img.any()


def test_predict_input_errors(tmp_path):
    from detector.errors import DetectorError
    from detector.predict import load_input, parse_K

    assert parse_K("500,510,320,240")[1, 1] == 510
    with pytest.raises(DetectorError, match="4 .* or 9 values"):
        parse_K("1,2,3")
    with pytest.raises(DetectorError, match="cannot tell"):
        load_input(str(tmp_path / "x.txt"))
    with pytest.raises(DetectorError, match="not found"):
        load_input(str(tmp_path / "x.ply"))


# ------------------------------------------------------------------------------- network end to end (CLI)


@pytest.fixture(scope="module")
def random_checkpoint(label_file, tmp_path_factory):
    """A randomly initialised tiny PointNet2 saved through detector.checkpoint (detects nothing useful)."""
    torch.set_num_threads(1)
    torch.manual_seed(0)
    cfg = model.ModelConfig.from_dict({**model.preset("cpu").to_dict(), **TINY_MODEL})
    with LabelFile(label_file) as lf:
        objects = object_table_dict(lf.objects)
    net = model.PointNet2(cfg, num_classes=len(objects["ids"]))
    path = tmp_path_factory.mktemp("ckpt") / "random.pt"
    save_checkpoint(path, model=net, model_config=cfg, class_ids=objects["ids"], objects=objects, num_points=1024,
                    step=0, normalisation=NORMALISATION)
    return path


def test_cli_eval_and_predict_with_a_random_network(random_checkpoint, dataset, tmp_path):
    from detector.cli.app import app

    ds, h5 = dataset
    runner = CliRunner()
    r = runner.invoke(app, ["eval", str(random_checkpoint), str(h5), "--out", str(tmp_path / "rep"), "--frames", "1",
                            "--tau", "0", "--quiet"])
    assert r.exit_code == 0, r.output
    js = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert js["num_frames"] == 1 and js["timing_ms"]["network"] > 0 and js["timing_ms"]["sampling"] > 0
    # the mean is the objects' shares of instances within 10 % of their diameter
    per_object = {}
    for row in js["instances"]:
        per_object.setdefault(row["obj_id"], []).append(row["noicp"] is not None and row["noicp"] < 0.1 * row["diameter"])
    assert per_object and js["mean"]["noicp"]["0.10"] == pytest.approx(np.mean([np.mean(v) for v in per_object.values()]))
    csv_path = next((tmp_path / "rep").glob("*_*-*.csv"))
    head = csv_path.read_text().splitlines()[0]
    assert head == "scene_id,im_id,obj_id,score,R,t,time"
    rows = read_bop_csv(csv_path)
    assert len(rows) == js["f1"]["noicp"]["num_det"] > 0  # a row per detection
    for row in rows:
        assert np.allclose(row["R"] @ row["R"].T, np.eye(3), atol=1e-5) and np.linalg.det(row["R"]) > 0
        assert row["time"] > 0
    assert (tmp_path / "rep" / "curve.png").is_file() and (tmp_path / "rep" / "report.md").is_file()
    assert "BOP19 AR: " in r.output and (tmp_path / "rep" / "scores_bop19.json").is_file()
    r = runner.invoke(app, ["eval", str(random_checkpoint), str(h5), "--out", str(tmp_path / "rep"), "--quiet",
                            "--bop-dataset", str(tmp_path / "nowhere")])
    assert r.exit_code == 2 and "--bop-dataset" in r.output and len(r.output.strip().splitlines()) == 1

    from argen import bop

    for im_id in bop.load_scene(ds, "train_pbr", 0).im_ids:  # a random network may find nothing in a frame
        r = runner.invoke(app, ["predict", str(random_checkpoint), str(ds / "train_pbr" / "000000" / str(im_id)),
                                "--out", str(tmp_path / "pred"), "--tau", "0", "--min-score", "0"])
        assert r.exit_code == 0, r.output
        out = json.loads((tmp_path / "pred" / "poses.json").read_text())
        if out["detections"]:
            break
    assert out["timing_ms"]["network"] > 0 and out["detections"]
    assert f"{len(out['detections'])} detections" in r.stdout
    for d in out["detections"]:  # every pose a rotation, T_cam_model the same pose
        R, T = np.array(d["R"]), np.array(d["T_cam_model"])
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) == pytest.approx(1.0)
        assert np.array_equal(T[:3, :3], R) and np.array_equal(T[:3, 3], d["t"]) and T[3].tolist() == [0, 0, 0, 1]
    assert (tmp_path / "pred" / "poses.png").read_bytes()[:4] == b"\x89PNG"

    r = runner.invoke(app, ["predict", str(random_checkpoint), str(tmp_path / "missing.ply")])
    assert r.exit_code == 2 and "detector: error:" in r.output and len(r.output.strip().splitlines()) == 1
    # a depth PNG without its colour image: a model that sees colour says it will find little, and still predicts
    cam = bop.load_scene(ds, "train_pbr", 0).cameras[im_id]
    K = ",".join(str(v) for v in (cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]))
    r = runner.invoke(app, ["predict", str(random_checkpoint), str(bop.image_path(ds, "train_pbr", 0, im_id, "depth")),
                            "--K", K, "--depth-scale", str(cam.depth_scale), "--out", str(tmp_path / "pred3")])
    assert r.exit_code == 0 and "detector: warning:" in r.stderr and "--rgb" in r.stderr, r.output
    assert (tmp_path / "pred3" / "poses.json").is_file()
    assert "warning" not in runner.invoke(app, ["predict", str(random_checkpoint), str(ds / "train_pbr" / "000000" /
                                                str(im_id)), "--out", str(tmp_path / "pred4")]).stderr
    # the working volume: the model's own (this one records none: every point), or --max-depth in metres
    assert out["max_depth"] is None
    frame = str(ds / "train_pbr" / "000000" / str(im_id))
    for value, words in (("0", ["--max-depth", "metres"]), ("800", ["--max-depth", "metres"]),
                         ("0.01", ["no valid pixels within 0.01 m"])):
        r = runner.invoke(app, ["predict", str(random_checkpoint), frame, "--out", str(tmp_path / "pred2"),
                                "--max-depth", value])
        assert_one_line_error(r, *words)
    assert not (tmp_path / "pred2").exists()


def test_a_report_killed_while_written_leaves_no_report_json(label_file, tmp_path, monkeypatch):
    """report.json, which --reuse trusts, leaves the folder before the other files are written and comes back last:
    a run that dies in between leaves none, and no temporary file either."""
    import detector.report as report

    evaluate(oracle_predictor(), label_file, tmp_path, icp=False, bop19=False)
    assert (tmp_path / "report.json").is_file()

    def dies(*_args, **_kwargs):
        raise RuntimeError("killed")

    monkeypatch.setattr(report, "write_bop_csv", dies)
    with pytest.raises(RuntimeError, match="killed"):
        evaluate(oracle_predictor(), label_file, tmp_path, icp=False, bop19=False)
    assert not (tmp_path / "report.json").exists()
    monkeypatch.undo()

    def refused(*_args, **_kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", refused)  # the report.json rename itself fails: its temporary file goes too
    with pytest.raises(ArgenError, match="disk full while writing .*report.json"):
        evaluate(oracle_predictor(), label_file, tmp_path, icp=False, bop19=False)
    assert not (tmp_path / "report.json").exists() and not list(tmp_path.glob(".tmp-*"))
    monkeypatch.undo()
    evaluate(oracle_predictor(), label_file, tmp_path, icp=False, bop19=False)
    assert json.loads((tmp_path / "report.json").read_text())["f1"]["noicp"]["f1"] == 1.0


def test_eval_reuse_keeps_a_report_only_when_the_same_run_made_it(random_checkpoint, label_file, tmp_path):
    """--reuse keeps a report made from the same model and label bytes, settings, seed and options, and evaluates
    again when any one of them differs from the run that made it; the report records what made it."""
    import shutil

    from detector.cli.app import app
    from detector.net_dtype import resolve_net_dtype

    runner, rep = CliRunner(), tmp_path / "rep"
    base = [str(label_file), "--frames", "1", "--tau", "0", "--quiet", "--reuse"]

    def run(out, *extra: str, model=random_checkpoint) -> tuple[str, int]:
        r = runner.invoke(app, ["eval", str(model), *base, "--out", str(out), *extra])
        assert r.exit_code == 0, r.output
        return r.output, (out / "report.json").stat().st_mtime_ns

    out, made = run(rep)
    assert "up to date" not in out
    js = json.loads((rep / "report.json").read_text())
    assert js["run"]["seed"] == 0 and js["run"]["frames"] == 1
    assert js["run"]["model"]["sha256"] == hashlib.sha256(random_checkpoint.read_bytes()).hexdigest()
    assert js["run"]["labels"]["bytes"] == label_file.stat().st_size
    out, again = run(rep)
    assert "up to date" in out and again == made  # nothing evaluated, nothing written
    copy = tmp_path / "copy.pt"  # the same bytes under another name: the same model
    shutil.copy(random_checkpoint, copy)
    assert "up to date" in run(rep, model=copy)[0]
    other = tmp_path / "other.pt"  # another model's bytes
    ck = torch.load(random_checkpoint, weights_only=False)
    ck["step"] = 1
    torch.save(ck, other)
    assert js["run"]["net_dtype"] == resolve_net_dtype("auto")  # what auto chose on this CPU
    other_dtype = "float32" if js["run"]["net_dtype"] == "bfloat16" else "bfloat16"
    changes = [["--seed", "1"], ["--set", "geometry.min_votes=4"], ["--set", "sampling.passes=2"],
               ["--min-score", "0.3"], ["--min-visib", "0.2"], ["--icp"], ["--net-dtype", other_dtype],
               ["--set", "geometry.min_score_unrefined=.inf"]]
    for k, extra in enumerate(changes):  # each against the base run's report
        shutil.copytree(rep, tmp_path / f"r{k}")
        assert "up to date" not in run(tmp_path / f"r{k}", *extra)[0], extra
    assert "up to date" not in run(tmp_path / "r0", model=other)[0]
    # a setting that is infinite is not read back as the default None
    inf = tmp_path / f"r{len(changes) - 1}"
    assert json.loads((inf / "report.json").read_text())["config"]["min_score_unrefined"] == "inf"
    assert "up to date" not in run(inf)[0]
    # a report from before reports recorded their run: evaluated again
    js = json.loads((rep / "report.json").read_text())
    js.pop("run")
    (rep / "report.json").write_text(json.dumps(js))
    assert "up to date" not in run(rep)[0] and "run" in json.loads((rep / "report.json").read_text())


def test_eval_reuse_evaluates_again_once_the_bop_dataset_is_there(random_checkpoint, dataset, tmp_path):
    """A report whose BOP19 AR was skipped because the BOP dataset folder was gone is not kept once it is back."""
    import shutil

    import h5py

    from detector.cli.app import app

    ds, h5 = dataset
    copy, labels = tmp_path / "ds", tmp_path / "labels.h5"
    shutil.copytree(ds, copy)
    shutil.copy(h5, labels)
    with h5py.File(labels, "r+") as f:
        f.attrs["source_dataset"] = str(copy)
    args = ["eval", str(random_checkpoint), str(labels), "--out", str(tmp_path / "rep"), "--frames", "1", "--tau",
            "0", "--quiet", "--reuse"]
    copy.rename(tmp_path / "gone")
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0 and "BOP19 AR not computed" in r.output, r.output
    assert "up to date" in CliRunner().invoke(app, args).output  # still gone: nothing to do
    (tmp_path / "gone").rename(copy)
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0 and "up to date" not in r.output and "BOP19 AR: " in r.output, r.output


def assert_one_line_error(r, *words: str) -> None:
    lines = r.stderr.strip().splitlines()
    assert r.exit_code == 2 and len(lines) == 1 and lines[0].startswith("detector: error: "), r.output
    assert all(w in lines[0] for w in words), lines[0]


@pytest.mark.parametrize("args, words", [
    (["--frames", "-3"], ["--frames", "at least 1"]),
    (["--frames", "0"], ["--frames", "at least 1"]),
    (["--min-visib", "1.5"], ["--min-visib"]),
    (["--tau", "-0.1"], ["--tau"]),
    (["--min-score", "2"], ["--min-score"]),
])
def test_eval_refuses_bad_options_in_one_line(random_checkpoint, label_file, tmp_path, args, words):
    from detector.cli.app import app

    r = CliRunner().invoke(app, ["eval", str(random_checkpoint), str(label_file), "--out", str(tmp_path / "rep"),
                                 "--quiet", *args])
    assert_one_line_error(r, *words)
    assert not (tmp_path / "rep").exists()


def test_eval_refuses_a_label_file_of_other_objects(random_checkpoint, label_file, tmp_path):
    """The model learned objects by id; a label file whose ids are other objects (another model under the same id)
    or none of the model's would be scored against the wrong models: refused. Its objects are the label file's."""
    from detector.cli.app import app
    from detector.training.checkpoint_file import atomic_torch_save, read_checkpoint

    payload = read_checkpoint(random_checkpoint)
    for name, change, words in [
        ("bigger.pt", lambda o: {**o, "diameters": [1.5 * d for d in o["diameters"]]}, ["is not the model's object"]),
        ("other-ids.pt", lambda o: {**o, "ids": [100 + i for i in o["ids"]]}, ["shares no object"]),
    ]:
        atomic_torch_save({**payload, "objects": change(payload["objects"])}, tmp_path / name)
        r = CliRunner().invoke(app, ["eval", str(tmp_path / name), str(label_file), "--out", str(tmp_path / "rep"),
                                     "--quiet", "--frames", "1"])
        assert_one_line_error(r, *words)
    assert not (tmp_path / "rep").exists()


def test_predict_refuses_a_colour_png_as_depth(random_checkpoint, dataset, tmp_path):
    """An 8-bit image is not a depth image (BOP depth: one 16-bit channel); taken as depth in millimetres it holds
    nothing within reach and would silently give no detections."""
    import cv2

    from argen import bop
    from detector.cli.app import app

    ds, _ = dataset
    rgb = bop.read_rgb(bop.rgb_path(ds, "train_pbr", 0, bop.load_scene(ds, "train_pbr", 0).im_ids[0]))
    for name, img in (("colour.png", rgb), ("grey.png", rgb[:, :, 0])):
        cv2.imwrite(str(tmp_path / name), img)
        r = CliRunner().invoke(app, ["predict", str(random_checkpoint), str(tmp_path / name), "--K", "572,573,325,242",
                                     "--out", str(tmp_path / "pred")])
        assert_one_line_error(r, name, "8-bit", "not a depth image")
    assert not (tmp_path / "pred").exists()


@pytest.fixture(scope="session")
def lchf_file(tmp_path_factory):
    """2 noise-free frames of the lchf template: several instances of one object per frame."""
    d = tmp_path_factory.mktemp("lchf")
    r = CliRunner().invoke(argen_app, ["capture-sim", "--scene", "lchf", "--frames", "2", "--noise", "none",
                                       "--out", str(d / "ds"), "--seed", "3", "--quiet"])
    assert r.exit_code == 0, r.output
    run_label(LabelRequest(dataset=d / "ds", split="train_pbr", out=d / "l.h5", progress=False,
                           cfg=LabelConfig(max_points=20000)))
    return d / "l.h5"


def test_oracle_multi_instance_f1_and_a_missed_instance(lchf_file, tmp_path):
    with LabelFile(lchf_file) as lf:
        counts = [np.bincount(f.instances.obj_id).max() for f in lf.frames()]
    assert max(counts) >= 3  # several instances of the same object in one frame
    s = evaluate(oracle_predictor(), lchf_file, tmp_path / "a")
    f = s["f1"]["noicp"]
    assert (f["precision"], f["recall"], f["f1"]) == (1.0, 1.0, 1.0) and f["num_det"] == f["num_gt"]
    n = f["num_gt"]
    assert n == sum(o["num_gt"] for o in s["objects"]) >= 6

    base = oracle_predictor()

    def drop_first_instance(frame):  # the network misses instance 0 of every frame
        p = base(frame)  # all the frame's points, in its order
        keep = frame.instance != 0
        return Predictions(p.xyz[keep], p.class_probs[keep], p.class_ids, p.control_points[keep], p.confidence[keep])

    s2 = evaluate(drop_first_instance, lchf_file, tmp_path / "b")
    f = s2["f1"]["noicp"]
    assert f["precision"] == 1.0 and f["recall"] == pytest.approx((n - 2) / n) and f["num_det"] == n - 2


def test_a_higher_scoring_far_pose_is_the_answer_for_add_while_f1_counts_every_detection(label_file, tmp_path,
                                                                                           monkeypatch):
    """Per frame, the first visible instance gets its true pose (score 0.5) and, scored higher (0.9), a pose 0.8
    diameters off: ADD takes the top-scoring pose, so that instance is wrong; F1 counts one TP and one FP."""
    import detector.evaluate as ev
    from detector.geometry.types import Detection

    with LabelFile(label_file) as lf:
        dia = {int(o): float(d) for o, d in zip(lf.objects.ids, lf.objects.diameters)}

    def fake_estimate(preds, objects, cfg, timings, cloud, poser, features, check_unrefined=None):
        inst = fake_estimate.frame.instances
        valid = np.flatnonzero(inst.visib_fract >= 0.1)
        dets = [Detection(int(inst.obj_id[g]), 0.5, inst.R[g].astype(float), inst.t[g].astype(float), 1,
                          np.zeros((9, 3)), np.zeros(0, np.int64)) for g in valid]
        g = valid[0]
        far = inst.t[g] + [0.8 * dia[int(inst.obj_id[g])], 0, 0]
        dets.append(Detection(int(inst.obj_id[g]), 0.9, inst.R[g].astype(float), far, 1, np.zeros((9, 3)),
                              np.zeros(0, np.int64)))
        return dets, None

    def predictor(frame):
        fake_estimate.frame = frame
        return Predictions(np.zeros((0, 3)), np.zeros((0, 1)), [], np.zeros((0, 9, 3)), np.zeros(0))

    monkeypatch.setattr(ev, "estimate", fake_estimate)
    s = evaluate(predictor, label_file, tmp_path)
    rows = s["instances"]
    frames = sorted({r["frame"] for r in rows})
    first = [next(r for r in rows if r["frame"] == f) for f in frames]
    assert all(r["noicp"] == np.inf for r in first)  # the top-scoring pose is 0.8 diameters off
    assert all(r["noicp"] < 1e-5 for r in rows if r not in first)
    assert s["mean"]["noicp"]["0.30"] < 1.0
    f = s["f1"]["noicp"]
    assert (f["num_det"], f["num_gt"]) == (len(rows) + len(frames), len(rows))
    assert f["recall"] == 1.0 and f["precision"] == pytest.approx(len(rows) / (len(rows) + len(frames)))


def test_a_predictor_that_finds_nothing_scores_zero(label_file, tmp_path):
    base = oracle_predictor()

    def background(frame):
        p = base(frame)
        probs = np.zeros_like(p.class_probs)
        probs[:, 0] = 1
        return Predictions(p.xyz, probs, p.class_ids, p.control_points, p.confidence)

    s = evaluate(background, label_file, tmp_path, icp=True)
    assert s["mean"]["noicp"]["0.10"] == 0.0 and s["mean"]["icp"]["0.10"] == 0.0
    assert s["f1"]["icp"] == {"precision": 0.0, "recall": 0.0, "f1": 0.0, "num_det": 0, "num_gt": s["f1"]["icp"]["num_gt"]}
    assert (tmp_path / s["bop_csv"]).read_text() == "scene_id,im_id,obj_id,score,R,t,time\n"
    assert json.loads((tmp_path / "report.json").read_text())["instances"][0]["noicp"] is None  # inf -> null


def test_bop19_is_skipped_with_its_reason_when_the_dataset_is_gone(label_file, tmp_path):
    from detector.errors import DetectorError

    (tmp_path / "scores_bop19.json").write_text("{}")  # an earlier run's: must not stay beside this report
    s = evaluate(oracle_predictor(), label_file, tmp_path, frames=[0], bop_dataset=None, bop19=True)
    assert "skipped" not in s["bop19"] and s["bop19"]["num_images"] == 1  # the evaluated frame's targets only
    s = evaluate(oracle_predictor(), label_file, tmp_path, frames=[0], bop19=False)
    assert "skipped" in s["bop19"] and not (tmp_path / "scores_bop19.json").exists()
    assert "Not computed" in (tmp_path / "report.md").read_text()
    with pytest.raises(DetectorError, match="--bop-dataset"):
        evaluate(oracle_predictor(), label_file, tmp_path, bop_dataset=tmp_path / "nowhere")
    assert "is not there" in bop19_summary([], set(), tmp_path / "moved away", "train_pbr")["skipped"]


def test_bop_results_file_name_round_trip():
    """The BOP toolkit parses METHOD_DATASET-SPLIT[-SPLITTYPE].csv at '_' and '-': our names parse back."""
    from detector.errors import DetectorError
    from detector.report import bop_csv_name, default_dataset_name, parse_bop_csv_name

    assert bop_csv_name("argen", "lm", "test") == "argen_lm-test.csv"
    assert parse_bop_csv_name(bop_csv_name("argen", "lmtest", "train_pbr")) == {
        "method": "argen", "dataset": "lmtest", "split": "train", "split_type": "pbr"}
    assert parse_bop_csv_name("argen_lmo-test.csv")["split_type"] is None
    assert default_dataset_name("data/lm_test") == "lmtest" and default_dataset_name("") == "argen"
    for bad in [("my_method", "lm", "test"), ("argen", "lm-o", "test"), ("argen", "lm", "a_b_c"), ("", "lm", "test")]:
        with pytest.raises(DetectorError):
            bop_csv_name(*bad)
    with pytest.raises(ValueError):
        parse_bop_csv_name("results_bop_x.csv")


def test_a_network_trained_without_colour_ignores_the_frame_colours(random_checkpoint, label_file, tmp_path):
    """A checkpoint whose normalisation says colour "none" (``detector.data.input_normalisation``) predicts the same
    whatever colours the frame has; the same weights with colour input do not (the control)."""
    from types import SimpleNamespace

    from detector.checkpoint import load_checkpoint
    from detector.data.augment import input_normalisation
    from detector.stage1.predictor import network_predictor

    ck = load_checkpoint(random_checkpoint)
    path = tmp_path / "none.pt"
    save_checkpoint(path, model=ck.model, model_config=ck.model_config, class_ids=ck.class_ids, objects=ck.objects,
                    num_points=ck.num_points, step=0, normalisation=input_normalisation("none"))
    none = load_checkpoint(path)
    with LabelFile(label_file) as lf:
        feats = np.asarray(lf.frame(0).features, np.float32)
    other = feats.copy()
    other[:, 3:6] = np.random.default_rng(0).random((len(feats), 3))
    for ckpt, same in ((none, True), (ck, False)):
        a = network_predictor(ckpt)(SimpleNamespace(features=feats))
        b = network_predictor(ckpt)(SimpleNamespace(features=other))
        assert np.array_equal(a.xyz, b.xyz)
        assert np.allclose(a.class_probs, b.class_probs, atol=1e-6) == same
        assert np.allclose(a.control_points, b.control_points, atol=1e-6) == same


def test_sampling_passes_pool_samplings_and_each_pass_predicts_as_alone(random_checkpoint, label_file):
    """With ``sampling.passes`` 2 stage 1 predicts on two samplings of the frame, in one batch: the first pass's rows
    are the single pass's (same points, same predictions up to the batch's float rounding), the second's are the
    network run alone on the draw of the seed sequence (seed, 1); every prediction sits on a frame point."""
    from types import SimpleNamespace

    import torch

    from detector.checkpoint import load_checkpoint
    from detector.stage1.dataset import inference_batch
    from detector.stage1.predictor import network_predictor

    one, two = load_checkpoint(random_checkpoint), load_checkpoint(random_checkpoint, sampling={"passes": 2})
    assert (one.sampling["passes"], two.sampling["passes"]) == (1, 2)
    with LabelFile(label_file) as lf:
        feats = np.asarray(lf.frame(0).features, np.float32)
    frame = SimpleNamespace(features=feats)
    a, b = network_predictor(one, 3)(frame), network_predictor(two, 3)(frame)
    k = len(a.xyz)
    assert len(b.xyz) == 2 * k and b.class_probs.shape == (2 * k, a.class_probs.shape[1])
    assert b.control_points.shape == (2 * k, 9, 3) and b.confidence.shape == (2 * k,)
    assert np.array_equal(a.xyz, b.xyz[:k])
    for x, y in ((a.class_probs, b.class_probs[:k]), (a.control_points, b.control_points[:k]),
                 (a.confidence, b.confidence[:k])):
        assert np.allclose(x, y, atol=1e-5)
    # the second pass alone: its own draw through the network, mapped back to the frame's points
    batch = inference_batch(feats, one.model_config, one.num_points, [3, 1], normalisation=one.normalisation or None,
                            plane_keep=one.plane_keep)
    rows = batch.pop("point_index").numpy()
    with torch.no_grad():
        out = one.model(batch.pop("features"), batch)
    second = feats[rows[out["keypoints"][0].numpy()], :3].astype(np.float64)
    assert np.array_equal(b.xyz[k:], second) and not np.array_equal(b.xyz[k:], b.xyz[:k])
    assert np.allclose(b.class_probs[k:], torch.softmax(out["logits"][0].float(), -1).numpy(), atol=1e-5)
    assert np.allclose(b.control_points[k:] - b.xyz[k:, None], out["offsets"][0].double().numpy(), atol=1e-5)
    on_frame = {tuple(p) for p in feats[:, :3].astype(np.float64)}
    assert all(tuple(p) in on_frame for p in b.xyz)


def test_sampling_fps_tree_predicts_at_the_tree_fps_keypoints_of_the_same_draw(random_checkpoint, label_file):
    """``sampling.fps`` "tree": stage 1 sees the same drawn points as with the training's FPS, and predicts at the
    keypoints fpsample's tree-based FPS picks among them (an exact FPS sequence from another first point)."""
    from types import SimpleNamespace

    from detector.checkpoint import load_checkpoint
    from detector.stage1.dataset import inference_batch
    from detector.stage1.ops import fps_numpy
    from detector.stage1.predictor import network_predictor

    trained, tree = load_checkpoint(random_checkpoint), load_checkpoint(random_checkpoint, sampling={"fps": "tree"})
    assert (trained.sampling["fps"], tree.sampling["fps"]) == ("trained", "tree")
    with LabelFile(label_file) as lf:
        feats = np.asarray(lf.frame(0).features, np.float32)
    frame = SimpleNamespace(features=feats)
    a, b = network_predictor(trained, 5)(frame), network_predictor(tree, 5)(frame)
    batch = inference_batch(feats, trained.model_config, trained.num_points, 5,
                            normalisation=trained.normalisation or None, plane_keep=trained.plane_keep)
    drawn = feats[batch["point_index"].numpy(), :3]
    keypoints = trained.model_config.npoints[0]
    loop, tree_order = fps_numpy(drawn, keypoints), fps_numpy(drawn, keypoints, tree=True)
    assert np.array_equal(a.xyz, drawn[loop].astype(np.float64))
    assert np.array_equal(b.xyz, drawn[tree_order].astype(np.float64))
    assert not np.array_equal(a.xyz, b.xyz)
    # two passes (drawn in two threads): the first pass's keypoints are the single pass's tree ones
    two = network_predictor(load_checkpoint(random_checkpoint, sampling={"fps": "tree", "passes": 2}), 5)(frame)
    assert np.array_equal(two.xyz[:len(b.xyz)], b.xyz) and len(two.xyz) == 2 * len(b.xyz)


def test_stage1_in_bfloat16_predicts_at_the_same_points_close_to_float32(random_checkpoint, label_file):
    """``net_dtype`` bfloat16 changes the network's arithmetic only: the same sampled keypoints, float outputs within
    bfloat16's rounding of the float32 ones; a bad value fails when the predictor is made."""
    from types import SimpleNamespace

    from detector.checkpoint import load_checkpoint
    from detector.errors import DetectorError
    from detector.stage1.predictor import network_predictor

    ck = load_checkpoint(random_checkpoint)
    with LabelFile(label_file) as lf:
        frame = SimpleNamespace(features=np.asarray(lf.frame(0).features, np.float32))
    a, b = network_predictor(ck, 3)(frame), network_predictor(ck, 3, net_dtype="bfloat16")(frame)
    assert np.array_equal(a.xyz, b.xyz)
    assert b.class_probs.dtype == a.class_probs.dtype and b.control_points.dtype == np.float64
    np.testing.assert_allclose(b.class_probs.sum(1), 1.0, atol=1e-5)
    assert np.abs(b.class_probs - a.class_probs).mean() < 0.01
    assert np.abs(b.control_points - a.control_points).max() < 0.01  # metres, of offsets of a few centimetres
    assert not np.array_equal(b.control_points, a.control_points)  # it did compute in bfloat16
    with pytest.raises(DetectorError, match="net_dtype"):
        network_predictor(ck, 3, net_dtype="float16")


def test_cli_net_dtype_reaches_both_stages_and_the_outputs(random_checkpoint, dataset, tmp_path, monkeypatch):
    """eval and predict make stage 1's predictor and stage 2's poser in the format --net-dtype names (auto resolved
    on this CPU), record it in report.json, report.md and poses.json, and refuse a bad value or device in one line."""
    import detector.infer
    import detector.stage1.predictor
    from detector.cli.app import app
    from detector.net_dtype import resolve_net_dtype

    made = []
    for mod, name in ((detector.stage1.predictor, "network_predictor"), (detector.infer, "checkpoint_poser")):
        real = getattr(mod, name)

        def spy(*args, real=real, name=name, **kw):
            made.append((name, kw.get("net_dtype", args[5] if name == "checkpoint_poser" and len(args) > 5 else None)))
            return real(*args, **kw)
        monkeypatch.setattr(mod, name, spy)
    from argen import bop

    ds, h5 = dataset
    runner = CliRunner()
    for asked, want in (("bfloat16", "bfloat16"), ("float32", "float32"), ("auto", resolve_net_dtype("auto"))):
        made.clear()
        rep = tmp_path / f"rep_{asked}"
        r = runner.invoke(app, ["eval", str(random_checkpoint), str(h5), "--out", str(rep), "--frames", "1",
                                "--tau", "0", "--quiet", "--net-dtype", asked])
        assert r.exit_code == 0, r.output
        assert sorted(made) == [("checkpoint_poser", want), ("network_predictor", want)]
        assert json.loads((rep / "report.json").read_text())["run"]["net_dtype"] == want
        assert f"the networks in {want}" in (rep / "report.md").read_text()
    frame = str(ds / "train_pbr" / "000000" / str(bop.load_scene(ds, "train_pbr", 0).im_ids[0]))
    r = runner.invoke(app, ["predict", str(random_checkpoint), frame, "--out", str(tmp_path / "p"), "--net-dtype",
                            "bfloat16"])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "p" / "poses.json").read_text())["net_dtype"] == "bfloat16"
    for bad, words in ((["--net-dtype", "half"], ["--net-dtype must be one of"]),
                       (["--device", "gpu"], ["--device gpu", "not a torch device"])):
        for cmd in (["eval", str(random_checkpoint), str(h5), "--out", str(tmp_path / "bad")],
                    ["predict", str(random_checkpoint), frame, "--out", str(tmp_path / "bad")]):
            assert_one_line_error(runner.invoke(app, cmd + bad), *words)
    assert not (tmp_path / "bad").exists()
