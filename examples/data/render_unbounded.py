"""Render a small unbounded 360-degree capture with Blender/Cycles: one mesh standing on a
textured ground that runs to the horizon, distant walls and a sky behind, opaque images.

Run (Blender 3.x, background mode):

    blender -b -P examples/data/render_unbounded.py -- \
        --mesh /usr/share/assimp/models/PLY/Wuson.ply --out examples/data/wuson_unbounded --seed 0

Writes (nerfstudio layout: one transforms.json, every 8th frame held out by the loader)
  <out>/transforms.json      fl_x, fl_y, cx, cy, w, h and per frame file_path and
                             transform_matrix (camera to world, OpenGL axes, Z up); no
                             aabb_scale: the scene has no bounds
  <out>/images/frame_<i>.png  100x100 RGB, opaque
  <out>/scene.json            what is where, and the render settings

The object (the mesh normalised to radius 0.5 on the ground at z = 0) fills the middle;
the ground is a 4 km checker-and-noise plane, eight walls of noise texture stand 8 to 40
units away, a Preetham sky fills the rest. Cameras circle the object at distances 1.2 to
2.2 and heights 0.15 to 1.1, looking at points near it. Reuses render_dataset.py's mesh
import, normalisation, material and PNG helpers. Deterministic given --seed.
"""

import argparse
import json
import math
import os
import random
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import render_dataset as rd  # noqa: E402

import bpy  # noqa: E402

WIDTH = HEIGHT = 100
FRAMES = 96
OBJECT_RADIUS = 0.5


def parse_args():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mesh", default="/usr/share/assimp/models/PLY/Wuson.ply")
    p.add_argument("--out", default="examples/data/wuson_unbounded")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--up-axis", choices=["Z", "Y"], default="Y")
    p.add_argument("--samples", type=int, default=32)
    p.add_argument("--frames", type=int, default=FRAMES)
    return p.parse_args(argv)


