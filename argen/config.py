"""Typed scene configuration, loaded from the YAML templates in ``templates/``.

Every stage of the capture pipeline reads its parameters from one of these dataclasses. Units are
metres and degrees as named in each field. Loading is strict: an unknown key, a wrong type or an
out-of-range value is an :class:`ArgenError` naming the key (the loader is :mod:`argen.settings`, shared with
``detector``; the range checks are :func:`validate`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from argen import settings
from argen.errors import ArgenError

TEMPLATES_DIR = Path(__file__).resolve().parent / "templates"

Range = tuple[float, float]
IntRange = tuple[int, int]


@dataclass
class CameraConfig:
    """Pinhole intrinsics (OpenCV convention, pixels) and the shell camera views are sampled on."""

    width: int = 640
    height: int = 480
    fx: float = 572.4114
    fy: float = 573.57043
    cx: float = 325.2611
    cy: float = 242.04899
    distance: Range = (0.6, 1.15)  # metres, camera centre to look-at point
    elevation_deg: Range = (0.0, 90.0)  # above the board plane
    azimuth_deg: Range = (0.0, 360.0)
    look_at_jitter: float = 0.05  # metres, std of the look-at point around the board centre
    roll_deg: float = 5.0  # std of the camera roll about its optical axis
    z_near: float = 0.05
    z_far: float = 6.0


@dataclass
class BoardConfig:
    """A LineMOD-style capture board: a ring of square ArUco markers around a free central area."""

    dictionary: str = "DICT_4X4_100"
    markers_per_side: int = 8  # markers along each edge of the ring
    marker_size: float = 0.05  # metres, black square side
    marker_gap: float = 0.02  # metres between neighbouring markers
    margin: float = 0.01  # metres of white border outside the ring
    print_dpi: int = 300  # for `argen board`
    texture_px_per_m: int = 2000  # resolution of the rendered board texture
    thickness: float = 0.003  # metres


@dataclass
class PlacementConfig:
    """Random placement of the objects on the board's free area."""

    objects_per_frame: IntRange = (3, 4)  # distinct objects drawn per frame
    instances_per_object: IntRange = (1, 1)  # copies of each drawn object (lchf: several)
    max_tries: int = 200  # placement attempts per instance before giving up on it
    min_gap: float = 0.005  # metres between footprints
    beside: float = 0.5  # probability that an instance stands right next to one already placed (min_gap + 0-2 cm)
    stable_poses: int = 4  # most likely resting poses of each object to choose from
    uniform_poses: float = 0.0  # share of draws uniform over those poses (people stand a box on its end; physics rarely)


@dataclass
class ClutterConfig:
    """Distractors (argen.sim.distractors: mugs, bowls, bottles, boxes, books, tools, toys, cables, ...):
    among the targets on the board, on the desk around it and on a shelf; all of them background."""

    count: IntRange = (8, 16)  # on the desk around the board
    ring: Range = (0.25, 0.8)  # metres from the board centre (desk distractors)
    on_board: IntRange = (1, 4)  # on the board's free area, among the targets (occluders)
    board_cover: float = 0.6  # probability that a printed sheet, cloth or mat covers the board's free area
    near_target: float = 0.6  # probability that an on-board distractor stands right next to a target (0-1 cm)
    scale: Range = (0.85, 1.2)  # factor on each distractor's real size
    papers: IntRange = (0, 3)  # magazines and papers lying on the desk
    monitor: float = 0.5  # probability of a monitor on the desk behind the board
    # keyboards with separate keys, open laptops and mice on the desk around the board (argen.sim.distractors.DESK);
    # none by default, which keeps the captures of the shipped models' recipes as they were
    desk_things: IntRange = (0, 0)
    shelf: float = 0.3  # probability of a shelf on a wall, with things on it
    shelf_items: IntRange = (1, 4)
    # no distractor of a target's box size (argen.sim.distractors.lookalike) is placed; false places them, e.g. for
    # free-form targets that no mug, cup, fruit or box of their size could pass for (RESULTS.md, lm8)
    avoid_lookalikes: bool = True


