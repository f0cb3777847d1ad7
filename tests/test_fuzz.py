"""Property-based tests of the readers users feed files to: templates and BOP JSON / PLY / PNG.

Whatever the content, a reader either returns a valid result or raises ``ArgenError`` (one line, which
the CLI prints); any other exception would reach the user as a traceback.
"""

from __future__ import annotations

import json

import numpy as np
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from argen import bop
from argen.config import TemplateConfig, from_dict, load_template, to_dict
from argen.errors import ArgenError

SETTINGS = settings(max_examples=150, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# JSON-like values: what json.load / yaml.safe_load can return
scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8))
json_values = st.recursive(scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=6), inner, max_size=4)), max_leaves=20)


def _one_line(exc: ArgenError) -> None:
    msg = str(exc)
    assert msg and "\n" not in msg and "Traceback" not in msg


def _template_mutations():
    """A real template with one leaf replaced, deleted, or an extra key added somewhere."""
    base = to_dict(load_template("linemod"))
    paths = []

    def walk(d, prefix):
        for k, v in d.items():
            paths.append(prefix + (k,))
            if isinstance(v, dict):
                walk(v, prefix + (k,))

    walk(base, ())
    return base, paths


BASE, PATHS = _template_mutations()


@SETTINGS
@given(path=st.sampled_from(PATHS), value=json_values, action=st.sampled_from(["set", "delete", "add"]),
       key=st.text(min_size=1, max_size=6))
def test_mutated_template_is_valid_or_a_clear_error(path, value, action, key):
    data = json.loads(json.dumps(BASE))
    parent = data
    for k in path[:-1]:
        parent = parent[k]
    if action == "set":
        parent[path[-1]] = value
    elif action == "delete":
        del parent[path[-1]]
    else:
        target = parent[path[-1]] if isinstance(parent[path[-1]], dict) else parent
        target[key] = value
    try:
        cfg = from_dict(TemplateConfig, data, where="fuzz.yaml")
    except ArgenError as exc:
        _one_line(exc)
        return
    assert isinstance(cfg, TemplateConfig)
    # a config that loads survives a round trip unchanged
    assert to_dict(from_dict(TemplateConfig, to_dict(cfg))) == to_dict(cfg)


@SETTINGS
@given(text=st.text(max_size=200))
def test_arbitrary_yaml_text_as_template(tmp_path_factory, text):
    p = tmp_path_factory.mktemp("tpl") / "t.yaml"
    p.write_text(text)
    try:
        load_template(p)
    except ArgenError as exc:
        _one_line(exc)


def _models_info_entry():
    num = st.one_of(st.floats(-1e4, 1e4), st.integers(-1000, 1000), st.text(max_size=3), st.none())
    return st.fixed_dictionaries(
        {k: num for k in ("diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z")},
        optional={"symmetries_discrete": json_values, "symmetries_continuous": json_values})


@SETTINGS
@given(data=st.one_of(json_values, st.dictionaries(st.text(max_size=4), _models_info_entry(), max_size=3)))
def test_models_info_is_parsed_or_a_clear_error(data):
    try:
        infos = bop.parse_models_info(data)
    except ArgenError as exc:
        _one_line(exc)
        return
    for info in infos.values():
        assert info.diameter > 0 and np.all(info.bbox_size > 0)
        assert all(T.shape == (4, 4) for T in info.symmetries_discrete)


def _gt_like():
    mat = st.one_of(st.lists(st.floats(-1e3, 1e3), min_size=0, max_size=10), json_values)
    return st.fixed_dictionaries({}, optional={"obj_id": json_values, "cam_R_m2c": mat, "cam_t_m2c": mat,
                                               "cam_K": mat, "depth_scale": json_values,
                                               "cam_R_w2c": mat, "cam_t_w2c": mat})


@SETTINGS
@given(data=st.dictionaries(st.text(max_size=4), st.one_of(json_values, _gt_like(), st.lists(_gt_like(), max_size=3)),
                            max_size=3))
def test_scene_json_is_parsed_or_a_clear_error(data):
    for parse in (bop.parse_scene_camera, bop.parse_scene_gt):
        try:
            out = parse(data, "fuzz.json")
        except ArgenError as exc:
            _one_line(exc)
            continue
        for value in out.values():
            items = value if isinstance(value, list) else [value]
            for item in items:
                if hasattr(item, "K"):
                    assert item.K.shape == (3, 3) and np.all(np.isfinite(item.K))
                    assert item.depth_scale > 0
                else:
                    assert item.R.shape == (3, 3) and item.t.shape == (3,)
                    assert np.all(np.isfinite(item.R)) and np.all(np.isfinite(item.t))


@SETTINGS
@given(blob=st.binary(max_size=400), kind=st.sampled_from(["ply", "png", "json"]))
def test_arbitrary_bytes_as_model_image_or_json(tmp_path_factory, blob, kind):
    d = tmp_path_factory.mktemp("blob")
    if kind == "ply":
        blob = b"ply\nformat ascii 1.0\n" + blob
    p = d / f"x.{kind}"
    p.write_bytes(blob)
    try:
        if kind == "ply":
            mesh = bop.read_mesh(p)
            assert len(mesh.faces) > 0 and np.all(np.isfinite(mesh.vertices))
        elif kind == "png":
            bop.read_rgb(p)
        else:
            bop.read_models_info(p)
    except ArgenError as exc:
        _one_line(exc)


def test_yaml_dump_of_a_loaded_template_loads_again(tmp_path):
    p = tmp_path / "copy.yaml"
    p.write_text(yaml.safe_dump(to_dict(load_template("lchf"))))
    assert to_dict(load_template(p)) == to_dict(load_template("lchf"))
