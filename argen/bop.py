"""The BOP dataset format: the only module that knows its file layout and its millimetres.

Everything this module returns is in metres; everything it is given is in metres and converted to
BOP millimetres on the way out. Layout (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md):

    DATASET/models/{models_info.json, obj_OBJID.ply}
    DATASET/camera.json    (also the intrinsics of a recording folder, argen.real.recording)
    DATASET/SPLIT/SCENE/{scene_camera.json, scene_gt.json, scene_gt_info.json}
    DATASET/SPLIT/SCENE/rgb/IMID.{png,jpg}  (JPEG in pbr splits, e.g. train_pbr, as BOP's toolkit expects)
    DATASET/SPLIT/SCENE/depth/IMID.png
    DATASET/SPLIT/SCENE/{mask,mask_visib}/IMID_GTIDX.png

with SCENE and IMID six-digit zero-padded ids. ``depth_mm = png_value * depth_scale``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from argen.errors import ArgenError
from argen.fileio import atomic_path, read_json, write_bytes, write_json

MM_PER_M = 1000.0


# ------------------------------------------------------------------------------------------ paths


def scene_dir(root: str | os.PathLike, split: str, scene_id: int) -> Path:
    """Folder of one scene: ``root/split/SCENE``."""
    return Path(root) / split / f"{scene_id:06d}"


def image_path(root, split: str, scene_id: int, im_id: int, kind: str = "rgb", ext: str = ".png") -> Path:
    """Path of an ``rgb`` or ``depth`` image."""
    return scene_dir(root, split, scene_id) / kind / f"{im_id:06d}{ext}"


#: Quality of the JPEG colour images of pbr splits (BOP's own pbr renders are JPEG too).
JPEG_QUALITY = 95
RGB_EXTS = (".png", ".jpg", ".jpeg", ".tif")


def split_type(split: str) -> str:
    """BOP's split type: what follows the first '_' of the split name (``train_pbr`` -> ``pbr``), or ''."""
    return split.split("_", 1)[1] if "_" in split else ""


def rgb_ext(split: str) -> str:
    """The colour image extension BOP's toolkit expects in ``split``: ``.jpg`` for pbr splits, else ``.png``."""
    return ".jpg" if split_type(split) == "pbr" or split == "pbr" else ".png"


def rgb_path(root, split: str, scene_id: int, im_id: int) -> Path:
    """The colour image of a frame: the existing file (rgb/ or gray/, any of RGB_EXTS), else the path that
    :func:`write_rgb` writes."""
    d = scene_dir(root, split, scene_id)
    for ext in RGB_EXTS:
        for kind in ("rgb", "gray"):
            p = d / kind / f"{im_id:06d}{ext}"
            if p.is_file():
                return p
    return image_path(root, split, scene_id, im_id, "rgb", rgb_ext(split))


def write_rgb(root, split: str, scene_id: int, im_id: int, rgb: np.ndarray) -> Path:
    """Write a frame's colour image (H,W,3) uint8 as the split wants it (JPEG for pbr splits, else PNG)."""
    path = image_path(root, split, scene_id, im_id, "rgb", rgb_ext(split))
    if path.suffix == ".jpg":
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise ArgenError(f"cannot encode image {path} ({rgb.dtype}, shape {rgb.shape})")
        write_bytes(path, buf.tobytes(), sync=False)
    else:
        write_png(path, rgb)
    return path


def mask_path(root, split: str, scene_id: int, im_id: int, gt_idx: int, visib: bool = True) -> Path:
    """Path of a (visible) instance mask."""
    kind = "mask_visib" if visib else "mask"
    return scene_dir(root, split, scene_id) / kind / f"{im_id:06d}_{gt_idx:06d}.png"


# ---------------------------------------------------------------------------------- models_info


@dataclass
class ModelInfo:
    """One entry of ``models_info.json`` in metres.

    diameter: metres. bbox_min, bbox_size: (3,) metres, model frame.
    symmetries_discrete: list of (4,4) transforms, translation in metres.
    symmetries_continuous: list of {"axis": (3,), "offset": (3,) metres}.
    """

    diameter: float
    bbox_min: np.ndarray
    bbox_size: np.ndarray
    symmetries_discrete: list[np.ndarray] = field(default_factory=list)
    symmetries_continuous: list[dict] = field(default_factory=list)


