"""Off-screen rendering with pyrender + OSMesa: colour, depth, instance segmentation, full silhouettes.

Every other module that needs pyrender imports it through here, so the OSMesa platform choice and
the numpy-2 fix for pyrender 0.1.45 (``np.infty``) live in this one place.

Conventions of the API (metres everywhere):
- Camera: OpenCV (x right, y down, z forward), pixel centres at integer coordinates. ``K`` is (3, 3)
  with zero skew; ``T_cam_world`` (4, 4) maps world points into the camera frame. pyrender's camera
  looks down -z with y up: the conversion is done here only (camera node pose =
  inv(T_cam_world) @ diag(1, -1, -1, 1), and cx, cy shifted by +0.5 px because pyrender's
  ``IntrinsicsCamera`` puts pixel centres at half-integers).
- Depth: (H, W) float32, the z coordinate in the camera frame (not the ray length), 0 where no
  surface is hit (or it lies outside [znear, zfar]).
- Segmentation: (H, W) int32, the ``seg_id`` of the visible surface, 0 for background and for items
  that are not instances (table, board, clutter). Exact: no anti-aliasing, ids round-trip through
  24-bit colours.

Speed: one persistent ``pyrender.Scene`` per renderer. Meshes are converted to ``pyrender.Mesh``
once per ``RenderItem.key`` and their nodes stay in the scene; items absent from a frame are hidden
with ``Mesh.is_visible`` rather than removed, because pyrender's ``Renderer._update_context`` frees a
mesh's GPU buffers as soon as no node of the scene uses it (and re-uploads it when it comes back).
The OSMesa platform renders straight into a single-sample default framebuffer, so colour is not
anti-aliased and depth / seg are sampled at pixel centres (same coverage in all three outputs).
pyrender's shader cache never hits under OSMesa (it keys programs by a context object that is new
on every call), which recompiled the shaders for every draw: ``_ProgramCache`` fixes that.
Measured on 2 cores (llvmpipe, 640 x 480, board + 4 LineMOD models, 114k faces): colour + depth
~27 ms, + seg ~45 ms, depth only ~16 ms, full_masks ~21 ms; with 10 models (271k faces) about
twice that. Cost grows with the number of triangles: ``max_faces`` (decimation) trades < 0.25 mm
of geometry (10k faces) for up to 2x speed. llvmpipe uses all cores (LP_NUM_THREADS).

Lighting: Lambertian (no specular), so results are flat-ish and view independent:
colour = albedo * (ambient + sum over lights of intensity * max(n . l, 0) / pi [/ d^2 for point
lights]), then gamma-encoded with x^(1/2.2) as pyrender does. Albedo is the linearised sRGB vertex
colour or texture, so a surface under total light 1 shows about its own colour.

Processes: ``get_renderer`` keeps one renderer per (process, image size, max_faces). OSMesa
contexts do not survive ``fork``; start workers with the "spawn" method (argen.sim.capture does).
"""

from __future__ import annotations

import atexit
import os

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np  # noqa: E402

if not hasattr(np, "infty"):  # pyrender 0.1.45 uses np.infty, removed in numpy 2
    np.infty = np.inf

from collections import OrderedDict  # noqa: E402
from collections.abc import Hashable, Sequence  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import OpenGL.platform  # noqa: E402
import pyrender  # noqa: E402
import trimesh  # noqa: E402
from OpenGL import GL  # noqa: E402
from PIL import Image  # noqa: E402
from scipy.sparse import coo_matrix  # noqa: E402
from scipy.sparse.csgraph import connected_components  # noqa: E402

from argen.models.texture import texture_image  # noqa: E402

if os.environ["PYOPENGL_PLATFORM"] == "osmesa" and not hasattr(OpenGL.platform.PLATFORM, "OSMesa"):
    raise ImportError("PyOpenGL was imported before argen.sim.render could select OSMesa: import argen.sim.render "
                      "before pyrender/OpenGL, or set PYOPENGL_PLATFORM=osmesa in the environment")

__all__ = ["RenderItem", "Light", "RenderOutput", "Renderer", "get_renderer", "textured_plane", "pyrender"]

CREASE_ANGLE = np.deg2rad(30.0)  # faces meeting at a sharper angle get separate vertex normals
_FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes <-> OpenGL camera axes


@dataclass
class RenderItem:
    """One mesh instance to render.

    key: hashable id of the geometry (``mesh``); the converted pyrender mesh is cached under it, so
        one key must always come with the same geometry. mesh: trimesh.Trimesh in metres with vertex
        colours, face colours or a texture (no visual: grey). T_world_obj: (4, 4) pose, may include a
        positive scale. seg_id: instance id for seg / full_masks, 0 = not an instance.
    """

    key: Hashable
    mesh: trimesh.Trimesh
    T_world_obj: np.ndarray
    seg_id: int = 0


