"""Data-parallel training: ``detector train`` under torchrun with 2 CPU processes (gloo) follows the
single-process run on the same data, and the pieces that make it so (batch shares, global normalisation)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from test_data import TINY_MODEL, write_synthetic_h5

from detector.checkpoint import load_checkpoint
from detector.data.batches import StreamBatchSampler, rank_share
from detector.errors import DetectorError
from detector.stage1.loss import LossConfig, multitask_loss
from detector.training.metrics_log import read_metrics

torch.set_num_threads(1)


def test_rank_shares_tile_the_global_batch():
    full = StreamBatchSampler(10, 4, seed=3)
    parts = [StreamBatchSampler(10, 4, seed=3, rank=r, world_size=2) for r in range(2)]
    for b, (whole, *shares) in zip(range(6), zip(iter(full), *map(iter, parts))):
        assert sum(shares, []) == whole, b
    with pytest.raises(DetectorError, match="not divisible by the 3"):
        rank_share(4, 0, 3)


def test_loss_normalised_over_the_global_batch_averages_to_the_whole_batch_loss():
    g = torch.Generator().manual_seed(0)
    b, k, c = 4, 64, 3
    out = {"logits": torch.randn(b, k, c + 1, generator=g), "xyz": torch.randn(b, k, 3, generator=g) * 0.1,
           "offsets": torch.randn(b, k, 9, 3, generator=g) * 0.05, "confidence": torch.rand(b, k, generator=g)}
    target = {"cls": torch.randint(0, c + 1, (b, k), generator=g),
              "control_points": torch.randn(b, k, 9, 3, generator=g) * 0.1}
    target["cls"][2:] = torch.where(target["cls"][2:] > 1, 0, target["cls"][2:])  # shares with unequal object counts
    cfg = LossConfig()
    whole, _ = multitask_loss(out, target, cfg)
    n_global = float((target["cls"] > 0).sum())
    halves = [multitask_loss({kk: v[s] for kk, v in out.items()}, {kk: v[s] for kk, v in target.items()}, cfg,
                             pos_count=n_global / 2)[0] for s in (slice(0, 2), slice(2, 4))]
    assert torch.allclose((halves[0] + halves[1]) / 2, whole, rtol=1e-6)
    plain = [multitask_loss({kk: v[s] for kk, v in out.items()}, {kk: v[s] for kk, v in target.items()}, cfg)[0]
             for s in (slice(0, 2), slice(2, 4))]
    assert not torch.allclose((plain[0] + plain[1]) / 2, whole, rtol=1e-4)  # per-share normalisation would differ


def _train_args(h5: Path, out: Path, steps: int) -> list[str]:
    args = ["train", str(h5), "--out", str(out), "--preset", "cpu", "--steps", str(steps), "--batch-size", "4", "--workers", "0",
            "--quiet", "--set", "num_points=1024", "--set", "warmup_steps=1", "--seg-pretrain-steps", "1",
            "--set", "checkpoint_every=2"]
    for key, value in TINY_MODEL.items():
        args += ["--set", f"model.{key}={value}"]
    return args


def _env() -> dict[str, str]:
    """This environment with one thread per process and without an outer torchrun's variables."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).parent)}
    return {k: v for k, v in env.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")}


def _run(cmd: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=_env(), cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    return res


def test_two_gloo_processes_match_single_process_training(tmp_path):
    h5 = write_synthetic_h5(tmp_path / "syn.h5", num_frames=6, seed=4)
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    for name, launch in (("single", [sys.executable]), ("ddp", torchrun)):
        # 2 steps, then resumed to 4 (the schedule stretches the same way in both runs)
        res = _run([*launch, "-m", "detector.cli.app", *_train_args(h5, tmp_path / name, 2)], tmp_path)
        assert ("(2 processes)" in res.stdout) == (name == "ddp"), res.stdout
        _run([*launch, "-m", "detector.cli.app", "train", str(h5), "--out", str(tmp_path / name), "--resume",
              "--steps", "4", "--quiet"], tmp_path)
    one, two = read_metrics(tmp_path / "single" / "metrics.csv"), read_metrics(tmp_path / "ddp" / "metrics.csv")
    assert [r["step"] for r in two] == [1, 2, 3, 4] and [r["phase"] for r in two] == ["seg", "full", "full", "full"]
    for a, b in zip(one, two):
        for key in ("loss", "cls", "offset", "conf", "acc"):
            assert b[key] == pytest.approx(a[key], rel=1e-5, abs=1e-7), (a["step"], key)
    single = load_checkpoint(tmp_path / "single" / "last.pt")
    w1 = single.model.state_dict()
    w2 = load_checkpoint(tmp_path / "ddp" / "last.pt").model.state_dict()
    assert w1.keys() == w2.keys()
    worst = max(float((w1[k].double() - w2[k].double()).abs().max()) for k in w1 if w1[k].is_floating_point())
    assert worst < 1e-5, worst  # 4 AdamW steps of lr 2e-3 move weights by up to ~8e-3
    moved = max(float((w1[k].double() - w0).abs().max())
                for k, w0 in _initial_weights(tmp_path, len(single.class_ids)).items())
    assert moved > 1e-3  # the comparison is not between two untrained models


def _initial_weights(tmp_path: Path, num_classes: int) -> dict[str, torch.Tensor]:
    from detector.stage1.network import PointNet2
    from detector.stage1.train import build_model_config, load_config_file

    cfg = load_config_file(tmp_path / "single" / "config.yaml")
    torch.manual_seed(cfg.seed)
    net = PointNet2(build_model_config(cfg), num_classes=num_classes)
    return {k: v.double() for k, v in net.state_dict().items() if v.is_floating_point()}


def test_batch_not_divisible_by_the_processes_is_one_line(tmp_path):
    h5 = write_synthetic_h5(tmp_path / "syn.h5", num_frames=3, seed=5)
    args = _train_args(h5, tmp_path / "r", 2)
    args[args.index("--batch-size") + 1] = "3"
    res = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                          "-m", "detector.cli.app", *args], capture_output=True, text=True, timeout=600, env=_env())
    assert res.returncode != 0
    assert "detector: error: batch_size 3 is not divisible by the 2 distributed processes" in res.stderr
    assert not (tmp_path / "r" / "last.pt").exists()
