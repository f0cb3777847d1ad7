"""Training stage 1 (or the paper's single network): AdamW with a warm-up schedule (:mod:`detector.training`), optional
segmentation-only pre-training, validation, atomic checkpoints (``last.pt`` every N steps, ``best.pt`` on validation
loss), ``metrics.csv``, exact resume.

A run folder holds ``config.yaml`` (the resolved :class:`TrainConfig`), ``metrics.csv`` (one row per step),
``last.pt`` and, with a validation file, ``best.pt``. Resuming reloads model, optimiser, scheduler, torch
RNG and the data position; items are pure functions of (seed, epoch, frame), so the resumed run repeats
the uninterrupted one step for step. Resuming with more ``steps`` is allowed (the schedule is a function
of (step, total), so it stretches from there); other settings must stay those of the run.

Under ``torchrun`` (:mod:`detector.training.distributed`) the same function trains data-parallel with DDP:
``batch_size`` is the global batch, split over the processes, and the loss is normalised over the global
batch, so N processes follow the single-process run up to floating-point order; rank 0 alone writes the
run folder and validates. With ``model.norm=bn`` each process normalises over its own share of the batch.

Presets (``detector/presets/{cpu,paper}.yaml``, their ``train`` sections): ``cpu`` = the TrainConfig defaults (cpu model, 4096 points, 2000 steps,
lr 2e-3, cosine, 50 warm-up steps); ``paper`` = the paper's model, 16384 points, batch 4, 20000 steps,
lr 1e-3, 500 warm-up steps, the first 2000 steps segmentation-only (the paper pre-trains segmentation;
it gives no step counts or learning rate, these are ours).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from tqdm import tqdm

from detector.config import NETWORK_PRESETS, config_from_dict, config_to_dict, load_preset, load_yaml, set_dotted
from detector.data.augment import COLOUR_MODES, COLOUR_MODES_TEXT
from detector.data.batches import StreamBatchSampler, collate
from detector.errors import DetectorError
from detector.stage1.dataset import PointDataset
from detector.stage1.loss import LossConfig, multitask_loss
from detector.stage1.network import ModelConfig, PointNet2, preset
from detector.training import distributed
from detector.training.checkpoint_file import read_checkpoint, save_checkpoint
from detector.training.devices import loader_generator, resolve_device, worker_init
from detector.training.distributed import DistContext
from detector.training.metrics_log import MetricsLog
from detector.training.optim import optimiser_step
from detector.training.resume import restore_state, rng_state, run_checkpoint, with_added_settings
from detector.training.schedule import lr_factor


#: Keys of a batch that are labels or bookkeeping; every other key is a sampling index for the network.
LABEL_KEYS = ("features", "cls", "instance", "control_points", "frame", "point_index")

#: Config keys that may differ when resuming: they do not change the numbers of the steps (``steps`` / ``epochs``
#: lengthen or shorten the schedule from the step reached; ``indices`` says where the same sampling indices are
#: computed).
RESUME_FREE_KEYS = frozenset({"steps", "epochs", "checkpoint_every", "val_every", "val_frames", "num_workers", "device",
                              "indices"})

#: Settings added to TrainConfig after runs were first saved, with the value that reproduces a run saved without
#: them (:func:`saved_run_settings`): such a run resumes as it was trained.
ADDED_SETTINGS = {"plane_keep": 1.0, "loss.fg_weight": 1.0}

METRIC_FIELDS = ["step", "epoch", "phase", "loss", "cls", "offset", "conf", "lr", "acc", "steps_per_s",
                 "val_loss", "val_acc"]


@dataclass
class TrainConfig:
    """Everything that defines a training run (the model is ``preset`` with ``model`` overrides)."""

    preset: str = "cpu"  # model preset of detector.stage1.network.preset: "paper" or "cpu"
    model: dict = field(default_factory=dict)  # ModelConfig field overrides
    num_points: int = 4096  # points sampled per frame (>= the first stage's keypoints)
    plane_keep: float = 1.0  # share of the frame's dominant plane that sampling keeps (detector.data.plane); 1 = all
    steps: int | None = 2000  # optimiser steps in all (segmentation pre-training included)
    epochs: float | None = None  # instead of steps: passes over the training frames
    batch_size: int = 4
    lr: float = 2e-3
    weight_decay: float = 1e-4
    schedule: str = "cosine"  # cosine (linear warm-up, cosine decay) | onecycle | constant
    warmup_steps: int = 50
    min_lr_ratio: float = 0.01  # cosine: final lr = lr * min_lr_ratio
    grad_clip: float = 10.0  # max gradient norm, 0 = off
    seg_pretrain_steps: int = 0  # first steps train the segmentation head only (the paper's pre-training)
    loss: LossConfig = field(default_factory=LossConfig)
    augment: bool = True
    colour: str = "light"  # colour augmentation: detector.data.augment.COLOUR_MODES
    class_ids: list[int] | None = None  # object ids to learn; None = all objects of the training file
    checkpoint_every: int = 200
    val_every: int = 200
    val_frames: int = 0  # validation frames per evaluation, 0 = all
    num_workers: int = 2
    device: str = "auto"  # auto | cpu | cuda
    indices: str = "auto"  # where sampling indices are computed: auto | loader | model
    seed: int = 0


@dataclass
class TrainSummary:
    """What a run did: steps, time, the last training losses and the validation result."""

    out_dir: Path
    start_step: int
    steps: int
    seconds: float
    last: dict  # mean of the last (up to 10) steps: loss, cls, offset, conf, acc
    val: dict | None  # last validation: loss, cls, offset, conf, acc
    best_val_loss: float | None
    checkpoint: Path

    def line(self) -> str:
        """One line for the terminal."""
        rate = (self.steps - self.start_step) / self.seconds if self.seconds > 0 else float("nan")
        txt = (f"{self.steps} steps ({rate:.2f} steps/s), loss {self.last.get('loss', float('nan')):.4f}, "
               f"point accuracy {self.last.get('acc', float('nan')):.3f}")
        if self.val:
            txt += f", val loss {self.val['loss']:.4f}, val accuracy {self.val['acc']:.3f}"
        return txt + f"; checkpoint {self.checkpoint}"


def make_config(preset: str = "cpu", overrides: dict[str, Any] | None = None, base: TrainConfig | None = None
                ) -> TrainConfig:
    """A validated TrainConfig: ``base`` (or the training preset) with dotted ``overrides`` applied."""
    if base is None:
        if preset not in NETWORK_PRESETS:
            raise DetectorError(f"unknown preset '{preset}' (available: {', '.join(NETWORK_PRESETS)})")
        data = config_to_dict(TrainConfig())
        data.update(load_preset(preset)["train"] or {})
    else:
        data = config_to_dict(base)
    for key, value in (overrides or {}).items():
        set_dotted(data, key, value)
    cfg = config_from_dict(TrainConfig, data)
    validate_config(cfg)
    return cfg


def load_config_file(path: str | Path) -> TrainConfig:
    """A TrainConfig from a YAML file (e.g. a run folder's ``config.yaml``)."""
    path = Path(path)
    cfg = config_from_dict(TrainConfig, load_yaml(path), where=path.name)
    validate_config(cfg)
    return cfg


def validate_config(cfg: TrainConfig) -> None:
    """Range checks; a bad value is a one-line DetectorError naming the key."""
    checks = [
        (cfg.steps is None or cfg.steps >= 1, "steps must be at least 1"),
        (cfg.epochs is None or cfg.epochs > 0, "epochs must be positive"),
        ((cfg.steps is None) != (cfg.epochs is None), "give either steps or epochs"),
        (cfg.batch_size >= 1, "batch_size must be at least 1"),
        (cfg.num_points >= 1, "num_points must be at least 1"),
        (0.0 <= cfg.plane_keep <= 1.0, "plane_keep must be in [0, 1]"),
        (cfg.lr > 0 and cfg.weight_decay >= 0, "lr must be positive and weight_decay non-negative"),
        (cfg.schedule in ("cosine", "onecycle", "constant"), "schedule must be cosine, onecycle or constant"),
        (cfg.warmup_steps >= 0 and 0 <= cfg.min_lr_ratio <= 1, "warmup_steps >= 0 and min_lr_ratio in [0, 1]"),
        (cfg.grad_clip >= 0 and cfg.seg_pretrain_steps >= 0, "grad_clip and seg_pretrain_steps must be >= 0"),
        (cfg.checkpoint_every >= 1 and cfg.val_every >= 1, "checkpoint_every and val_every must be at least 1"),
        (cfg.num_workers >= 0 and cfg.val_frames >= 0, "num_workers and val_frames must be >= 0"),
        (cfg.device in ("auto", "cpu", "cuda"), "device must be auto, cpu or cuda"),
        (cfg.indices in ("auto", "loader", "model"), "indices must be auto, loader or model"),
        (cfg.colour in COLOUR_MODES, f"colour must be {COLOUR_MODES_TEXT}"),
    ]
    for ok, msg in checks:
        if not ok:
            raise DetectorError(f"config: {msg}")


def build_model_config(cfg: TrainConfig):
    """The ModelConfig of a run: the model preset with the config's ``model`` overrides."""

    try:
        base = preset(cfg.preset).to_dict()
    except (KeyError, ValueError) as exc:
        raise DetectorError(f"unknown model preset '{cfg.preset}' ({exc})") from None
    unknown = [k for k in cfg.model if k not in base]
    if unknown:
        raise DetectorError(f"config: unknown model option '{unknown[0]}' (known: {', '.join(base)})")
    try:
        return ModelConfig.from_dict({**base, **cfg.model})
    except (TypeError, ValueError) as exc:
        raise DetectorError(f"config: bad model options ({exc})") from None


def total_steps(cfg: TrainConfig, num_frames: int) -> int:
    """Optimiser steps of the run: ``steps``, or ``ceil(epochs * frames / batch_size)``."""
    if cfg.steps is not None:
        return cfg.steps
    return max(1, math.ceil(cfg.epochs * num_frames / cfg.batch_size))


def split_batch(batch: dict[str, torch.Tensor], device: torch.device, use_indices: bool
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor] | None]:
    """Network input of a batch: features (B, N, 9) and the sampling indices (or None) on ``device``."""
    feats = batch["features"].to(device, non_blocking=True)
    if not use_indices:
        return feats, None
    return feats, {k: v.to(device, non_blocking=True) for k, v in batch.items() if k not in LABEL_KEYS}


