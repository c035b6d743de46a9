"""Render a small NeRF-synthetic style dataset of one mesh with Blender/Cycles.

Run (Blender 3.x, background mode):

    blender -b -P examples/data/render_dataset.py -- \
        --mesh /usr/share/assimp/models/PLY/Wuson.ply --out examples/data/wuson --seed 0

Writes
  <out>/transforms_{train,val,test}.json   Blender synthetic layout
  <out>/{train,val,test}/r_<i>.png          100x100 RGBA, transparent background
  <out>/points.json                         8 mesh vertices + their pixels in every frame
  <out>/scene.json                          normalising transform and render settings
  <dtu-out>/image/000000.png ...            IDR/DTU copy of the test split (RGB on black)
  <dtu-out>/mask/000.png ...                8-bit masks (alpha >= 0.5)
  <dtu-out>/cameras.npz                     world_mat_i / scale_mat_i (numpy.savez)
  <dtu-out>/points.json                     the same 8 points in the DTU world frame

Options for other scenes (the defaults reproduce the committed wuson files byte
for byte; examples/data/render_suite.sh renders the scene suite with them):
  --material bands|fine|glossy   the procedural material: bands (default), the same
                                 bands with a fine checker and noise, or a glossy one
  --object-radius R              radius of the normalised mesh's bounding sphere
                                 (default 1; the cameras stay at radius 4)
  --no-dtu                       skip the DTU copy
Meshes: .ply, .stl, .obj, and .dae (Collada) and binary .fbx, whose importers
turn the file to Blender's Z-up themselves (pass --up-axis Z for those, and for
.obj, which is imported as Y-up).  Imported cameras, lights, armatures and empties
are dropped; the meshes are baked in their posed, modified world shape and joined.
(Blender 3.4's X3D/VRML importer fails under Python 3.11 and its glTF importer
needs numpy inside Blender, so .x3d/.wrl/.gltf/.glb are not offered.)

The DTU part needs numpy.  If Blender's own Python has no numpy, this same
file is run a second time by an ordinary Python interpreter (``--python``,
default ``python3``) in ``--dtu-only`` mode, reading what the Blender stage
wrote.  Everything is deterministic given ``--seed`` (camera positions and
the Cycles sampling seed): two runs give byte-identical files (text chunks with
render times are stripped from the PNGs; numpy 2.x writes a fixed date into
the zip entries of cameras.npz, older numpy the current time).
"""

import argparse
import json
import math
import os
import random
import shutil
import struct
import subprocess
import sys
import time
import zlib

try:
    import bpy  # noqa: F401
    IN_BLENDER = True
except ImportError:
    IN_BLENDER = False

# ---------------------------------------------------------------- constants
WIDTH = 100
HEIGHT = 100
SAMPLES = 32
CAMERA_RADIUS = 4.0
N_TRAIN = 50
N_VAL = 10
N_TEST = 20
ELEV_RANGE_DEG = (10.0, 70.0)
TEST_ELEV_DEG = 30.0
# Blender's default 50 mm lens on a 36 mm sensor: the camera_angle_x of the
# published Blender synthetic scenes, 2*atan(18/50).
LENS_MM = 50.0
SENSOR_MM = 36.0
EXPECTED_ANGLE_X = 0.6911112070083618

# DTU copy: a different world frame, like DTU's millimetres.
DTU_SCALE = 200.0
DTU_OFFSET = (30.0, -20.0, 500.0)
DTU_SPHERE = 1.1  # unit sphere of the normalised frame = radius 1.1 in Blender units
N_POINTS = 8

MATERIALS = ("bands", "fine", "glossy")
FINE_CHECKER_SCALE = 14.0
FINE_NOISE_SCALE = 12.0
GLOSSY_ROUGHNESS = 0.2
GLOSSY_SPECULAR = 0.7
GLOSSY_METALLIC = 0.2
MAX_OBJECT_RADIUS = 3.0  # the cameras sit at CAMERA_RADIUS = 4, clip_start 0.1


def set_resolution(n):
    """Render n x n images (the cameras' field of view is unchanged)."""
    global WIDTH, HEIGHT
    WIDTH = HEIGHT = n


