"""Stage 1's sampling at inference (detector.stage1.sampling.SamplingConfig): a model file's density scales the points
drawn from a frame and the keypoints the network predicts at; ``--set sampling.density`` overrides it."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from detector.checkpoint import load_checkpoint
from detector.errors import DetectorError
from detector.infer import split_sets
from detector.stage1.predictor import network_predictor
from detector.stage1.sampling import SamplingConfig

CHECKPOINTS = Path(__file__).resolve().parents[1] / "checkpoints"


def test_density_scales_counts_to_multiples_of_64_and_one_keeps_them():
    assert SamplingConfig(1).scaled(1000) == 1000  # as trained, whatever the count
    assert SamplingConfig(1.25).scaled(4096) == 5120 and SamplingConfig(1.25).scaled(1024) == 1280
    assert SamplingConfig(1.1).scaled(3200) == 3520 and SamplingConfig(1.12).scaled(4800) == 5376  # exact products
    for density in (0.3, 1.1, 1.5, 2, 3.7):
        for count in (100, 1024, 4096):
            n = SamplingConfig(density).scaled(count)
            assert n % 64 == 0 and count * density <= n < count * density + 64
    for bad in (0, 0.1, 9, "abc", None, True, [1]):
        with pytest.raises(DetectorError):
            SamplingConfig(bad)
    assert SamplingConfig().passes == 1 and SamplingConfig(passes=3.0).passes == 3
    for bad in (0, 9, 1.5, True, "2", None, float("nan"), float("inf")):
        with pytest.raises(DetectorError, match="sampling.passes"):
            SamplingConfig(passes=bad)
    with pytest.raises(DetectorError, match="unknown sampling option 'points'"):
        SamplingConfig.from_dict({"points": 8192})
    assert SamplingConfig().fps == "trained" and SamplingConfig.from_dict({"fps": "tree"}).fps == "tree"
    for bad in ("exact", "", None, 1, True):
        with pytest.raises(DetectorError, match="sampling.fps must be one of trained, tree"):
            SamplingConfig(fps=bad)


def test_the_predictor_checks_a_model_objects_sampling_settings():
    """network_predictor reads the sampling settings through SamplingConfig: a model object's bad or unknown
    setting is a one-line DetectorError when the predictor is made, not a frame later."""
    network_predictor(SimpleNamespace(model=torch.nn.Linear(1, 1)))  # none stored: one pass, the training's FPS (SamplingConfig's defaults)
    for bad, match in (({"passes": 0}, "sampling.passes"), ({"fps": "exact"}, "sampling.fps"),
                       ({"points": 8192}, "unknown sampling option")):
        with pytest.raises(DetectorError, match=match):
            network_predictor(SimpleNamespace(model=torch.nn.Linear(1, 1), sampling=bad))


def test_split_sets_routes_geometry_sampling_and_stage2_settings():
    assert split_sets(["geometry.tau=0.3", "sampling.density=1.5", "geometry.icp_points=[1, 2]",
                       "infer.hypotheses=64"]) == \
        (["geometry.tau=0.3", "geometry.icp_points=[1, 2]"], {"density": 1.5}, {"hypotheses": 64})
    assert split_sets(None) == ([], {}, {})
    for bad in ("stage1.lr=1", "density=2", "sampling=2", "infer=3"):
        with pytest.raises(DetectorError, match="geometry, sampling and infer"):
            split_sets([bad])


def test_shipped_models_draw_as_trained_with_the_tree_fps_and_a_stored_density_is_applied(tmp_path):
    import torch

    # both store density 1: they draw as many points as they trained on (4096 points, 1024 keypoints), and both find
    # the farthest points with the tree-based FPS; lm8.pt samples twice, ycbv3.pt once
    for name, passes in (("lm8.pt", 2), ("ycbv3.pt", 1)):
        ck = load_checkpoint(CHECKPOINTS / name)
        assert ck.sampling == {"density": 1.0, "passes": passes, "fps": "tree"}
        assert (ck.num_points, ck.model_config.npoints[0]) == (4096, 1024)
        assert ck.num_points == int(ck.extra["train_config"]["num_points"])
    payload = torch.load(CHECKPOINTS / "lm8.pt", map_location="cpu", weights_only=False)
    payload["extra"]["sampling_config"] = {"density": 1.25}
    torch.save(payload, tmp_path / "dense.pt")
    dense = load_checkpoint(tmp_path / "dense.pt")
    assert dense.sampling == {"density": 1.25, "passes": 1, "fps": "trained"}  # a file without fps: as trained
    assert (dense.num_points, dense.model_config.npoints) == (5120, [1280, *ck.model_config.npoints[1:]])
    back = load_checkpoint(tmp_path / "dense.pt", sampling={"density": 1})  # --set over the stored setting
    assert (back.num_points, back.model_config.npoints[0]) == (4096, 1024)
