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
    out: Path = typer.Option(..., "--out", help="run folder: config.yaml, metrics.csv, last.pt, best.pt"),
    val: Optional[Path] = typer.Option(None, "--val", help="validation label file (enables best.pt)"),
    preset: Optional[str] = typer.Option(None, "--preset",
                                         help="two-stage (default: finds objects, then their pose in crops), or the "
                                              "paper's single-shot network: cpu or paper"),
    config: Optional[Path] = typer.Option(None, "--config", help="YAML TrainConfig to start from instead of a preset"),
    steps: Optional[int] = typer.Option(None, "--steps", help="optimiser steps in all"),
    epochs: Optional[float] = typer.Option(None, "--epochs", help="passes over the training frames (instead of --steps)"),
    batch_size: Optional[int] = typer.Option(None, "--batch-size"),
    lr: Optional[float] = typer.Option(None, "--lr", help="peak learning rate (AdamW)"),
    device: Optional[str] = typer.Option(None, "--device", help="auto, cpu or cuda"),
    seed: Optional[int] = typer.Option(None, "--seed"),
    workers: Optional[int] = typer.Option(None, "--workers", help="data-loader processes"),
    seg_pretrain_steps: Optional[int] = typer.Option(None, "--seg-pretrain-steps",
                                                     help="first steps train segmentation only"),
    resume: bool = typer.Option(False, "--resume", help="continue the run in --out from its last.pt"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace an existing run folder"),
    sets: list[str] = typer.Option([], "--set", help="any config key, e.g. --set loss.w_conf=2 --set model.fp_mlps=..."),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
):
    """Train a detector on a label file; checkpoints and metrics go to --out.

    The default two-stage model writes --out/model.pt (both stages; the file eval and predict take) after
    training --out/detect (stage 1) and --out/pose (stage 2); set their lengths with --set stage1.steps=N
    --set stage2.steps=M. --preset cpu or paper trains the paper's single network (--out/last.pt).
    """
    # lazy: torch loads in seconds; `detector --help` and the other commands do not need it
    from detector import distributed
    from detector.train import load_config_file, make_config, train

    if preset is not None:
        two_stage = preset == TWO_STAGE
    elif resume:
        two_stage = (out / "two_stage.yaml").is_file()
    else:
        two_stage = config is None  # a --config alone is a TrainConfig of the single network
    if two_stage:
        _train_two_stage(train_file, out, config, sets, resume, overwrite, quiet,
                         {"steps": steps, "epochs": epochs, "batch_size": batch_size, "lr": lr, "device": device,
                          "seed": seed, "num_workers": workers, "seg_pretrain_steps": seg_pretrain_steps})
        return
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


def _train_two_stage(train_file: Path, out: Path, config: Optional[Path], sets: list[str], resume: bool,
                     overwrite: bool, quiet: bool, flags: dict) -> None:
    """``detector train`` for the two-stage model (see :mod:`detector.two_stage`)."""
    from detector.two_stage import load_two_stage_config, train_two_stage  # lazy: torch (see train_cmd)

    given = [f"--{k.replace('_', '-')}" for k, v in flags.items() if v is not None]
    if given:
        raise DetectorError(f"{given[0]} applies to one network; for the two-stage model use --set stage1.KEY=V or "
                            "--set stage2.KEY=V (e.g. --set stage2.steps=3000)")
    if resume and overwrite:
        raise DetectorError("--resume and --overwrite exclude each other")
    if resume:
        if config is not None or sets:
            raise DetectorError("--resume continues the run's own two_stage.yaml; drop --config/--set")
        config = out / "two_stage.yaml"
    cfg = load_two_stage_config(config, parse_set_options(sets))
    prepare_run_folder(out, resume, overwrite)
    path = train_two_stage(cfg, train_file, out, resume=resume, progress=not quiet)
    typer.echo(f"{out}: two-stage model -> {path}")


