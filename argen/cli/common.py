"""What the ``argen`` commands share: the error wrapper (user errors become one line on stderr, exit 2), the
template loader with the CLI's shortcuts (``--set`` parsed by :func:`argen.settings.parse_sets`), ``--shard``
parsing, the placement check, and the options and steps both capture commands (``capture-sim``, ``capture``) take."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Optional

import typer

from argen.bop import load_camera
from argen.config import load_template, override
from argen.errors import ArgenError
from argen.settings import parse_sets


def fail(msg: str) -> None:
    """Print one error line and exit with code 2."""
    typer.echo(f"argen: error: {msg}", err=True)
    raise typer.Exit(2)


def user_errors(fn):
    """Turn ArgenError, and an OSError on a path the user gave or that lies under it (a folder that cannot be made,
    a file that is a folder, no permission), into one line on stderr and exit 2."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except ArgenError as exc:
            fail(str(exc))
        except OSError as exc:
            if exc.filename is None or not exc.strerror:
                raise
            fail(f"cannot use {exc.filename}: {exc.strerror[0].lower()}{exc.strerror[1:]}")
        except KeyboardInterrupt:
            typer.echo("argen: interrupted; run the same command again to resume", err=True)
            raise typer.Exit(130)

    return wrapper


def load_config(scene: str, seed: Optional[int], noise: Optional[str], sets: list[str], objects: Optional[str],
                sensor: Optional[str] = None, camera: Optional[Path] = None):
    """The template with the CLI's options applied: the camera file's intrinsics and size (``--camera``, a BOP
    camera.json) over the sensor profile's, then seed, noise, objects and ``--set`` keys."""
    cfg = load_template(scene, sensor=sensor)
    dotted = camera_keys(camera) if camera is not None else {}
    dotted.update(parse_sets(sets))  # the --set syntax of both command lines (argen.settings)
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


def camera_keys(path: Path) -> dict:
    """Template keys for a BOP ``camera.json``'s intrinsics and image size: {"camera.fx": ..., "camera.width": ...}."""
    cam = load_camera(path)
    if cam.width is None or cam.height is None:
        raise ArgenError(f"{path}: --camera needs the image size (width and height) in the camera file")
    K = cam.K
    return {"camera.width": int(cam.width), "camera.height": int(cam.height), "camera.fx": float(K[0, 0]),
            "camera.fy": float(K[1, 1]), "camera.cx": float(K[0, 2]), "camera.cy": float(K[1, 2])}


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
    # lazy: trimesh and cv2.aruco load slowly; `argen --help` and most commands do not need them
    from argen.sim.board import Board
    from argen.sim.placement import never_fit

    half = Board.from_config(cfg.board).free_half_extent
    bad = never_fit(objs, cfg.placement, half)
    if bad:
        raise ArgenError(f"impossible placement: {', '.join(bad)} cannot fit on the board's free area "
                         f"({2 * half:.3f} m square); use a larger board (board.markers_per_side, board.marker_gap)")


# The options both capture commands take (each call makes a new typer.Option: typer keeps state in it)
def out_option():
    return typer.Option(..., "--out", help="output BOP dataset folder")


def models_option():
    return typer.Option(None, "--models", help="BOP models folder (PLY in mm), or a folder of plain meshes (imported "
                        "on the fly); default: built-in objects")


def objects_option():
    return typer.Option(None, "--objects", help="comma-separated object names or ids")


def workers_option():
    return typer.Option(1, "--workers", help="processes, each with its own renderer")


def overwrite_option():
    return typer.Option(False, "--overwrite", help="replace an output folder made with other options")


def sets_option():
    return typer.Option([], "--set", help="override any template key, e.g. --set camera.distance=[0.5,1.0]")


def quiet_option():
    return typer.Option(False, "--quiet", help="no progress bar")


def capture_objects(cfg, models: Optional[Path], workers: int) -> tuple[list, str]:
    """The objects a capture places (``--models`` or the built-in ones, with the template's selection), after the
    checks both capture commands make: at least one worker, and every object fits the board in some resting pose.
    Import notes go to stderr. Returns (objects, models_source for the dataset's argen.json)."""
    # lazy: trimesh loads slowly; `argen --help` does not need it
    from argen.models.meshimport import load_any_models

    if workers < 1:
        raise ArgenError(f"--workers must be at least 1, got {workers}")
    objs, notes = load_any_models(models, cfg.objects or None)
    for line in notes:
        typer.echo(line, err=True)
    check_placeable(cfg, objs)
    return objs, str(models.resolve()) if models else "builtin"
