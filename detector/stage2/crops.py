"""Stage 2 data: object-centred crops of a frame's points, and their dense model-coordinate targets.

A crop is the ball of radius ``radius * diameter`` around a centre (a stage-1 box-centre vote at inference,
the ground-truth centre plus jitter in training), taken from the label file's frame points (not the network's
subsample, so an object keeps hundreds of points). Its network input expresses the points relative to the
centre in units of the ball radius. Targets, derived from the label file's instance poses: which points are the
instance's (foreground), and each foreground point's model-frame coordinates in units of the diameter,
``R.T @ (p - t) / diameter``.

Everything is pure numpy; metres; camera frame (OpenCV axes); poses map model into camera points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from detector.data.augment import CAMERA_MODES, camera_colour, normalised_colour


@dataclass
class CropConfig:
    """How crops are cut and sampled.

    radius: ball radius as a fraction of the object's diameter; num_points: points fed per crop; min_points: crops
    with fewer frame points are not used; centre_jitter: standard deviation per axis of the training crop centre
    around the true centre, as a fraction of the diameter (stage 1's centre error, which grows with the object:
    measured 0.09-0.1 of the diameter per axis on a validation capture, from 1.6 cm for the ape to 3.7 cm for the
    driller); centre_jitter_clip: its bound per axis, same unit; min_visib: training instances with a smaller
    visible fraction are left out; min_object_points: nor those with fewer labelled points; roll_deg: augmentation
    rolls a crop about the camera ray by up to this many degrees (a camera's roll about its view direction varies
    little in a capture: capture-sim draws it with a 5 degree spread, a hand-held sensor also stays near upright,
    and the support plane below an object is a cue the network should keep); colour: the colour augmentation,
    "light" (a gain of 0.8-1.2 and noise on the normalised colours), "camera"
    (:func:`detector.data.augment.camera_colour`: exposure, white balance, gamma, sometimes grey or no colour at
    all, as real cameras differ from the renderer), "camera_tone" ("camera" plus contrast and saturation gains),
    "camera_rgb" ("camera" never grey or colourless), "rank" ("camera_tone"'s changes, the network seeing each
    channel's rank among the crop's points: :func:`detector.data.augment.colour_ranks`), "grey_world" ("camera"'s
    changes, the colours balanced over the crop's points: :func:`detector.data.augment.grey_world`) or "none" (no
    colour input); neighbour: augmentation puts, with this chance, a copy of the instance's own points beside it as
    background (:func:`add_neighbour`), at a lateral distance of ``neighbour_offset`` (min, max) diameters between
    the centres: scenes such as LC-HF hold several instances of one object side by side, and a crop around one of
    them must not take its neighbour for it; shape_turns: with colour "none", an object's coordinates are also
    taught under the turns that map its shape onto itself and that only its print breaks
    (:func:`shape_only_symmetries`; the colour check then chooses among them), false: under its own symmetries only;
    negatives: with this chance each usable training instance is also tried for a negative crop
    (:func:`negative_crop`): a crop that holds no point of the object it is asked about, all of whose points are
    background, so that the network learns to answer "not here" to a stage-1 detection on clutter or of the wrong
    object; about half the tries give none (the asked object is in the ball, or the ball holds too few points);
    0 = none, the first design; part_turns: an object with a part symmetry (a mug's handle breaks its turns about
    its body's axis: ``argen.models.symmetry.find_part_symmetry``) has the coordinates of a crop that does not show
    its odd part (:class:`PartTurns`) taught up to those turns as well, since nothing in such a crop tells them
    apart; false: under its own symmetries only, as if the odd part were always in sight.
    """

    radius: float = 0.7
    num_points: int = 256
    min_points: int = 32
    centre_jitter: float = 0.1
    centre_jitter_clip: float = 0.25
    min_visib: float = 0.1
    min_object_points: int = 30
    roll_deg: float = 15.0
    colour: str = "light"
    neighbour: float = 0.0
    neighbour_offset: tuple[float, float] = (0.5, 1.0)
    shape_turns: bool = True
    negatives: float = 0.0
    part_turns: bool = True

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    @classmethod
    def from_dict(cls, d: dict) -> "CropConfig":
        """A CropConfig from :meth:`to_dict`'s mapping."""
        d = dict(d)
        if "neighbour_offset" in d:
            d["neighbour_offset"] = tuple(d["neighbour_offset"])
        return cls(**d)


def ball_rows(xyz: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Rows of the points (N,3) metres within ``radius`` metres of ``centre`` (3,). Returns (k,) int64, sorted.
    Only the points whose depth is within ``radius`` of the centre's are measured (a frame's slab around an object
    holds a small share of its points); the slab is a millionth wider than the ball, so rounding cannot leave out a
    point the ball holds: the same rows as measuring them all."""
    p, c = np.asarray(xyz, np.float64), np.asarray(centre, np.float64)
    near = np.flatnonzero(np.abs(p[:, 2] - c[2]) <= radius * (1 + 1e-6))
    d2 = np.sum((p[near] - c) ** 2, axis=1)
    return near[d2 <= radius * radius]


def sample_crop(rows: np.ndarray, num_points: int, rng: np.random.Generator) -> np.ndarray:
    """``num_points`` of ``rows``: a random subset when there are enough, else all of them and random repeats."""
    if len(rows) >= num_points:
        return rows[np.sort(rng.choice(len(rows), num_points, replace=False))]
    return np.concatenate([rows, rows[rng.choice(len(rows), num_points - len(rows), replace=True)]])


def crop_input(features: np.ndarray, rows: np.ndarray, centre: np.ndarray, radius: float,
               normalisation: dict) -> np.ndarray:
    """Network input of a crop: (n, 9) float32 ``[(p - centre) / radius, colour (normalised), normal]``.

    features: (N,9) float32 label-file features, colour in [0, 1]; rows: (n,) the crop's rows; centre: (3,)
    metres; radius: metres; normalisation: {"rgb_mean", "rgb_std"} (``detector.data.augment.NORMALISATION``).
    """
    out = np.array(np.asarray(features)[rows], dtype=np.float32, copy=True)
    out[:, 3:6] = normalised_colour(out[:, 3:6], normalisation)
    out[:, :3] = (out[:, :3] - np.asarray(centre, np.float32)) / np.float32(radius)
    return out


def model_coordinates(xyz: np.ndarray, R: np.ndarray, t: np.ndarray, diameter: float) -> np.ndarray:
    """Model-frame coordinates of camera points in units of the diameter: ``R.T @ (p - t) / diameter``.

    xyz: (n,3) metres; R (3,3), t (3,) T_cam_model. Returns (n,3) float32.
    """
    return (((np.asarray(xyz, np.float64) - t) @ np.asarray(R, np.float64)) / diameter).astype(np.float32)


def symmetry_targets(coords: np.ndarray, sym_transforms: np.ndarray, diameter: float) -> np.ndarray:
    """The model coordinates under every symmetry of the object: the pose ``T @ S`` looks the same as ``T``, and
    a point with coordinates x has coordinates ``S^-1 x`` under it.

    coords: (n,3) in diameters; sym_transforms: (S,4,4) model-frame symmetries (identity first), metres.
    Returns (S,n,3) float32 in diameters.
    """
    S = np.asarray(sym_transforms, np.float64)
    inv = np.linalg.inv(S)
    x = np.asarray(coords, np.float64) * diameter
    out = np.einsum("sij,nj->sni", inv[:, :3, :3], x) + inv[:, None, :3, 3]
    return (out / diameter).astype(np.float32)


def shape_only_symmetries(sym_transforms: np.ndarray, shape_turns: np.ndarray) -> np.ndarray:
    """The symmetries a stage 2 without colour input is trained under: the object's own, each followed by every turn
    that maps its shape onto itself but that only its print breaks (``argen.models.texture.shape_symmetries``). A
    network that sees geometry only cannot tell those turns apart, so it is not pulled toward their mean; which way
    round the object lies is then the colour check's to choose (:mod:`detector.geometry.colour_check`).

    sym_transforms: (S,4,4) model frame, metres, identity first; shape_turns: (T,4,4), not the identity (T may be 0).
    Returns (S*(T+1),4,4) float32, identity first.
    """
    S = np.asarray(sym_transforms, np.float64).reshape(-1, 4, 4)
    turns = np.asarray(shape_turns, np.float64).reshape(-1, 4, 4)
    both = np.concatenate([np.eye(4)[None], turns])
    return np.einsum("sij,tjk->stik", S, both).reshape(-1, 4, 4).astype(np.float32)


#: A crop point shows the odd part when it lies within this many diameters of one of the odd part's samples (a
#: third of the spacing of ``argen``'s 50000 surface samples on the YCB mug is 1 mm; scan noise and a part's rim
#: are more).
ODD_REACH = 0.03
#: A crop shows its object's odd part when at least this many of its foreground points do.
ODD_SEEN = 5


@dataclass
class PartTurns:
    """What stage 2's training needs of an object's part symmetry (``argen.models.symmetry.find_part_symmetry``).

    symmetries: (S*(P+1),4,4) float32, model frame, metres: its own symmetries, each followed by every part turn
    (identity first), which a crop that does not show the odd part is taught under; odd: cKDTree of the odd part's
    samples (K,3) metres, model frame; diameter: metres.
    """

    symmetries: np.ndarray
    odd: cKDTree
    diameter: float

    @classmethod
    def build(cls, sym_transforms: np.ndarray, part_symmetries: np.ndarray, odd_points: np.ndarray,
              diameter: float) -> "PartTurns | None":
        """From the object's own symmetries (S,4,4), its part turns (P,4,4) and odd points (K,3), metres; None when
        it has no part symmetry (P or K = 0)."""
        turns = np.asarray(part_symmetries, np.float64).reshape(-1, 4, 4)
        odd = np.asarray(odd_points, np.float64).reshape(-1, 3)
        if not len(turns) or not len(odd):
            return None
        return cls(shape_only_symmetries(sym_transforms, turns), cKDTree(odd), float(diameter))

    def shown(self, coords: np.ndarray) -> bool:
        """Whether foreground points with model coordinates ``coords`` (n,3) in diameters show the odd part: at
        least ``ODD_SEEN`` of them lie within ``ODD_REACH`` diameters of its samples."""
        if len(coords) < ODD_SEEN:
            return False
        d = self.odd.query(np.asarray(coords, np.float64) * self.diameter, distance_upper_bound=ODD_REACH * self.diameter)[0]
        return int(np.isfinite(d).sum()) >= ODD_SEEN

    def crop_symmetries(self, own: np.ndarray, coords: np.ndarray) -> np.ndarray:
        """The symmetries a crop's coordinates are taught under: ``own`` (S,4,4) when its foreground points'
        coordinates (n,3) in diameters show the odd part, else :attr:`symmetries`."""
        return own if self.shown(coords) else self.symmetries


@dataclass
class CropFrame:
    """The part of a labelled frame that :func:`training_crop` reads (duck-typed like ``argen.h5.FrameLabels``).

    features: (n,9) float32 label features; instance: (n,) int32 row in ``instances``, -1 = background;
    instances: the frame's ``argen.h5.InstanceTable``."""

    features: np.ndarray
    instance: np.ndarray
    instances: object

    @property
    def nbytes(self) -> int:
        return int(self.features.nbytes + self.instance.nbytes)


def crop_region(frame, diameters: dict[int, float], cfg: CropConfig) -> CropFrame:
    """The points of ``frame`` (an ``argen.h5.FrameLabels``) that a training crop can hold, in their order.

    A crop around instance g is a ball of ``cfg.radius`` diameters around its centre jittered by at most
    ``cfg.centre_jitter_clip`` diameters per axis, so it lies within ``radius + clip * sqrt(3)`` diameters of the
    true centre (with ``cfg.negatives``, as far as :func:`negative_reach` says a negative crop beside it reaches,
    which keeps most of a frame: 1.7 times the points on the ycbv template);
    the instance's own points (the neighbour augmentation copies them) are kept too. Instances of
    objects not in ``diameters`` (obj_id -> metres) hold no crop. Because the kept points keep their order,
    :func:`training_crop` cuts the same crops from the region as from the whole frame (a third of a 30000-point
    frame of the linemod template), which is what makes it worth keeping in memory between epochs.
    """
    xyz = np.asarray(frame.features[:, :3], np.float64)
    inst = frame.instances
    keep = np.zeros(len(xyz), bool)
    reach = cfg.radius + cfg.centre_jitter_clip * np.sqrt(3.0)
    largest = max(diameters.values(), default=0.0)
    for g in range(len(inst)):
        dia = diameters.get(int(inst.obj_id[g]))
        if dia is None:
            continue
        far = reach * dia if cfg.negatives <= 0 else max(reach * dia, negative_reach(dia, largest, cfg))
        keep[ball_rows(xyz, inst.control_points[g][8], far + 0.001)] = True  # 1 mm against rounding
        keep |= np.asarray(frame.instance) == g
    return CropFrame(np.ascontiguousarray(frame.features[keep]), np.ascontiguousarray(frame.instance[keep]), inst)


def jittered_centre(centre: np.ndarray, diameter: float, cfg: CropConfig, rng: np.random.Generator) -> np.ndarray:
    """A training crop centre: ``centre`` (3,) metres plus Gaussian jitter per axis of ``cfg.centre_jitter *
    diameter`` metres, clipped at ``cfg.centre_jitter_clip * diameter``. Returns (3,) float64."""
    lim = cfg.centre_jitter_clip * diameter
    return np.asarray(centre, np.float64) + np.clip(rng.normal(0.0, cfg.centre_jitter * diameter, 3), -lim, lim)


def ray_roll(centre: np.ndarray, angle: float) -> np.ndarray:
    """The rotation Q (3,3) float64 by ``angle`` radians about the camera ray through ``centre`` (3,) metres."""
    axis = np.asarray(centre, np.float64) / np.linalg.norm(centre)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def roll_about_ray(points: np.ndarray, centre: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Rotate points about the camera ray through ``centre`` by ``angle`` radians (a camera roll seen from the crop).

    points: (n,3) metres; centre: (3,). Returns the rotated points (n,3) and the rotation Q (3,3) (p' = Q (p - c) + c,
    :func:`ray_roll`).
    """
    Q = ray_roll(centre, angle)
    return (np.asarray(points, np.float64) - centre) @ Q.T + centre, Q


def roll_crop_input(feats: np.ndarray, centre: np.ndarray, angle: float) -> np.ndarray:
    """A crop's network input (n,9) (:func:`crop_input`, centred on ``centre`` (3,) metres) rolled about the camera
    ray through ``centre`` by ``angle`` radians, as :func:`roll_about_ray` rolls the points: positions and normals
    turned, colours kept. Returns a new array; the input itself for angle 0."""
    if angle == 0:
        return feats
    Q = ray_roll(centre, angle).astype(np.float32)
    out = np.array(feats, dtype=np.float32, copy=True)
    out[:, :3] = out[:, :3] @ Q.T
    out[:, 6:9] = out[:, 6:9] @ Q.T
    return out


def add_neighbour(own_xyz: np.ndarray, own_feats: np.ndarray, centre: np.ndarray, diameter: float,
                  offset: tuple[float, float], rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A second instance of an object beside it, made of the object's own points: own_xyz (m,3) metres and
    own_feats (m,9) label features, turned about the camera ray through ``centre`` (3,) metres (the instance's
    centre) by up to 30 degrees (it stays upright, as instances standing side by side are) and moved across the ray
    by a random ``offset`` (min, max) times ``diameter``. Returns the copy's points (m,3) metres and features (m,9)
    (xyz replaced, normals turned with the points)."""
    ray = np.asarray(centre, np.float64) / np.linalg.norm(centre)
    side = np.cross(ray, rng.normal(size=3))
    side /= np.linalg.norm(side)
    p, Q = roll_about_ray(own_xyz, centre, np.deg2rad(rng.uniform(-30.0, 30.0)))
    p = p + side * rng.uniform(*offset) * diameter
    f = np.array(own_feats, dtype=np.float32, copy=True)
    f[:, :3] = p.astype(np.float32)
    f[:, 6:9] = f[:, 6:9] @ Q.T.astype(np.float32)
    return p, f


def training_crop(frame, g: int, diameter: float, sym_transforms: np.ndarray, cfg: CropConfig,
                  rng: np.random.Generator, normalisation: dict, augment: bool = False,
                  part: PartTurns | None = None) -> dict | None:
    """One training crop around instance ``g`` of ``frame`` (an ``argen.h5.FrameLabels``, or its
    :func:`crop_region`, which gives the same crop), or None (too few points).

    Returns {"features": (n,9) float32 network input, "fg": (n,) float32 1 on the instance's points,
    "coords": (S,n,3) float32 model coordinates (diameters) of every point under each symmetry (meaningful on
    foreground points only), "centre": (3,) metres}. With ``augment`` the crop is rolled about the camera ray by up
    to ``cfg.roll_deg`` (model coordinates do not change), colour is changed (``cfg.colour``), points get 1 mm
    noise and, with chance ``cfg.neighbour``, a copy of the instance stands beside it as background
    (:func:`add_neighbour`). With ``part`` (the object's :class:`PartTurns`), a crop whose foreground does not show
    the odd part has its coordinates under the part turns too.
    """
    inst = frame.instances
    xyz = np.asarray(frame.features[:, :3], np.float64)
    features, instance = frame.features, np.asarray(frame.instance)
    radius = cfg.radius * diameter
    centre = jittered_centre(inst.control_points[g][8], diameter, cfg, rng)
    rows = ball_rows(xyz, centre, radius)
    if len(rows) < cfg.min_points:
        return None
    if augment and cfg.neighbour > 0 and rng.random() < cfg.neighbour:
        # the crop's points plus a copy of the instance beside it (background, instance -2), as one small frame
        own = np.flatnonzero(instance == g)
        p, f = add_neighbour(xyz[own], np.asarray(features)[own], inst.control_points[g][8], diameter,
                             cfg.neighbour_offset, rng)
        keep = np.sum((p - centre) ** 2, axis=1) <= radius * radius
        if keep.any():  # copied points within 5 mm of a crop point would interpenetrate it: dropped
            keep[keep] = cKDTree(xyz[rows]).query(p[keep], distance_upper_bound=0.005)[0] >= 0.005
        xyz = np.concatenate([xyz[rows], p[keep]])
        features = np.concatenate([np.asarray(features)[rows], f[keep]])
        instance = np.concatenate([instance[rows], np.full(int(keep.sum()), -2, instance.dtype)])
        rows = np.arange(len(xyz))
    rows = sample_crop(rows, cfg.num_points, rng)
    fg = instance[rows] == g
    coords = model_coordinates(xyz[rows], inst.R[g], inst.t[g], diameter)
    feats = crop_input(features, rows, centre, radius, normalisation)
    if augment:
        augment_crop(feats, xyz[rows], np.asarray(features)[rows, 3:6], centre, radius, cfg, rng, normalisation)
    if part is not None:
        sym_transforms = part.crop_symmetries(sym_transforms, coords[fg])
    return {"features": feats, "fg": fg.astype(np.float32),
            "coords": symmetry_targets(coords, sym_transforms, diameter), "centre": centre}


def augment_crop(feats: np.ndarray, xyz: np.ndarray, rgb: np.ndarray, centre: np.ndarray, radius: float,
                 cfg: CropConfig, rng: np.random.Generator, normalisation: dict) -> None:
    """Training augmentation of a crop's network input ``feats`` (n,9), in place: a roll about the camera ray
    through ``centre`` (3,) metres by up to ``cfg.roll_deg`` and 1 mm noise on the points ``xyz`` (n,3) metres, and
    ``cfg.colour``'s colour change of their colours ``rgb`` (n,3) in [0, 1]; radius: the crop's, metres."""
    p, Q = roll_about_ray(xyz, centre, np.deg2rad(rng.uniform(-cfg.roll_deg, cfg.roll_deg)))
    p = p + rng.normal(0.0, 0.001, p.shape)
    feats[:, :3] = ((p - centre) / radius).astype(np.float32)
    feats[:, 6:9] = (feats[:, 6:9] @ Q.T.astype(np.float32))
    if cfg.colour in CAMERA_MODES:
        feats[:, 3:6] = normalised_colour(camera_colour(rgb, rng, **CAMERA_MODES[cfg.colour]), normalisation)
    elif cfg.colour == "light":
        feats[:, 3:6] = feats[:, 3:6] * np.float32(rng.uniform(0.8, 1.2)) + rng.normal(0, 0.1, 3).astype(np.float32)


def negative_reach(diameter: float, largest: float, cfg: CropConfig) -> float:
    """How far from an instance's true centre a negative crop beside it (:func:`negative_crop`) can reach, metres:
    its centre lies within ``diameter`` (the instance's, metres) of it plus a push of ``0.3 * largest`` (the largest
    crop object's diameter) along the ray, its ball's radius is at most ``cfg.radius * largest``; and the wrong-class
    crop at the jittered centre stays within the same bound."""
    return max(diameter, cfg.centre_jitter_clip * np.sqrt(3.0) * diameter) + (0.3 + cfg.radius) * largest


def negative_crop(frame, g: int, diameter: float, diameters: dict[int, float], cfg: CropConfig,
                  rng: np.random.Generator, normalisation: dict, augment: bool = False) -> dict | None:
    """A negative training crop beside instance ``g`` of ``frame`` (as :func:`training_crop`'s): a crop asked about
    an object that has no point in it, so all of its points are background.

    diameters: {object id: diameter metres} of the objects a crop may be asked about (the network's classes, g's
    own among them);
    diameter: instance g's, metres. Half the time the crop is cut around g's jittered centre and asked about
    another object (a stage-1 detection of the wrong object); otherwise it is centred on a random point of the frame
    within ``diameter`` of g's centre that is not g's, pushed 0.3 of the asked object's diameter away from the
    camera (a detection's centre lies behind the surface it saw), and asked about any object (a detection on
    clutter, or on the desk beside an object). Returns {"features": (n,9) float32, "fg": (n,) zeros, "obj_id":
    the object asked about, "centre": (3,) metres}, or None when the asked object has points in the ball or the
    ball holds too few points.
    """
    inst = frame.instances
    xyz = np.asarray(frame.features[:, :3], np.float64)
    instance = np.asarray(frame.instance)
    ids = sorted(diameters)
    own = int(inst.obj_id[g])
    if rng.random() < 0.5:
        choices = [o for o in ids if o != own]
        if not choices:
            return None
        oid = choices[int(rng.integers(len(choices)))]
        centre = jittered_centre(inst.control_points[g][8], diameter, cfg, rng)
    else:
        oid = ids[int(rng.integers(len(ids)))]
        near = ball_rows(xyz, inst.control_points[g][8], diameter)
        near = near[instance[near] != g]
        if len(near) == 0:
            return None
        p = xyz[near[int(rng.integers(len(near)))]]
        centre = p + 0.3 * diameters[oid] * p / np.linalg.norm(p)
    radius = cfg.radius * diameters[oid]
    rows = ball_rows(xyz, centre, radius)
    asked = np.flatnonzero(np.asarray(inst.obj_id) == oid)
    if len(rows) < cfg.min_points or np.isin(instance[rows], asked).any():
        return None
    rows = sample_crop(rows, cfg.num_points, rng)
    feats = crop_input(frame.features, rows, centre, radius, normalisation)
    if augment:
        augment_crop(feats, xyz[rows], np.asarray(frame.features)[rows, 3:6], centre, radius, cfg, rng, normalisation)
    return {"features": feats, "fg": np.zeros(len(rows), np.float32), "obj_id": oid, "centre": centre}