def parse_models_info(data: dict, where: str = "models_info.json") -> dict[int, ModelInfo]:
    """Parse the JSON content of ``models_info.json`` (mm) into ``{obj_id: ModelInfo}`` (metres)."""
    if not isinstance(data, dict) or not data:
        raise ArgenError(f"{where} holds no objects")
    out: dict[int, ModelInfo] = {}
    for key, entry in data.items():
        try:
            obj_id = int(key)
            diameter = float(entry["diameter"]) / MM_PER_M
            bmin = np.array([entry["min_x"], entry["min_y"], entry["min_z"]], float) / MM_PER_M
            bsize = np.array([entry["size_x"], entry["size_y"], entry["size_z"]], float) / MM_PER_M
            sym_d, sym_c = _parse_symmetries(entry)
        except (KeyError, TypeError, ValueError) as exc:
            raise ArgenError(f"{where}: entry '{key}' is malformed ({exc.__class__.__name__}: {exc})") from exc
        if not (diameter > 0 and np.all(bsize > 0)):
            raise ArgenError(f"{where}: entry '{key}' has a non-positive diameter or size")
        out[obj_id] = ModelInfo(diameter, bmin, bsize, sym_d, sym_c)
    return out


def _parse_symmetries(entry: dict) -> tuple[list[np.ndarray], list[dict]]:
    sym_d = []
    for s in entry.get("symmetries_discrete", []):
        T = np.array(s, float).reshape(4, 4)
        T[:3, 3] /= MM_PER_M
        sym_d.append(T)
    sym_c = [{"axis": np.array(s["axis"], float), "offset": np.array(s["offset"], float) / MM_PER_M}
             for s in entry.get("symmetries_continuous", [])]
    return sym_d, sym_c


def parse_symmetries(entry: dict, where: str) -> tuple[list[np.ndarray], list[dict]]:
    """The ``symmetries_discrete`` ((4,4) transforms, translation in metres) and ``symmetries_continuous``
    ({"axis": (3,), "offset": (3,) metres}) of one models_info-style entry (mm); absent keys mean none."""
    try:
        if not isinstance(entry, dict):
            raise TypeError("not an object")
        return _parse_symmetries(entry)
    except (KeyError, TypeError, ValueError) as exc:
        raise ArgenError(f"{where}: malformed symmetries ({exc.__class__.__name__}: {exc})") from exc


def symmetry_transforms(info: ModelInfo, steps: int) -> np.ndarray:
    """All symmetry transforms of an object, identity first, built as the BOP toolkit builds them
    (``misc.get_symmetry_transformations``): the identity and the discrete symmetries, each combined with every
    rotation of the discretised continuous symmetries (``steps`` rotations about each axis through its offset,
    the axes' rotations listed one after the other). Returns (S,4,4) float64 (model frame, translation metres)
    that map a model point x to R x + t, the same surface seen at the same pose."""
    disc = [np.eye(4)] + [np.asarray(T, float) for T in info.symmetries_discrete]
    conts = []
    for s in info.symmetries_continuous:
        axis = np.asarray(s["axis"], float)
        axis = axis / np.linalg.norm(axis)
        off = np.asarray(s["offset"], float)
        for k in range(steps):
            T = np.eye(4)
            T[:3, :3] = cv2.Rodrigues(axis * (2 * np.pi * k / steps))[0]
            T[:3, 3] = off - T[:3, :3] @ off
            conts.append(T)
    return np.stack([c @ d for d in disc for c in (conts or [np.eye(4)])])


def read_models_info(path: str | os.PathLike) -> dict[int, ModelInfo]:
    """Read ``models_info.json`` into ``{obj_id: ModelInfo}`` in metres."""
    return parse_models_info(read_json(path, "models_info.json"), where=str(path))


