"""argen label / validate / preview on tiny capture-sim datasets (noise off) and on the LineMOD models."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from pykdtree.kdtree import KDTree
from typer.testing import CliRunner

from argen.cli.app import app
from argen.errors import ArgenError
from argen.features import grid_normals
from argen.h5 import LabelFile
from argen.label import LabelConfig, LabelRequest, object_table, run_label, sample_surface
from argen.models.objects import builtin_objects, load_models

runner = CliRunner()


def cli(*args: str):
    return runner.invoke(app, [str(a) for a in args])


def capture(out: Path, seed: int, *extra: str) -> Path:
    r = cli("capture-sim", "--frames", "3", "--noise", "none", "--out", out, "--seed", str(seed), "--quiet", *extra)
    assert r.exit_code == 0, r.output
    return out


def label(dataset: Path, out: Path, **kw) -> Path:
    run_label(LabelRequest(dataset=dataset, split="train_pbr", out=out, progress=False, **kw))
    return out


@pytest.fixture(scope="session")
def builtin_ds(tmp_path_factory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("label_builtin")
    ds = capture(d / "ds", 11)
    return ds, label(ds, d / "train.h5", cfg=LabelConfig(max_points=20000), chunk=2)


@pytest.fixture(scope="session")
def lm_ds(tmp_path_factory, lm_models) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("label_lm")
    ds = capture(d / "ds", 12, "--models", str(lm_models), "--objects", "ape,can")
    return ds, label(ds, d / "train.h5")


def surface_distances(lf: LabelFile, dataset: Path) -> np.ndarray:
    """Distance of every object-labelled point to its object's surface under the GT pose, metres."""
    models = {o.obj_id: o for o in load_models(dataset / "models")}
    trees = {i: KDTree(sample_surface(o.mesh.vertices, o.mesh.faces, 100_000, np.random.default_rng(i)))
             for i, o in models.items()}
    out = []
    for fr in lf.frames():
        fg = fr.instance >= 0
        inst = fr.instances
        p, k = fr.features[fg, :3].astype(np.float64), fr.instance[fg]
        pm = np.einsum("nji,nj->ni", inst.R[k].astype(np.float64), p - inst.t[k])  # R^T (p - t)
        for i in np.unique(inst.obj_id[k]):
            sel = inst.obj_id[k] == i
            out.append(trees[i].query(pm[sel], k=1)[0])
    return np.concatenate(out)


@pytest.mark.parametrize("which", ["builtin_ds", "lm_ds"])
def test_object_points_lie_on_the_object_surface(which, request):
    dataset, path = request.getfixturevalue(which)
    with LabelFile(path) as lf:
        d = surface_distances(lf, dataset)
    assert len(d) > 500
    assert np.mean(d < 0.002) >= 0.99, np.percentile(d, [50, 99, 100])


def test_control_points_are_the_posed_box_from_scene_gt(builtin_ds):
    dataset, path = builtin_ds
    info = json.loads((dataset / "models/models_info.json").read_text())
    gt = json.loads((dataset / "train_pbr/000000/scene_gt.json").read_text())
    with LabelFile(path) as lf:
        assert lf.num_frames == len(gt) >= 2
        for fr in lf.frames():
            entries = gt[str(fr.im_id)]
            assert len(fr.instances) == len(entries)
            for k, e in enumerate(entries):
                m = info[str(e["obj_id"])]
                lo = np.array([m["min_x"], m["min_y"], m["min_z"]]) / 1000
                hi = lo + np.array([m["size_x"], m["size_y"], m["size_z"]]) / 1000
                corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
                R = np.array(e["cam_R_m2c"]).reshape(3, 3)
                t = np.array(e["cam_t_m2c"]) / 1000
                cps = fr.instances.control_points[k]
                np.testing.assert_allclose(cps[:8], corners @ R.T + t, atol=2e-6)
                np.testing.assert_allclose(cps[8], (lo + hi) / 2 @ R.T + t, atol=2e-6)
                pts = fr.instance == k
                assert np.all(fr.semantic[pts] == e["obj_id"])
                np.testing.assert_array_equal(fr.control_points[pts], np.broadcast_to(cps, (pts.sum(), 9, 3)))
            assert np.all(fr.control_points[fr.instance < 0] == 0) and np.all(fr.semantic[fr.instance < 0] == 0)


def test_features_colours_normals_and_subsampling(builtin_ds):
    dataset, path = builtin_ds
    from argen.bop import read_rgb

    with LabelFile(path) as lf:
        assert lf.attrs["max_points"] == 20000 and lf.attrs["subsampling"] == "random"
        fr = lf.frame(1)
        assert len(fr) == 20000  # the frame had more valid pixels
        assert len(np.unique(fr.pixel[:, 0] * 10000 + fr.pixel[:, 1])) == len(fr)
        rgb = read_rgb(dataset / f"train_pbr/000000/rgb/{fr.im_id:06d}.jpg")
        np.testing.assert_allclose(fr.features[:, 3:6] * 255, rgb[fr.pixel[:, 0], fr.pixel[:, 1]], atol=1e-3)
        n = fr.features[:, 6:9]
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-5)
        assert np.all(np.einsum("ij,ij->i", n, fr.features[:, :3]) <= 0)


