"""Tests for argen.sim.render: OpenCV camera convention, exact depth, seg and silhouettes, textures,
determinism and the reuse of one renderer (and its uploaded meshes) across frames."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from argen.sim.render import (
    Light,
    Renderer,
    RenderItem,
    _consistent_winding,
    _crease_split,
    get_renderer,
    textured_plane,
)

W, H = 160, 120
K = np.array([[200.0, 0.0, 79.3], [0.0, 210.0, 61.7], [0.0, 0.0, 1.0]])


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_cam_world of an OpenCV camera at ``eye`` looking at ``target`` (image up ~ ``up``)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z])
    T[:3, 3] = -T[:3, :3] @ eye
    return T


def pose(rotvec=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = trimesh.transformations.rotation_matrix(np.linalg.norm(rotvec), rotvec if np.any(rotvec) else
                                                        (0, 0, 1))[:3, :3]
    T[:3, 3] = t
    return T


def coloured_box(extents, rgb=(200, 120, 40)) -> trimesh.Trimesh:
    m = trimesh.creation.box(extents=extents)
    m.visual = trimesh.visual.ColorVisuals(m, vertex_colors=np.tile([*rgb, 255], (len(m.vertices), 1)))
    return m


def pixel_rays(K_, T_cam_world, h=H, w=W):
    """World-frame origin (3,) and (h, w, 3) directions with camera-z component 1 (so t = depth)."""
    v, u = np.mgrid[0:h, 0:w]
    d_cam = np.stack([u, v, np.ones_like(u)], axis=-1).astype(float) @ np.linalg.inv(K_).T
    R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
    return -R.T @ t, d_cam @ R


def box_depth(extents, T_world_box, K_, T_cam_world, h=H, w=W) -> np.ndarray:
    """Analytic depth (h, w) of a box through every pixel centre; nan where the ray misses it."""
    o, d = pixel_rays(K_, T_cam_world, h, w)
    Ti = np.linalg.inv(T_world_box)
    o_b = Ti[:3, :3] @ o + Ti[:3, 3]
    d_b = d @ Ti[:3, :3].T
    half = np.asarray(extents) / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - o_b) / d_b, (half - o_b) / d_b
    t_near = np.minimum(t1, t2).max(axis=-1)
    t_far = np.maximum(t1, t2).min(axis=-1)
    return np.where((t_near <= t_far) & (t_near > 0), t_near, np.nan)


def box_sdf(points, extents, T_world_box) -> np.ndarray:
    """Signed distance (N,) of world points to a box surface, metres."""
    Ti = np.linalg.inv(T_world_box)
    q = np.abs(points @ Ti[:3, :3].T + Ti[:3, 3]) - np.asarray(extents) / 2
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


def backproject(depth, K_, T_cam_world) -> np.ndarray:
    """World points (N, 3) of the pixels with depth > 0."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    p_cam = np.stack([(u - K_[0, 2]) * z / K_[0, 0], (v - K_[1, 2]) * z / K_[1, 1], z], axis=1)
    Ti = np.linalg.inv(T_cam_world)
    return p_cam @ Ti[:3, :3].T + Ti[:3, 3]


@pytest.fixture(scope="module")
def renderer() -> Renderer:
    return get_renderer(W, H)


EXT = (0.2, 0.12, 0.08)
T_BOX = pose((0.3, -0.5, 0.9), (0.02, -0.01, 0.0))
T_CAM = look_at((0.35, -0.5, 0.45), (0.0, 0.0, 0.0))


