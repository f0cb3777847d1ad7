"""The learning-rate schedule both trainers use: linear (or, for ``onecycle``, cosine) warm-up, then cosine
decay, one-cycle or constant. ``cfg`` is any config with ``schedule``, ``warmup_steps`` and ``min_lr_ratio``."""

from __future__ import annotations

import math



def lr_factor(step: int, total: int, cfg) -> float:
    """Learning-rate multiplier at ``step`` (0-based) of ``total``: warm-up, then the schedule's decay."""
    warm = min(cfg.warmup_steps, max(total - 1, 0))
    if cfg.schedule == "onecycle":  # cosine ramp from lr/25 to lr, cosine decay to lr/1e4 (torch OneCycleLR shape)
        lo, end = 1 / 25, 1e-4
        if step < warm:
            return lo + (1 - lo) * 0.5 * (1 - math.cos(math.pi * step / warm))
        frac = (step - warm) / max(total - warm, 1)
        return end + (1 - end) * 0.5 * (1 + math.cos(math.pi * min(frac, 1.0)))
    if step < warm:
        return (step + 1) / (warm + 1)
    if cfg.schedule == "constant":
        return 1.0
    frac = (step - warm) / max(total - warm, 1)
    return cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * min(frac, 1.0)))
