"""Stage 1's network, the paper's multi-task PointNet++ (:class:`PointNet2`): an input SA stage, 4 SA and 4 FP layers,
three per-keypoint heads.

Shapes (B batch, N input points, K keypoints of the input SA stage, C object classes):

- input ``features`` (B, N, 9) float32 ``[X, Y, Z, R, G, B, Nx, Ny, Nz]``, camera metres;
- output ``keypoints`` (B, K) int64 rows of the input (= ``indices["sample_0"]``), ``xyz`` (B, K, 3) metres,
  ``logits`` (B, K, C+1) (class 0 = background), ``offsets`` (B, K, 9, 3) metres (control point =
  ``xyz[:, :, None] + offsets``), ``confidence`` (B, K) in [0, 1].

Presets (:func:`preset`):

- ``paper``: the paper's sizes. Input SA stage [K_s, R_s, N_s, C_s] = [4096, 0.05 m, 128, 32]; SA layers
  with 1024, 512, 256, 128 centroids, radii 0.1, 0.15, 0.2, 0.25 m, 32 neighbours, output channels 64,
  128, 256, 512; FP layers back to 256, 512, 1024, 4096 points with 512, 512, 256, 256 channels; heads on
  the 4096 x 256 features. Not given by the paper, chosen here: the shared MLPs are PointNet++ SSG style
  (two hidden layers of half the output width, e.g. 32-32-64), FP MLPs have two layers of the output width,
  each head has one hidden layer of 128. Meant for 16384 input points. 2,061,054 parameters
  (C = 1; 2,061,183 for C = 2).
- ``cpu``: the same architecture made smaller to train on a 2-core CPU: 1024 keypoints from 4096 input
  points (R_s 0.05 m, 32 neighbours, C_s 32), SA centroids 256, 128, 64, 32 (same radii, 16 neighbours),
  channels 64, 128, 192, 256, FP widths 256, 192, 128, 128, heads of 64 hidden units.
  545,310 parameters (C = 1). About 0.2 s per forward+backward step at batch 4 on 2 CPU threads
  (bench/bench_model.py), so 200 steps take about a minute plus data loading.

Normalisation is GroupNorm (the paper's batch of 4 is small, and train and eval then behave the same).
Inside the model, the per-point input features are the coordinates minus the cloud's centroid plus
colour and normal; grouped neighbour coordinates are relative to their centroid and divided by the radius.
Offsets are predicted in units of ``offset_scale`` metres and returned in metres.

Each SA layer gathers, around each sampled centroid, the neighbours' relative coordinates and features,
applies a shared MLP (1x1 conv + norm + ReLU) and max-pools over the neighbours. Each FP layer
interpolates the coarser level's features onto the finer level (3-NN inverse distance), concatenates the
finer level's own features (skip) and applies a shared MLP. Sampling and neighbour indices come from the
data loader (:func:`detector.stage1.ops.precompute_indices`, batched) or, when ``indices`` is None, are computed
in torch on the model's device (:func:`detector.stage1.ops.compute_indices_torch`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import nn

from detector.config import NETWORK_PRESETS, load_preset
from detector.errors import DetectorError
from detector.stage1.ops import compute_indices_torch, gather, group, three_interpolate


NUM_CONTROL_POINTS = 9


@dataclass
class ModelConfig:
    """Sizes of a PointNet2; level l of ``npoints``/``radii``/``nsamples``/``sa_mlps`` is SA layer l (0 = input stage)."""

    in_channels: int = 9
    npoints: list[int] = dataclasses.field(default_factory=lambda: [4096, 1024, 512, 256, 128])
    radii: list[float] = dataclasses.field(default_factory=lambda: [0.05, 0.1, 0.15, 0.2, 0.25])
    nsamples: list[int] = dataclasses.field(default_factory=lambda: [128, 32, 32, 32, 32])
    sa_mlps: list[list[int]] = dataclasses.field(
        default_factory=lambda: [[16, 16, 32], [32, 32, 64], [64, 64, 128], [128, 128, 256], [256, 256, 512]])
    fp_mlps: list[list[int]] = dataclasses.field(
        default_factory=lambda: [[512, 512], [512, 512], [256, 256], [256, 256]])
    head_channels: int = 128
    norm: str = "gn"  # gn (GroupNorm) | bn (BatchNorm)
    offset_scale: float = 0.1  # metres per unit of the offset head's output
    centre_input: bool = True  # subtract the cloud's centroid from the input coordinates features

    def __post_init__(self) -> None:
        self.npoints = [int(v) for v in self.npoints]
        self.radii = [float(v) for v in self.radii]
        self.nsamples = [int(v) for v in self.nsamples]
        self.sa_mlps = [[int(c) for c in m] for m in self.sa_mlps]
        self.fp_mlps = [[int(c) for c in m] for m in self.fp_mlps]
        levels = len(self.npoints)
        if levels < 2 or not (len(self.radii) == len(self.nsamples) == len(self.sa_mlps) == levels):
            raise ValueError("npoints, radii, nsamples and sa_mlps need one entry per SA level (at least 2)")
        if len(self.fp_mlps) != levels - 1:
            raise ValueError(f"fp_mlps needs {levels - 1} entries (one per SA level after the input stage)")
        if any(b > a for a, b in zip(self.npoints, self.npoints[1:])) or min(self.npoints) < 1:
            raise ValueError("npoints must be positive and non-increasing")
        if min(self.radii) <= 0 or min(self.nsamples) < 1 or self.in_channels < 3:
            raise ValueError("radii and nsamples must be positive and in_channels at least 3")
        if any(not m or min(m) < 1 for m in self.sa_mlps + self.fp_mlps) or self.head_channels < 1:
            raise ValueError("every MLP needs at least one layer of positive width")
        if self.norm not in ("gn", "bn"):
            raise ValueError(f"norm must be 'gn' or 'bn', got '{self.norm}'")

    def sampling_specs(self) -> list[tuple[int, float, int]]:
        """(npoint, radius, nsample) per SA level, for :mod:`detector.stage1.ops`."""
        return list(zip(self.npoints, self.radii, self.nsamples))

    def to_dict(self) -> dict:
        """Plain dict (YAML / checkpoint friendly)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "ModelConfig":
        """Inverse of :meth:`to_dict`; TypeError for an unknown key, ValueError for inconsistent sizes."""
        return cls(**data)


