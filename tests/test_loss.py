"""detector.stage1.loss: zero for a perfect prediction, hand-computed confidence targets, gradients only where due."""

import math

import pytest
import torch

from detector.errors import DetectorError
from detector.stage1.loss import LossConfig, confidence_target, multitask_loss

torch.set_num_threads(1)


def make_case(seed: int = 0, k: int = 12, classes: int = 2):
    """A batch of 2 x k keypoints, half of them object points, and a prediction equal to the target."""
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(2, k, 3, generator=g)
    cls = torch.randint(1, classes + 1, (2, k), generator=g)
    cls[:, : k // 2] = 0
    cps = xyz[:, :, None] + 0.1 * torch.randn(2, k, 9, 3, generator=g)
    cps[cls == 0] = 0.0  # background control points are zeros in the label files
    logits = torch.full((2, k, classes + 1), -30.0)
    logits.scatter_(-1, cls[..., None], 30.0)
    out = {"xyz": xyz, "logits": logits, "offsets": cps - xyz[:, :, None], "confidence": (cls > 0).float()}
    return out, {"cls": cls, "control_points": cps}


def leaf(out: dict) -> dict:
    return {k: v.clone().requires_grad_(v.is_floating_point()) for k, v in out.items()}


def test_perfect_prediction_gives_zero_loss():
    out, target = make_case()
    loss, parts = multitask_loss(out, target, LossConfig())
    assert loss.item() < 1e-6 and parts["total"] < 1e-6
    assert parts["offset"] < 1e-9 and parts["conf"] < 1e-9
    # a 1 cm error on every object control point gives the SmoothL1 value by hand, nothing from background
    out["offsets"] = out["offsets"] + 0.01 * (target["cls"] > 0)[..., None, None]
    _, parts = multitask_loss(out, target, LossConfig(offset_unit=0.1, beta=0.05))
    assert parts["offset"] == pytest.approx(0.1 - 0.5 * 0.05, rel=1e-4)  # |x| = 0.1 units > beta: |x| - beta/2


def test_confidence_target_hand_values():
    d = torch.tensor([0.0, 0.015, 0.03, 0.06, 0.09])
    lin = confidence_target(d, 0.06, "linear")
    assert torch.allclose(lin, torch.tensor([1.0, 0.75, 0.5, 0.0, 0.0]))
    e = confidence_target(d, 0.06, "exp", alpha=2.0)
    want = [1.0, (math.exp(1.5) - 1) / (math.exp(2) - 1), (math.e - 1) / (math.exp(2) - 1), 0.0, 0.0]
    assert torch.allclose(e, torch.tensor(want), atol=1e-6)


def test_confidence_loss_uses_distance_of_predicted_boxes():
    out, target = make_case(1)
    shift = torch.tensor([0.03, 0.0, 0.0])  # every control point 3 cm off -> d3D = 0.03, target 0.5
    out["offsets"] = out["offsets"] + shift
    out["confidence"] = torch.full_like(out["confidence"], 0.5)
    _, parts = multitask_loss(out, target, LossConfig(d_th=0.06))
    assert parts["conf"] == pytest.approx(0.0, abs=1e-10)
    out["confidence"] = torch.ones_like(out["confidence"])
    _, parts = multitask_loss(out, target, LossConfig(d_th=0.06))
    assert parts["conf"] == pytest.approx(0.25, rel=1e-5)  # (1 - 0.5)^2 on object points only


def test_gradients_flow_only_where_they_should():
    out, target = make_case(2)
    out["offsets"] = out["offsets"] + 0.02
    out["confidence"] = torch.full_like(out["confidence"], 0.3)
    out["logits"] = torch.zeros_like(out["logits"])
    bg = target["cls"] == 0
    x = leaf(out)
    loss, _ = multitask_loss(x, target, LossConfig())
    loss.backward()
    assert x["offsets"].grad[bg].abs().max() == 0 and x["offsets"].grad[~bg].abs().min() > 0
    assert x["confidence"].grad[bg].abs().max() == 0 and x["confidence"].grad[~bg].abs().min() > 0
    assert x["logits"].grad.abs().sum(-1).min() > 0  # CE on every keypoint
    # the confidence target is detached: the conf term alone sends nothing into the offsets
    x = leaf(out)
    loss, _ = multitask_loss(x, target, LossConfig(w_cls=0.0, w_offset=0.0))
    loss.backward()
    assert x["offsets"].grad is None or x["offsets"].grad.abs().max() == 0
    # segmentation-only pre-training: only the logits learn, parts still reported
    x = leaf(out)
    loss, parts = multitask_loss(x, target, LossConfig(seg_only=True))
    loss.backward()
    assert x["offsets"].grad is None and x["confidence"].grad is None
    assert parts["offset"] > 0 and parts["total"] == pytest.approx(parts["cls"])


def test_no_object_points_and_bad_config():
    out, target = make_case(3)
    target["cls"] = torch.zeros_like(target["cls"])
    out["logits"] = torch.zeros_like(out["logits"])
    loss, parts = multitask_loss(out, target, LossConfig())
    assert torch.isfinite(loss) and parts["offset"] == 0 and parts["conf"] == 0
    assert parts["cls"] == pytest.approx(math.log(3), rel=1e-5)
    with pytest.raises(DetectorError, match="score"):
        LossConfig(score="cubic")


def test_foreground_weight_is_the_weighted_mean_of_the_keypoints_cross_entropy():
    out, target = make_case(seed=3, classes=3)
    g = torch.Generator().manual_seed(4)
    out["logits"] = torch.randn(out["logits"].shape, generator=g)  # a wrong, uncertain classifier
    per_point = torch.nn.functional.cross_entropy(out["logits"].reshape(-1, 4), target["cls"].reshape(-1),
                                                  reduction="none")
    fg = (target["cls"].reshape(-1) > 0).float()
    plain = multitask_loss(out, target, LossConfig(seg_only=True))[1]["cls"]
    assert plain == pytest.approx(float(per_point.mean()), rel=1e-6)  # fg_weight 1: the paper's plain mean
    for w in (0.5, 2.0, 3.0):
        got = multitask_loss(out, target, LossConfig(seg_only=True, fg_weight=w))[1]["cls"]
        weights = 1.0 + (w - 1.0) * fg
        assert got == pytest.approx(float((weights * per_point).sum() / weights.sum()), rel=1e-6)
    # object keypoints misclassified cost more with a larger weight, background ones less
    wrong_fg = dict(out, logits=out["logits"].clone())
    wrong_fg["logits"][..., 0] = 10.0  # everything called background: only the object keypoints are wrong
    losses = [multitask_loss(wrong_fg, target, LossConfig(seg_only=True, fg_weight=w))[1]["cls"] for w in (1, 2, 4)]
    assert losses[0] < losses[1] < losses[2]
    with pytest.raises(DetectorError, match="fg_weight"):
        LossConfig(fg_weight=0)