def test_box_depth_and_projection_follow_K_opencv(renderer):
    depth = renderer.render_depth([RenderItem("box", coloured_box(EXT), T_BOX, 1)], K, T_CAM)
    assert depth.shape == (H, W) and depth.dtype == np.float32
    z = box_depth(EXT, T_BOX, K, T_CAM)
    hit, true_hit = depth > 0, ~np.isnan(z)
    both = hit & true_hit
    assert both.sum() > 1500
    # depth at every pixel centre equals the ray/box intersection (a half-pixel shift would be mm off)
    assert np.abs(depth[both] - z[both]).max() < 1e-4
    assert (hit ^ true_hit).sum() <= 0.01 * true_hit.sum()  # only pixel centres on the very outline
    assert np.all(depth[~hit] == 0)
    # the silhouette's extent is where K puts the projected corners
    corners = np.stack(np.meshgrid(*[(-e / 2, e / 2) for e in EXT], indexing="ij"), -1).reshape(-1, 3)
    p = (corners @ T_BOX[:3, :3].T + T_BOX[:3, 3]) @ T_CAM[:3, :3].T + T_CAM[:3, 3]
    uv = (p @ K.T)[:, :2] / p[:, 2:3]
    v, u = np.nonzero(hit)
    lo, hi = np.array([u.min(), v.min()]), np.array([u.max(), v.max()])
    assert np.all(lo >= uv.min(axis=0)) and np.all(lo <= uv.min(axis=0) + 2)  # corners are thin wedges
    assert np.all(hi <= uv.max(axis=0)) and np.all(hi >= uv.max(axis=0) - 2)


def test_backprojected_depth_lies_on_the_surface(renderer):
    items = [RenderItem("box", coloured_box(EXT), T_BOX, 1)]
    out = renderer.render(items, K, T_CAM, seg=True)
    pts = backproject(out.depth, K, T_CAM)
    assert len(pts) > 1500
    assert np.abs(box_sdf(pts, EXT, T_BOX)).max() < 1e-3
    assert np.array_equal(out.seg > 0, out.depth > 0)