@dataclass
class Light:
    """A light for the colour pass.

    kind: "directional" | "point". intensity: pyrender units (directional: W/m^2-like, point: W/sr-like,
    falls off with 1/d^2). colour: (3,) RGB in [0, 1]. T_world_light: (4, 4) pyrender-style pose: a
    directional light shines along the pose's -z axis, a point light sits at its translation.
    """

    kind: str
    intensity: float
    colour: np.ndarray
    T_world_light: np.ndarray


@dataclass
class RenderOutput:
    """rgb: (H, W, 3) uint8. depth: (H, W) float32, metres, 0 = nothing. seg: (H, W) int32 seg_id or None."""

    rgb: np.ndarray
    depth: np.ndarray
    seg: np.ndarray | None = None


# ----------------------------------------------------------------------------------------------------
# trimesh -> pyrender conversion (once per key)
# ----------------------------------------------------------------------------------------------------


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB values in [0, 1] -> linear; pyrender's shader gamma-encodes its output (x^(1/2.2))."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _consistent_winding(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray | None:
    """Faces re-oriented so that neighbours agree on winding (pyrender culls back faces).

    vertices: (V, 3) float, faces: (F, 3) int. In each connected patch the minority orientation is
    flipped; if the mesh is closed, patches enclosing negative volume are then turned outwards.
    Returns (F, 3) faces, or None if some patch is not orientable (e.g. a Moebius strip).
    """
    n_f = len(faces)
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).astype(np.int64)
    fid = np.repeat(np.arange(n_f), 3)
    key = e.min(axis=1) * (int(faces.max()) + 1) + e.max(axis=1)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    start = np.r_[True, ks[1:] != ks[:-1]]
    first = np.flatnonzero(start)
    count = np.diff(np.r_[first, len(ks)])
    two = first[count == 2]  # manifold edges: shared by exactly two faces
    i, j = order[two], order[two + 1]
    flip = (e[i, 0] == e[j, 0]).astype(np.int64)  # same direction: one of the two must flip
    # double cover: node f = face f as is, node f + F = face f flipped
    fi, fj = fid[i], fid[j]
    rows = np.r_[fi, fi + n_f]
    cols = np.r_[fj + flip * n_f, fj + (1 - flip) * n_f]
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * n_f, 2 * n_f))
    n_lab, lab = connected_components(graph, directed=False)
    l0, l1 = lab[:n_f], lab[n_f:]
    if np.any(l0 == l1):
        return None
    c0 = np.bincount(l0, minlength=n_lab)
    keep = (c0[l0] > c0[l1]) | ((c0[l0] == c0[l1]) & (l0 < l1))
    if np.all(count == 2):  # closed: orient every patch outwards
        patch = np.where(keep, l0, l1)
        tri = vertices[faces]
        vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) * np.where(keep, 1.0, -1.0)
        keep ^= np.bincount(patch, weights=vol, minlength=n_lab)[patch] < 0
    out = faces.copy()
    out[~keep] = out[~keep][:, ::-1]
    return out


def _crease_split(vertices: np.ndarray, faces: np.ndarray, crease: float = CREASE_ANGLE):
    """Per-corner smooth normals that stay sharp across creases, with vertices split where needed.

    vertices: (V, 3) float, faces: (F, 3) int.
    Returns (src, normals, new_faces): src (V',) int index of each new vertex into ``vertices``,
    normals (V', 3) float32 unit normals, new_faces (F, 3) int into the new vertices. A corner's
    normal is the area-weighted mean of the normals of the faces around its vertex that are within
    ``crease`` radians of its own face.
    """
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    fn = cross / np.maximum(area2, 1e-30)[:, None]
    nc = 3 * len(faces)
    cv = faces.ravel()
    cf = np.repeat(np.arange(len(faces)), 3)
    order = np.argsort(cv, kind="stable")
    cv_s, cf_s = cv[order], cf[order]
    counts = np.bincount(cv_s, minlength=len(vertices))
    starts = np.cumsum(counts) - counts
    deg = counts[cv_s]
    a = np.repeat(np.arange(nc), deg)  # every pair of corners sharing a vertex
    b = starts[cv_s][a] + np.arange(a.size) - np.repeat(np.cumsum(deg) - deg, deg)
    fa, fb = cf_s[a], cf_s[b]
    w = (np.einsum("ij,ij->i", fn[fa], fn[fb]) >= np.cos(crease)) * area2[fb]
    n_s = np.stack([np.bincount(a, weights=w * fn[fb, k], minlength=nc) for k in range(3)], axis=1)
    n = np.empty_like(n_s)
    n[order] = n_s
    length = np.linalg.norm(n, axis=1)
    own = fn[cf]
    n = np.where(length[:, None] > 1e-20, n / np.maximum(length, 1e-30)[:, None], own)
    q = np.round(n * 1000.0).astype(np.int64) + 1000  # in [0, 2000]
    key = ((cv.astype(np.int64) * 2001 + q[:, 0]) * 2001 + q[:, 1]) * 2001 + q[:, 2]
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    return cv[first], n[first].astype(np.float32), inverse.reshape(-1, 3)


