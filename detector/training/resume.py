"""Exact resume, shared by the trainers: torch RNG states, the settings check (only those that do not change the
result may differ), ``last.pt`` as a run's marker, and restoring weights, optimiser, scheduler and RNG."""

from __future__ import annotations

from pathlib import Path

import torch

from detector.config import config_to_dict
from detector.errors import DetectorError
from detector.training.schedule import lr_factor


def rng_state(device: torch.device) -> dict:
    """Torch's CPU (and CUDA) generator states, for exact resume."""
    state = {"cpu": torch.get_rng_state()}
    if device.type == "cuda":
        state["cuda"] = torch.cuda.get_rng_state(device)
    return state


def set_rng_state(state: dict, device: torch.device) -> None:
    torch.set_rng_state(state["cpu"].cpu())
    if device.type == "cuda" and "cuda" in state:
        torch.cuda.set_rng_state(state["cuda"].cpu(), device)


def check_resumable(saved: dict, cfg, path: Path, free: frozenset) -> None:
    """A resumed run must use the settings that produced the checkpoint (``saved``, a config dict), bar the keys
    in ``free`` (settings that do not change the result, each trainer's ``RESUME_FREE_KEYS``)."""
    now = config_to_dict(cfg)
    for key in sorted(set(saved) | set(now)):
        if key not in free and saved.get(key) != now.get(key):
            raise DetectorError(f"{path}: cannot resume with {key}={now.get(key)!r}; the run used "
                                f"{key}={saved.get(key)!r}")


def run_checkpoint(out_dir: Path, resume: bool) -> Path:
    """``out_dir/last.pt``, checked: it must exist to resume and must not to start a run (DetectorError)."""
    last_path = Path(out_dir) / "last.pt"
    if resume and not last_path.is_file():
        raise DetectorError(f"nothing to resume: {last_path} does not exist")
    if not resume and last_path.exists():
        raise DetectorError(f"{out_dir} already holds a run; resume it or choose another folder")
    return last_path


def restore_state(net: torch.nn.Module, opt, sched, model_state: dict, state: dict, cfg, path: Path,
                  device: torch.device, start: int, total: int, free: frozenset) -> None:
    """Resume: check the run's settings (:func:`check_resumable` with the keys ``free`` to change), load weights,
    optimiser, scheduler and RNG state; the learning rate then follows this run's schedule of ``total`` steps from
    ``start`` (which differs from the saved one when ``steps`` grew)."""
    check_resumable(state["config"], cfg, path, free)
    net.load_state_dict(model_state)
    opt.load_state_dict(state["optimizer"])
    sched.load_state_dict(state["scheduler"])
    set_rng_state(state["rng"], device)
    for group, base_lr in zip(opt.param_groups, sched.base_lrs):
        group["lr"] = base_lr * lr_factor(start, total, cfg)


def with_added_settings(saved: dict, added: dict) -> dict:
    """``saved`` (a config dict) with each dotted key of ``added`` ("loss.fg_weight": 1.0) that it lacks set to
    its value, where the key's section is there (a section the saved run lacks is left out: the config check then
    names it); the saved dict and its sections are not changed (copies where a key is added)."""
    out = dict(saved)
    for key, value in added.items():
        *path, last = key.split(".")
        node = out
        for part in path:
            if not isinstance(node.get(part), dict):
                break
            node[part] = dict(node[part])
            node = node[part]
        else:
            node.setdefault(last, value)
    return out
