"""The number format the networks compute in at inference (``detector eval`` / ``predict --net-dtype``).

``float32`` runs both stages' networks as they trained. ``bfloat16`` runs them under torch's CPU autocast: their
linear layers and convolutions in bfloat16 (8 significant bits), and with them the element-wise steps and max-pools
between those layers (LayerNorm and GroupNorm compute their statistics in float32 and return bfloat16; stage 2's
neighbour distances stay float32); the outputs are read back as float32 or float64. On a CPU that multiplies
bfloat16 in hardware (x86's AVX512_BF16 or AMX_BF16) the networks take about a fifth less time than in float32; on
one without it they are slower. ``auto`` picks bfloat16 on such a CPU and float32 everywhere else (a GPU included:
not measured there). The geometry (voting, RANSAC, ICP, the checks) stays in float64 either way; BENCHMARKS.md and
RESULTS.md give the time and accuracy of each.
"""

from __future__ import annotations

import contextlib
from functools import lru_cache
from pathlib import Path

import torch

from detector.errors import DetectorError

#: The values ``--net-dtype`` takes.
NET_DTYPES = ("auto", "float32", "bfloat16")
#: /proc/cpuinfo flags of x86 CPUs that multiply bfloat16 in hardware.
BF16_FLAGS = frozenset({"avx512_bf16", "amx_bf16"})


def cpu_flags(cpuinfo: str) -> set[str]:
    """The feature flags of the first processor in a /proc/cpuinfo text (x86's ``flags`` line); empty if none."""
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags":
            return set(value.split())
    return set()


@lru_cache(maxsize=1)
def native_bfloat16() -> bool:
    """Whether this CPU multiplies bfloat16 in hardware (:data:`BF16_FLAGS`, read from /proc/cpuinfo: Linux on x86
    only; False elsewhere, where ``auto`` keeps float32)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return bool(cpu_flags(text) & BF16_FLAGS)


def _device_type(device: str | torch.device) -> str:
    try:
        return torch.device(device).type
    except (RuntimeError, TypeError, ValueError):
        raise DetectorError(f"--device {device}: not a torch device (e.g. cpu, cuda)") from None


def resolve_net_dtype(name: str, device: str | torch.device = "cpu") -> str:
    """``float32`` or ``bfloat16`` for ``name`` (one of :data:`NET_DTYPES`) on ``device``: ``auto`` is bfloat16
    on a CPU with :func:`native_bfloat16`, else float32. bfloat16 on a GPU is refused (autocast here is the CPU's)."""
    if name not in NET_DTYPES:
        raise DetectorError(f"--net-dtype must be one of {', '.join(NET_DTYPES)}, got {name!r}")
    if name == "auto":
        return "bfloat16" if _device_type(device) == "cpu" and native_bfloat16() else "float32"
    check_net_dtype(name, device)
    return name


def check_net_dtype(net_dtype: str, device: str | torch.device = "cpu") -> None:
    """A DetectorError unless ``net_dtype`` is a resolved format (float32 or bfloat16) that runs on ``device``
    (bfloat16: the CPU only)."""
    if net_dtype not in ("float32", "bfloat16"):
        raise DetectorError(f"net_dtype must be float32 or bfloat16 once resolved, got {net_dtype!r}")
    if net_dtype == "bfloat16" and _device_type(device) != "cpu":
        raise DetectorError(f"--net-dtype bfloat16 runs on the CPU only, not on {device}")


def net_autocast(net_dtype: str):
    """The context a network's forward runs in for a resolved ``net_dtype`` (:func:`check_net_dtype`): CPU
    autocast to bfloat16, or nothing for float32. Its outputs may be bfloat16: read them with ``.float()``."""
    check_net_dtype(net_dtype)
    return torch.autocast("cpu", dtype=torch.bfloat16) if net_dtype == "bfloat16" else contextlib.nullcontext()
