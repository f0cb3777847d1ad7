"""Checkpoint files as both trainers write and read them: a ``torch.save`` dict of plain values and tensors only,
read back with ``torch.load(weights_only=True)`` (no pickled code runs when a file is loaded), written atomically
(temp file + rename).

Version 1 holds one network (stage 1 or the paper's single-shot network, :func:`save_checkpoint`). Version 3 holds
the parts of a two-stage model: ``stage1`` (the version-1 keys), ``stage2`` (the crop network,
:func:`detector.stage2.train.stage2_payload`) and ``extra`` with the inference settings chosen at training time
(``geometry_config``: e.g. the score threshold); a stage-2 run's own ``last.pt`` is version 3 with ``stage2`` only.
Version 2 is version 3 under older names (``detect``, ``pose``, ``pose_config``): :func:`read_checkpoint` renames
them on load (:func:`rename_old_keys`), so model files and run folders written before keep working.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from argen.fileio import atomic_path
from detector.errors import DetectorError, argen_errors


FORMAT = "detector-checkpoint"
VERSION = 1  # one network
TWO_STAGE_VERSION = 3  # a two-stage model, or a stage-2 run's checkpoint
VERSIONS = (1, 2, 3)  # 2: version 3 under the older key names (OLD_KEYS)
#: Version 2's names of version 3's keys: at the top of the file, and in its ``extra``.
OLD_KEYS = {"detect": "stage1", "pose": "stage2"}
OLD_EXTRA_KEYS = {"pose_config": "geometry_config"}


def rename_old_keys(payload: dict) -> dict:
    """A version-2 checkpoint dict with version 3's key names (``detect`` -> ``stage1``, ``pose`` -> ``stage2``,
    ``extra.pose_config`` -> ``extra.geometry_config``); other versions unchanged. The values are not copied."""
    if payload.get("version") != 2:
        return payload
    out = {OLD_KEYS.get(k, k): v for k, v in payload.items()}
    if isinstance(out.get("extra"), dict):
        out["extra"] = {OLD_EXTRA_KEYS.get(k, k): v for k, v in out["extra"].items()}
    out["version"] = TWO_STAGE_VERSION
    return out


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
    """The checkpoint dict, checked to be ours, with version 2's keys renamed (:func:`rename_old_keys`); a missing or
    foreign file is a :class:`DetectorError`."""
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
    return rename_old_keys(payload)
