"""Small scenes of the glossy shader nodes real Blender assets use (a bare Glossy BSDF, the classic
Mix(Diffuse, Glossy) plastic with a Fresnel or Layer Weight factor, Add Shader, the Metallic
BSDF, Glass; a Principled metal with an edge tint, a Principled glass), built by a bpy subprocess: a smooth sphere on a floor under an area lamp in a black
world, so every glossy light is the lamp's. Shared by tests/test_glossy_nodes.py and
bench/glossy_nodes.py (which measures them against Cycles)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

KINDS = ("glossy", "mix_fresnel", "mix_layer_weight", "add", "metallic", "glass", "tinted_metal", "principled_glass")

SCENE = textwrap.dedent("""
    import sys, bpy
    from mathutils import Vector
    kind, path = sys.argv[-2], sys.argv[-1]
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene

    def material(name):
        m = bpy.data.materials.new(name)
        m.use_nodes = True
        tree = m.node_tree
        tree.nodes.remove(tree.nodes["Principled BSDF"])
        return m, tree, tree.nodes["Material Output"].inputs["Surface"]

    def node(tree, kind, **inputs):
        n = tree.nodes.new(kind)
        for key, value in inputs.items():
            if key.startswith("_"):
                setattr(n, key[1:], value)
            else:
                n.inputs[key].default_value = value
        return n

    def glossy(tree, colour, roughness, distribution="MULTI_GGX"):
        return node(tree, "ShaderNodeBsdfGlossy", Color=(*colour, 1.0), Roughness=roughness, _distribution=distribution)

    def diffuse(tree, colour):
        return node(tree, "ShaderNodeBsdfDiffuse", Color=(*colour, 1.0))

    def plastic(name, colour, factor):
        m, tree, out = material(name)
        mix = tree.nodes.new("ShaderNodeMixShader")
        tree.links.new(diffuse(tree, colour).outputs[0], mix.inputs[1])
        tree.links.new(glossy(tree, (1.0, 1.0, 1.0), 0.3).outputs[0], mix.inputs[2])
        if factor == "fresnel":
            tree.links.new(node(tree, "ShaderNodeFresnel", IOR=1.45).outputs[0], mix.inputs["Fac"])
        else:
            weight = node(tree, "ShaderNodeLayerWeight", Blend=0.3)
            tree.links.new(weight.outputs[factor], mix.inputs["Fac"])
        tree.links.new(mix.outputs[0], out)
        return m

    def single(name, make):
        m, tree, out = material(name)
        tree.links.new(make(tree).outputs[0], out)
        return m

    if kind == "glossy":
        ball = single("ball", lambda t: glossy(t, (0.9, 0.7, 0.4), 0.35))
        floor = single("floor", lambda t: glossy(t, (0.5, 0.6, 0.7), 0.5, "BECKMANN"))
    elif kind == "mix_fresnel":
        ball, floor = plastic("ball", (0.2, 0.4, 0.8), "fresnel"), plastic("floor", (0.6, 0.5, 0.4), "fresnel")
    elif kind == "mix_layer_weight":
        ball, floor = plastic("ball", (0.2, 0.4, 0.8), "Facing"), plastic("floor", (0.6, 0.5, 0.4), "Fresnel")
    elif kind == "add":
        def added(tree):
            add = tree.nodes.new("ShaderNodeAddShader")
            tree.links.new(diffuse(tree, (0.5, 0.3, 0.2)).outputs[0], add.inputs[0])
            tree.links.new(glossy(tree, (0.25, 0.25, 0.25), 0.4, "GGX").outputs[0], add.inputs[1])
            return add
        ball = single("ball", added)
        floor = single("floor", lambda t: diffuse(t, (0.6, 0.5, 0.4)))
    elif kind == "metallic":
        ball = single("ball", lambda t: node(t, "ShaderNodeBsdfMetallic", Roughness=0.35, _fresnel_type="F82",
                                              **{"Base Color": (0.9, 0.6, 0.3, 1.0), "Edge Tint": (0.9, 0.8, 0.7, 1.0)}))
        floor = single("floor", lambda t: node(t, "ShaderNodeBsdfMetallic", Roughness=0.5,
                                               _fresnel_type="PHYSICAL_CONDUCTOR"))
    elif kind == "principled_glass":
        # 40% transmission: under the clear threshold (`snapshot.Material.clear`), so the glass
        # closure's reflection is rendered over the diffuse base.
        ball = single("ball", lambda t: node(t, "ShaderNodeBsdfPrincipled", Roughness=0.3,
                                              **{"Transmission Weight": 0.4}))
        floor = single("floor", lambda t: diffuse(t, (0.6, 0.5, 0.4)))
    elif kind == "tinted_metal":
        ball = single("ball", lambda t: node(t, "ShaderNodeBsdfPrincipled", Metallic=1.0, Roughness=0.35,
                                              **{"Base Color": (0.9, 0.6, 0.3, 1.0),
                                                 "Specular Tint": (0.4, 0.7, 1.0, 1.0)}))
        floor = single("floor", lambda t: diffuse(t, (0.6, 0.5, 0.4)))
    else:
        ball = single("ball", lambda t: node(t, "ShaderNodeBsdfGlass", Roughness=0.3, IOR=1.5, _distribution="GGX"))
        floor = single("floor", lambda t: diffuse(t, (0.6, 0.5, 0.4)))

    bpy.ops.mesh.primitive_plane_add(size=12.0)
    bpy.context.active_object.data.materials.append(floor)
    bpy.ops.mesh.primitive_uv_sphere_add(radius=1.0, location=(0.0, 0.0, 1.0), segments=64, ring_count=32)
    bpy.ops.object.shade_smooth()
    bpy.context.active_object.data.materials.append(ball)
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.location = (0.0, -7.0, 3.0)
    camera.rotation_euler = (Vector((0.0, 0.0, 0.8)) - camera.location).to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(camera)
    scene.camera = camera
    lamp = bpy.data.objects.new("lamp", bpy.data.lights.new("lamp", "AREA"))
    lamp.data.energy = 600.0
    lamp.data.size = 2.0
    lamp.location = (2.0, 2.0, 4.0)
    lamp.rotation_euler = (Vector((0.0, 0.0, 0.5)) - lamp.location).to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(lamp)
    scene.world = bpy.data.worlds.new("world")
    scene.world.color = (0.0, 0.0, 0.0)
    for flag in ("use_pass_glossy_direct", "use_pass_glossy_indirect", "use_pass_glossy_color"):
        setattr(scene.view_layers[0], flag, True)
    bpy.ops.wm.save_as_mainfile(filepath=path)
""")


def build(kind: str, path) -> None:
    """Write the scene `kind` (one of KINDS) to the .blend `path`."""
    if kind not in KINDS:
        raise ValueError(f"unknown scene {kind!r}")
    subprocess.run([sys.executable, "-c", SCENE, kind, str(path)], check=True, capture_output=True)
