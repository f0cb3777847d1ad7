"""``detector train``: the default two-stage model, or the paper's single network (``--preset cpu`` / ``paper``)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from detector.cli.common import TWO_STAGE, prepare_run_folder, user_errors
from detector.config import parse_set_options
from detector.errors import DetectorError


def register(app: typer.Typer) -> None:
    """Add the ``train`` command to ``app``."""
    app.command("train")(user_errors(train_cmd))


def train_cmd(
    train_file: Path = typer.Argument(..., help="label file (HDF5) from `argen label`"),
    out: Path = typer.Option(..., "--out", help="run folder: two_stage.yaml, model.pt (the file eval and predict "
                                                "take), stage1/ and stage2/ (each stage's config.yaml, metrics.csv, "
                                                "last.pt); --preset cpu or paper: config.yaml, metrics.csv, last.pt"),
    val: Optional[Path] = typer.Option(None, "--val", help="validation label file: val_loss in metrics.csv and the "
                                                           "best weights in best.pt (two-stage: of stage 1, "
                                                           "stage1/best.pt)"),
    preset: Optional[str] = typer.Option(None, "--preset",
                                         help="two-stage (default: finds objects, then their pose in crops), or the "
                                              "paper's single-shot network: cpu or paper"),
    config: Optional[Path] = typer.Option(None, "--config", help="YAML TrainConfig to start from instead of a preset"),
    steps: Optional[int] = typer.Option(None, "--steps",
                                        help="optimiser steps in all (cpu/paper; two-stage: --set stage1.steps=N)"),
    epochs: Optional[float] = typer.Option(None, "--epochs",
                                           help="passes over the training frames, instead of --steps (cpu/paper)"),
    batch_size: Optional[int] = typer.Option(None, "--batch-size", help="frames per optimiser step, the global batch "
                                                                        "under torchrun (cpu/paper)"),
    lr: Optional[float] = typer.Option(None, "--lr", help="peak learning rate, AdamW (cpu/paper)"),
    device: Optional[str] = typer.Option(None, "--device", help="auto, cpu or cuda (two-stage: both stages)"),
    seed: Optional[int] = typer.Option(None, "--seed", help="seed of the weights' initialisation and of the data "
                                                            "sampling and augmentation (two-stage: both stages)"),
    workers: Optional[int] = typer.Option(None, "--workers", help="data-loader processes (two-stage: both stages)"),
    seg_pretrain_steps: Optional[int] = typer.Option(None, "--seg-pretrain-steps",
                                                     help="first steps train segmentation only (cpu/paper)"),
    resume: bool = typer.Option(False, "--resume", help="continue the run in --out where it stopped"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace an existing run folder"),
    sets: list[str] = typer.Option([], "--set", help="any config key, e.g. --set stage2.steps=3000 "
                                                                  "(two-stage) or --set loss.w_conf=2 (cpu/paper)"),
    stage1_data: list[Path] = typer.Option([], "--stage1-data", help="two-stage: a label file of the same "
                                           "objects for stage 1 alone (default: the training file), e.g. a capture "
                                           "without distractors; give it twice or more to train stage 1 on the "
                                           "files' frames together"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
):
    """Train a detector on a label file; checkpoints and metrics go to --out.

    The default two-stage model writes --out/model.pt (both stages; the file eval and predict take) after
    training --out/stage1 and --out/stage2 (side by side on a CPU; --set stage2.narrow_steps=0: one after the
    other); set their lengths with --set stage1.steps=N --set stage2.steps=M. --resume continues it, also with --set of settings that do not change the result
    (e.g. --set stage2.cache_mb=256). --preset cpu or paper trains the paper's single network (--out/last.pt).
    """
    # lazy: torch loads in seconds; `detector --help` and the other commands do not need it
    from detector.stage1.train import load_config_file, make_config, train
    from detector.training import distributed

    if preset is not None:
        two_stage = preset == TWO_STAGE
    elif resume:
        two_stage = (out / "two_stage.yaml").is_file()
    else:
        two_stage = config is None  # a --config alone is a TrainConfig of the single network
    if two_stage:
        _train_two_stage(train_file, out, val, config, sets, resume, overwrite, quiet, stage1_data,
                         {"steps": steps, "epochs": epochs, "batch_size": batch_size, "lr": lr,
                          "seg_pretrain_steps": seg_pretrain_steps},
                         {"device": device, "seed": seed, "num_workers": workers})
        return
    if stage1_data:
        raise DetectorError("--stage1-data is for the two-stage model (the default), not --preset cpu or paper")
    if steps is not None and epochs is not None:
        raise DetectorError("give --steps or --epochs, not both")
    if resume and overwrite:
        raise DetectorError("--resume and --overwrite exclude each other")
    overrides = parse_set_options(sets)
    given = {"batch_size": batch_size, "lr": lr, "device": device, "seed": seed, "num_workers": workers,
             "seg_pretrain_steps": seg_pretrain_steps}
    overrides.update({k: v for k, v in given.items() if v is not None})
    if steps is not None:
        overrides.update(steps=steps, epochs=None)
    if epochs is not None:
        overrides.update(epochs=epochs, steps=None)
    base = None
    if resume:
        if preset is not None or config is not None:
            raise DetectorError("--resume continues the run's own config.yaml; drop --preset/--config")
        base = load_config_file(out / "config.yaml")
    elif config is not None:
        if preset is not None:
            raise DetectorError("give --preset or --config, not both")
        base = load_config_file(config)
    cfg = make_config(preset or "cpu", overrides, base)
    ctx = distributed.setup(cfg.device)  # under torchrun: join the process group; else a world of one
    try:
        if ctx.is_main:
            prepare_run_folder(out, resume, overwrite)
        ctx.barrier()
        summary = train(cfg, train_file, out, val_path=val, resume=resume, progress=not quiet)
    finally:
        distributed.teardown(ctx)
    if ctx.is_main:
        typer.echo(f"{out}: {summary.line()}" + (f" ({ctx.world_size} processes)" if ctx.enabled else ""))


def _train_two_stage(train_file: Path, out: Path, val: Optional[Path], config: Optional[Path], sets: list[str],
                     resume: bool, overwrite: bool, quiet: bool, stage1_data: list[Path], network_flags: dict,
                     shared_flags: dict) -> None:
    """``detector train`` for the two-stage model (see :mod:`detector.two_stage`). network_flags: options of one
    network (refused: the stages differ); shared_flags: options that both stages take (set on both)."""
    from detector.two_stage import load_two_stage_config, train_two_stage  # lazy: torch (see train_cmd)

    given = [f"--{k.replace('_', '-')}" for k, v in network_flags.items() if v is not None]
    if given:
        raise DetectorError(f"{given[0]} applies to one network; for the two-stage model use --set stage1.KEY=V or "
                            "--set stage2.KEY=V (e.g. --set stage2.steps=3000)")
    if resume and overwrite:
        raise DetectorError("--resume and --overwrite exclude each other")
    overrides = parse_set_options(sets)
    overrides.update({f"{stage}.{k}": v for k, v in shared_flags.items() if v is not None
                      for stage in ("stage1", "stage2")})
    if resume:
        if config is not None:
            raise DetectorError("--resume continues the run's own two_stage.yaml; drop --config")
        config = out / "two_stage.yaml"
    cfg = load_two_stage_config(config, overrides)
    prepare_run_folder(out, resume, overwrite)
    path = train_two_stage(cfg, train_file, out, resume=resume, progress=not quiet, val_path=val,
                           stage1_path=stage1_data or None)
    typer.echo(f"{out}: two-stage model -> {path}")
