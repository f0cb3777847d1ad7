"""Smoke tests of the ``detector`` command line: train, refuse, resume, one-line errors with exit code 2."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from test_data import TINY_MODEL, write_synthetic_h5
from typer.testing import CliRunner

from detector.cli.app import app
from detector.training.metrics_log import read_metrics

torch.set_num_threads(1)
runner = CliRunner()


@pytest.fixture(scope="module")
def h5_path(tmp_path_factory) -> Path:
    return write_synthetic_h5(tmp_path_factory.mktemp("data") / "syn.h5", num_frames=3, seed=1)


def tiny_args() -> list[str]:
    args = ["--preset", "cpu", "--workers", "0", "--batch-size", "2", "--quiet", "--set", "num_points=1024",
            "--set", "warmup_steps=1"]
    for k, v in TINY_MODEL.items():
        args += ["--set", f"model.{k}={v}"]
    return args


def run(*args: str):
    return runner.invoke(app, [str(a) for a in args])


def assert_one_line_error(res, *words: str) -> None:
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("detector: error: "), res.stderr
    for w in words:
        assert w in lines[0], lines[0]


def test_train_refuse_resume_overwrite(h5_path, tmp_path):
    out = tmp_path / "runs" / "a"
    res = run("train", h5_path, "--out", out, "--steps", "2", "--val", h5_path, "--seg-pretrain-steps", "1",
              *tiny_args())
    assert res.exit_code == 0, res.output
    assert (out / "last.pt").is_file() and (out / "best.pt").is_file() and (out / "config.yaml").is_file()
    rows = read_metrics(out / "metrics.csv")
    assert [r["step"] for r in rows] == [1, 2] and [r["phase"] for r in rows] == ["seg", "full"]
    assert_one_line_error(run("train", h5_path, "--out", out, "--steps", "2", *tiny_args()), "--resume", "--overwrite")
    res = run("train", h5_path, "--out", out, "--resume", "--steps", "3", "--quiet")
    assert res.exit_code == 0, res.output
    assert [r["step"] for r in read_metrics(out / "metrics.csv")] == [1, 2, 3]
    res = run("train", h5_path, "--out", out, "--overwrite", "--steps", "1", *tiny_args())
    assert res.exit_code == 0, res.output
    assert [r["step"] for r in read_metrics(out / "metrics.csv")] == [1]


def test_user_errors_are_one_line_with_exit_code_2(h5_path, tmp_path):
    out = tmp_path / "r"
    assert_one_line_error(run("train", tmp_path / "missing.h5", "--out", out, *tiny_args()), "missing.h5")
    assert_one_line_error(run("train", h5_path, "--out", out, "--steps", "2", "--epochs", "1"), "--steps")
    assert_one_line_error(run("train", h5_path, "--out", out, "--set", "batchsize=3"), "batchsize")
    assert_one_line_error(run("train", h5_path, "--out", out, "--set", "lr"), "KEY=VALUE")
    assert_one_line_error(run("train", h5_path, "--out", out, "--preset", "huge"), "huge")
    assert_one_line_error(run("train", h5_path, "--out", out, "--resume"), "config.yaml")
    (tmp_path / "notarun").mkdir()
    (tmp_path / "notarun" / "keep.txt").write_text("x")
    assert_one_line_error(run("train", h5_path, "--out", tmp_path / "notarun", "--overwrite"), "not look like a run")
    assert (tmp_path / "notarun" / "keep.txt").is_file()


def test_console_script_help():
    exe = Path(sys.executable).with_name("detector")
    cmd = [str(exe)] if exe.is_file() else [sys.executable, "-m", "detector.cli.app"]
    res = subprocess.run([*cmd, "train", "--help"], capture_output=True, text=True, timeout=60,
                         env={**os.environ, "COLUMNS": "200"})
    assert res.returncode == 0 and "--seg-pretrain-steps" in res.stdout and "--resume" in res.stdout
