"""Files written under the older names still load: model files and stage-2 checkpoints with the keys ``detect``,
``pose`` and ``extra.pose_config`` (each shipped model re-saved that way), two_stage.yaml
with a ``pose`` section (and ``--set pose.KEY``), and run folders with ``detect/`` and ``pose/``."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml

from detector.checkpoint import load_checkpoint
from detector.errors import DetectorError
from detector.training.checkpoint_file import FORMAT, TWO_STAGE_VERSION, read_checkpoint, rename_old_keys
from detector.two_stage import load_two_stage_config, stage_dirs

CHECKPOINTS = Path(__file__).resolve().parents[1] / "checkpoints"


def test_rename_old_keys():
    old = {"format": FORMAT, "version": 2, "detect": {"step": 1}, "pose": {"step": 2},
           "extra": {"pose_config": {"tau": 0.1}, "train_file": "x.h5"}}
    new = rename_old_keys(old)
    assert new == {"format": FORMAT, "version": TWO_STAGE_VERSION, "stage1": {"step": 1}, "stage2": {"step": 2},
                   "extra": {"geometry_config": {"tau": 0.1}, "train_file": "x.h5"}}
    assert new["stage1"] is old["detect"]  # renamed, not copied
    assert rename_old_keys({"format": FORMAT, "version": 2, "pose": {"step": 3}}) == \
        {"format": FORMAT, "version": TWO_STAGE_VERSION, "stage2": {"step": 3}}  # a stage-2 run's last.pt
    for unchanged in ({"format": FORMAT, "version": 1, "step": 4, "extra": {"pose_config": {}}},
                      {"format": FORMAT, "version": 3, "stage2": {"step": 5}}):
        assert rename_old_keys(unchanged) == unchanged


def _as_old_file(payload: dict) -> dict:
    """A version-3 model payload written the way files were before the names changed (version 2: ``detect``,
    ``pose``, ``extra.pose_config``)."""
    old = {k: v for k, v in payload.items() if k not in ("stage1", "stage2", "extra")}
    extra = dict(payload["extra"])
    extra["pose_config"] = extra.pop("geometry_config")
    return {**old, "version": 2, "detect": payload["stage1"], "pose": payload["stage2"], "extra": extra}


@pytest.mark.parametrize("name", ["lm8.pt", "ycbv3.pt"])
def test_shipped_checkpoints_load_under_the_old_names_too(name, tmp_path):
    """Each shipped model, read as it is and re-saved under the old keys, gives the same model both ways."""
    path = CHECKPOINTS / name
    payload = read_checkpoint(path)
    assert payload["version"] == TWO_STAGE_VERSION and {"stage1", "stage2"} <= set(payload)
    assert not {"detect", "pose"} & set(payload) and "geometry_config" in payload["extra"]
    old_path = tmp_path / name
    torch.save(_as_old_file(payload), old_path)
    raw = torch.load(old_path, map_location="cpu", weights_only=True)
    assert raw["version"] == 2 and {"detect", "pose"} <= set(raw) and "pose_config" in raw["extra"]
    new, old = load_checkpoint(path), load_checkpoint(old_path)
    assert old.stage2_net is not None and old.stage2["class_ids"] == old.class_ids == new.class_ids
    assert old.geometry_config == new.geometry_config == payload["extra"]["geometry_config"]
    for a, b in ((new.model, old.model), (new.stage2_net, old.stage2_net)):
        sa, sb = a.state_dict(), b.state_dict()
        assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_an_old_stage2_checkpoint_reads_as_stage2(tmp_path):
    path = tmp_path / "last.pt"
    torch.save({"format": FORMAT, "version": 2, "pose": {"step": 7, "class_ids": [1]}}, path)
    assert read_checkpoint(path)["stage2"]["step"] == 7
    with pytest.raises(DetectorError, match="holds a stage-2 network only"):
        load_checkpoint(path)


def test_two_stage_yaml_with_a_pose_section(tmp_path):
    path = tmp_path / "two_stage.yaml"
    path.write_text(yaml.safe_dump({"stage1": {"steps": 5}, "stage2": {"steps": 6}, "pose": {"tau": 0.3},
                                    "infer": {"samples": 2}}))
    cfg = load_two_stage_config(path, {"pose.min_score": 0.5, "stage2.cache_mb": 1.0})
    assert cfg.geometry == {"tau": 0.3, "min_score": 0.5} and cfg.stage2 == {"steps": 6, "cache_mb": 1.0}
    s1, s2, geometry, infer = cfg.resolved()
    assert (s1.steps, s2.steps, geometry["tau"], infer["samples"]) == (5, 6, 0.3, 2)
    assert load_two_stage_config(None, {"geometry.tau": 0.4}).geometry == {"tau": 0.4}
    with pytest.raises(DetectorError, match="unknown two-stage option"):
        load_two_stage_config(None, {"detect.tau": 0.4})


def test_stage_dirs(tmp_path):
    assert stage_dirs(tmp_path) == (tmp_path / "stage1", tmp_path / "stage2")  # a new run
    (tmp_path / "detect").mkdir()
    (tmp_path / "pose").mkdir()
    assert stage_dirs(tmp_path) == (tmp_path / "detect", tmp_path / "pose")  # a run from before the names changed
    (tmp_path / "stage1").mkdir()
    assert stage_dirs(tmp_path) == (tmp_path / "stage1", tmp_path / "stage2")


def test_combine_stages_takes_each_stage_and_the_chosen_settings_from_its_file(tmp_path):
    """combine_stages: stage 1's weights and object table from the first file, stage 2's from the second, the
    inference settings from the one named; files of other objects, or not two-stage model files, are refused."""
    from detector.checkpoint import combine_stages

    src = read_checkpoint(CHECKPOINTS / "ycbv3.pt")
    other = read_checkpoint(CHECKPOINTS / "ycbv3.pt")  # the same objects, another stage 2 and other settings
    other["stage2"]["model_state"] = {k: v + 1.0 if v.is_floating_point() else v
                                      for k, v in other["stage2"]["model_state"].items()}
    other["stage2"]["infer_config"] = {**other["stage2"].get("infer_config", {}), "verify": 8}
    other["extra"]["geometry_config"] = {**other["extra"]["geometry_config"], "min_score": 0.5}
    torch.save(other, tmp_path / "other.pt")
    out = combine_stages(CHECKPOINTS / "ycbv3.pt", tmp_path / "other.pt", tmp_path / "mixed.pt")
    mixed = read_checkpoint(out)
    for k, v in src["stage1"]["model_state"].items():
        assert torch.equal(mixed["stage1"]["model_state"][k], v)
    for k, v in other["stage2"]["model_state"].items():
        assert torch.equal(mixed["stage2"]["model_state"][k], v)
    assert mixed["extra"]["geometry_config"]["min_score"] == 0.5 and mixed["stage2"]["infer_config"]["verify"] == 8
    assert load_checkpoint(out).stage2_net is not None  # a model file eval and predict take
    kept = read_checkpoint(combine_stages(CHECKPOINTS / "ycbv3.pt", tmp_path / "other.pt", tmp_path / "kept.pt",
                                          settings_from="stage1"))
    assert kept["extra"] == src["extra"] and kept["stage2"]["infer_config"] == src["stage2"].get("infer_config")
    with pytest.raises(DetectorError, match="learned objects"):
        combine_stages(CHECKPOINTS / "ycbv3.pt", CHECKPOINTS / "lm8.pt", tmp_path / "no.pt")
    torch.save({"format": FORMAT, "version": TWO_STAGE_VERSION, "stage2": {"step": 3}}, tmp_path / "last.pt")
    with pytest.raises(DetectorError, match="not a two-stage model file"):
        combine_stages(tmp_path / "last.pt", CHECKPOINTS / "ycbv3.pt", tmp_path / "no.pt")
    with pytest.raises(DetectorError, match="settings_from"):
        combine_stages(CHECKPOINTS / "ycbv3.pt", CHECKPOINTS / "ycbv3.pt", tmp_path / "no.pt", settings_from="both")
    assert not (tmp_path / "no.pt").exists()