def parse_args():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mesh", default="/usr/share/assimp/models/PLY/Wuson.ply")
    p.add_argument("--out", default="examples/data/wuson")
    p.add_argument("--dtu-out", default=None, help="default: <out>_dtu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--up-axis", choices=["Z", "Y"], default="Y",
                   help="the mesh file's up axis; Y-up meshes are turned to Blender's Z-up")
    p.add_argument("--max-frames", type=int, default=None,
                   help="debugging only: render at most this many frames per split")
    p.add_argument("--python", default="python3",
                   help="interpreter with numpy for the DTU stage if Blender's Python lacks numpy")
    p.add_argument("--dtu-only", action="store_true",
                   help="internal: only build the DTU copy from an existing <out>")
    p.add_argument("--resolution", type=int, default=WIDTH,
                   help="image width and height in pixels (the committed dataset: 100)")
    p.add_argument("--samples", type=int, default=SAMPLES,
                   help="Cycles samples per pixel (the committed dataset: %d)" % SAMPLES)
    p.add_argument("--filter-width", type=float, default=None,
                   help="Cycles' pixel filter width in pixels (default: Blender's, a "
                        "Blackman-Harris filter 1.5 pixels wide; 0.01, Blender's least, "
                        "samples each pixel's centre)")
    p.add_argument("--material", choices=MATERIALS, default=None,
                   help="procedural material: bands (default: the committed dataset's), fine "
                        "(the bands with a checker of scale 14 and value noise) or glossy (the "
                        "bands, roughness 0.2, specular 0.7, metallic 0.2); recorded in "
                        "scene.json when given")
    p.add_argument("--object-radius", type=float, default=None,
                   help="radius of the normalised mesh's bounding sphere in Blender units "
                        "(default 1; cameras at radius %g, field of view unchanged: about 1.4 "
                        "fills the frame); recorded in scene.json when given" % CAMERA_RADIUS)
    p.add_argument("--no-dtu", action="store_true",
                   help="do not build the DTU copy")
    a = p.parse_args(argv)
    if a.object_radius is not None and not (
            math.isfinite(a.object_radius) and 0.0 < a.object_radius <= MAX_OBJECT_RADIUS):
        raise SystemExit("--object-radius must lie in (0, %g] (the cameras sit at radius %g), "
                         "got %r" % (MAX_OBJECT_RADIUS, CAMERA_RADIUS, a.object_radius))
    if (a.object_radius is not None and a.object_radius > DTU_SPHERE and not a.no_dtu
            and not a.dtu_only):
        raise SystemExit("--object-radius %g > %g: the DTU copy's scale_mat would not hold the "
                         "object in its unit sphere; pass --no-dtu" % (a.object_radius, DTU_SPHERE))
    if a.no_dtu and a.dtu_only:
        raise SystemExit("--no-dtu and --dtu-only contradict each other")
    if a.no_dtu and a.dtu_out is not None:
        raise SystemExit("--no-dtu and --dtu-out contradict each other")
    if a.resolution < 1:
        raise SystemExit("--resolution must be at least 1")
    if a.samples < 1:
        raise SystemExit("--samples must be at least 1")
    if a.filter_width is not None and not 0.01 <= a.filter_width <= 10.0:
        raise SystemExit("--filter-width must lie in [0.01, 10] pixels")
    set_resolution(a.resolution)
    a.out = os.path.abspath(a.out)
    if a.dtu_out is None:
        a.dtu_out = a.out.rstrip("/") + "_dtu"
    a.dtu_out = os.path.abspath(a.dtu_out)
    return a


# ------------------------------------------------------- minimal PNG codec
# (Blender's Python need not have PIL; the DTU stage reads and writes PNG
# with zlib only.)

def _png_chunk(tag, data):
    return (struct.pack(">I", len(data)) + tag + data
            + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))


def png_write(path, width, height, channels, rows):
    """rows: list of bytes objects, width*channels bytes each, 8-bit."""
    color_type = {1: 0, 3: 2, 4: 6}[channels]
    raw = b"".join(b"\x00" + bytes(r) for r in rows)
    ihdr = struct.pack(">IIBBBBB", width, height, 8, color_type, 0, 0, 0)
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n")
        f.write(_png_chunk(b"IHDR", ihdr))
        f.write(_png_chunk(b"IDAT", zlib.compress(raw, 9)))
        f.write(_png_chunk(b"IEND", b""))


def png_strip_text(path):
    """Drop tEXt/zTXt/iTXt chunks (Blender writes Cycles render times there, which would
    make otherwise identical files differ); every other chunk is kept byte for byte."""
    with open(path, "rb") as f:
        data = f.read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", path
    pos, keep = 8, [data[:8]]
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        tag = data[pos + 4:pos + 8]
        if tag not in (b"tEXt", b"zTXt", b"iTXt"):
            keep.append(data[pos:pos + 12 + n])
        pos += 12 + n
    with open(path, "wb") as f:
        f.write(b"".join(keep))