def _decimate(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """Quadric decimation to at most ``max_faces`` faces (open3d), keeping vertex colours.

    Only for meshes with vertex colours or no visual; others are returned unchanged. LineMOD
    models at 10k faces stay within 0.25 mm of the original surface, at 5k within 0.5 mm.
    """
    kind = mesh.visual.kind if mesh.visual is not None and mesh.visual.defined else None
    if len(mesh.faces) <= max_faces or kind not in (None, "vertex"):
        return mesh
    # lazy: open3d loads in about a second; only meshes too large to render are simplified with it
    import open3d as o3d

    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=np.float64)),
                                   o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)))
    if kind == "vertex":
        om.vertex_colors = o3d.utility.Vector3dVector(np.asarray(mesh.visual.vertex_colors)[:, :3] / 255.0)
    d = om.simplify_quadric_decimation(int(max_faces))
    colours = None
    if kind == "vertex":
        colours = np.clip(np.round(np.asarray(d.vertex_colors) * 255.0), 0, 255).astype(np.uint8)
    return trimesh.Trimesh(np.asarray(d.vertices), np.asarray(d.triangles), vertex_colors=colours, process=False)


def _to_pyrender(mesh: trimesh.Trimesh) -> pyrender.Mesh:
    """Convert a trimesh (metres) to an opaque, diffuse pyrender mesh with crease-aware normals.

    Vertex colours are converted to linear RGB (see the module's lighting note). Faces are
    re-oriented consistently (several LineMOD models have a few flipped faces), since pyrender always
    culls back faces in depth and seg passes; a non-orientable mesh gets every face twice instead.
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if len(faces) == 0:
        raise ValueError("cannot render a mesh without faces")
    visual = mesh.visual
    kind = visual.kind if visual is not None and visual.defined else None
    colours = uv = image = None
    if kind == "vertex":
        colours = np.asarray(visual.vertex_colors)[:, :3]
    elif kind == "face":  # one vertex per corner, so each face keeps its colour
        colours = np.repeat(np.asarray(visual.face_colors)[:, :3], 3, axis=0)
        vertices, faces = vertices[faces].reshape(-1, 3), np.arange(3 * len(faces)).reshape(-1, 3)
    elif kind == "texture":
        image = texture_image(visual)
        if image is not None and visual.uv is not None:
            uv = np.asarray(visual.uv, dtype=np.float64)[:, :2]
        else:
            image = None
    oriented = _consistent_winding(vertices, faces)
    faces = np.concatenate([faces, faces[:, ::-1]]) if oriented is None else oriented
    src, normals, new_faces = _crease_split(vertices, faces)
    colour_0 = None
    if colours is not None:
        lin = _srgb_to_linear(colours[src].astype(np.float64) / 255.0)
        colour_0 = np.c_[lin, np.ones(len(src))].astype(np.float32)
    texture = None
    if image is not None:
        sampler = pyrender.Sampler(magFilter=GL.GL_LINEAR, minFilter=GL.GL_LINEAR_MIPMAP_LINEAR,
                                   wrapS=GL.GL_CLAMP_TO_EDGE, wrapT=GL.GL_CLAMP_TO_EDGE)
        texture = pyrender.Texture(source=image, source_channels="RGB", sampler=sampler)
    base = [1.0, 1.0, 1.0, 1.0] if (colours is not None or texture is not None) else [0.2, 0.2, 0.2, 1.0]
    material = pyrender.MetallicRoughnessMaterial(baseColorFactor=base, baseColorTexture=texture,
                                                  metallicFactor=0.0, roughnessFactor=1.0,
                                                  alphaMode="OPAQUE", doubleSided=False)
    prim = pyrender.Primitive(positions=vertices[src].astype(np.float32), normals=normals,
                              texcoord_0=None if uv is None else uv[src].astype(np.float32),
                              color_0=colour_0, indices=new_faces.astype(np.uint32),
                              material=material, mode=pyrender.GLTF.TRIANGLES)
    return pyrender.Mesh(primitives=[prim])


def textured_plane(side: float, image: np.ndarray, thickness: float = 0.0) -> trimesh.Trimesh:
    """A square board of ``side`` metres in the z = 0 plane, top surface textured with ``image``.

    side: metres. image: (h, w, 3) uint8 RGB. thickness: metres; > 0 adds a box below the top surface
    (z in [-thickness, 0]) whose sides show the texture's edge pixels.
    Texture convention (same as argen.sim.board): image column 0 is x = -side/2, row 0 is y = +side/2, so
    the image looks upright and unmirrored seen from above (from +z, x right, y up). The top surface
    faces +z; a board without thickness is invisible from below (back faces are culled).
    Returns a trimesh.Trimesh with TextureVisuals (uv: u = (x + side/2) / side, v = (y + side/2) / side).
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"texture must be (h, w, 3), got {image.shape}")
    if not side > 0 or thickness < 0:
        raise ValueError(f"need side > 0 and thickness >= 0, got {side}, {thickness}")
    h = side / 2.0
    if thickness > 0:
        box = trimesh.creation.box(extents=(side, side, thickness))
        box.apply_translation([0.0, 0.0, -thickness / 2.0])
        vertices = box.vertices[box.faces].reshape(-1, 3)  # one vertex per corner: sharp edges
        faces = np.arange(len(vertices)).reshape(-1, 3)
    else:
        vertices = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
        faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.clip((vertices[:, :2] + h) / side, 0.0, 1.0)
    visual = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(image.astype(np.uint8)))
    return trimesh.Trimesh(vertices=vertices, faces=faces, visual=visual, process=False)


