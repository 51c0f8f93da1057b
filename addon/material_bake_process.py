"""The bake process of `material_bake` (run as a script by Blender or the bpy module; never
imported by the add-on): argv = the jobs' JSON (naming each material's library .blend), the folder of the
jobs' mesh arrays and of the baked textures. Each job: a mesh built from the arrays (corner
order kept), the material with its socket's source wired into an Emission shader, a float image
baked with type EMIT over the atlas UV map. A job that fails writes KEY.err and the next runs."""

import json
import os
import sys
import time
import traceback

import bpy
import numpy as np

jobs_path, folder = sys.argv[-2:]
spec = json.load(open(jobs_path))
materials = {}
for blend in sorted({job["blend"] for job in spec["jobs"]}):
    with bpy.data.libraries.load(blend) as (data_from, data_to):
        data_to.materials = list(data_from.materials)
    for material in data_to.materials:
        materials[(blend, material.name)] = material
scene = bpy.context.scene
for obj in list(scene.objects):
    bpy.data.objects.remove(obj)
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.samples = int(spec["samples"])
scene.cycles.use_denoising = False
scene.cycles.use_adaptive_sampling = False
scene.render.bake.margin = int(spec["margin"])
scene.render.bake.margin_type = "EXTEND"
scene.render.bake.use_clear = True


def source_socket(tree, node_name, socket_id):
    socket = next(s for s in tree.nodes[node_name].inputs if s.identifier == socket_id)
    while socket.is_linked:
        link = socket.links[0]
        if link.from_node.type != "REROUTE":
            return link.from_socket
        socket = link.from_node.inputs[0]
    raise RuntimeError(f"input {socket_id} of {node_name} is not linked")


#: The pseudo-input of a shader's emission (`sync.EMISSION_BAKE`): colour and strength wired into one
#: Emission shader, so the bake is their product, HDR.
EMISSION_INPUTS = {"BSDF_PRINCIPLED": ("Emission Color", "Emission Strength"), "EMISSION": ("Color", "Strength")}


#: Scalar inputs baked as a grey (`sync.BAKED_SCALARS`).
SCALARS = {"Metallic", "Roughness", "Alpha", "Fac"}


def wire(tree, target, node_name, socket_name):
    """Feed input `socket_name` of node `node_name` into `target`: its source, or its value."""
    socket = tree.nodes[node_name].inputs[socket_name]
    while socket.is_linked and not socket.links[0].is_muted:
        link = socket.links[0]
        if link.from_node.type != "REROUTE":
            if not link.from_node.mute:
                tree.links.new(link.from_socket, target)
                return
            break
        socket = link.from_node.inputs[0]
    socket = tree.nodes[node_name].inputs[socket_name]
    value = socket.default_value
    target.default_value = tuple(value) if hasattr(value, "__len__") else value


def constant_object_info(tree, values):
    """Feed the Object Info nodes' outputs that `values` gives (`sync.object_values`) from
    constant nodes: the bake's own object is not the one the texture is for."""
    for node in [n for n in tree.nodes if n.type == "OBJECT_INFO"]:
        for out in node.outputs:
            if not out.is_linked:
                continue
            if out.name == "Random" and "random" in values:
                const = tree.nodes.new("ShaderNodeValue")
                const.outputs[0].default_value = float(values["random"])
            elif out.name == "Location" and "location" in values:
                const = tree.nodes.new("ShaderNodeCombineXYZ")
                for i, v in enumerate(values["location"]):
                    const.inputs[i].default_value = float(v)
            elif out.name == "Color" and "color" in values:
                const = tree.nodes.new("ShaderNodeRGB")
                const.outputs[0].default_value = tuple(float(v) for v in values["color"])
            elif out.name == "Alpha" and "color" in values:
                const = tree.nodes.new("ShaderNodeValue")
                const.outputs[0].default_value = float(values["color"][3])
            elif out.name == "Object Index" and "object_index" in values:
                const = tree.nodes.new("ShaderNodeValue")
                const.outputs[0].default_value = float(values["object_index"])
            else:
                continue
            for link in list(out.links):
                tree.links.new(const.outputs[0], link.to_socket)


