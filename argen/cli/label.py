"""The ``argen label``, ``argen validate`` and ``argen preview`` commands (registered by argen.cli.app)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from argen.cli.common import parse_shard, user_errors
from argen.errors import ArgenError


def register(app: typer.Typer) -> None:
    """Add the label, validate and preview commands to ``app``."""

    @app.command("label")
    @user_errors
    def label_cmd(
        dataset: Path = typer.Argument(..., help="BOP dataset folder (argen capture-sim output, a BOP test set, ...)"),
        out: Path = typer.Option(..., "--out", help="label file to write (.h5)"),
        split: str = typer.Option("train_pbr", "--split", help="split folder inside the dataset"),
        models: Optional[Path] = typer.Option(None, "--models", help="BOP models folder (default: DATASET/models)"),
        max_points: int = typer.Option(30000, "--max-points", help="points kept per frame (random subsampling)"),
        max_depth: Optional[float] = typer.Option(None, "--max-depth", help="working volume: drop points farther "
                                                  "than this (metres; default: template camera distance + 0.6, else 2)"),
        voxel: float = typer.Option(0.0, "--voxel", help="voxel edge (metres) for one-point-per-voxel before the "
                                    "random subsampling (0 = off)"),
        seed: int = typer.Option(0, "--seed", help="subsampling seed"),
        render_masks: bool = typer.Option(False, "--render-masks", help="compute visible masks by rendering the "
                                          "GT poses even when the dataset has mask_visib"),
        workers: int = typer.Option(1, "--workers", help="processes"),
        chunk: int = typer.Option(16, "--chunk", help="frames per resumable part (a killed run redoes at most "
                                  "one part per worker)"),
        compression: str = typer.Option("lzf", "--compression", help="lzf (fast, h5py built-in), gzip (~20%% "
                                        "smaller, any HDF5 tool, slower) or none"),
        overwrite: bool = typer.Option(False, "--overwrite", help="replace an existing output or interrupted run"),
        quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
        shard: Optional[str] = typer.Option(None, "--shard", help="I/N: label only chunks k with k % N == I "
                                            "(one of N machines); join the files with `argen merge`"),
    ):
        """Turn BOP scenes into per-point labels (features, semantic, instance, 9 control points) in HDF5."""
        # lazy: pyrender, open3d and trimesh take seconds to load; --help and the other commands need none
        from argen.label import LabelConfig, LabelRequest, run_label

        cfg = LabelConfig(max_points=max_points, max_depth=max_depth, voxel=voxel, seed=seed,
                          render_masks=render_masks)
        req = LabelRequest(dataset=dataset, split=split, out=out, cfg=cfg, models=models, workers=workers,
                           overwrite=overwrite, progress=not quiet, chunk=chunk,
                           compression=None if compression == "none" else compression,
                           shard=parse_shard(shard))
        summary = run_label(req)
        typer.echo(f"{out}: {summary.line()}")

    @app.command("validate")
    @user_errors
    def validate_cmd(
        file: Path = typer.Argument(..., help="label file (.h5) written by argen label"),
        max_errors: int = typer.Option(10, "--max-errors", help="stop after this many violations"),
    ):
        """Check a label file's schema and label invariants; exit 1 and list the first violations."""
        # lazy: pyrender, open3d and trimesh take seconds to load; --help and the other commands need none
        from argen.validate import validate_file

        n, errs = validate_file(file, max_errors=max(1, max_errors))
        if errs:
            for e in errs:
                typer.echo(f"argen: invalid: {file}: {e}", err=True)
            raise typer.Exit(1)
        typer.echo(f"{file}: valid ({n} frames)")

    @app.command("preview")
    @user_errors
    def preview_cmd(
        source: Path = typer.Argument(..., help="label file (.h5) or BOP dataset folder"),
        out: Path = typer.Option(..., "--out", help="PNG to write"),
        frame: int = typer.Option(0, "--frame", help="frame index (file order, or split order for a dataset)"),
        split: str = typer.Option("train_pbr", "--split", help="split, when SOURCE is a BOP dataset"),
        models: Optional[Path] = typer.Option(None, "--models", help="models folder, when SOURCE is a BOP dataset"),
    ):
        """Draw a frame's points coloured by instance and the 3D boxes from the control points."""
        # lazy: pyrender, open3d and trimesh take seconds to load; --help and the other commands need none
        from argen.preview import preview_bop, preview_file

        if out.suffix.lower() != ".png":
            raise ArgenError(f"--out must name a .png file, got {out}")
        if source.is_dir():
            fr = preview_bop(source, split, frame, out, models=models)
        elif source.exists():
            fr = preview_file(source, frame, out)
        else:
            raise ArgenError(f"not found: {source}")
        typer.echo(f"{out}: scene {fr.scene_id} image {fr.im_id}, {len(fr)} points, {len(fr.instances)} instances")