def test_grid_normals_of_a_tilted_plane():
    K = np.array([[500.0, 0, 80], [0, 500, 60], [0, 0, 1]])
    n_true = np.array([0.3, -0.2, -1.0])
    n_true /= np.linalg.norm(n_true)
    rows, cols = np.mgrid[0:120, 0:160]
    rays = np.stack([(cols - 80) / 500, (rows - 60) / 500, np.ones_like(cols, float)], -1)
    depth = (n_true @ np.array([0, 0, 0.8]) / (rays @ n_true)).astype(np.float32)  # plane through (0,0,0.8)
    depth[:, :40] = 0  # a hole: the pixels beside it use one-sided tangents
    r, c = np.nonzero(depth > 0)
    n = grid_normals(depth, K, r, c)
    assert np.degrees(np.arccos(np.clip(n @ n_true, -1, 1))).max() < 0.5


def test_object_table_symmetries_and_model_points():
    objs = builtin_objects(["bottle", "eggcrate", "duck"])
    table = object_table(objs, n_points=200, seed=1)
    assert list(table.ids) == [3, 4, 6]
    assert [len(s) for s in table.sym_transforms] == [36, 1, 2]
    assert list(table.symmetric) == [True, False, True]
    for o, pts, syms in zip(sorted(objs, key=lambda o: o.obj_id), table.model_points, table.sym_transforms):
        lo, hi = o.mesh.bounds
        assert np.all(pts >= lo - 1e-6) and np.all(pts <= hi + 1e-6)
        assert np.all(pts.max(0) - pts.min(0) > 0.8 * (hi - lo))  # spread over the whole model
        np.testing.assert_array_equal(syms[0], np.eye(4))
        # every symmetry maps the model's surface onto itself
        tree = KDTree(sample_surface(o.mesh.vertices, o.mesh.faces, 100_000, np.random.default_rng(0)))
        for S in syms:
            d = tree.query(pts.astype(np.float64) @ S[:3, :3].T + S[:3, 3], k=1)[0]
            assert np.mean(d < 0.002) > 0.97


def test_missing_mask_visib_is_rendered_with_the_same_labels(builtin_ds, tmp_path):
    dataset, path = builtin_ds
    real = tmp_path / "real"
    shutil.copytree(dataset, real, ignore=shutil.ignore_patterns("mask_visib", "mask", "scene_gt_info.json"))
    out = label(real, tmp_path / "real.h5", cfg=LabelConfig(max_points=20000), chunk=2)
    with LabelFile(path) as a, LabelFile(out) as b:
        for i in range(a.num_frames):
            fa, fb = a.frame(i), b.frame(i)
            np.testing.assert_array_equal(fa.pixel, fb.pixel)
            for k in range(len(fa.instances)):
                sa, sb = fa.instance == k, fb.instance == k
                iou = (sa & sb).sum() / max((sa | sb).sum(), 1)
                assert iou > 0.98, (i, k, iou)
            np.testing.assert_allclose(fa.instances.visib_fract, fb.instances.visib_fract, atol=0.02)


def test_validate_accepts_then_rejects_tampered_labels(builtin_ds, tmp_path):
    path = builtin_ds[1]
    r = cli("validate", path)
    assert r.exit_code == 0 and "valid (" in r.output
    messages = {"control_points": "control points differ", "semantic": "semantic label",
                "part_sym": "is not a rotation", "odd_points": "outside its box"}  # and valid ones pass: above
    for what, message in messages.items():
        bad = tmp_path / f"bad_{what}.h5"
        shutil.copy(path, bad)
        with h5py.File(bad, "r+") as f:
            if what == "control_points":
                f["instances/control_points"][1, 3, 0] += 0.01
            elif what == "semantic":
                sem = f["points/semantic"]
                i = int(np.flatnonzero(sem[()] > 0)[0])
                sem[i] = 0
            else:  # the first object given a part symmetry: a turn scaled by 1.1, or odd points 1 m off
                n = len(f["objects/ids"])
                turn = np.eye(4, dtype=np.float32)[None] * (1.1 if what == "part_sym" else 1.0)
                turn[0, 3, 3] = 1.0
                odd = f["objects/model_points"][0, :3] + (0.0 if what == "part_sym" else 1.0)
                for name, data in (("part_sym", turn), ("part_sym_offsets", np.r_[0, [1] * n]),
                                   ("odd_points", odd), ("odd_offsets", np.r_[0, [3] * n])):
                    del f[f"objects/{name}"]
                    f[f"objects/{name}"] = data
        r = cli("validate", bad)
        assert r.exit_code == 1
        assert message in r.output, r.output