def preset(name: str) -> ModelConfig:
    """The ModelConfig of a named preset: ``paper`` or ``cpu`` (``detector/presets/NAME.yaml``'s ``model``
    section over the defaults; see the module docstring); KeyError otherwise."""
    if name not in NETWORK_PRESETS:
        raise KeyError(f"unknown model preset '{name}' (available: {', '.join(NETWORK_PRESETS)})")
    return ModelConfig(**(load_preset(name)["model"] or {}))


def norm_layer(kind: str, channels: int, dims: int) -> nn.Module:
    """GroupNorm (about 4+ channels per group, at most 32 groups) or BatchNorm over 1D/2D maps."""
    if kind == "bn":
        return nn.BatchNorm2d(channels) if dims == 2 else nn.BatchNorm1d(channels)
    groups = max(1, min(32, channels // 4))
    while channels % groups:
        groups -= 1
    return nn.GroupNorm(groups, channels)


def shared_mlp(in_ch: int, widths: list[int], norm: str, dims: int) -> nn.Sequential:
    """1x1 convolutions (no bias) + norm + ReLU, over (B, C, S) (dims 1) or (B, C, S, k) (dims 2) maps."""
    conv = nn.Conv2d if dims == 2 else nn.Conv1d
    layers: list[nn.Module] = []
    for c in widths:
        layers += [conv(in_ch, c, 1, bias=False), norm_layer(norm, c, dims), nn.ReLU(inplace=True)]
        in_ch = c
    return nn.Sequential(*layers)


class SetAbstraction(nn.Module):
    """Sample centroids, group neighbours (relative xyz / radius + features), shared MLP, max-pool."""

    def __init__(self, in_ch: int, widths: list[int], radius: float, norm: str):
        super().__init__()
        self.radius = radius
        self.mlp = shared_mlp(in_ch + 3, widths, norm, dims=2)

    def forward(self, xyz: torch.Tensor, feats: torch.Tensor, sample: torch.Tensor, grp: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """xyz (B, n, 3) metres, feats (B, n, C), sample (B, S), grp (B, S, k) -> new xyz (B, S, 3), feats (B, S, C')."""
        new_xyz = gather(xyz, sample)
        rel = (group(xyz, grp) - new_xyz[:, :, None]) / self.radius
        x = torch.cat([rel, group(feats, grp)], dim=-1).permute(0, 3, 1, 2)  # (B, 3+C, S, k)
        return new_xyz, self.mlp(x).amax(dim=-1).transpose(1, 2)


class FeaturePropagation(nn.Module):
    """3-NN inverse-distance interpolation of coarse features onto finer points, skip concat, shared MLP."""

    def __init__(self, coarse_ch: int, skip_ch: int, widths: list[int], norm: str):
        super().__init__()
        self.mlp = shared_mlp(coarse_ch + skip_ch, widths, norm, dims=1)

    def forward(self, coarse: torch.Tensor, skip: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """coarse (B, m, C2), skip (B, n, C1), idx/w (B, n, 3) -> (B, n, C')."""
        x = torch.cat([three_interpolate(coarse, idx, w), skip], dim=-1).transpose(1, 2)
        return self.mlp(x).transpose(1, 2)


def head(in_ch: int, hidden: int, out_ch: int, norm: str) -> nn.Sequential:
    """Per-keypoint head: 1x1 conv + norm + ReLU, then a 1x1 conv to ``out_ch`` over (B, C, K)."""
    return nn.Sequential(*shared_mlp(in_ch, [hidden], norm, dims=1), nn.Conv1d(hidden, out_ch, 1))


class PointNet2(nn.Module):
    """Multi-task PointNet++: per keypoint class logits, 9 control-point offsets and a confidence."""

    def __init__(self, cfg: ModelConfig, num_classes: int):
        super().__init__()
        if num_classes < 1:
            raise DetectorError(f"PointNet2 needs at least one object class, got {num_classes}")
        self.cfg, self.num_classes = cfg, num_classes
        self.specs = cfg.sampling_specs()
        chans = [cfg.in_channels]
        self.sa = nn.ModuleList()
        for widths, radius in zip(cfg.sa_mlps, cfg.radii):
            self.sa.append(SetAbstraction(chans[-1], widths, radius, cfg.norm))
            chans.append(widths[-1])
        # chans[l + 1] = channels of level l + 1; FP j goes from level L - j to level L - 1 - j
        self.fp = nn.ModuleList()
        coarse = chans[-1]
        for j, widths in enumerate(cfg.fp_mlps):
            self.fp.append(FeaturePropagation(coarse, chans[len(cfg.npoints) - 1 - j], widths, cfg.norm))
            coarse = widths[-1]
        self.cls_head = head(coarse, cfg.head_channels, num_classes + 1, cfg.norm)
        self.offset_head = head(coarse, cfg.head_channels, NUM_CONTROL_POINTS * 3, cfg.norm)
        self.conf_head = head(coarse, cfg.head_channels, 1, cfg.norm)

    def check_inputs(self, features: torch.Tensor, indices: dict | None) -> None:
        """DetectorError (one line) for features that are not (B, N >= K_s, in_channels) float32 or bad indices."""
        cfg = self.cfg
        if not isinstance(features, torch.Tensor):
            raise DetectorError(f"features must be a torch.Tensor, got {type(features).__name__}")
        if features.dim() != 3 or features.shape[-1] != cfg.in_channels:
            raise DetectorError(f"features must have shape (B, N, {cfg.in_channels}), got {tuple(features.shape)}")
        if features.dtype != torch.float32:
            raise DetectorError(f"features must be float32, got {features.dtype}")
        if features.shape[1] < cfg.npoints[0]:
            raise DetectorError(f"the model samples {cfg.npoints[0]} keypoints but the cloud has only "
                                f"{features.shape[1]} points")
        if indices is None:
            return
        bsz = features.shape[0]
        for key, shape in self.index_shapes(features.shape[1]).items():
            if key not in indices:
                raise DetectorError(f"indices lack '{key}' (expected the keys of detector.stage1.ops.precompute_indices)")
            got = indices[key]
            if tuple(got.shape) != (bsz, *shape):
                raise DetectorError(f"indices['{key}'] must have shape {(bsz, *shape)}, got {tuple(got.shape)}")
            if not key.endswith("_w") and got.dtype != torch.int64:
                raise DetectorError(f"indices['{key}'] must be int64, got {got.dtype}")

    def index_shapes(self, num_points: int) -> dict[str, tuple[int, ...]]:
        """Expected per-cloud shape of every index array (see :func:`detector.stage1.ops.precompute_indices`)."""
        shapes: dict[str, tuple[int, ...]] = {}
        for level, (npoint, _, nsample) in enumerate(self.specs):
            shapes[f"sample_{level}"] = (npoint,)
            shapes[f"group_{level}"] = (npoint, nsample)
        for level in range(1, len(self.specs)):
            shapes[f"interp_{level}_idx"] = shapes[f"interp_{level}_w"] = (self.specs[level - 1][0], 3)
        return shapes

    def forward(self, features: torch.Tensor, indices: dict[str, torch.Tensor] | None = None
                ) -> dict[str, torch.Tensor]:
        """features (B, N, 9) float32 metres; indices: batched precompute_indices arrays or None (computed here).

        Returns keypoints (B, K) int64, xyz (B, K, 3), logits (B, K, C+1), offsets (B, K, 9, 3) metres,
        confidence (B, K) in [0, 1].
        """
        self.check_inputs(features, indices)
        xyz = features[..., :3]
        if indices is None:
            indices = compute_indices_torch(xyz.detach(), self.specs)
        centre = xyz.mean(dim=1, keepdim=True) if self.cfg.centre_input else torch.zeros_like(xyz[:, :1])
        levels_xyz, levels_feat = [xyz], [torch.cat([xyz - centre, features[..., 3:]], dim=-1)]
        for level, sa in enumerate(self.sa):
            new_xyz, feats = sa(levels_xyz[-1], levels_feat[-1], indices[f"sample_{level}"], indices[f"group_{level}"])
            levels_xyz.append(new_xyz)
            levels_feat.append(feats)
        x = levels_feat[-1]
        for j, fp in enumerate(self.fp):
            level = len(self.sa) - 1 - j
            x = fp(x, levels_feat[level], indices[f"interp_{level}_idx"], indices[f"interp_{level}_w"])
        h = x.transpose(1, 2)  # (B, C, K)
        bsz, k = h.shape[0], h.shape[2]
        offsets = self.offset_head(h).transpose(1, 2).reshape(bsz, k, NUM_CONTROL_POINTS, 3) * self.cfg.offset_scale
        return {"keypoints": indices["sample_0"], "xyz": levels_xyz[1], "logits": self.cls_head(h).transpose(1, 2),
                "offsets": offsets, "confidence": torch.sigmoid(self.conf_head(h)).squeeze(1)}
