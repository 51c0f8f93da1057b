"""Raster passes on Blender's GPU (llvmpipe headless): every check reads pixels back.

Expected values come from an independent numpy ray caster over the same triangles and camera
matrices (pixel centres, rows bottom-up like the read-back), and from the pass formulas written
out in numpy. Images are tiny (64x48) to keep the file fast on two shared cores.
"""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core.snapshot import Material, concat_geometry, geometry_from_arrays, make_snapshot

pytestmark = pytest.mark.blender

W, H = 64, 48
F = 4  # downsample factor: 16x12 low res


# ----------------------------------------------------------------------------------------------
# numpy reference: cameras, rays, scenes
# ----------------------------------------------------------------------------------------------
def perspective(fov_y_deg: float, near: float = 0.1, far: float = 100.0) -> np.ndarray:
    t = np.tan(np.radians(fov_y_deg) / 2)
    a = W / H
    return np.array([[1 / (t * a), 0, 0, 0], [0, 1 / t, 0, 0],
                     [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)], [0, 0, -1, 0]])


def orthographic(half_height: float, near: float = 0.1, far: float = 100.0) -> np.ndarray:
    half_width = half_height * W / H
    return np.array([[1 / half_width, 0, 0, 0], [0, 1 / half_height, 0, 0],
                     [0, 0, -2 / (far - near), -(far + near) / (far - near)], [0, 0, 0, 1]])


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    rot = np.stack([r, u, -f])
    view = np.eye(4)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ eye
    return view


def pixel_rays(view, proj, w=W, h=H):
    """Rays through pixel centres: origins, unit directions (h, w, 3), row 0 = bottom."""
    inv = np.linalg.inv(np.asarray(proj, np.float64) @ np.asarray(view, np.float64))
    x = (np.arange(w) + 0.5) / w * 2 - 1
    y = (np.arange(h) + 0.5) / h * 2 - 1
    xx, yy = np.meshgrid(x, y)
    ones = np.ones_like(xx)

    def unproject(z):
        p = np.stack([xx, yy, z * ones, ones], -1) @ inv.T
        return p[..., :3] / p[..., 3:]

    near, far = unproject(-1.0), unproject(1.0)
    d = far - near
    return near, d / np.linalg.norm(d, axis=-1, keepdims=True)


def raycast(origins, dirs, tri_pos):
    """Nearest hit per ray. tri_pos (T, 3, 3). Returns t (h, w) inf on miss, tri (h, w) -1, u, v."""
    o = origins.reshape(-1, 1, 3)
    d = dirs.reshape(-1, 1, 3)
    p0, e1, e2 = tri_pos[:, 0], tri_pos[:, 1] - tri_pos[:, 0], tri_pos[:, 2] - tri_pos[:, 0]
    pv = np.cross(d, e2)
    det = np.einsum("ntk,tk->nt", pv, e1)
    inv_det = 1.0 / np.where(np.abs(det) < 1e-12, np.nan, det)
    tv = o - p0
    u = np.einsum("ntk,ntk->nt", tv, pv) * inv_det
    qv = np.cross(tv, e1)
    v = np.einsum("ntk,ntk->nt", d, qv) * inv_det
    t = np.einsum("tk,ntk->nt", e2, qv) * inv_det
    ok = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)
    t = np.where(ok, t, np.inf)
    idx = np.argmin(t, axis=1)
    rows = np.arange(t.shape[0])
    hit_t = t[rows, idx]
    miss = ~np.isfinite(hit_t)
    shape = origins.shape[:2]
    return (hit_t.reshape(shape), np.where(miss, -1, idx).reshape(shape),
            u[rows, idx].reshape(shape), v[rows, idx].reshape(shape))


def interior(labels, margin=1):
    """Pixels whose (2 margin + 1)^2 neighbourhood carries the same label (no edges nearby)."""
    ok = np.ones(labels.shape, bool)
    for dy in range(-margin, margin + 1):
        for dx in range(-margin, margin + 1):
            shifted = np.full(labels.shape, -2, labels.dtype)
            ys = slice(max(dy, 0), labels.shape[0] + min(dy, 0))
            yd = slice(max(-dy, 0), labels.shape[0] + min(-dy, 0))
            xs = slice(max(dx, 0), labels.shape[1] + min(dx, 0))
            xd = slice(max(-dx, 0), labels.shape[1] + min(-dx, 0))
            shifted[yd, xd] = labels[ys, xs]
            ok &= shifted == labels
    return ok


def quad(corner, edge_u, edge_v, uv=None, material=0):
    """Two triangles spanning corner + [0,1] edge_u + [0,1] edge_v (normal = edge_u x edge_v)."""
    c, a, b = (np.asarray(x, np.float32) for x in (corner, edge_u, edge_v))
    pos = np.stack([c, c + a, c + a + b, c + b])
    uvs = None if uv is None else np.asarray(uv, np.float32)
    return geometry_from_arrays(pos, [[0, 1, 2], [0, 2, 3]], material_index=material, uvs=uvs)


def box(lo, hi, material_of_axis=(0, 1, 2)):
    """Closed axis-aligned box, outward normals; faces of axis k use material_of_axis[k]."""
    lo, hi = np.asarray(lo, np.float32), np.asarray(hi, np.float32)
    s = hi - lo
    ex, ey, ez = np.diag(s)
    m = material_of_axis
    return concat_geometry([
        quad(lo, ey, ex, material=m[2]), quad(lo + ez, ex, ey, material=m[2]),
        quad(lo, ez, ey, material=m[0]), quad(lo + ex, ey, ez, material=m[0]),
        quad(lo, ex, ez, material=m[1]), quad(lo + ey, ez, ex, material=m[1]),
    ])


def expected_gbuffer(snapshot, view, proj):
    """Ray-cast reference: dict of albedo (untextured), normal, position, depth, tri, hit."""
    g = snapshot.geometry
    tri_pos = g.positions[g.triangles].astype(np.float64)
    o, d = pixel_rays(view, proj)
    t, tri, u, v = raycast(o, d, tri_pos)
    hit = tri >= 0
    pos = o + d * np.where(hit, t, 0)[..., None]
    fn = g.face_normals()[np.maximum(tri, 0)].astype(np.float64)
    fn = np.where((np.einsum("hwk,hwk->hw", fn, d) > 0)[..., None], -fn, fn)
    depth = -(pos @ np.asarray(view)[2, :3] + np.asarray(view)[2, 3])
    mat = g.material_index[np.maximum(tri, 0)]
    albedo = np.stack([snapshot.materials[m].base_color for m in range(len(snapshot.materials))])[mat]
    return {"hit": hit, "tri": tri, "u": u, "v": v, "position": pos, "normal": fn, "depth": depth,
            "albedo": albedo, "material": np.where(hit, mat, -1)}


def bilinear_repeat(tex, uv):
    """Cycles' Linear + REPEAT image lookup: tex (h, w, 3), row 0 at v = 0; uv (..., 2)."""
    th, tw = tex.shape[:2]
    s = uv[..., 0] * tw - 0.5
    t = uv[..., 1] * th - 0.5
    x0, y0 = np.floor(s).astype(int), np.floor(t).astype(int)
    fx, fy = (s - x0)[..., None], (t - y0)[..., None]

    def at(x, y):
        return tex[np.mod(y, th), np.mod(x, tw)]

    return ((at(x0, y0) * (1 - fx) + at(x0 + 1, y0) * fx) * (1 - fy)
            + (at(x0, y0 + 1) * (1 - fx) + at(x0 + 1, y0 + 1) * fx) * fy)


