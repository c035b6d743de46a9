"""Where two groups of reconstructions differ from the source mesh, by height.

Chamfer-L1 is the mean of two one-sided distances: accuracy (from the reconstruction's
surface to the source's) and completeness (from the source's surface to the
reconstruction's). This script samples both surfaces uniformly by area, reports both
sides for every mesh, and splits the completeness of each group (the mean over its meshes
at every source sample) into height bands of equal sample count along the dataset's up
axis (z), so that a difference between two groups of runs can be placed on the object.

    python3 examples/data/chamfer_by_height.py --data examples/data/wuson \\
        --group true out/dvr_true out/dvr_true_s1 \\
        --group refined out/lm_fixed15 out/lm_fixed_s2

Each run folder holds the `mesh.ply` that `examples/dvr_multiview/` writes (in the
dataset's frame). The source mesh and its normalisation come from the dataset's
`scene.json` (`mesh`, `normalisation.matrix`), as in the example; distances are in the
source's unit cube (ONet's normalisation: centred on its bounding box, the longest side
1). Needs numpy and plyfile. Absolute figures differ a little from the example's
`chamfer_l1` (another sampler and sample count); compare groups with each other.
"""

import argparse
import io
import json
import os

import numpy as np
from plyfile import PlyData


def read_mesh(path, matrix=None):
    """Vertices (n, 3) and triangles (m, 3) of a PLY file, skipping header lines that are
    not PLY keywords (some exporters write a bare "Created by ..." line)."""
    with open(path, "rb") as f:
        data = f.read()
    end = data.index(b"end_header")
    header = data[:end].split(b"\n")
    keep = [l for l in header if l.split(b" ")[0] in (b"ply", b"format", b"comment",
                                                       b"obj_info", b"element",
                                                       b"property", b"")]
    ply = PlyData.read(io.BytesIO(b"\n".join(keep) + data[end:]))
    v = np.stack([ply["vertex"][k] for k in "xyz"], 1).astype(np.float64)
    faces = np.stack(ply["face"]["vertex_indices"]).astype(np.int64)
    if matrix is not None:
        v = v @ matrix[:3, :3].T + matrix[:3, 3]
    return v, faces


def sample_surface(v, faces, n, rng):
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    idx = rng.choice(len(faces), n, p=area / area.sum())
    u, w = rng.random(n), rng.random(n)
    flip = u + w > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    return a[idx] + u[:, None] * (b[idx] - a[idx]) + w[:, None] * (c[idx] - a[idx])


def nearest_distance(p, q, chunk=256):
    """For each row of p, the distance to the nearest row of q (brute force, chunk x len(q)
    distances at a time: 61 MB for the default 30 000 samples)."""
    out = np.empty(len(p))
    qq = (q * q).sum(1)
    for i in range(0, len(p), chunk):
        x = p[i:i + chunk]
        d = (x * x).sum(1)[:, None] - 2 * x @ q.T + qq[None]
        out[i:i + chunk] = np.sqrt(np.maximum(d.min(1), 0))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="dataset folder with scene.json")
    ap.add_argument("--group", nargs="+", action="append", required=True,
                    metavar=("NAME", "RUN"), help="a name and run folders (mesh.ply)")
    ap.add_argument("--samples", type=int, default=30000)
    ap.add_argument("--bands", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    scene = json.load(open(os.path.join(args.data, "scene.json")))
    matrix = np.array(scene["normalisation"]["matrix"], dtype=np.float64)
    src_v, src_f = read_mesh(scene["mesh"], matrix)
    lo, hi = src_v.min(0), src_v.max(0)
    centre, scale = (lo + hi) / 2, 1 / (hi - lo).max()
    rng = np.random.default_rng(args.seed)
    src = (sample_surface(src_v, src_f, args.samples, rng) - centre) * scale
    completeness = {}
    for name, *runs in args.group:
        per_run = []
        for run in runs:
            v, f = read_mesh(os.path.join(run, "mesh.ply"))
            pts = (sample_surface(v, f, args.samples, rng) - centre) * scale
            acc, comp = nearest_distance(pts, src), nearest_distance(src, pts)
            per_run.append(comp)
            print(f"{name:>10} {run}: accuracy {acc.mean():.5f}, completeness "
                  f"{comp.mean():.5f}, Chamfer-L1 {(acc.mean() + comp.mean()) / 2:.5f}")
        completeness[name] = np.mean(per_run, 0)
    edges = np.quantile(src[:, 2], np.linspace(0, 1, args.bands + 1))
    print("completeness (1e-3 of the unit cube) by height band, the lowest first:")
    print("  z band           " + "".join(f"{n:>12}" for n in completeness))
    for lo_z, hi_z in zip(edges[:-1], edges[1:]):
        band = (src[:, 2] >= lo_z) & (src[:, 2] <= hi_z)
        print(f"  [{lo_z:+.3f}, {hi_z:+.3f}]" +
              "".join(f"{1e3 * c[band].mean():>12.2f}" for c in completeness.values()))


if __name__ == "__main__":
    main()
