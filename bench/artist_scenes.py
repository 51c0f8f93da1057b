"""Artist-scene QA cases (what a Blender artist's scene holds), built as small .blend files.

    python bench/artist_scenes.py OUT_DIR [NAME ...]

writes OUT_DIR/NAME.blend (128x96) for every case in CASES (or the named ones): a floor, a wall, a
red cube and a blue ball under a sun and a grey world, each case changing one thing (instances,
modifiers, hair, holdouts, ray visibility, camera settings, node materials, film).
`bench/artist_sweep.py` renders them with HybridGI and Cycles and prints the errors. Run in its
own process: it resets the bpy module's file.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

# ruff: noqa: I001  (bpy must come first: importing it makes bmesh and mathutils importable)
import bpy
import bmesh
from mathutils import Vector

W, H = 128, 96


def reset():
    bpy.ops.wm.read_homefile(use_empty=True)
    s = bpy.context.scene
    s.render.resolution_x, s.render.resolution_y = W, H
    s.render.resolution_percentage = 100
    s.frame_start = s.frame_end = s.frame_current = 1
    return s


def mat(name, color=(0.8, 0.8, 0.8), rough=0.5):
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    b = m.node_tree.nodes["Principled BSDF"]
    b.inputs["Base Color"].default_value = (*color, 1.0)
    b.inputs["Roughness"].default_value = rough
    return m


def mesh_from(name, build):
    bm = bmesh.new()
    build(bm)
    me = bpy.data.meshes.new(name)
    bm.to_mesh(me)
    bm.free()
    return me


def cube_mesh(name="cube", size=1.0):
    return mesh_from(name, lambda bm: bmesh.ops.create_cube(bm, size=size))


def sphere_mesh(name="sphere", r=1.0, seg=32):
    me = mesh_from(name, lambda bm: bmesh.ops.create_uvsphere(bm, u_segments=seg, v_segments=seg // 2, radius=r,
                                                              calc_uvs=True))
    for p in me.polygons:
        p.use_smooth = True
    return me


def plane_mesh(name="plane", sx=1.0, sy=None):
    sy = sx if sy is None else sy
    me = bpy.data.meshes.new(name)
    me.from_pydata([(-sx / 2, -sy / 2, 0), (sx / 2, -sy / 2, 0), (sx / 2, sy / 2, 0), (-sx / 2, sy / 2, 0)], [],
                   [(0, 1, 2, 3)])
    me.uv_layers.new(name="UVMap")
    uv = me.uv_layers[0].data
    for i, c in enumerate([(0, 0), (1, 0), (1, 1), (0, 1)]):
        uv[i].uv = c
    return me


def obj(s, name, data, loc=(0, 0, 0), rot=(0, 0, 0), scale=(1, 1, 1), material=None, coll=None):
    o = bpy.data.objects.new(name, data)
    o.location, o.rotation_euler, o.scale = loc, rot, scale
    if material is not None and hasattr(data, "materials") and not data.materials:
        data.materials.append(material)
    (coll or s.collection).objects.link(o)
    return o


def camera(s, loc=(0.0, -6.5, 2.6), target=(0, 0.3, 0.7), lens=35.0):
    c = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    c.location = loc
    d = Vector(target) - Vector(loc)
    c.rotation_euler = d.to_track_quat("-Z", "Y").to_euler()
    c.data.lens = lens
    s.collection.objects.link(c)
    s.camera = c
    return c


def sun(s, strength=3.0, direction=(0.5, 0.6, -1.0)):
    o = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    o.data.energy = strength
    o.rotation_euler = Vector(direction).to_track_quat("-Z", "Y").to_euler()
    s.collection.objects.link(o)
    return o


def floor_node(kind, **inputs):
    """A new node of the floor's material with these input values (names with spaces: a dict)."""
    node = bpy.data.objects["floor"].active_material.node_tree.nodes.new(kind)
    for key, value in inputs.items():
        node.inputs[key].default_value = value
    return node


def floor_link(a, output, b, socket):
    """Link node a's `output` into node b's `socket` (or the floor material's node of that name)."""
    nt = bpy.data.objects["floor"].active_material.node_tree
    b = nt.nodes[b] if isinstance(b, str) else b
    nt.links.new(a.outputs[output], b.inputs[socket])