def test_linemod_depth_matches_ray_casting(lm_models):
    o3d = pytest.importorskip("open3d")
    mesh = trimesh.load(lm_models / "obj_000005.ply")  # has a few flipped faces
    mesh.apply_scale(0.001)
    w, h = 240, 180
    K2 = np.array([[300.0, 0.0, 121.1], [0.0, 300.0, 88.6], [0.0, 0.0, 1.0]])
    T_cam = look_at((0.25, -0.35, 0.3), (0.0, 0.0, 0.09))
    depth = get_renderer(w, h).render_depth([RenderItem("lm5", mesh, np.eye(4), 1)], K2, T_cam)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    o, d = pixel_rays(K2, T_cam, h, w)
    rays = np.concatenate([np.broadcast_to(o, d.shape), d], axis=-1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    true_hit, hit = np.isfinite(t), depth > 0
    both = hit & true_hit
    assert both.sum() > 3000
    err = np.abs(depth[both] - t[both])
    assert np.quantile(err, 0.999) < 1e-5 and err.max() < 1e-3  # a grazing pixel may differ a little
    assert (hit ^ true_hit).sum() <= 0.01 * true_hit.sum()  # no holes, only outline pixels differ
    dist = scene.compute_distance(o3d.core.Tensor(backproject(depth, K2, T_cam).astype(np.float32))).numpy()
    assert dist.max() < 1e-3


def test_seg_front_object_wins_and_full_mask_covers_the_occluded_one(renderer):
    T_cam = look_at((0.0, -0.6, 0.3), (0.0, 0.0, 0.05))
    back, front = 70000, 1  # 70000 needs all three bytes of the seg colour
    items = [
        RenderItem("plane", textured_plane(0.8, np.full((4, 4, 3), 90, np.uint8)), np.eye(4), 0),
        RenderItem("box", coloured_box(EXT), pose((0, 0, 0.4), (0.0, 0.1, 0.04)), back),
        RenderItem("small", coloured_box((0.06, 0.06, 0.06)), pose((0, 0, 0.2), (0.03, -0.05, 0.05)), front),
    ]
    out = renderer.render(items, K, T_cam, seg=True)
    full = renderer.full_masks(items, K, T_cam)
    assert set(np.unique(out.seg)) == {0, front, back}
    assert set(full) == {front, back}
    overlap = full[front] & full[back]
    assert overlap.sum() > 50
    assert np.all(out.seg[overlap] == front)
    assert np.array_equal(full[front], out.seg == front)
    assert np.all(full[back][out.seg == back]) and full[back].sum() > (out.seg == back).sum() + 50
    # the occluder's depth is in front of the occluded box there
    z_back = box_depth(EXT, items[1].T_world_obj, K, T_cam)
    assert np.all(out.depth[overlap] < z_back[overlap])


def test_full_masks_sharing_a_pass_equal_single_renders(renderer):
    T_cam = look_at((0.0, -0.5, 0.5), (0.0, 0.0, 0.0))
    items = [RenderItem("box", coloured_box(EXT), pose((0, 0, a), (x, y, 0.04)), i + 1)
             for i, (a, x, y) in enumerate([(0.1, -0.22, 0.0), (0.7, 0.22, 0.05), (1.2, 0.2, -0.05)])]
    items.append(RenderItem("plane", textured_plane(0.9, np.zeros((2, 2, 3), np.uint8)), np.eye(4), 0))
    full = renderer.full_masks(items, K, T_cam)
    for it in items[:3]:
        alone = renderer.render_depth([it], K, T_cam) > 0
        assert alone.sum() > 100
        assert np.array_equal(full[it.seg_id], alone)


def test_textured_plane_seen_from_above_is_upright(renderer):
    img = np.zeros((64, 64, 3), np.uint8)
    img[:32, :32] = (255, 0, 0)  # top-left red
    img[:32, 32:] = (0, 255, 0)
    img[32:, :32] = (0, 0, 255)
    img[32:, 32:] = (255, 255, 255)
    # camera on +z looking down: x right, y (image down) = world -y, z = world -z
    T_cam = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1.0], [0, 0, 0, 1]])
    K_c = np.array([[200.0, 0, 79.5], [0, 200, 59.5], [0, 0, 1]])
    out = renderer.render([RenderItem(("tex", 0), textured_plane(0.4, img, 0.01), np.eye(4), 0)], K_c, T_cam,
                          ambient=1.0)
    c = out.rgb.astype(int)
    assert np.all(c[40, 60] > (200, -1, -1)) and np.all(c[40, 60, 1:] < 30)  # top-left: red
    assert np.all(c[40, 100, [0, 2]] < 30) and c[40, 100, 1] > 200  # top-right: green
    assert np.all(c[80, 60, :2] < 30) and c[80, 60, 2] > 200  # bottom-left: blue
    assert np.all(c[80, 100] > 200)  # bottom-right: white
    assert abs(out.depth[60, 80] - 1.0) < 1e-4
    assert out.depth[5, 5] == 0 and np.all(out.rgb[5, 5] == 0)  # nothing hit: zeros


def test_textured_plane_geometry_and_uv_convention():
    m = textured_plane(0.5, np.zeros((8, 8, 3), np.uint8), thickness=0.02)
    assert np.allclose(m.bounds, [[-0.25, -0.25, -0.02], [0.25, 0.25, 0.0]])
    top = np.abs(m.vertices[:, 2]) < 1e-12
    assert np.allclose(m.visual.uv[top], (m.vertices[top, :2] + 0.25) / 0.5)
    flat = textured_plane(0.5, np.zeros((8, 8, 3), np.uint8))
    assert np.allclose(flat.face_normals, [0, 0, 1])


def test_lambert_lighting_is_calibrated(renderer):
    plane = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]],
                            vertex_colors=np.full((4, 4), 255, np.uint8), process=False)
    T_cam = np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1.0], [0, 0, 0, 1]])
    items = [RenderItem("white", plane, np.eye(4), 0)]
    dim = renderer.render(items, K, T_cam, ambient=0.25).rgb
    assert np.all(np.abs(dim.astype(int) - round(255 * 0.25 ** (1 / 2.2))) <= 1)
    down = Light("directional", np.pi * 0.75, np.ones(3), np.eye(4))  # shines along -z onto the plane
    lit = renderer.render(items, K, T_cam, lights=[down], ambient=0.25).rgb
    assert np.all(lit >= 254)


