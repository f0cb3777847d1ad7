"""BOP19 Average Recall of pose estimates on a BOP dataset (argen's or a real one), as the BOP toolkit's
``eval_bop19_pose.py`` computes it, without the toolkit: the dataset is read through :mod:`argen.bop`, the models
rendered with argen's renderer (:mod:`argen.sim.render`, pyrender + OSMesa) and scored by :mod:`detector.evaluation.bop19`.

The protocol, step by step:

- targets: the (image, object, inst_count) entries of ``test_targets_bop19.json`` at the dataset root (computed with
  BOP's rule, instances at least 10 % visible, when the file is absent), optionally only those of given images;
- estimates: per target, the inst_count best-scoring estimates of that object in that image (the n_top rule);
- errors of each against every ground-truth instance of its object in the image: VSD (delta 15 mm, taus 0.05-0.5 of
  the diameter; 1 when the bounding spheres' images do not overlap), MSSD (inf when the spheres do not overlap) and
  MSPD, over the symmetries of ``models_info.json`` (continuous ones in steps of max_sym_disc_step 0.01), on the
  vertices of ``models_eval/`` (``models/`` when there is none), which VSD also renders;
- valid instances: per target, its inst_count most visible instances (scene_gt_info's visib_fract);
- per threshold, greedy matching by score; recall over all targets; AR per error, and their mean.

Rendering follows the dataset's own pixel-centre convention (argen.json's ``output.pixel_centres``; "integer", K's
pixel (u, v) seen at (u, v), for real data), so the model rendered at the true pose lies on the test depth. The BOP
toolkit's renderers put pixel centres at (u + 0.5, v + 0.5): on argen's "integer" data its VSD differs at silhouette
edges, by well under 0.01 of AR (README, "Using argen data with the BOP toolkit").
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from argen import bop
from detector.errors import DetectorError, argen_errors
from detector.evaluation import bop19
from detector.evaluation.metrics import top_k


#: The toolkit's keys of ``scores_bop19.json``.
SCORE_KEYS = ("bop19_average_recall", "bop19_average_recall_vsd", "bop19_average_recall_mssd",
              "bop19_average_recall_mspd")

#: Where the toolkit's MSPD thresholds hold: an image 640 pixels wide.
MSPD_REFERENCE_WIDTH = 640.0


def dataset_pixel_centres(argen_json: str | dict | None) -> str:
    """The pixel-centre convention of a dataset from its argen.json (text or parsed; "" or None for a dataset argen
    did not make): ``output.pixel_centres``, else "integer"."""
    if isinstance(argen_json, str):
        try:
            argen_json = json.loads(argen_json) if argen_json.strip() else {}
        except ValueError:
            argen_json = {}
    out = (argen_json or {}).get("output", {}) if isinstance(argen_json, dict) else {}
    value = out.get("pixel_centres", "integer") if isinstance(out, dict) else "integer"
    return value if value in ("integer", "half") else "integer"


#: Datasets the BOP toolkit (commit cea62d6) knows, whose table an argen capture can fit: {name: (object ids, image
#: width and height)}. For a pbr split the toolkit takes scenes 0-49 of any dataset, and it needs every listed
#: object's model in models_eval/.
TOOLKIT_DATASETS = {"lm": (tuple(range(1, 16)), (640, 480)), "lmo": ((1, 5, 6, 8, 9, 10, 11, 12), (640, 480)),
                    "ycbv": (tuple(range(1, 22)), (640, 480))}


def toolkit_dataset_name(root: str | Path, split: str) -> str | None:
    """The name under which the BOP toolkit runs unmodified on the pbr split ``split`` of the dataset at ``root``: the
    entry of :data:`TOOLKIT_DATASETS` with the same object ids (models_eval/, else models/) and image size
    (camera.json); None for another split, another set of objects, or a dataset that cannot be read."""
    root = Path(root)
    if bop.split_type(split) != "pbr" or not (root / bop.CAMERA_FILE).is_file():
        return None
    try:
        models = ModelSet(root)
        cam = bop.load_camera(root / bop.CAMERA_FILE)
    except DetectorError:
        return None
    for name, (ids, size) in TOOLKIT_DATASETS.items():
        if sorted(models.info) == list(ids) and (cam.width, cam.height) == size:
            return name
    return None


def load_targets(root: Path, split: str, images: set[tuple[int, int]] | None = None) -> tuple[list[dict], str]:
    """The BOP19 targets [{"scene_id", "im_id", "obj_id", "inst_count"}] and where they came from: the dataset's
    ``test_targets_bop19.json``, else computed from ``split`` with BOP's 10 % rule; only those of ``images``
    ((scene_id, im_id) pairs) when given."""
    path = Path(root) / bop.TEST_TARGETS
    with argen_errors():
        if path.is_file():
            targets, source = bop.load_test_targets(path), bop.TEST_TARGETS
        else:
            targets, source = bop.test_targets(root, split), f"computed from {split} (no {bop.TEST_TARGETS})"
    if images is not None:
        targets = [t for t in targets if (t["scene_id"], t["im_id"]) in images]
    return targets, source


class ModelSet:
    """The dataset's evaluation models, loaded on first use: per object id the vertices (P,3) metres, the mesh
    (for VSD's renders), the diameter (metres) and the BOP symmetry transforms (S,4,4)."""

    def __init__(self, root: Path):
        d = Path(root) / "models_eval"
        self.dir = d if (d / "models_info.json").is_file() else Path(root) / "models"
        with argen_errors():
            self.info = bop.read_models_info(self.dir / "models_info.json")
        self._cache: dict[int, tuple] = {}

    def get(self, obj_id: int):
        """(vertices (P,3) float64 metres, trimesh mesh in metres, diameter metres, symmetries (S,4,4))."""
        if obj_id not in self._cache:
            if obj_id not in self.info:
                raise DetectorError(f"object {obj_id} of the BOP targets is not in {self.dir / 'models_info.json'}")
            with argen_errors():
                mesh = bop.read_mesh(bop.model_path(self.dir, obj_id))
            info = self.info[obj_id]
            syms = bop.symmetry_transforms(info, bop19.continuous_symmetry_steps())
            self._cache[obj_id] = (np.asarray(mesh.vertices, np.float64), mesh, float(info.diameter), syms)
        return self._cache[obj_id]


def render_depth(mesh, key, R: np.ndarray, t: np.ndarray, K: np.ndarray, shape: tuple[int, int],
                 pixel_centres: str = "integer") -> np.ndarray:
    """The model alone at pose R (3,3), t (3,) metres: depth (H,W) float32 metres (z, 0 = background), rendered with
    argen's renderer for an image of ``shape`` (H, W) and K (3,3) pixels in the dataset's pixel-centre convention."""
    # lazy: pyrender and OSMesa load in about a second; only VSD renders
    from argen.sim.render import RenderItem, get_renderer

    Kr = np.array(K, np.float64)
    if pixel_centres == "half":  # pixel (u, v) is seen along K^-1 (u + 0.5, v + 0.5, 1)
        Kr[:2, 2] -= 0.5
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    z = np.asarray(t, np.float64).reshape(3)[2]
    renderer = get_renderer(int(shape[1]), int(shape[0]))
    return renderer.render_depth([RenderItem(key, mesh, T)], Kr, np.eye(4), znear=0.01, zfar=max(10.0, 2 * z))


def _by_image(rows: list[dict]) -> dict[tuple[int, int, int], list[int]]:
    """Indices of the estimate rows per (scene_id, im_id, obj_id), in file order."""
    out: dict[tuple[int, int, int], list[int]] = defaultdict(list)
    for i, r in enumerate(rows):
        out[(int(r["scene_id"]), int(r["im_id"]), int(r["obj_id"]))].append(i)
    return out


def image_errors(rows: list[dict], est_ids: list[int], gt_ids: list[int], gts, depth: np.ndarray, K: np.ndarray,
                 model, render) -> list[dict]:
    """The errors of the estimates ``est_ids`` (rows of ``rows``) of one object in one image against its instances
    ``gt_ids`` (indices into ``gts``, argen.bop FrameGT: R, t metres): per estimate {"est_id", "score", "gt":
    {gt_id: {"vsd": [T], "mssd": metres, "mspd": pixels}}}. depth: the test image (H,W) metres; K (3,3); model: a
    :meth:`ModelSet.get` tuple; render(R, t): the model's depth (H,W) metres at that pose (called for each pose
    once)."""
    points, _, diameter, syms = model
    rendered: dict[int, np.ndarray] = {}
    out = []
    for e in est_ids:
        R, t = np.asarray(rows[e]["R"], np.float64), np.asarray(rows[e]["t"], np.float64)
        errs, d_est = {}, None
        for g in gt_ids:
            Rg, tg = gts[g].R, gts[g].t
            if bop19.sphere_projections_overlap(t, tg, diameter):
                if d_est is None:
                    d_est = render(R, t)
                if g not in rendered:
                    rendered[g] = render(Rg, tg)
                v = bop19.vsd(depth, d_est, rendered[g], K, diameter)
            else:
                v = np.ones(len(bop19.VSD_TAUS))
            ms = bop19.mssd(R, t, Rg, tg, points, syms) if bop19.spheres_overlap(t, tg, diameter) else float("inf")
            errs[g] = {"vsd": [float(x) for x in v], "mssd": ms, "mspd": bop19.mspd(R, t, Rg, tg, K, points, syms)}
        out.append({"est_id": int(e), "score": float(rows[e]["score"]), "gt": errs})
    return out


def score_bop19(root: str | Path, split: str, rows: list[dict], images: set[tuple[int, int]] | None = None,
                pixel_centres: str = "integer", progress: bool = False) -> dict:
    """BOP19 Average Recall of estimate rows (:func:`detector.report.read_bop_csv`'s: scene_id, im_id, obj_id, score,
    R (3,3), t (3,) metres) on the BOP dataset at ``root``, split ``split``; only the targets of ``images``
    ((scene_id, im_id) pairs) when given (the frames that were evaluated).

    Returns the toolkit's four figures (``SCORE_KEYS``) and: "num_targets", "num_images", "targets" (where they
    came from), "objects" {obj_id: {"num_targets", "vsd", "mssd", "mspd", "ar"}} (recall over that object's
    targets), "errors" [{"scene_id", "im_id", "obj_id", "est_id" (row index), "score", "gt": {gt index in
    scene_gt: {"vsd": [10 taus], "mssd": metres, "mspd": pixels}}}] for every estimate scored.
    """
    root = Path(root)
    targets, source = load_targets(root, split, images)
    models = ModelSet(root)
    ests = _by_image(rows)
    per_image: dict[int, dict[int, dict[int, int]]] = defaultdict(lambda: defaultdict(dict))
    for t in targets:
        per_image[t["scene_id"]][t["im_id"]][t["obj_id"]] = t["inst_count"]
    groups: dict[str, list] = {"vsd": [], "mssd": [], "mspd": []}  # entries (obj_id, scores, errors, valid)
    records = []
    todo = [(s, i) for s in sorted(per_image) for i in sorted(per_image[s])]
    scene = None
    for scene_id, im_id in (tqdm(todo, desc="BOP19", unit="image") if progress else todo):
        with argen_errors():
            if scene is None or scene.scene_id != scene_id:
                scene = bop.load_scene(root, split, scene_id)
            if im_id not in scene.gts:
                raise DetectorError(f"BOP target image {im_id} of scene {scene_id} has no ground truth in {root}")
            if len(scene.gt_infos.get(im_id, [])) != len(scene.gts[im_id]):
                raise DetectorError(f"{bop.scene_dir(root, split, scene_id)}: no scene_gt_info.json entry for image "
                                    f"{im_id} (BOP19 needs each instance's visib_fract)")
            depth = scene.read_depth(im_id)
        K, gts = scene.cameras[im_id].K, scene.gts[im_id]
        obj_ids = np.array([g.obj_id for g in gts], np.int64)
        valid = bop19.valid_instances(obj_ids, [float(i["visib_fract"]) for i in scene.gt_infos[im_id]],
                                      per_image[scene_id][im_id])
        for obj_id in sorted(per_image[scene_id][im_id]):
            model = models.get(obj_id)
            mine = ests.get((scene_id, im_id, obj_id), [])
            top = [mine[j] for j in top_k(np.array([rows[e]["score"] for e in mine], np.float64),
                                          per_image[scene_id][im_id][obj_id])]
            cols = np.flatnonzero(obj_ids == obj_id)
            key = ("bop19", str(models.dir), obj_id)

            def render(R, t, mesh=model[1], key=key):
                return render_depth(mesh, key, R, t, K, depth.shape, pixel_centres)

            errs = image_errors(rows, top, cols.tolist(), gts, depth, K, model, render)
            records += [{"scene_id": scene_id, "im_id": im_id, "obj_id": obj_id, **r} for r in errs]
            scores = np.array([r["score"] for r in errs], np.float64)
            vsd = np.array([[r["gt"][g]["vsd"] for g in cols] for r in errs], np.float64)
            vsd = vsd.reshape(len(errs), len(cols), len(bop19.VSD_TAUS))
            mssd, mspd = (np.array([[r["gt"][g][n] for g in cols] for r in errs], np.float64).reshape(
                len(errs), len(cols)) for n in ("mssd", "mspd"))
            groups["vsd"].append((obj_id, scores, vsd, valid[cols]))
            groups["mssd"].append((obj_id, scores, mssd / model[2], valid[cols]))
            groups["mspd"].append((obj_id, scores, mspd * MSPD_REFERENCE_WIDTH / depth.shape[1], valid[cols]))
    result = average_recalls(groups)
    result.update(num_targets=int(sum(np.sum(g[3]) for g in groups["mssd"])), num_images=len(todo), targets=source,
                  errors=records)
    return result


def average_recalls(groups: dict[str, list]) -> dict:
    """The four BOP19 figures and per object {obj_id: {"num_targets", "vsd", "mssd", "mspd", "ar"}} from the groups
    {"vsd": [(obj_id, scores (D,), errors (D,G,T), valid (G,))], "mssd"/"mspd": [(obj_id, scores, errors (D,G) in
    the thresholds' units, valid)]}: mean recall over the thresholds (VSD: over taus and thresholds)."""

    def ar(name: str, obj_id: int | None = None) -> float:
        sel = [g for g in groups[name] if obj_id is None or g[0] == obj_id]
        if name == "vsd":
            return float(np.mean([bop19.recalls([(s, e[..., j], v) for _, s, e, v in sel], bop19.VSD_THRESHOLDS)
                                  for j in range(len(bop19.VSD_TAUS))]))
        ths = bop19.MSSD_THRESHOLDS if name == "mssd" else bop19.MSPD_THRESHOLDS
        return float(np.mean(bop19.recalls([(s, e, v) for _, s, e, v in sel], ths)))

    out = {}
    for name in ("vsd", "mssd", "mspd"):
        out[f"bop19_average_recall_{name}"] = ar(name)
    out["bop19_average_recall"] = float(np.mean([out[f"bop19_average_recall_{n}"] for n in ("vsd", "mssd", "mspd")]))
    objects = {}
    for obj_id in sorted({g[0] for g in groups["mssd"]}):
        o = {"num_targets": int(sum(np.sum(v) for oid, _, _, v in groups["mssd"] if oid == obj_id))}
        o.update({n: ar(n, obj_id) for n in ("vsd", "mssd", "mspd")})
        o["ar"] = float(np.mean([o["vsd"], o["mssd"], o["mspd"]]))
        objects[obj_id] = o
    out["objects"] = objects
    return {k: out[k] for k in (*SCORE_KEYS, "objects")}