def keypoint_targets(batch: dict[str, torch.Tensor], keypoints: torch.Tensor) -> dict[str, torch.Tensor]:
    """Labels of the network's K keypoints: ``cls`` (B, K) int64 and ``control_points`` (B, K, 9, 3) metres.

    keypoints: (B, K) int64 indices into the batch's N points (the model's ``out["keypoints"]``).
    """
    kp = keypoints.to(batch["cls"].device)
    cls = torch.gather(batch["cls"], 1, kp)
    cps = torch.gather(batch["control_points"], 1, kp[:, :, None, None].expand(-1, -1, 9, 3))
    return {"cls": cls.to(keypoints.device), "control_points": cps.to(keypoints.device)}


def forward_loss(model: torch.nn.Module, batch: dict[str, torch.Tensor], loss_cfg: LossConfig, device: torch.device,
                 use_indices: bool, ctx: DistContext | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Forward a batch and return the loss and its parts, plus ``acc``: keypoint segmentation accuracy.

    With a distributed ``ctx`` the batch is this process's share: the offset and confidence terms are
    normalised by the object keypoints of the whole global batch (so DDP's gradient mean equals the
    single-process gradient), the reported parts are means over the processes, and during segmentation
    pre-training the unused heads get zero gradients (DDP needs a gradient for every parameter).
    """
    feats, idx = split_batch(batch, device, use_indices)
    out = model(feats, idx)
    target = keypoint_targets(batch, out["keypoints"])
    pos_count = None
    if ctx is not None and ctx.enabled:
        pos_count = ctx.sum_((target["cls"] > 0).sum().to(torch.float64)).clamp(min=1.0) / ctx.world_size
    loss, parts = multitask_loss(out, target, loss_cfg, pos_count=pos_count)
    if ctx is not None and ctx.enabled and loss_cfg.seg_only:
        loss = loss + 0.0 * (out["offsets"].sum() + out["confidence"].sum())
    parts = {k: float(v) for k, v in parts.items()}
    parts["acc"] = float((out["logits"].argmax(-1) == target["cls"]).float().mean())
    if ctx is not None:
        parts = ctx.mean_of(parts)
    return loss, parts


@torch.no_grad()
def validation_metrics(model: torch.nn.Module, dataset: PointDataset, cfg: TrainConfig, device: torch.device,
             use_indices: bool) -> dict[str, float]:
    """Mean loss parts and keypoint accuracy over (the first ``val_frames`` of) ``dataset``, epoch 0, no grad."""
    n = len(dataset) if cfg.val_frames == 0 else min(cfg.val_frames, len(dataset))
    batches = [[(0, i) for i in range(s, min(s + cfg.batch_size, n))] for s in range(0, n, cfg.batch_size)]
    loader = torch.utils.data.DataLoader(dataset, batch_sampler=batches, collate_fn=collate,
                                         num_workers=min(cfg.num_workers, len(batches)),
                                         generator=loader_generator(cfg.seed))
    was_training = model.training
    model.eval()
    sums: dict[str, float] = {}
    for keys, batch in zip(batches, loader):
        _, parts = forward_loss(model, batch, cfg.loss, device, use_indices)
        for k, v in parts.items():
            sums[k] = sums.get(k, 0.0) + v * len(keys)
    model.train(was_training)
    out = {k: v / n for k, v in sums.items()}
    out["loss"] = out.pop("total")
    return out


def train(cfg: TrainConfig, train_path: str | Path | Sequence[str | Path], out_dir: str | Path,
          val_path: str | Path | None = None,
          resume: bool = False, progress: bool = True, stop_after: int | None = None,
          before_step: Callable[[int], None] | None = None) -> TrainSummary:
    """Train a PointNet2 on a label file (or on several of the same objects together: ``train_path`` a list); write
    checkpoints and metrics to ``out_dir``; return a summary.

    ``stop_after``: end after this step as if interrupted there (``last.pt`` is written; ``resume=True``
    continues the same schedule), e.g. to train in time-boxed pieces. ``before_step``: called with each step's
    0-based number before it (a two-stage run checks there that stage 2, training beside it, has not failed).
    Under torchrun this joins the process group (:func:`detector.training.distributed.setup`) and trains with DDP.
    """
    ctx = distributed.setup(cfg.device)
    try:
        return _train(cfg, train_path, out_dir, val_path, resume, progress, stop_after, ctx, before_step)
    finally:
        distributed.teardown(ctx)


def _train(cfg: TrainConfig, train_path: str | Path | Sequence[str | Path], out_dir: str | Path,
           val_path: str | Path | None, resume: bool,
           progress: bool, stop_after: int | None, ctx: DistContext,
           before_step: Callable[[int], None] | None = None) -> TrainSummary:

    validate_config(cfg)
    out_dir = Path(out_dir)
    last_path = run_checkpoint(out_dir, resume)
    ctx.barrier()  # no process may see last.pt written by rank 0 before passing the checks above
    device = resolve_device(cfg.device)
    if device.type == "cuda" and ctx.enabled:
        device = torch.device("cuda", ctx.local_rank)
    use_indices = cfg.indices == "loader" or (cfg.indices == "auto" and device.type == "cpu")
    model_cfg = build_model_config(cfg)
    ds = PointDataset(train_path, model_cfg, cfg.num_points, augment=cfg.augment, seed=cfg.seed, colour=cfg.colour,
                      class_ids=cfg.class_ids, precompute=use_indices, plane_keep=cfg.plane_keep)
    ds_paths = " ".join(map(str, ds.paths))  # the label file(s), as the checkpoint records them
    val_ds = None
    if val_path is not None and ctx.is_main:
        val_ds = PointDataset(val_path, model_cfg, cfg.num_points, augment=False, seed=cfg.seed,
                              class_ids=ds.class_ids, precompute=use_indices, colour=cfg.colour,
                              plane_keep=cfg.plane_keep)
    total = total_steps(cfg, len(ds))
    devices = [device] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(cfg.seed)
        net = PointNet2(model_cfg, num_classes=len(ds.class_ids)).to(device)
        opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, total, cfg))
        start, best, val = 0, None, None
        if resume:
            payload = read_checkpoint(last_path, device)
            state = payload.get("train_state") or {}
            if "optimizer" not in state:
                raise DetectorError(f"{last_path} holds no training state to resume from")
            start, best, val = int(payload["step"]), state.get("best_val_loss"), state.get("val")
            state = {**state, "config": saved_run_settings(state["config"])}
            restore_state(net, opt, sched, payload["model_state"], state, cfg, last_path, device, start, total,
                          RESUME_FREE_KEYS)
        model = net
        if ctx.enabled:
            model = torch.nn.parallel.DistributedDataParallel(
                net, device_ids=[device.index] if device.type == "cuda" else None)
        log = None
        if ctx.is_main:
            out_dir.mkdir(parents=True, exist_ok=True)
            (out_dir / "config.yaml").write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
            log = MetricsLog(out_dir / "metrics.csv", keep_until=start if resume else None, fields=METRIC_FIELDS)

        def save(path: Path, step: int) -> None:
            extra = {"train_config": config_to_dict(cfg), "train_file": ds_paths, "val": val,
                     "max_depth": ds.max_depth}  # the working volume of its points: predict keeps to it
            train_state = {"optimizer": opt.state_dict(), "scheduler": sched.state_dict(), "rng": rng_state(device),
                           "data_position": step * cfg.batch_size, "config": config_to_dict(cfg),
                           "best_val_loss": best, "val": val, "total_steps": total}
            save_checkpoint(path, model=net, model_config=model_cfg, class_ids=ds.class_ids, objects=ds.objects,
                            num_points=cfg.num_points, step=step, normalisation=ds.normalisation, extra=extra,
                            train_state=train_state if path == last_path else None)

        sampler = StreamBatchSampler(len(ds), cfg.batch_size, cfg.seed, start=start, rank=ctx.rank,
                                     world_size=ctx.world_size)
        loader = torch.utils.data.DataLoader(ds, batch_sampler=sampler, collate_fn=collate,
                                             num_workers=cfg.num_workers, worker_init_fn=worker_init,
                                             pin_memory=device.type == "cuda",
                                             generator=loader_generator(cfg.seed))
        seg_cfg = dataclasses.replace(cfg.loss, seg_only=True)
        seg_unused = [*net.offset_head.parameters(), *net.conf_head.parameters()]
        recent: list[dict] = []
        bar = tqdm(total=total, initial=start, disable=not progress or not ctx.is_main, dynamic_ncols=True,
                   desc="train")
        t0 = t_last = time.perf_counter()
        step = start
        batches = iter(loader)
        model.train()
        end = total if stop_after is None else min(total, stop_after)
        try:
            while step < end:
                if before_step is not None:
                    before_step(step)
                batch = next(batches)
                phase = "seg" if step < cfg.seg_pretrain_steps else "full"
                lr = opt.param_groups[0]["lr"]
                loss, parts = forward_loss(model, batch, seg_cfg if phase == "seg" else cfg.loss, device,
                                           use_indices, ctx)
                # as in one process: under DDP the unused heads of segmentation pre-training take no AdamW step
                frozen = seg_unused if ctx.enabled and phase == "seg" else ()
                optimiser_step(loss, net, opt, sched, cfg.grad_clip, frozen)
                step += 1
                now = time.perf_counter()
                row = {"step": step, "epoch": step * cfg.batch_size / len(ds), "phase": phase,
                       "loss": parts["total"], "cls": parts["cls"], "offset": parts["offset"], "conf": parts["conf"],
                       "lr": lr, "acc": parts["acc"], "steps_per_s": 1.0 / max(now - t_last, 1e-9)}
                t_last = now
                recent = (recent + [row])[-10:]
                if val_ds is not None and (step % cfg.val_every == 0 or step == total):
                    val = validation_metrics(net, val_ds, cfg, device, use_indices)
                    row.update(val_loss=val["loss"], val_acc=val["acc"])
                    if best is None or val["loss"] < best:
                        best = val["loss"]
                        save(out_dir / "best.pt", step)
                if log is not None:
                    log.write(row)
                bar.set_postfix_str(f"loss {row['loss']:.3f} cls {row['cls']:.3f} off {row['offset']:.4f} "
                                    f"conf {row['conf']:.3f} acc {row['acc']:.3f} lr {lr:.2e}", refresh=False)
                bar.update(1)
                if ctx.is_main and (step % cfg.checkpoint_every == 0 or step == end):
                    save(last_path, step)
        finally:
            del batches  # stops the loader workers now
            bar.close()
            if log is not None:
                log.close()
            ds.close()
            if val_ds is not None:
                val_ds.close()
    last = {k: float(np.mean([r[k] for r in recent])) for k in ("loss", "cls", "offset", "conf", "acc")} if recent else {}
    return TrainSummary(out_dir=out_dir, start_step=start, steps=step, seconds=time.perf_counter() - t0, last=last,
                        val=val, best_val_loss=best, checkpoint=last_path)


def saved_run_settings(saved: dict) -> dict:
    """A run's saved settings (a config dict) as this code writes them: a setting added since the run was saved
    (:data:`ADDED_SETTINGS`) takes the value the run was trained with."""
    return with_added_settings(saved, ADDED_SETTINGS)
