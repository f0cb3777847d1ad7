"""The networks' number format at inference (detector.net_dtype): choosing it, and stage 2 in bfloat16."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from detector.data.augment import NORMALISATION
from detector.errors import DetectorError
from detector import net_dtype as nd
from detector.stage2.crops import CropConfig
from detector.stage2.network import CropNet, CropNetConfig
from detector.stage2.poser import CropPoser, crop_predictions


def test_cpu_flags_are_read_from_cpuinfo():
    text = "processor\t: 0\nmodel name\t: X\nflags\t\t: fpu avx2 avx512f avx512_bf16\n\nprocessor\t: 1\n"
    assert nd.cpu_flags(text) == {"fpu", "avx2", "avx512f", "avx512_bf16"}
    assert nd.cpu_flags("processor\t: 0\nFeatures\t: fp asimd\n") == set()  # no x86 flags line: none known
    assert nd.BF16_FLAGS & nd.cpu_flags(text) and not nd.BF16_FLAGS & nd.cpu_flags("flags : avx2 avx512f")


def test_auto_is_bfloat16_only_on_a_cpu_that_multiplies_it(monkeypatch):
    for native, want in ((True, "bfloat16"), (False, "float32")):
        monkeypatch.setattr(nd, "native_bfloat16", lambda native=native: native)
        assert nd.resolve_net_dtype("auto", "cpu") == want
        assert nd.resolve_net_dtype("auto", "cuda") == "float32"  # a GPU: not measured, float32
        assert nd.resolve_net_dtype("float32", "cpu") == "float32"
        assert nd.resolve_net_dtype("bfloat16", "cpu") == "bfloat16"  # asked for: given, native or not
    with pytest.raises(DetectorError, match="--net-dtype must be one of auto, float32, bfloat16"):
        nd.resolve_net_dtype("half")
    with pytest.raises(DetectorError, match="CPU only"):
        nd.resolve_net_dtype("bfloat16", "cuda")
    with pytest.raises(DetectorError, match="once resolved"):
        nd.net_autocast("auto")
    with pytest.raises(DetectorError, match="CPU only"):
        nd.check_net_dtype("bfloat16", "cuda")  # a predictor or poser made for a GPU refuses it, not ignores it
    nd.check_net_dtype("float32", "cuda")
    with pytest.raises(DetectorError, match="not a torch device"):
        nd.resolve_net_dtype("auto", "gpu")


def test_stage2_in_bfloat16_predicts_the_same_points_close_to_float32():
    """The crop network in bfloat16: the same crops' rows, foreground probabilities and model coordinates within
    bfloat16's rounding of float32's (a network of the shipped widths, random weights, on a cloud of crop size)."""
    torch.manual_seed(0)
    net = CropNet(CropNetConfig(), 4).eval()
    rng = np.random.default_rng(0)
    feats = np.zeros((3000, 9), np.float32)
    feats[:, :3] = rng.normal(0, 0.05, (3000, 3)) + [0.0, 0.0, 0.8]
    feats[:, 3:6] = rng.random((3000, 3))
    n = rng.normal(size=(3000, 3))
    feats[:, 6:9] = n / np.linalg.norm(n, axis=1, keepdims=True)
    centres, classes, dia = np.array([[0.0, 0.0, 0.8], [0.03, 0.0, 0.8]]), np.array([1, 3]), np.array([0.1, 0.15])
    args = (net, feats, centres, classes, dia, CropConfig(), NORMALISATION, 7, "cpu", 2)
    a, b = crop_predictions(*args), crop_predictions(*args, net_dtype="bfloat16")
    with pytest.raises(DetectorError, match="CPU only"):
        CropPoser(net, [1, 2, 3, 4], None, CropConfig(), NORMALISATION, device="cuda", net_dtype="bfloat16")
    for (ra, pa, ca), (rb, pb, cb), d in zip(a, b, dia):
        assert np.array_equal(ra, rb) and pb.dtype == pa.dtype and cb.dtype == np.float64
        assert np.abs(pb - pa).max() < 0.05
        assert np.abs(cb - ca).max() < 0.05 * d and np.abs(cb - ca).mean() < 0.01 * d  # metres
        assert not np.array_equal(cb, ca)
