"""Stage 2's network: per-point foreground and model coordinates in an object-centred crop.

Input: a crop (B, n, 9) from :func:`detector.stage2.crops.crop_input` and the class index of each crop (B,). The
class enters as a one-hot feature and picks the output head, so one network serves all objects. Layers:
a per-point MLP, two edge-convolutions over the k nearest neighbours in the crop (``relu(LN(max_j W [x_i, x_j -
x_i]))`` over the neighbours j of i), a global max-pooled feature concatenated to every point, and a per-point MLP
to per-class outputs: a foreground logit and 3 model coordinates (units of the diameter). The same code runs
on CPU and CUDA (the neighbour search is a batched torch top-k).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from detector.errors import DetectorError


@dataclass
class CropNetConfig:
    """Widths of the stage-2 network. width: first per-point width; k: neighbours per edge-convolution."""

    width: int = 64
    edge_width: int = 128
    global_width: int = 128
    head_width: int = 128
    k: int = 12

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "CropNetConfig":
        """From :meth:`to_dict`'s mapping. Model files of the edge-convolution's first design, which normalised
        before the max, are refused; the files written since store ``norm_before_max: false`` (checkpoints/lm8.pt),
        which is this network."""
        d = dict(d)
        if d.pop("norm_before_max", False):
            raise DetectorError("the stage-2 network normalises before the max (norm_before_max): a design this "
                                "detector no longer runs")
        return cls(**d)


def knn(xyz: torch.Tensor, k: int) -> torch.Tensor:
    """Indices (B, n, k) of each point's k nearest points (itself included) in xyz (B, n, 3)."""
    d = torch.cdist(xyz, xyz)
    # unsorted: the same neighbours, in an order nothing depends on at inference (the max over them is a max);
    # training keeps the sorted order, whose first neighbour wins a tie in _NeighbourMax's backward
    return d.topk(min(k, xyz.shape[1]), dim=-1, largest=False, sorted=torch.is_grad_enabled()).indices


