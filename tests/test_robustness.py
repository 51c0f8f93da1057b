"""Issue 13 in the core and the CLI's helpers: settings refused by name and range, limits checked
before allocation, tolerances relative to each object, one pass over the triangles, atomic
output. bpy-free except the GPU gather test. (The same defects through the real command:
tests/test_corpus.py.)"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from hybridgi_cli import output
from hybridgi_core import snapshot as snap
from hybridgi_core.errors import LimitError, SettingsError
from hybridgi_core.raster import gather
from hybridgi_core.raster.settings import RasterSettings
from hybridgi_core.settings import CacheSettings
from tests import test_raster
from tests.shapes import box
from tests.test_raster import raster  # noqa: F401, F811  (the GPU passes fixture, shared)

# --- settings ------------------------------------------------------------------------------------


@pytest.mark.parametrize(("changes", "words"), [
    ({"resolution": 0}, ("resolution=0", "1 <= value <= 512")),
    ({"rays_per_cell": -1}, ("rays_per_cell=-1", "1 <= value <= 65536")),
    ({"hysteresis": 2.0}, ("hysteresis=2.0", "0.0 <= value < 1.0")),
    ({"hysteresis": 1.0}, ("hysteresis=1.0", "< 1.0")),
    ({"ray_length": -5.0}, ("ray_length=-5.0", ">= 0.0")),
    ({"ray_length": math.nan}, ("ray_length=nan", "not a finite number")),
    ({"ray_length": math.inf}, ("ray_length=inf", "not a finite number")),
    ({"ao_distance": 0.0}, ("ao_distance=0.0", "> 0.0")),
    ({"normal_bias": math.nan}, ("normal_bias=nan",)),
    ({"sh_order": 3}, ("sh_order=3", "1, 2")),
    ({"max_memory_mib": 0}, ("max_memory_mib=0",)),
])
def test_cache_settings_refuse_with_name_and_range(changes, words):
    with pytest.raises(SettingsError) as err:
        CacheSettings(**changes)
    assert isinstance(err.value, ValueError)  # what a caller that only knows ValueError catches
    for word in words:
        assert word in str(err.value)


def test_every_problem_is_named_at_once():
    with pytest.raises(SettingsError, match=r"resolution=0 .*; hysteresis=nan"):
        CacheSettings(resolution=0, hysteresis=math.nan)


@pytest.mark.parametrize("name", ["ssao_radius", "ssao_strength", "bilateral_sigma", "bilateral_normal_power"])
def test_raster_settings_refuse_non_finite(name):
    for value in (math.nan, math.inf, -math.inf):
        with pytest.raises(SettingsError, match=f"{name}="):
            RasterSettings(**{name: value})


def test_defaults_and_the_documented_extremes_are_accepted():
    CacheSettings()
    CacheSettings(resolution=512, hysteresis=0.99, ray_length=0.0, rays_per_cell=65536)
    RasterSettings(ssao_strength=4.0, downsample=16)


# --- limits --------------------------------------------------------------------------------------


def test_cache_memory_is_estimated_and_capped_before_allocation():
    s = CacheSettings(resolution=512)
    with pytest.raises(LimitError) as err:
        s.check_cell_count((512, 512, 128))
    text = str(err.value)
    assert "cache memory limit of 4.0 GiB" in text and "lower the HybridGI Resolution to" in text
    fits = int(text.rsplit("to ", 1)[1].split()[0])
    # The suggested resolution does fit (cells scale with its cube).
    scale = fits / 512
    CacheSettings(resolution=fits).check_cell_count(tuple(int(d * scale) for d in (512, 512, 128)))
    # The estimate is the cache's real size.
    from hybridgi_core.cache import IrradianceCache
    from hybridgi_core.grid import CacheGrid

    grid = CacheGrid.from_bounds(np.zeros(3), np.array([1.0, 1.0, 0.5]), 16)
    cache = IrradianceCache(grid, CacheSettings(resolution=16))
    arrays = [cache.sh_direct, cache.sh_indirect, cache.ao_sh, cache.depth, cache.backface, cache.samples,
              cache.last_frame, cache.urgency, cache.centers]
    assert sum(a.nbytes for a in arrays) == grid.count * cache.settings.cell_bytes


def test_resolution_128_fits_a_16384_texture_and_165_cubed_is_refused_early():
    s = CacheSettings(resolution=128)
    s.check_cell_count((128, 128, 128))
    gather.check_cache_textures(128**3, s.sh_coeffs, s.depth_texels, 16384)
    rows, width = gather._layout(128**3 * s.depth_texels**2, 16384)
    assert (rows, width) == (8192, 16384)  # the old 4096-wide layout needed 32768 rows
    with pytest.raises(LimitError, match="16384x16384 texture limit"):
        CacheSettings(resolution=165).check_cell_count((165, 165, 165))
    with pytest.raises(LimitError, match="texture size limit of 8192"):
        gather.check_cache_textures(128**3, s.sh_coeffs, s.depth_texels, 8192)


def test_cache_refuses_before_allocating():
    from hybridgi_core.cache import IrradianceCache
    from hybridgi_core.grid import CacheGrid

    grid = CacheGrid.from_bounds(np.zeros(3), np.ones(3), 512)
    start = time.perf_counter()
    with pytest.raises(LimitError):
        IrradianceCache(grid, CacheSettings(resolution=512))
    assert time.perf_counter() - start < 0.5


def test_large_textures_are_box_filtered_to_the_cap():
    tex = np.zeros((10, 9000, 3), np.float32)
    tex[:, 4500:, 1] = 1.0
    tex[0, 0, 0] = np.nan
    m = snap.Material(texture=tex)
    h, w = m.texture.shape[:2]
    assert max(h, w) <= snap.MAX_TEXTURE_SIZE and w == 3000 and np.isfinite(m.texture).all()
    assert np.allclose(m.texture[:, :1490, 1], 0.0) and np.allclose(m.texture[:, 1510:, 1], 1.0)
    small = np.random.default_rng(0).random((16, 8, 3)).astype(np.float32)
    assert np.array_equal(snap.Material(texture=small).texture, small)


def test_non_finite_lights_world_and_colours_are_sanitised():
    light = snap.Light("POINT", (1.0, math.nan, 1.0), math.nan, np.eye(4), name="lamp")
    assert light.power == 0.0 and np.isfinite(light.color).all()
    assert np.isfinite(snap.World(color=(math.nan, 0.1, 0.2)).color).all()
    assert np.isfinite(snap.Material(base_color=(math.inf, 0.5, 0.5)).base_color).all()
    # Blender stores an "inf" typed into Emission Strength as FLT_MAX: finite, but every pixel of
    # the render was NaN (the CLI refused the frame).
    flt_max = float(np.finfo(np.float32).max)
    assert snap.Material(emission=(flt_max, 0.5 * flt_max, 1.0)).emission.tolist() == [0.0, 0.0, 1.0]
    assert snap.World(color=(1e38, 0.1, 0.2)).color.tolist() == pytest.approx([0.0, 0.1, 0.2])
    assert snap.Material(emission=(1e6, 1e6, 1e6)).emission.tolist() == [1e6, 1e6, 1e6]  # a bright lamp panel
    with pytest.raises(snap.InvalidGeometryError, match="transform is not finite"):
        snap.Light("SUN", (1, 1, 1), 1.0, np.full((4, 4), np.nan), name="sun")


# --- geometry tolerances -------------------------------------------------------------------------


def sphere(centre, radius, n=24):
    th, ph = np.meshgrid(np.linspace(0, np.pi, n), np.linspace(0, 2 * np.pi, 2 * n), indexing="ij")
    pts = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    w = 2 * n
    tris = [(i * w + j, (i + 1) * w + j, i * w + j + 1) for i in range(n - 1) for j in range(w - 1)]
    tris += [(i * w + j + 1, (i + 1) * w + j, (i + 1) * w + j + 1) for i in range(n - 1) for j in range(w - 1)]
    return snap.geometry_from_arrays(pts * radius + np.asarray(centre), np.array(tris))


@pytest.mark.parametrize(("centre", "radius"), [((0, 0, 0), 1.0), ((1e5, 0, 0), 0.5), ((0, 0, 0), 1e-6),
                                                ((3e3, -2e3, 1e3), 0.1)])
def test_zero_area_tolerance_follows_the_object_not_the_origin(centre, radius):
    g = sphere(centre, radius)
    at_origin = snap.make_snapshot(sphere((0, 0, 0), 1.0), [snap.Material()]).geometry.triangle_count
    # Only the rows at the poles are degenerate (zero area), wherever and however large.
    assert snap.make_snapshot(g, [snap.Material()]).geometry.triangle_count == at_origin < g.triangle_count


def test_micrometre_and_kilometre_boxes_keep_every_triangle():
    parts = [box((0, 0, 0), (1e-6, 1e-6, 1e-6), inward=False, obj=0), box((1e5, 1e5, 0), (1e5 + 1e3, 1e5 + 1e3, 10), obj=1)]
    s = snap.make_snapshot(snap.concat_geometry(parts), [snap.Material()])
    assert s.geometry.triangle_count == 24


def test_flat_object_from_a_zero_scale_is_kept_with_face_normals():
    g = box((0, 0, 0.3), (1, 1, 0.3), inward=False)  # what a scale of 0 along z makes of a cube
    g.normals[:] = np.nan  # the inverse transpose of a singular matrix
    s = snap.make_snapshot(g, [snap.Material()])
    assert s.geometry.triangle_count == 4  # top and bottom; the sides have no area
    assert np.allclose(np.abs(s.geometry.normals[:, 2]), 1.0)


# --- one pass over the triangles -----------------------------------------------------------------


def test_focus_bounds_is_one_pass_over_many_objects():
    n = 20000
    parts = [box((i % 150 * 2.0, i // 150 * 2.0, 0), (i % 150 * 2.0 + 1, i // 150 * 2.0 + 1, 1), inward=False, obj=i)
             for i in range(n)]
    parts.append(box((-1000, -1000, -0.01), (1300, 1300, 0.0), inward=False, obj=n))  # a ground plane
    s = snap.make_snapshot(snap.concat_geometry(parts), [snap.Material()])
    start = time.perf_counter()
    lo, hi = s.focus_bounds()
    seconds = time.perf_counter() - start
    assert seconds < 1.0, seconds  # the per-object scan took ~40 s here
    ids, blo, bhi = snap.object_boxes(s.geometry)
    assert ids.size == n + 1 and np.allclose(blo[5], (10, 0, 0)) and np.allclose(bhi[5], (11, 1, 1))
    # The ground plane does not set the bounds; the boxes' own extent (plus the margin) does.
    assert lo[0] > -1000 and hi[0] < 1300 and lo[2] == pytest.approx(-0.01)


def test_focus_bounds_matches_the_per_object_definition():
    parts = [box((0, 0, 0), (1, 1, 1), inward=False, obj=0), box((2, 0, 0), (3, 2, 0.5), inward=False, obj=1),
             box((-20, -20, -0.001), (20, 20, 0.0), inward=False, obj=2)]
    s = snap.make_snapshot(snap.concat_geometry(parts), [snap.Material()])
    lo, hi = s.focus_bounds()
    pad = snap.FOCUS_MARGIN * 3.0  # the rest spans 3 m
    assert np.allclose(lo, (0 - pad, 0 - pad, -0.001), atol=1e-5)
    assert np.allclose(hi, (3 + pad, 2 + pad, 1), atol=1e-5)  # within the full bounds


# --- the CLI's output helpers --------------------------------------------------------------------


def test_out_resolves_like_blender(tmp_path, monkeypatch):
    blend = tmp_path / "scenes" / "shot.blend"
    blend.parent.mkdir()
    monkeypatch.chdir(tmp_path)
    assert output.resolve_prefix("//render/x", blend) == tmp_path / "scenes" / "render" / "x"
    assert output.resolve_prefix("//", blend) == tmp_path / "scenes" / "shot"
    assert output.resolve_prefix("frames/", blend) == tmp_path / "frames" / "shot"
    (tmp_path / "existing").mkdir()
    assert output.resolve_prefix("existing", blend) == tmp_path / "existing" / "shot"
    assert output.resolve_prefix("out/x", blend) == tmp_path / "out" / "x"
    assert output.frame_paths(tmp_path / "x", 7) == (tmp_path / "x_0007.png", tmp_path / "x_0007.exr")
    assert output.frame_paths(tmp_path / "s_###_v", 7)[0] == tmp_path / "s_007_v.png"


def test_output_folder_problems_are_named(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(output.OutputError, match="a file of that name exists|Not a directory"):
        output.prepare_folder(tmp_path / "file" / "sub" / "x")
    with pytest.raises(output.OutputError, match="cannot create output folder /proc"):
        output.prepare_folder(output.resolve_prefix("/proc/hybridgi_test/x", tmp_path / "a.blend"))
    output.prepare_folder(tmp_path / "new" / "deeper" / "x")
    assert list((tmp_path / "new" / "deeper").iterdir()) == []  # the write probe is gone


def test_frame_files_appear_only_when_complete(tmp_path):
    png, exr = tmp_path / "x_0001.png", tmp_path / "x_0001.exr"
    with output.FrameFiles(png, exr) as files:
        files.temp[png].write_bytes(b"png")
        files.temp[exr].write_bytes(b"")  # Blender wrote an empty file
        with pytest.raises(output.OutputError, match="did not write"):
            files.commit()
    assert list(tmp_path.iterdir()) == []  # temporary files removed, nothing renamed
    with pytest.raises(RuntimeError):
        with output.FrameFiles(png, exr) as files:
            files.temp[png].write_bytes(b"png")
            raise RuntimeError("render failed")
    assert list(tmp_path.iterdir()) == []
    with output.FrameFiles(png, exr) as files:
        files.temp[png].write_bytes(b"png")
        files.temp[exr].write_bytes(b"exr")
        files.commit()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x_0001.exr", "x_0001.png"]
    # An interrupt discards what is being written.
    with output.FrameFiles(tmp_path / "y.png") as files:
        files.temp[tmp_path / "y.png"].write_bytes(b"partial")
        output.discard_pending()
        assert not files.temp[tmp_path / "y.png"].exists()


# --- GPU: the widened texture layout gathers the same values -------------------------------------


def test_gpu_gather_with_textures_wider_than_the_pack_width(raster, monkeypatch):  # noqa: F811
    widths = []
    real_upload = gather.upload_texture_2d

    def upload(data, fmt):
        widths.append(data.shape[1])
        return real_upload(data, fmt)

    # A tiny GPU: 48 texels per side, so the test cache's rows overflow an 8-wide layout.
    monkeypatch.setattr(gather, "PACK_WIDTH", 8)
    monkeypatch.setattr(gather, "max_texture_size", lambda: 48)
    monkeypatch.setattr(gather, "upload_texture_2d", upload)
    test_raster.test_gpu_gather_equals_evaluate(raster)
    assert 48 in widths  # the cache textures did widen (the mask texture keeps its own width)


def test_tracebacks_of_reported_errors_are_held_back():
    import io

    from hybridgi_cli.tracebacks import TracebackFilter

    stream = io.StringIO()
    f = TracebackFilter(stream)
    f.write("hybridgi: frame 1 (1/1): rendering\nTraceback (most recent call last):\n  File \"x.py\", line 1")
    f.write(", in render\n    boom()\nTypeError: boom\nBlender's own line\n")
    f.write("Exception ignored in: <function E.__del__>\nTraceback (most recent call last):\n  File \"e.py\"\n")
    f.write("ReferenceError: removed\nhybridgi: error: frame 1: internal error: TypeError: boom\n")
    f.flush()
    assert stream.getvalue().splitlines() == [
        "hybridgi: frame 1 (1/1): rendering", "Blender's own line", "hybridgi: error: frame 1: internal error: TypeError: boom"]
    assert "TypeError: boom" in f.held and "ReferenceError: removed" in f.held


def test_exr_with_non_finite_pixels_is_named(bpy_module, tmp_path):
    bpy = bpy_module
    image = bpy.data.images.new("nan", 4, 2, alpha=True, float_buffer=True)
    pixels = np.ones((2, 4, 4), np.float32)
    pixels[0, 1, 0] = np.nan
    pixels[1, 2, 1] = np.nan
    image.pixels.foreach_set(pixels.ravel())
    image.filepath_raw = str(tmp_path / "nan.exr")
    image.file_format = "OPEN_EXR"
    image.save()
    bpy.data.images.remove(image)
    assert sorted(output.non_finite_channels(tmp_path / "nan.exr")) == ["G (1)", "R (1)"]


def test_peer_engines_fail_only_on_a_non_finite_combined():
    """Cycles leaves NaN in Diffuse Color where a volume fills a pixel (its own output): a peer
    engine's frame fails only when Combined is not finite; HybridGI's on any channel."""
    colour = ["ViewLayer.Diffuse Color.R (40)", "ViewLayer.Diffuse Color.G (40)"]
    combined = ["ViewLayer.Combined.R (2)"]
    assert output.fatal_non_finite(colour, "CYCLES") == []
    assert output.fatal_non_finite(colour + combined, "CYCLES") == combined
    assert output.fatal_non_finite(["R (1)"], "BLENDER_EEVEE_NEXT") == ["R (1)"]
    assert output.fatal_non_finite(colour, "HYBRIDGI") == colour


def test_gpu_gather_uploads_depth_moments_only_for_the_chebyshev_test(raster, monkeypatch):  # noqa: F811
    from hybridgi_core.raster.gather import GatherPass

    formats = []
    real_upload = gather.upload_texture_2d
    monkeypatch.setattr(gather, "upload_texture_2d", lambda data, fmt: formats.append((fmt, data.size)) or real_upload(data, fmt))
    scene = test_raster.box_snapshot()
    gbuf, _ = test_raster.render_gbuffer(raster, scene, test_raster.look_at((1.6, -1.7, 1.9), (-0.5, 0.6, 0.5)),
                                         test_raster.perspective(70.0))
    low = raster["downsample"].execute(gbuf)
    cache = test_raster.random_cache(scene, 2)
    depth_size = cache.depth.size
    w, h = test_raster.W // test_raster.F, test_raster.H // test_raster.F
    with GatherPass() as gp:
        gp.resize(w, h)
        gp.upload(cache)
        gp.execute(low, corner_visible=np.ones((h, w, 8), bool))  # final renders: a corner mask
        gp.execute(low, visibility=False)
        assert not any(fmt == "RG32F" and size >= depth_size for fmt, size in formats)
        gp.execute(low)  # the Chebyshev test reads the moments: uploaded now, once
        gp.execute(low)
        assert sum(fmt == "RG32F" and size >= depth_size for fmt, size in formats) == 1
        cache.version += 1  # the cache moved on: the next upload packs its SH, depth waits again
        assert gp.upload(cache)
        gp.execute(low, corner_visible=np.ones((h, w, 8), bool))
        assert sum(fmt == "RG32F" and size >= depth_size for fmt, size in formats) == 1


def test_a_vanishing_normal_takes_the_face_normal_whether_handed_over_or_not():
    """A normal too short to trust (|n| < 1e-6) takes its face's normal, also where `sanitized`
    normalizes the caller's handed-over normals in place (it must be judged before it is scaled)."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    for owned in (False, True):
        g = snap.geometry_from_arrays(pos.copy(), np.array([[0, 1, 2]], np.int32))
        g.normals[:] = (0.0, 0.0, -1.0)
        g.normals[1] = (1e-7, 0.0, 0.0)
        out = snap.sanitized(g, 1, 1, owned=owned)
        np.testing.assert_allclose(out.normals[1], (0.0, 0.0, 1.0), atol=1e-6)  # the face's, not +x
        np.testing.assert_allclose(out.normals[0], (0.0, 0.0, -1.0))