# ----------------------------------------------------------------------------------------------------
# Shaders: pyrender's, with a fixed program cache and a Lambertian fragment shader for colour
# ----------------------------------------------------------------------------------------------------

_LAMBERT_NAME = "argen-lambert.frag"
_LAMBERT_FRAG = """
struct DirectionalLight { vec3 color; float intensity; vec3 direction; };
struct PointLight { vec3 color; float intensity; vec3 position; };
struct Material {
    vec4 base_color_factor;
#ifdef HAS_BASE_COLOR_TEX
    sampler2D base_color_texture;
#endif
};
uniform Material material;
uniform DirectionalLight directional_lights[MAX_DIRECTIONAL_LIGHTS];
uniform int n_directional_lights;
uniform PointLight point_lights[MAX_POINT_LIGHTS];
uniform int n_point_lights;
uniform vec3 ambient_light;

in vec3 frag_position;
in vec3 frag_normal;
#ifdef TEXCOORD_0_LOC
in vec2 uv_0;
#endif
#ifdef COLOR_0_LOC
in vec4 color_multiplier;
#endif
out vec4 frag_color;

const float INV_PI = 0.3183098861837907;

vec3 srgb_to_linear(vec3 c)
{
    return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), step(vec3(0.04045), c));
}

void main()
{
    vec3 albedo = material.base_color_factor.rgb;
#ifdef HAS_BASE_COLOR_TEX
    albedo *= srgb_to_linear(texture(material.base_color_texture, uv_0).rgb);
#endif
#ifdef COLOR_0_LOC
    albedo *= color_multiplier.rgb;
#endif
    vec3 n = normalize(frag_normal);
    vec3 light = ambient_light;
    for (int i = 0; i < n_directional_lights; i++) {
        float nl = max(dot(n, -normalize(directional_lights[i].direction)), 0.0);
        light += nl * INV_PI * directional_lights[i].intensity * directional_lights[i].color;
    }
    for (int i = 0; i < n_point_lights; i++) {
        vec3 d = point_lights[i].position - frag_position;
        float d2 = max(dot(d, d), 1e-8);
        float nl = max(dot(n, d) * inversesqrt(d2), 0.0);
        light += nl * INV_PI / d2 * point_lights[i].intensity * point_lights[i].color;
    }
    frag_color = vec4(clamp(pow(albedo * light, vec3(1.0 / 2.2)), 0.0, 1.0), 1.0);
}
"""


class _ShaderProgram(pyrender.shader_program.ShaderProgram):
    """pyrender's shader program, which also knows the in-memory Lambertian fragment shader."""

    def _load(self, shader_filename):
        if shader_filename != _LAMBERT_NAME:
            return super()._load(shader_filename)
        defines = "".join(f"#define {k} {v}\n" for k, v in sorted(self.defines.items()))
        return "#version 330 core\n" + defines + _LAMBERT_FRAG


