"""The default detector: two stages, trained side by side on a CPU, saved as one model file.

Stage 1 is the paper's PointNet++ (:mod:`detector.stage1`, cpu preset) trained to segment objects and vote for
their box centres only (``loss.centre_only``); stage 2 is the crop network (:mod:`detector.stage2`) trained on crops
around the true centres, jittered like stage 1's centre error. A run folder holds ``stage1/`` and ``stage2/`` (each a
resumable run of its own) and ``model.pt``: both stages' weights and the inference settings
(:func:`detector.checkpoint.save_two_stage`), written when both have ended. ``resume`` continues whichever stage is
unfinished. On a CPU with two or more torch threads, stage 2 trains in a process of its own while stage 1 trains
(:mod:`detector.training.threads`: the thread counts follow the steps, so the weights are those of the stages
trained one after the other); on a GPU, one after the other.

Older run folders name the stages ``detect/`` and ``pose/`` and their ``two_stage.yaml`` the geometry section
``pose``: they still resume (:func:`stage_dirs`, :data:`OLD_SECTIONS`).
"""

from __future__ import annotations

import multiprocessing
import os
import sys
import traceback
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path

import torch
import yaml

from detector.checkpoint import save_two_stage
from detector.config import config_to_dict, load_preset, load_yaml
from detector.errors import DetectorError
from detector.data.augment import reads_colour
from detector.data.frames import FrameSource
from detector.geometry.types import GeometryConfig
from detector.stage1.sampling import SamplingConfig
from detector.stage1.train import RESUME_FREE_KEYS, make_config, saved_run_settings, train
from detector.stage2.colour_level import colour_levels
from detector.stage2.poser import PoserConfig
from detector.stage2.train import STAGE2_RESUME_FREE_KEYS, load_stage2_config, saved_settings, train_stage2
from detector.training.checkpoint_file import read_checkpoint
from detector.training.devices import resolve_device
from detector.training.resume import check_resumable
from detector.training.threads import ThreadPlan, check_parent, default_narrow_steps, split_threads

SECTIONS = ("stage1", "stage2", "geometry", "infer", "sampling")
#: Older names of the sections (in run folders' two_stage.yaml and in ``--set``): ``pose`` held the geometry settings.
OLD_SECTIONS = {"pose": "geometry"}
#: The stages' run folders, and their older names.
STAGE_DIRS = ("stage1", "stage2")
OLD_STAGE_DIRS = ("detect", "pose")

#: The defaults of each section (``detector/presets/two-stage.yaml``): stage 1's overrides of the cpu training
#: preset (centre votes only), stage 2's of Stage2TrainConfig, and the inference settings stored in the model file:
#: geometry (keys of detector.geometry.types.GeometryConfig), infer (stage 2's, detector.stage2.poser.PoserConfig)
#: and sampling (stage 1's at inference, detector.stage1.sampling.SamplingConfig).
DEFAULTS: dict[str, dict] = {k: dict(v or {}) for k, v in load_preset("two-stage").items()}


@dataclass
class TwoStageConfig:
    """stage1: dotted overrides of the cpu TrainConfig; stage2: dotted overrides of Stage2TrainConfig;
    geometry: GeometryConfig values, infer: stage 2's PoserConfig values and sampling: SamplingConfig values (stage
    1's at inference), stored in model.pt (the defaults of eval and predict)."""

    stage1: dict = field(default_factory=dict)
    stage2: dict = field(default_factory=dict)
    geometry: dict = field(default_factory=dict)
    infer: dict = field(default_factory=dict)
    sampling: dict = field(default_factory=dict)

    def resolved(self):
        """(TrainConfig of stage 1, Stage2TrainConfig of stage 2, geometry settings, stage-2 inference settings),
        checked."""

        s1 = make_config("cpu", {**DEFAULTS["stage1"], **self.stage1})
        s2 = load_stage2_config(None, {**DEFAULTS["stage2"], **self.stage2})
        if s2.narrow_steps is None:
            s2 = replace(s2, narrow_steps=default_narrow_steps(s1.steps))
        geometry = {**DEFAULTS["geometry"], **self.geometry}
        infer = {**DEFAULTS["infer"], **self.infer}
        for name, keys, given in (("geometry", GeometryConfig.__dataclass_fields__, geometry),
                                  ("infer", PoserConfig.__dataclass_fields__, infer)):
            unknown = [k for k in given if k not in keys]
            if unknown:
                raise DetectorError(f"two-stage config: unknown {name} option '{unknown[0]}'")
        return s1, s2, geometry, asdict(PoserConfig(**infer))

    def resolved_sampling(self) -> dict:
        """Stage 1's sampling at inference (:class:`detector.stage1.sampling.SamplingConfig` values), checked."""
        return vars(SamplingConfig.from_dict({**DEFAULTS["sampling"], **self.sampling}))