@dataclass
class SceneConfig:
    """Room and lighting: a desk of random size (its edges may be in view), the floor below it, walls, lights."""

    table_margin: Range = (0.1, 0.9)  # metres from the board's edge to each desk edge, drawn per edge
    table_height: Range = (0.7, 0.78)  # metres from the floor to the desk top
    walls: IntRange = (0, 2)  # walls beyond desk edges
    wall_gap: Range = (0.0, 0.4)  # metres from a desk edge to its wall
    ambient: Range = (0.15, 0.45)
    light_intensity: Range = (1.0, 2.4)  # directional light (diffuse: intensity * cos / pi)
    point_lights: IntRange = (1, 2)
    point_light_intensity: Range = (0.8, 3.0)  # each point light (further divided by distance^2)
    light_tint: float = 0.15  # largest change of a light's colour channels from white (warm or cool light)


@dataclass
class ARConfig:
    """Acceptance of the marker-based camera pose (as the paper filtered frames by hand)."""

    min_markers: int = 4
    max_reproj_px: float = 2.0


@dataclass
class PlaneConfig:
    """The support plane of a markerless capture (``argen capture --recording`` without a board, argen.real.support).

    A point lies on the plane when its distance to it is below ``inlier_m + inlier_per_m2 * z^2`` (z: its depth,
    metres; the depth noise of structured light grows with z^2); anything higher above the plane is real geometry
    that the objects must keep clear of.
    """

    support: str = "auto"  # "auto": the board where it is found, else the plane; "board": board only; "plane": plane only
    inlier_m: float = 0.004  # metres
    inlier_per_m2: float = 0.0025  # 1/metre: the tolerance's growth with depth squared
    max_tilt_deg: float = 85.0  # largest angle between the plane normal and the camera's up axis (-y): the camera
    # looks down at the support by as much (a wall in front of a camera looking down is tilted more than 90)
    centre: float = 0.35  # the fit uses the pixels within this fraction of the image size around its centre
    candidates: int = 4  # planes fitted one after another (each without the previous ones' inliers)
    min_inliers: int = 300  # fewest central inliers of a usable plane (on the fit's 4-pixel grid)
    cell: float = 0.01  # metres: the grid cell of the plane's extent and the clearance above it
    clearance: float = 0.005  # metres: gap between a placed object and any real point above the plane


@dataclass
class NoiseConfig:
    """Depth-sensor model (``argen.sim.noise``). The defaults are the plain Kinect v1 model of Nguyen et al. 2012;
    the sensor profiles (``argen/sensors/*.yaml``) switch on and calibrate the other effects."""

    enabled: bool = True
    model: str = "structured_light"  # structured_light (Kinect v1), tof (Kinect v2 / Azure), stereo (RealSense)
    axial_a: float = 0.0012  # metres: sigma_z = a + b (z - z0)^2
    axial_b: float = 0.0019  # 1/metre
    axial_z0: float = 0.4  # metres
    angle_term: bool = True  # sigma_z grows as theta^2 / (pi/2 - theta)^2 (incidence angle theta)
    lateral_px: float = 0.5  # std of the lateral pixel shift
    baseline: float = 0.075  # metres, projector-camera baseline for disparity
    disparity_step_px: float = 0.125  # disparity quantisation step (1/8 px)
    min_range: float = 0.4  # metres
    max_range: float = 4.0
    edge_threshold: float = 0.03  # metres: depth jump that counts as a discontinuity
    edge_dropout: float = 0.6  # probability of losing a pixel next to a discontinuity
    grazing_deg: float = 78.0  # incidence angles beyond this return nothing
    random_dropout: float = 0.005  # share of pixels lost at random
    correlated_sigma: float = 0.0  # metres at 1 m (grows with z^2): spatially correlated axial error
    correlated_px: float = 4.0  # its correlation radius (a 9 x 9 matching window: 4 px)
    shadow: bool = False  # holes where the projector (or the second camera) cannot see: `baseline` along +x
    flying: float = 0.0  # probability that a kept pixel at a discontinuity takes a depth between its sides
    edge_fatten_px: int = 0  # the nearer side of a discontinuity spreads this far into the farther one
    multipath: float = 0.0  # ToF: gain of the extra depth in concave regions (z minus its local mean)
    multipath_px: float = 6.0  # ToF: radius of that local mean
    dark_dropout: float = 0.0  # probability of losing a black pixel (falls linearly to 0 at dark_level)
    dark_level: float = 0.12  # luminance (0..1) below which dark dropout starts
    textureless_dropout: float = 0.0  # stereo: probability of losing a pixel whose 7x7 patch is flat
    textureless_level: float = 0.01  # std of luminance (0..1) below which a patch counts as flat
    scale_sigma: float = 0.0  # per-frame relative error of the depth scale (std)
    offset_sigma: float = 0.0  # per-frame depth offset, metres (std)
    native_fx: float = 0.0  # pixels: the depth camera's own fx; a finer image gets the noise at this pitch (0: off)