def world(s, color=(0.3, 0.3, 0.3)):
    w = bpy.data.worlds.new("world")
    w.use_nodes = True
    w.node_tree.nodes["Background"].inputs["Color"].default_value = (*color, 1.0)
    w.color = color
    s.world = w
    return w


def base(with_objects=True):
    s = reset()
    grey = mat("grey", (0.7, 0.7, 0.7))
    obj(s, "floor", plane_mesh("floor", 10.0), material=grey)
    obj(s, "wall", plane_mesh("wall", 10.0, 4.0), loc=(0, 2.5, 2.0), rot=(math.pi / 2, 0, 0), material=grey)
    if with_objects:
        obj(s, "cube", cube_mesh(), loc=(-1.2, 0.2, 0.5), rot=(0, 0, 0.4), material=mat("red", (0.8, 0.15, 0.1)))
        obj(s, "ball", sphere_mesh(r=0.6), loc=(1.1, 0.0, 0.6), material=mat("blue", (0.15, 0.35, 0.8)))
    camera(s)
    sun(s)
    world(s)
    return s


CASES = {}


def case(f):
    CASES[f.__name__] = f
    return f


@case
def c_base():
    base()


# ---------------- objects ----------------
@case
def collection_instance():
    s = base(False)
    coll = bpy.data.collections.new("props")
    s.collection.children.link(coll)
    obj(s, "cube", cube_mesh(), loc=(-1.2, 0.2, 0.5), rot=(0, 0, 0.4), material=mat("red", (0.8, 0.15, 0.1)), coll=coll)
    obj(s, "ball", sphere_mesh(r=0.6), loc=(1.1, 0.0, 0.6), material=mat("blue", (0.15, 0.35, 0.8)), coll=coll)
    # hide the source collection from the view layer (artists exclude it) and instance it twice
    s.view_layers[0].layer_collection.children["props"].exclude = True
    for i, (x, y, rz) in enumerate([(0.0, 0.0, 0.0), (0.3, 1.3, 0.5)]):
        e = bpy.data.objects.new(f"inst{i}", None)
        e.instance_type = "COLLECTION"
        e.instance_collection = coll
        e.location = (x, y, 0)
        e.rotation_euler = (0, 0, rz)
        e.scale = (0.8, 0.8, 0.8)
        s.collection.objects.link(e)