def png_read(path):
    """Read a non-interlaced 8-bit gray/RGB/RGBA PNG -> (w, h, channels, rows)."""
    with open(path, "rb") as f:
        data = f.read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", path
    pos, idat, hdr = 8, [], None
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        tag = data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + n]
        pos += 12 + n
        if tag == b"IHDR":
            hdr = struct.unpack(">IIBBBBB", body)
        elif tag == b"IDAT":
            idat.append(body)
        elif tag == b"IEND":
            break
    w, h, depth, ctype, _, _, interlace = hdr
    if depth != 8 or interlace != 0 or ctype not in (0, 2, 4, 6):
        raise ValueError("unsupported PNG %s: %r" % (path, hdr))
    ch = {0: 1, 2: 3, 4: 2, 6: 4}[ctype]
    raw = zlib.decompress(b"".join(idat))
    stride = w * ch
    prev = bytearray(stride)
    rows = []
    for y in range(h):
        ftype = raw[y * (stride + 1)]
        line = bytearray(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)])
        if ftype == 1:
            for i in range(ch, stride):
                line[i] = (line[i] + line[i - ch]) & 0xFF
        elif ftype == 2:
            for i in range(stride):
                line[i] = (line[i] + prev[i]) & 0xFF
        elif ftype == 3:
            for i in range(stride):
                left = line[i - ch] if i >= ch else 0
                line[i] = (line[i] + ((left + prev[i]) >> 1)) & 0xFF
        elif ftype == 4:
            for i in range(stride):
                a = line[i - ch] if i >= ch else 0
                b = prev[i]
                c = prev[i - ch] if i >= ch else 0
                pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
                pred = a if (pa <= pb and pa <= pc) else (b if pb <= pc else c)
                line[i] = (line[i] + pred) & 0xFF
        elif ftype != 0:
            raise ValueError("bad PNG filter %d in %s" % (ftype, path))
        rows.append(bytes(line))
        prev = line
    return w, h, ch, rows


# ------------------------------------------------------------ DTU stage

def build_dtu_copy(out, dtu_out):
    """Build the IDR/DTU layout copy of the test split from what the Blender stage wrote."""
    import numpy as np

    with open(os.path.join(out, "transforms_test.json")) as f:
        test = json.load(f)
    with open(os.path.join(out, "points.json")) as f:
        pts = json.load(f)
    angle_x = float(test["camera_angle_x"])
    W, H = int(pts["width"]), int(pts["height"])
    f_px = 0.5 * W / math.tan(0.5 * angle_x)
    K = np.array([[f_px, 0.0, W / 2.0],
                  [0.0, f_px, H / 2.0],
                  [0.0, 0.0, 1.0]])
    s = DTU_SCALE
    o = np.array(DTU_OFFSET, dtype=np.float64)
    gl_to_cv = np.diag([1.0, -1.0, -1.0])

    scale_mat = np.eye(4)
    scale_mat[:3, :3] *= s * DTU_SPHERE
    scale_mat[:3, 3] = o

    for sub in ("image", "mask"):
        os.makedirs(os.path.join(dtu_out, sub), exist_ok=True)

    cams = {}
    frames_out = []
    for i, fr in enumerate(test["frames"]):
        c2w = np.array(fr["transform_matrix"], dtype=np.float64)
        # Blender stores matrix_world in float32: re-orthonormalise the rotation
        # (Blender itself uses matrix_world.normalized()); deviations ~1e-7.
        u, _, vt = np.linalg.svd(c2w[:3, :3])
        r_c2w = u @ vt
        centre_dtu = s * c2w[:3, 3] + o
        r_w2c = gl_to_cv @ r_c2w.T              # OpenCV axes: x right, y down, z forward
        t_w2c = -r_w2c @ centre_dtu
        world_mat = np.eye(4)
        world_mat[:3, :4] = K @ np.hstack([r_w2c, t_w2c[:, None]])
        cams["world_mat_%d" % i] = world_mat
        cams["scale_mat_%d" % i] = scale_mat.copy()

        # image: RGBA -> RGB composited onto black (on the 8-bit sRGB values);
        # mask: 255 where alpha >= 0.5 (alpha byte >= 128).
        src = os.path.join(out, fr["file_path"] + ".png")
        w, h, ch, rows = png_read(src)
        assert (w, h, ch) == (W, H, 4), (src, w, h, ch)
        rgba = np.frombuffer(b"".join(rows), dtype=np.uint8).reshape(h, w, 4).astype(np.int64)
        rgb = (rgba[..., :3] * rgba[..., 3:4] + 127) // 255
        mask = np.where(rgba[..., 3] >= 128, 255, 0)
        png_write(os.path.join(dtu_out, "image", "%06d.png" % i), w, h, 3,
                  [r.tobytes() for r in rgb.astype(np.uint8)])
        png_write(os.path.join(dtu_out, "mask", "%03d.png" % i), w, h, 1,
                  [r.tobytes() for r in mask.astype(np.uint8)])

        pf = pts["frames"]["test"][i]
        frames_out.append({
            "index": i,
            "image": "image/%06d.png" % i,
            "mask": "mask/%03d.png" % i,
            "source": fr["file_path"],
            "pixels": pf["pixels"],
            "depth": [s * d for d in pf["depth"]],
        })

    np.savez(os.path.join(dtu_out, "cameras.npz"), **cams)

    pts_dtu = [[s * p[k] + o[k] for k in range(3)] for p in pts["points"]]
    doc = {
        "description": "8 mesh vertices in the DTU world frame and their pixel coordinates "
                       "in each test-split frame of this IDR/DTU copy (pixels computed by "
                       "Blender's bpy_extras.object_utils.world_to_camera_view in the Blender "
                       "stage; identical cameras)",
        "width": W,
        "height": H,
        "world_frame": "DTU: X_dtu = %g * X_blender + (%g, %g, %g)" % ((s,) + tuple(DTU_OFFSET)),
        "dtu_scale": s,
        "dtu_offset": list(DTU_OFFSET),
        "pixel_convention": pts["pixel_convention"],
        "depth_convention": "z of the point in the OpenCV camera frame (forward), in DTU units "
                            "(= %g * Blender camera-space depth)" % s,
        "vertex_indices": pts["vertex_indices"],
        "points": pts_dtu,
        "frames": frames_out,
    }
    with open(os.path.join(dtu_out, "points.json"), "w") as f:
        json.dump(doc, f, indent=1)
        f.write("\n")
    print("DTU copy written to %s (%d frames)" % (dtu_out, len(frames_out)))


