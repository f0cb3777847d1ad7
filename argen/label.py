"""BOP frames -> per-point labels: [X,Y,Z,R,G,B,Nx,Ny,Nz], semantic, instance, 9 control points.

One frame (``Labeller.label_frame``):
1. Depth (BOP, ``depth_scale``) -> metres; pixels with depth in (0, ``max_depth``] are points,
   back-projected with cam_K: ``X = (col - cx) Z / fx``, ``Y = (row - cy) Z / fy``.
2. Instance masks: the dataset's ``mask_visib`` when every instance has one; otherwise (real test sets)
   the ground-truth poses are rendered (argen.sim.render, one renderer per process) and a pixel is visible
   for the front-most rendered instance when the sensor depth agrees with the rendered depth within
   ``visib_tolerance``. Where masks overlap, the lower gt index wins. A masked pixel whose point lies
   more than ``FAR_MARGIN`` outside the object's bounding sphere (box centre, half box diagonal) is
   background: with sensor noise, mask edges hold some depths of the surface behind the object.
3. Subsampling when a frame has more than ``max_points`` points: with ``voxel`` > 0 ("voxel+random")
   first one point per ``voxel`` cube (the first in pixel order, which evens out the density between
   near and far surfaces); then ("random", the default) a uniform random choice of ``max_points`` of
   those (Generator seeded from (seed, scene_id, im_id), so reruns, workers and resumed runs give the
   same points). Points stay in pixel order.
4. Normals from the depth-image grid (not open3d): the depth is smoothed with an edge-preserving
   bilateral filter (5 px, 1 cm), then the normal at a pixel is the cross product of its horizontal and
   vertical tangents over +-2 px, each taken on the side without a depth jump (central when both sides
   are smooth); oriented toward the camera; a pixel with no smooth neighbour gets the direction to the
   camera. Measured on a 640x480 frame: ~8 ms for 30k points, against 45-65 ms for open3d's
   ``estimate_normals`` (hybrid KNN 10-30, radius 2 cm) on the same 30k points, which alone would miss
   the 20 frames/s target.
5. Colours: RGB / 255 (0 when the scene has no colour images).
6. Control points of each instance: the model box's 8 corners then its centre, ``R c + t`` (camera frame).

The run (``run_label``): frames are labelled in chunks of ``chunk`` frames (default ``CHUNK``); each
chunk is written to ``OUT.partial/part-NNNNNN.h5`` (a small uncompressed label file, written to a temporary name and
renamed), and when every chunk exists they are streamed into ``OUT`` (temporary name + rename) and the
partial folder is removed. A killed run, started again with the same options, skips the chunks already
there, so its file has the same content as an uninterrupted run.

Speed (bench/bench_label.py, 2 shared cores, LineMOD models, 640x480 Kinect-noise frames, 30k points):
``label_frame`` 23-26 ms (PNG decoding ~10 ms of it), 40-44 frames/s; a whole one-process run
19-21 frames/s on 20-60 frames (start-up, part files and the LZF-compressed final file included);
with rendered visible masks ~83 ms a frame.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from argen import __version__, bop
from argen.config import PIXEL_CENTRES, simulation_K
from argen.errors import ArgenError
from argen.features import check_max_depth, frame_points
from argen.fileio import read_json, remove_stray_temps, write_json
from argen.h5 import FrameLabels, InstanceTable, LabelFile, LabelWriter, ObjectTable, point_control_points
from argen.models.objects import ObjectModel, load_models
from argen.models.texture import TEXTURE_POINTS, shape_symmetries, surface_colours, textured

CHUNK = 16  # frames per partial file
FAR_MARGIN = 0.01  # metres beyond an object's bounding sphere where a masked pixel is taken as background
CONTINUOUS_STEPS = 36  # discretisation of a continuous symmetry (10 degrees)


@dataclass
class LabelConfig:
    """Options of a labelling run (metres).

    max_points: points kept per frame; max_depth: working volume along z (None: ``default_max_depth``
    of the dataset); voxel: subsampling cube edge (0 = random only, the default: at LineMOD distances a
    pixel is ~1.8 mm wide, so a few-mm voxel changes little and its sort costs ~25 ms a frame);
    seed: subsampling seed; visib_tolerance: depth agreement for rendered visible masks; render_masks: always render the visible masks, even when the dataset has them;
    model_points: surface sample size per object in the objects table; pixel_centres: the convention of the
    dataset's K (``output.pixel_centres``; None: run_label and preview take ``dataset_pixel_centres``, which
    is "integer" unless an argen.json says otherwise). Points are back-projected (and cam_K stored) with ``simulation_K``.
    """

    max_points: int = 30000
    max_depth: float | None = None
    voxel: float = 0.0
    seed: int = 0
    visib_tolerance: float = 0.01
    render_masks: bool = False
    model_points: int = 1000
    pixel_centres: str | None = None

    def check(self) -> None:
        if self.max_depth is None:
            raise ValueError("max_depth must be resolved (default_max_depth) before labelling")
        if self.pixel_centres is not None and self.pixel_centres not in PIXEL_CENTRES:
            raise ArgenError(f"pixel_centres must be {' or '.join(PIXEL_CENTRES)}, got '{self.pixel_centres}'")
        if self.max_points < 1:
            raise ArgenError(f"--max-points must be at least 1, got {self.max_points}")
        check_max_depth(self.max_depth)
        if not (0 <= self.voxel < 0.5):
            raise ArgenError(f"--voxel must be in [0, 0.5) metres, got {self.voxel}")
        if not self.visib_tolerance > 0:
            raise ArgenError(f"visib tolerance must be positive, got {self.visib_tolerance}")


# ------------------------------------------------------------------------------------ objects


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniform random points on a triangle mesh.

    vertices: (V,3) metres; faces: (F,3) int. Returns (n,3) float64 metres.
    """
    return sample_surface_normals(vertices, faces, n, rng)[0]