def run(job):
    arrays = np.load(os.path.join(folder, job["key"] + ".npz"))
    positions = arrays["positions"].astype(np.float64)
    n = positions.shape[0]
    mesh = bpy.data.meshes.new("hybridgi_bake")
    mesh.vertices.add(n)
    mesh.vertices.foreach_set("co", positions.ravel())
    mesh.loops.add(n)
    mesh.loops.foreach_set("vertex_index", np.arange(n, dtype=np.int32))
    mesh.polygons.add(n // 3)
    mesh.polygons.foreach_set("loop_start", np.arange(0, n, 3, dtype=np.int32))
    mesh.polygons.foreach_set("loop_total", np.full(n // 3, 3, np.int32))
    mesh.update()
    if "normals" in arrays.files:  # shading normals: box mapping and Normal coordinates read them
        try:
            mesh.polygons.foreach_set("use_smooth", np.ones(n // 3, bool))
            mesh.normals_split_custom_set(arrays["normals"].astype(np.float64).tolist())
        except (AttributeError, RuntimeError, TypeError):
            pass  # flat facet normals then
    for i, name in enumerate(job["uv_maps"]):
        layer = mesh.uv_layers.new(name=name)
        layer.uv.foreach_set("vector", arrays[f"uv{i}"].astype(np.float32).ravel())
    atlas = mesh.uv_layers.new(name="hybridgi_atlas")
    atlas.uv.foreach_set("vector", arrays["atlas"].astype(np.float32).ravel())
    for i, name in enumerate(job["colors"]):
        attr = mesh.color_attributes.new(name, "FLOAT_COLOR", "CORNER")
        attr.data.foreach_set("color", arrays[f"color{i}"].astype(np.float32).ravel())
    mesh.uv_layers.active = atlas  # the bake's target
    render_uv = mesh.uv_layers.get(job["render_uv"] or "") or atlas
    render_uv.active_render = True  # what nodes without a UV input read
    mesh.use_auto_texspace = False
    mesh.texspace_location, mesh.texspace_size = job["texspace"]
    material = materials[(job["blend"], job["material"])].copy()
    mesh.materials.append(material)
    tree = material.node_tree
    if job.get("object_values"):
        constant_object_info(tree, job["object_values"])
    output = tree.get_output_node("CYCLES")
    emission = tree.nodes.new("ShaderNodeEmission")
    emission.inputs["Strength"].default_value = 1.0
    if job["socket"] == "emission":
        colour, strength = EMISSION_INPUTS[tree.nodes[job["node"]].type]
        wire(tree, emission.inputs["Color"], job["node"], colour)
        wire(tree, emission.inputs["Strength"], job["node"], strength)
    elif job["socket"] in SCALARS:
        # A float input: Blender's own conversion of what feeds it (a colour's luminance), clamped
        # as the BSDF clamps it, as a grey.
        scalar = tree.nodes.new("ShaderNodeMath")
        scalar.operation, scalar.use_clamp = "ADD", True
        scalar.inputs[1].default_value = 0.0
        tree.links.new(source_socket(tree, job["node"], job["socket"]), scalar.inputs[0])
        tree.links.new(scalar.outputs[0], emission.inputs["Color"])
    else:
        tree.links.new(source_socket(tree, job["node"], job["socket"]), emission.inputs["Color"])
    tree.links.new(emission.outputs[0], output.inputs["Surface"])
    if output.inputs.get("Displacement") is not None:
        for link in list(output.inputs["Displacement"].links):
            tree.links.remove(link)
    size = int(job["size"])
    image = bpy.data.images.new("hybridgi_bake", size, size, alpha=False, float_buffer=True)
    target = tree.nodes.new("ShaderNodeTexImage")
    target.image = image
    for node in tree.nodes:
        node.select = False
    target.select = True
    tree.nodes.active = target
    obj = bpy.data.objects.new("hybridgi_bake", mesh)
    scene.collection.objects.link(obj)
    for other in scene.objects:
        other.select_set(other is obj)
    bpy.context.view_layer.objects.active = obj
    # The atlas named as the target: Blender bakes into the render UV map otherwise, which is the
    # mesh's own where it has one (its UV layout, not the atlas the G-buffer reads).
    bpy.ops.object.bake(type="EMIT", margin=int(spec["margin"]), use_clear=True, uv_layer="hybridgi_atlas")
    pixels = np.empty(size * size * 4, np.float32)
    image.pixels.foreach_get(pixels)
    np.save(os.path.join(folder, job["key"] + ".npy"), pixels.reshape(size, size, 4)[..., :3])
    bpy.data.objects.remove(obj)


for job in spec["jobs"]:
    try:
        t0 = time.perf_counter()
        run(job)
        with open(os.path.join(folder, job["key"] + ".s"), "w") as f:
            f.write(f"{time.perf_counter() - t0:.3f}")
    except Exception:  # noqa: BLE001  one job's failure is reported by its .err file, the next runs
        with open(os.path.join(folder, job["key"] + ".err"), "w") as f:
            f.write(traceback.format_exc())
