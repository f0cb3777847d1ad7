import pytest

from argen.config import TemplateConfig, available_templates, from_dict, load_template, override, to_dict
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
    ("clutter:\n  desk_things: [2, 1]\n", "clutter desk_things must be 0 <= min <= max"),
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


def test_sensor_profiles_set_intrinsics_and_noise_and_the_template_or_set_wins():
    from argen.config import available_sensors, load_sensor, load_template, override

    assert {"kinect_v1", "kinect_v2", "realsense_d435"} <= set(available_sensors())
    lm = load_template("linemod")
    assert lm.sensor == "kinect_v1" and (lm.camera.width, lm.camera.fx) == (640, 572.4114)
    assert lm.noise.shadow and lm.noise.correlated_sigma > 0 and lm.noise.model == "structured_light"
    d435 = load_template("linemod", sensor="realsense_d435")
    assert (d435.camera.width, d435.camera.height, d435.noise.model) == (848, 480, "stereo")
    assert d435.camera.distance == lm.camera.distance  # the template's own keys stay
    v2 = load_template("lchf", sensor="kinect_v2")
    assert v2.noise.model == "tof" and v2.noise.disparity_step_px == 0 and v2.noise.multipath > 0
    assert override(v2, {"noise.multipath": 0.0}).noise.multipath == 0.0
    for name in available_sensors():
        prof = load_sensor(name)
        assert prof["sources"] and prof["description"]  # every profile says where its numbers come from
    with pytest.raises(ArgenError, match="unknown sensor"):
        load_template("linemod", sensor="sonar")
