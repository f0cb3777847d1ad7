"""The types the geometry works with: :class:`GeometryConfig` (voting, ICP and score settings), a
:class:`Detection` and :class:`ObjectInfo` (each object's control points, diameter and model points, with the
cached model cloud and surface). Metres; poses map model into camera points (``x_cam = R @ x_model + t``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree


@dataclass
class GeometryConfig:
    """Options of the geometry: voting, Kabsch, ICP, scores and thresholds.

    tau: confidence threshold; cell: voting voxel size, metres; min_votes: fewest votes an instance needs;
    mode_radius: > 0 clusters the centre votes around their density modes within this fraction of the diameter
    (:func:`vote_modes`; instances side by side stay apart) instead of in touching ``cell`` voxels;
    nms_fraction: posed box centres closer than this fraction of the object's diameter are one detection;
    nms_across_objects: the output keeps one detection per place whatever its object: posed box centres of two
    objects closer than ``nms_fraction`` of the smaller diameter are one detection, the higher-scoring
    (:func:`nms`; a two-stage model poses a stage-1 detection as each object its points make likely, and without it
    a wrong object's pose stayed beside the right one's: an eggbox on a glue in 25 of the 27 false eggboxes of a
    simulated LineMOD test capture, RESULTS.md);
    inlier_fraction: votes farther than this fraction of the diameter from the median are outliers;
    icp: refine with ICP; icp_distance: ICP correspondence distance as a fraction of the diameter;
    icp_kernel: Tukey robust-loss scale as a fraction of the diameter (0 = plain least squares);
    icp_iterations: ICP iteration limit; icp_min_points: fewest scene points to run ICP;
    icp_trim: share of the scene points (the best-fitting ones) whose point-to-plane RMS decides whether
    the ICP pose is kept (see :func:`fit_rms`); icp_gate: a scene point farther than this fraction of the
    diameter from every model point counts as an outlier at that distance; icp_starts: ICP runs from the
    detection's pose and from up to ``icp_starts - 1`` of its ``alternatives`` and keeps the best-fitting result
    (a wrong-way first pose is a local minimum that ICP alone cannot leave); icp_half_turns: ICP also starts from
    the detection's pose turned half way about each of the object's axes through its centroid (:func:`half_turns`):
    a pose that shows the object's other side fits its points nearly as well and ICP cannot leave it (measured on
    the simulated linemod test capture: the duck and the can turned about their upright axis); icp_min_gain: the ICP pose is kept
    only when it lowers that trimmed RMS by at least this fraction of the diameter (a smaller gain is within what
    the model's point sampling itself contributes, and on a few points of a smooth surface ICP can slide a right
    pose by centimetres for such a gain); icp_depth_margin: a consistency difference in [0, 1] that lets the frame's
    depth choose a detection's ICP candidate: of its results whose depth consistency (the depth check's measure on
    250 model points, :func:`detector.geometry.verify.pose_consistency`) is within this of the most consistent
    one's, the best-fitting; the candidate is then also accepted when it is more than this more consistent than
    the detection's unrefined pose, whatever the fits (None: off, the fits alone decide). The trimmed fit leaves out
    the worst-fitting points, and those are where a half-turned pose shows its difference (a can's spout posed where
    the sensor sees the desk behind). Not the default: on the simulated captures it found a few more poses and let a
    few more wrong ones through the depth check (RESULTS.md); icp_own_margin: the result of ICP from the
    detection's own pose is the candidate unless the best other result's trimmed RMS is lower than its by more than
    this share of that best RMS (0: off, the best fit is the candidate): from a half-turned start ICP can end on
    the wrong way round of an object whose sides look alike, fitting the points a little better by chance (the
    sensor's noise). Not the default: a mug's right turn about its body, its handle hidden, often fits only a
    little better (RESULTS.md); icp_points: ICP and its acceptance test use at most this many of a
    detection's scene points, evenly spread over them (0 = all; their cost grows with the points, and a stage 2
    that pools several crop samples hands over several hundred), the score after ICP uses them all;
    propagate: metres, a frame point belongs to a detection when its ``owner_votes`` nearest predicted points
    within this distance are all that detection's members (ICP points);
    centre_votes: instances from the box-centre votes alone (a two-stage model's stage 1, whose corners are
    not trained): the detection's centre is their robust mean and its orientation is left to stage 2;
    min_score: final detections scoring less are dropped (with ICP, by their score after ICP);
    min_score_unrefined: the threshold of the unrefined detections (None: ``min_score``); a two-stage detection's
    support before ICP is lower than after it, so the two get thresholds of their own;
    support_distance: a two-stage detection's score is the share of its points within this fraction of the
    diameter of the model surface under its pose (:func:`surface_support`), recomputed after ICP;
    support_floor: metres, that distance is at least this much (:func:`support_radius`): a depth sensor's error
    does not shrink with the object, and 2 % of a small object's diameter (2 mm for the ape) is below a Kinect
    v1's median depth error near 1 m (2.4 mm), so right poses of small objects would score low;
    depth_check: lower the score of a detection whose pose the frame's depth contradicts
    (:func:`detector.geometry.verify.depth_checked`: the share of its model points the sensor saw rather than saw
    past); needs the frame's cloud; depth_tolerance: the check's depth tolerance in multiples of the support
    distance (the free-space margin is twice it); depth_consistent: a detection at least this consistent keeps its
    score, a less consistent one's is scaled by consistency / depth_consistent (on a simulated LineMOD capture, 97 %
    of the right poses after ICP are at least 0.85 consistent, and 3 % of the far-wrong ones);
    depth_consistent_refined: the same for the poses after ICP, which fit their points closer than the poses before
    it (None: ``depth_consistent``);
    other_classes: a two-stage model also poses each stage-1 detection as every other object whose class its
    points give at least this mean probability (:func:`detector.geometry.voting.other_classes`); > 1: never;
    colour_check: turn a detection of an object whose print breaks its shape's symmetries (a printed box) to the
    way round the frame's colours match (:func:`detector.geometry.colour_check.colour_checked`); needs the frame's
    colours and a model whose label file carried the print (``ObjectInfo.texture``); part_check: turn a detection of
    an object with a part symmetry (a mug, whose handle breaks its turns about its body) about its axis to where
    the frame's depth allows its odd part to be (:func:`detector.geometry.part_check.part_checked`); needs the
    frame's cloud and a model whose label file carried the part symmetry (``ObjectInfo.part_symmetries``);
    continuation_check: lower the score of a detection whose model the frame's surfaces run on past, in the planes of
    its faces (:func:`detector.geometry.verify.continuation_checked`: a pose on part of a larger thing, a box on a
    keyboard's edge; the frame's dominant plane, the table, counts only for a pose lying in it); needs the frame's
    cloud and the objects' surface normals (label files written since 2026-12-07 carry them, and so do the models
    trained on them; on by default); with ICP only the poses after it are checked unless an evaluation asks for
    both (:func:`detector.infer.estimate`); continuation_limit:
    continued frame points per explained one above which the score is scaled by the square root of limit / ratio
    (on the 10 ycbv_real frames, 8 sampling seeds, ``ycbv3.pt``'s poses within 2 cm of their object are at most
    0.025, its other poses 0.037 at the 10th percentile, median about 0.07; ``lm8.pt``'s right poses on a
    simulated LineMOD capture about 0.02 at the 90th percentile, a few 0.04-0.06); continuation_tolerance: metres,
    a frame point this close to the posed model is explained, and this close to a face's plane lies in it;
    continuation_reach: the frame points within this fraction of the diameter of the model's visible surface are
    looked at; continuation_gap: metres, a continued point lies at least this far from the model (nearer ones may be the
    object's own points, off its model by the sensor's noise: a Kinect v1's at 1 m).
    """

    tau: float = 0.8
    cell: float = 0.02
    min_votes: int = 3
    mode_radius: float = 0.0
    nms_fraction: float = 0.5
    nms_across_objects: bool = True
    inlier_fraction: float = 0.15
    icp: bool = False
    icp_distance: float = 0.2
    icp_kernel: float = 0.0
    icp_iterations: int = 30
    icp_min_points: int = 30
    icp_trim: float = 0.7
    icp_gate: float = 0.05
    icp_starts: int = 8
    icp_half_turns: bool = True
    icp_min_gain: float = 0.001
    icp_depth_margin: float | None = None
    icp_own_margin: float = 0.0
    icp_points: int = 0
    support_distance: float = 0.02
    support_floor: float = 0.004
    propagate: float = 0.01
    owner_votes: int = 3
    centre_votes: bool = False
    min_score: float = 0.0
    min_score_unrefined: float | None = None
    depth_check: bool = True
    depth_tolerance: float = 2.0
    depth_consistent: float = 0.85
    depth_consistent_refined: float | None = None
    other_classes: float = 0.1
    colour_check: bool = True
    part_check: bool = True
    continuation_check: bool = True
    continuation_limit: float = 0.03
    continuation_tolerance: float = 0.005
    continuation_reach: float = 0.3
    continuation_gap: float = 0.01


@dataclass
class Detection:
    """One detected object instance.

    obj_id: object id; score: mean confidence of its votes x share of kept votes in [0, 1];
    R: (3,3) float64; t: (3,) float64 metres (model -> camera); support: number of votes;
    control_points: (9,3) float64 metres, the aggregated predicted control points (camera frame);
    members: (S,) int64 rows of the prediction arrays that voted for it; refined: the ICP pose was kept;
    icp: what ICP did - "" (not run), "accepted", "rejected" (it did not improve the fit: pose unchanged),
    "skipped" (too few scene points);
    points: (P,) int64 rows of the frame cloud that are this instance's (a two-stage model's crop foreground),
    or None (ICP then carries ``members`` to the cloud); alternatives: other candidate poses [(R, t), ...], best
    first (a two-stage model's other verified RANSAC hypotheses), from which ICP also starts; other_class: a copy of
    a stage-1 detection as another object (:func:`detector.geometry.voting.other_classes`).
    """

    obj_id: int
    score: float
    R: np.ndarray
    t: np.ndarray
    support: int
    control_points: np.ndarray
    members: np.ndarray = field(repr=False)
    refined: bool = False
    icp: str = ""
    points: np.ndarray | None = field(default=None, repr=False)
    alternatives: list | None = field(default=None, repr=False)
    other_class: bool = False

    @property
    def pose(self) -> np.ndarray:
        """(4,4) float64 T_cam_model, metres."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T


def make_model_cloud(model_points: np.ndarray):
    """An open3d cloud of model points (metres) with estimated normals (their sign does not matter)."""
    # lazy: open3d loads in about a second; only ICP and the fit measure need it
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(model_points, np.float64)))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(12))
    return pc