def test_preview_of_file_and_of_bop_scene(builtin_ds, tmp_path):
    dataset, path = builtin_ds
    from argen.bop import read_rgb

    with LabelFile(path) as lf:
        im_id = lf.frame(1).im_id
    for src in (path, dataset):
        out = tmp_path / f"{Path(src).stem}.png"
        r = cli("preview", src, "--frame", "1", "--out", out)
        assert r.exit_code == 0, r.output
        img = read_rgb(out)
        rgb = read_rgb(dataset / f"train_pbr/000000/rgb/{im_id:06d}.jpg")
        changed = np.any(img != rgb, axis=2)
        assert 0.002 < changed.mean() < 0.5  # tinted object points and box lines, the rest untouched


@pytest.mark.parametrize("args, message", [
    (["--split", "test"], "split folder not found"),
    (["--max-points", "0"], "--max-points"),
    (["--max-depth", "1500"], "metres"),
    (["--models", "/nonexistent"], "models folder not found"),
])
def test_bad_input_is_one_line_error(builtin_ds, tmp_path, args, message):
    r = cli("label", builtin_ds[0], "--out", tmp_path / "x.h5", "--quiet", *args)
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and message in lines[0], r.output
    assert not (tmp_path / "x.h5").exists()


def test_existing_output_and_changed_options(builtin_ds, tmp_path):
    r = cli("label", builtin_ds[0], "--out", builtin_ds[1], "--quiet")
    assert r.exit_code == 2 and "--overwrite" in r.output
    partial = tmp_path / "y.h5.partial"
    partial.mkdir()
    (partial / "run.json").write_text("{}")
    with pytest.raises(ArgenError, match="other options"):
        label(builtin_ds[0], tmp_path / "y.h5")


def contents(path: Path) -> dict:
    out = {}
    with h5py.File(path, "r") as f:
        out["attrs"] = {k: (v.tolist() if hasattr(v, "tolist") else v) for k, v in f.attrs.items()}
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def assert_same_contents(a: Path, b: Path) -> None:
    ca, cb = contents(a), contents(b)
    assert ca.keys() == cb.keys()
    assert ca.pop("attrs") == cb.pop("attrs")
    for k in ca:
        np.testing.assert_array_equal(ca[k], cb[k], err_msg=k)


def test_kill_and_resume_equals_uninterrupted_run(builtin_ds, tmp_path):
    dataset, _ = builtin_ds
    ref = label(dataset, tmp_path / "ref.h5", chunk=1, cfg=LabelConfig(render_masks=True))
    argen = [sys.executable, "-c", "from argen.cli.app import main; main()"]
    for attempt in range(3):
        out = tmp_path / f"run{attempt}.h5"
        first_part = tmp_path / f"run{attempt}.h5.partial" / "part-000000.h5"
        cmd = argen + ["label", str(dataset), "--out", str(out), "--chunk", "1", "--render-masks", "--quiet"]
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 60
        while not first_part.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.005)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        if not out.exists():
            break  # really interrupted (else it finished first: try again)
    assert not out.exists() and first_part.exists()
    assert len(list(first_part.parent.glob("part-*.h5"))) < 3
    # what a kill inside a write leaves (the kill above rarely hits that window): the resumed run removes them,
    # but not another output's temporary file in the same folder
    strays = [first_part.parent / ".tmp-part-000001-abcd1234.h5", tmp_path / f".tmp-{out.stem}-abcd1234.h5"]
    other = tmp_path / f".tmp-{out.stem}-b-abcd1234.h5"  # of a run writing "{stem}-b.h5"
    for p in [*strays, other]:
        p.write_bytes(b"half")
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "already done" in r.stdout and not first_part.parent.exists()
    assert not any(p.exists() for p in strays) and other.exists()
    assert_same_contents(ref, out)


def test_two_workers_equal_one(builtin_ds, tmp_path):
    dataset, path = builtin_ds
    r = cli("label", dataset, "--out", tmp_path / "w2.h5", "--max-points", "20000", "--chunk", "1",
            "--workers", "2", "--quiet")
    assert r.exit_code == 0, r.output
    a, b = contents(path), contents(tmp_path / "w2.h5")
    for k in a:
        if k != "attrs":
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_masked_points_outside_the_bounding_sphere_become_background():
    from argen.label import FAR_MARGIN, Labeller

    obj = builtin_objects(["duck"])[0]
    lab = Labeller({obj.obj_id: obj}, LabelConfig())
    t = np.array([0.05, -0.02, 0.9])
    cps = (obj.control_points + t)[None]
    radius = np.linalg.norm(obj.corners - obj.control_points[8], axis=1).max()
    dirs = np.random.default_rng(0).normal(size=(6, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dist = np.array([0.0, 0.5, 1.0, 1.0, 1.5, 3.0]) * radius + np.array([0, 0, 0, FAR_MARGIN * 0.9, 0, 0])
    pts = cps[0, 8] + dirs * dist[:, None]
    inst = lab._drop_far(np.array([0, 0, 0, 0, 0, -1]), pts, cps, np.array([obj.obj_id]))
    assert inst.tolist() == [0, 0, 0, 0, -1, -1]
