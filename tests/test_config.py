import pytest

from argen.config import (TemplateConfig, available_templates, from_dict, load_template, override, to_dict)
from argen.errors import ArgenError


def test_builtin_templates_load_with_linemod_intrinsics():
    assert {"linemod", "lchf"} <= set(available_templates())
    cfg = load_template("linemod")
    assert (cfg.camera.width, cfg.camera.height) == (640, 480)
    assert cfg.camera.fx == pytest.approx(572.4114) and cfg.camera.cy == pytest.approx(242.04899)
    assert cfg.camera.distance == (0.6, 1.15)
    lchf = load_template("lchf")
    assert lchf.placement.instances_per_object[0] > 1 and lchf.placement.objects_per_frame == (1, 1)


def test_unknown_key_is_named_with_a_suggestion(tmp_path):
    p = tmp_path / "t.yaml"
    p.write_text("camera:\n  distnce: [0.5, 1.0]\n")
    with pytest.raises(ArgenError, match=r"unknown key 'distnce'.*did you mean 'distance'"):
        load_template(p)


@pytest.mark.parametrize("yaml_text, msg", [
    ("camera:\n  fx: fast\n", "expected a number"),
    ("camera:\n  distance: [1.0]\n", "list of 2"),
    ("camera:\n  distance: [1.2, 0.5]\n", "distance"),
    ("placement:\n  objects_per_frame: [0, 2]\n", "objects_per_frame"),
    ("noise:\n  enabled: maybe\n", "true or false"),
    ("camera: 3\n", "expected a mapping"),
    ("camera: [\n", "not valid YAML"),
])
def test_invalid_values_are_clear_errors(tmp_path, yaml_text, msg):
    p = tmp_path / "t.yaml"
    p.write_text(yaml_text)
    with pytest.raises(ArgenError, match=msg):
        load_template(p)


def test_unknown_template_lists_the_available_ones():
    with pytest.raises(ArgenError, match="unknown scene template 'nope'.*linemod"):
        load_template("nope")


def test_override_and_round_trip():
    cfg = load_template("linemod")
    cfg2 = override(cfg, {"camera.distance": [0.5, 0.9], "noise.enabled": False, "seed": 7})
    assert cfg2.camera.distance == (0.5, 0.9) and not cfg2.noise.enabled and cfg2.seed == 7
    assert cfg.camera.distance == (0.6, 1.15)  # original untouched
    assert from_dict(TemplateConfig, to_dict(cfg2)) == cfg2
    with pytest.raises(ArgenError, match="unknown option 'camera.nope'"):
        override(cfg, {"camera.nope": 1})
