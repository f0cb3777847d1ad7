"""Stage 1's sampling at inference (detector.checkpoint.SamplingConfig): a model file's density scales the points
drawn from a frame and the keypoints the network predicts at; ``--set sampling.density`` overrides it."""

from __future__ import annotations

from pathlib import Path

import pytest

from detector.checkpoint import SamplingConfig, load_checkpoint
from detector.errors import DetectorError
from detector.infer import split_sets

CHECKPOINTS = Path(__file__).resolve().parents[1] / "checkpoints"


def test_density_scales_counts_to_multiples_of_64_and_one_keeps_them():
    assert SamplingConfig(1).scaled(1000) == 1000  # as trained, whatever the count
    assert SamplingConfig(1.25).scaled(4096) == 5120 and SamplingConfig(1.25).scaled(1024) == 1280
    for density in (0.3, 1.1, 1.5, 2, 3.7):
        for count in (100, 1024, 4096):
            n = SamplingConfig(density).scaled(count)
            assert n % 64 == 0 and count * density <= n < count * density + 64
    for bad in (0, 0.1, 9, "abc", None):
        with pytest.raises(DetectorError):
            SamplingConfig(bad)
    with pytest.raises(DetectorError, match="unknown sampling option 'points'"):
        SamplingConfig.from_dict({"points": 8192})


def test_split_sets_routes_geometry_and_sampling_settings():
    assert split_sets(["geometry.tau=0.3", "sampling.density=1.5", "geometry.icp_points=[1, 2]"]) == \
        (["geometry.tau=0.3", "geometry.icp_points=[1, 2]"], {"density": 1.5})
    assert split_sets(None) == ([], {})
    for bad in ("stage1.lr=1", "density=2", "sampling=2"):
        with pytest.raises(DetectorError, match="geometry and sampling"):
            split_sets([bad])


def test_shipped_models_sample_as_their_files_say():
    lm8 = load_checkpoint(CHECKPOINTS / "lm8.pt")
    density = SamplingConfig(lm8.sampling["density"])
    trained = load_checkpoint(CHECKPOINTS / "lm8.pt", sampling={"density": 1})
    assert (trained.num_points, trained.model_config.npoints[0]) == (4096, 1024)  # what stage 1 trained on
    assert (lm8.num_points, lm8.model_config.npoints[0]) == (density.scaled(4096), density.scaled(1024))
    assert lm8.model_config.npoints[1:] == trained.model_config.npoints[1:]
    # a model file without the setting samples as it trained
    ycbv = load_checkpoint(CHECKPOINTS / "ycbv3.pt")
    assert ycbv.sampling == {"density": 1.0}
    assert ycbv.num_points == int(ycbv.extra["train_config"]["num_points"])