class EdgeConv(nn.Module):
    """``relu(LN(max_j (W1 x_i + W2 (x_j - x_i))))`` over the neighbours j of i; the linear map is applied before
    the gather (``(W1 - W2) x_i + W2 x_j``), so only the neighbours' max of ``W2 x_j`` is needed. Without gradients
    (inference) the max is a running maximum over the k neighbour slices (B, n, out): no (B, n, k, out) tensor, and
    several times faster on a CPU than a gather and a max over that tensor's neighbour axis. Training does the same
    with :class:`_NeighbourMax`, which also keeps which neighbour won for the backward."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.self_lin = nn.Linear(c_in, c_out)
        self.nb_lin = nn.Linear(c_in, c_out, bias=False)
        self.norm = nn.LayerNorm(c_out)

    def forward(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        B, n, k = idx.shape
        b = self.nb_lin(x)  # (B, n, out)
        a = self.self_lin(x) - b
        flat = b.reshape(B * n, -1)
        rows = idx + (torch.arange(B, device=idx.device) * n)[:, None, None]  # (B, n, k) rows of flat
        if torch.is_grad_enabled():
            return torch.relu(self.norm(a + _NeighbourMax.apply(flat, rows.reshape(B * n, k)).reshape(B, n, -1)))
        # inference: a running maximum over the k neighbour slices, the same values several times faster on a CPU
        # (index_select on a neighbour's column of row numbers: twice as fast as indexing with it)
        cols = rows.reshape(B * n, k).t().contiguous()  # (k, B*n)
        m = flat.index_select(0, cols[0])
        for j in range(1, k):
            torch.maximum(m, flat.index_select(0, cols[j]), out=m)
        return torch.relu(self.norm(a + m.reshape(B, n, -1)))


class _NeighbourMax(torch.autograd.Function):
    """``out[i] = max_j b[rows[i, j]]`` per channel, for training: the forward is a running maximum over the k
    neighbour columns that remembers which column won each channel (uint8), and the backward adds each output
    gradient to the winning row. The same values and gradients as a gather to (M, k, C) followed by a max over k
    (ties go to the first neighbour in both), without that tensor, the zeros of its max's backward, or the scatter
    of its gather's backward: the edge-convolutions' share of a training step falls several times on a CPU.

    b: (R, C) the rows' features; rows: (M, k) int64 row indices into b. Returns (M, C)."""

    @staticmethod
    def forward(ctx, b: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        m = b.index_select(0, rows[:, 0])
        won = torch.zeros(m.shape, dtype=torch.uint8, device=b.device)
        for j in range(1, rows.shape[1]):
            cand = b.index_select(0, rows[:, j])
            won.masked_fill_(cand > m, j)
            torch.maximum(m, cand, out=m)
        ctx.save_for_backward(rows, won)
        ctx.num_rows = b.shape[0]
        return m

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        rows, won = ctx.saved_tensors
        out = torch.zeros(ctx.num_rows, grad.shape[1], dtype=grad.dtype, device=grad.device)
        out.scatter_add_(0, rows.gather(1, won.long()), grad.contiguous())
        return out, None


def mlp(sizes: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(a, b), nn.LayerNorm(b), nn.ReLU()]
    return nn.Sequential(*layers)


class CropNet(nn.Module):
    """Foreground logits and model coordinates of the points of object-centred crops (see module doc)."""

    def __init__(self, cfg: CropNetConfig, num_classes: int):
        super().__init__()
        self.cfg, self.num_classes = cfg, num_classes
        w, e, g, h = cfg.width, cfg.edge_width, cfg.global_width, cfg.head_width
        self.point = mlp([9 + num_classes, w, w])
        self.edge1 = EdgeConv(w, w)
        self.edge2 = EdgeConv(w, e)
        self.glob = mlp([w + w + e, g])
        self.head = nn.Sequential(mlp([w + w + e + g, h, h // 2]), nn.Linear(h // 2, 4 * num_classes))

    def forward(self, features: torch.Tensor, cls: torch.Tensor) -> dict[str, torch.Tensor]:
        """features: (B, n, 9) crop input; cls: (B,) int64 class index in [0, num_classes). Returns
        {"fg_logit": (B, n), "coords": (B, n, 3) model coordinates in diameters} of each crop's class."""
        B, n, _ = features.shape
        onehot = nn.functional.one_hot(cls, self.num_classes).to(features.dtype)
        x0 = self.point(torch.cat([features, onehot[:, None, :].expand(-1, n, -1)], dim=-1))
        idx = knn(features[..., :3], self.cfg.k)
        x1 = self.edge1(x0, idx)
        x2 = self.edge2(x1, idx)
        local = torch.cat([x0, x1, x2], dim=-1)
        gfeat = self.glob(local).max(dim=1).values  # (B, g)
        # the head's first layer on [local, gfeat]: the global columns once a crop, not once a point (the same map)
        first, c = self.head[0][0], local.shape[-1]
        h = nn.functional.linear(local, first.weight[:, :c]) + \
            nn.functional.linear(gfeat, first.weight[:, c:], first.bias)[:, None, :]
        out = self.head[1](self.head[0][1:](h))  # (B, n, 4C)
        out = out.reshape(B, n, self.num_classes, 4)
        pick = out[torch.arange(B, device=out.device), :, cls]  # (B, n, 4)
        return {"fg_logit": pick[..., 0], "coords": pick[..., 1:]}


def crop_loss(out: dict[str, torch.Tensor], fg: torch.Tensor, coords: torch.Tensor, sym_mask: torch.Tensor,
              w_coord: float = 5.0, beta: float = 0.02) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Stage-2 loss: BCE on foreground + smooth-L1 on foreground model coordinates, minimum over symmetries.

    out: the network output; fg: (B, n) float 0/1; coords: (B, S, n, 3) targets in diameters under each of up to
    S symmetries; sym_mask: (B, S) bool, which symmetries are real (padding is False); beta: smooth-L1 knee
    (diameters). The coordinate term of a crop is the mean over its foreground points, taking the symmetry that
    fits the prediction best (so a symmetric object is not pulled toward the mean of its equivalent poses).
    Returns the total and its parts {"fg", "coord"}.
    """
    bce = nn.functional.binary_cross_entropy_with_logits(out["fg_logit"], fg)
    err = nn.functional.smooth_l1_loss(out["coords"][:, None].expand_as(coords), coords, beta=beta,
                                       reduction="none").sum(-1)  # (B, S, n)
    per = (err * fg[:, None]).sum(-1) / fg.sum(-1, keepdim=True).clamp(min=1.0)  # (B, S)
    per = per.masked_fill(~sym_mask, float("inf")).min(dim=1).values
    has_fg = fg.sum(-1) > 0
    coord = per[has_fg].mean() if has_fg.any() else per.sum() * 0.0
    return bce + w_coord * coord, {"fg": bce.detach(), "coord": coord.detach()}


def build_stage2_net(part: dict, where: str, device: torch.device | str = "cpu") -> CropNet:
    """The CropNet of a checkpoint's stage-2 part with its weights; a mismatch is a :class:`DetectorError`."""
    try:
        net = CropNet(CropNetConfig.from_dict(part["net_config"]), len(part["class_ids"]))
        net.load_state_dict(part["model_state"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DetectorError(f"{where}: the stage-2 weights do not match their config ({first})") from None
    return net.to(device)