def models_info_entry(info: ModelInfo) -> dict:
    """One ``models_info.json`` entry (mm) for ``info`` (metres)."""
    mn, sz = info.bbox_min * MM_PER_M, info.bbox_size * MM_PER_M
    entry = {
        "diameter": float(info.diameter * MM_PER_M),
        "min_x": float(mn[0]), "min_y": float(mn[1]), "min_z": float(mn[2]),
        "size_x": float(sz[0]), "size_y": float(sz[1]), "size_z": float(sz[2]),
    }
    if info.symmetries_discrete:
        syms = []
        for T in info.symmetries_discrete:
            T = np.array(T, float).copy()
            T[:3, 3] *= MM_PER_M
            syms.append([float(v) for v in T.reshape(-1)])
        entry["symmetries_discrete"] = syms
    if info.symmetries_continuous:
        entry["symmetries_continuous"] = [
            {"axis": [float(v) for v in s["axis"]], "offset": [float(v) * MM_PER_M for v in s["offset"]]}
            for s in info.symmetries_continuous
        ]
    return entry


def write_models_info(path: str | os.PathLike, infos: dict[int, ModelInfo]) -> None:
    """Write ``{obj_id: ModelInfo}`` (metres) as ``models_info.json`` (mm), atomically."""
    write_json(path, {str(k): models_info_entry(v) for k, v in sorted(infos.items())})


def model_path(models_dir: str | os.PathLike, obj_id: int) -> Path:
    return Path(models_dir) / f"obj_{obj_id:06d}.ply"


def read_mesh(path: str | os.PathLike):
    """Load a BOP PLY model (mm) as a ``trimesh.Trimesh`` in metres, keeping vertex colours and the file's vertex
    normals (written back unchanged by :func:`write_mesh`; computed from the faces when the file has none)."""
    # lazy: trimesh loads in about a second and only mesh files need it
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ArgenError(f"model file not found: {path}")
    if path.stat().st_size == 0:
        raise ArgenError(f"model file is empty: {path}")
    try:
        with path.open("rb") as f:
            kw = trimesh.exchange.ply.load_ply(f)
        # built from the file's own arrays: trimesh.load recomputes the normals, so the source's were lost
        mesh = trimesh.Trimesh(**{k: kw[k] for k in ("vertices", "faces", "vertex_normals", "vertex_colors",
                                                     "face_colors") if kw.get(k) is not None}, process=False)
    except Exception as exc:  # trimesh raises many kinds on corrupt input
        raise ArgenError(f"cannot read model {path}: corrupt or not a PLY mesh ({exc.__class__.__name__})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0 or len(mesh.vertices) < 4:
        raise ArgenError(f"model {path} holds no triangle mesh")
    if not np.all(np.isfinite(mesh.vertices)):
        raise ArgenError(f"model {path} has non-finite vertices")
    mesh.apply_scale(1.0 / MM_PER_M)
    return mesh


def write_mesh(path: str | os.PathLike, mesh) -> None:
    """Write a mesh given in metres as a binary BOP PLY in millimetres (with normals and colours)."""
    normals = np.array(mesh.vertex_normals)  # the mesh's own (a source file's); Trimesh.copy would recompute them
    m = mesh.copy()
    m.apply_scale(MM_PER_M)
    m.vertex_normals = normals
    data = m.export(file_type="ply", encoding="binary", vertex_normal=True)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data)


# -------------------------------------------------------------------------------------- images