# ----------------------------------------------------------------------------------------------
# fixtures: one instance per pass type (shaders compile once per module)
# ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def raster(gpu_context):
    from hybridgi_core.raster.bilateral import BilateralPass, BilateralVerticalPass
    from hybridgi_core.raster.deferred import DeferredPass
    from hybridgi_core.raster.downsample import DownsamplePass
    from hybridgi_core.raster.gbuffer import GBufferPass
    from hybridgi_core.raster.settings import RasterSettings
    from hybridgi_core.raster.ssao import SSAOPass

    settings = RasterSettings(downsample=F, ssao_radius=0.5, ssao_samples=16)
    passes = {
        "gbuffer": GBufferPass(), "downsample": DownsamplePass(F), "ssao": SSAOPass(settings),
        "bilateral": BilateralPass(settings), "vertical": BilateralVerticalPass(settings),
        "deferred": DeferredPass(settings),
    }
    for p in passes.values():
        p.create()
    passes["gbuffer"].resize(W, H)
    passes["downsample"].resize(W, H)
    passes["ssao"].resize(W // F, H // F)
    passes["bilateral"].resize(W, H)
    passes["vertical"].resize(W, H)
    passes["deferred"].resize(W, H)
    yield passes
    for p in passes.values():
        p.free()


def render_gbuffer(raster, snapshot, view, proj):
    gb = raster["gbuffer"]
    gb.upload(snapshot)
    out = gb.execute(view, proj)
    return out, {n: gb.read(n) for n in ("albedo", "normal", "position", "emission", "depth")}


# ----------------------------------------------------------------------------------------------
# G-buffer
# ----------------------------------------------------------------------------------------------
def check_against_reference(got, ref):
    hit = ref["hit"]
    assert np.array_equal(got["position"][..., 3] > 0.5, hit) or \
        np.mean((got["position"][..., 3] > 0.5) != hit) < 0.01, "coverage differs from the ray cast"
    inner = interior(np.where(hit, ref["tri"] // 2, -1)) & hit
    assert inner.sum() > 200
    np.testing.assert_allclose(got["position"][..., :3][inner], ref["position"][inner], atol=2e-4)
    np.testing.assert_allclose(got["depth"][..., 0][inner], ref["depth"][inner], rtol=2e-5)
    np.testing.assert_allclose(got["normal"][..., :3][inner], ref["normal"][inner], atol=2e-3)
    np.testing.assert_allclose(got["albedo"][..., :3][inner], ref["albedo"][inner], atol=1e-3)
    bg = interior(np.where(hit, 0, -1)) & ~hit
    assert bg.sum() > 20
    assert np.all(got["position"][bg] == 0) and np.all(got["albedo"][bg] == 0)
    assert np.all(got["depth"][bg][:, 0] == 1e10)


def box_snapshot():
    mats = [Material(base_color=np.array(c, np.float32)) for c in
            ((0.8, 0.1, 0.1), (0.1, 0.7, 0.2), (0.2, 0.3, 0.9))]
    geo = box((-0.6, -0.4, 0.0), (0.5, 0.7, 0.9))
    return make_snapshot(geo, mats)


def test_gbuffer_box_perspective_matches_ray_cast(raster):
    snap = box_snapshot()
    view = look_at((2.5, -3.0, 2.2), (0.0, 0.1, 0.4))
    proj = perspective(40.0)
    _, got = render_gbuffer(raster, snap, view, proj)
    ref = expected_gbuffer(snap, view, proj)
    check_against_reference(got, ref)
    # Three faces are visible, each with its material's colour and outward normal.
    assert set(np.unique(ref["material"][ref["hit"]])) == {0, 1, 2}
    # Depth is the view-axis distance, not the ray length (they differ off-centre).
    inner = interior(np.where(ref["hit"], ref["tri"] // 2, -1)) & ref["hit"]
    ray_len = np.linalg.norm(ref["position"] - np.linalg.inv(view)[:3, 3], axis=-1)
    assert np.max(np.abs(ray_len - got["depth"][..., 0])[inner]) > 0.05


def test_gbuffer_orthographic_back_face_normal_faces_camera(raster):
    # Quad tilted about x, normal (0, -sin, cos) pointing away from the camera below it.
    tilt = np.radians(30)
    geo = quad((-1.5, -1.0, 0.0), (3.0, 0.0, 0.0), (0.0, 2.0 * np.cos(tilt), 2.0 * np.sin(tilt)))
    mat = Material(base_color=np.array([0.3, 0.5, 0.7], np.float32),
                   emission=np.array([2.0, 0.5, 0.0], np.float32))
    snap = make_snapshot(geo, [mat])
    view = look_at((0.3, 0.2, -4.0), (0.3, 0.2, 0.0), up=(0.0, 1.0, 0.0))
    proj = orthographic(1.2)
    _, got = render_gbuffer(raster, snap, view, proj)
    ref = expected_gbuffer(snap, view, proj)
    check_against_reference(got, ref)
    inner = interior(np.where(ref["hit"], 0, -1)) & ref["hit"]
    # The geometric normal points up (+z side); seen from below it is flipped towards -z.
    assert np.all(got["normal"][inner][:, 2] < -0.8)
    np.testing.assert_allclose(got["emission"][inner][:, :3], np.broadcast_to([2.0, 0.5, 0.0], (inner.sum(), 3)),
                               atol=1e-3)
    # Orthographic: depth varies linearly along the tilted plane, equal to the ray distance here.
    o, _d = pixel_rays(view, proj)
    np.testing.assert_allclose(got["depth"][..., 0][inner],
                               np.linalg.norm(ref["position"] - o, axis=-1)[inner] + 0.1, rtol=1e-4)


def test_gbuffer_texture_reaches_albedo_and_nan_uvs_fall_back(raster):
    rng = np.random.default_rng(3)
    tex = rng.uniform(0.05, 1.0, (4, 5, 3)).astype(np.float32)
    base = np.array([0.5, 1.0, 0.8], np.float32)
    textured = Material(base_color=base, texture=tex)
    # Left quad: UVs from -0.4 to 1.7 (REPEAT wrap); right quad: no UVs (NaN) -> mean albedo.
    uv = [[-0.4, -0.3], [1.7, -0.3], [1.7, 1.2], [-0.4, 1.2]]
    left = quad((-2.0, -1.0, 0.0), (1.9, 0.0, 0.0), (0.0, 2.0, 0.0), uv=uv)
    right = quad((0.1, -1.0, 0.0), (1.9, 0.0, 0.0), (0.0, 2.0, 0.0))
    snap = make_snapshot(concat_geometry([left, right]), [textured])
    view = look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    proj = perspective(30.0)
    _, got = render_gbuffer(raster, snap, view, proj)
    ref = expected_gbuffer(snap, view, proj)
    inner = interior(np.where(ref["hit"], ref["tri"] // 2, -1)) & ref["hit"]
    # Barycentric UVs of the reference hit (triangle corners follow quad()'s corner order).
    g = snap.geometry
    tri_uv = g.uvs[g.triangles[np.maximum(ref["tri"], 0)]]
    uvs = (tri_uv[..., 0, :] * (1 - ref["u"] - ref["v"])[..., None] + tri_uv[..., 1, :] * ref["u"][..., None]
           + tri_uv[..., 2, :] * ref["v"][..., None])
    on_left = inner & (ref["tri"] < 2)
    on_right = inner & (ref["tri"] >= 2)
    want = base * bilinear_repeat(tex, uvs[on_left])
    np.testing.assert_allclose(got["albedo"][on_left][:, :3], want, atol=3e-3)
    assert np.ptp(got["albedo"][on_left][:, 0]) > 0.2, "texture variation must reach the G-buffer"
    np.testing.assert_allclose(got["albedo"][on_right][:, :3],
                               np.broadcast_to(textured.mean_albedo, (on_right.sum(), 3)), atol=2e-3)


def test_gbuffer_plain_vertex_layout_draws_what_the_full_one_draws(raster):
    """Scenes without normal maps upload vertices without tangents and map UVs (`upload`'s
    "plain" layout, half the bytes): the same G-buffer, bit for bit, as the full layout with zero
    tangents and the texture UVs as the maps', bump maps and textures included."""
    from dataclasses import replace

    from hybridgi_core.snapshot import BumpMap, NormalMap

    rng = np.random.default_rng(5)
    tex = rng.uniform(0.05, 1.0, (4, 5, 3)).astype(np.float32)
    ramp = np.broadcast_to(np.linspace(0.0, 2.0, 16, dtype=np.float32)[None, :], (4, 16)).copy()
    materials = [Material(base_color=np.array([0.5, 1.0, 0.8], np.float32), texture=tex),
                 Material(name="bump", normal_map=NormalMap(bump=BumpMap(ramp, 1.0, 0.3)))]
    uv = [[-0.4, -0.3], [1.7, -0.3], [1.7, 1.2], [-0.4, 1.2]]
    geo = concat_geometry([quad((-2.0, -1.0, 0.0), (1.9, 0.0, 0.0), (0.0, 2.0, 0.0), uv=uv, material=0),
                           quad((0.1, -1.0, 0.2), (1.9, 0.0, 0.0), (0.0, 2.0, 0.3), uv=uv, material=1)])
    view = look_at((0.3, -0.5, 5.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    gb = raster["gbuffer"]
    images = {}
    for layout, tangents in (("plain", None), ("main", np.zeros((geo.positions.shape[0], 4), np.float32))):
        gb.upload(make_snapshot(replace(geo, tangents=tangents), materials))
        assert gb._layout == layout
        gb.execute(view, perspective(35.0))
        images[layout] = {n: gb.read(n) for n in ("albedo", "normal", "position", "emission", "depth")}
        images[layout]["surface"] = gb.read_surface(images[layout]["normal"])
    assert (images["plain"]["position"][..., 3] > 0.5).sum() > 1000
    for name, image in images["plain"].items():
        np.testing.assert_array_equal(image, images["main"][name], err_msg=name)


def test_gbuffer_blender_camera_matrices_and_update_positions(raster, bpy_module):
    import mathutils

    bpy = bpy_module
    cam = bpy.data.objects.new("raster_test_cam", bpy.data.cameras.new("raster_test_cam"))
    bpy.context.scene.collection.objects.link(cam)
    cam.location = (3.0, -2.0, 2.5)
    cam.rotation_euler = (mathutils.Vector((0.0, 0.0, 0.4)) - cam.location).to_track_quat("-Z", "Y").to_euler()
    bpy.context.view_layer.update()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    proj = cam.calc_matrix_camera(depsgraph, x=W, y=H)
    view = cam.matrix_world.inverted()
    snap = box_snapshot()
    gb = raster["gbuffer"]
    gb.upload(snap)
    gb.execute(view, proj)  # mathutils matrices are accepted as they come
    got = {n: gb.read(n) for n in ("albedo", "normal", "position", "depth")}
    check_against_reference(got, expected_gbuffer(snap, np.array(view), np.array(proj)))

    moved = make_snapshot(box((-0.6, -0.4, 0.0), (0.5, 0.7, 0.9)), snap.materials)
    moved.geometry.positions += np.float32([0.2, 0.1, -0.15])
    gb.update_positions(moved.geometry.positions)
    gb.execute(view, proj)
    got = {n: gb.read(n) for n in ("albedo", "normal", "position", "depth")}
    check_against_reference(got, expected_gbuffer(moved, np.array(view), np.array(proj)))
    bpy.data.objects.remove(cam)


def test_gbuffer_258k_triangles(raster):
    n = 361  # (n - 1) x (n - 1) quads x 2 = 259,200 triangles, plus a small box
    xs = np.linspace(-2.0, 2.0, n, dtype=np.float32)
    gx, gy = np.meshgrid(xs, xs)
    gz = 0.1 * np.sin(3 * gx) * np.cos(2 * gy)
    pos = np.stack([gx, gy, gz], -1).reshape(-1, 3)
    i = np.arange(n - 1)
    a = (i[None, :] + n * i[:, None]).ravel()
    tris = np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])
    nor = np.tile(np.float32([0, 0, 1]), (pos.shape[0], 1))
    geo = geometry_from_arrays(pos, tris, normals=nor)
    small_box = box((-0.3, -0.3, 0.2), (0.3, 0.3, 0.8), material_of_axis=(0, 0, 0))
    snap = make_snapshot(concat_geometry([geo, small_box]), [Material()])
    assert snap.geometry.triangle_count >= 258_000
    view = look_at((0.0, -4.0, 3.0), (0.0, 0.0, 0.0))
    proj = perspective(50.0)
    _, got = render_gbuffer(raster, snap, view, proj)
    ref = expected_gbuffer(make_snapshot(small_box, [Material()]), view, proj)
    # Coverage ~ the 4 m x 4 m square (its +-0.1 m waves move only a few edge pixels).
    o, d = pixel_rays(view, proj)
    t = -o[..., 2] / d[..., 2]
    p = o + d * t[..., None]
    square = (t > 0) & (np.abs(p[..., 0]) < 2) & (np.abs(p[..., 1]) < 2)
    covered = got["position"][..., 3] > 0.5
    assert covered.sum() > 1000 and np.mean(covered != (square | ref["hit"])) < 0.03
    inner = interior(np.where(ref["hit"], ref["tri"] // 2, -1)) & ref["hit"]
    # The box in the middle rasterizes exactly as its ray cast, on top of the big grid.
    np.testing.assert_allclose(got["position"][..., :3][inner], ref["position"][inner], atol=2e-4)


# ----------------------------------------------------------------------------------------------
# downsample
# ----------------------------------------------------------------------------------------------
def edge_scene():
    """A near quad (left part of the view) in front of a far wall; returns snapshot, view, proj."""
    wall = quad((-4.0, -3.0, 0.0), (8.0, 0.0, 0.0), (0.0, 6.0, 0.0))
    near = quad((-3.0, -0.9, 1.5), (2.9, 0.0, 0.0), (0.0, 2.0, 0.0))
    snap = make_snapshot(concat_geometry([wall, near]),
                         [Material(base_color=np.array([0.8, 0.8, 0.8], np.float32))])
    view = look_at((0.13, 0.07, 5.0), (0.13, 0.07, 0.0), up=(0.0, 1.0, 0.0))
    return snap, view, perspective(45.0)


def test_downsample_keeps_depth_edges(raster):
    snap, view, proj = edge_scene()
    gbuf, full = render_gbuffer(raster, snap, view, proj)
    ds = raster["downsample"]
    low = ds.execute(gbuf)
    assert (low.width, low.height) == (W // F, H // F)
    normal, position = ds.read_normal_position()
    depth = ds.read("depth")[..., 0]
    assert normal.shape == position.shape == (H // F, W // F, 4)
    blocks_d = full["depth"][..., 0].reshape(H // F, F, W // F, F).transpose(0, 2, 1, 3).reshape(H // F, W // F, -1)
    blocks_p = full["position"].reshape(H // F, F, W // F, F, 4).transpose(0, 2, 1, 3, 4).reshape(H // F, W // F, -1, 4)
    pick = np.argmin(blocks_d, axis=-1)
    want = np.take_along_axis(blocks_p, pick[..., None, None], axis=2)[:, :, 0]
    np.testing.assert_array_equal(position, want)  # a copy of one real sample, never a blend
    np.testing.assert_array_equal(depth, np.min(blocks_d, axis=-1))
    # The depth edge survives: both surfaces present, no low-res point between them.
    z = position[..., 2][position[..., 3] > 0.5]
    assert np.any(np.abs(z) < 1e-4) and np.any(np.abs(z - 1.5) < 1e-4)
    assert np.all((np.abs(z) < 1e-4) | (np.abs(z - 1.5) < 1e-4))
    np.testing.assert_allclose(np.linalg.norm(normal[..., :3], axis=-1)[position[..., 3] > 0.5], 1.0, atol=2e-3)


# ----------------------------------------------------------------------------------------------
# SSAO
# ----------------------------------------------------------------------------------------------
def run_ssao(raster, snap, view, proj, irradiance=None):
    """SSAO on a factor-1 'downsample' (64x48): 16x12 is too coarse to resolve a corner.

    irradiance : optional (3,) uniform irradiance of every pixel, uploaded as the SSAO input.
    """
    from hybridgi_core.raster.downsample import DownsamplePass
    from hybridgi_core.raster.readback import upload_texture_2d
    from hybridgi_core.raster.ssao import SSAOPass

    gbuf, _ = render_gbuffer(raster, snap, view, proj)
    with DownsamplePass(1) as ds, SSAOPass(raster["ssao"].settings) as ssao:
        ds.resize(W, H)
        low = ds.execute(gbuf)
        _n, position = ds.read_normal_position()
        ssao.resize(W, H)
        tex = None if irradiance is None else upload_texture_2d(np.broadcast_to(irradiance, (H, W, 3)), "RGBA16F")
        ssao.execute(low, view, proj, irradiance=tex)
        assert ssao.relative_bounce == (irradiance is None)
        return ssao.read(), position.copy()


def test_ssao_darkens_concave_corner_not_open_plane(raster):
    red = Material(base_color=np.array([0.9, 0.1, 0.1], np.float32))
    grey = Material(base_color=np.array([0.7, 0.7, 0.7], np.float32))
    floor = quad((-2.0, -2.0, 0.0), (4.0, 0.0, 0.0), (0.0, 4.0, 0.0), material=1)
    wall = quad((0.0, -2.0, 0.0), (0.0, 4.0, 0.0), (0.0, 0.0, 3.0), material=0)  # plane x = 0, normal +x
    view = look_at((3.0, -0.5, 2.2), (0.6, 0.0, 0.2))
    proj = perspective(55.0)

    corner_scene = make_snapshot(concat_geometry([floor, wall]), [red, grey])
    ssao, pos = run_ssao(raster, corner_scene, view, proj)
    geo = pos[..., 3] > 0.5
    on_floor = geo & (np.abs(pos[..., 2]) < 1e-4)
    near_corner = on_floor & (pos[..., 0] < 0.2)
    open_floor = on_floor & (pos[..., 0] > 1.2)
    assert near_corner.sum() >= 4 and open_floor.sum() >= 10
    ao = ssao[..., 3]
    assert ao[near_corner].mean() < 0.8, ao[near_corner]
    assert ao[open_floor].min() > 0.97, ao[open_floor]
    # Marched screen-space rays give the share of cosine rays blocked within the radius: for a
    # floor point at distance x from an infinite wall, 1 - (acos(a) - a sqrt(1 - a^2)) / pi, a = x/R.
    x = pos[..., 0][on_floor]
    a = np.clip(x / 0.5, 0.0, 1.0)
    analytic = 1.0 - (np.arccos(a) - a * np.sqrt(1.0 - a * a)) / np.pi
    for lo, hi in ((0.0, 0.1), (0.1, 0.2), (0.2, 0.3), (0.3, 0.5)):
        band = (x >= lo) & (x < hi)
        assert band.sum() >= 10
        assert abs(ao[on_floor][band].mean() - analytic[band].mean()) < 0.06, (lo, hi)
    # Colour bleeding: the floor by the red wall receives red-tinted bounce (albedo of occluder).
    bounce = ssao[..., :3][near_corner].mean(axis=0)
    assert bounce[0] > 0.05 and bounce[0] > 4 * bounce[1]
    assert np.all(ssao[~geo][:, 3] == 1.0)
    # With an irradiance input the bounce is albedo x the occluders' irradiance (W/m^2).
    lit, _ = run_ssao(raster, corner_scene, view, proj, irradiance=np.float32([2.0, 4.0, 1.0]))
    np.testing.assert_allclose(lit[..., :3], ssao[..., :3] * [2.0, 4.0, 1.0], rtol=2e-3, atol=1e-4)
    np.testing.assert_array_equal(lit[..., 3], ssao[..., 3])

    ssao_open, pos_open = run_ssao(raster, make_snapshot(floor, [red, grey]), view, proj)
    plane = pos_open[..., 3] > 0.5
    assert plane.sum() > 50
    assert ssao_open[..., 3][plane].min() > 0.97
    assert ssao_open[..., :3][plane].max() < 1e-3


# ----------------------------------------------------------------------------------------------
# bilateral upsampling (horizontal pass + the vertical taps the deferred pass runs)
# ----------------------------------------------------------------------------------------------
def upsample(raster, gbuf, low, gi_low):
    """Run H + V on gi_low (h_lo, w_lo, 4) used for all three inputs; returns full-res (H, W, 4)."""
    from hybridgi_core.raster.readback import upload_texture_2d

    tex = upload_texture_2d(gi_low, "RGBA16F")
    filtered = raster["bilateral"].execute(gbuf, low, tex, tex, tex)
    assert (filtered.width, filtered.height) == (W, H // F)
    raster["vertical"].execute(gbuf, filtered)
    return raster["vertical"].read(0), raster["vertical"].read(2)


def test_bilateral_keeps_depth_edge_and_smooths_noise(raster):
    snap, view, proj = edge_scene()
    gbuf, full = render_gbuffer(raster, snap, view, proj)
    low = raster["downsample"].execute(gbuf)
    _n, lo_pos = raster["downsample"].read_normal_position()
    far_lo = lo_pos[..., 3] > 0.5
    near_lo = far_lo & (lo_pos[..., 2] > 1.0)
    far_lo &= ~near_lo
    rng = np.random.default_rng(7)
    gi = np.zeros((H // F, W // F, 4), np.float32)
    gi[far_lo, :3] = 1.0 + rng.uniform(-0.5, 0.5, (far_lo.sum(), 1))
    gi[near_lo, :3] = 0.0
    gi[..., 3] = 1.0
    up, _ = upsample(raster, gbuf, low, gi)

    hit = full["position"][..., 3] > 0.5
    near = hit & (full["position"][..., 2] > 1.0)
    far = hit & ~near
    assert near.sum() > 100 and far.sum() > 100
    # Edge kept: no far-surface GI on the near quad, even in pixels touching the silhouette.
    assert up[near][:, 0].max() < 1e-3
    far_inner = far & interior(np.where(hit, near.astype(int), -1), margin=F)
    assert up[far_inner][:, 0].min() > 0.45
    # Noise smoothed within the surface, mean kept.
    noisy = gi[far_lo, 0]
    assert up[far_inner][:, 0].std() < 0.6 * noisy.std()
    assert abs(up[far_inner][:, 0].mean() - noisy.mean()) < 0.05
    # Plain bilinear upsampling would have bled: check the scene really has a hard edge.
    near_edge = near & ~interior(np.where(hit, near.astype(int), -1), margin=F)
    assert near_edge.sum() > 10


# ----------------------------------------------------------------------------------------------
# deferred combine
# ----------------------------------------------------------------------------------------------
E_LAMP = np.array([3.0, 2.0, 1.0], np.float32)
E_IND = np.array([0.6, 0.9, 1.2], np.float32)
E_CACHE = np.array([0.4, 0.5, 0.2], np.float32)
BOUNCE = np.array([0.05, 0.1, 0.02], np.float32)
RAY_AO, SS_AO = 0.8, 0.5
ALBEDO = np.array([0.6, 0.4, 0.2], np.float32)
EMIT = np.array([0.1, 0.0, 0.3], np.float32)
WORLD = (0.05, 0.1, 0.2)


def deferred_inputs(raster):
    from hybridgi_core.raster.readback import upload_texture_2d

    geo = quad((-1.0, -0.8, 0.0), (2.0, 0.0, 0.0), (0.0, 1.6, 0.0))
    snap = make_snapshot(geo, [Material(base_color=ALBEDO, emission=EMIT)])
    view = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    gbuf, full = render_gbuffer(raster, snap, view, perspective(50.0))
    low = raster["downsample"].execute(gbuf)
    lo = (H // F, W // F)

    def const(rgb, a):
        return upload_texture_2d(np.broadcast_to(np.float32([*rgb, a]), lo + (4,)), "RGBA16F")

    filtered = raster["bilateral"].execute(gbuf, low, const(E_IND, RAY_AO), const(E_CACHE, 0.0),
                                           const(BOUNCE, SS_AO))
    direct = upload_texture_2d(np.broadcast_to(E_LAMP, (H, W, 3)), "RGBA32F")
    hit = full["position"][..., 3] > 0.5
    return gbuf, direct, filtered, hit


def shade(raster, inputs, **kwargs):
    gbuf, direct, filtered, _hit = inputs
    raster["deferred"].execute(gbuf, direct, filtered, world_color=WORLD, **kwargs)
    d = raster["deferred"]
    return {n: d.read(n) for n in ("combined", "diffuse_direct", "diffuse_indirect", "diffuse_color", "ao")}


def test_deferred_combine_follows_cycles_passes_and_blend_modes(raster):
    inputs = deferred_inputs(raster)
    hit = inputs[3]
    inner = interior(np.where(hit, 0, -1)) & hit
    assert inner.sum() > 300
    results = {}
    for mode, ao, factor in (("MUL", RAY_AO * SS_AO, SS_AO), ("MIN", min(RAY_AO, SS_AO), SS_AO / RAY_AO)):
        out = shade(raster, inputs, blend_mode=mode)
        e_dir = E_LAMP + E_CACHE * factor
        e_ind = E_IND * factor + BOUNCE
        want = {
            "combined": ALBEDO * (e_dir + e_ind) / np.pi + EMIT,
            "diffuse_direct": e_dir / np.pi,
            "diffuse_indirect": e_ind / np.pi,
            "diffuse_color": ALBEDO,
        }
        for name, value in want.items():
            np.testing.assert_allclose(out[name][inner][:, :3], np.broadcast_to(value, (inner.sum(), 3)),
                                       rtol=3e-3, atol=1e-4, err_msg=f"{mode} {name}")
        np.testing.assert_allclose(out["ao"][inner][:, 0], ao, rtol=2e-3, err_msg=mode)
        assert np.all(out["combined"][inner][:, 3] == 1.0)
        # Background: world radiance, alpha 0, no diffuse passes.
        bg = ~hit
        np.testing.assert_allclose(out["combined"][bg], np.broadcast_to([*WORLD, 0.0], (bg.sum(), 4)), atol=1e-6)
        assert np.all(out["diffuse_direct"][bg] == 0) and np.all(out["ao"][bg] == 0)
        results[mode] = out
    assert abs(results["MIN"]["ao"][inner].mean() - results["MUL"]["ao"][inner].mean()) > 0.05
    assert np.all(results["MIN"]["combined"][inner][:, 0] > results["MUL"]["combined"][inner][:, 0])


def test_deferred_relative_bounce_and_debug_views(raster):
    from hybridgi_core.raster.settings import DEBUG_AO, DEBUG_AO_SPLIT, DEBUG_INDIRECT

    inputs = deferred_inputs(raster)
    hit = inputs[3]
    inner = interior(np.where(hit, 0, -1)) & hit
    out = shade(raster, inputs, blend_mode="MUL", relative_bounce=True)
    e_ind = E_IND * SS_AO + BOUNCE * (E_LAMP + E_CACHE + E_IND)
    np.testing.assert_allclose(out["diffuse_indirect"][inner][:, :3], np.broadcast_to(e_ind / np.pi, (inner.sum(), 3)),
                               rtol=3e-3)
    out = shade(raster, inputs, blend_mode="MUL", debug_view=DEBUG_INDIRECT)
    np.testing.assert_allclose(out["combined"][inner][:, :3],
                               np.broadcast_to(ALBEDO * (E_IND * SS_AO + BOUNCE) / np.pi, (inner.sum(), 3)), rtol=3e-3)
    out = shade(raster, inputs, blend_mode="MIN", debug_view=DEBUG_AO)
    np.testing.assert_allclose(out["combined"][inner][:, :3], min(RAY_AO, SS_AO), rtol=2e-3)
    out = shade(raster, inputs, debug_view=DEBUG_AO_SPLIT)
    cols = np.arange(W)[None, :].repeat(H, 0)
    np.testing.assert_allclose(out["combined"][inner & (cols < W // 2)][:, 0], RAY_AO, rtol=2e-3)
    np.testing.assert_allclose(out["combined"][inner & (cols >= W // 2)][:, 0], SS_AO, rtol=2e-3)


@pytest.mark.parametrize("ortho", [False, True])
def test_deferred_background_is_the_world_map_along_each_pixels_ray(raster, ortho):
    """The pixels without geometry show the world's map (`world_background`) where the world has
    one: per pixel, the map read along the ray through the projection the G-buffer was drawn
    with, as `BackgroundMap.radiance` reads it in numpy (a rotated map, a jittered projection,
    perspective and orthographic); the uniform colour where it has none."""
    from hybridgi_core.environment import BackgroundMap
    from hybridgi_core.raster.subpixel import jittered_projection
    from hybridgi_core.raster.world_background import WorldTexture, pixel_directions

    gbuf, direct, filtered, hit = deferred_inputs(raster)
    view = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    proj = orthographic(1.2) if ortho else perspective(50.0)
    proj = jittered_projection(proj, (0.3, -0.2), W, H)
    raster["gbuffer"].execute(view, proj)  # the G-buffer this shade reads, drawn with `proj`
    hit = raster["gbuffer"].read("position")[..., 3] > 0.5
    # A map with detail in both directions, seen from the front (-Z looks at the horizon's texels).
    rows, cols = 64, 128
    v, u = np.meshgrid((np.arange(rows) + 0.5) / rows, (np.arange(cols) + 0.5) / cols, indexing="ij")
    pixels = np.stack([1.0 + np.sin(9 * np.pi * u), 1.0 + np.cos(7 * np.pi * v), 0.5 + u * v], axis=-1)
    c, s = np.cos(0.7), np.sin(0.7)
    rotate = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    background = BackgroundMap(pixels.astype(np.float16), strength=2.5, to_world=rotate)
    world = WorldTexture()
    world.update(background)
    out = shade(raster, (gbuf, direct, filtered, hit), world=world, camera=(view, proj))
    bg = ~hit
    assert bg.sum() > 500
    want = background.radiance(pixel_directions(view, proj, W, H)).reshape(H, W, 3)
    # Within the GPU's bilinear weights (8 bits on llvmpipe: ~0.006 on these steep gradients).
    np.testing.assert_allclose(out["combined"][bg][:, :3], want[bg], rtol=2e-3, atol=1e-2)
    assert np.all(out["combined"][bg][:, 3] == 0.0)
    if ortho:  # every ray looks down -Z: one texel's radiance, not the uniform colour
        np.testing.assert_allclose(want[bg], np.broadcast_to(background.radiance(np.array([[0.0, 0.0, -1.0]])),
                                                             (bg.sum(), 3)), rtol=1e-5)
        assert np.abs(want[bg][0] - np.asarray(WORLD)).min() > 0.5
    else:
        assert want[bg].std(axis=0).min() > 0.1  # a map, not a colour: the check could fail
    # A strength edit (the same split's pixels) keeps the texture; other pixels upload anew.
    texture = world.texture
    world.update(BackgroundMap(background.pixels, strength=1.0, to_world=rotate))
    assert world.texture is texture
    out = shade(raster, (gbuf, direct, filtered, hit), world=world, camera=(view, proj))
    np.testing.assert_allclose(out["combined"][bg][:, :3], want[bg] / 2.5, rtol=2e-3, atol=1e-2)
    world.update(BackgroundMap(background.pixels.copy(), strength=1.0, to_world=rotate))
    assert world.texture is not texture
    # No map: the uniform colour, as before.
    world.update(None)
    out = shade(raster, (gbuf, direct, filtered, hit), world=world, camera=(view, proj))
    np.testing.assert_allclose(out["combined"][bg], np.broadcast_to([*WORLD, 0.0], (bg.sum(), 4)), atol=1e-6)


# ----------------------------------------------------------------------------------------------
# read-back / upload helpers and lifecycle
# ----------------------------------------------------------------------------------------------
def test_readback_orientation_and_formats(gpu_context):
    from hybridgi_core.raster.readback import read_texture, read_texture_3d, upload_texture_2d, upload_texture_3d

    rng = np.random.default_rng(0)
    img = rng.uniform(-2, 5, (7, 9, 4)).astype(np.float32)
    np.testing.assert_array_equal(read_texture(upload_texture_2d(img, "RGBA32F")), img)
    rgb = rng.uniform(0, 1, (5, 6, 3)).astype(np.float32)
    back = read_texture(upload_texture_2d(rgb, "RGBA32F"))
    np.testing.assert_array_equal(back[..., :3], rgb)
    assert np.all(back[..., 3] == 1.0)  # missing alpha padded with 1
    scalar = rng.uniform(0, 1, (4, 3)).astype(np.float32)
    np.testing.assert_array_equal(read_texture(upload_texture_2d(scalar, "R32F"))[..., 0], scalar)
    vol = rng.uniform(0, 1, (3, 4, 5, 4)).astype(np.float32)
    np.testing.assert_allclose(read_texture_3d(upload_texture_3d(vol, "RGBA16F"), 3), vol, atol=1e-3)
    with pytest.raises(TypeError):
        from hybridgi_core.raster.readback import read_framebuffer
        read_framebuffer(None, 0, 2, 2, 4, out=np.zeros((2, 2, 4), np.float64))


def test_lifecycle_errors(gpu_context):
    from hybridgi_core.raster.downsample import DownsamplePass
    from hybridgi_core.raster.passes import RasterError

    p = DownsamplePass(2)
    with pytest.raises(RasterError):
        p.execute(None)  # not resized yet
    p.resize(10, 7)
    assert (p.low_width, p.low_height) == (5, 4)
    p.free()
    assert p.width == 0
    with pytest.raises(RasterError):
        DownsamplePass(0)


# ----------------------------------------------------------------------------------------------
# GPU gather == evaluate.gather
# ----------------------------------------------------------------------------------------------
def random_cache(snapshot, sh_order, seed=11):
    from hybridgi_core.cache import IrradianceCache
    from hybridgi_core.settings import CacheSettings

    settings = CacheSettings(resolution=5, sh_order=sh_order, depth_texels=4, normal_bias=0.2)
    cache = IrradianceCache.for_scene(snapshot, settings)
    rng = np.random.default_rng(seed)
    n, k = cache.sh_direct.shape[:2]
    # A positive DC term with smaller higher bands: irradiance mostly positive, but not everywhere.
    scale = np.r_[1.0, np.full(k - 1, 0.4)][None, :, None].astype(np.float32)
    cache.sh_direct[:] = rng.uniform(-1, 1, (n, k, 3)) * scale + np.r_[1.5, np.zeros(k - 1)][None, :, None]
    cache.sh_indirect[:] = rng.uniform(-1, 1, (n, k, 3)) * scale + np.r_[1.0, np.zeros(k - 1)][None, :, None]
    cache.ao_sh[:] = rng.uniform(-0.3, 0.3, (n, k)) + np.r_[2.5, np.zeros(k - 1)][None, :]
    mean = rng.uniform(0.05, 1.0, cache.depth.shape[:2]) * cache.depth_cap
    cache.depth[..., 0] = mean
    cache.depth[..., 1] = mean * mean * rng.uniform(1.0, 1.3, mean.shape)
    cache.samples[:] = 1
    cache.samples[rng.random(n) < 0.15] = 0  # some cells never sampled ...
    cache.backface[rng.random(n) < 0.1] = 0.9  # ... and some inside geometry: both invalid
    cache.version += 1
    return cache


def test_gpu_gather_equals_evaluate(raster):
    from hybridgi_core.evaluate import gather
    from hybridgi_core.raster.gather import GatherPass

    snap = box_snapshot()
    # Inside a room: flip the box so its inner faces are seen (normals face the camera anyway).
    room = make_snapshot(box((-2.0, -2.0, 0.0), (2.0, 2.0, 2.5), material_of_axis=(0, 0, 0)),
                         [Material()] + snap.materials[1:])
    scene = make_snapshot(concat_geometry([room.geometry, snap.geometry]), snap.materials)
    view = look_at((1.6, -1.7, 1.9), (-0.5, 0.6, 0.5))
    gbuf, _ = render_gbuffer(raster, scene, view, perspective(70.0))
    low = raster["downsample"].execute(gbuf)
    normal, position = (a.copy() for a in raster["downsample"].read_normal_position())
    geo = position[..., 3] > 0.5
    assert geo.all()  # the camera is inside the room
    pts, nrm = position[..., :3].reshape(-1, 3), normal[..., :3].reshape(-1, 3)

    with GatherPass() as gp:
        gp.resize(W // F, H // F)
        rng = np.random.default_rng(5)
        for sh_order in (1, 2):
            cache = random_cache(scene, sh_order)
            assert gp.upload(cache) and not gp.upload(cache)
            mask = rng.random((H // F, W // F, 8)) < 0.6
            results = []
            for visibility, corner in ((False, None), (True, None), (True, mask)):
                gp.execute(low, visibility=visibility, corner_visible=corner)
                ind, dirc = gp.read(0), gp.read(1)
                ref = gather(cache, pts, nrm, visibility=visibility,
                             corner_visible=None if corner is None else corner.reshape(-1, 8))
                label = f"L{sh_order} visibility={visibility} mask={corner is not None}"
                for got, want in ((ind[..., :3], ref.indirect), (dirc[..., :3], ref.direct),
                                  (ind[..., 3], ref.ao)):
                    want = want.reshape(got.shape)
                    scale = max(float(np.abs(want).max()), 1e-6)
                    # Same float32 formula on both sides: llvmpipe agrees to ~5e-7 relative.
                    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * scale, err_msg=label)
                results.append(ind[..., :3].copy())
            assert ref.indirect.std() > 0.05  # the comparison is not between constants
            # ... and the three visibility modes really are different weightings.
            assert np.abs(results[0] - results[1]).max() > 0.1 and np.abs(results[1] - results[2]).max() > 0.1


def test_gpu_gather_reads_bent_normals_through_the_bent_lobe(gpu_context):
    """Normal-mapped pixels (shading normals bent off the smooth surface, which the downsampled
    material target carries in gba): the GPU gather reads the light through Cycles' bent lobe
    (`bump.irradiance_kernel`), as the numpy reference does, AO with the cosine; unbent pixels and
    surfaces=False keep the plain cosine lobe."""
    from types import SimpleNamespace

    from hybridgi_core.evaluate import gather
    from hybridgi_core.raster.gather import GatherPass
    from hybridgi_core.raster.readback import upload_texture_2d

    scene = box_snapshot()
    h, w = 12, 16
    rng = np.random.default_rng(9)
    pts = rng.uniform((-0.5, -0.3, 0.1), (0.4, 0.6, 0.8), (h * w, 3)).astype(np.float32)
    smooth = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (h * w, 1))
    tilt = rng.uniform(0.0, 1.2, h * w)  # up to ~69 degrees off the surface
    phi = rng.uniform(0.0, 2.0 * np.pi, h * w)
    bent = np.stack([np.sin(tilt) * np.cos(phi), np.sin(tilt) * np.sin(phi), np.cos(tilt)], axis=1).astype(np.float32)
    bent[: h * w // 4] = smooth[: h * w // 4]  # a quarter not bent
    position = np.concatenate([pts, np.ones((h * w, 1), np.float32)], axis=1).reshape(h, w, 4)
    normal = np.concatenate([bent, np.ones((h * w, 1), np.float32)], axis=1).reshape(h, w, 4)
    material = np.concatenate([np.ones((h * w, 1), np.float32), smooth], axis=1).reshape(h, w, 4)
    low = SimpleNamespace(position=upload_texture_2d(position), normal=upload_texture_2d(normal),
                          material=upload_texture_2d(material), width=w, height=h)
    with GatherPass() as gp:
        gp.resize(w, h)
        cache = random_cache(scene, 2)
        gp.upload(cache)
        for surfaces in (True, False):
            gp.execute(low, visibility=False, surfaces=surfaces)
            ind, dirc = gp.read(0).reshape(-1, 4), gp.read(1).reshape(-1, 4)
            ref = gather(cache, pts, bent, visibility=False, surfaces=smooth if surfaces else None)
            for got, want in ((ind[:, :3], ref.indirect), (dirc[:, :3], ref.direct), (ind[:, 3], ref.ao)):
                scale = max(float(np.abs(want).max()), 1e-6)
                # The lobe table is interpolated in float32 on the GPU, float64 in numpy.
                np.testing.assert_allclose(got, want, rtol=2e-3, atol=2e-3 * scale, err_msg=f"surfaces={surfaces}")
        plain = gather(cache, pts, bent, visibility=False)
        through = gather(cache, pts, bent, visibility=False, surfaces=smooth)
        # The bent lobe differs where normals are bent (no light from below the surface), not elsewhere.
        q = h * w // 4
        np.testing.assert_allclose(through.indirect[:q], plain.indirect[:q], rtol=1e-5)
        assert np.abs(through.indirect[q:] - plain.indirect[q:]).max() > 0.05
        np.testing.assert_allclose(through.ao, plain.ao)


def test_gpu_gather_of_two_levels_equals_the_numpy_reference(raster):
    """Cache levels without pixel rays: the GPU gather of each level with its own corner mask,
    joined by CacheLevels.blend (`gather_levels`), equals CacheLevels.gather in numpy; level 1
    (half the cells, over part of the room) really changes part of the image and not the rest."""
    from hybridgi_core.cache import IrradianceCache
    from hybridgi_core.evaluate import gather
    from hybridgi_core.grid import CacheGrid
    from hybridgi_core.levels import CacheLevels
    from hybridgi_core.raster.gather import GatherPass, gather_levels
    from hybridgi_core.visible import pixels_to_points

    snap = box_snapshot()
    room = make_snapshot(box((-2.0, -2.0, 0.0), (2.0, 2.0, 2.5), material_of_axis=(0, 0, 0)),
                         [Material()] + snap.materials[1:])
    scene = make_snapshot(concat_geometry([room.geometry, snap.geometry]), snap.materials)
    view = look_at((1.6, -1.7, 1.9), (-0.5, 0.6, 0.5))
    gbuf, _ = render_gbuffer(raster, scene, view, perspective(70.0))
    low = raster["downsample"].execute(gbuf)
    normal, position = (a.copy() for a in raster["downsample"].read_normal_position())
    pts, nrm, pix = pixels_to_points(position, normal)
    base = random_cache(scene, 2)
    g0 = base.grid
    # Level 1: half the cell size over the coarse cells 1..3 of each axis (part of the room).
    fine_grid = CacheGrid((g0.lo + g0.cell_size).astype(np.float32), g0.cell_size / 2, (6, 6, 6))
    donor = random_cache(scene, 2, seed=23)
    fine = IrradianceCache(fine_grid, base.settings)
    rng = np.random.default_rng(8)
    for name in ("sh_direct", "sh_indirect", "ao_sh"):
        src = getattr(donor, name)
        getattr(fine, name)[:] = src[rng.integers(0, src.shape[0], fine_grid.count)]
    fine.samples[:] = 1
    fine.samples[rng.random(fine_grid.count) < 0.1] = 0
    levels = CacheLevels(base, [fine])
    visible = rng.random((pts.shape[0], 16)) < 0.7
    with GatherPass() as gp:
        gp.resize(W // F, H // F)
        got = gather_levels(gp, levels, low, pts, nrm, pix, visible)
    ref = levels.gather(pts, nrm, visible)
    for a, b in ((got.direct, ref.direct), (got.indirect, ref.indirect), (got.ao, ref.ao)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4 * max(float(np.abs(b).max()), 1e-6))
    plain = gather(base, pts, nrm, corner_visible=visible[:, :8])
    share = levels.level_shares(pts, nrm, visible)[0]
    changed = np.abs(ref.indirect - plain.indirect).max(axis=1) > 1e-3
    assert changed.any() and (share > 0).sum() < pts.shape[0]
    assert not changed[share == 0].any()
    np.testing.assert_array_equal(ref.indirect[share == 0], plain.indirect[share == 0])


def test_gpu_accumulation_equals_the_numpy_film(gpu_context):
    """The pixel filter's GPU sums (AccumulatePass, ping-pong over 3 subframes) read out as the
    numpy reference FilmAccumulator.add computes them; a second frame starts new sums."""
    from types import SimpleNamespace

    from hybridgi_core.raster.accumulate import AccumulatePass
    from hybridgi_core.raster.deferred import ShadedFrame
    from hybridgi_core.raster.readback import upload_texture_2d
    from hybridgi_core.raster.subpixel import FilmAccumulator

    rng = np.random.default_rng(5)
    acc = AccumulatePass()
    acc.resize(W, H)
    ref = FilmAccumulator()
    try:
        for s in range(3):
            arrays = {name: rng.random((H, W, 4), dtype=np.float32) for name in
                      ("combined", "diffuse_direct", "diffuse_indirect", "diffuse_color", "normal")}
            arrays["ao"] = rng.random((H, W, 1), dtype=np.float32)
            position = rng.random((H, W, 4), dtype=np.float32)
            position[..., 3] = rng.random((H, W)) > 0.3  # w = 1 on geometry
            arrays["depth"] = np.where(position[..., 3:] > 0.5, 2.0, 1e10).astype(np.float32)
            tex = {n: upload_texture_2d(a, "R32F" if n == "ao" else "RGBA32F") for n, a in arrays.items()}
            shaded = ShadedFrame(tex["combined"], tex["diffuse_direct"], tex["diffuse_indirect"],
                                 tex["diffuse_color"], tex["ao"], W, H)
            acc.execute(shaded, SimpleNamespace(normal=tex["normal"], position=upload_texture_2d(position)),
                        first=s == 0)
            ref.add(arrays)
        assert acc.count == 3
        film = FilmAccumulator()
        film.set_sums(acc.read_all(), acc.count)
        for name in ("combined", "combined_premultiplied", "diffuse_direct", "diffuse_indirect",
                     "diffuse_color", "ao", "normal"):
            np.testing.assert_allclose(film.read(name), ref.read(name), rtol=1e-5, atol=1e-6, err_msg=name)
        acc.execute(shaded, SimpleNamespace(normal=tex["normal"], position=upload_texture_2d(position)), first=True)
        assert acc.count == 1
        np.testing.assert_allclose(acc.read("combined"), arrays["combined"], rtol=1e-6)
    finally:
        acc.free()


@pytest.mark.parametrize("filter_type, size, count", [("BLACKMAN_HARRIS", 1.5, 3), ("GAUSSIAN", 1.5, 1), ("BOX", 1.0, 2)])
def test_gpu_film_resolve_equals_the_numpy_film(gpu_context, filter_type, size, count):
    """The film's GPU resolve (FilmResolvePass: the pixel filter and Cycles' colour divisions over
    the accumulated sums) reads as the numpy FilmAccumulator reads the same sums, for a 3-tap and
    a 5-tap filter and none: channels without colour (the mean of the others), pixels whose own
    samples saw none (0 though a neighbour's filtered colour reaches them), the image's edges."""
    from types import SimpleNamespace

    from hybridgi_core.raster import film_resolve
    from hybridgi_core.raster.accumulate import AccumulatePass
    from hybridgi_core.raster.deferred import ShadedFrame
    from hybridgi_core.raster.readback import upload_texture_2d
    from hybridgi_core.raster.subpixel import FilmAccumulator, reconstruction_taps

    taps = reconstruction_taps(count, size, filter_type)
    assert film_resolve.supports(taps) and taps.size == {"BLACKMAN_HARRIS": 3, "GAUSSIAN": 5, "BOX": 1}[filter_type]
    rng = np.random.default_rng(11)
    acc = AccumulatePass()
    acc.resize(W, H)
    resolve = film_resolve.FilmResolvePass()
    resolve.resize(W, H)
    try:
        for s in range(count):
            arrays = {name: rng.random((H, W, 4), dtype=np.float32) for name in
                      ("combined", "diffuse_direct", "diffuse_indirect", "diffuse_color", "normal")}
            colour = arrays["diffuse_color"]
            colour[rng.random((H, W)) < 0.2, 1] = 0.0  # a channel without colour
            colour[3:6, 4:9, :3] = 0.0  # pixels that see no colour at all, among others that do
            arrays["ao"] = rng.random((H, W, 1), dtype=np.float32)
            position = rng.random((H, W, 4), dtype=np.float32)
            position[..., 3] = 1.0
            tex = {n: upload_texture_2d(a, "R32F" if n == "ao" else "RGBA32F") for n, a in arrays.items()}
            shaded = ShadedFrame(tex["combined"], tex["diffuse_direct"], tex["diffuse_indirect"],
                                 tex["diffuse_color"], tex["ao"], W, H)
            acc.execute(shaded, SimpleNamespace(normal=tex["normal"], position=upload_texture_2d(position)),
                        first=s == 0)
        ref = FilmAccumulator()
        ref.set_filter(taps)
        ref.set_sums(acc.read_all(), acc.count)
        resolve.execute(acc, taps)
        got = FilmAccumulator()
        got.set_filter(taps)
        got.set_resolved(resolve.read_all(), acc.count)
        for name in ("combined", "combined_premultiplied", "diffuse_direct", "diffuse_indirect",
                     "diffuse_color", "ao", "normal"):
            np.testing.assert_allclose(got.read(name), ref.read(name), rtol=1e-5, atol=1e-6, err_msg=name)
        if taps.size > 1:
            assert (ref.read("diffuse_direct")[3:6, 4:9, :3] == 0).all()  # the mask is exercised
            assert (ref.read("diffuse_color")[3:6, 4:9, :3] > 0).any()
    finally:
        acc.free()
        resolve.free()


def test_film_resolve_refuses_filters_wider_than_it_takes():
    from hybridgi_core.raster import film_resolve
    from hybridgi_core.raster.subpixel import reconstruction_taps

    wide = reconstruction_taps(1, 10.0, "GAUSSIAN")
    assert not film_resolve.supports(wide)  # the frame keeps the numpy film for it
    assert film_resolve.supports(reconstruction_taps(8, 1.5, "BLACKMAN_HARRIS"))


def test_pixel_directions_are_the_rays_through_the_pixel_centres():
    """`world_background.pixel_directions` (the CPU background of a frame without geometry):
    the centre of a perspective view looks along the camera's -Z, a corner pixel along its own
    ray; an orthographic view's rays are all the camera's -Z."""
    from hybridgi_core.raster.world_background import pixel_directions

    view = look_at((1.0, -2.0, 0.5), (0.0, 1.0, 0.3))
    forward = np.array([-1.0, 3.0, -0.2]) / np.linalg.norm([-1.0, 3.0, -0.2])
    w, h = 5, 3
    proj = np.array(perspective(60.0))
    proj[0, 0] = proj[1, 1] * h / w  # this image's aspect
    d = pixel_directions(view, proj, w, h).reshape(h, w, 3)
    np.testing.assert_allclose(d[1, 2], forward, atol=1e-6)
    # The top-right pixel (rows bottom-up): its centre at x = 0.8, y = 2/3 of the half-extent.
    right, up = np.cross(forward, [0.0, 0.0, 1.0]), None
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    t = np.tan(np.radians(30.0))
    ray = forward + 0.8 * t * w / h * right + (2.0 / 3.0) * t * up
    np.testing.assert_allclose(d[2, 4], ray / np.linalg.norm(ray), atol=1e-6)
    flat = pixel_directions(view, orthographic(1.0), w, h)
    np.testing.assert_allclose(flat, np.broadcast_to(forward, flat.shape), atol=1e-6)
