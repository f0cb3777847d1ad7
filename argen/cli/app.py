"""The ``argen`` command line: parse, call, print. User errors become one line on stderr, exit 2."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from argen.cli.common import (capture_objects, load_config, models_option, objects_option, out_option, overwrite_option,
                              parse_shard, quiet_option, sets_option, user_errors, workers_option)
from argen.cli.label import register as register_label
from argen.cli.models import register as register_models
from argen.cli.real import register as register_real
from argen.errors import ArgenError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="argen: simulated AR capture and per-point labels for 6-DoF pose estimation.")


@app.command("capture-sim")
@user_errors
def capture_sim(
    out: Path = out_option(),
    scene: str = typer.Option("linemod", "--scene", help="template name (linemod, lchf) or a YAML file"),
    frames: int = typer.Option(20, "--frames", help="frames to capture (accepted + rejected)"),
    models: Optional[Path] = models_option(),
    objects: Optional[str] = objects_option(),
    seed: Optional[int] = typer.Option(None, "--seed", help="random seed (default: the template's)"),
    noise: Optional[str] = typer.Option(None, "--noise", help="'on' (the sensor's noise model) or 'none' "
                                        "(default: the template's)"),
    sensor: Optional[str] = typer.Option(None, "--sensor", help="sensor profile: kinect_v1 (default), kinect_v2 "
                                         "(time of flight), realsense_d435 (active stereo)"),
    camera: Optional[Path] = typer.Option(None, "--camera", help="a BOP camera.json (fx, fy, cx, cy, width, height): "
                                          "your sensor's intrinsics and image size, over the sensor profile's"),
    workers: int = workers_option(),
    overwrite: bool = overwrite_option(),
    sets: list[str] = sets_option(),
    quiet: bool = quiet_option(),
    shard: Optional[str] = typer.Option(None, "--shard", help="I/N: make only frames with index % N == I "
                                        "(one of N machines); join the shards with `argen merge`"),
):
    """Simulate an AR capture (boards, placed objects, rendering, sensor noise) and write BOP scenes."""
    # lazy: pyrender, open3d and trimesh take seconds to load; --help and the other commands need none
    from argen.sim.capture import CaptureRequest, run_capture

    if frames < 1:
        raise ArgenError(f"--frames must be at least 1, got {frames}")
    cfg = load_config(scene, seed, noise, sets, objects, sensor, camera)
    objs, source = capture_objects(cfg, models, workers)
    req = CaptureRequest(cfg=cfg, objects=objs, out=out, frames=frames, workers=workers, models_source=source,
                         overwrite=overwrite, progress=not quiet, shard=parse_shard(shard))
    summary = run_capture(req)
    typer.echo(f"{out}: {summary.line()}")


@app.command("merge")
@user_errors
def merge_cmd(
    shards: list[Path] = typer.Argument(..., help="the shards: capture-sim --shard folders, or label --shard .h5 files"),
    out: Path = typer.Option(..., "--out", help="merged dataset folder (or .h5 file)"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace a non-empty output"),
):
    """Join the shards of a capture or labelling run made on several machines (equal to a single run)."""
    if all(p.suffix.lower() in (".h5", ".hdf5") for p in shards):
        # lazy: pyrender, open3d and trimesh take seconds to load; --help and the other commands need none
        from argen.label import merge_label_files

        n = merge_label_files(shards, out, overwrite=overwrite)
    elif any(p.suffix.lower() in (".h5", ".hdf5") for p in shards):
        raise ArgenError("give either capture folders or label files to merge, not both")
    else:
        # lazy: pyrender, open3d and trimesh take seconds to load; --help and the other commands need none
        from argen.merge import merge_captures

        n = merge_captures(shards, out, overwrite=overwrite)
    typer.echo(f"{out}: merged {len(shards)} shards, {n} frames")


@app.command("board")
@user_errors
def board_cmd(
    out: Path = typer.Option(..., "--out", help="PNG file to write"),
    scene: str = typer.Option("linemod", "--scene", help="template whose board to print"),
    dpi: Optional[int] = typer.Option(None, "--dpi", help="print resolution (default: the template's)"),
):
    """Write the template's marker board as a PNG at true print scale."""
    # lazy: pyrender, open3d and trimesh take seconds to load; --help and the other commands need none
    from argen.config import load_template
    from argen.sim.board import Board

    cfg = load_template(scene)
    if dpi is not None and dpi <= 0:
        raise ArgenError(f"--dpi must be positive, got {dpi}")
    board = Board.from_config(cfg.board)
    board.save_print(out, dpi=dpi)
    d = dpi or cfg.board.print_dpi
    typer.echo(f"{out}: board {board.side * 1000:.0f} mm square, markers {cfg.board.marker_size * 1000:.0f} mm, "
               f"{d} dpi: print at 100% scale")


def main() -> None:
    app(prog_name="argen")


for _register in (register_label, register_real, register_models):
    _register(app)


if __name__ == "__main__":
    sys.exit(main())