def write_png(path: str | os.PathLike, image: np.ndarray, compression: int = 1) -> None:
    """Write an image atomically (RGB (H,W,3) uint8, or (H,W) uint8/uint16)."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, compression])
    if not ok:
        raise ArgenError(f"cannot encode image {path} ({image.dtype}, shape {image.shape})")
    # encoded in memory, written by Python: OS errors (disk full, permissions) get a clear message
    write_bytes(path, buf.tobytes(), sync=False)


def write_depth(path: str | os.PathLike, depth: np.ndarray, depth_scale: float) -> None:
    """Write depth (H,W) float metres (0 = missing) as a uint16 PNG with ``depth_mm = v * depth_scale``."""
    v = np.round(depth * (MM_PER_M / depth_scale))
    if v.max(initial=0) > 65535:
        raise ArgenError(f"depth beyond {65535 * depth_scale / MM_PER_M:.2f} m cannot be stored with "
                         f"depth_scale {depth_scale}")
    write_png(path, v.astype(np.uint16))


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> None:
    """Write a boolean (H,W) mask as a 0/255 PNG."""
    write_png(path, mask.astype(np.uint8) * 255)


def _read_image(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise ArgenError(f"image not found: {path}")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise ArgenError(f"cannot read image {path}: corrupt or not an image")
    return img


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """Read an RGB image: (H,W,3) uint8."""
    img = _read_image(Path(path), cv2.IMREAD_COLOR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: str | os.PathLike, depth_scale: float) -> np.ndarray:
    """Read a BOP depth PNG: (H,W) float32 metres, 0 = missing. BOP depth is one 16-bit channel; anything else (an
    8-bit colour or grey image given as depth) is an ArgenError, not depths of at most 255 units."""
    img = _read_image(Path(path), cv2.IMREAD_UNCHANGED)
    if img.dtype != np.uint16 or img.ndim != 2:
        what = f"{img.shape[2]}-channel " if img.ndim == 3 else ""
        raise ArgenError(f"{path} is a {what}{img.dtype.itemsize * 8}-bit image, not a depth image (one 16-bit "
                         "channel)")
    return img.astype(np.float32) * np.float32(depth_scale / MM_PER_M)


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """Read a mask PNG: (H,W) bool."""
    return _read_image(Path(path), cv2.IMREAD_GRAYSCALE) > 127


# ------------------------------------------------------------------------------------ camera.json

#: The dataset-level camera file (also a recording folder's intrinsics file).
CAMERA_FILE = "camera.json"


@dataclass
class CameraFile:
    """What a ``camera.json`` says. K: (3,3) pixels; depth_scale: mm per depth-PNG unit, or None when not given;
    width, height: pixels or None; dist: distortion coefficients as given (empty when none)."""

    K: np.ndarray
    depth_scale: float | None
    width: int | None
    height: int | None
    dist: list


def parse_intrinsics(cam: dict, where: str) -> np.ndarray:
    """K (3,3) float64 from a JSON object with fx, fy, cx, cy, or cam_K (9 values), or K (3x3); checked."""
    try:
        if "K" in cam:
            K = np.array(cam["K"], float).reshape(3, 3)
        elif "cam_K" in cam:
            K = np.array(cam["cam_K"], float).reshape(3, 3)
        else:
            K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], float)
    except KeyError as exc:
        raise ArgenError(f"{where}: no intrinsics: give fx, fy, cx, cy (or cam_K / K); missing {exc}") from None
    except (TypeError, ValueError) as exc:
        raise ArgenError(f"{where}: malformed intrinsics ({exc})") from None
    if not (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0 and K[0, 1] == 0 and (K[2] == [0, 0, 1]).all()):
        raise ArgenError(f"{where}: intrinsics must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    return K


def load_camera(path: str | os.PathLike) -> CameraFile:
    """Read a ``camera.json`` (BOP's fx, fy, cx, cy, depth_scale, width, height; cam_K or K also accepted)."""
    path = Path(path)
    cam = read_json(path, CAMERA_FILE)
    if not isinstance(cam, dict):
        raise ArgenError(f"{path} must hold an object with fx, fy, cx, cy and depth_scale")
    K = parse_intrinsics(cam, str(path))
    try:
        size = [int(cam[k]) if k in cam else None for k in ("width", "height")]
        scale = float(cam["depth_scale"]) if "depth_scale" in cam else None
        dist = [float(v) for v in np.ravel(cam.get("dist", []))]
    except (TypeError, ValueError) as exc:
        raise ArgenError(f"{path}: malformed camera.json ({exc})") from None
    return CameraFile(K, scale, size[0], size[1], dist)


def save_camera(path: str | os.PathLike, K: np.ndarray, width: int, height: int, depth_scale: float) -> None:
    """Write a BOP ``camera.json`` (fx, fy, cx, cy pixels, depth_scale, width, height), atomically."""
    K = np.asarray(K, np.float64)
    write_json(path, {"cx": float(K[0, 2]), "cy": float(K[1, 2]), "fx": float(K[0, 0]), "fy": float(K[1, 1]),
                      "depth_scale": float(depth_scale), "width": int(width), "height": int(height)})


# ---------------------------------------------------------------------------------- scene JSONs


def camera_entry(K: np.ndarray, depth_scale: float, T_cam_world: np.ndarray | None = None) -> dict:
    """A ``scene_camera.json`` entry. K: (3,3) pixels; T_cam_world: (4,4), translation metres."""
    e = {"cam_K": [float(v) for v in np.asarray(K).reshape(-1)], "depth_scale": float(depth_scale)}
    if T_cam_world is not None:
        e["cam_R_w2c"] = [float(v) for v in T_cam_world[:3, :3].reshape(-1)]
        e["cam_t_w2c"] = [float(v) * MM_PER_M for v in T_cam_world[:3, 3]]
    return e


def gt_entry(obj_id: int, R: np.ndarray, t: np.ndarray) -> dict:
    """A ``scene_gt.json`` instance entry. R: (3,3) model->camera; t: (3,) metres."""
    return {
        "cam_R_m2c": [float(v) for v in np.asarray(R).reshape(-1)],
        "cam_t_m2c": [float(v) * MM_PER_M for v in np.asarray(t).reshape(-1)],
        "obj_id": int(obj_id),
    }


def bbox_of(mask: np.ndarray) -> list[int]:
    """BOP bounding box [x, y, w, h] of a boolean mask; [-1, -1, -1, -1] when empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    x0, y0 = int(xs.min()), int(ys.min())
    return [x0, y0, int(xs.max()) - x0 + 1, int(ys.max()) - y0 + 1]


def gt_info_entry(mask_full: np.ndarray, mask_visib: np.ndarray, depth: np.ndarray,
                  outside: tuple[int, list[int]] | None = None) -> dict:
    """A ``scene_gt_info.json`` entry from the full and visible masks (H,W) bool and the written depth (H,W).

    outside: for a silhouette cut by the image edge, (its pixels beyond the edge, its whole unclipped
    [x, y, w, h]) (``Renderer.outside_silhouettes``). As in BOP's toolkit, ``px_count_all``, ``visib_fract`` and
    ``bbox_obj`` then cover the whole silhouette (``bbox_obj`` may start at negative x, y), while
    ``px_count_valid``, ``px_count_visib`` and ``bbox_visib`` count what is in the image.
    """
    n_out, bbox_all = outside if outside is not None else (0, bbox_of(mask_full))
    px_all = int(mask_full.sum()) + int(n_out)
    px_visib = int(mask_visib.sum())
    return {
        "bbox_obj": [int(v) for v in bbox_all],
        "bbox_visib": bbox_of(mask_visib),
        "px_count_all": px_all,
        "px_count_valid": int((mask_full & (depth > 0)).sum()),
        "px_count_visib": px_visib,
        "visib_fract": float(px_visib / px_all) if px_all else 0.0,
    }


@dataclass
class FrameCamera:
    """One frame's camera. K: (3,3) pixels; depth_scale: BOP; T_cam_world: (4,4) metres or None."""

    K: np.ndarray
    depth_scale: float
    T_cam_world: np.ndarray | None = None


@dataclass
class FrameGT:
    """One ground-truth instance. R: (3,3) model->camera, a proper rotation; t: (3,) metres; R_correction: the
    largest entry change that projecting the file's rotation onto SO(3) made (:func:`rotation_from_bop`)."""

    obj_id: int
    R: np.ndarray
    t: np.ndarray
    R_correction: float = 0.0


def rotation_from_bop(values, where: str = "rotation") -> tuple[np.ndarray, float]:
    """A BOP rotation (9 row-major values) as the nearest proper rotation, and how much that changed it.

    BOP files store rotations to about 8 digits and real ground truth is not exactly orthonormal (LM-O's driller:
    det 1.0029, |R R^T - I| up to 2e-3), so every rotation read from a BOP file passes here: SVD projection onto
    SO(3) (``U V^T`` with the sign of the determinant fixed). Returns R (3,3) float64 and the largest absolute
    entry change. A reflection or a degenerate matrix is an ArgenError.
    """
    M = np.asarray(values, float).reshape(3, 3)
    U, sv, Vt = np.linalg.svd(M)
    if sv.min() < 0.5 or np.linalg.det(M) <= 0:
        raise ArgenError(f"{where}: not a rotation (singular values {np.round(sv, 4).tolist()}, det "
                         f"{np.linalg.det(M):.4f})")
    R = U @ Vt
    return R, float(np.abs(R - M).max())


def _scene_json(path: Path, what: str) -> dict:
    data = read_json(path, what)
    if not isinstance(data, dict):
        raise ArgenError(f"{path} must hold an object keyed by image id")
    return data


def parse_scene_camera(data: dict, where: str) -> dict[int, FrameCamera]:
    """Parse ``scene_camera.json`` content into ``{im_id: FrameCamera}`` (metres)."""
    out = {}
    for key, e in data.items():
        try:
            K = np.array(e["cam_K"], float).reshape(3, 3)
            T = None
            if "cam_R_w2c" in e and "cam_t_w2c" in e:
                T = np.eye(4)
                T[:3, :3] = rotation_from_bop(e["cam_R_w2c"], f"{where}: image '{key}' cam_R_w2c")[0]
                T[:3, 3] = np.array(e["cam_t_w2c"], float).reshape(3) / MM_PER_M
            out[int(key)] = FrameCamera(K, float(e.get("depth_scale", 1.0)), T)
        except (KeyError, TypeError, ValueError) as exc:
            raise ArgenError(f"{where}: image '{key}' is malformed ({exc.__class__.__name__}: {exc})") from exc
    return out


def parse_scene_gt(data: dict, where: str) -> dict[int, list[FrameGT]]:
    """Parse ``scene_gt.json`` content into ``{im_id: [FrameGT, ...]}`` (metres)."""
    out = {}
    for key, items in data.items():
        try:
            gts = []
            for g in items:
                R, corr = rotation_from_bop(g["cam_R_m2c"], f"{where}: image '{key}' cam_R_m2c")
                gts.append(FrameGT(int(g["obj_id"]), R, np.array(g["cam_t_m2c"], float).reshape(3) / MM_PER_M, corr))
            out[int(key)] = gts
        except (KeyError, TypeError, ValueError) as exc:
            raise ArgenError(f"{where}: image '{key}' is malformed ({exc.__class__.__name__}: {exc})") from exc
    return out


@dataclass
class BopScene:
    """The JSON side of one BOP scene, parsed (metres)."""

    root: Path
    split: str
    scene_id: int
    cameras: dict[int, FrameCamera]
    gts: dict[int, list[FrameGT]]
    gt_infos: dict[int, list[dict]]

    @property
    def im_ids(self) -> list[int]:
        """Image ids that have both a camera and a ground truth entry, sorted."""
        return sorted(set(self.cameras) & set(self.gts))

    def rgb_path(self, im_id: int) -> Path:
        return rgb_path(self.root, self.split, self.scene_id, im_id)

    def read_rgb(self, im_id: int) -> np.ndarray | None:
        """(H,W,3) uint8, or None when the scene has no colour images."""
        p = self.rgb_path(im_id)
        return read_rgb(p) if p.is_file() else None

    def read_depth(self, im_id: int) -> np.ndarray:
        """(H,W) float32 metres."""
        return read_depth(image_path(self.root, self.split, self.scene_id, im_id, "depth"),
                          self.cameras[im_id].depth_scale)

    def read_mask(self, im_id: int, gt_idx: int, visib: bool = True) -> np.ndarray | None:
        """(H,W) bool, or None when the mask file does not exist."""
        p = mask_path(self.root, self.split, self.scene_id, im_id, gt_idx, visib)
        return read_mask(p) if p.is_file() else None


def list_scenes(root: str | os.PathLike, split: str) -> list[int]:
    """Scene ids of a split, sorted; an ArgenError when the split folder is missing or empty."""
    d = Path(root) / split
    if not d.is_dir():
        raise ArgenError(f"split folder not found: {d}")
    ids = sorted(int(p.name) for p in d.iterdir() if p.is_dir() and p.name.isdigit())
    if not ids:
        raise ArgenError(f"split folder {d} holds no scenes")
    return ids


def load_scene_camera(path: str | os.PathLike) -> dict[int, FrameCamera]:
    """Read one ``scene_camera.json`` into ``{im_id: FrameCamera}`` (metres)."""
    return parse_scene_camera(_scene_json(Path(path), "scene_camera.json"), str(path))


def depth_image_camera(path: str | os.PathLike) -> FrameCamera | None:
    """The camera of a depth image inside a BOP scene (``SCENE/depth/IMID.png``): its entry in the scene's
    ``scene_camera.json``; None when the path is not laid out so, the scene has no such file or it has no entry for
    the image."""
    path = Path(path)
    scene_cam = path.parent.parent / "scene_camera.json"
    if path.parent.name != "depth" or not path.stem.isdigit() or not scene_cam.is_file():
        return None
    return load_scene_camera(scene_cam).get(int(path.stem))


def camera_file_near(path: str | os.PathLike) -> Path | None:
    """The ``camera.json`` that holds an image's intrinsics: beside the image, one folder up (a recording), or at the
    root of the BOP dataset whose scene holds it (``DATASET/SPLIT/SCENE/depth/IMID.png``); None when there is none."""
    p = Path(path)
    near = [p.parent, p.parent.parent] + ([p.parents[3]] if len(p.parents) > 3 else [])
    return next((d / CAMERA_FILE for d in near if (d / CAMERA_FILE).is_file()), None)


def load_scene(root: str | os.PathLike, split: str, scene_id: int) -> BopScene:
    """Read and check the JSON files of one scene."""
    d = scene_dir(root, split, scene_id)
    cam_p, gt_p, info_p = d / "scene_camera.json", d / "scene_gt.json", d / "scene_gt_info.json"
    cameras = parse_scene_camera(_scene_json(cam_p, "scene_camera.json"), str(cam_p))
    gts = parse_scene_gt(_scene_json(gt_p, "scene_gt.json"), str(gt_p))
    infos = {int(k): v for k, v in _scene_json(info_p, "scene_gt_info.json").items()} if info_p.is_file() else {}
    for im_id, g in gts.items():
        if im_id not in cameras:
            raise ArgenError(f"{gt_p}: image {im_id} has ground truth but no entry in scene_camera.json")
        if infos and im_id in infos and len(infos[im_id]) != len(g):
            raise ArgenError(f"{info_p}: image {im_id} lists {len(infos[im_id])} instances, scene_gt.json {len(g)}")
    return BopScene(Path(root), split, scene_id, cameras, gts, infos)


# ------------------------------------------------------------------------------- writing scene JSONs

#: The per-scene JSON files, without ``.json``.
SCENE_FILES = ("scene_camera", "scene_gt", "scene_gt_info")


def load_scene_jsons(root: str | os.PathLike, split: str, scene_id: int) -> dict[str, dict]:
    """The raw content of a scene's three JSON files {name: {im_id str: entry}} ({} for a missing file)."""
    d = scene_dir(root, split, scene_id)
    return {name: (_scene_json(d / f"{name}.json", f"{name}.json") if (d / f"{name}.json").is_file() else {})
            for name in SCENE_FILES}


def save_scene_jsons(root: str | os.PathLike, split: str, scene_id: int, data: dict[str, dict]) -> None:
    """Write a scene's JSON files from {name: {im_id str: entry}} (images in id order, compact), atomically."""
    d = scene_dir(root, split, scene_id)
    for name, content in data.items():
        write_json(d / f"{name}.json", {k: content[k] for k in sorted(content, key=int)}, indent=None)


class SceneJsons:
    """The per-scene JSON files of a split being written: kept in memory, merged with what is on disk, and flushed
    atomically (a resumed or merged capture keeps the entries already there)."""

    def __init__(self, root: str | os.PathLike, split: str):
        self.root, self.split = Path(root), split
        self.data: dict[int, dict[str, dict]] = {}
        self.dirty: set[int] = set()

    def scene(self, scene_id: int) -> dict[str, dict]:
        """The scene's {name: {im_id str: entry}}, read from disk the first time; the caller may change it (then
        :meth:`touch` it)."""
        if scene_id not in self.data:
            self.data[scene_id] = load_scene_jsons(self.root, self.split, scene_id)
        return self.data[scene_id]

    def touch(self, scene_id: int) -> None:
        """Mark a scene as changed: the next :meth:`flush` writes it."""
        self.dirty.add(scene_id)

    def add(self, scene_id: int, im_id: int, camera: dict, gt: list, gt_info: list) -> None:
        """One image's entries: ``camera_entry``, [``gt_entry``, ...] and [``gt_info_entry``, ...]."""
        s = self.scene(scene_id)
        key = str(im_id)
        s["scene_camera"][key], s["scene_gt"][key], s["scene_gt_info"][key] = camera, gt, gt_info
        self.touch(scene_id)

    def flush(self) -> None:
        """Write the changed scenes."""
        for sid in sorted(self.dirty):
            save_scene_jsons(self.root, self.split, sid, self.data[sid])
        self.dirty.clear()


# ---------------------------------------------------------------------------------------- test targets

#: The BOP19 test-target list at a dataset's root: the images and objects the BOP toolkit evaluates.
TEST_TARGETS = "test_targets_bop19.json"


def test_targets(root: str | os.PathLike, split: str, min_visib: float = 0.1) -> list[dict]:
    """The BOP19 targets of a split: per image with ground truth and per object, how many of its instances are
    at least ``min_visib`` visible (BOP's rule: 0.1), from each scene's scene_gt_info.json (scene_gt.json for the
    object ids). Returns [{"im_id", "inst_count", "obj_id", "scene_id"}] sorted by scene, image, object; objects
    with no instance that visible are left out."""
    out = []
    split_dir = Path(root) / split
    for d in sorted(p for p in split_dir.iterdir() if p.is_dir() and p.name.isdigit()) if split_dir.is_dir() else []:
        gt_p, info_p = d / "scene_gt.json", d / "scene_gt_info.json"
        if not (gt_p.is_file() and info_p.is_file()):
            continue
        gts, infos = _scene_json(gt_p, "scene_gt.json"), _scene_json(info_p, "scene_gt_info.json")
        for key in sorted(gts, key=int):
            counts: dict[int, int] = {}
            for g, info in zip(gts[key], infos.get(key, [])):
                if float(info.get("visib_fract", 0.0)) >= min_visib:
                    counts[int(g["obj_id"])] = counts.get(int(g["obj_id"]), 0) + 1
            out += [{"im_id": int(key), "inst_count": n, "obj_id": o, "scene_id": int(d.name)}
                    for o, n in sorted(counts.items())]
    return out


def save_test_targets(root: str | os.PathLike, split: str, min_visib: float = 0.1) -> Path:
    """Write :func:`test_targets` of ``split`` as ``ROOT/test_targets_bop19.json`` (atomically)."""
    path = Path(root) / TEST_TARGETS
    write_json(path, test_targets(root, split, min_visib), indent=None)
    return path


def load_test_targets(path: str | os.PathLike) -> list[dict]:
    """Read a ``test_targets_bop19.json``: [{"im_id", "inst_count", "obj_id", "scene_id"}] (ints)."""
    data = read_json(Path(path), TEST_TARGETS)
    try:
        return [{k: int(e[k]) for k in ("im_id", "inst_count", "obj_id", "scene_id")} for e in data]
    except (KeyError, TypeError, ValueError) as exc:
        raise ArgenError(f"{path}: not a BOP test-target list ({exc.__class__.__name__}: {exc})") from None