@case
def gn_instances():
    s = base(False)
    # a grid of points instancing a sphere via geometry nodes
    me = plane_mesh("grid", 3.0)
    o = obj(s, "scatter", me, loc=(0, 0, 0.35), material=mat("red", (0.8, 0.15, 0.1)))
    src = obj(s, "src_ball", sphere_mesh(r=0.3, seg=16), loc=(0, 0, -5), material=mat("blue", (0.15, 0.35, 0.8)))
    src.hide_render = True
    tree = bpy.data.node_groups.new("inst", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    tree.nodes.new("NodeGroupInput")
    n_out = tree.nodes.new("NodeGroupOutput")
    grid = tree.nodes.new("GeometryNodeMeshGrid")
    grid.inputs["Size X"].default_value = 3.0
    grid.inputs["Size Y"].default_value = 2.0
    grid.inputs["Vertices X"].default_value = 4
    grid.inputs["Vertices Y"].default_value = 3
    pts = tree.nodes.new("GeometryNodeMeshToPoints")
    iop = tree.nodes.new("GeometryNodeInstanceOnPoints")
    info = tree.nodes.new("GeometryNodeObjectInfo")
    info.inputs["Object"].default_value = src
    rot = tree.nodes.new("FunctionNodeRandomValue")
    rot.data_type = "FLOAT_VECTOR"
    tree.links.new(grid.outputs["Mesh"], pts.inputs["Mesh"])
    tree.links.new(pts.outputs["Points"], iop.inputs["Points"])
    tree.links.new(info.outputs["Geometry"], iop.inputs["Instance"])
    tree.links.new(rot.outputs["Value"], iop.inputs["Rotation"])
    tree.links.new(iop.outputs["Instances"], n_out.inputs["Geometry"])
    mod = o.modifiers.new("GN", "NODES")
    mod.node_group = tree


@case
def modifiers():
    s = base(False)
    c = obj(s, "cube", cube_mesh(size=0.6), loc=(-2.0, 0.2, 0.3), material=mat("red", (0.8, 0.15, 0.1)))
    a = c.modifiers.new("arr", "ARRAY")
    a.count = 4
    a.relative_offset_displace = (1.4, 0, 0)
    c2 = obj(s, "half", cube_mesh(size=0.8), loc=(0.0, -0.8, 0.4), material=mat("green", (0.2, 0.7, 0.2)))
    m = c2.modifiers.new("mir", "MIRROR")
    m.use_axis = (False, True, False)
    m.mirror_object = None
    b = obj(s, "blob", cube_mesh(size=1.0), loc=(1.2, 0.8, 0.6), material=mat("blue", (0.15, 0.35, 0.8)))
    sub = b.modifiers.new("sub", "SUBSURF")
    sub.levels = sub.render_levels = 2


@case
def text_curve():
    s = base(False)
    t = bpy.data.curves.new("txt", "FONT")
    t.body = "HGI"
    t.extrude = 0.15
    t.bevel_depth = 0.03
    t.size = 1.4
    o = obj(s, "text", t, loc=(-1.5, 0.0, 0.0), rot=(math.pi / 2, 0, 0), material=mat("red", (0.8, 0.15, 0.1)))
    cu = bpy.data.curves.new("pipe", "CURVE")
    cu.dimensions = "3D"
    cu.bevel_depth = 0.12
    sp = cu.splines.new("BEZIER")
    sp.bezier_points.add(2)
    for p, co in zip(sp.bezier_points, [(-2, -1, 0.2), (0, -1.5, 1.2), (2, -1, 0.2)], strict=True):
        p.co = co
        p.handle_left_type = p.handle_right_type = "AUTO"
    obj(s, "pipe", cu, material=mat("blue", (0.15, 0.35, 0.8)))
    del o


@case
def hair_curves():
    s = base()
    hc = bpy.data.hair_curves.new("hair")
    rng = np.random.default_rng(1)
    n, k = 400, 6
    hc.add_curves([k] * n)
    pos = np.zeros((n, k, 3), np.float32)
    base_pts = np.column_stack([rng.uniform(-0.9, 0.9, n) - 0.2, rng.uniform(-1.0, -0.2, n), np.zeros(n)])
    for j in range(k):
        pos[:, j] = base_pts + np.array([0.0, 0.0, 0.12 * j]) + rng.normal(0, 0.01, (n, 3))
    hc.position_data.foreach_set("vector", pos.ravel())
    rad = hc.attributes.get("radius") or hc.attributes.new("radius", "FLOAT", "POINT")
    rad.data.foreach_set("value", np.full(n * k, 0.02, np.float32))
    o = obj(s, "grass", hc, material=mat("green", (0.2, 0.7, 0.2)))
    del o


@case
def metaball():
    s = base(False)
    mb = bpy.data.metaballs.new("mb")
    mb.resolution = mb.render_resolution = 0.1
    for x in (-0.5, 0.3):
        e = mb.elements.new()
        e.co = (x, 0, 0)
        e.radius = 0.7
    obj(s, "meta", mb, loc=(0, 0, 0.6), material=mat("blue", (0.15, 0.35, 0.8)))


def _flag(name, prop, value):
    def f():
        base()
        setattr(bpy.data.objects[name], prop, value)
    f.__name__ = f"{prop}_off" if value is False else prop
    CASES[f.__name__] = f


_flag("cube", "visible_shadow", False)
_flag("cube", "visible_diffuse", False)
_flag("cube", "visible_glossy", False)
_flag("cube", "is_holdout", True)


def _ball_in_collection(name):
    """The base scene with the ball moved into a collection of its own: its layer collection."""
    s = base()
    coll = bpy.data.collections.new(name)
    s.collection.children.link(coll)
    ball = bpy.data.objects["ball"]
    s.collection.objects.unlink(ball)
    coll.objects.link(ball)
    return s.view_layers[0].layer_collection.children[name]


@case
def holdout_collection():
    _ball_in_collection("ho").holdout = True


@case
def indirect_only_collection():
    _ball_in_collection("io").indirect_only = True


@case
def negative_scale():
    base()
    bpy.data.objects["cube"].scale = (-1, 1, 1)
    bpy.data.objects["ball"].scale = (1, -1.3, 1)


@case
def no_material():
    base()
    bpy.data.objects["cube"].data.materials.clear()


@case
def shadow_catcher():
    base()
    bpy.data.objects["floor"].is_shadow_catcher = True


# ---------------- camera ----------------
@case
def ortho():
    s = base()
    s.camera.data.type = "ORTHO"
    s.camera.data.ortho_scale = 7.0


@case
def shift():
    s = base()
    s.camera.data.shift_x = 0.15
    s.camera.data.shift_y = -0.1


@case
def sensor_vertical_portrait():
    s = base()
    s.render.resolution_x, s.render.resolution_y = 72, 128
    s.camera.data.sensor_fit = "VERTICAL"
    s.camera.data.sensor_height = 24.0


@case
def sensor_horizontal_portrait():
    s = base()
    s.render.resolution_x, s.render.resolution_y = 72, 128
    s.camera.data.sensor_fit = "HORIZONTAL"


@case
def clip_start():
    s = base()
    s.camera.data.clip_start = 6.5  # cuts the near floor and part of the cube
    s.camera.data.clip_end = 100.0


@case
def clip_end():
    s = base()
    s.camera.data.clip_end = 7.5  # the wall and far floor are cut away


@case
def res_percent():
    s = base()
    s.render.resolution_x, s.render.resolution_y = 256, 192
    s.render.resolution_percentage = 50


@case
def pixel_aspect():
    s = base()
    s.render.pixel_aspect_x = 2.0


@case
def dof():
    s = base()
    s.camera.data.dof.use_dof = True
    s.camera.data.dof.aperture_fstop = 0.5
    s.camera.data.dof.focus_distance = 6.0


# ---------------- materials ----------------
OUT_DIR = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("out/artist_scenes")


def saved_image(img, colorspace=None):
    """Write a generated image to a PNG beside the scenes and load it back (pack() keeps nothing)."""
    path = OUT_DIR / f"{img.name}.png"
    img.filepath_raw = str(path)
    img.file_format = "PNG"
    img.save()
    bpy.data.images.remove(img)
    out = bpy.data.images.load(str(path))
    if colorspace:
        out.colorspace_settings.name = colorspace
    return out


def _leaf_image(alpha_hole=True):
    img = bpy.data.images.new("leaf", 64, 64, alpha=True)
    px = np.zeros((64, 64, 4), np.float32)
    yy, xx = np.mgrid[0:64, 0:64]
    inside = ((xx - 32) ** 2 / 28 ** 2 + (yy - 32) ** 2 / 18 ** 2) < 1
    px[..., 0], px[..., 1], px[..., 2] = 0.1, 0.6, 0.1
    px[..., 3] = inside.astype(np.float32)
    img.pixels.foreach_set(px.ravel())
    return saved_image(img)


def _leaf_plane(s, m):
    # a vertical plane between camera and wall, 2.5 x 2.5, with leaf-shaped alpha
    return obj(s, "leaf", plane_mesh("leaf", 2.5), loc=(0.0, -1.0, 1.3), rot=(math.pi / 2, 0, 0), material=m)


@case
def alpha_image_principled():
    s = base()
    m = mat("leafmat", (0.1, 0.6, 0.1))
    nt = m.node_tree
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = _leaf_image()
    b = nt.nodes["Principled BSDF"]
    nt.links.new(tex.outputs["Color"], b.inputs["Base Color"])
    nt.links.new(tex.outputs["Alpha"], b.inputs["Alpha"])
    _leaf_plane(s, m)


@case
def mix_transparent():
    s = base()
    m = mat("leafmix", (0.1, 0.6, 0.1))
    nt = m.node_tree
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = _leaf_image()
    b = nt.nodes["Principled BSDF"]
    nt.links.new(tex.outputs["Color"], b.inputs["Base Color"])
    mix = nt.nodes.new("ShaderNodeMixShader")
    tr = nt.nodes.new("ShaderNodeBsdfTransparent")
    nt.links.new(tex.outputs["Alpha"], mix.inputs["Fac"])
    nt.links.new(tr.outputs[0], mix.inputs[1])
    nt.links.new(b.outputs[0], mix.inputs[2])
    nt.links.new(mix.outputs[0], nt.nodes["Material Output"].inputs["Surface"])
    _leaf_plane(s, m)


@case
def alpha_constant_half():
    base()
    m = bpy.data.objects["ball"].active_material
    m.node_tree.nodes["Principled BSDF"].inputs["Alpha"].default_value = 0.4


@case
def subsurface():
    base()
    b = bpy.data.objects["ball"].active_material.node_tree.nodes["Principled BSDF"]
    b.inputs["Base Color"].default_value = (0.8, 0.5, 0.4, 1)
    b.inputs["Subsurface Weight"].default_value = 1.0
    b.inputs["Subsurface Radius"].default_value = (1.0, 0.3, 0.2)
    b.inputs["Subsurface Scale"].default_value = 0.2


@case
def metallic_texture():
    base()
    m = bpy.data.objects["floor"].active_material
    nt = m.node_tree
    chk = nt.nodes.new("ShaderNodeTexChecker")
    chk.inputs["Scale"].default_value = 4.0
    chk.inputs["Color1"].default_value = (1, 1, 1, 1)
    chk.inputs["Color2"].default_value = (0, 0, 0, 1)
    nt.links.new(chk.outputs["Fac"], nt.nodes["Principled BSDF"].inputs["Metallic"])


@case
def roughness_texture():
    base()
    m = bpy.data.objects["floor"].active_material
    nt = m.node_tree
    chk = nt.nodes.new("ShaderNodeTexChecker")
    chk.inputs["Scale"].default_value = 4.0
    nt.links.new(chk.outputs["Fac"], nt.nodes["Principled BSDF"].inputs["Roughness"])


@case
def color_attribute():
    base()
    me = bpy.data.objects["ball"].data
    ca = me.color_attributes.new("Col", "FLOAT_COLOR", "POINT")
    for i, v in enumerate(me.vertices):
        ca.data[i].color = (0.9 if v.co.z > 0 else 0.1, 0.3, 0.9 if v.co.z <= 0 else 0.1, 1)
    m = bpy.data.objects["ball"].active_material
    nt = m.node_tree
    a = nt.nodes.new("ShaderNodeVertexColor")
    a.layer_name = "Col"
    nt.links.new(a.outputs["Color"], nt.nodes["Principled BSDF"].inputs["Base Color"])


@case
def holdout_shader():
    base()
    m = bpy.data.objects["ball"].active_material
    nt = m.node_tree
    h = nt.nodes.new("ShaderNodeHoldout")
    nt.links.new(h.outputs[0], nt.nodes["Material Output"].inputs["Surface"])


@case
def emission_shader():
    base()
    m = bpy.data.objects["ball"].active_material
    nt = m.node_tree
    e = nt.nodes.new("ShaderNodeEmission")
    e.inputs["Color"].default_value = (1.0, 0.6, 0.2, 1)
    e.inputs["Strength"].default_value = 5.0
    nt.links.new(e.outputs[0], nt.nodes["Material Output"].inputs["Surface"])


@case
def world_is_camera_ray():
    s = base()
    w = s.world
    nt = w.node_tree
    bg = nt.nodes["Background"]
    bg.inputs["Color"].default_value = (1.0, 0.9, 0.7, 1)
    bg.inputs["Strength"].default_value = 1.0
    bg2 = nt.nodes.new("ShaderNodeBackground")
    bg2.inputs["Color"].default_value = (0.05, 0.05, 0.08, 1)
    lp = nt.nodes.new("ShaderNodeLightPath")
    mix = nt.nodes.new("ShaderNodeMixShader")
    nt.links.new(lp.outputs["Is Camera Ray"], mix.inputs["Fac"])
    nt.links.new(bg.outputs[0], mix.inputs[1])
    nt.links.new(bg2.outputs[0], mix.inputs[2])
    nt.links.new(mix.outputs[0], nt.nodes["World Output"].inputs["Surface"])


@case
def world_sky_texture():
    s = base()
    nt = s.world.node_tree
    sky = nt.nodes.new("ShaderNodeTexSky")
    nt.links.new(sky.outputs[0], nt.nodes["Background"].inputs["Color"])
    nt.nodes["Background"].inputs["Strength"].default_value = 0.3


@case
def material_light_path_shadow():
    """Common 'glass that doesn't block light' trick: Mix(Principled, Transparent) by Is Shadow Ray."""
    s = base()
    m = mat("pane", (0.8, 0.8, 0.8))
    nt = m.node_tree
    lp = nt.nodes.new("ShaderNodeLightPath")
    mix = nt.nodes.new("ShaderNodeMixShader")
    tr = nt.nodes.new("ShaderNodeBsdfTransparent")
    nt.links.new(lp.outputs["Is Shadow Ray"], mix.inputs["Fac"])
    nt.links.new(nt.nodes["Principled BSDF"].outputs[0], mix.inputs[1])
    nt.links.new(tr.outputs[0], mix.inputs[2])
    nt.links.new(mix.outputs[0], nt.nodes["Material Output"].inputs["Surface"])
    obj(s, "pane", plane_mesh("pane", 3.0), loc=(0.5, 0.3, 2.4), material=m)


# ---------------- film / colour ----------------
@case
def filmic():
    s = base()
    s.view_settings.view_transform = "Filmic"


@case
def film_transparent():
    s = base()
    s.render.film_transparent = True


@case
def filter_width_wide():
    s = base()
    s.cycles.filter_width = 3.0


@case
def huge_scale():
    s = base()
    root = bpy.data.objects.new("root", None)
    s.collection.objects.link(root)
    for o in list(s.objects):
        if o.parent is None and o is not root:
            o.parent = root
    root.scale = (1000.0,) * 3
    s.camera.data.clip_end = 1e6
    s.camera.data.clip_start = 10.0


@case
def tiny_scale():
    s = base()
    root = bpy.data.objects.new("root", None)
    s.collection.objects.link(root)
    for o in list(s.objects):
        if o.parent is None and o is not root:
            o.parent = root
    root.scale = (0.001,) * 3
    s.camera.data.clip_start = 1e-5
    s.camera.data.clip_end = 1.0
    s.world.light_settings.distance = 0.001




@case
def metallic_const():
    base()
    bpy.data.objects["floor"].active_material.node_tree.nodes["Principled BSDF"].inputs["Metallic"].default_value = 1.0


@case
def metallic_image():
    """A metallic mask image (Non-Color) straight into Metallic: the common PBR asset wiring."""
    base()
    m = bpy.data.objects["floor"].active_material
    nt = m.node_tree
    img = bpy.data.images.new("metal_mask", 32, 32, alpha=False)
    px = np.zeros((32, 32, 4), np.float32)
    px[..., 3] = 1
    px[:, 16:, :3] = 1.0
    img.pixels.foreach_set(px.ravel())
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = saved_image(img, "Non-Color")
    tex.interpolation = "Closest"
    nt.links.new(tex.outputs["Color"], nt.nodes["Principled BSDF"].inputs["Metallic"])


@case
def pbr_images():
    """Base colour, metallic mask and normal map images on the floor (a downloaded PBR asset)."""
    base()
    nt = bpy.data.objects["floor"].active_material.node_tree
    b = nt.nodes["Principled BSDF"]
    yy, xx = np.mgrid[0:64, 0:64]
    col = np.ones((64, 64, 4), np.float32)
    col[..., 0] = 0.8
    col[..., 1] = 0.6 + 0.2 * ((xx // 8) % 2)
    col[..., 2] = 0.4
    ci = bpy.data.images.new("pbr_col", 64, 64)
    ci.pixels.foreach_set(col.ravel())
    met = np.ones((64, 64, 4), np.float32)
    met[..., :3] = (((xx // 16) + (yy // 16)) % 2)[..., None]
    mi = bpy.data.images.new("pbr_met", 64, 64)
    mi.pixels.foreach_set(met.ravel())
    nor = np.ones((64, 64, 4), np.float32)
    ang = np.sin(xx / 64 * 2 * np.pi * 8) * 0.5
    nor[..., 0] = 0.5 + 0.5 * ang
    nor[..., 1] = 0.5
    nor[..., 2] = 0.5 + 0.5 * np.sqrt(1 - ang ** 2)
    ni = bpy.data.images.new("pbr_nor", 64, 64)
    ni.pixels.foreach_set(nor.ravel())
    tc = nt.nodes.new("ShaderNodeTexImage")
    tc.image = saved_image(ci)
    tm = nt.nodes.new("ShaderNodeTexImage")
    tm.image = saved_image(mi, "Non-Color")
    tn = nt.nodes.new("ShaderNodeTexImage")
    tn.image = saved_image(ni, "Non-Color")
    nm = nt.nodes.new("ShaderNodeNormalMap")
    nt.links.new(tc.outputs["Color"], b.inputs["Base Color"])
    nt.links.new(tm.outputs["Color"], b.inputs["Metallic"])
    nt.links.new(tn.outputs["Color"], nm.inputs["Color"])
    nt.links.new(nm.outputs["Normal"], b.inputs["Normal"])
    me = bpy.data.objects["floor"].data
    for loop in me.uv_layers[0].data:
        loop.uv = loop.uv * 3.0


@case
def particle_hair():
    """Old-style hair: a particle system of type HAIR on a floor patch (assets before Curves)."""
    s = base()
    patch = obj(s, "patch", plane_mesh("patch", 1.8), loc=(-0.2, -0.8, 0.01), material=mat("green", (0.2, 0.7, 0.2)))
    mod = patch.modifiers.new("hair", "PARTICLE_SYSTEM")
    ps = mod.particle_system.settings
    ps.type = "HAIR"
    ps.count = 400
    ps.hair_length = 0.6
    ps.root_radius = 1.0
    ps.radius_scale = 0.04
    ps.material_slot = "green"


@case
def displacement_bump():
    """A height texture into the Material Output's Displacement (Cycles' default: Bump Only)."""
    base()
    disp = floor_node("ShaderNodeDisplacement", Scale=0.3)
    floor_link(floor_node("ShaderNodeTexWave", Scale=3.0), "Fac", disp, "Height")
    floor_link(disp, "Displacement", "Material Output", "Displacement")


@case
def multi_material():
    """One mesh, two material slots (faces alternate)."""
    base()
    cube = bpy.data.objects["cube"]
    cube.data.materials.append(mat("yellow", (0.9, 0.8, 0.1)))
    for i, p in enumerate(cube.data.polygons):
        p.material_index = i % 2


@case
def displacement_image():
    """A height image into a Displacement node on the Material Output (Bump Only, the default)."""
    base()
    m = bpy.data.objects["floor"].active_material
    nt = m.node_tree
    xx = np.arange(64)
    h = np.ones((64, 64, 4), np.float32)
    h[..., :3] = (0.5 + 0.5 * np.sin(xx / 64 * 2 * np.pi * 4))[None, :, None]
    img = bpy.data.images.new("height", 64, 64)
    img.pixels.foreach_set(h.ravel())
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = saved_image(img, "Non-Color")
    disp = nt.nodes.new("ShaderNodeDisplacement")
    disp.inputs["Scale"].default_value = 0.3
    nt.links.new(tex.outputs["Color"], disp.inputs["Height"])
    nt.links.new(disp.outputs["Displacement"], nt.nodes["Material Output"].inputs["Displacement"])


@case
def mix_mask():
    """Two surfaces on the floor, the grey and a blue, mixed by a checker mask (dirt, wear)."""
    base()
    mix = floor_node("ShaderNodeMixShader")
    floor_link(floor_node("ShaderNodeTexChecker", Scale=5.0), "Fac", mix, "Fac")
    floor_link(bpy.data.objects["floor"].active_material.node_tree.nodes["Principled BSDF"], 0, mix, 1)
    floor_link(floor_node("ShaderNodeBsdfPrincipled", **{"Base Color": (0.1, 0.3, 0.8, 1.0)}), 0, mix, 2)
    floor_link(mix, 0, "Material Output", "Surface")


@case
def bump_noise():
    """A Noise texture into a Bump node on the floor's Normal (procedural bump)."""
    base()
    bump = floor_node("ShaderNodeBump", Distance=1.0)
    floor_link(floor_node("ShaderNodeTexNoise", Scale=2.0), "Fac", bump, "Height")
    floor_link(bump, "Normal", "Principled BSDF", "Normal")


@case
def dof_strong():
    """A wide aperture (f/0.05) focused on the cube over a checkered floor."""
    s = base()
    floor_link(floor_node("ShaderNodeTexChecker", Scale=30.0), "Color", "Principled BSDF", "Base Color")
    s.camera.data.dof.use_dof = True
    s.camera.data.dof.aperture_fstop = 0.05
    s.camera.data.dof.focus_object = bpy.data.objects["cube"]


@case
def sphere_lamp():
    """A point lamp of radius 1 m with Soft Falloff off (a glowing sphere) instead of the sun."""
    s = base()
    bpy.data.objects.remove(bpy.data.objects["sun"])
    lamp = bpy.data.objects.new("lamp", bpy.data.lights.new("lamp", "POINT"))
    lamp.data.energy, lamp.data.shadow_soft_size, lamp.data.use_soft_falloff = 600.0, 1.0, False
    lamp.location = (1.0, -1.0, 2.2)
    s.collection.objects.link(lamp)


if __name__ == "__main__":
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    names = sys.argv[2:] or list(CASES)
    for n in names:
        CASES[n]()
        bpy.ops.wm.save_as_mainfile(filepath=str(out / f"{n}.blend"))
        print("built", n)