def half_turns(model_points: np.ndarray) -> np.ndarray:
    """The turns by 180 degrees about the model frame's x, y and z axes through the centroid of an object's surface
    points, as (3,4,4) float64 model-frame transforms x -> F (x - c) + c.

    model_points: (P,3) metres, model frame. A half turn about the centroid keeps the object where it was; the axes
    are the mesh's own, which a mesh made of an object (BOP's models, a CAD export) aligns with its upright and its
    sides. Measured against the shape's principal axes on the simulated linemod test capture: 85.2 against 84.8 %
    ADD(-S) with ICP, the duck 90.2 against 83.3 (its upright is not a principal axis)."""
    x = np.asarray(model_points, np.float64)
    c = x.mean(axis=0)
    out = np.tile(np.eye(4), (3, 1, 1))
    for k in range(3):
        F = -np.eye(3)
        F[k, k] = 1.0  # 180 degrees about axis k
        out[k, :3, :3], out[k, :3, 3] = F, c - F @ c
    return out


def same_mesh(diameter: float, other: float) -> bool:
    """Whether two object tables' entries under one id are of the same mesh, by their diameters (metres): equal to
    1e-4 of ``diameter``. Surface samples are taken from one table into another only then
    (:meth:`ObjectInfo.take_surfaces`, :func:`detector.checkpoint.add_surfaces`)."""
    return abs(float(other) - float(diameter)) <= 1e-4 * max(float(diameter), 1e-9)