# ---------------------------------------------------------- Blender stage

def reset_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    for coll in (bpy.data.objects, bpy.data.meshes, bpy.data.materials, bpy.data.cameras,
                 bpy.data.lights, bpy.data.worlds, bpy.data.images, bpy.data.node_groups,
                 bpy.data.textures, bpy.data.collections):
        for block in list(coll):
            coll.remove(block)
    return bpy.context.scene


SCENE_FORMATS = (".dae", ".fbx")


def import_mesh(path):
    ext = os.path.splitext(path)[1].lower()
    if not os.path.isfile(path):
        raise SystemExit("no such mesh file: %s" % path)
    before = set(bpy.data.objects)
    if ext == ".ply":
        bpy.ops.import_mesh.ply(filepath=path)
    elif ext == ".stl":
        bpy.ops.import_mesh.stl(filepath=path)
    elif ext == ".obj":
        bpy.ops.import_scene.obj(filepath=path, axis_forward="-Z", axis_up="Y")
    elif ext in SCENE_FORMATS:
        return import_scene_file(path, ext, before)
    else:
        raise SystemExit("unsupported mesh format: %s (.ply, .stl, .obj, %s)"
                         % (path, ", ".join(SCENE_FORMATS)))
    objs = [o for o in bpy.data.objects if o not in before and o.type == "MESH"]
    if not objs:
        raise SystemExit("no mesh imported from %s" % path)
    if len(objs) > 1:
        ctx = bpy.context
        for o in ctx.scene.objects:
            o.select_set(o in objs)
        ctx.view_layer.objects.active = objs[0]
        bpy.ops.object.join()
    obj = objs[0]
    obj.data.transform(obj.matrix_world)  # bake any importer transform
    obj.matrix_world.identity()
    return obj