def test_repeated_renders_are_bit_identical(renderer):
    a = [RenderItem("box", coloured_box(EXT), T_BOX, 3)]
    b = [RenderItem("small", coloured_box((0.06, 0.06, 0.06)), np.eye(4), 1)]
    lights = [Light("point", 2.0, np.ones(3), pose(t=(0.2, -0.3, 1.0)))]
    first = renderer.render(a, K, T_CAM, lights=lights, seg=True)
    renderer.render(b, K, T_CAM, seg=True)
    again = renderer.render(a, K, T_CAM, lights=lights, seg=True)
    assert first.rgb.any()
    for x, y in [(first.rgb, again.rgb), (first.depth, again.depth), (first.seg, again.seg)]:
        assert np.array_equal(x, y)


def test_surfaces_at_equal_depth_go_to_the_item_listed_first(renderer):
    """Two equal slabs at one pose (a paper on a desk, a board on a table) tie in depth at every pixel: the item
    listed first is drawn, in colour and seg alike, whatever the renderer cached before (pyrender alone leaves the
    tie to the order of a set of nodes, i.e. to their memory addresses)."""
    red, blue = coloured_box((0.3, 0.3, 0.01), (220, 20, 20)), coloured_box((0.3, 0.3, 0.01), (20, 20, 220))
    for fill in range(4):  # other cached meshes change where nodes sit in pyrender's set
        for j in range(3 * fill):
            renderer.render([RenderItem(("fill", fill, j), coloured_box((0.02, 0.02, 0.02)), pose(t=(1, 1, 1)), 1)],
                            K, T_CAM)
        for order, want_rgb, want_seg in (((0, 1), 0, 1), ((1, 0), 2, 2)):
            items = [RenderItem("red", red, np.eye(4), 1), RenderItem("blue", blue, np.eye(4), 2)]
            out = renderer.render([items[i] for i in order], K, T_CAM, seg=True)
            hit = out.seg > 0
            assert hit.sum() > 1000
            assert (out.seg[hit] == want_seg).all(), (fill, order)
            assert (out.rgb[hit].argmax(axis=1) == want_rgb).all(), (fill, order)


def test_renderer_and_uploaded_meshes_are_reused(renderer):
    assert get_renderer(W, H) is renderer
    assert get_renderer(W + 2, H) is not renderer
    box = coloured_box(EXT)
    items = [RenderItem("reuse", box, T_BOX, 1), RenderItem("reuse", box, pose(t=(0, 0, 0.1)), 2)]
    renderer.render(items, K, T_CAM, seg=True)
    prim = renderer._entries["reuse"].mesh.primitives[0]
    vao = prim._vaid
    programs = len(renderer._osr._renderer._program_cache._program_cache)
    renderer.render([RenderItem("other", coloured_box((0.05, 0.05, 0.05)), np.eye(4), 1)], K, T_CAM, seg=True)
    out = renderer.render(items, K, T_CAM, seg=True)
    assert vao is not None and prim._vaid == vao  # not re-uploaded after being hidden
    assert len(renderer._osr._renderer._program_cache._program_cache) == programs  # no recompiles
    assert set(np.unique(out.seg)) == {0, 1, 2}  # two instances of one cached mesh


def test_bad_inputs_raise(renderer):
    box = coloured_box(EXT)
    with pytest.raises(ValueError):
        renderer.render_depth([RenderItem("box", box, T_BOX)], np.array([[200, 1, 80], [0, 200, 60], [0, 0, 1.0]]),
                              T_CAM)
    with pytest.raises(ValueError):
        renderer.render_depth([RenderItem("mirror", box, np.diag([1, 1, -1, 1.0]))], K, T_CAM)
    with pytest.raises(ValueError):
        renderer.render_depth([RenderItem("box", coloured_box((0.01, 0.01, 0.01)).subdivide(), T_BOX)], K, T_CAM)


