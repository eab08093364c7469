"""Runs inside Blender (`blender -b --factory-startup -P blender_scene.py -- settings.json`):
builds a small room with coloured walls from the settings, path-traces it with Cycles
from every camera and writes one linear EXR per view. Not importable outside Blender (bpy).

settings.json: {"out": folder, "width", "height", "samples", "seed",
"walls": {"left", "right", "back", "floor": [r, g, b]}, "objects": [{"kind": "sphere" |
"cube" | "cylinder", "location": [x, y, z], "size": s, "color": [r, g, b], "checker":
[r, g, b] or null, "rotation": deg}], "light": {"location": [x, y, z], "size": m,
"power": W}, "poses": [(4, 4) camera-to-world, OpenGL convention], "fov_deg": horizontal
field of view}. The light is white: the capture's light colour is applied afterwards in
the renderer's RGB (gridnerf.sim.cycles), which is exact for an RGB path tracer (each
channel is transported alone, so the render under a light of colour L is L times the
render under a white one, interreflections included).
"""

import json
import math
import sys

import bpy  # noqa: F401  (Blender's own module)
from mathutils import Matrix


def material(name, color, checker=None, scale=6.0, roughness=0.7):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes["Principled BSDF"]
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Specular"].default_value = 0.2
    if checker is None:
        bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    else:
        tex = nodes.new("ShaderNodeTexChecker")
        tex.inputs["Color1"].default_value = (*color, 1.0)
        tex.inputs["Color2"].default_value = (*checker, 1.0)
        tex.inputs["Scale"].default_value = scale
        noise = nodes.new("ShaderNodeTexNoise")
        noise.inputs["Scale"].default_value = 40.0
        mix = nodes.new("ShaderNodeMixRGB")
        mix.blend_type = "MULTIPLY"
        mix.inputs["Fac"].default_value = 0.35
        links.new(tex.outputs["Color"], mix.inputs["Color1"])
        links.new(noise.outputs["Color"], mix.inputs["Color2"])
        links.new(mix.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def plane(name, location, rotation, size, mat):
    bpy.ops.mesh.primitive_plane_add(size=size, location=location,
                                     rotation=[math.radians(a) for a in rotation])
    obj = bpy.context.active_object
    obj.name = name
    obj.data.materials.append(mat)
    return obj


def build(s):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(s["samples"])
    scene.cycles.seed = int(s["seed"])
    scene.cycles.max_bounces = 6
    scene.cycles.diffuse_bounces = 4
    scene.cycles.glossy_bounces = 2
    scene.cycles.use_denoising = False  # Debian's Blender has no OpenImageDenoise
    scene.render.resolution_x = int(s["width"])
    scene.render.resolution_y = int(s["height"])
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    scene.view_settings.view_transform = "Standard"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.image_settings.color_mode = "RGB"
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    scene.world = world

    walls = s["walls"]
    w, h, d = s.get("room", [6.0, 3.5, 6.0])
    plane("floor", (0, 0, 0), (0, 0, 0), max(w, d),
          material("floor", walls["floor"], walls.get("floor_checker"), 8.0))
    plane("back", (0, -d / 2, h / 2), (90, 0, 0), max(w, h) * 1.2,
          material("back", walls["back"], walls.get("back_checker"), 5.0))
    plane("left", (-w / 2, 0, h / 2), (90, 0, 90), max(d, h) * 1.2,
          material("left", walls["left"]))
    plane("right", (w / 2, 0, h / 2), (90, 0, -90), max(d, h) * 1.2,
          material("right", walls["right"]))
    for k, o in enumerate(s["objects"]):
        mat = material(f"obj{k}", o["color"], o.get("checker"), o.get("scale", 4.0),
                       o.get("roughness", 0.6))
        size, loc = float(o["size"]), o["location"]
        if o["kind"] == "sphere":
            bpy.ops.mesh.primitive_uv_sphere_add(radius=size, location=loc, segments=48,
                                                 ring_count=24)
            bpy.ops.object.shade_smooth()
        elif o["kind"] == "cube":
            bpy.ops.mesh.primitive_cube_add(size=2 * size, location=loc,
                                            rotation=(0, 0, math.radians(o.get("rotation", 0))))
        else:
            bpy.ops.mesh.primitive_cylinder_add(radius=size, depth=o.get("height", 2 * size),
                                                location=loc, vertices=48)
            bpy.ops.object.shade_smooth()
        bpy.context.active_object.data.materials.append(mat)
    li = s["light"]
    light = bpy.data.lights.new("lamp", type="AREA")
    light.size = float(li["size"])
    light.energy = float(li["power"])
    light.color = (1.0, 1.0, 1.0)
    lamp = bpy.data.objects.new("lamp", light)
    lamp.location = li["location"]
    lamp.rotation_euler = [math.radians(a) for a in li.get("rotation", (0, 0, 0))]
    scene.collection.objects.link(lamp)

    cam_data = bpy.data.cameras.new("cam")
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.angle = math.radians(float(s["fov_deg"]))
    cam_data.clip_start = 0.05
    cam_data.clip_end = 100.0
    cam = bpy.data.objects.new("cam", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    return scene, cam


def main():
    settings = json.loads(open(sys.argv[sys.argv.index("--") + 1]).read())
    scene, cam = build(settings)
    for i, pose in enumerate(settings["poses"]):
        cam.matrix_world = Matrix(pose)  # Blender cameras look down -z, +y up: OpenGL's
        scene.render.filepath = f"{settings['out']}/view_{i:03d}.exr"
        bpy.ops.render.render(write_still=True)
        print(f"rendered view {i}", flush=True)


main()
