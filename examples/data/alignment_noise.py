#!/usr/bin/env python3
"""How much of a refined-pose run's Chamfer-L1 the evaluation's alignment alone costs.

`examples/dvr_multiview` evaluates a run that refines poses in the frame the scene was
learnt in: the similarity that best maps the refined training-camera centres onto the
true ones moves the mesh into the dataset's frame. Centres that are each a little off
make that similarity a little off, and a perfect mesh placed by it scores worse than it
is. This script measures that floor: it takes a mesh of the true-pose run (already in the
dataset's frame), the residuals of a refined run's aligned centres (`poses.json`,
`cam_to_world_aligned`) against the true centres, flips each residual's sign at random
(same sizes and directions, no common part), fits the similarity as the example does
(Umeyama), places the mesh by it and scores it against the source mesh, `--draws` times.

    python3 examples/data/alignment_noise.py --data examples/data/wuson \
        --mesh out/dvr_true/mesh.ply --poses out/lm_final/poses.json

Chamfer-L1 here is ONet's (mean of both directions' mean nearest distance, unit-cube
normalisation of the source mesh) from 30 000 area-weighted samples per mesh, so it reads
somewhat above the example's 100 000-sample figure; compare ratios, not values.
Needs only numpy.
"""
import argparse
import json
import os

import numpy as np


def read_ply(path):
    """Vertices [V, 3] and triangles [F, 3] of an ASCII or binary little-endian PLY
    (polygons fanned into triangles)."""
    with open(path, "rb") as f:
        header = []
        while True:
            line = f.readline().decode("ascii", "replace").strip()
            header.append(line)
            if line == "end_header":
                break
        body = f.read()
    fmt = next(l.split()[1] for l in header if l.startswith("format"))
    nv = nf = 0
    vprops, element = [], None
    for l in header:
        t = l.split()
        if t[:1] == ["element"]:
            element = t[1]
            if element == "vertex":
                nv = int(t[2])
            elif element == "face":
                nf = int(t[2])
        elif t[:1] == ["property"] and element == "vertex":
            vprops.append(t[1])
    faces = []
    if fmt == "ascii":
        rows = body.decode("ascii").split("\n")
        v = np.array([[float(x) for x in rows[k].split()[:3]] for k in range(nv)])
        for k in range(nf):
            t = [int(x) for x in rows[nv + k].split()]
            faces += [[t[1], t[j], t[j + 1]] for j in range(2, t[0])]
    else:
        size = {"float": 4, "uchar": 1, "int": 4, "double": 8}
        dt = np.dtype([(f"p{i}", {"float": "<f4", "uchar": "u1", "int": "<i4",
                                  "double": "<f8"}[p]) for i, p in enumerate(vprops)])
        stride = sum(size[p] for p in vprops)
        verts = np.frombuffer(body[: nv * stride], dtype=dt)
        v = np.stack([verts["p0"], verts["p1"], verts["p2"]], 1).astype(np.float64)
        off = nv * stride
        for _ in range(nf):
            n = body[off]
            idx = np.frombuffer(body[off + 1: off + 1 + 4 * n], "<i4")
            faces += [[idx[0], idx[j], idx[j + 1]] for j in range(1, n - 1)]
            off += 1 + 4 * n
    return v, np.array(faces, dtype=np.int64)


def sample(v, f, n, seed):
    rng = np.random.default_rng(seed)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    i = rng.choice(len(f), n, p=area / area.sum())
    u, w = rng.random(n), rng.random(n)
    flip = u + w > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    return a[i] + u[:, None] * (b[i] - a[i]) + w[:, None] * (c[i] - a[i])


def nearest(x, y):
    out = np.empty(len(x))
    yy = (y**2).sum(1)
    for k in range(0, len(x), 2048):
        xs = x[k: k + 2048]
        d2 = (xs**2).sum(1)[:, None] - 2 * xs @ y.T + yy[None]
        out[k: k + 2048] = np.sqrt(np.maximum(d2.min(1), 0))
    return out


def umeyama(x, y):
    """The similarity (s, R, t) minimising Σ‖s R xᵢ + t − yᵢ‖²."""
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    u, s, vt = np.linalg.svd(yc.T @ xc / len(x))
    d = np.eye(3)
    if np.linalg.det(u @ vt) < 0:
        d[2, 2] = -1
    r = u @ d @ vt
    scale = np.trace(np.diag(s) @ d) / (xc**2).sum(1).mean()
    return scale, r, my - scale * r @ mx


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True)
    ap.add_argument("--mesh", required=True, help="a true-pose run's mesh.ply")
    ap.add_argument("--poses", required=True, help="a refined run's poses.json")
    ap.add_argument("--draws", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    scene = json.load(open(os.path.join(a.data, "scene.json")))
    m = np.array(scene["normalisation"]["matrix"])
    gv, gf = read_ply(scene["mesh"])
    gv = gv @ m[:3, :3].T + m[:3, 3]
    lo, hi = gv.min(0), gv.max(0)
    centre, scale = (lo + hi) / 2, 1 / (hi - lo).max()
    gt = (sample(gv, gf, 30000, 1) - centre) * scale

    def chamfer(points):
        p = (points - centre) * scale
        return (nearest(p, gt).mean() + nearest(gt, p).mean()) / 2

    frames = json.load(open(os.path.join(a.data, "transforms_train.json")))["frames"]
    true = {os.path.normpath(os.path.join(a.data, f["file_path"])): np.array(f["transform_matrix"])[:3, 3]
            for f in frames}
    views = json.load(open(a.poses))["views"]
    def key(name):
        # The split's folder and the file's stem ("train/r_0"), whatever the prefix.
        parts = os.path.normpath(os.path.splitext(name)[0]).split(os.sep)
        return "/".join(parts[-2:])

    truth = {key(k): c for k, c in true.items()}
    c = np.array([truth[key(v["name"])] for v in views])
    residual = np.array([np.array(v["cam_to_world_aligned"])[:3, 3] for v in views]) - c
    rel = (np.linalg.norm(residual, axis=1) / np.linalg.norm(c, axis=1)).mean()
    v, f = read_ply(a.mesh)
    q = sample(v, f, 30000, 2)
    base = chamfer(q)
    rng = np.random.default_rng(a.seed)
    scores = []
    for _ in range(a.draws):
        signs = rng.choice([-1.0, 1.0], size=(len(c), 1))
        s, r, t = umeyama(c + signs * residual, c)
        scores.append(chamfer(s * q @ r.T + t))
    scores = np.array(scores)
    print(f"residuals: mean {100 * rel:.3f} % of the distance over {len(c)} cameras")
    print(f"mesh as it is: Chamfer-L1 {base:.5f}")
    print(f"placed by {a.draws} noisy alignments: mean {scores.mean():.5f} "
          f"(min {scores.min():.5f}, max {scores.max():.5f}), {scores.mean() / base:.3f}x")


if __name__ == "__main__":
    main()
