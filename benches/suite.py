"""Run the examples at their defaults on every scene of the scene suite, with the plain
PyTorch NeRFs beside them, and write one table and one plot.

    cargo build --release --examples
    venv/bin/python benches/suite.py                       # report set, full budgets
    venv/bin/python benches/suite.py --set tuning --minutes 3 --runs nerf,torch

The suite is examples/data/suite (examples/data/render_suite.sh; `suite.json` names the
tuning and the report set). Per scene, one after another on the same cores (each run
alone on the machine):

- `nerf`: `examples/nerf --data SCENE --minutes M` (frequency encoding, its defaults);
- `nerf_hash`: the same with `--encoding hash`;
- `torch`: benches/torch/nerf_train.py `--model nerf` on the box the `nerf` run chose
  (its metrics.json `scene_box`), at each learning rate of `--torch-lrs`; the best counts;
- `torch_hash`: the same with `--model hash` (learning rates `--torch-hash-lrs`);
- `sparse_views`: `examples/sparse_views --data SCENE --minutes S` (plain, regularised);
- `dvr` / `idr`: `examples/dvr_multiview --model dvr|idr --data SCENE --minutes D`.

The runs of one scene alternate between the crate and PyTorch (nerf, torch, nerf_hash,
torch_hash, ...). Writes under `--out` (default target/suite): each run's folder,
`suite.json` (every figure), `suite.md` (one table: held-out PSNR per scene and run, mask
IoU and Chamfer-L1 for dvr_multiview, the mean and the worst scene) and `suite.svg` (the
held-out PSNR per scene and run). Runs whose `metrics.json` exists are not run again
(`--fresh` reruns them).
"""
import argparse
import json
import os
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2"]


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--suite", default=os.path.join(ROOT, "examples/data/suite"))
    p.add_argument("--set", default="report", choices=["report", "tuning", "all"])
    p.add_argument("--scenes", default=None, help="comma-separated names (default: the set)")
    p.add_argument("--runs", default="nerf,torch,nerf_hash,torch_hash,sparse_views,dvr,idr")
    p.add_argument("--minutes", type=float, default=10.0, help="nerf and its PyTorch twins")
    p.add_argument("--sparse-minutes", type=float, default=3.0, help="per sparse_views run")
    p.add_argument("--dvr-minutes", type=float, default=15.0)
    p.add_argument("--torch-lrs", default="5e-4,1e-3,5e-3")
    p.add_argument("--torch-hash-lrs", default="1e-3,1e-2")
    p.add_argument("--python", default=sys.executable, help="interpreter with torch")
    p.add_argument("--bin", default=os.path.join(ROOT, "target/release/examples"))
    p.add_argument("--out", default=os.path.join(ROOT, "target/suite"))
    p.add_argument("--fresh", action="store_true")
    a = p.parse_args()
    for flag, v in (("--minutes", a.minutes), ("--sparse-minutes", a.sparse_minutes),
                    ("--dvr-minutes", a.dvr_minutes)):
        if not v > 0:
            raise SystemExit("%s must be positive" % flag)
    known = {"nerf", "torch", "nerf_hash", "torch_hash", "sparse_views", "dvr", "idr"}
    a.runs = [r for r in a.runs.split(",") if r]
    bad = [r for r in a.runs if r not in known]
    if bad:
        raise SystemExit("--runs: unknown %s (known: %s)" % (bad, sorted(known)))
    a.torch_lrs = [float(x) for x in a.torch_lrs.split(",")]
    a.torch_hash_lrs = [float(x) for x in a.torch_hash_lrs.split(",")]
    return a


def scenes_of(a):
    with open(os.path.join(a.suite, "suite.json")) as f:
        suite = json.load(f)
    if a.scenes:
        names = a.scenes.split(",")
        unknown = [n for n in names if n not in suite["scenes"]]
        if unknown:
            raise SystemExit("--scenes: %s not in %s/suite.json" % (unknown, a.suite))
        return names
    return suite["tuning"] + suite["report"] if a.set == "all" else suite[a.set]