@dataclass
class ColourConfig:
    """The colour camera's artefacts (argen.sim.colour): misregistration to the depth, blur, sensor noise."""

    enabled: bool = True
    shift_px: Range = (0.0, 2.0)  # colour image shifted against the depth by this many pixels, any direction
    blur_px: Range = (0.0, 1.2)  # Gaussian blur sigma, pixels
    noise: Range = (0.005, 0.025)  # sensor noise std, in [0, 1] colour units


@dataclass
class OutputConfig:
    frames_per_scene: int = 1000  # BOP convention for PBR-style folders
    split: str = "train_pbr"
    depth_scale: float = 0.1  # BOP depth_scale: depth_mm = png_value * depth_scale
    # where K puts pixel centres: "integer" (OpenCV, and what a real sensor's calibrated K means: pixel (u, v)
    # is seen along K^-1 (u, v, 1)), or "half" (at (u + 0.5, v + 0.5): the BOP toolkit renderer's convention,
    # so its calc_gt_masks reproduces argen's masks exactly; argen label reads the choice from argen.json)
    pixel_centres: str = "integer"


NOISE_MODELS = ("structured_light", "tof", "stereo")
SUPPORTS = ("auto", "board", "plane")  # plane.support values

#: output.pixel_centres values and the offset (pixels) from a file's K to the K that images are made with.
PIXEL_CENTRES = {"integer": 0.0, "half": -0.5}


def simulation_K(K, pixel_centres: str):
    """The intrinsics (3,3) that images are rendered and back-projected with, for the K (3,3) written to the files:
    the same for "integer" pixel centres; cx, cy - 0.5 for "half" (pixel (u, v) is then seen along the ray that
    the file's K gives (u + 0.5, v + 0.5))."""
    Ks = np.array(K, dtype=np.float64)
    Ks[0, 2] += PIXEL_CENTRES[pixel_centres]
    Ks[1, 2] += PIXEL_CENTRES[pixel_centres]
    return Ks


