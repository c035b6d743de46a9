"""Sanity checks for the rendered dataset (python3 with numpy and pillow).

    python3 examples/data/check_dataset.py [examples/data/wuson] [examples/data/wuson_dtu]
    python3 examples/data/check_dataset.py --allow-border examples/data/suite/duck

(A dataset without a DTU copy, such as the scenes of examples/data/suite, skips check 2
and the DTU part of check 3.  --allow-border: the object may touch the image border,
for a scene meant to fill the frame; points projected outside the image are not
checked against the alpha in any case.)

1. Blender layout: projects points.json's points with each frame's transform_matrix and
   camera_angle_x (OpenGL camera axes) and compares with the pixels Blender's
   world_to_camera_view gave.
2. DTU layout: projects the DTU-frame points with P = world_mat_i (and with
   world_mat_i @ scale_mat_i on normalised coordinates) and compares with the same pixels.
3. Images: the DTU image / mask are the composite / thresholded alpha of the RGBA render,
   every projected point lands next to a covered pixel, and the object is not cut off.
Exits non-zero if a deviation exceeds 0.01 px or a check fails.
"""

import json
import math
import os
import sys

import numpy as np
from PIL import Image

TOL_PX = 0.01


def project_gl(c2w, angle_x, w, h, pts):
    """Pixels (x right, y down, origin top-left corner) and depths of world points for a
    Blender/OpenGL camera-to-world matrix (camera looks along -z, y up)."""
    f = 0.5 * w / math.tan(0.5 * angle_x)
    w2c = np.linalg.inv(c2w)
    pc = (w2c[:3, :3] @ pts.T).T + w2c[:3, 3]
    depth = -pc[:, 2]
    x = w / 2.0 + f * pc[:, 0] / depth
    y = h / 2.0 - f * pc[:, 1] / depth
    return np.stack([x, y], 1), depth


def project_p(p, pts):
    ph = (p[:3, :3] @ pts.T).T + p[:3, 3]
    return ph[:, :2] / ph[:, 2:3], ph[:, 2]


