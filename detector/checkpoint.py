"""Checkpoint files: the trained network with everything needed to use it (config, classes, objects,
normalisation) and, for ``--resume``, the whole training state. Written atomically (temp file + rename).

A checkpoint is a ``torch.save`` dict of plain values and tensors only, read back with
``torch.load(weights_only=True)``: no pickled code runs when a file is loaded.

Version 1 holds one network (the paper's single-shot PoseNet). Version 2 holds the stages of a two-stage model:
``detect`` (the PoseNet that finds objects and their centres, the version-1 keys) and ``pose`` (the crop network,
:func:`detector.train_pose.pose_payload`), plus ``extra`` with the inference settings chosen at training time
(``pose_config``: e.g. the score threshold). A stage-2 run's own ``last.pt`` is version 2 with ``pose`` only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from detector.cropnet import build_pose_net
from argen.fileio import atomic_path
from detector.errors import DetectorError, argen_errors
from detector.model import ModelConfig, PoseNet

FORMAT = "detector-checkpoint"
VERSION = 1
VERSIONS = (1, 2)  # 2: a two-stage model (or a stage-2 run)


@dataclass
class Checkpoint:
    """A trained network ready for inference, and what it was trained on.

    model: PoseNet in eval mode on the requested device; class_ids: object id of class index c + 1;
    objects: the label file's object table as plain lists (ids, names, diameters metres, symmetric,
    control_points (M, 9, 3) metres, model_points (M, P, 3) metres, sym_transforms per object (S, 4, 4));
    num_points: points sampled per frame; step: training steps done; extra: train config, metrics;
    normalisation: the network input's colour normalisation (``detector.data.input_normalisation``: with "colour":
    "none" the network has no colour input);
    pose_net: a two-stage model's crop network (stage 2) or None; pose: its part of the file (configs, classes)
    without the weights; pose_config: inference settings stored with the model ({} for none).
    """

    model: Any
    model_config: Any
    class_ids: list[int]
    objects: dict
    num_points: int
    step: int
    extra: dict
    normalisation: dict = field(default_factory=dict)
    pose_net: Any = None
    pose: dict | None = None
    pose_config: dict = field(default_factory=dict)


def atomic_torch_save(obj: Any, path: Path) -> None:
    """``torch.save`` to a temporary file beside ``path``, then rename (:func:`argen.fileio.atomic_path`, the one
    atomic-write helper): readers never see half a file; a full disk is a one-line DetectorError."""
    with argen_errors(), atomic_path(path) as tmp:
        torch.save(obj, tmp)


def save_checkpoint(path: str | Path, *, model: torch.nn.Module, model_config, class_ids: list[int], objects: dict,
                    num_points: int, step: int, normalisation: dict, extra: dict | None = None,
                    train_state: dict | None = None) -> Path:
    """Write a checkpoint atomically; ``train_state`` (optimiser, scheduler, RNG, data position) is for resume."""
    path = Path(path)
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "model_state": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "model_config": model_config.to_dict(),
        "class_ids": [int(c) for c in class_ids],
        "objects": objects,
        "num_points": int(num_points),
        "step": int(step),
        "normalisation": dict(normalisation),
        "extra": extra or {},
        "train_state": train_state,
    }
    atomic_torch_save(payload, path)
    return path


def read_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> dict:
    """The raw checkpoint dict, checked to be ours; a missing or foreign file is a :class:`DetectorError`."""
    path = Path(path)
    if not path.is_file():
        raise DetectorError(f"checkpoint not found: {path}")
    try:
        payload = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # torch raises many types for a foreign or truncated file
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DetectorError(f"{path} is not a readable detector checkpoint ({first})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise DetectorError(f"{path} is not a detector checkpoint")
    if payload.get("version") not in VERSIONS:
        raise DetectorError(f"{path}: checkpoint version {payload.get('version')} is not supported "
                            f"(this detector reads versions {', '.join(map(str, VERSIONS))})")
    return payload


def build_model(payload: dict, path: Path, device: str | torch.device):
    """The PoseNet of a checkpoint dict with its weights loaded; a mismatch is a :class:`DetectorError`."""

    try:
        cfg = ModelConfig.from_dict(payload["model_config"])
        model = PoseNet(cfg, num_classes=len(payload["class_ids"]))
        model.load_state_dict(payload["model_state"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DetectorError(f"{path}: the weights do not match the stored model config ({first})") from None
    return model.to(device), cfg


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> Checkpoint:
    """Load a checkpoint for inference: the model (both stages of a two-stage one) in eval mode on ``device``
    plus its metadata."""
    path = Path(path)
    payload = read_checkpoint(path, "cpu")
    pose_net, pose = None, None
    if payload["version"] == 2:
        if "detect" not in payload:
            raise DetectorError(f"{path} holds a stage-2 network only; use the two-stage model file (model.pt) "
                                "that `detector train` writes")
        pose = {k: v for k, v in payload["pose"].items() if k not in ("model_state", "train_state")}
        pose_net = build_pose_net(payload["pose"], str(path), device).eval()
        extra_top = payload.get("extra") or {}
        payload = payload["detect"]
    else:
        extra_top = {}
    model, cfg = build_model(payload, path, device)
    model.eval()
    return Checkpoint(model=model, model_config=cfg, class_ids=list(payload["class_ids"]),
                      objects=payload["objects"], num_points=int(payload["num_points"]), step=int(payload["step"]),
                      extra=payload.get("extra") or {}, normalisation=payload.get("normalisation") or {},
                      pose_net=pose_net, pose=pose, pose_config=dict(extra_top.get("pose_config") or {}))


def save_two_stage(path: str | Path, detect: dict, pose: dict, extra: dict | None = None) -> Path:
    """Write a two-stage model file (version 2) from a stage-1 checkpoint dict and a stage-2 part, without their
    training states (what inference needs only). extra: e.g. {"pose_config": {...}, "timing": ...}."""
    d = {k: v for k, v in detect.items() if k not in ("format", "version", "train_state")}
    p = {k: v for k, v in pose.items() if k != "train_state"}
    path = Path(path)
    atomic_torch_save({"format": FORMAT, "version": 2, "detect": d, "pose": p, "extra": extra or {}}, path)
    return path
