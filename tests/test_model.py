"""detector.stage1.network: shapes and frames of the outputs, both index paths, learning on one cloud, input errors."""

import dataclasses

import numpy as np
import pytest
import torch

from detector.errors import DetectorError
from detector.stage1.loss import LossConfig, multitask_loss
from detector.stage1.network import ModelConfig, PointNet2, preset
from detector.stage1.ops import precompute_indices

torch.set_num_threads(1)

TINY = ModelConfig(npoints=[64, 32, 16], radii=[0.1, 0.2, 0.4], nsamples=[8, 8, 8],
                   sa_mlps=[[8, 16], [16, 32], [32, 32]], fp_mlps=[[32], [32]], head_channels=16)


def scene(n: int = 256, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A table plane with a 10 cm cube on it 1 m in front of the camera: features (n, 9), cls (n,), cps (n, 9, 3)."""
    rng = np.random.default_rng(seed)
    m = n // 4
    plane = np.c_[rng.uniform(-0.3, 0.3, (n - m, 2)), np.zeros(n - m)]
    cube = rng.uniform(-0.05, 0.05, (m, 3)) + [0.1, 0.0, -0.05]
    xyz = np.r_[plane, cube] + [0.0, 0.0, 1.0]
    rgb = np.r_[np.tile([0.2, 0.2, 0.2], (n - m, 1)), np.tile([0.8, 0.1, 0.1], (m, 1))]
    normals = np.tile([0.0, 0.0, -1.0], (n, 1))
    feats = np.c_[xyz, rgb, normals].astype(np.float32)
    cls = np.r_[np.zeros(n - m), np.ones(m)].astype(np.int64)
    corners = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05) for z in (-0.05, 0.05)] + [[0, 0, 0]])
    cps = np.zeros((n, 9, 3), np.float32)
    cps[cls == 1] = corners + [0.1, 0.0, 0.95]
    return feats, cls, cps


def batch_indices(feats: np.ndarray, cfg: ModelConfig) -> dict[str, torch.Tensor]:
    per = [precompute_indices(f[:, :3], cfg.sampling_specs()) for f in feats]
    return {k: torch.from_numpy(np.stack([p[k] for p in per])) for k in per[0]}


def two_clouds() -> torch.Tensor:
    return torch.from_numpy(np.stack([scene(seed=0)[0], scene(seed=1)[0]]))


def test_outputs_shapes_and_frames():
    torch.manual_seed(0)
    model = PointNet2(TINY, num_classes=3).eval()
    x = two_clouds()
    idx = batch_indices(x.numpy(), TINY)
    with torch.no_grad():
        out = model(x, idx)
    assert out["keypoints"].dtype == torch.int64 and torch.equal(out["keypoints"], idx["sample_0"])
    assert out["logits"].shape == (2, 64, 4) and out["offsets"].shape == (2, 64, 9, 3)
    assert torch.equal(out["xyz"], torch.gather(x[..., :3], 1, out["keypoints"][..., None].expand(-1, -1, 3)))
    assert ((out["confidence"] >= 0) & (out["confidence"] <= 1)).all()
    # camera metres: moving the cloud moves xyz by the same amount and leaves offsets and logits unchanged
    shift = torch.tensor([0.3, -0.2, 0.5])
    moved = x.clone()
    moved[..., :3] += shift
    with torch.no_grad():
        out2 = model(moved, idx)
    torch.testing.assert_close(out2["xyz"], out["xyz"] + shift)
    torch.testing.assert_close(out2["offsets"], out["offsets"], atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(out2["logits"], out["logits"], atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("norm", ["gn", "bn"])
def test_torch_indices_equal_precomputed_indices(norm):
    cfg = dataclasses.replace(TINY, norm=norm)
    torch.manual_seed(1)
    model = PointNet2(cfg, num_classes=1).eval()
    x = two_clouds()
    with torch.no_grad():
        a, b = model(x, batch_indices(x.numpy(), cfg)), model(x)
    assert torch.equal(a["keypoints"], b["keypoints"])
    for key in ("xyz", "logits", "offsets", "confidence"):
        torch.testing.assert_close(a[key], b[key], atol=1e-5, rtol=1e-4)


def test_overfits_one_cloud():
    feats, cls, cps = scene(seed=3)
    x = torch.from_numpy(feats)[None]
    idx = batch_indices(feats[None], TINY)
    kp = idx["sample_0"][0]
    target = {"cls": torch.from_numpy(cls)[kp][None], "control_points": torch.from_numpy(cps)[kp][None]}
    torch.manual_seed(2)
    model = PointNet2(TINY, num_classes=1)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(80):
        loss, parts = multitask_loss(model(x, idx), target, LossConfig())
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(parts["total"])
    model.eval()
    with torch.no_grad():
        out = model(x, idx)
    acc = (out["logits"].argmax(-1) == target["cls"]).float().mean()
    err = (out["xyz"][:, :, None] + out["offsets"] - target["control_points"]).norm(dim=-1).mean(-1)[target["cls"] > 0]
    assert min(losses[-5:]) < 0.2 * losses[0], losses[::10]
    zero = (out["xyz"][:, :, None] - target["control_points"]).norm(dim=-1).mean(-1)[target["cls"] > 0]
    assert acc == 1.0 and err.mean() < 0.4 * zero.mean(), (acc, err.mean(), zero.mean())


def test_bad_inputs_raise_detector_error():
    model = PointNet2(TINY, num_classes=1)
    x = two_clouds()
    idx = batch_indices(x.numpy(), TINY)
    with pytest.raises(DetectorError, match=r"shape \(B, N, 9\)"):
        model(x[..., :6])
    with pytest.raises(DetectorError, match="float32"):
        model(x.double())
    with pytest.raises(DetectorError, match="only 32 points"):
        model(x[:, :32])
    with pytest.raises(DetectorError, match="lack 'group_1'"):
        model(x, {k: v for k, v in idx.items() if k != "group_1"})
    with pytest.raises(DetectorError, match="sample_0"):
        model(x, {**idx, "sample_0": idx["sample_0"][:1]})
    with pytest.raises(DetectorError, match="int64"):
        model(x, {**idx, "group_0": idx["group_0"].int()})
    with pytest.raises(DetectorError, match="torch.Tensor"):
        model(x.numpy())


def test_presets_and_config_round_trip():
    paper = preset("paper")
    assert paper.sampling_specs() == [(4096, 0.05, 128), (1024, 0.1, 32), (512, 0.15, 32), (256, 0.2, 32),
                                      (128, 0.25, 32)]
    assert [m[-1] for m in paper.sa_mlps] == [32, 64, 128, 256, 512]
    assert [m[-1] for m in paper.fp_mlps] == [512, 512, 256, 256]
    cpu = preset("cpu")
    assert cpu.npoints[0] == 1024 and sum(p.numel() for p in PointNet2(cpu, 1).parameters()) < \
        sum(p.numel() for p in PointNet2(paper, 1).parameters())
    assert ModelConfig.from_dict(cpu.to_dict()) == cpu
    with pytest.raises(KeyError):
        preset("huge")
    with pytest.raises(TypeError):
        ModelConfig.from_dict({**cpu.to_dict(), "depth": 3})
    with pytest.raises(ValueError):
        ModelConfig.from_dict({**cpu.to_dict(), "fp_mlps": [[8]]})