def sample_surface_normals(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator
                           ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sample_surface`'s points (the same ones for the same generator) and the unit normals of their faces,
    by the faces' winding (outward for a mesh whose faces wind counter-clockwise seen from outside, as BOP's do).

    vertices: (V,3) metres; faces: (F,3) int. Returns (n,3) float64 metres and (n,3) float64 unit vectors.
    """
    tri = np.asarray(vertices, float)[np.asarray(faces)]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = np.linalg.norm(cross, axis=1)
    f = rng.choice(len(tri), size=n, p=area / area.sum())
    a, b = rng.random(n), rng.random(n)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    t = tri[f]
    return t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0]), cross[f] / area[f, None]


#: Surface samples with their normals per object in the objects table (seeded (seed, obj_id, 2)): what the detector's
#: surface-continuation check measures a pose's outline with (detector.geometry.verify.surface_continuation)
SURFACE_POINTS = 4000


def object_table(objects: list[ObjectModel], n_points: int = 1000, seed: int = 0) -> ObjectTable:
    """The label file's objects table (sorted by id); model points sampled with a Generator seeded (seed, obj_id).
    An object with shape symmetries its texture breaks (:func:`argen.models.texture.shape_symmetries`) also gets
    ``TEXTURE_POINTS`` surface points with their colours (seeded (seed, obj_id, 1)), when its colours vary. An
    object without a continuous symmetry of its own gets its part symmetry, if it has one
    (:func:`argen.models.symmetry.find_part_symmetry`, searched once a process: turns about an axis, every
    ``360 / PART_STEPS`` degrees, and samples of the odd part that breaks them)."""
    objects = sorted(objects, key=lambda o: o.obj_id)
    pts = [sample_surface(o.mesh.vertices, o.mesh.faces, n_points, np.random.default_rng([seed, o.obj_id]))
           for o in objects]
    cps = np.stack([o.control_points for o in objects])
    from argen.models.symmetry import PART_STEPS, part_symmetry_of  # lazy: it loads open3d (about a second)

    surface = [sample_surface_normals(o.mesh.vertices, o.mesh.faces, SURFACE_POINTS,
                                      np.random.default_rng([seed, o.obj_id, 2])) for o in objects]
    shape_sym, tex_pts, tex_cols, part_sym, odd_pts = [], [], [], [], []
    for o in objects:  # the turns only a print tells apart, and the print (argen.models.texture)
        turns = shape_symmetries(o)
        tp = sample_surface(o.mesh.vertices, o.mesh.faces, TEXTURE_POINTS, np.random.default_rng([seed, o.obj_id, 1])) \
            if len(turns) else np.zeros((0, 3))
        tc = surface_colours(o.mesh, tp) if len(tp) else None
        if tc is None or not textured(tc):
            tp, tc = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        shape_sym.append(turns.astype(np.float32))
        tex_pts.append(tp.astype(np.float32))
        tex_cols.append(tc)
        part = None if o.info.symmetries_continuous else part_symmetry_of(o.mesh, o.diameter)
        part_sym.append(np.zeros((0, 4, 4), np.float32) if part is None else part.turns(PART_STEPS).astype(np.float32))
        odd_pts.append(np.zeros((0, 3), np.float32) if part is None else part.odd_points.astype(np.float32))
    return ObjectTable(
        ids=np.array([o.obj_id for o in objects], np.int32),
        names=[o.name for o in objects],
        diameters=np.array([o.diameter for o in objects], np.float32),
        symmetric=np.array([o.symmetric for o in objects], bool),
        corners=cps[:, :8].astype(np.float32),
        control_points=cps.astype(np.float32),
        model_points=np.stack(pts).astype(np.float32),
        sym_transforms=[bop.symmetry_transforms(o.info, CONTINUOUS_STEPS).astype(np.float32) for o in objects],
        shape_symmetries=shape_sym, texture_points=tex_pts, texture_colours=tex_cols,
        part_symmetries=part_sym, odd_points=odd_pts,
        surface_points=[p.astype(np.float32) for p, _ in surface],
        surface_normals=[n.astype(np.float32) for _, n in surface],
    )


def instance_image(masks: list[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """(H,W) int32 index of the instance whose mask covers a pixel (lowest index wins), -1 = none."""
    out = np.full(shape, -1, np.int32)
    for k in range(len(masks) - 1, -1, -1):
        out[masks[k]] = k
    return out


# ---------------------------------------------------------------------------------- labeller


@dataclass
class FrameStats:
    rendered_masks: bool = False
    seconds: float = 0.0


class Labeller:
    """Labels frames of one BOP dataset split. objects: {obj_id: ObjectModel} (every id in the GT)."""

    def __init__(self, objects: dict[int, ObjectModel], cfg: LabelConfig):
        self.objects = objects
        self.cfg = cfg
        self._cps = {i: o.control_points for i, o in objects.items()}
        # half the box diagonal: no surface point of the object is farther from the box centre
        self._radius = {i: float(np.linalg.norm(c[:8] - c[8], axis=1).max()) for i, c in self._cps.items()}

    def _render_masks(self, gts: list[bop.FrameGT], K: np.ndarray, depth: np.ndarray, full: bool):
        """Visible masks (H,W) bool, and when ``full`` the pixel counts of the whole silhouettes, of the GT
        instances, by rendering them."""
        # lazy: pyrender (OSMesa) loads in a second; only datasets without masks are rendered
        from argen.sim.render import RenderItem, get_renderer

        h, w = depth.shape
        r = get_renderer(w, h)
        items = []
        for k, g in enumerate(gts):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = g.R, g.t
            items.append(RenderItem(key=("label", g.obj_id), mesh=self.objects[g.obj_id].mesh, T_world_obj=T,
                                    seg_id=k + 1))
        out = r.render(items, K, np.eye(4), seg=True)
        agree = (depth > 0) & (np.abs(depth - out.depth) <= self.cfg.visib_tolerance)
        visib = [(out.seg == k + 1) & agree for k in range(len(gts))]
        fulls = None
        if full:  # whole silhouettes: the in-image part plus what lies beyond the edge (BOP's visib_fract)
            fm = r.full_masks(items, K, np.eye(4))
            beyond = r.outside_silhouettes(items, K, np.eye(4), fm)
            fulls = [int(fm[k + 1].sum()) + beyond.get(k + 1, (0, None))[0] for k in range(len(gts))]
        return visib, fulls

    def _drop_far(self, instance: np.ndarray, pts: np.ndarray, cps: np.ndarray, obj_ids: np.ndarray) -> np.ndarray:
        """Background for mask pixels whose point lies outside the object's bounding sphere (+ FAR_MARGIN).

        instance: (N,) int, -1 = background; pts: (N,3) metres; cps: (I,9,3) camera-frame control points.
        With sensor noise a mask edge pixel can hold the depth of the surface behind the object.
        """
        fg = np.flatnonzero(instance >= 0)
        if len(fg) == 0:
            return instance
        k = instance[fg]
        radius = np.array([self._radius[i] for i in obj_ids])[k]
        far = np.linalg.norm(pts[fg] - cps[k, 8], axis=1) > radius + FAR_MARGIN
        out = instance.copy()
        out[fg[far]] = -1
        return out

    def label_frame(self, scene: bop.BopScene, im_id: int) -> tuple[FrameLabels, FrameStats]:
        """Label one frame of ``scene``."""
        t0 = time.perf_counter()
        cfg = self.cfg
        cam = scene.cameras[im_id]
        K = simulation_K(cam.K, cfg.pixel_centres or "integer")
        gts = scene.gts[im_id]
        for g in gts:
            if g.obj_id not in self.objects:
                raise ArgenError(f"scene {scene.scene_id} image {im_id}: object {g.obj_id} has no model "
                                 "(give the models folder with --models)")
        depth = scene.read_depth(im_id)
        h, w = depth.shape
        rgb = scene.read_rgb(im_id)
        if rgb is not None and rgb.shape[:2] != (h, w):
            raise ArgenError(f"scene {scene.scene_id} image {im_id}: rgb is {rgb.shape[1]}x{rgb.shape[0]} "
                             f"but depth is {w}x{h}")
        masks = [] if cfg.render_masks else [scene.read_mask(im_id, k, visib=True) for k in range(len(gts))]
        infos = scene.gt_infos.get(im_id, [])
        have_fract = len(infos) == len(gts) and all("visib_fract" in i for i in infos)
        rendered = bool(gts) and (cfg.render_masks or any(m is None for m in masks) or not have_fract)
        fulls = None
        if rendered:
            need_masks = cfg.render_masks or any(m is None for m in masks)
            vis_r, fulls = self._render_masks(gts, K, depth, full=not have_fract)
            if need_masks:
                masks = vis_r
        for k, m in enumerate(masks):
            if m.shape != (h, w):
                raise ArgenError(f"scene {scene.scene_id} image {im_id}: mask {k} is {m.shape[1]}x{m.shape[0]} "
                                 f"but depth is {w}x{h}")
        if have_fract:
            fract = np.array([float(i["visib_fract"]) for i in infos], np.float32)
        else:
            fract = np.array([m.sum() / max(f, 1) for m, f in zip(masks, fulls)], np.float32) if gts \
                else np.zeros(0, np.float32)
        fract = np.clip(fract, 0, 1)

        rng = np.random.default_rng([cfg.seed, scene.scene_id, im_id])
        fp = frame_points(depth, K, rgb, cfg.max_points, cfg.voxel, rng, cfg.max_depth)
        flat, rows, cols = fp.flat, fp.rows, fp.cols
        pts = fp.features[:, :3].astype(np.float64)
        inst_img = instance_image(masks, (h, w))
        instance = inst_img.reshape(-1)[flat]
        obj_ids = np.array([g.obj_id for g in gts], np.int32)
        cps = np.array([self._cps[g.obj_id] @ g.R.T + g.t for g in gts], np.float64).reshape(-1, 9, 3)
        instance = self._drop_far(instance, pts, cps, obj_ids)
        semantic = np.where(instance >= 0, obj_ids[np.maximum(instance, 0)] if len(gts) else 0, 0).astype(np.int32)

        R = np.array([g.R for g in gts], np.float64).reshape(-1, 3, 3)
        t = np.array([g.t for g in gts], np.float64).reshape(-1, 3)
        inst = InstanceTable(
            obj_id=obj_ids, gt_index=np.arange(len(gts), dtype=np.int32),
            R=R.astype(np.float32), t=t.astype(np.float32), control_points=cps.astype(np.float32),
            visib_fract=fract, num_points=np.bincount(instance[instance >= 0], minlength=len(gts)).astype(np.int32),
        )
        features = fp.features
        frame = FrameLabels(
            scene_id=scene.scene_id, im_id=im_id, cam_K=np.asarray(K, np.float32),
            image_size=np.array([h, w], np.int32), features=features,
            pixel=np.stack([rows, cols], axis=1).astype(np.int32), semantic=semantic,
            instance=instance.astype(np.int32),
            control_points=point_control_points(inst.control_points, instance), instances=inst,
        )
        return frame, FrameStats(rendered, time.perf_counter() - t0)


# ------------------------------------------------------------------------------------ dataset


def dataset_frames(root: Path, split: str) -> tuple[dict[int, bop.BopScene], list[tuple[int, int]]]:
    """The split's scenes and its (scene_id, im_id) frames in order."""
    scenes = {sid: bop.load_scene(root, split, sid) for sid in bop.list_scenes(root, split)}
    frames = [(sid, im) for sid, s in scenes.items() for im in s.im_ids]
    if not frames:
        raise ArgenError(f"{root / split} holds no frames with ground truth")
    return scenes, frames


def resolve_models(root: Path, models: Path | None) -> Path:
    """The models folder: ``--models`` or the dataset's ``models/`` (also BOP's ``models_eval``-less layouts)."""
    d = Path(models) if models else root / "models"
    if not d.is_dir():
        raise ArgenError(f"models folder not found: {d} (give one with --models)")
    return d


def load_label_objects(models_dir: Path, ids: list[int]) -> dict[int, ObjectModel]:
    """Load the models of ``ids`` from a BOP models folder; ArgenError naming a missing one."""
    if not ids:
        return {}
    missing = [i for i in ids if not bop.model_path(models_dir, i).is_file()]
    if missing:
        raise ArgenError(f"models folder {models_dir} has no model for object(s) {', '.join(map(str, missing))}")
    return {o.obj_id: o for o in load_models(models_dir, [str(i) for i in ids])}


def _argen_config(root: Path) -> dict:
    """The capture config an argen dataset's argen.json records ({} for other BOP datasets)."""
    try:
        cfg = read_json(root / "argen.json", "argen.json")["config"]
    except (ArgenError, KeyError, TypeError):
        return {}
    return cfg if isinstance(cfg, dict) else {}


def dataset_pixel_centres(root: Path) -> str:
    """The pixel-centre convention of a dataset's K: its argen.json's ``output.pixel_centres``, else "integer"
    (BOP datasets of real sensors, and argen datasets made before the option existed)."""
    out = _argen_config(root).get("output")
    value = out.get("pixel_centres", "integer") if isinstance(out, dict) else "integer"
    return value if isinstance(value, str) and value in PIXEL_CENTRES else "integer"


def default_max_depth(root: Path) -> float:
    """Working volume for a dataset: beyond the template's farthest camera distance + 0.6 m, else 2 m."""
    try:
        return float(max(_argen_config(root)["camera"]["distance"])) + 0.6
    except (KeyError, TypeError, ValueError):
        return 2.0


@dataclass
class LabelRequest:
    """A labelling run: dataset folder, split, output file, options."""

    dataset: Path
    split: str
    out: Path
    cfg: LabelConfig = field(default_factory=LabelConfig)
    models: Path | None = None
    workers: int = 1
    overwrite: bool = False
    progress: bool = True
    chunk: int = CHUNK
    compression: str | None = "lzf"
    shard: tuple[int, int] = (0, 1)  # (I, N): label only the chunks k with k % N == I (see merge_label_files)


@dataclass
class LabelSummary:
    frames: int
    skipped: int
    points: int
    instances: int
    rendered: int
    seconds: float

    def line(self) -> str:
        done = self.frames - self.skipped
        fps = done / self.seconds if self.seconds > 0 else 0.0
        return (f"{self.frames} frames ({self.skipped} already done), {self.points} points, {self.instances} instances"
                + (f", visible masks rendered for {self.rendered} frames" if self.rendered else "")
                + f"; {fps:.1f} frames/s")


def run_signature(req: LabelRequest, models_dir: Path) -> dict:
    """What a resumed run must share with the interrupted one."""
    return {"argen_version": __version__, "dataset": str(req.dataset.resolve()), "split": req.split,
            "models": str(models_dir.resolve()), "config": asdict(req.cfg), "chunk": req.chunk,
            "shard": list(req.shard)}


def file_attrs(req: LabelRequest) -> dict:
    """Root attributes of the label file (schema_version and num_frames are added by the writer)."""
    meta = req.dataset / "argen.json"
    return {"created_by": f"argen {__version__}", "source_dataset": str(req.dataset.resolve()),
            "source_split": req.split, "source_argen_json": meta.read_text() if meta.is_file() else "",
            "max_points": int(req.cfg.max_points), "max_depth": float(req.cfg.max_depth),
            "subsampling": "voxel+random" if req.cfg.voxel > 0 else "random",
            "voxel": float(req.cfg.voxel), "seed": int(req.cfg.seed),
            **({"shard": f"{req.shard[0]}/{req.shard[1]}", "shard_chunk": int(req.chunk)} if req.shard[1] > 1 else {})}


def part_path(partial: Path, k: int) -> Path:
    return partial / f"part-{k:06d}.h5"


_state: dict = {}


def _init_worker(req: LabelRequest, models_dir: Path, ids: list[int], threads: int) -> None:
    os.environ.setdefault("LP_NUM_THREADS", str(threads))
    cv2.setNumThreads(1)
    objects = load_label_objects(models_dir, ids)
    scenes, frames = dataset_frames(req.dataset, req.split)
    _state.update(req=req, labeller=Labeller(objects, req.cfg), scenes=scenes, frames=frames,
                  table=object_table(list(objects.values()), req.cfg.model_points, req.cfg.seed))


def _label_chunk(k: int, on_frame=None) -> tuple[int, int, int, int, int]:
    """Label chunk ``k`` into its part file; returns (k, frames, points, instances, rendered).

    on_frame: called after each frame (progress in the single-process run).
    """
    req, lab, scenes = _state["req"], _state["labeller"], _state["scenes"]
    todo = _state["frames"][k * req.chunk:(k + 1) * req.chunk]
    pts = inst = rendered = 0
    partial = partial_dir(req.out)
    with LabelWriter(part_path(partial, k), file_attrs(req), _state["table"], compression=None) as w:
        for sid, im in todo:
            fr, st = lab.label_frame(scenes[sid], im)
            w.append(fr)
            pts += len(fr)
            inst += len(fr.instances)
            rendered += st.rendered_masks
            if on_frame is not None:
                on_frame()
    return k, len(todo), pts, inst, rendered


def partial_dir(out: Path) -> Path:
    return out.with_name(out.name + ".partial")


def _prepare(req: LabelRequest, models_dir: Path) -> Path:
    """Create or check ``OUT.partial``; returns it."""
    if req.out.exists():
        if req.out.is_dir():
            raise ArgenError(f"output path {req.out} is a folder; give a .h5 file name")
        if not req.overwrite:
            raise ArgenError(f"{req.out} exists; use --overwrite to replace it")
    partial = partial_dir(req.out)
    sig = json.loads(json.dumps(run_signature(req, models_dir)))
    sig_p = partial / "run.json"
    if partial.is_dir():
        old = read_json(sig_p, "run.json") if sig_p.is_file() else None
        if old != sig:
            if not req.overwrite:
                raise ArgenError(f"{partial} holds an interrupted run with other options; use --overwrite to "
                                 "start again or rerun with the same options")
            shutil.rmtree(partial)
    partial.mkdir(parents=True, exist_ok=True)
    remove_stray_temps(partial)  # part files a killed run was writing (their chunks are labelled again)
    # its final file, half-written (atomic_path's name: mkstemp's 8 random characters, so no other file's)
    for p in req.out.parent.glob(f".tmp-{req.out.stem}-{'?' * 8}{req.out.suffix}"):
        p.unlink(missing_ok=True)
    if not sig_p.is_file():
        write_json(sig_p, sig)
    return partial


def run_label(req: LabelRequest) -> LabelSummary:
    """Label ``req.split`` of ``req.dataset`` into ``req.out`` (resuming an interrupted run)."""
    if req.cfg.max_depth is None:
        req = replace(req, cfg=replace(req.cfg, max_depth=default_max_depth(req.dataset)))
    if req.cfg.pixel_centres is None:
        req = replace(req, cfg=replace(req.cfg, pixel_centres=dataset_pixel_centres(req.dataset)))
    req.cfg.check()
    if req.workers < 1:
        raise ArgenError(f"--workers must be at least 1, got {req.workers}")
    if req.compression not in ("lzf", "gzip", None):
        raise ArgenError(f"--compression must be lzf, gzip or none, got {req.compression}")
    if req.chunk < 1:
        raise ArgenError(f"--chunk must be at least 1, got {req.chunk}")
    if req.out.suffix.lower() not in (".h5", ".hdf5"):
        raise ArgenError(f"--out must name an .h5 file, got {req.out}")
    if not req.dataset.is_dir():
        raise ArgenError(f"dataset folder not found: {req.dataset}")
    t0 = time.perf_counter()
    scenes, frames = dataset_frames(req.dataset, req.split)
    ids = sorted({g.obj_id for s in scenes.values() for gl in s.gts.values() for g in gl})
    if not ids:
        raise ArgenError(f"{req.dataset / req.split} has no ground-truth instances")
    models_dir = resolve_models(req.dataset, req.models)
    missing = [i for i in ids if not bop.model_path(models_dir, i).is_file()]
    if missing:
        raise ArgenError(f"models folder {models_dir} has no model for object(s) {', '.join(map(str, missing))}")
    shard_i, shard_n = req.shard
    if not (shard_n >= 1 and 0 <= shard_i < shard_n):
        raise ArgenError(f"--shard must be I/N with 0 <= I < N, got {shard_i}/{shard_n}")
    partial = _prepare(req, models_dir)
    n_chunks = (len(frames) + req.chunk - 1) // req.chunk
    mine = list(range(shard_i, n_chunks, shard_n))
    if not mine:
        raise ArgenError(f"shard {shard_i}/{shard_n} gets no frames: {len(frames)} frames make only {n_chunks} "
                         f"chunks of {req.chunk}; use fewer shards or a smaller --chunk")
    todo = [k for k in mine if not part_path(partial, k).is_file()]
    n_mine = sum(len(frames[k * req.chunk:(k + 1) * req.chunk]) for k in mine)
    skipped = n_mine - sum(len(frames[k * req.chunk:(k + 1) * req.chunk]) for k in todo)

    bar = tqdm(total=n_mine, initial=skipped,
               desc="label", unit="frame", disable=not req.progress, file=sys.stderr)
    rendered = 0
    try:
        for _, n, _, _, r, counted in _chunks(req, models_dir, ids, todo, lambda: bar.update(1)):
            rendered += r
            if not counted:
                bar.update(n)
    finally:
        bar.close()
    points, instances = assemble(req, partial, mine)
    shutil.rmtree(partial, ignore_errors=True)
    return LabelSummary(n_mine, skipped, points, instances, rendered, time.perf_counter() - t0)


def _chunks(req: LabelRequest, models_dir: Path, ids: list[int], todo: list[int], on_frame):
    """Label the chunks ``todo``; yields _label_chunk's tuple + whether on_frame already counted its frames."""
    if not todo:
        return
    if req.workers == 1 or len(todo) == 1:
        _init_worker(req, models_dir, ids, os.cpu_count() or 1)
        try:
            for k in todo:
                yield (*_label_chunk(k, on_frame), True)
        finally:
            _state.clear()
        return
    ctx = mp.get_context("spawn")  # OSMesa contexts do not survive fork
    threads = max(1, (os.cpu_count() or 1) // req.workers)
    with ctx.Pool(req.workers, initializer=_init_worker, initargs=(req, models_dir, ids, threads)) as pool:
        for res in pool.imap_unordered(_label_chunk, todo, chunksize=1):
            yield (*res, False)


def assemble(req: LabelRequest, partial: Path, chunks: list[int]) -> tuple[int, int]:
    """Stream the part files ``chunks``, in order, into ``req.out`` (atomic); returns (points, instances)."""
    with LabelFile(part_path(partial, chunks[0])) as first:
        table = first.objects
    with LabelWriter(req.out, file_attrs(req), table, compression=req.compression) as w:
        for k in chunks:
            with LabelFile(part_path(partial, k)) as part:
                w.extend(part)
        return w.num_points, w.num_instances


def merge_label_files(paths: list[Path], out: Path, overwrite: bool = False, compression: str | None = "lzf") -> int:
    """Join the label files of ``argen label --shard I/N`` (all N of them) into ``out``; returns its frames.

    Shard I holds chunks I, I+N, I+2N, ... of ``shard_chunk`` frames each, so the merge interleaves them
    back in chunk order; the result equals the file of a single run with the same options (the per-frame
    subsampling generator depends only on the seed and the frame's ids). ArgenError on any mismatch.
    """
    out = Path(out)
    if out.exists() and not overwrite:
        raise ArgenError(f"{out} exists; use --overwrite to replace it")
    files = [LabelFile(p) for p in paths]
    try:
        shards = {}
        for lf in files:
            if "shard" not in lf.attrs:
                raise ArgenError(f"{lf.path} is not a shard (made without argen label --shard)")
            i, n = (int(v) for v in str(lf.attrs["shard"]).split("/"))
            if i in shards:
                raise ArgenError(f"shard {i}/{n} given twice ({shards[i].path}, {lf.path})")
            shards[i] = lf
        first = files[0]
        n = int(str(first.attrs["shard"]).split("/")[1])
        skip = {"shard", "num_frames", "schema_version"}
        for lf in files[1:]:
            for key in set(first.attrs) | set(lf.attrs):
                if key in skip:
                    continue
                a, b = first.attrs.get(key), lf.attrs.get(key)
                if not np.array_equal(np.asarray(a), np.asarray(b)):
                    raise ArgenError(f"{lf.path} and {first.path} differ in '{key}': not shards of one labelling run")
            if int(str(lf.attrs["shard"]).split("/")[1]) != n:
                raise ArgenError("the files were made with different --shard counts N")
        missing = sorted(set(range(n)) - set(shards))
        if missing:
            raise ArgenError(f"cannot merge: missing shard(s) {', '.join(f'{i}/{n}' for i in missing)}")
        chunk = int(first.attrs["shard_chunk"])
        attrs = {k: v for k, v in first.attrs.items() if k not in skip and k != "shard_chunk"}
        total = sum(lf.num_frames for lf in files)
        pos = {i: 0 for i in shards}
        with LabelWriter(out, attrs, first.objects, compression=compression) as w:
            for k in range((total + chunk - 1) // chunk):
                lf = shards[k % n]
                stop = min(pos[k % n] + chunk, lf.num_frames)
                for j in range(pos[k % n], stop):
                    w.append(lf.frame(j))
                pos[k % n] = stop
        return total
    finally:
        for lf in files:
            lf.close()
