"""What only a model's print tells apart: the rotations that map its shape onto itself but that its texture breaks
(:func:`shape_symmetries`), and its surface colours at sample points (:func:`surface_colours`).

A box with a printed label is the common case: its shape looks the same turned half way about any of its three axes,
so depth alone cannot say which way round it lies; its print can. BOP's ``models_info.json`` lists an object's
symmetries with its texture in mind (a printed box has none), so the shape symmetries of an object that the file
calls asymmetric are the turns its texture breaks. The detector chooses among them by the frame's colours
(:mod:`detector.geometry.colour_check`). Metres; transforms (4,4) map model points to model points.
"""

from __future__ import annotations

import numpy as np
import trimesh
from PIL import Image

from argen.models.objects import ObjectModel, surface_scene

#: Surface samples a textured object carries for the colour check (measured on the real gelatin box: 2000 or more
#: choose its way round as well as 8000; fewer miss fine print).
TEXTURE_POINTS = 4000
#: A texture whose grey level varies less than this (standard deviation, colours in [0, 1]) over the surface cannot
#: tell turns apart: such an object carries no texture sample.
MIN_TEXTURE_STD = 0.03


def texture_image(visual) -> np.ndarray | None:
    """The base-colour image of a trimesh TextureVisuals as (H,W,3) uint8, or None (also the renderer's texture)."""
    mat = getattr(visual, "material", None)
    img = getattr(mat, "baseColorTexture", None)
    if img is None:
        img = getattr(mat, "image", None)
    if img is None:
        return None
    if isinstance(img, Image.Image):
        img = np.asarray(img.convert("RGB"))
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8) if img.dtype.kind == "f" else img.astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return np.ascontiguousarray(img[..., :3])


def surface_colours(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray | None:
    """The mesh's colour at surface points: (N,3) uint8 RGB, or None when the mesh has no colours.

    points: (N,3) on (or near) the surface, the mesh's units. Each point takes the colour of its closest surface
    point: vertex colours interpolated over the triangle, or the texture image at the interpolated UV (nearest
    pixel)."""
    import open3d as o3d  # lazy: open3d loads in about a second (as in surface_scene)

    visual = mesh.visual
    image = texture_image(visual) if getattr(visual, "kind", None) == "texture" else None
    uv_map = getattr(visual, "uv", None) if image is not None else None
    if image is None and getattr(visual, "kind", None) != "vertex":
        return None
    hit = surface_scene(mesh).compute_closest_points(o3d.core.Tensor(np.asarray(points, np.float32)))
    face = hit["primitive_ids"].numpy().astype(np.int64)
    bu, bv = (hit["primitive_uvs"].numpy().astype(np.float64).T)
    w = np.stack([1.0 - bu - bv, bu, bv], axis=1)  # barycentric weights of the face's three vertices
    corners = np.asarray(mesh.faces)[face]
    if uv_map is not None:
        uv = np.einsum("nk,nkj->nj", w, np.asarray(uv_map, np.float64)[corners])
        h, wd = image.shape[:2]
        col = np.clip(np.round(np.mod(uv[:, 0], 1.0) * (wd - 1)), 0, wd - 1).astype(np.int64)
        row = np.clip(np.round((1.0 - np.mod(uv[:, 1], 1.0)) * (h - 1)), 0, h - 1).astype(np.int64)
        return image[row, col]
    vc = np.asarray(visual.vertex_colors, np.float64)[:, :3]
    return np.clip(np.round(np.einsum("nk,nkj->nj", w, vc[corners])), 0, 255).astype(np.uint8)


def shape_symmetries(obj: ObjectModel) -> np.ndarray:
    """(S,4,4) float64: the rotations (not the identity) that map the object's shape onto itself within
    :func:`argen.models.symmetry.find_symmetries`' default tolerance, for an object its models_info calls
    asymmetric (its texture breaks them); (0,4,4) for an object listed as symmetric (its symmetries are its own)
    or a shape without any."""
    if obj.symmetric:
        return np.zeros((0, 4, 4))
    from argen.models.symmetry import find_symmetries  # lazy: it loads open3d (about a second) at import

    found = find_symmetries(obj.mesh, obj.diameter).discrete
    return np.stack(found).astype(np.float64) if found else np.zeros((0, 4, 4))


def textured(colours: np.ndarray) -> bool:
    """Whether surface colours (N,3) uint8 vary enough to tell turns apart (grey-level std at least
    ``MIN_TEXTURE_STD``)."""
    return len(colours) > 0 and float(np.std(np.asarray(colours, np.float64).mean(axis=1) / 255.0)) >= MIN_TEXTURE_STD


#: A shape symmetry keeps an object's print when the print, averaged over ``PRINT_SCALE`` x the diameter, moves
#: under it by less than this mean absolute difference (RGB in [0, 1]). Measured: the LineMOD eggbox's and glue's
#: listed symmetries move their scans' print by 0.032 and 0.036 (BOP lists them: the print keeps them); the YCB
#: gelatin box's three half turns move its print by 0.104, 0.172 and 0.176 (BOP lists none).
PRINT_TOL = 0.06
PRINT_SCALE = 0.05


def print_moves(mesh: trimesh.Trimesh, diameter: float, transforms: list, n_points: int = 4000,
                seed: int = 0) -> np.ndarray:
    """How far each transform moves the mesh's print: the mean absolute difference (RGB in [0, 1]) between the
    print at surface samples and at their images, each averaged over the samples within ``PRINT_SCALE`` x
    ``diameter`` (scan noise and fine text average out; faces and labels do not). transforms: (4,4) each, the mesh's
    units; returns (T,) float64, zeros when the mesh has no colours."""
    from scipy.spatial import cKDTree  # lazy: only an import with colours needs it

    pts = trimesh.sample.sample_surface(mesh, n_points, seed=seed)[0]
    cols = surface_colours(mesh, pts)
    if cols is None:
        return np.zeros(len(transforms))
    cols = cols.astype(np.float64) / 255.0
    tree = cKDTree(pts)

    def averaged(q: np.ndarray) -> np.ndarray:
        near = tree.query_ball_point(q, PRINT_SCALE * diameter)
        nearest = tree.query(q)[1]
        return np.array([cols[i].mean(axis=0) if len(i) else cols[j] for i, j in zip(near, nearest)])

    base = averaged(pts)
    T = [np.asarray(t, np.float64) for t in transforms]
    return np.array([float(np.abs(base - averaged(pts @ t[:3, :3].T + t[:3, 3])).mean()) for t in T])