def run(cmd, out_dir, log_name="log.txt"):
    """Runs cmd once (unless out_dir/metrics.json exists), logging to out_dir."""
    os.makedirs(out_dir, exist_ok=True)
    metrics = os.path.join(out_dir, "metrics.json")
    if os.path.exists(metrics):
        with open(metrics) as f:
            return json.load(f)
    print("$ " + " ".join(cmd), flush=True)
    t0 = time.time()
    with open(os.path.join(out_dir, log_name), "w") as log:
        rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT).returncode
    print("  exit %d after %.0f s" % (rc, time.time() - t0), flush=True)
    if rc != 0 or not os.path.exists(metrics):
        return {"error": "exit %d, see %s" % (rc, os.path.join(out_dir, log_name))}
    with open(metrics) as f:
        return json.load(f)


def torch_runs(a, scene_dir, out, model, lrs, box):
    """The PyTorch twin at each learning rate; the best run's figures and every PSNR."""
    best, tried = None, {}
    for lr in lrs:
        d = os.path.join(out, "%s_lr%g" % (model, lr))
        os.makedirs(d, exist_ok=True)
        cmd = [a.python, os.path.join(ROOT, "benches/torch/nerf_train.py"), "--data", scene_dir,
               "--model", model, "--lr", str(lr), "--minutes", str(a.minutes),
               "--aabb"] + [str(v) for v in box] + ["--out", os.path.join(d, "metrics.json")]
        m = run(cmd, d)
        tried[str(lr)] = m.get("psnr")
        if "psnr" in m and (best is None or m["psnr"] > best["psnr"]):
            best = dict(m, lr=lr)
    return dict(best or {"error": "no run finished"}, psnr_by_lr=tried)


def run_scene(a, name):
    scene_dir = os.path.join(a.suite, name)
    out = os.path.join(a.out, name)
    res = {}
    nerf = os.path.join(a.bin, "nerf")
    if "nerf" in a.runs or "torch" in a.runs or "torch_hash" in a.runs:
        d = os.path.join(out, "nerf")
        res["nerf"] = run([nerf, "--data", scene_dir, "--minutes", str(a.minutes), "--out", d], d)
    box = res.get("nerf", {}).get("scene_box")
    if "torch" in a.runs and box:
        res["torch"] = torch_runs(a, scene_dir, out, "nerf", a.torch_lrs, box)
    if "nerf_hash" in a.runs:
        d = os.path.join(out, "nerf_hash")
        res["nerf_hash"] = run([nerf, "--data", scene_dir, "--encoding", "hash", "--minutes",
                                str(a.minutes), "--out", d], d)
    if "torch_hash" in a.runs and box:
        res["torch_hash"] = torch_runs(a, scene_dir, out, "hash", a.torch_hash_lrs, box)
    if "sparse_views" in a.runs:
        d = os.path.join(out, "sparse_views")
        m = run([os.path.join(a.bin, "sparse_views"), "--data", scene_dir, "--minutes",
                 str(a.sparse_minutes), "--out", d], d)
        for part in ("plain", "regularised"):
            p = os.path.join(d, part, "metrics.json")
            if os.path.exists(p):
                with open(p) as f:
                    m[part + "_psnr"] = json.load(f).get("psnr")
        res["sparse_views"] = m
    for model in ("dvr", "idr"):
        if model in a.runs:
            d = os.path.join(out, model)
            res[model] = run([os.path.join(a.bin, "dvr_multiview"), "--model", model, "--data",
                              scene_dir, "--minutes", str(a.dvr_minutes), "--out", d], d)
    return res


PSNR_COLUMNS = [("nerf", "nerf"), ("torch", "PyTorch NeRF"), ("nerf_hash", "nerf --encoding hash"),
                ("torch_hash", "PyTorch hash NeRF"), ("sparse_plain", "sparse_views plain"),
                ("sparse_reg", "sparse_views regularised")]


def psnr_of(res, key):
    if key == "sparse_plain":
        return res.get("sparse_views", {}).get("plain_psnr")
    if key == "sparse_reg":
        return res.get("sparse_views", {}).get("regularised_psnr")
    return res.get(key, {}).get("psnr")


def fmt(v, digits=2):
    return "—" if v is None else ("%.*f" % (digits, v))