def test_sanitized_shares_arrays_only_when_handed_over_and_nothing_is_dropped():
    """sanitized(owned=False) never shares an array with its input (the caller may keep and change
    it); owned=True (a sync's fresh concatenation) takes the arrays as they are where every
    triangle is kept, and still copies where one is dropped; the geometry is the same either way."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [2, 0, 0], [2, 0, 0]], np.float32)

    def geometry(tris):
        return snap.geometry_from_arrays(pos.copy(), np.array(tris, np.int32))

    for tris, dropped in (([[0, 1, 2]], False), ([[0, 1, 2], [3, 4, 5]], True)):
        results = []
        for owned in (False, True):
            g = geometry(tris)
            g.normals *= 2.0  # not unit: sanitized normalizes them (in place only where handed over)
            before = g.normals.copy()
            out = snap.sanitized(g, 1, 1, owned=owned)
            assert np.shares_memory(out.positions, g.positions) == (owned and not dropped)
            assert np.shares_memory(out.normals, g.normals) == (owned and not dropped)
            if not owned:
                np.testing.assert_array_equal(g.normals, before)  # the caller's arrays untouched
            np.testing.assert_allclose(np.linalg.norm(out.normals, axis=1), 1.0, rtol=1e-6)
            results.append(out)
        assert results[0].triangle_count == results[1].triangle_count == 1
        for name in ("positions", "triangles", "normals", "uvs", "material_index", "object_index"):
            np.testing.assert_array_equal(getattr(results[0], name), getattr(results[1], name))