def import_scene_file(path, ext, before):
    """Import a scene format (Collada, binary FBX) and bake every imported mesh object,
    as evaluated (parents, armature pose, modifiers, instancing applied), into one new
    mesh object in world coordinates; every other imported object (cameras, lights,
    armatures, empties) is removed so that only this script's camera and lights remain."""
    import bmesh

    try:
        if ext == ".dae":
            bpy.ops.wm.collada_import(filepath=path)
        else:
            bpy.ops.import_scene.fbx(filepath=path)
    except RuntimeError as e:
        raise SystemExit("cannot import %s: %s" % (path, e))
    new = [o for o in bpy.data.objects if o not in before]
    meshes = [o for o in new if o.type == "MESH"]
    if not meshes:
        raise SystemExit("no mesh imported from %s" % path)
    dg = bpy.context.evaluated_depsgraph_get()
    bm = bmesh.new()
    for o in sorted(meshes, key=lambda o: o.name):
        me = bpy.data.meshes.new_from_object(o.evaluated_get(dg))
        me.transform(o.matrix_world)
        bm.from_mesh(me)  # appends to what bm holds
        bpy.data.meshes.remove(me)
    for o in new:
        bpy.data.objects.remove(o, do_unlink=True)
    me = bpy.data.meshes.new(os.path.splitext(os.path.basename(path))[0])
    bm.to_mesh(me)
    bm.free()
    me.use_auto_smooth = False  # ignore any custom split normals from the file
    for p in me.polygons:
        p.material_index = 0
    if not me.polygons:
        raise SystemExit("no faces imported from %s" % path)
    obj = bpy.data.objects.new(me.name, me)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def normalise_mesh(obj, up_axis):
    """Weld duplicate vertices, turn to Z-up, centre the bounding box at the origin and
    scale so the largest vertex distance from it is 1.  Returns the 4x4 applied."""
    import bmesh
    from mathutils import Matrix, Vector

    me = obj.data
    n_in = len(me.vertices)
    co = [v.co.copy() for v in me.vertices]
    lo = Vector([min(c[k] for c in co) for k in range(3)])
    hi = Vector([max(c[k] for c in co) for k in range(3)])
    bm = bmesh.new()
    bm.from_mesh(me)
    bmesh.ops.remove_doubles(bm, verts=bm.verts, dist=1e-6 * (hi - lo).length)
    bm.to_mesh(me)
    bm.free()
    me.update()

    rot = Matrix.Identity(4)
    if up_axis == "Y":  # (x, y, z) -> (x, -z, y): file +Y becomes Blender +Z
        rot = Matrix(((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -1.0, 0.0),
                      (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))
    co = [(rot @ v.co.to_4d()).to_3d() for v in me.vertices]
    lo = Vector([min(c[k] for c in co) for k in range(3)])
    hi = Vector([max(c[k] for c in co) for k in range(3)])
    centre = (lo + hi) / 2.0
    radius = max((c - centre).length for c in co)
    scale = 1.0 / radius
    m = Matrix.Diagonal((scale, scale, scale, 1.0)) @ Matrix.Translation(-centre) @ rot
    me.transform(m)
    for p in me.polygons:
        p.use_smooth = True
    me.update()
    return {
        "matrix": [list(map(float, row)) for row in m],
        "formula": "X_world = matrix @ [X_file, 1]  (= scale * (R @ X_file - centre))",
        "rotation_file_to_blender": [list(map(float, row)) for row in rot.to_3x3()],
        "centre_after_rotation": list(map(float, centre)),
        "bbox_radius_file_units": float(radius),
        "scale": float(scale),
        "vertices_in_file": n_in,
        "vertices_after_weld": len(me.vertices),
        "faces": len(me.polygons),
        "bounding_sphere": "centre = axis-aligned bounding-box centre, radius = max vertex distance",
    }


def make_material(obj, preset="bands"):
    """The procedural material.  bands: the committed dataset's; fine: the same bands
    with a checker of scale 14 (cells about 2.5 px wide at object radius 1) whose
    colours are modulated by value noise; glossy: the bands (checker scale 3) on a
    low-roughness, slightly metallic principled BSDF (view-dependent highlights)."""
    if preset not in MATERIALS:
        raise SystemExit("unknown material %r (%s)" % (preset, ", ".join(MATERIALS)))
    mat = bpy.data.materials.new("ProceduralBands")
    mat.use_nodes = True
    nt = mat.node_tree
    nodes, links = nt.nodes, nt.links
    for n in list(nodes):
        nodes.remove(n)
    out = nodes.new("ShaderNodeOutputMaterial")
    bsdf = nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.inputs["Roughness"].default_value = 0.9
    bsdf.inputs["Specular"].default_value = 0.1
    texco = nodes.new("ShaderNodeTexCoord")
    sep = nodes.new("ShaderNodeSeparateXYZ")
    # bands along height, slightly tilted along the body (+y):
    # t = 0.5 + 0.5 * z + 0.1 * y, five constant colour bands
    tilt = nodes.new("ShaderNodeMath")
    tilt.operation = "MULTIPLY_ADD"
    tilt.inputs[1].default_value = 0.1
    tilt.inputs[2].default_value = 0.5
    madd = nodes.new("ShaderNodeMath")
    madd.operation = "MULTIPLY_ADD"
    madd.inputs[1].default_value = 0.5
    ramp = nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.interpolation = "CONSTANT"
    cr = ramp.color_ramp
    band_stops = (0.0, 0.38, 0.48, 0.58, 0.68)
    band_colours = [(0.70, 0.08, 0.05, 1.0),   # red
                    (0.85, 0.60, 0.05, 1.0),   # yellow
                    (0.10, 0.50, 0.12, 1.0),   # green
                    (0.08, 0.20, 0.75, 1.0),   # blue
                    (0.60, 0.10, 0.55, 1.0)]   # magenta
    cr.elements[0].position = band_stops[0]
    cr.elements[0].color = band_colours[0]
    cr.elements[1].position = band_stops[1]
    cr.elements[1].color = band_colours[1]
    for pos, col in zip(band_stops[2:], band_colours[2:]):
        e = cr.elements.new(pos)
        e.color = col
    # checker on object coordinates, dark cells = band colour * 0.3
    dark = nodes.new("ShaderNodeMixRGB")
    dark.blend_type = "MULTIPLY"
    dark.inputs["Fac"].default_value = 1.0
    dark.inputs["Color2"].default_value = (0.3, 0.3, 0.3, 1.0)
    checker = nodes.new("ShaderNodeTexChecker")
    checker.inputs["Scale"].default_value = 3.0
    if preset == "fine":
        checker.inputs["Scale"].default_value = FINE_CHECKER_SCALE
    elif preset == "glossy":
        bsdf.inputs["Roughness"].default_value = GLOSSY_ROUGHNESS
        bsdf.inputs["Specular"].default_value = GLOSSY_SPECULAR
        bsdf.inputs["Metallic"].default_value = GLOSSY_METALLIC

    links.new(texco.outputs["Object"], sep.inputs["Vector"])
    links.new(sep.outputs["Y"], tilt.inputs[0])
    links.new(sep.outputs["Z"], madd.inputs[0])
    links.new(tilt.outputs["Value"], madd.inputs[2])
    links.new(madd.outputs["Value"], ramp.inputs["Fac"])
    links.new(ramp.outputs["Color"], dark.inputs["Color1"])
    links.new(texco.outputs["Object"], checker.inputs["Vector"])
    links.new(ramp.outputs["Color"], checker.inputs["Color1"])
    links.new(dark.outputs["Color"], checker.inputs["Color2"])
    if preset == "fine":
        # value noise on object coordinates: colour * (0.6 + 0.8 * noise), noise in ~[0, 1]
        noise = nodes.new("ShaderNodeTexNoise")
        noise.noise_dimensions = "3D"
        noise.inputs["Scale"].default_value = FINE_NOISE_SCALE
        noise.inputs["Detail"].default_value = 2.0
        noise.inputs["Roughness"].default_value = 0.5
        noise.inputs["Distortion"].default_value = 0.0
        nmap = nodes.new("ShaderNodeMath")
        nmap.operation = "MULTIPLY_ADD"
        nmap.inputs[1].default_value = 0.8
        nmap.inputs[2].default_value = 0.6
        shade = nodes.new("ShaderNodeMixRGB")
        shade.blend_type = "MULTIPLY"
        shade.inputs["Fac"].default_value = 1.0
        links.new(texco.outputs["Object"], noise.inputs["Vector"])
        links.new(noise.outputs["Fac"], nmap.inputs[0])
        links.new(checker.outputs["Color"], shade.inputs["Color1"])
        links.new(nmap.outputs["Value"], shade.inputs["Color2"])
        links.new(shade.outputs["Color"], bsdf.inputs["Base Color"])
    else:
        links.new(checker.outputs["Color"], bsdf.inputs["Base Color"])
    links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    obj.data.materials.clear()
    obj.data.materials.append(mat)
    if preset == "fine":
        return {
            "bsdf": "Principled, roughness 0.9, specular 0.1",
            "base_color": "checker(object coords, scale %g) of band colour and 0.3 * band colour, "
                          "times 0.6 + 0.8 * noise (Blender noise texture on object coords, "
                          "scale %g, detail 2, roughness 0.5, distortion 0); band colour = "
                          "constant colour ramp of t = 0.5 + 0.5 * z + 0.1 * y (object "
                          "coordinates) with stops at %s"
                          % (FINE_CHECKER_SCALE, FINE_NOISE_SCALE, band_stops),
            "band_colours_linear": [list(c[:3]) for c in band_colours],
        }
    if preset == "glossy":
        return {
            "bsdf": "Principled, roughness %g, specular %g, metallic %g"
                    % (GLOSSY_ROUGHNESS, GLOSSY_SPECULAR, GLOSSY_METALLIC),
            "base_color": "checker(object coords, scale 3) of band colour and 0.3 * band colour; "
                          "band colour = constant colour ramp of t = 0.5 + 0.5 * z + 0.1 * y "
                          "(object coordinates) with stops at %s" % (band_stops,),
            "band_colours_linear": [list(c[:3]) for c in band_colours],
        }
    return {
        "bsdf": "Principled, roughness 0.9, specular 0.1",
        "base_color": "checker(object coords, scale 3) of band colour and 0.3 * band colour; "
                      "band colour = constant colour ramp of t = 0.5 + 0.5 * z + 0.1 * y "
                      "(object coordinates) with stops at %s" % (band_stops,),
        "band_colours_linear": [list(c[:3]) for c in band_colours],
    }


def setup_lighting(scene):
    from mathutils import Euler
    world = bpy.data.worlds.new("World")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    bg.inputs["Strength"].default_value = 0.5
    scene.world = world
    sun_data = bpy.data.lights.new("Sun", type="SUN")
    sun_data.energy = 2.5
    sun_data.angle = math.radians(5.0)
    sun = bpy.data.objects.new("Sun", sun_data)
    sun.rotation_euler = Euler((math.radians(40.0), 0.0, math.radians(35.0)), "XYZ")
    scene.collection.objects.link(sun)
    return {"world": "uniform white background, strength 0.5",
            "sun": "strength 2.5, angle 5 deg, rotation_euler XYZ (40, 0, 35) deg"}


def setup_render(scene, seed, samples, filter_width):
    import _cycles
    r = scene.render
    r.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    c.samples = samples
    if filter_width is not None:
        c.filter_width = filter_width
    c.use_adaptive_sampling = False
    c.seed = seed
    c.use_animated_seed = False
    oidn = bool(getattr(_cycles, "with_openimagedenoise", False))
    c.use_denoising = oidn
    if oidn:
        c.denoiser = "OPENIMAGEDENOISE"
    r.resolution_x = WIDTH
    r.resolution_y = HEIGHT
    r.resolution_percentage = 100
    r.pixel_aspect_x = 1.0
    r.pixel_aspect_y = 1.0
    r.film_transparent = True
    r.dither_intensity = 0.0
    r.use_persistent_data = True
    r.use_file_extension = True
    # no date / time / render-time text chunks in the PNGs (byte-for-byte reproducible files)
    for name in dir(r):
        if name.startswith("use_stamp"):
            setattr(r, name, False)
    im = r.image_settings
    im.file_format = "PNG"
    im.color_mode = "RGBA"
    im.color_depth = "8"
    im.compression = 100
    scene.display_settings.display_device = "sRGB"
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    return {"engine": "CYCLES", "device": "CPU", "samples": samples,
            "adaptive_sampling": False, "cycles_seed": seed,
            "denoising": "OpenImageDenoise" if oidn else "off (this build has no OpenImageDenoise)",
            "resolution": [WIDTH, HEIGHT], "pixel_aspect": 1, "film_transparent": True,
            "png": "RGBA 8-bit, compression 100", "view_transform": "Standard (sRGB)",
            "dither": 0}


def make_camera(scene):
    cam_data = bpy.data.cameras.new("Camera")
    cam_data.type = "PERSP"
    cam_data.lens_unit = "MILLIMETERS"
    cam_data.lens = LENS_MM
    cam_data.sensor_width = SENSOR_MM
    cam_data.sensor_fit = "AUTO"
    cam_data.shift_x = 0.0
    cam_data.shift_y = 0.0
    cam_data.clip_start = 0.1
    cam_data.clip_end = 100.0
    cam = bpy.data.objects.new("Camera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    if abs(cam_data.angle_x - EXPECTED_ANGLE_X) > 1e-6:
        raise SystemExit("camera_angle_x %r != %r" % (cam_data.angle_x, EXPECTED_ANGLE_X))
    return cam


def camera_positions(seed):
    rng = random.Random(seed)
    splits = {}
    for name, n in (("train", N_TRAIN), ("val", N_VAL)):
        pos = []
        for _ in range(n):
            elev = math.radians(rng.uniform(*ELEV_RANGE_DEG))
            azim = rng.uniform(0.0, 2.0 * math.pi)
            pos.append((elev, azim))
        splits[name] = pos
    splits["test"] = [(math.radians(TEST_ELEV_DEG), 2.0 * math.pi * i / N_TEST)
                      for i in range(N_TEST)]
    return splits


def look_at_matrix(elev, azim):
    from mathutils import Matrix, Vector
    p = Vector((CAMERA_RADIUS * math.cos(elev) * math.cos(azim),
                CAMERA_RADIUS * math.cos(elev) * math.sin(azim),
                CAMERA_RADIUS * math.sin(elev)))
    rot = (-p).to_track_quat("-Z", "Y").to_matrix().to_4x4()
    return Matrix.Translation(p) @ rot


def pick_points(obj):
    """N_POINTS vertices spread over the object: the extreme vertex along each of the
    8 diagonal directions (+-1, +-1, +-1)."""
    verts = obj.data.vertices
    chosen = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            for sz in (-1, 1):
                # The most extreme vertex not chosen yet (a mesh with few extreme vertices
                # can be most extreme along two diagonals).
                candidates = [i for i in range(len(verts)) if i not in chosen]
                best = max(candidates,
                           key=lambda i: (sx * verts[i].co.x + sy * verts[i].co.y
                                          + sz * verts[i].co.z, -i))
                chosen.append(best)
    return chosen


def blender_stage(args):
    from bpy_extras.object_utils import world_to_camera_view

    t_start = time.perf_counter()
    scene = reset_scene()
    obj = import_mesh(args.mesh)
    norm = normalise_mesh(obj, args.up_axis)
    if args.object_radius is not None:
        # The object's matrix_world scales the unit-sphere mesh; the material reads object
        # coordinates, so the texture scales with the object.
        r = args.object_radius
        obj.scale = (r, r, r)
        bpy.context.view_layer.update()
    mat_info = make_material(obj, args.material or "bands")
    if args.material is not None:
        mat_info = dict([("preset", args.material)] + list(mat_info.items()))
    light_info = setup_lighting(scene)
    render_info = setup_render(scene, args.seed, args.samples, args.filter_width)
    if args.filter_width is not None:
        render_info["pixel_filter"] = {"type": scene.cycles.pixel_filter_type,
                                       "width_px": args.filter_width}
    cam = make_camera(scene)
    angle_x = float(cam.data.angle_x)

    vidx = pick_points(obj)
    mw = obj.matrix_world
    points = [mw @ obj.data.vertices[i].co for i in vidx]

    os.makedirs(args.out, exist_ok=True)
    splits = camera_positions(args.seed)
    proj = {}
    n_rendered = 0
    t_render = 0.0
    for split in ("train", "val", "test"):
        os.makedirs(os.path.join(args.out, split), exist_ok=True)
        frames, pframes = [], []
        cams = splits[split]
        if args.max_frames is not None:
            cams = cams[:args.max_frames]
        for i, (elev, azim) in enumerate(cams):
            cam.matrix_world = look_at_matrix(elev, azim)
            bpy.context.view_layer.update()
            rel = "./%s/r_%d" % (split, i)
            scene.render.filepath = os.path.join(args.out, split, "r_%d" % i)
            t0 = time.perf_counter()
            bpy.ops.render.render(write_still=True)
            t_render += time.perf_counter() - t0
            png_strip_text(scene.render.filepath + ".png")
            n_rendered += 1
            frames.append({
                "file_path": rel,
                "rotation": 0.0,
                "transform_matrix": [[float(x) for x in row] for row in cam.matrix_world],
            })
            pix, depth = [], []
            for p in points:
                ndc = world_to_camera_view(scene, cam, p)
                pix.append([float(ndc.x) * WIDTH, (1.0 - float(ndc.y)) * HEIGHT])
                depth.append(float(ndc.z))
            pframes.append({"file_path": rel, "pixels": pix, "depth": depth})
        with open(os.path.join(args.out, "transforms_%s.json" % split), "w") as f:
            json.dump({"camera_angle_x": angle_x, "frames": frames}, f, indent=4)
            f.write("\n")
        proj[split] = pframes

    points_doc = {
        "description": "8 mesh vertices (Blender world frame, after the normalising transform) "
                       "and their pixel coordinates in every frame of every split, computed "
                       "with bpy_extras.object_utils.world_to_camera_view",
        "width": WIDTH,
        "height": HEIGHT,
        "world_frame": "Blender world (Z up) after the normalising transform in scene.json"
                       + ("" if args.object_radius is None else
                          " and the object_radius scale (%g)" % args.object_radius),
        "pixel_convention": "x = column, y = row, continuous, origin at the top-left corner of the "
                            "top-left pixel; the centre of pixel (u, v) is (u + 0.5, v + 0.5); "
                            "x = ndc.x * width, y = (1 - ndc.y) * height",
        "depth_convention": "ndc.z of world_to_camera_view: distance along the camera's viewing "
                            "axis (-Z of the camera in Blender axes), Blender units",
        "vertex_indices": vidx,
        "points": [[float(x) for x in p] for p in points],
        "frames": proj,
    }
    with open(os.path.join(args.out, "points.json"), "w") as f:
        json.dump(points_doc, f, indent=1)
        f.write("\n")

    scene_doc = {
        "blender_version": bpy.app.version_string,
        "mesh": args.mesh,
        "mesh_up_axis": args.up_axis,
        "seed": args.seed,
        "normalisation": norm,
    }
    if args.object_radius is not None:
        scene_doc["object_radius"] = args.object_radius
        scene_doc["object_matrix_world"] = [list(map(float, row)) for row in obj.matrix_world]
        scene_doc["object_note"] = ("the mesh is normalised to the unit bounding sphere "
                                    "(normalisation.matrix) and the object's matrix_world "
                                    "scales it by object_radius: X_world = object_radius * "
                                    "(normalisation.matrix @ [X_file, 1]); the material reads "
                                    "the unit-sphere object coordinates")
    scene_doc.update({
        "material": mat_info,
        "lighting": light_info,
        "render": render_info,
        "camera": {"lens_mm": LENS_MM, "sensor_width_mm": SENSOR_MM, "sensor_fit": "AUTO",
                   "camera_angle_x": angle_x, "radius": CAMERA_RADIUS,
                   "train_val": "elevation uniform in [10, 70] deg, azimuth uniform in [0, 360) "
                                "deg, Python random.Random(seed), train drawn before val",
                   "test": "elevation 30 deg, azimuth 360 * i / 20 deg",
                   "orientation": "looks at the origin, camera up towards +Z"},
    })
    with open(os.path.join(args.out, "scene.json"), "w") as f:
        json.dump(scene_doc, f, indent=1)
        f.write("\n")

    print("rendered %d frames in %.1f s (total %.1f s)"
          % (n_rendered, t_render, time.perf_counter() - t_start))

    if args.no_dtu:
        return
    try:
        import numpy  # noqa: F401
        have_numpy = True
    except ImportError:
        have_numpy = False
    if have_numpy:
        build_dtu_copy(args.out, args.dtu_out)
    else:
        exe = shutil.which(args.python) or args.python
        script = os.path.abspath(__file__)
        print("Blender's Python has no numpy: running the DTU stage with %s" % exe)
        subprocess.run([exe, script, "--dtu-only", "--out", args.out,
                        "--dtu-out", args.dtu_out], check=True)


def main():
    args = parse_args()
    if args.dtu_only or not IN_BLENDER:
        if not args.dtu_only:
            raise SystemExit("run inside Blender: blender -b -P %s -- ..." % sys.argv[0])
        build_dtu_copy(args.out, args.dtu_out)
    else:
        blender_stage(args)


if __name__ == "__main__":
    main()