def table(results):
    cols = [(k, t) for k, t in PSNR_COLUMNS if any(psnr_of(r, k) is not None for r in results.values())]
    dvr = [m for m in ("dvr", "idr") if any(m in r for r in results.values())]
    head = ["scene"] + [t for _, t in cols]
    for m in dvr:
        head += ["%s mask IoU" % m, "%s masked PSNR" % m, "%s Chamfer-L1" % m]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    rows = {}
    for name, r in results.items():
        vals = [psnr_of(r, k) for k, _ in cols]
        for m in dvr:
            mm = r.get(m, {})
            vals += [mm.get("mask_iou"), mm.get("psnr_masked"), mm.get("chamfer_l1")]
        rows[name] = vals
        lines.append("| " + " | ".join([name] + [fmt(v, 4 if i >= len(cols) else 2)
                                                 for i, v in enumerate(vals)]) + " |")
    n = len(head) - 1
    for label, pick in (("mean", lambda xs: sum(xs) / len(xs)), ("worst", None)):
        cells = []
        for i in range(n):
            xs = [v[i] for v in rows.values() if v[i] is not None]
            if not xs:
                cells.append("—")
                continue
            if pick is None:  # worst: lowest PSNR / IoU, highest Chamfer
                lower_better = i >= len(cols) and (i - len(cols)) % 3 == 2
                v = max(xs) if lower_better else min(xs)
            else:
                v = pick(xs)
            cells.append(fmt(v, 4 if i >= len(cols) else 2))
        lines.append("| **%s** | " % label + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n", cols


def plot(results, cols, path):
    """Grouped bars: held-out PSNR per scene and run, as a plain SVG."""
    names = list(results)
    w, h, left, bottom, top = 120 * max(len(names), 1) + 220, 360, 50, 40, 20
    vals = [[psnr_of(results[n], k) for k, _ in cols] for n in names]
    hi = max([v for row in vals for v in row if v is not None] + [1.0])
    ymax = 5.0 * (int(hi / 5.0) + 1)
    ph = h - bottom - top
    y = lambda v: top + ph * (1.0 - v / ymax)
    out = ['<svg xmlns="http://www.w3.org/2000/svg" width="%d" height="%d" font-family="sans-serif" font-size="11">' % (w, h),
           '<rect width="100%" height="100%" fill="white"/>']
    for t in range(0, int(ymax) + 1, 5):
        out.append('<line x1="%d" x2="%d" y1="%.1f" y2="%.1f" stroke="#ddd"/>' % (left, w - 200, y(t), y(t)))
        out.append('<text x="%d" y="%.1f" text-anchor="end">%d</text>' % (left - 4, y(t) + 4, t))
    out.append('<text x="12" y="%d" transform="rotate(-90 12 %d)" text-anchor="middle">held-out PSNR (dB)</text>' % (h // 2, h // 2))
    group = 120
    bw = (group - 20) / max(len(cols), 1)
    for i, n in enumerate(names):
        x0 = left + 10 + i * group
        for j, v in enumerate(vals[i]):
            if v is None:
                continue
            out.append('<rect x="%.1f" y="%.1f" width="%.1f" height="%.1f" fill="%s"/>'
                       % (x0 + j * bw, y(v), bw - 1, y(0) - y(v), COLOURS[j % len(COLOURS)]))
        out.append('<text x="%.1f" y="%d" text-anchor="middle">%s</text>' % (x0 + (group - 20) / 2, h - bottom + 16, n))
    for j, (_, t) in enumerate(cols):
        yy = top + 16 * j
        out.append('<rect x="%d" y="%d" width="10" height="10" fill="%s"/>' % (w - 190, yy, COLOURS[j % len(COLOURS)]))
        out.append('<text x="%d" y="%d">%s</text>' % (w - 175, yy + 9, t))
    out.append("</svg>")
    with open(path, "w") as f:
        f.write("\n".join(out) + "\n")


def main():
    a = parse_args()
    names = scenes_of(a)
    if a.fresh and os.path.isdir(a.out):
        import shutil
        shutil.rmtree(a.out)
    os.makedirs(a.out, exist_ok=True)
    results = {}
    for name in names:
        results[name] = run_scene(a, name)
        with open(os.path.join(a.out, "suite.json"), "w") as f:
            json.dump({"args": vars(a), "results": results}, f, indent=1, default=str)
    md, cols = table(results)
    with open(os.path.join(a.out, "suite.md"), "w") as f:
        f.write(md)
    plot(results, cols, os.path.join(a.out, "suite.svg"))
    print(md)


if __name__ == "__main__":
    main()