def load_two_stage_config(path: str | Path | None = None, overrides: dict | None = None) -> TwoStageConfig:
    """A TwoStageConfig from a YAML file (keys stage1, stage2, geometry, infer, sampling) and ``--set`` overrides
    such as ``{"stage2.steps": 3000, "stage1.lr": 1e-3, "geometry.tau": 0.5, "infer.verify": 8, "sampling.density":
    1.25}``. The older section name ``pose`` (:data:`OLD_SECTIONS`) is read as ``geometry``, in the file and in the
    overrides."""
    data: dict = {k: {} for k in SECTIONS}
    if path is not None:
        path = Path(path)
        loaded = {OLD_SECTIONS.get(k, k): v for k, v in load_yaml(path).items()}
        if set(loaded) - set(data):
            raise DetectorError(f"{path}: a two-stage config has the keys {', '.join(SECTIONS)}")
        for k, v in loaded.items():
            data[k].update(v or {})
    for key, value in (overrides or {}).items():
        head, _, rest = key.partition(".")
        head = OLD_SECTIONS.get(head, head)
        if head not in data or not rest:
            raise DetectorError(f"unknown two-stage option '{key}' (use stage1.KEY, stage2.KEY, geometry.KEY, "
                                "infer.KEY or sampling.KEY)")
        data[head][rest] = value
    cfg = TwoStageConfig(**data)
    cfg.resolved()
    cfg.resolved_sampling()
    return cfg


