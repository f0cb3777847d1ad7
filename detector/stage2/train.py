"""Stage-2 training: the crop network (:mod:`detector.stage2.network`) on ground-truth-centred, jittered crops.

A run folder holds ``config.yaml``, ``metrics.csv`` (one row per step) and ``last.pt`` (every
``checkpoint_every`` steps and at the end, with the optimiser state for ``resume``). Items are pure functions of
(seed, epoch, frame), batches are ``batch_frames`` frames' crops, so a resumed run repeats the uninterrupted
one. The learning-rate schedule is :func:`detector.training.schedule.lr_factor`'s. CPU or CUDA, the same code.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import yaml
from tqdm import tqdm

from detector.config import config_from_dict, config_to_dict, set_dotted
from detector.data.augment import COLOUR_MODES, COLOUR_MODES_TEXT, input_normalisation
from detector.data.batches import StreamBatchSampler
from detector.errors import DetectorError
from detector.net_dtype import check_net_dtype, net_autocast
from detector.stage2.crops import CropConfig
from detector.stage2.dataset import CropDataset, collate_crops
from detector.stage2.network import CropNet, CropNetConfig, crop_loss
from detector.training.checkpoint_file import FORMAT, TWO_STAGE_VERSION, atomic_torch_save, read_checkpoint
from detector.training.devices import loader_generator, resolve_device, worker_init
from detector.training.metrics_log import MetricsLog
from detector.training.optim import optimiser_step
from detector.training.resume import restore_state, rng_state, run_checkpoint, with_added_settings
from detector.training.schedule import lr_factor
from detector.training.threads import ThreadPlan


STAGE2_KIND = "crop-pose"

STAGE2_METRICS = ["step", "epoch", "loss", "fg", "coord", "fg_acc", "crops", "lr", "steps_per_s", "threads"]

#: Settings added to Stage2TrainConfig after runs were first saved, with the value that reproduces a run saved
#: without them (:func:`saved_settings`).
STAGE2_ADDED_SETTINGS = {"crop.negatives": 0.0, "crop.part_turns": False, "narrow_steps": 0, "net_dtype": "float32"}

#: Stage2TrainConfig keys that may differ when resuming: they do not change the steps' numbers (``steps`` stretches
#: or shortens the schedule from the step reached; the crop cache holds the same crops whatever its size).
STAGE2_RESUME_FREE_KEYS = frozenset({"steps", "checkpoint_every", "keep_every", "num_workers", "cache_mb", "device"})


@dataclass
class Stage2TrainConfig:
    """A stage-2 run. steps: optimiser steps; batch_frames: frames per batch (each gives its instances' crops);
    keep_every: besides ``last.pt``, keep the weights every this many steps as ``step_NNNNNN.pt`` (0 = none;
    each is a stage-2 checkpoint without the optimiser state, about 1 MB, e.g. for a time-to-accuracy curve);
    cache_mb: the data process keeps the frames' crop regions in memory up to this many MB and cuts later epochs'
    crops from there (:class:`detector.stage2.dataset.CropDataset`; the same crops; about 0.4 MB a frame of a 30000-point label
    file of the linemod template, more with ``crop.negatives``, whose crops reach further: 1.7 times as much on the
    ycbv template; 0 = read every frame from the file each time); narrow_steps: the first this many steps train on
    the threads stage 1 leaves when the stages train side by side, the later ones on all
    (:mod:`detector.training.threads`; thread counts change a step's rounding, so this is a setting of the run;
    None = the two-stage config sets it from stage 1's steps; 0 = the stages one after the other, each on all
    threads, as runs saved before this setting trained); net_dtype: the number format of the network's forward
    and loss, "float32" or "bfloat16" (torch's CPU autocast, as ``detector eval --net-dtype``; the weights, their
    gradients and the optimiser stay float32; on the CPU only)."""

    crop: CropConfig = field(default_factory=CropConfig)
    net: CropNetConfig = field(default_factory=CropNetConfig)
    steps: int = 18000
    batch_frames: int = 8
    lr: float = 2e-3
    weight_decay: float = 1e-4
    schedule: str = "cosine"
    warmup_steps: int = 100
    min_lr_ratio: float = 0.01
    grad_clip: float = 10.0
    w_coord: float = 5.0
    augment: bool = True
    class_ids: list[int] | None = None
    checkpoint_every: int = 200
    keep_every: int = 0
    num_workers: int = 1
    cache_mb: float = 2048.0
    device: str = "auto"
    seed: int = 0
    narrow_steps: int | None = None
    net_dtype: str = "float32"


def stage2_payload(net: CropNet, cfg: Stage2TrainConfig, class_ids: list[int], objects: dict, step: int,
                   train_state: dict | None = None) -> dict:
    """The stage-2 part of a checkpoint: weights, configs, classes and the object table (plain values)."""
    return {"kind": STAGE2_KIND, "model_state": {k: v.detach().cpu() for k, v in net.state_dict().items()},
            "net_config": cfg.net.to_dict(), "crop_config": cfg.crop.to_dict(), "class_ids": list(class_ids),
            "objects": objects, "normalisation": input_normalisation(cfg.crop.colour), "step": int(step),
            "train_config": config_to_dict(cfg), "train_state": train_state}


def forward_stage2_loss(net: torch.nn.Module, batch: dict, cfg: Stage2TrainConfig, device: torch.device
                      ) -> tuple[torch.Tensor, dict[str, float]]:
    """Loss of a batch of crops and its parts, plus the foreground accuracy and the number of crops."""
    feats, cls = batch["features"].to(device), batch["cls"].to(device)
    fg, coords, mask = batch["fg"].to(device), batch["coords"].to(device), batch["sym_mask"].to(device)
    with net_autocast(cfg.net_dtype):
        out = net(feats, cls)
        loss, parts = crop_loss(out, fg, coords, mask, cfg.w_coord)
    acc = ((out["fg_logit"] > 0).float() == fg).float().mean()
    return loss, {"loss": float(loss.detach()), "fg": float(parts["fg"]), "coord": float(parts["coord"]),
                  "fg_acc": float(acc), "crops": int(len(cls))}


def train_stage2(cfg: Stage2TrainConfig, train_path: str | Path, out_dir: str | Path, resume: bool = False,
               progress: bool = True, stop_after: int | None = None, log_every: int = 0,
               threads: ThreadPlan | None = None, bar_position: int = 0) -> dict:
    """Train the stage-2 crop network on a label file; checkpoints and metrics in ``out_dir``.

    stop_after: end after this step as if interrupted (``resume=True`` continues the same schedule);
    log_every: print a progress line every this many steps (0 = a tqdm bar when ``progress``);
    threads: the torch threads of each step (:class:`detector.training.threads.ThreadPlan`; None: torch's as they
    are); bar_position: the progress bar's line (1 below stage 1's when the stages train side by side).
    Returns {"steps", "seconds", "last" (mean of the last 20 steps' parts), "checkpoint"}.
    """
    out_dir = Path(out_dir)
    last_path = run_checkpoint(out_dir, resume)
    device = resolve_device(cfg.device)
    check_net_dtype(cfg.net_dtype, device)  # bfloat16: the CPU only
    ds = CropDataset(train_path, cfg.crop, augment=cfg.augment, seed=cfg.seed, class_ids=cfg.class_ids,
                     cache_mb=cfg.cache_mb)
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        torch.manual_seed(cfg.seed)
        net = CropNet(cfg.net, len(ds.class_ids)).to(device)
        opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, cfg.steps, cfg))
        start = 0
        if resume:
            payload = read_checkpoint(last_path, device)
            part = payload.get("stage2") or {}
            state = part.get("train_state") or {}
            if "optimizer" not in state:
                raise DetectorError(f"{last_path} holds no stage-2 training state to resume from")
            start = int(part["step"])
            restore_state(net, opt, sched, part["model_state"], {**state, "config": saved_settings(state["config"])},
                          cfg, last_path, device, start, cfg.steps, STAGE2_RESUME_FREE_KEYS)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "config.yaml").write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
        log = MetricsLog(out_dir / "metrics.csv", keep_until=start if resume else None, fields=STAGE2_METRICS)

        def save(step: int) -> None:
            state = {"optimizer": opt.state_dict(), "scheduler": sched.state_dict(), "rng": rng_state(device),
                     "config": config_to_dict(cfg)}
            atomic_torch_save({"format": FORMAT, "version": TWO_STAGE_VERSION,
                               "stage2": stage2_payload(net, cfg, ds.class_ids, ds.objects, step, state)}, last_path)

        sampler = StreamBatchSampler(len(ds), cfg.batch_frames, cfg.seed, start=start)
        loader = torch.utils.data.DataLoader(ds, batch_sampler=sampler, collate_fn=collate_crops,
                                             num_workers=cfg.num_workers, generator=loader_generator(cfg.seed),
                                             worker_init_fn=worker_init)
        batches = iter(loader)
        bar = tqdm(total=cfg.steps, initial=start, disable=not progress or log_every > 0, desc="train stage 2",
                   position=bar_position)
        end = cfg.steps if stop_after is None else min(cfg.steps, stop_after)
        recent: list[dict] = []
        step, t0 = start, time.perf_counter()
        t_last = t0
        net.train()
        empty = 0
        try:
            while step < end:
                if threads is not None:  # before the batch too (with no loader process it is made here)
                    threads.before_step(step)
                batch = next(batches)
                if len(batch["cls"]) == 0:  # frames without a usable instance: no step (resume sees the same)
                    empty += 1
                    if empty > 100:
                        raise DetectorError(f"{train_path}: 100 batches in a row hold no usable instance")
                    continue
                empty = 0
                lr = opt.param_groups[0]["lr"]
                loss, parts = forward_stage2_loss(net, batch, cfg, device)
                optimiser_step(loss, net, opt, sched, cfg.grad_clip)
                step += 1
                now = time.perf_counter()
                row = {"step": step, "epoch": f"{step * cfg.batch_frames / len(ds):.4f}", **parts, "lr": lr,
                       "steps_per_s": 1.0 / max(now - t_last, 1e-9), "threads": torch.get_num_threads()}
                t_last = now
                log.write(row)
                recent = (recent + [parts])[-20:]
                bar.update(1)
                if log_every and step % log_every == 0:
                    m = {k: np.mean([r[k] for r in recent]) for k in ("loss", "fg", "coord", "fg_acc")}
                    print(f"stage 2 step {step}/{cfg.steps} {now - t0:.0f}s loss {m['loss']:.4f} fg {m['fg']:.4f} "
                          f"coord {m['coord']:.4f} fg_acc {m['fg_acc']:.3f}", flush=True)
                if step % cfg.checkpoint_every == 0 or step == end:
                    save(step)
                if cfg.keep_every > 0 and step % cfg.keep_every == 0:
                    atomic_torch_save({"format": FORMAT, "version": TWO_STAGE_VERSION, "stage2": stage2_payload(
                        net, cfg, ds.class_ids, ds.objects, step)}, out_dir / f"step_{step:06d}.pt")
        finally:
            del batches
            bar.close()
            log.close()
            ds.close()
    last = {k: float(np.mean([r[k] for r in recent])) for k in ("loss", "fg", "coord", "fg_acc")} if recent else {}
    return {"steps": step, "seconds": time.perf_counter() - t0, "last": last, "checkpoint": last_path}


def saved_settings(saved: dict) -> dict:
    """A stage-2 run's saved settings (a config dict) as this code writes them: runs started before
    ``net.norm_before_max`` was removed store it as false, which is the one network there is now; runs started
    before ``crop.shape_turns`` existed get the value that reproduces them (false for a colour-free stage 2, which
    was taught its objects' own symmetries only; the default for any other, which the setting does not touch),
    runs started before ``crop.negatives`` existed none (0) and those started before ``crop.part_turns`` existed
    false (they were taught without part symmetries)."""
    out = dict(saved)
    net = dict(saved.get("net") or {})
    if net.get("norm_before_max") is False:
        del net["norm_before_max"]
        out["net"] = net
    crop = saved.get("crop")
    if isinstance(crop, dict) and "shape_turns" not in crop:
        out["crop"] = {**crop, "shape_turns": crop.get("colour") != "none"}
    return with_added_settings(out, STAGE2_ADDED_SETTINGS)


def load_stage2_config(data: dict | None, overrides: dict | None = None) -> Stage2TrainConfig:
    """A checked Stage2TrainConfig from a mapping (YAML) with flat dotted ``overrides`` ("crop.radius": 0.8)."""
    d = config_to_dict(Stage2TrainConfig())
    for k, v in (data or {}).items():
        set_dotted(d, k, v)
    for k, v in (overrides or {}).items():
        set_dotted(d, k, v)
    cfg = config_from_dict(Stage2TrainConfig, d)
    if cfg.steps < 1 or cfg.batch_frames < 1 or cfg.lr <= 0 or cfg.crop.num_points < 3 or cfg.crop.radius <= 0:
        raise DetectorError("stage-2 config: steps, batch_frames, lr, crop.num_points and crop.radius must be positive")
    if cfg.narrow_steps is not None and cfg.narrow_steps < 0:
        raise DetectorError(f"stage-2 config: narrow_steps must be 0 or more, got {cfg.narrow_steps}")
    if cfg.cache_mb < 0:
        raise DetectorError(f"stage-2 config: cache_mb must be 0 (no cache) or more, got {cfg.cache_mb}")
    lo, hi = cfg.crop.neighbour_offset
    if not (0.0 <= cfg.crop.neighbour <= 1.0 and 0.0 < lo <= hi):
        raise DetectorError("stage-2 config: crop.neighbour must lie in [0, 1] and crop.neighbour_offset be "
                            "[min, max] with 0 < min <= max")
    if not 0.0 <= cfg.crop.negatives <= 1.0:
        raise DetectorError(f"stage-2 config: crop.negatives must lie in [0, 1], got {cfg.crop.negatives}")
    if cfg.net_dtype not in ("float32", "bfloat16"):
        raise DetectorError(f"stage-2 config: net_dtype must be float32 or bfloat16, got '{cfg.net_dtype}'")
    if cfg.crop.colour not in COLOUR_MODES:
        raise DetectorError(f"stage-2 config: crop.colour must be {COLOUR_MODES_TEXT}, got '{cfg.crop.colour}'")
    return cfg