def main():
    args = [a for a in sys.argv[1:] if a != "--allow-border"]
    allow_border = len(args) < len(sys.argv) - 1
    root = args[0] if len(args) > 0 else "examples/data/wuson"
    dtu = args[1] if len(args) > 1 else root.rstrip("/") + "_dtu"
    has_dtu = os.path.isdir(dtu)
    ok = True
    pts_doc = json.load(open(os.path.join(root, "points.json")))
    W, H = pts_doc["width"], pts_doc["height"]
    pts = np.array(pts_doc["points"], dtype=np.float64)
    scene = json.load(open(os.path.join(root, "scene.json")))
    print("points: %d, max |X| = %.6f (bounding sphere radius %g)"
          % (len(pts), np.linalg.norm(pts, axis=1).max(), scene.get("object_radius", 1.0)))

    # 1. Blender synthetic layout
    worst_px, worst_depth = 0.0, 0.0
    n_frames = 0
    for split in ("train", "val", "test"):
        tr = json.load(open(os.path.join(root, "transforms_%s.json" % split)))
        ref = pts_doc["frames"][split]
        assert len(ref) == len(tr["frames"]), split
        for i, fr in enumerate(tr["frames"]):
            assert fr["file_path"] == "./%s/r_%d" % (split, i), fr["file_path"]
            assert os.path.exists(os.path.join(root, fr["file_path"] + ".png"))
            c2w = np.array(fr["transform_matrix"], dtype=np.float64)
            uv, depth = project_gl(c2w, tr["camera_angle_x"], W, H, pts)
            d_px = np.abs(uv - np.array(ref[i]["pixels"])).max()
            d_z = np.abs(depth - np.array(ref[i]["depth"])).max()
            worst_px, worst_depth = max(worst_px, d_px), max(worst_depth, d_z)
            r = np.linalg.norm(c2w[:3, 3])
            if abs(r - 4.0) > 1e-5:
                print("camera %s/%d at radius %r" % (split, i, r))
                ok = False
            n_frames += 1
    print("Blender layout, %d frames x %d points: max |pixel - world_to_camera_view| = %.3g px,"
          " max |depth diff| = %.3g" % (n_frames, len(pts), worst_px, worst_depth))
    ok &= worst_px < TOL_PX

    # 2. DTU layout
    if not has_dtu:
        print("no DTU copy at %s: DTU checks skipped" % dtu)
        dd = {"frames": []}
    else:
        dd = json.load(open(os.path.join(dtu, "points.json")))
        cams = np.load(os.path.join(dtu, "cameras.npz"))
        pts_dtu = np.array(dd["points"], dtype=np.float64)
        s, o = dd["dtu_scale"], np.array(dd["dtu_offset"])
        assert np.allclose(pts_dtu, s * pts + o, atol=1e-9)
        worst_p, worst_pn, worst_dz, worst_k = 0.0, 0.0, 0.0, 0.0
        max_norm_radius = 0.0
        test = json.load(open(os.path.join(root, "transforms_test.json")))
        f_ref = 0.5 * W / math.tan(0.5 * test["camera_angle_x"])
        for i, fr in enumerate(dd["frames"]):
            wm = cams["world_mat_%d" % i]
            sm = cams["scale_mat_%d" % i]
            assert wm.shape == (4, 4) and sm.shape == (4, 4)
            assert wm.dtype == np.float64 and sm.dtype == np.float64
            assert np.array_equal(wm[3], [0, 0, 0, 1]) and np.array_equal(sm[3], [0, 0, 0, 1])
            ref = np.array(fr["pixels"])
            uv, z = project_p(wm, pts_dtu)
            worst_p = max(worst_p, np.abs(uv - ref).max())
            worst_dz = max(worst_dz, np.abs(z - np.array(fr["depth"])).max())
            xn = (np.linalg.inv(sm) @ np.c_[pts_dtu, np.ones(len(pts_dtu))].T).T[:, :3]
            max_norm_radius = max(max_norm_radius, np.linalg.norm(xn, axis=1).max())
            uvn, _ = project_p(wm @ sm, xn)
            worst_pn = max(worst_pn, np.abs(uvn - ref).max())
            # K and pose back from P (RQ via QR of the flipped matrix)
            m = wm[:3, :3]
            q, r = np.linalg.qr(np.flipud(m).T)
            k = np.flipud(np.fliplr(r.T))
            k = k @ np.diag(np.sign(np.diag(k)))
            k /= k[2, 2]
            worst_k = max(worst_k, np.abs(k - [[f_ref, 0, W / 2], [0, f_ref, H / 2], [0, 0, 1]]).max())
            centre = -np.linalg.solve(m, wm[:3, 3])
            c_b = np.array(test["frames"][i]["transform_matrix"])[:3, 3]
            assert np.allclose(centre, s * c_b + o, atol=1e-3), (centre, s * c_b + o)
        print("DTU layout, %d frames: max |K[R|t]X - pixel| = %.3g px, via world_mat @ scale_mat on "
              "normalised points = %.3g px, max depth diff = %.3g DTU units, max |K - K_ref| = %.3g"
              % (len(dd["frames"]), worst_p, worst_pn, worst_dz, worst_k))
        print("normalised points: max radius %.4f (< 1)" % max_norm_radius)
        ok &= worst_p < TOL_PX and worst_pn < TOL_PX and max_norm_radius < 1.0

    # 3. images
    cut = 0
    outside = 0
    for i, fr in enumerate(dd["frames"]):
        rgba = np.asarray(Image.open(os.path.join(root, fr["source"] + ".png"))).astype(np.int64)
        img = Image.open(os.path.join(dtu, fr["image"]))
        msk = Image.open(os.path.join(dtu, fr["mask"]))
        assert img.mode == "RGB" and msk.mode == "L", (img.mode, msk.mode)
        want = (rgba[..., :3] * rgba[..., 3:4] + 127) // 255
        if not np.array_equal(np.asarray(img), want):
            print("image %d differs from the composite" % i)
            ok = False
        if not np.array_equal(np.asarray(msk), np.where(rgba[..., 3] >= 128, 255, 0)):
            print("mask %d differs from alpha >= 0.5" % i)
            ok = False
    for split in ("train", "val", "test"):
        for i, fr in enumerate(pts_doc["frames"][split]):
            a = np.asarray(Image.open(os.path.join(root, fr["file_path"] + ".png")))[..., 3]
            if a[0].any() or a[-1].any() or a[:, 0].any() or a[:, -1].any():
                cut += 1
            for x, y in fr["pixels"]:
                u, v = int(math.floor(x)), int(math.floor(y))
                if not (0 <= u < W and 0 <= v < H):
                    outside += 1
                    continue
                if not a[max(v - 1, 0):v + 2, max(u - 1, 0):u + 2].any():
                    print("%s/%d: point at (%.2f, %.2f) lands on empty pixels" % (split, i, x, y))
                    ok = False
    print("frames whose object touches the image border: %d%s"
          % (cut, " (allowed)" if allow_border else ""))
    if outside:
        print("points projected outside the image (not checked): %d" % outside)
    ok &= cut == 0 or allow_border
    print("OK" if ok else "FAILED")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