def train_two_stage(cfg: TwoStageConfig, train_path: str | Path, out_dir: str | Path, resume: bool = False,
                    progress: bool = True, val_path: str | Path | None = None,
                    stage1_path: str | Path | Sequence[str | Path] | None = None, side_by_side: bool = True) -> Path:
    """Train stage 1 into ``out_dir/stage1`` and stage 2 into ``out_dir/stage2`` (:func:`stage_dirs`), then write
    ``out_dir/model.pt``.

    A stage whose run is complete is not trained again; one that was interrupted is resumed (with ``resume``).
    Resuming checks both stages' settings first: only those that do not change the result (e.g. ``stage2.cache_mb``,
    the devices, more steps) may differ from the run's, and a setting the run's ``two_stage.yaml`` does not name
    keeps the run's own value (:func:`run_settings`). val_path: a validation label file for stage 1 (its
    ``metrics.csv`` gets val_loss / val_acc every ``stage1.val_every`` steps, and ``stage1/best.pt`` keeps the
    weights of the lowest); the model file takes the last weights of each stage. stage1_path: a label file of the
    same objects for stage 1 alone, or a list of them whose frames it takes together (default: train_path for
    both), e.g. a capture without distractors while stage 2 learns among them (RESULTS.md, ablation row F).
    side_by_side: on a CPU with two or more threads, train stage 2 in a process of its own while stage 1 trains,
    when both are to train (False: one after the other; the same weights, :mod:`detector.training.threads`). With ``stage2.narrow_steps`` 0 the stages train one after the other,
    each on all threads (as runs saved before that setting did). Returns the model file's path.
    """
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        raise DetectorError("the two-stage model trains in one process (on a GPU with --device cuda); torchrun is "
                            "for --preset cpu or paper")
    out_dir = Path(out_dir)
    s1, s2, geometry, infer = cfg.resolved()
    if stage1_path is not None:  # before hours of stage 1: the files must open and hold the same objects
        _check_same_objects(stage1_path, Path(train_path), s1.class_ids, s2.class_ids)
    d1, d2 = stage_dirs(out_dir)
    done1, saved1 = _progress(d1 / "last.pt", "stage1")
    done2, saved2 = _progress(d2 / "last.pt", "stage2")
    saved1 = saved_run_settings(saved1) if saved1 is not None else None
    if resume and saved1 is not None and saved2 is None and "narrow_steps" not in cfg.stage2:
        # a run started before stage2.narrow_steps (new runs name it in two_stage.yaml, below), stopped in stage 1:
        # its stages train one after the other, each on all threads, as it started
        cfg = replace(cfg, stage2={**cfg.stage2, "narrow_steps": 0})
    if resume:  # a run keeps the settings it started with where its two_stage.yaml and --set name none
        cfg = replace(cfg, stage1=run_settings(saved1, s1, cfg.stage1, RESUME_FREE_KEYS),
                      stage2=run_settings(saved_settings(saved2) if saved2 is not None else None, s2, cfg.stage2,
                                          STAGE2_RESUME_FREE_KEYS))
        s1, s2, geometry, infer = cfg.resolved()
        # before anything runs: a stage that is complete is not trained again, so its settings are checked here
        if saved1 is not None:
            check_resumable(saved1, s1, d1 / "last.pt", RESUME_FREE_KEYS)
        if saved2 is not None:
            check_resumable(saved_settings(saved2), s2, d2 / "last.pt", STAGE2_RESUME_FREE_KEYS)
    if "narrow_steps" not in cfg.stage2:  # named, so that a resumed run knows it started with the setting
        cfg = replace(cfg, stage2={**cfg.stage2, "narrow_steps": s2.narrow_steps})
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "two_stage.yaml").write_text(yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
    need1, need2 = done1 is None or done1 < s1.steps, done2 is None or done2 < s2.steps
    if (need1 and done1 is not None or need2 and done2 is not None) and not resume:
        raise DetectorError(f"{out_dir} holds an unfinished run; add --resume to continue it")
    total = torch.get_num_threads()
    # narrow_steps 0 (runs saved before the setting) or a GPU: the stages one after the other, each on all threads
    shared = s2.narrow_steps > 0 and "cpu" == resolve_device(s1.device).type == resolve_device(s2.device).type
    first, narrow = split_threads(total) if shared else (total, total)
    side_by_side = side_by_side and shared and need1 and need2 and total >= 2
    run1 = partial(train, s1, stage1_path or train_path, d1, val_path=val_path, resume=done1 is not None,
                   progress=progress)
    plan = ThreadPlan(s2.narrow_steps, narrow, total)
    try:
        if side_by_side:
            _side_by_side(run1, first, s2, train_path, d2, done2 is not None, progress, plan)
        else:
            if need1:
                torch.set_num_threads(first)
                run1()
            if need2:
                train_stage2(s2, train_path, d2, resume=done2 is not None, progress=progress, threads=plan)
    finally:
        torch.set_num_threads(total)
    stage1 = read_checkpoint(d1 / "last.pt")
    part = read_checkpoint(d2 / "last.pt")["stage2"]
    if list(part["class_ids"]) != list(stage1["class_ids"]):
        raise DetectorError(f"the stages learned different objects ({stage1['class_ids']} vs {part['class_ids']})")
    # each object's colour level in stage 2's training file, for infer.colour_level (a network without colour: none)
    levels = colour_levels(train_path, part["class_ids"]) if reads_colour(part.get("normalisation")) else None
    return save_two_stage(out_dir / "model.pt", stage1, {**part, "infer_config": infer, "colour_levels": levels},
                          {"geometry_config": geometry, "sampling_config": cfg.resolved_sampling(),
                           "train_file": str(train_path)})


def _side_by_side(run1, threads1: int, s2, train_path: Path, d2: Path, resume2: bool, progress: bool,
                  plan: ThreadPlan) -> None:
    """Train stage 2 in a process of its own (on ``plan``'s threads, waiting for stage 1 at its first wide step)
    while ``run1(before_step=...)`` trains stage 1 here on ``threads1`` torch threads
    (:mod:`detector.training.threads`). An error in either stops both (stage 1 at its next step); stage 2's is raised
    here as a one-line DetectorError."""
    ctx = multiprocessing.get_context("spawn")  # a fresh interpreter: no copy of this process's torch threads
    ended, errors = ctx.Event(), ctx.SimpleQueue()
    child = ctx.Process(target=_stage2_process, name="detector-stage2",
                        args=(s2, str(train_path), str(d2), resume2, progress, plan, ended, os.getpid(), errors))
    child.start()

    def failure() -> DetectorError:
        return DetectorError(errors.get() if not errors.empty() else
                             f"stage 2 stopped with exit code {child.exitcode}")

    def stage2_alive(_step: int) -> None:  # before each stage-1 step: a failed stage 2 ends the run now
        if child.exitcode not in (None, 0):
            raise failure()

    try:
        torch.set_num_threads(threads1)
        run1(before_step=stage2_alive)
    except BaseException:
        child.terminate()
        child.join()
        raise
    ended.set()
    child.join()
    if child.exitcode != 0:
        raise failure()


def _stage2_process(s2, train_path: str, d2: str, resume: bool, progress: bool, plan: ThreadPlan, ended,
                    parent: int, errors) -> None:
    """Stage 2 beside stage 1 (:func:`_side_by_side`): train it, its first wide step after ``ended`` is set; a
    DetectorError (or any other failure, as one line) goes to ``errors`` and the process exits with 2."""
    torch.set_num_threads(plan.narrow)

    def wait() -> None:  # for stage 1 to end, or for the parent to end without a word (killed)
        while not ended.wait(timeout=2.0):
            check_parent(parent)

    try:
        train_stage2(s2, train_path, d2, resume=resume, progress=progress, bar_position=1,
                     threads=replace(plan, wait=wait, parent=parent))
    except KeyboardInterrupt:
        sys.exit(130)
    except DetectorError as exc:  # one line, and short: the pipe must take it before the parent reads it
        errors.put(str(exc).splitlines()[0][:2000] if str(exc) else "stage 2 failed")
        sys.exit(2)
    except Exception as exc:  # noqa: BLE001 - a bug: one line for the parent, the traceback on stderr here
        traceback.print_exc()
        errors.put(f"stage 2 failed: {type(exc).__name__}: {str(exc)[:2000]}".splitlines()[0])
        sys.exit(2)


def _leaves(d: dict, prefix: str = "") -> dict:
    """``{"loss.w_conf": 5.0, ...}``: the dotted keys and values of a nested settings dict."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict) and v:
            out.update(_leaves(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def run_settings(saved: dict | None, now, given: dict, free: frozenset = frozenset()) -> dict:
    """A stage's overrides for resuming its run: ``given`` (dotted keys from the run's two_stage.yaml and --set),
    plus the run's own value (``saved``, the nested settings in its last.pt) of every setting that ``given`` does
    not name and today's defaults (``now``, the resolved config) set otherwise. So a default changed since the run
    started (stage 1's colour input became ``grey_world``) does not change or refuse the run; a setting named
    differently from the run's is still refused by :func:`check_resumable`. The settings in ``free`` (those that do
    not change the result: devices, workers, ...) follow today's defaults; keys the settings no longer have are left
    to that check."""
    if saved is None:
        return dict(given)
    current = _leaves(config_to_dict(now))

    def named(key: str) -> bool:
        return any(key == g or key.startswith(g + ".") or g.startswith(key + ".") for g in given)

    kept = {k: v for k, v in _leaves(saved).items()
            if k in current and current[k] != v and k.split(".")[0] not in free and not named(k)}
    return {**kept, **given}


def _check_same_objects(stage1_path: str | Path | Sequence[str | Path], train_path: Path, ids1, ids2) -> None:
    """Raise a one-line DetectorError unless the label files open and stage 1 and stage 2 would learn the
    same object ids from them (stage1_path: one file or several; ids1 / ids2: the stages' ``class_ids`` settings,
    None = all of the file's)."""
    stage1 = FrameSource(stage1_path, class_ids=ids1)
    learned = [stage1.class_ids, FrameSource(train_path, class_ids=ids2).class_ids]
    if learned[0] != learned[1]:
        given = " ".join(map(str, stage1.paths))
        raise DetectorError(f"--stage1-data {given} holds objects {learned[0]}, the training file "
                            f"{train_path} {learned[1]}: both stages must learn the same objects")


def stage_dirs(out_dir: str | Path) -> tuple[Path, Path]:
    """The run folders of stage 1 and stage 2 in ``out_dir``: ``stage1/`` and ``stage2/``, or a run's older
    ``detect/`` and ``pose/`` when it has them (and not the new ones)."""
    out_dir = Path(out_dir)
    new, old = [out_dir / d for d in STAGE_DIRS], [out_dir / d for d in OLD_STAGE_DIRS]
    if not any(d.exists() for d in new) and any(d.is_dir() for d in old):
        return old[0], old[1]
    return new[0], new[1]


def _progress(path: Path, stage: str) -> tuple[int | None, dict | None]:
    """(steps done, training settings) of the run whose last.pt is ``path``; (None, None): no such run."""
    if not path.is_file():
        return None, None
    payload = read_checkpoint(path)
    part = payload["stage2"] if stage == "stage2" else payload
    return int(part["step"]), (part.get("train_state") or {}).get("config")