def test_crease_split_keeps_box_edges_sharp_and_spheres_smooth():
    box = trimesh.creation.box()
    src, normals, faces = _crease_split(box.vertices, box.faces)
    assert len(src) == 24 and np.allclose(np.abs(normals).max(axis=1), 1.0)
    sphere = trimesh.creation.icosphere(subdivisions=2)
    src, normals, faces = _crease_split(sphere.vertices, sphere.faces)
    assert len(src) == len(sphere.vertices)
    assert np.all(np.einsum("ij,ij->i", normals, sphere.vertices[src]) > 0.99)
    assert np.array_equal(src[faces], sphere.faces)


def test_consistent_winding_repairs_flipped_faces(renderer):
    rng = np.random.default_rng(0)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    flipped = sphere.faces.copy()
    sel = rng.random(len(flipped)) < 0.3
    flipped[sel] = flipped[sel][:, ::-1]
    fixed = _consistent_winding(sphere.vertices, flipped)
    assert np.allclose(np.cross(*(sphere.vertices[fixed][:, 1:] - sphere.vertices[fixed][:, :1]).transpose(1, 0, 2)),
                       np.cross(*(sphere.vertices[sphere.faces][:, 1:]
                                  - sphere.vertices[sphere.faces][:, :1]).transpose(1, 0, 2)))
    inside_out = _consistent_winding(sphere.vertices, sphere.faces[:, ::-1])
    assert trimesh.Trimesh(sphere.vertices, inside_out, process=False).volume > 0
    # rendered, the broken sphere has no holes
    T_cam = look_at((0.3, -0.3, 0.2), (0, 0, 0))
    good = renderer.render_depth([RenderItem("sphere", sphere, np.eye(4), 1)], K, T_cam)
    bad = renderer.render_depth([RenderItem("broken", trimesh.Trimesh(sphere.vertices, flipped, process=False),
                                            np.eye(4), 1)], K, T_cam)
    assert np.array_equal(good, bad)


def test_max_faces_decimates_with_small_error():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)  # 5120 faces
    T_cam = look_at((0.3, -0.3, 0.2), (0, 0, 0))
    r = get_renderer(W, H, max_faces=800)
    assert r is not get_renderer(W, H)
    depth = r.render_depth([RenderItem("sphere", sphere, np.eye(4), 1)], K, T_cam)
    assert len(r._entries["sphere"].mesh.primitives[0].indices) <= 800
    radius = np.linalg.norm(backproject(depth, K, T_cam), axis=1)
    assert (depth > 0).sum() > 1500 and np.abs(radius - 0.1).max() < 2e-3


def test_silhouettes_cut_by_the_image_edge_count_whole_like_a_3x_canvas(renderer):
    """outside_silhouettes (tiles around the image) equals rendering on BOP calc_gt_info's 3x canvas."""
    T_cam = look_at((0.0, -0.5, 0.5), (0.0, 0.0, 0.0))
    items = [RenderItem("box", coloured_box(EXT), pose((0, 0, a), (x, y, 0.04)), i + 1)
             for i, (a, x, y) in enumerate([(0.3, -0.33, 0.1), (0.7, 0.02, 0.0), (1.2, 0.3, -0.25)])]
    full = renderer.full_masks(items, K, T_cam)
    beyond = renderer.outside_silhouettes(items, K, T_cam, full)
    big = Renderer(3 * W, 3 * H)
    try:
        K3 = K.copy()
        K3[0, 2] += W
        K3[1, 2] += H
        canvas = big.full_masks(items, K3, T_cam)
    finally:
        big.close()
    assert 2 in full and 2 not in beyond  # the middle box is wholly in view: nothing to add
    assert {1, 3} <= set(beyond)  # the others leave the image
    for sid in (1, 3):
        whole = canvas[sid]
        assert np.array_equal(whole[H:2 * H, W:2 * W], full[sid])  # the same rasteriser in the image
        n_out, bbox = beyond[sid]
        assert n_out > 100 and n_out + full[sid].sum() == whole.sum()
        ys, xs = np.nonzero(whole)
        assert bbox == [xs.min() - W, ys.min() - H, xs.max() - xs.min() + 1, ys.max() - ys.min() + 1]
        assert bbox[0] < 0 or bbox[1] < 0 or bbox[0] + bbox[2] > W or bbox[1] + bbox[3] > H