class _ProgramCache(pyrender.shader_program.ShaderProgramCache):
    """pyrender's shader cache, keyed without the OpenGL context; colour uses the Lambert shader.

    pyrender keys programs by ``OpenGL.contextdata.getContext()``, which under OSMesa returns a new
    object on every call: every draw compiled its shaders again (most of the frame time) and the
    cache grew without bound. Each Renderer has its own context and its own cache, so the key needs
    no context.
    """

    def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
        defines = dict(defines or {})
        key = (vertex_shader, fragment_shader, geometry_shader, tuple(sorted(defines.items())))
        program = self._program_cache.get(key)
        if program is None:
            vs, fs, gs = (None if s is None else os.path.join(self.shader_dir, s)
                          for s in (vertex_shader, fragment_shader, geometry_shader))
            if fragment_shader == "mesh.frag":
                fs = _LAMBERT_NAME
            program = _ShaderProgram(vs, fs, gs, defines=defines)
            self._program_cache[key] = program
        return program


# ----------------------------------------------------------------------------------------------------
# The renderer
# ----------------------------------------------------------------------------------------------------


@dataclass
class _Entry:
    """A cached geometry: its pyrender mesh, the trimesh it came from, and its nodes in the scene."""

    mesh: pyrender.Mesh
    source: trimesh.Trimesh
    corners: np.ndarray  # (8, 3) corners of the mesh's bounding box, object frame, metres
    nodes: list


def _seg_colour(seg_id: int) -> tuple[int, int, int]:
    """seg_id (0 <= id < 2^24) -> the RGB colour that encodes it exactly."""
    if not 0 <= seg_id < 1 << 24:
        raise ValueError(f"seg_id must be in [0, 2^24), got {seg_id}")
    return (seg_id & 255, (seg_id >> 8) & 255, (seg_id >> 16) & 255)


def _decode_seg(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 colours written by a SEG pass -> (H, W) int32 seg ids."""
    c = rgb.astype(np.int32)
    return c[..., 0] | (c[..., 1] << 8) | (c[..., 2] << 16)


def _boxes_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two [u0, v0, u1, v1] pixel boxes intersect."""
    return bool(a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3])


class _LightNode(pyrender.Node):
    """A light's node whose hash is its place in the renderer's light pool (small distinct integers).

    pyrender binds the lights to the shader in the order of a set of nodes; with the default, address-based hash
    that order, and with it the order in which the shader sums the lights' contributions, changed with what the
    process had allocated before, and colour images differed in the last bit. Small integer hashes iterate in the
    same order in any set.
    """

    def __init__(self, rank: int, **kwargs):
        super().__init__(**kwargs)
        self._rank = int(rank)

    def __hash__(self) -> int:
        return self._rank


