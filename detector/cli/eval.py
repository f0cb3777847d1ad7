"""``detector eval`` and ``detector predict``, added to the ``detector`` typer app by :func:`register`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from detector.cli.common import user_errors
from detector.errors import DetectorError


#: eval's and predict's --net-dtype.
NET_DTYPE_HELP = ("The networks' number format: float32, bfloat16 (CPU autocast: about a fifth less network time on "
                  "a CPU that multiplies bfloat16 in hardware, slower on one that does not) or auto (bfloat16 on "
                  "such a CPU, else float32).")


#: eval's and predict's --set: the model file's settings they change for one run (detector.infer.split_sets).
SET_HELP = ("A geometry, sampling or stage-2 inference setting of the model file, e.g. --set "
            "geometry.depth_check=false (keys of detector.geometry.types.GeometryConfig), --set sampling.density=1 "
            "(stage 1 draws as many points as it trained on), --set sampling.passes=1 (stage 1 samples a frame "
            "once; with geometry.min_votes=3 for a model that samples twice), --set sampling.fps=trained (the training's "
            "farthest point sampling instead of the tree-based one) or --set infer.hypotheses=64 (keys of "
            "detector.stage2.poser.PoserConfig).")


def register(app: typer.Typer) -> None:
    """Add the ``eval`` and ``predict`` commands to ``app``."""

    @app.command("eval")
    @user_errors
    def eval_cmd(
        checkpoint: Path = typer.Argument(..., help="Checkpoint written by 'detector train'."),
        data: Path = typer.Argument(..., help="Label file (HDF5) written by 'argen label'."),
        out: Path = typer.Option(..., "--out", help="Report folder (report.md, report.json, curve.png, BOP CSV)."),
        icp: bool = typer.Option(False, "--icp", help="Also refine with ICP (Table II 'with refinement')."),
        tau: Optional[float] = typer.Option(None, "--tau", help="Confidence threshold (default: the model's own, "
                                                                "else the paper's 0.8)."),
        min_score: Optional[float] = typer.Option(None, "--min-score",
                                                  help="Drop detections scoring less (default: the model's own)."),
        min_visib: float = typer.Option(0.1, "--min-visib", help="Ignore instances less visible than this."),
        frames: Optional[int] = typer.Option(None, "--frames", help="Evaluate only the first N frames."),
        method: str = typer.Option("argen", "--method", help="Method name of the BOP results file "
                                                              "METHOD_DATASET-SPLIT.csv (letters and digits)."),
        dataset_name: Optional[str] = typer.Option(None, "--dataset-name",
                                                   help="Dataset name of the BOP results file (default: the BOP "
                                                        "toolkit's name for a capture of lm / lmo / ycbv objects, "
                                                        "else the label file's dataset folder, letters and digits "
                                                        "only)."),
        bop_dataset: Optional[Path] = typer.Option(None, "--bop-dataset",
                                                   help="BOP dataset folder the label file was made from, for "
                                                        "BOP19 AR (default: the one the label file names)."),
        device: str = typer.Option("cpu", "--device", help="torch device, e.g. cpu or cuda."),
        seed: int = typer.Option(0, "--seed", help="Point sampling seed."),
        net_dtype: str = typer.Option("auto", "--net-dtype", help=NET_DTYPE_HELP),
        sets: list[str] = typer.Option([], "--set", help=SET_HELP),
        quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
        reuse: bool = typer.Option(False, "--reuse", help="Keep the report in --out when it was made as this run "
                                                          "would make it (the same model and label file bytes, "
                                                          "settings, seed and options; the code is not compared) and "
                                                          "evaluate nothing; else evaluate. For scripts that are run "
                                                          "again."),
    ) -> None:
        """Evaluate a checkpoint on a label file: ADD/ADD-S accuracy, F1, BOP19 AR, timings, BOP results CSV."""
        # lazy: torch and open3d load in seconds; `detector --help` and the other commands do not need them
        from detector.checkpoint import load_checkpoint
        from detector.data.frames import open_label_file
        from detector.evaluate import evaluate, report_settings, scored_dataset
        from detector.infer import (check_label_objects, checkpoint_geometry_config, checkpoint_objects,
                                    checkpoint_poser, split_sets)
        from detector.net_dtype import resolve_net_dtype
        from detector.report import made_alike, previous_report, run_record
        from detector.stage1.predictor import network_predictor

        if frames is not None and frames < 1:
            raise DetectorError(f"--frames must be at least 1, got {frames}")
        if not 0 <= min_visib <= 1:
            raise DetectorError(f"--min-visib is a visible fraction in [0, 1], got {min_visib}")
        sets, sampling, infer_sets = split_sets(sets)
        dtype = resolve_net_dtype(net_dtype, device)
        ckpt = load_checkpoint(checkpoint, device, sampling)
        cfg = checkpoint_geometry_config(ckpt, tau, icp, min_score, sets)
        with open_label_file(data) as lf:
            n = lf.num_frames
            if n == 0:
                raise DetectorError(f"{data} holds no frames")
            check_label_objects(ckpt, lf.objects)
            scored_on = scored_dataset(lf, bop_dataset)
        objects = checkpoint_objects(ckpt)[0]
        poser = checkpoint_poser(ckpt, objects, device, seed, infer_sets, dtype)
        run = run_record(checkpoint, data, seed=seed, device=device, net_dtype=dtype, min_visib=min_visib,
                         frames=frames, method=method,
                         dataset_name=dataset_name, bop_dataset=None if bop_dataset is None else str(bop_dataset),
                         bop_dataset_found=bool(scored_on) and Path(scored_on).is_dir())
        if reuse and made_alike(previous_report(out), report_settings(cfg, icp, ckpt.sampling_used, poser, run)):
            typer.echo(f"{out / 'report.md'} is up to date: made from the same model, label file, settings and seed")
            return
        s = evaluate(network_predictor(ckpt, seed, net_dtype=dtype), data, out, icp=icp, cfg=cfg, device=device,
                     frames=list(range(min(n, frames or n))), min_visib=min_visib, progress=not quiet,
                     poser=poser, method=method, dataset_name=dataset_name, bop_dataset=bop_dataset,
                     sampling=ckpt.sampling_used, objects=objects, run=run)
        key = "icp" if icp else "noicp"
        b = s["bop19"]
        ar = f"BOP19 AR: {b['bop19_average_recall']:.3f}  " if "skipped" not in b else ""
        typer.echo(f"ADD@10%: {100 * s['mean'][key]['0.10']:.1f} %  F1@15%: {100 * s['f1'][key]['f1']:.1f} %  {ar}"
                   f"{s['fps']:.2f} frames/s  -> {out / 'report.md'}")
        if "skipped" in b:
            typer.echo(f"detector: warning: BOP19 AR not computed: {b['skipped']}", err=True)

    @app.command("predict")
    @user_errors
    def predict_cmd(
        checkpoint: Path = typer.Argument(..., help="Checkpoint written by 'detector train'."),
        input: str = typer.Argument(..., help="A BOP frame SPLIT_DIR/SCENE_ID/IM_ID, a depth .png or a .ply cloud."),
        out: Path = typer.Option(Path("predict"), "--out", help="Folder for poses.json and poses.png."),
        K: Optional[str] = typer.Option(None, "--K", help="Intrinsics of a depth PNG: fx,fy,cx,cy or 9 values."),
        camera: Optional[Path] = typer.Option(None, "--camera", help="BOP camera.json for a depth PNG."),
        depth_scale: Optional[float] = typer.Option(None, "--depth-scale",
                                                    help="Depth PNG value x scale = millimetres (BOP)."),
        rgb: Optional[Path] = typer.Option(None, "--rgb", help="Colour image for a depth PNG."),
        icp: bool = typer.Option(False, "--icp", help="Refine with ICP."),
        tau: Optional[float] = typer.Option(None, "--tau", help="Confidence threshold (default: the model's own, "
                                                                "else the paper's 0.8)."),
        min_score: Optional[float] = typer.Option(None, "--min-score",
                                                  help="Drop detections scoring less (default: the model's own)."),
        device: str = typer.Option("cpu", "--device", help="torch device."),
        seed: int = typer.Option(0, "--seed", help="Point sampling seed."),
        net_dtype: str = typer.Option("auto", "--net-dtype", help=NET_DTYPE_HELP),
        max_depth: Optional[float] = typer.Option(None, "--max-depth",
                                                  help="Use the points up to this depth, metres (default: the "
                                                       "working volume the model was trained in, when it says)."),
        sets: list[str] = typer.Option([], "--set", help=SET_HELP),
    ) -> None:
        """Predict the poses in one frame: poses.json (metres) and poses.png (3D boxes)."""
        # lazy: torch and open3d load in seconds; `detector --help` and the other commands do not need them
        from detector.checkpoint import load_checkpoint
        from detector.infer import (checkpoint_geometry_config, checkpoint_max_depth, checkpoint_objects,
                                    checkpoint_poser, colour_networks, colour_readers, missing_surfaces, split_sets)
        from detector.net_dtype import resolve_net_dtype
        from detector.predict import load_input, predict
        from detector.stage1.predictor import network_predictor

        sets, sampling, infer_sets = split_sets(sets)
        dtype = resolve_net_dtype(net_dtype, device)
        ckpt = load_checkpoint(checkpoint, device, sampling)
        cfg = checkpoint_geometry_config(ckpt, tau, icp, min_score, sets)
        depth = checkpoint_max_depth(ckpt, max_depth)
        inp = load_input(input, K=K, depth_scale=depth_scale, camera=camera, rgb=rgb, seed=seed, max_depth=depth)
        objects, names = checkpoint_objects(ckpt)
        readers = colour_readers(ckpt, objects, cfg)
        if readers and not inp.features[:, 3:6].any():
            cost = ("it finds little without it (RESULTS.md)" if colour_networks(ckpt) else
                    "without it a printed object's way round is left unchecked")
            typer.echo(f"detector: warning: {checkpoint.name} reads colour ({', '.join(readers)}) and {input} has "
                       f"none (give the colour image with --rgb): {cost}", err=True)
        if (warning := missing_surfaces(cfg, objects, checkpoint.name)) is not None:
            typer.echo(f"detector: warning: {warning}", err=True)
        res = predict(network_predictor(ckpt, seed, net_dtype=dtype), inp, objects, out, cfg, names,
                      poser=checkpoint_poser(ckpt, objects, device, seed, infer_sets, dtype), max_depth=depth,
                      net_dtype=dtype)
        for d in res["detections"]:
            typer.echo(f"{d['name']} (obj {d['obj_id']}): score {d['score']:.2f}, t = "
                       + " ".join(f"{v:.3f}" for v in d["t"]) + " m")
        typer.echo(f"{len(res['detections'])} detections -> {out / 'poses.json'}, {out / 'poses.png'}")