@dataclass
class TemplateConfig:
    """A whole capture template (``templates/NAME.yaml``)."""

    name: str = "linemod"
    sensor: str = "kinect_v1"  # argen/sensors/NAME.yaml: intrinsics, resolution, range and noise
    seed: int = 0
    objects: list[str] = field(default_factory=list)  # names or ids; empty = all available
    camera: CameraConfig = field(default_factory=CameraConfig)
    board: BoardConfig = field(default_factory=BoardConfig)
    placement: PlacementConfig = field(default_factory=PlacementConfig)
    clutter: ClutterConfig = field(default_factory=ClutterConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    ar: ARConfig = field(default_factory=ARConfig)
    plane: PlaneConfig = field(default_factory=PlaneConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    colour: ColourConfig = field(default_factory=ColourConfig)
    output: OutputConfig = field(default_factory=OutputConfig)


# --------------------------------------------------------------------------------------- loading


SENSORS_DIR = Path(__file__).resolve().parent / "sensors"


def available_templates() -> list[str]:
    """Names of the built-in templates."""
    return sorted(p.stem for p in TEMPLATES_DIR.glob("*.yaml"))


def available_sensors() -> list[str]:
    """Names of the built-in sensor profiles."""
    return sorted(p.stem for p in SENSORS_DIR.glob("*.yaml"))


def load_sensor(name: str) -> dict:
    """A sensor profile (``argen/sensors/NAME.yaml``): {name, description, kind, sources, camera, noise}."""
    path = SENSORS_DIR / f"{name}.yaml"
    if not path.is_file():
        raise ArgenError(f"unknown sensor '{name}' (available: {', '.join(available_sensors())})")
    data = settings.load_yaml(path, "sensor profile")
    for key in ("camera", "noise"):
        if not isinstance(data.get(key), dict):
            raise ArgenError(f"sensor profile {path.name} has no '{key}' section")
    return data


def load_template(name_or_path: str | Path, sensor: str | None = None) -> TemplateConfig:
    """Load a built-in template by name, or a YAML file by path, into a :class:`TemplateConfig`.

    The sensor profile (``sensor``, else the template's ``sensor`` key, else kinect_v1) gives the camera's
    intrinsics and resolution and the noise model; keys the template sets itself take precedence over the
    profile's, and ``--set`` (:func:`override`) over both.
    """
    path = Path(name_or_path)
    if not path.suffix:
        path = TEMPLATES_DIR / f"{name_or_path}.yaml"
        if not path.is_file():
            raise ArgenError(
                f"unknown scene template '{name_or_path}' (available: {', '.join(available_templates())})"
            )
    if not path.is_file():
        raise ArgenError(f"template file not found: {path}")
    data = settings.load_yaml(path, "template file")
    name = sensor or data.get("sensor") or TemplateConfig.sensor
    profile = load_sensor(str(name))
    data = dict(data, sensor=str(name))
    for key in ("camera", "noise"):
        own = data.get(key) or {}
        if not isinstance(own, dict):
            raise ArgenError(f"{path.name}: expected a mapping for {key}")
        data[key] = {**profile[key], **own}
    return from_dict(TemplateConfig, data, where=path.name)


def from_dict(cls: type, data: Any, where: str = "config") -> Any:
    """Build dataclass ``cls`` from a mapping, strictly (:func:`argen.settings.from_dict`), with the range checks
    of :func:`validate`."""
    return settings.from_dict(cls, data, where, check=validate)


def _check(cond: bool, where: str, msg: str) -> None:
    if not cond:
        raise ArgenError(f"{where}: {msg}")


def validate(obj: Any, where: str = "config") -> None:
    """Range checks for the values that have a physical meaning."""
    if isinstance(obj, CameraConfig):
        _check(obj.width > 0 and obj.height > 0, where, "camera width and height must be positive")
        _check(obj.fx > 0 and obj.fy > 0, where, "camera fx and fy must be positive")
        _check(0 < obj.distance[0] <= obj.distance[1], where, "camera distance must be 0 < min <= max")
        _check(0 <= obj.elevation_deg[0] <= obj.elevation_deg[1] <= 90, where,
               "camera elevation_deg must lie in [0, 90] with min <= max")
        _check(obj.azimuth_deg[0] <= obj.azimuth_deg[1], where, "camera azimuth_deg min must be <= max")
        _check(0 < obj.z_near < obj.z_far, where, "camera z_near must be positive and below z_far")
    elif isinstance(obj, BoardConfig):
        _check(obj.markers_per_side >= 2, where, "board markers_per_side must be at least 2")
        _check(obj.marker_size > 0 and obj.marker_gap >= 0 and obj.margin >= 0, where,
               "board marker_size must be positive, marker_gap and margin non-negative")
        _check(obj.print_dpi > 0 and obj.texture_px_per_m > 0, where, "board resolutions must be positive")
    elif isinstance(obj, PlacementConfig):
        _check(1 <= obj.objects_per_frame[0] <= obj.objects_per_frame[1], where,
               "placement objects_per_frame must be 1 <= min <= max")
        _check(1 <= obj.instances_per_object[0] <= obj.instances_per_object[1], where,
               "placement instances_per_object must be 1 <= min <= max")
        _check(obj.max_tries >= 1, where, "placement max_tries must be at least 1")
        _check(obj.min_gap >= 0, where, "placement min_gap must be non-negative")
        _check(0 <= obj.beside <= 1, where, "placement beside must lie in [0, 1]")
        _check(obj.stable_poses >= 1, where, "placement stable_poses must be at least 1")
        _check(0 <= obj.uniform_poses <= 1, where, "placement uniform_poses must lie in [0, 1]")
    elif isinstance(obj, ClutterConfig):
        for name in ("count", "on_board", "papers", "desk_things", "shelf_items"):
            lo, hi = getattr(obj, name)
            _check(0 <= lo <= hi, where, f"clutter {name} must be 0 <= min <= max")
        _check(0 <= obj.ring[0] <= obj.ring[1], where, "clutter ring must be 0 <= min <= max")
        _check(0 < obj.scale[0] <= obj.scale[1], where, "clutter scale must be 0 < min <= max")
        for name in ("board_cover", "near_target", "monitor", "shelf"):
            _check(0 <= getattr(obj, name) <= 1, where, f"clutter {name} must lie in [0, 1]")
    elif isinstance(obj, SceneConfig):
        _check(0 <= obj.table_margin[0] <= obj.table_margin[1], where, "scene table_margin must be 0 <= min <= max")
        _check(0 < obj.table_height[0] <= obj.table_height[1], where, "scene table_height must be 0 < min <= max")
        _check(0 <= obj.walls[0] <= obj.walls[1] <= 4, where, "scene walls must be 0 <= min <= max <= 4")
        _check(0 <= obj.wall_gap[0] <= obj.wall_gap[1], where, "scene wall_gap must be 0 <= min <= max")
        _check(0 <= obj.point_lights[0] <= obj.point_lights[1], where, "scene point_lights must be 0 <= min <= max")
        for name in ("ambient", "light_intensity", "point_light_intensity"):
            lo, hi = getattr(obj, name)
            _check(0 <= lo <= hi, where, f"scene {name} must be 0 <= min <= max")
        _check(0 <= obj.light_tint < 1, where, "scene light_tint must lie in [0, 1)")
    elif isinstance(obj, ARConfig):
        _check(obj.min_markers >= 1, where, "ar min_markers must be at least 1")
        _check(obj.max_reproj_px > 0, where, "ar max_reproj_px must be positive")
    elif isinstance(obj, PlaneConfig):
        _check(obj.support in SUPPORTS, where, f"plane support must be one of {', '.join(SUPPORTS)}, got '{obj.support}'")
        _check(obj.inlier_m > 0 and obj.inlier_per_m2 >= 0, where,
               "plane inlier_m must be positive and inlier_per_m2 non-negative")
        _check(0 < obj.max_tilt_deg <= 90, where, "plane max_tilt_deg must lie in (0, 90]")
        _check(0 < obj.centre <= 1, where, "plane centre must lie in (0, 1]")
        _check(obj.candidates >= 1 and obj.min_inliers >= 3, where,
               "plane candidates must be at least 1 and min_inliers at least 3")
        _check(obj.cell > 0 and obj.clearance >= 0, where, "plane cell must be positive and clearance non-negative")
    elif isinstance(obj, NoiseConfig):
        _check(obj.axial_a >= 0 and obj.axial_b >= 0, where, "noise axial terms must be non-negative")
        _check(obj.lateral_px >= 0, where, "noise lateral_px must be non-negative")
        _check(obj.baseline > 0 and obj.disparity_step_px >= 0, where,
               "noise baseline must be positive and disparity_step_px non-negative")
        _check(0 <= obj.min_range < obj.max_range, where, "noise range must be 0 <= min_range < max_range")
        for name in ("edge_dropout", "random_dropout"):
            _check(0 <= getattr(obj, name) <= 1, where, f"noise {name} must lie in [0, 1]")
        _check(0 < obj.grazing_deg <= 90, where, "noise grazing_deg must lie in (0, 90]")
        _check(obj.model in NOISE_MODELS, where, f"noise model must be one of {', '.join(NOISE_MODELS)}, "
                                                 f"got '{obj.model}'")
        for name in ("flying", "dark_dropout", "textureless_dropout"):
            _check(0 <= getattr(obj, name) <= 1, where, f"noise {name} must lie in [0, 1]")
        for name in ("correlated_sigma", "correlated_px", "multipath", "multipath_px", "scale_sigma",
                     "offset_sigma", "dark_level", "textureless_level"):
            _check(getattr(obj, name) >= 0, where, f"noise {name} must be non-negative")
        _check(obj.edge_fatten_px >= 0, where, "noise edge_fatten_px must be non-negative")
    elif isinstance(obj, ColourConfig):
        for name in ("shift_px", "blur_px", "noise"):
            lo, hi = getattr(obj, name)
            _check(0 <= lo <= hi, where, f"colour {name} must be 0 <= min <= max")
    elif isinstance(obj, OutputConfig):
        _check(obj.frames_per_scene >= 1, where, "output frames_per_scene must be at least 1")
        _check(obj.depth_scale > 0, where, "output depth_scale must be positive")
        _check(obj.pixel_centres in PIXEL_CENTRES, where,
               f"output pixel_centres must be {' or '.join(PIXEL_CENTRES)}, got '{obj.pixel_centres}'")


def to_dict(cfg: Any) -> dict:
    """Plain dict of a config dataclass (tuples as lists), for ``argen.json``."""
    return settings.to_dict(cfg)


def override(cfg: TemplateConfig, dotted: dict[str, Any]) -> TemplateConfig:
    """Return a copy of ``cfg`` with ``{"camera.distance": (0.5, 1.0), ...}`` applied and validated."""
    return settings.apply_sets(cfg, dotted, "options", check=validate)
