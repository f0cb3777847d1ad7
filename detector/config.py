"""The detector's settings: the presets (YAML files in ``detector/presets/``) and the strict loader.

Loading is :mod:`argen.settings`' (the same rules and ``--set`` syntax as argen's templates), with its errors
re-raised as :class:`detector.errors.DetectorError`. A preset file names the settings of one way to train:

- ``cpu.yaml`` and ``paper.yaml``: the paper's single network, ``model`` (ModelConfig values over its defaults,
  the paper's sizes) and ``train`` (TrainConfig values over its defaults, the cpu preset's);
- ``two-stage.yaml``: the default detector, sections ``stage1``, ``stage2``, ``pose`` and ``infer``
  (:mod:`detector.two_stage`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from argen import settings
from detector.errors import argen_errors

PRESETS_DIR = Path(__file__).resolve().parent / "presets"
#: The presets of the paper's single network (each with a ``model`` and a ``train`` section).
NETWORK_PRESETS = ("cpu", "paper")


def available_presets() -> list[str]:
    """Names of the preset files."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def load_preset(name: str) -> dict[str, Any]:
    """The sections of preset ``name`` (``detector/presets/NAME.yaml``); KeyError for an unknown name."""
    path = PRESETS_DIR / f"{name}.yaml"
    if not path.is_file():
        raise KeyError(f"unknown preset '{name}' (available: {', '.join(available_presets())})")
    with argen_errors():
        return settings.load_yaml(path, "preset")


def config_from_dict(cls: type, data: Any, where: str = "config") -> Any:
    """Build dataclass ``cls`` strictly from a mapping (:func:`argen.settings.from_dict`): unknown keys and wrong
    types are DetectorErrors."""
    with argen_errors():
        return settings.from_dict(cls, data, where)


def config_to_dict(cfg: Any) -> dict:
    """Plain nested dict of a config dataclass (for YAML and checkpoints)."""
    return settings.to_dict(cfg)


def set_dotted(data: dict, key: str, value: Any, open_sections: tuple[str, ...] = ("model",)) -> None:
    """Set ``data["loss"]["w_conf"] = value`` for key ``"loss.w_conf"`` (keys under ``model`` may be new: the model
    preset checks them)."""
    with argen_errors():
        settings.set_dotted(data, key, value, open_sections)


def parse_set_options(pairs: list[str] | None) -> dict[str, Any]:
    """``["lr=1e-3", "loss.w_conf=2"]`` -> ``{"lr": 0.001, "loss.w_conf": 2}`` (:func:`argen.settings.parse_sets`)."""
    with argen_errors():
        return settings.parse_sets(pairs)


def apply_set_options(cfg: Any, dotted: dict[str, Any], where: str = "--set") -> Any:
    """A copy of the settings dataclass ``cfg`` with ``{"key": value}`` overrides applied and checked
    (:func:`argen.settings.apply_sets`: an unknown key or a value of the wrong type is a DetectorError)."""
    with argen_errors():
        return settings.apply_sets(cfg, dotted, where)


def load_yaml(path: str | Path, what: str = "config file") -> dict:
    """The mapping in a YAML file; a missing file or bad YAML is a DetectorError."""
    with argen_errors():
        return settings.load_yaml(path, what)
