"""Shards of a capture (`--shard I/N`) merged with `argen merge` equal a single-machine run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from argen.cli.app import app

runner = CliRunner()
ARGS = ["--frames", "5", "--seed", "21", "--quiet", "--set", "camera.elevation_deg=[30.0,80.0]"]


def run(*args):
    res = runner.invoke(app, list(args))
    return res


def files_of(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def untimed_log(root: Path) -> list[dict]:
    return [{k: v for k, v in e.items() if "time" not in k}
            for e in json.loads((root / "capture_log.json").read_text())["frames"]]


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    d = tmp_path_factory.mktemp("shards")
    assert run("capture-sim", "--out", str(d / "single"), *ARGS).exit_code == 0
    for i in range(3):
        res = run("capture-sim", "--out", str(d / f"s{i}"), "--shard", f"{i}/3", *ARGS)
        assert res.exit_code == 0, res.output
    return d


def test_merged_shards_equal_a_single_run(shards):
    res = run("merge", str(shards / "s2"), str(shards / "s0"), str(shards / "s1"), "--out", str(shards / "merged"))
    assert res.exit_code == 0, res.output
    a, b = files_of(shards / "single"), files_of(shards / "merged")
    assert a.keys() == b.keys()
    assert {k for k in a if a[k] != b[k]} <= {"capture_log.json"}  # timings only, checked below
    assert untimed_log(shards / "single") == untimed_log(shards / "merged")
    # each shard made only its own frames
    idx = [e["index"] for e in json.loads((shards / "s1" / "capture_log.json").read_text())["frames"]]
    assert idx == [1, 4]


def test_missing_or_foreign_shards_are_refused(shards, tmp_path):
    res = run("merge", str(shards / "s0"), str(shards / "s1"), "--out", str(tmp_path / "m"))
    assert res.exit_code == 2 and "missing shard(s) 2/3" in res.output
    res = run("merge", str(shards / "s0"), str(shards / "s1"), str(shards / "single"), "--out", str(tmp_path / "m"))
    assert res.exit_code == 2 and ("not shards of one capture" in res.output or "--shard counts" in res.output)
    assert not (tmp_path / "m").exists()


@pytest.mark.parametrize("value", ["3/3", "x", "1/0", "-1/2"])
def test_bad_shard_option(tmp_path, value):
    res = run("capture-sim", "--out", str(tmp_path / "o"), "--shard", value, *ARGS)
    assert res.exit_code == 2 and "--shard" in res.output


def h5_contents(path: Path) -> dict:
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        out["attrs"] = {k: (v.tolist() if hasattr(v, "tolist") else v) for k, v in f.attrs.items()}
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def test_label_shards_merge_to_the_single_run_file(shards, tmp_path):
    import numpy as np

    ds = shards / "single"
    common = ["--max-points", "3000", "--chunk", "1", "--quiet"]
    assert run("label", str(ds), "--out", str(tmp_path / "one.h5"), *common).exit_code == 0
    for i in range(2):
        res = run("label", str(ds), "--out", str(tmp_path / f"p{i}.h5"), "--shard", f"{i}/2", *common)
        assert res.exit_code == 0, res.output
    res = run("merge", str(tmp_path / "p1.h5"), str(tmp_path / "p0.h5"), "--out", str(tmp_path / "m.h5"))
    assert res.exit_code == 0, res.output
    a, b = h5_contents(tmp_path / "one.h5"), h5_contents(tmp_path / "m.h5")
    assert a.keys() == b.keys() and a.pop("attrs") == b.pop("attrs")
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    res = run("merge", str(tmp_path / "p1.h5"), "--out", str(tmp_path / "m2.h5"))
    assert res.exit_code == 2 and "missing shard(s) 0/2" in res.output
    res = run("merge", str(tmp_path / "one.h5"), "--out", str(tmp_path / "m3.h5"))
    assert res.exit_code == 2 and "not a shard" in res.output