def noise_material(name, scale, colours, checker=None):
    """A matte material: noise between two colours, optionally multiplied by a checker."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes["Principled BSDF"]
    bsdf.inputs["Roughness"].default_value = 0.95
    bsdf.inputs["Specular"].default_value = 0.05
    texco = nodes.new("ShaderNodeTexCoord")
    noise = nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = scale
    noise.inputs["Detail"].default_value = 6.0
    ramp = nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = colours[0]
    ramp.color_ramp.elements[1].color = colours[1]
    links.new(texco.outputs["Object"], noise.inputs["Vector"])
    links.new(noise.outputs["Fac"], ramp.inputs["Fac"])
    colour = ramp.outputs["Color"]
    if checker is not None:
        chk = nodes.new("ShaderNodeTexChecker")
        chk.inputs["Scale"].default_value = checker
        chk.inputs["Color1"].default_value = (1.0, 1.0, 1.0, 1.0)
        chk.inputs["Color2"].default_value = (0.55, 0.55, 0.55, 1.0)
        mix = nodes.new("ShaderNodeMixRGB")
        mix.blend_type = "MULTIPLY"
        mix.inputs["Fac"].default_value = 1.0
        links.new(texco.outputs["Object"], chk.inputs["Vector"])
        links.new(colour, mix.inputs["Color1"])
        links.new(chk.outputs["Color"], mix.inputs["Color2"])
        colour = mix.outputs["Color"]
    links.new(colour, bsdf.inputs["Base Color"])
    return mat


def add_box(scene, name, size, location, mat):
    mesh = bpy.data.meshes.new(name)
    sx, sy, sz = (s / 2.0 for s in size)
    verts = [(x * sx, y * sy, z * sz) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    mesh.from_pydata(verts, [], faces)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    obj.data.materials.append(mat)
    scene.collection.objects.link(obj)
    return obj


def build_scene(args):
    from mathutils import Euler, Matrix, Vector

    scene = rd.reset_scene()
    obj = rd.import_mesh(args.mesh)
    rd.normalise_mesh(obj, args.up_axis)
    rd.make_material(obj)
    me = obj.data
    me.transform(Matrix.Diagonal((OBJECT_RADIUS,) * 3 + (1.0,)))
    z_min = min(v.co.z for v in me.vertices)
    me.transform(Matrix.Translation((0.0, 0.0, -z_min)))  # stands on z = 0
    me.update()

    ground = bpy.data.meshes.new("Ground")
    h = 2000.0
    ground.from_pydata([(-h, -h, 0.0), (h, -h, 0.0), (h, h, 0.0), (-h, h, 0.0)], [],
                       [(0, 1, 2, 3)])
    ground.update()
    g = bpy.data.objects.new("Ground", ground)
    g.data.materials.append(noise_material(
        "GroundMat", 2.0, [(0.25, 0.18, 0.10, 1.0), (0.55, 0.50, 0.35, 1.0)], checker=4.0))
    scene.collection.objects.link(g)

    rng = random.Random(args.seed + 17)
    walls = []
    for k in range(8):
        azim = 2.0 * math.pi * (k + rng.uniform(0.2, 0.8)) / 8.0
        dist = rng.uniform(8.0, 40.0)
        size = (rng.uniform(2.0, 8.0), rng.uniform(0.5, 2.0), rng.uniform(1.5, 6.0))
        loc = (dist * math.cos(azim), dist * math.sin(azim), size[2] / 2.0)
        hue = [(0.15, 0.25, 0.55, 1.0), (0.55, 0.15, 0.12, 1.0), (0.12, 0.45, 0.18, 1.0),
               (0.60, 0.55, 0.20, 1.0)][k % 4]
        mat = noise_material("Wall%d" % k, 1.5, [hue, (0.9, 0.9, 0.85, 1.0)])
        box = add_box(scene, "Wall%d" % k, size, loc, mat)
        box.rotation_euler = Euler((0.0, 0.0, azim + math.pi / 2.0), "XYZ")
        walls.append({"azimuth_deg": math.degrees(azim), "distance": dist, "size": size})

    world = bpy.data.worlds.new("Sky")
    world.use_nodes = True
    nodes, links = world.node_tree.nodes, world.node_tree.links
    sky = nodes.new("ShaderNodeTexSky")
    sky.sky_type = "PREETHAM"
    sky.turbidity = 3.0
    sky.sun_direction = Vector((0.4, 0.3, 0.6)).normalized()
    links.new(sky.outputs["Color"], nodes["Background"].inputs["Color"])
    nodes["Background"].inputs["Strength"].default_value = 0.6
    scene.world = world
    sun_data = bpy.data.lights.new("Sun", type="SUN")
    sun_data.energy = 3.0
    sun_data.angle = math.radians(3.0)
    sun = bpy.data.objects.new("Sun", sun_data)
    sun.rotation_euler = Euler((math.radians(45.0), 0.0, math.radians(35.0)), "XYZ")
    scene.collection.objects.link(sun)
    return scene, walls


def main():
    from mathutils import Matrix, Vector

    args = parse_args()
    scene, walls = build_scene(args)
    render_info = rd.setup_render(scene, args.seed, args.samples, None)
    scene.render.film_transparent = False
    scene.render.image_settings.color_mode = "RGB"
    scene.render.resolution_x, scene.render.resolution_y = WIDTH, HEIGHT
    cam = rd.make_camera(scene)
    cam.data.clip_start = 0.01
    cam.data.clip_end = 10000.0
    fx = 0.5 * WIDTH / math.tan(0.5 * cam.data.angle_x)

    rng = random.Random(args.seed)
    os.makedirs(os.path.join(args.out, "images"), exist_ok=True)
    frames = []
    for i in range(args.frames):
        azim = 2.0 * math.pi * (i + rng.uniform(-0.3, 0.3)) / args.frames
        dist = rng.uniform(1.2, 2.2)
        height = rng.uniform(0.15, 1.1)
        p = Vector((dist * math.cos(azim), dist * math.sin(azim), height))
        target = Vector((rng.uniform(-0.15, 0.15), rng.uniform(-0.15, 0.15),
                         rng.uniform(0.1, 0.4)))
        rot = (target - p).to_track_quat("-Z", "Y").to_matrix().to_4x4()
        cam.matrix_world = Matrix.Translation(p) @ rot
        bpy.context.view_layer.update()
        rel = "images/frame_%03d" % i
        scene.render.filepath = os.path.join(args.out, rel)
        bpy.ops.render.render(write_still=True)
        rd.png_strip_text(scene.render.filepath + ".png")
        frames.append({"file_path": rel + ".png",
                       "transform_matrix": [[float(x) for x in row] for row in cam.matrix_world]})
    doc = {"camera_model": "OPENCV", "fl_x": fx, "fl_y": fx, "cx": WIDTH / 2.0,
           "cy": HEIGHT / 2.0, "w": WIDTH, "h": HEIGHT, "frames": frames}
    with open(os.path.join(args.out, "transforms.json"), "w") as f:
        json.dump(doc, f, indent=2)
        f.write("\n")
    scene_doc = {"blender_version": bpy.app.version_string, "mesh": args.mesh,
                 "seed": args.seed, "object": "normalised to radius %g, standing on z = 0"
                 % OBJECT_RADIUS, "ground": "4 km plane at z = 0, checker x noise",
                 "walls": walls, "sky": "Preetham, turbidity 3, strength 0.6",
                 "cameras": "azimuth 360 i / frames +- 0.3 step, distance U(1.2, 2.2), height "
                            "U(0.15, 1.1), looking at a point within 0.15 of (0, 0, 0.25)",
                 "render": render_info}
    scene_doc["render"]["film_transparent"] = False
    with open(os.path.join(args.out, "scene.json"), "w") as f:
        json.dump(scene_doc, f, indent=1)
        f.write("\n")
    print("rendered %d frames into %s" % (len(frames), args.out))


if __name__ == "__main__":
    main()
