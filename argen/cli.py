"""The ``argen`` command line: parse, call, print. User errors become one line on stderr, exit 2."""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import Optional

import typer
import yaml

from argen.errors import ArgenError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="argen: simulated AR capture and per-point labels for 6-DoF pose estimation.")


def fail(msg: str) -> None:
    """Print one error line and exit with code 2."""
    typer.echo(f"argen: error: {msg}", err=True)
    raise typer.Exit(2)


def user_errors(fn):
    """Turn ArgenError (and a few OS-level user errors) into one line on stderr and exit 2."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except ArgenError as exc:
            fail(str(exc))
        except KeyboardInterrupt:
            typer.echo("argen: interrupted; run the same command again to resume", err=True)
            raise typer.Exit(130)

    return wrapper


def parse_sets(sets: list[str]) -> dict:
    """``["camera.distance=[0.5, 1.0]", "noise.enabled=false"]`` -> dotted override dict (YAML values)."""
    out = {}
    for s in sets or []:
        if "=" not in s:
            raise ArgenError(f"--set expects KEY=VALUE, got '{s}'")
        key, value = s.split("=", 1)
        try:
            out[key.strip()] = yaml.safe_load(value)
        except yaml.YAMLError:
            raise ArgenError(f"--set {key}: cannot parse value '{value}'") from None
    return out


def load_config(scene: str, seed: Optional[int], noise: Optional[str], sets: list[str], objects: Optional[str],
                sensor: Optional[str] = None):
    from argen.config import load_template, override

    cfg = load_template(scene, sensor=sensor)
    dotted = parse_sets(sets)
    if seed is not None:
        dotted["seed"] = seed
    if noise is not None:
        if noise not in NOISE_CHOICES:
            raise ArgenError(f"--noise must be 'on' or 'none' ('kinect' = 'on'), got '{noise}'")
        dotted["noise.enabled"] = noise != "none"
    if objects is not None:
        dotted["objects"] = [o for o in objects.split(",") if o.strip()]
        if not dotted["objects"]:
            raise ArgenError("--objects names no object")
    return override(cfg, dotted) if dotted else cfg


#: --noise values: the sensor profile's noise on ("kinect", its old name, kept), or none.
NOISE_CHOICES = ("on", "kinect", "none")


def parse_shard(text: Optional[str]) -> tuple[int, int]:
    """``"2/8"`` -> (2, 8); None -> (0, 1)."""
    if text is None:
        return (0, 1)
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise ArgenError(f"--shard expects I/N (e.g. 0/4), got '{text}'") from None
    if not (n >= 1 and 0 <= i < n):
        raise ArgenError(f"--shard must be I/N with 0 <= I < N, got '{text}'")
    return (i, n)


def check_placeable(cfg, objs) -> None:
    """Refuse objects that fit on the board's free area in no resting pose (impossible placement)."""
    from argen.board import Board
    from argen.placement import never_fit

    half = Board.from_config(cfg.board).free_half_extent
    bad = never_fit(objs, cfg.placement, half)
    if bad:
        raise ArgenError(f"impossible placement: {', '.join(bad)} cannot fit on the board's free area "
                         f"({2 * half:.3f} m square); use a larger board (board.markers_per_side, board.marker_gap)")


@app.command("capture-sim")
@user_errors
def capture_sim(
    out: Path = typer.Option(..., "--out", help="output BOP dataset folder"),
    scene: str = typer.Option("linemod", "--scene", help="template name (linemod, lchf) or a YAML file"),
    frames: int = typer.Option(20, "--frames", help="frames to capture (accepted + rejected)"),
    models: Optional[Path] = typer.Option(None, "--models", help="BOP models folder (PLY in mm), or a folder of "
                                           "plain meshes (imported on the fly); default: built-in objects"),
    objects: Optional[str] = typer.Option(None, "--objects", help="comma-separated object names or ids"),
    seed: Optional[int] = typer.Option(None, "--seed", help="random seed (default: the template's)"),
    noise: Optional[str] = typer.Option(None, "--noise", help="'on' (the sensor's noise model) or 'none' "
                                        "(default: the template's)"),
    sensor: Optional[str] = typer.Option(None, "--sensor", help="sensor profile: kinect_v1 (default), kinect_v2 "
                                         "(time of flight), realsense_d435 (active stereo)"),
    workers: int = typer.Option(1, "--workers", help="processes, each with its own renderer"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace an output folder made with other options"),
    sets: list[str] = typer.Option([], "--set", help="override any template key, e.g. --set camera.distance=[0.5,1.0]"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
    shard: Optional[str] = typer.Option(None, "--shard", help="I/N: make only frames with index % N == I "
                                        "(one of N machines); join the shards with `argen merge`"),
):
    """Simulate an AR capture (boards, placed objects, rendering, sensor noise) and write BOP scenes."""
    from argen.capture import CaptureRequest, run_capture
    from argen.meshimport import load_any_models

    if frames < 1:
        raise ArgenError(f"--frames must be at least 1, got {frames}")
    if workers < 1:
        raise ArgenError(f"--workers must be at least 1, got {workers}")
    cfg = load_config(scene, seed, noise, sets, objects, sensor)
    objs, notes = load_any_models(models, cfg.objects or None)
    for line in notes:
        typer.echo(line, err=True)
    check_placeable(cfg, objs)
    req = CaptureRequest(cfg=cfg, objects=objs, out=out, frames=frames, workers=workers,
                         models_source=str(models.resolve()) if models else "builtin",
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
        from argen.label import merge_label_files

        n = merge_label_files(shards, out, overwrite=overwrite)
    elif any(p.suffix.lower() in (".h5", ".hdf5") for p in shards):
        raise ArgenError("give either capture folders or label files to merge, not both")
    else:
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
    from argen.board import Board
    from argen.config import load_template

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


from argen.cli_label import register as _register_label  # noqa: E402  (label, validate, preview)
_register_label(app)
from argen.cli_real import register as _register_real  # noqa: E402  (capture --recording, replace)
_register_real(app)
from argen.cli_models import register as _register_models  # noqa: E402  (models import)
_register_models(app)


if __name__ == "__main__":
    sys.exit(main())
