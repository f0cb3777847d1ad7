"""The ``argen capture`` (real recordings) and ``argen replace`` commands (registered by argen.cli.app)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from argen.cli.common import (NOISE_CHOICES, capture_objects, load_config, models_option,
                              objects_option, out_option, overwrite_option, quiet_option, sets_option, user_errors,
                              workers_option)
from argen.errors import ArgenError


def register(app: typer.Typer) -> None:
    """Add the capture and replace commands to ``app``."""

    @app.command("capture")
    @user_errors
    def capture_cmd(
        recording: Path = typer.Option(..., "--recording", help="recording: a folder (rgb/ + depth/ + camera.json; "
                                       "TUM's rgb.txt + depth.txt; or colour and 16-bit depth images + camera.json) "
                                       "or a ROS 1 .bag (RealSense)"),
        out: Path = out_option(),
        models: Optional[Path] = models_option(),
        scene: str = typer.Option("linemod", "--scene", help="template (board, placement, noise) or a YAML file"),
        objects: Optional[str] = objects_option(),
        seed: Optional[int] = typer.Option(None, "--seed", help="random seed of the placements"),
        noise: Optional[str] = typer.Option(None, "--noise", help="'on' or 'none': sensor noise on the virtual "
                                            "objects' depth (default: the template's)"),
        sensor: Optional[str] = typer.Option(None, "--sensor", help="sensor profile of the noise on the virtual "
                                             "objects (the intrinsics are the recording's)"),
        depth_scale: Optional[float] = typer.Option(None, "--depth-scale", help="mm per depth-PNG unit "
                                                    "(overrides camera.json; 1.0 for RealSense / Azure Kinect)"),
        camera: Optional[str] = typer.Option(None, "--camera", help="intrinsics: a BOP camera.json, or 'tum' (the "
                                             "TUM benchmark's default); overrides the recording's"),
        support: Optional[str] = typer.Option(None, "--support", help="where objects stand: 'auto' (the board where "
                                              "found, else the dominant horizontal plane), 'board' or 'plane' "
                                              "(default: the template's plane.support, auto)"),
        occlusion_margin: float = typer.Option(0.003, "--occlusion-margin", help="metres a real surface must be in "
                                               "front of a virtual one to hide it"),
        workers: int = workers_option(),
        overwrite: bool = overwrite_option(),
        sets: list[str] = sets_option(),
        quiet: bool = quiet_option(),
    ):
        """Composite virtual objects into a recorded RGB-D sequence, on the printed board or, without one, on the
        dominant horizontal plane; write BOP scenes."""
        # lazy: pyrender, open3d and trimesh take seconds to load; --help and the other commands need none
        from argen.real.capture import run_real_capture
        from argen.real.readers import camera_arg, open_any
        from argen.sim.capture import CaptureRequest

        rec = open_any(recording, depth_scale, camera_arg(camera))
        if rec.camera_source == "default":
            typer.echo(f"{recording}: no camera.json; using the TUM benchmark's default intrinsics (fx = fy = 525, "
                       "cx = 319.5, cy = 239.5); pass --camera to change them", err=True)
        cfg = load_config(scene, seed, noise, sets + ([f"plane.support={support}"] if support else []), objects, sensor)
        objs, source = capture_objects(cfg, models, workers)
        req = CaptureRequest(cfg=cfg, objects=objs, out=out, frames=len(rec), workers=workers, models_source=source,
                             overwrite=overwrite, progress=not quiet)
        summary = run_real_capture(req, rec, occlusion_margin)
        typer.echo(f"{out}: {summary.line()}")

    @app.command("replace")
    @user_errors
    def replace_cmd(
        dataset: Path = typer.Argument(..., help="BOP dataset with ground truth (e.g. the LineMOD test set)"),
        out: Path = typer.Option(..., "--out", help="output BOP dataset folder"),
        split: str = typer.Option("test", "--split", help="split folder inside the dataset"),
        models: Optional[Path] = typer.Option(None, "--models", help="BOP models folder, or a folder of plain meshes "
                                               "named obj_NNNNNN (imported on the fly); default: DATASET/models"),
        obj_id: Optional[int] = typer.Option(None, "--obj-id", help="target object (default: each frame's first "
                                             "GT instance)"),
        fraction: float = typer.Option(0.1, "--fraction", help="share of the frames to use (the paper: 0.1)"),
        step_deg: float = typer.Option(30.0, "--step-deg", help="rotation step about the plane normal, degrees"),
        seed: int = typer.Option(0, "--seed", help="frame choice, plane fit and noise seed"),
        noise: str = typer.Option("on", "--noise", help="'on' or 'none': sensor noise on the changed pixels"),
        scene: str = typer.Option("linemod", "--scene", help="template whose noise model to use"),
        sensor: Optional[str] = typer.Option(None, "--sensor", help="sensor profile whose noise model to use "
                                             "(default: the template's)"),
        overwrite: bool = typer.Option(False, "--overwrite", help="replace a non-empty output folder"),
        quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
    ):
        """The paper's fine-tuning frames: the target object removed and re-inserted every STEP degrees."""
        # lazy: pyrender, open3d and trimesh take seconds to load; --help and the other commands need none
        from argen.config import load_template
        from argen.real.replace import replace_dataset

        if noise not in NOISE_CHOICES:
            raise ArgenError(f"--noise must be 'on' or 'none' ('kinect' = 'on'), got '{noise}'")
        noise_cfg = load_template(scene, sensor=sensor).noise if noise != "none" else None
        summary = replace_dataset(dataset, out, split=split, models=models, obj_id=obj_id, fraction=fraction,
                                  step_deg=step_deg, seed=seed, noise=noise_cfg, overwrite=overwrite,
                                  progress=not quiet)
        for line in summary.notes:
            typer.echo(line, err=True)
        typer.echo(f"{out}: {summary.line()}")
