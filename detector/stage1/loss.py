"""The paper's multi-task loss: class cross-entropy, control-point regression and confidence.

    L = w_cls * CE(logits, cls) + w_offset * p* SmoothL1(offsets) + w_conf * p* MSE(confidence, target)

(CE weighs an object keypoint ``fg_weight`` times a background one; 1 by default, the paper's plain mean.)

``CE`` averages over all keypoints; ``p*`` averages over object keypoints only (cls > 0; zero when a batch
has none). The offset term compares predicted and true control points (equivalently offsets from the
keypoint) in units of ``offset_unit`` metres (0.1 m, so the terms are of the order of the CE term) with
SmoothL1 of ``beta`` units (0.1, i.e. quadratic below 1 cm), averaged over the 27 coordinates. The
confidence target is computed without gradient from d3D, the mean distance (metres) between a keypoint's 9
predicted and true control points: ``linear`` is ``clip(1 - d3D / d_th, 0, 1)`` (the score the paper
uses), ``exp`` the paper's Eq. score normalised to [0, 1]: ``(exp(alpha (1 - d3D / d_th)) - 1) /
(exp(alpha) - 1)`` for d3D < d_th, else 0 (d_th = 0.06 m, alpha = 2). ``seg_only`` trains the class
head alone (the paper's segmentation pre-training); the other parts are still reported. ``centre_only``
regresses only control point 8 (the box centre) and scores confidence on its distance: the loss of a two-stage
model's stage 1, which only has to find objects and their centres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from detector.errors import DetectorError


@dataclass
class LossConfig:
    """Weights and confidence target of the multi-task loss (distances in metres)."""

    w_cls: float = 1.0
    w_offset: float = 1.0
    w_conf: float = 5.0
    d_th: float = 0.06
    score: str = "linear"  # linear | exp
    alpha: float = 2.0
    seg_only: bool = False
    offset_unit: float = 0.1  # metres per unit of the SmoothL1 argument
    beta: float = 0.1  # SmoothL1 beta, in offset units
    centre_only: bool = False  # regress (and score confidence on) the box centre only: a two-stage model's stage 1
    fg_weight: float = 1.0  # an object keypoint's class cross-entropy weighs this many background ones (1: alike)

    def __post_init__(self) -> None:
        if self.score not in ("linear", "exp"):
            raise DetectorError(f"loss score must be 'linear' or 'exp', got '{self.score}'")
        if self.d_th <= 0 or self.offset_unit <= 0 or self.beta < 0:
            raise DetectorError("loss d_th and offset_unit must be positive and beta non-negative")
        if not self.fg_weight > 0:
            raise DetectorError(f"loss fg_weight must be positive, got {self.fg_weight}")


def confidence_target(d3d: torch.Tensor, d_th: float, score: str = "linear", alpha: float = 2.0) -> torch.Tensor:
    """Confidence target in [0, 1], 1 at d3D = 0 and 0 from d3D >= d_th.

    d3d: (...) mean control-point distance, metres. Returns (...) same dtype.
    """
    x = (1.0 - d3d / d_th).clamp(0.0, 1.0)
    if score == "linear":
        return x
    return torch.where(x > 0, torch.expm1(alpha * x) / math.expm1(alpha), torch.zeros_like(x))


def mean_control_point_distance(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """Mean Euclidean distance over the 9 control points.

    pred, true: (B, K, 9, 3) metres. Returns (B, K) metres.
    """
    return (pred - true).norm(dim=-1).mean(dim=-1)


def multitask_loss(out: dict, target: dict, cfg: LossConfig, pos_count: torch.Tensor | float | None = None
                   ) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss (scalar tensor) and its unweighted parts as floats: ``cls``, ``offset``, ``conf``, ``total``.

    out: PointNet2 output (``logits`` (B, K, C+1), ``xyz`` (B, K, 3), ``offsets`` (B, K, 9, 3) metres,
    ``confidence`` (B, K)); target: ``cls`` (B, K) int64 (0 = background), ``control_points`` (B, K, 9, 3) metres.
    pos_count: the object-keypoint count that divides the offset and confidence sums (default: this batch's;
    data-parallel training passes the global batch's count, at least 1, divided by the number of processes).
    """
    logits, cls = out["logits"], target["cls"].long()
    weight = None
    if cfg.fg_weight != 1:  # the weighted mean: sum of w_class * CE over the keypoints / sum of their w_class
        weight = torch.full((logits.shape[-1],), float(cfg.fg_weight), dtype=logits.dtype, device=logits.device)
        weight[0] = 1.0
    ce = F.cross_entropy(logits.reshape(-1, logits.shape[-1]), cls.reshape(-1), weight=weight)
    pos = (cls > 0).to(logits.dtype)
    n_pos = pos.sum().clamp(min=1.0) if pos_count is None else torch.as_tensor(pos_count, dtype=logits.dtype)
    true_offsets = target["control_points"].to(out["offsets"].dtype) - out["xyz"][:, :, None].detach()
    pred_offsets = out["offsets"]
    if cfg.centre_only:  # control point 8 is the centre
        pred_offsets, true_offsets = pred_offsets[:, :, 8:9], true_offsets[:, :, 8:9]
    sl1 = F.smooth_l1_loss(pred_offsets / cfg.offset_unit, true_offsets / cfg.offset_unit,
                           reduction="none", beta=cfg.beta).mean(dim=(-1, -2))  # (B, K)
    offset = (sl1 * pos).sum() / n_pos
    with torch.no_grad():
        d3d = mean_control_point_distance(pred_offsets, true_offsets)
        conf_target = confidence_target(d3d, cfg.d_th, cfg.score, cfg.alpha)
    conf = (((out["confidence"] - conf_target) ** 2) * pos).sum() / n_pos
    if cfg.seg_only:
        total = cfg.w_cls * ce
    else:
        total = cfg.w_cls * ce + cfg.w_offset * offset + cfg.w_conf * conf
    parts = {"cls": float(ce.detach()), "offset": float(offset.detach()), "conf": float(conf.detach()),
             "total": float(total.detach())}
    return total, parts