class Renderer:
    """An OSMesa off-screen renderer of ``width`` x ``height`` pixels with a persistent scene.

    Reuse one per process (``get_renderer``). Geometry is converted and uploaded once per
    ``RenderItem.key`` (at most ``max_meshes`` keys, least recently used dropped first).
    max_faces: if set, meshes with vertex colours are decimated to at most this many faces before
    upload (faster, see ``_decimate`` for the geometric error); None renders them exactly.
    """

    def __init__(self, width: int, height: int, max_faces: int | None = None, max_meshes: int = 256):
        if width <= 0 or height <= 0:
            raise ValueError(f"image size must be positive, got {width} x {height}")
        self.width, self.height = int(width), int(height)
        self.max_faces, self.max_meshes = max_faces, max_meshes
        self._osr = pyrender.OffscreenRenderer(self.width, self.height)
        self._osr._renderer._program_cache = _ProgramCache()
        self._scene = pyrender.Scene(bg_color=np.zeros(4), ambient_light=np.zeros(3))
        self._camera = pyrender.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=0.05, zfar=6.0)
        self._cam_node = self._scene.add(self._camera, pose=np.eye(4))
        self._entries: OrderedDict[Hashable, _Entry] = OrderedDict()
        self._lights: dict[str, list[pyrender.Node]] = {"directional": [], "point": []}
        self._draw_rank: dict[pyrender.Node, int] = {}  # node -> index of its item in the last _place
        self._osr._renderer._sorted_mesh_nodes = self._draw_order

    # -- scene management ----------------------------------------------------------------------------

    def _entry(self, item: RenderItem) -> _Entry:
        e = self._entries.get(item.key)
        if e is not None:
            if e.source is not item.mesh and (e.source.vertices.shape != item.mesh.vertices.shape
                                              or e.source.faces.shape != item.mesh.faces.shape):
                raise ValueError(f"render key {item.key!r} reused for a different mesh")
            self._entries.move_to_end(item.key)
            return e
        mesh = item.mesh if self.max_faces is None else _decimate(item.mesh, self.max_faces)
        b = np.asarray(item.mesh.bounds, dtype=np.float64)
        corners = np.stack(np.meshgrid(*b.T, indexing="ij"), axis=-1).reshape(-1, 3)
        e = _Entry(_to_pyrender(mesh), item.mesh, corners, [])
        self._entries[item.key] = e
        return e

    def _set_camera(self, K: np.ndarray, T_cam_world: np.ndarray, znear: float, zfar: float) -> None:
        if self._osr is None:
            raise RuntimeError("renderer is closed")
        K = np.asarray(K, dtype=np.float64)
        T = np.asarray(T_cam_world, dtype=np.float64)
        if K.shape != (3, 3) or T.shape != (4, 4):
            raise ValueError(f"K must be (3, 3) and T_cam_world (4, 4), got {K.shape}, {T.shape}")
        if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise ValueError("K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
        if not 0 < znear < zfar:
            raise ValueError(f"need 0 < znear < zfar, got {znear}, {zfar}")
        c = self._camera
        c.fx, c.fy = K[0, 0], K[1, 1]
        c.cx, c.cy = K[0, 2] + 0.5, K[1, 2] + 0.5  # pyrender: pixel centres at half-integers
        c.znear, c.zfar = float(znear), float(zfar)
        self._scene.set_pose(self._cam_node, np.linalg.inv(T) @ _FLIP_YZ)

    def _place(self, items: Sequence[RenderItem]) -> list[pyrender.Node]:
        """Show exactly ``items`` (one posed node each) and hide every other cached mesh.

        Returns the node of each item, in order.
        """
        entries = [self._entry(it) for it in items]
        used: dict[int, int] = {}
        nodes = []
        for it, e in zip(items, entries):
            k = used.get(id(e), 0)
            used[id(e)] = k + 1
            T = np.array(it.T_world_obj, dtype=np.float64)
            if T.shape != (4, 4) or not np.linalg.det(T[:3, :3]) > 0:
                raise ValueError(f"T_world_obj of {it.key!r} must be (4, 4) without reflection")
            if k < len(e.nodes):
                self._scene.set_pose(e.nodes[k], T)
            else:
                e.nodes.append(self._scene.add(e.mesh, pose=T))
            nodes.append(e.nodes[k])
        self._draw_rank = {n: i for i, n in enumerate(nodes)}
        for e in self._entries.values():
            n = used.get(id(e), 0)
            e.mesh.is_visible = n > 0
            # keep one node per mesh in the scene: its GPU buffers live as long as one node does
            while len(e.nodes) > max(n, 1):
                self._scene.remove_node(e.nodes.pop())
        for key in [k for k, e in self._entries.items() if id(e) not in used]:
            if len(self._entries) <= self.max_meshes:
                break
            for node in self._entries.pop(key).nodes:  # no node left: _update_context frees it
                self._scene.remove_node(node)
        return nodes

    def _draw_order(self, scene: pyrender.Scene) -> list[pyrender.Node]:
        """The mesh nodes in the order pyrender draws them: opaque before transparent, far before near (pyrender's
        order), and the items' order where two nodes are equally far.

        Replaces pyrender's own sort, which leaves such ties in the order of a set of nodes, i.e. of their memory
        addresses: where two surfaces meet at equal depth (paper on a desk, a board on a table, both at the world
        origin), the pixel went to whichever node came first, so the image depended on what the process had
        allocated before.
        """
        cam = scene.get_pose(scene.main_camera_node)[:3, 3]
        last = len(self._draw_rank)
        return sorted(scene.mesh_nodes, key=lambda n: (bool(n.mesh.is_transparent),
                                                       -float(np.linalg.norm(scene.get_pose(n)[:3, 3] - cam)),
                                                       self._draw_rank.get(n, last)))

    def _set_lights(self, lights: Sequence[Light], ambient: float) -> None:
        bad = [li.kind for li in lights if li.kind not in self._lights]
        if bad:
            raise ValueError(f"unknown light kind(s) {bad}; use 'directional' or 'point'")
        self._scene.ambient_light = np.full(3, float(ambient))
        for kind, pool in self._lights.items():
            wanted = [li for li in lights if li.kind == kind]
            while len(pool) > len(wanted):
                self._scene.remove_node(pool.pop())
            for i, li in enumerate(wanted):
                if i == len(pool):
                    light = pyrender.DirectionalLight() if kind == "directional" else pyrender.PointLight()
                    node = _LightNode(rank=(100 if kind == "directional" else 1) + i, light=light, matrix=np.eye(4))
                    self._scene.add_node(node)
                    pool.append(node)
                pool[i].light.color = np.asarray(li.colour, dtype=np.float64)
                pool[i].light.intensity = float(li.intensity)
                self._scene.set_pose(pool[i], np.array(li.T_world_light, dtype=np.float64))

    def _pass(self, flags: int, seg_node_map=None):
        return self._osr.render(self._scene, flags=flags, seg_node_map=seg_node_map)

    # -- public API ----------------------------------------------------------------------------------

    def render(self, items: Sequence[RenderItem], K: np.ndarray, T_cam_world: np.ndarray,
               lights: Sequence[Light] = (), ambient: float = 0.3, znear: float = 0.05, zfar: float = 6.0,
               seg: bool = False) -> RenderOutput:
        """Render colour and depth (and instance seg) of ``items`` seen from ``T_cam_world``.

        K: (3, 3) OpenCV intrinsics, pixels. T_cam_world: (4, 4) world -> camera (OpenCV axes).
        lights: lights of the colour pass; ambient: ambient intensity (see the lighting note).
        znear, zfar: clip distances along the optical axis, metres.
        Returns RenderOutput(rgb (H, W, 3) uint8 (black where nothing), depth (H, W) float32 metres
        (0 = nothing), seg (H, W) int32 seg_id of the visible surface, or None if ``seg`` is False).
        """
        self._set_camera(K, T_cam_world, znear, zfar)
        nodes = self._place(items)
        self._set_lights(lights, ambient)
        rgb, depth = self._pass(pyrender.RenderFlags.NONE)
        seg_im = None
        if seg:
            cmap = {n: _seg_colour(int(it.seg_id)) for n, it in zip(nodes, items)}
            seg_im = _decode_seg(self._pass(pyrender.RenderFlags.SEG, cmap)[0])
        return RenderOutput(np.ascontiguousarray(rgb), np.ascontiguousarray(depth, dtype=np.float32), seg_im)

    def render_depth(self, items: Sequence[RenderItem], K: np.ndarray, T_cam_world: np.ndarray,
                     znear: float = 0.05, zfar: float = 6.0) -> np.ndarray:
        """Depth only: (H, W) float32 z in metres, 0 where nothing is hit. Arguments as in ``render``."""
        self._set_camera(K, T_cam_world, znear, zfar)
        self._place(items)
        return np.ascontiguousarray(self._pass(pyrender.RenderFlags.DEPTH_ONLY), dtype=np.float32)

    def full_masks(self, items: Sequence[RenderItem], K: np.ndarray, T_cam_world: np.ndarray,
                   znear: float = 0.05, zfar: float = 6.0) -> dict[int, np.ndarray]:
        """Unoccluded silhouette of every instance (seg_id > 0), as if it were alone in the scene.

        Arguments as in ``render``. Returns {seg_id: (H, W) bool} for every seg_id > 0 in ``items``
        (all False when out of view); items sharing a seg_id form one silhouette. Instances whose
        projected bounding boxes do not overlap cannot occlude each other, so they share a pass.
        """
        self._set_camera(K, T_cam_world, znear, zfar)
        nodes = self._place(items)
        by_id = _items_by_seg_id(items)
        boxes = {sid: self._pixel_box(items, idx, K, T_cam_world, znear) for sid, idx in by_id.items()}
        groups: list[list[int]] = []
        for sid in sorted(by_id):
            for g in groups:
                if not any(_boxes_overlap(boxes[sid], boxes[o]) for o in g):
                    g.append(sid)
                    break
            else:
                groups.append([sid])
        out = {}
        for g in groups:
            cmap = {nodes[i]: _seg_colour(sid) for sid in g for i in by_id[sid]}
            ids = _decode_seg(self._pass(pyrender.RenderFlags.SEG, cmap)[0])
            for sid in g:
                out[sid] = ids == sid
        return out

    def outside_silhouettes(self, items: Sequence[RenderItem], K: np.ndarray, T_cam_world: np.ndarray,
                            inside: dict[int, np.ndarray], znear: float = 0.05,
                            zfar: float = 6.0) -> dict[int, tuple[int, list[int]]]:
        """The parts of silhouettes beyond the image edge, as BOP's toolkit counts them (calc_gt_info renders
        on a canvas 3 x the image each way, the image in its middle).

        For every seg_id whose projected box leaves the image: (pixels of its silhouette outside the image,
        BOP box [x, y, w, h] of the whole silhouette in image coordinates, unclipped: x and y can be negative).
        The outside part is rendered as image-sized tiles around the image (only those the projected box
        reaches), with the same rasteriser as ``full_masks``, so the counts add up exactly. inside: {seg_id:
        (H, W) bool} the in-image silhouettes (``full_masks``). Other arguments as in ``render``.
        """
        W, H = self.width, self.height
        K = np.asarray(K, dtype=np.float64)
        out = {}
        for sid, idx in sorted(_items_by_seg_id(items).items()):
            box = self._pixel_box(items, idx, K, T_cam_world, znear)
            if box[0] >= 0 and box[1] >= 0 and box[2] <= W - 1 and box[3] <= H - 1:
                continue
            xs, ys, n_out = [], [], 0
            m = inside.get(sid)
            if m is not None and m.any():
                yy, xx = np.nonzero(m)
                xs += [xx.min(), xx.max()]
                ys += [yy.min(), yy.max()]
            for ty in (-1, 0, 1):
                for tx in (-1, 0, 1):
                    x0, y0 = tx * W, ty * H
                    if (tx == 0 and ty == 0) or box[2] < x0 or box[0] > x0 + W - 1 or box[3] < y0 \
                            or box[1] > y0 + H - 1:
                        continue
                    Kt = K.copy()
                    Kt[0, 2] -= x0
                    Kt[1, 2] -= y0
                    self._set_camera(Kt, T_cam_world, znear, zfar)
                    nodes = self._place([items[i] for i in idx])
                    tile = _decode_seg(self._pass(pyrender.RenderFlags.SEG,
                                                  {n: _seg_colour(sid) for n in nodes})[0]) == sid
                    if tile.any():
                        n_out += int(tile.sum())
                        yy, xx = np.nonzero(tile)
                        xs += [xx.min() + x0, xx.max() + x0]
                        ys += [yy.min() + y0, yy.max() + y0]
            bbox = [int(min(xs)), int(min(ys)), int(max(xs) - min(xs) + 1), int(max(ys) - min(ys) + 1)] if xs \
                else [-1, -1, -1, -1]
            out[sid] = (n_out, bbox)
        return out

    def _pixel_box(self, items, idx, K, T_cam_world, znear) -> np.ndarray:
        """(4,) [u0, v0, u1, v1] enclosing the projected bounding boxes of ``items[idx]``, pixels."""
        K = np.asarray(K, dtype=np.float64)
        T_cw = np.asarray(T_cam_world, dtype=np.float64)
        pts = []
        for i in idx:
            T = T_cw @ np.asarray(items[i].T_world_obj, dtype=np.float64)
            c = self._entries[items[i].key].corners @ T[:3, :3].T + T[:3, 3]
            if np.any(c[:, 2] <= znear):  # crosses the near plane: assume it can cover everything
                return np.array([-np.inf, -np.inf, np.inf, np.inf])
            pts.append(c)
        p = np.concatenate(pts) @ K.T
        uv = p[:, :2] / p[:, 2:3]
        return np.r_[uv.min(axis=0) - 1.0, uv.max(axis=0) + 1.0]

    def reset(self) -> None:
        """Drop every cached mesh and its nodes, so the next frames render as in a new process (a capture's bytes
        must not depend on what the process rendered before it)."""
        for e in self._entries.values():
            for node in e.nodes:
                self._scene.remove_node(node)
        self._entries.clear()
        self._draw_rank = {}

    def close(self) -> None:
        """Free the OpenGL context and the cached meshes; the renderer cannot be used afterwards."""
        for k in [k for k, r in _RENDERERS.items() if r is self]:
            del _RENDERERS[k]
        if self._osr is not None:
            self._osr.delete()
            self._osr = None
        self._entries.clear()
        self._draw_rank = {}


_RENDERERS: dict[tuple, Renderer] = {}
_FORKED: list[Renderer] = []  # inherited through fork: their contexts are unusable; never touched


@atexit.register
def _close_all() -> None:
    """Free this process's contexts before interpreter shutdown (else PyOpenGL prints noise then)."""
    pid = os.getpid()
    for k, r in list(_RENDERERS.items()):
        if k[0] == pid:
            try:
                r.close()
            except Exception:  # shutting down: nothing useful to report
                pass


def _items_by_seg_id(items: Sequence[RenderItem]) -> dict[int, list[int]]:
    """{seg_id: indices into ``items``} of the items with seg_id > 0 (an instance may be several items)."""
    by_id: dict[int, list[int]] = {}
    for i, it in enumerate(items):
        if int(it.seg_id) > 0:
            by_id.setdefault(int(it.seg_id), []).append(i)
    return by_id


def get_renderer(width: int, height: int, max_faces: int | None = None) -> Renderer:
    """The process's renderer for ``width`` x ``height`` images (created on first use, then reused).

    max_faces: see ``Renderer``; renderers with different settings are kept apart.
    """
    pid = os.getpid()
    for k in [k for k in _RENDERERS if k[0] != pid]:
        _FORKED.append(_RENDERERS.pop(k))
    key = (pid, int(width), int(height), max_faces)
    if key not in _RENDERERS:
        _RENDERERS[key] = Renderer(width, height, max_faces=max_faces)
    return _RENDERERS[key]