@dataclass
class ObjectInfo:
    """What the geometry needs of each object, by obj_id.

    control_points: {obj_id: (9,3) metres model frame}; diameters: {obj_id: metres};
    model_points: {obj_id: (P,3) metres model frame}; shape_symmetries: {obj_id: (T,4,4)} the turns that map
    an object's shape onto itself but that its print breaks (only objects that have them and a print);
    texture: {obj_id: ((N,3) metres model frame, (N,3) RGB in [0, 1])} surface points and their colours, for the
    same objects (:func:`detector.geometry.colour_check.colour_checked`); part_symmetries: {obj_id: (P,4,4)} the
    turns by k x 360 / (P + 1) degrees (k = 1..P, in order) about an axis that map all of an object's surface but an
    odd part onto itself, and odd_points: {obj_id: (K,3) metres model frame} samples of that part, for the objects
    that have one (``argen.models.symmetry.find_part_symmetry``; :func:`detector.geometry.part_check.part_checked`);
    surfaces: {obj_id: ((S,3) metres model frame, (S,3) outward unit normals)} surface samples with their mesh
    normals, for the objects whose table carried them (:func:`detector.geometry.verify.continuation_checked`).
    """

    control_points: dict[int, np.ndarray]
    diameters: dict[int, float]
    model_points: dict[int, np.ndarray]
    shape_symmetries: dict[int, np.ndarray] = field(default_factory=dict)
    texture: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    part_symmetries: dict[int, np.ndarray] = field(default_factory=dict)
    odd_points: dict[int, np.ndarray] = field(default_factory=dict)
    surfaces: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    _clouds: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_table(cls, table) -> "ObjectInfo":
        """From an ``argen.h5.ObjectTable`` or the checkpoint's plain-list object dict."""
        get = (lambda k: table[k]) if isinstance(table, dict) else (lambda k: getattr(table, k))
        ids = [int(i) for i in get("ids")]
        cps, dia, mp = get("control_points"), get("diameters"), get("model_points")

        def optional(key: str) -> list:  # tables written before a field existed lack it
            try:
                got = get(key)
            except (KeyError, AttributeError):
                return []
            return list(got) if got is not None else []

        turns, tex_p, tex_c = optional("shape_symmetries"), optional("texture_points"), optional("texture_colours")
        textured = [k for k in range(len(ids)) if k < min(len(turns), len(tex_p), len(tex_c))
                    and len(turns[k]) and len(tex_p[k]) and len(tex_p[k]) == len(tex_c[k])]
        parts, odd = optional("part_symmetries"), optional("odd_points")
        with_part = [k for k in range(len(ids)) if k < min(len(parts), len(odd)) and len(parts[k]) and len(odd[k])]
        sp, sn = optional("surface_points"), optional("surface_normals")
        with_surface = [k for k in range(len(ids)) if k < min(len(sp), len(sn)) and len(sp[k])
                        and len(sp[k]) == len(sn[k])]
        return cls({i: np.asarray(cps[k], np.float64) for k, i in enumerate(ids)},
                   {i: float(dia[k]) for k, i in enumerate(ids)},
                   {i: np.asarray(mp[k], np.float64) for k, i in enumerate(ids)},
                   {ids[k]: np.asarray(turns[k], np.float64).reshape(-1, 4, 4) for k in textured},
                   {ids[k]: (np.asarray(tex_p[k], np.float64).reshape(-1, 3),
                             np.asarray(tex_c[k], np.float64).reshape(-1, 3) / 255.0) for k in textured},
                   {ids[k]: np.asarray(parts[k], np.float64).reshape(-1, 4, 4) for k in with_part},
                   {ids[k]: np.asarray(odd[k], np.float64).reshape(-1, 3) for k in with_part},
                   {ids[k]: (np.asarray(sp[k], np.float64).reshape(-1, 3), np.asarray(sn[k], np.float64).reshape(-1, 3))
                    for k in with_surface})

    def cloud(self, obj_id: int):
        """The cached open3d model cloud with normals of ``obj_id``."""
        if obj_id not in self._clouds:
            self._clouds[obj_id] = make_model_cloud(self.model_points[obj_id])
        return self._clouds[obj_id]

    def take_surfaces(self, other: "ObjectInfo") -> list[int]:
        """Copy into ``surfaces`` the surface samples and normals of ``other`` (e.g. a label file's objects) for the
        objects this one has without them, where the diameters say they are the same mesh (:func:`same_mesh`);
        returns the ids taken, ascending. For a model trained before its table carried the normals."""
        taken = [k for k in sorted(other.surfaces) if k in self.diameters and k not in self.surfaces
                 and k in other.diameters and same_mesh(self.diameters[k], other.diameters[k])]
        self.surfaces.update({k: other.surfaces[k] for k in taken})
        return taken

    def box_centres(self) -> dict[int, np.ndarray]:
        """Each object's box centre, (3,) metres in its model frame (its last control point): where a posed object
        stands is ``R @ c + t``, wherever its mesh puts the origin."""
        return {oid: np.asarray(cps[8], np.float64) for oid, cps in self.control_points.items()}

    def surface_spacing(self, obj_id: int) -> float:
        """The median distance (metres) between neighbouring samples of ``obj_id``'s surface (one in ``surfaces``),
        cached."""
        key = ("spacing", obj_id)
        if key not in self._clouds:
            pts = self.surfaces[obj_id][0]
            self._clouds[key] = float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1])) if len(pts) > 1 else 0.0
        return self._clouds[key]

    def half_turns(self, obj_id: int) -> np.ndarray:
        """(3,4,4) the model-frame half turns of ``obj_id`` about its axes through its centroid (:func:`half_turns`),
        cached."""
        key = ("half_turns", obj_id)
        if key not in self._clouds:
            self._clouds[key] = half_turns(self.model_points[obj_id])
        return self._clouds[key]

    def texture_tree(self, obj_id: int):
        """(cKDTree of the print's surface points, (N,3) their RGB in [0, 1]) of ``obj_id`` (one in ``texture``),
        cached."""
        key = ("texture", obj_id)
        if key not in self._clouds:
            self._clouds[key] = cKDTree(self.texture[obj_id][0])
        return self._clouds[key], self.texture[obj_id][1]

    def surface(self, obj_id: int):
        """(cKDTree of the model points, (P,3) their unit normals) of ``obj_id``, cached: the fit measure's model."""
        key = ("surface", obj_id)
        if key not in self._clouds:
            self._clouds[key] = (cKDTree(np.asarray(self.model_points[obj_id], np.float64)),
                                 np.asarray(self.cloud(obj_id).normals))
        return self._clouds[key]
