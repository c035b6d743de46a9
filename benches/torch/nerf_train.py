"""The plain PyTorch NeRF that the crate's `nerf` example is compared with on the scene
suite: trains a radiance field on a Blender-layout scene for a time (or step) budget and
reports the mean PSNR on its test views.

    venv/bin/python benches/torch/nerf_train.py --data DIR --model nerf|hash --minutes M \
        [--steps N] --lr LR --aabb X0 Y0 Z0 X1 Y1 Z1 [--threads N] [--seed S] \
        [--samples 64] [--batch 1024] [--init torch|candle] --out FILE.json

Data: DIR/transforms_{train,test}.json (`camera_angle_x`; frames with `file_path`
relative to DIR without `.png`, `transform_matrix` camera-to-world in OpenGL axes: the
camera looks along -Z, +Y up); 8-bit RGBA PNGs, colours the sRGB bytes / 255. The ray
through pixel (u, v) passes through its centre (u + 0.5, v + 0.5): direction
((u + 0.5 - W/2)/f, -(v + 0.5 - H/2)/f, -1) in camera axes, f = W/2 / tan(angle_x/2),
rotated by the camera-to-world rotation, not normalised (delta = (t1 - t0) |d|). Where the
layout has points.json (examples/data/render_dataset.py's projected mesh vertices), the
script first reprojects those vertices through its own rays and prints the largest error.

Training: each step --batch pixels drawn uniformly over all training views, a random
background colour per ray composited into the target (rgb a + bg (1 - a)) and behind the
rendered colour (C + (1 - sum w) bg); --samples stratified intervals between the ray's
entry into and exit from the box --aabb (interior edges jittered, one uniform draw per
edge within its stratum, samples at the interval midpoints, as benches/torch/train_step.py
and the crate's stratified sampler); rays missing the box render the background. Volume
rendering alpha_i = 1 - exp(-sigma_i delta_i), w_i = T_i alpha_i; loss the mean squared
error over rays and channels; Adam (0.9, 0.999, 1e-8) at lr 0.1^f --lr, f the larger of
elapsed / budget and step / steps (log-linear decay to a tenth, as the crate's example).
Evaluation (not timed): every test view on white, the same samples at the bins' midpoints
(no jitter), 4096 rays a chunk; PSNR per view against the image composited on white.

Models:
  nerf: train_step.Nerf, the crate's NerfConfig::default() (src/volume/nerf_model.rs):
        frequency encoding L = 10 of the world position, 4 x 64 ReLU trunk to 1 + 64,
        density trunc_exp(raw - 3), colour head on the L = 4 encoding of the unit
        direction + the 64 features -> 64 -> 3, sigmoid.
  hash: examples/nerf/main.rs's nerf_config for --encoding hash: train_step.HashGrid over
        the box (each axis mapped to [-1, 1] first, as the crate's per-axis lo/hi) with
        src/encoding/hash.rs's HashGridConfig::default() for levels (16), features (2),
        base resolution (16) and table init (U(-1e-4, 1e-4)); log2 table size 15, the
        example's --hash-log2 default (examples/nerf/flags.rs, = the config's default;
        instant-NGP's 19 is for GPUs); finest resolution 5 max(W, H), at least 16
        (Dataset::hash_finest, src/data/scene.rs, the example's default without
        --hash-finest); then the trunk with depth 1: Linear(32, 64), ReLU, Linear(64, 65),
        and the same density and colour head as nerf.
  --init torch (default, as train_step.py builds Nerf): PyTorch's layer initialisation;
  --init candle: train_step.candle_init_, candle-nn's, as the crate's layers.

What differs from the crate's example: its default sampler is an occupancy grid (64^3,
updated every 16 steps, marching only the visible samples), this one is the classic
NeRF's stratified sampling over the whole box (the example's `--sampler stratified` is
the closer twin); no coarse-to-fine, no proposal networks, no supersampling, SSIM not
computed. Random draws differ from the crate's; their distributions match.

Writes --out (JSON): psnr (mean test PSNR), psnr_per_view, steps, train_seconds, model,
lr, aabb, samples, batch, threads, data, torch_version (and seed, init, sanity figures).
"""
import argparse
import json
import math
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)),
                                "..", "..", "examples", "data"))
from render_dataset import png_read  # noqa: E402
from train_step import HashGrid, Nerf, TruncExp, candle_init_, freq_encode  # noqa: E402


# ------------------------------------------------------------------ data and rays

def load_split(data, split):
    """-> (rays_o [N, 3], rays_d [N, 3], rgba [N, 4] in [0, 1], (W, H), views) of a split."""
    with open(os.path.join(data, "transforms_%s.json" % split)) as f:
        meta = json.load(f)
    angle_x = float(meta["camera_angle_x"])
    origins, dirs, colours, size = [], [], [], None
    for frame in meta["frames"]:
        w, h, ch, rows = png_read(os.path.join(data, frame["file_path"] + ".png"))
        img = np.frombuffer(b"".join(rows), np.uint8).reshape(h, w, ch).astype(np.float32) / 255.0
        if ch == 1 or ch == 2:
            img = np.concatenate([np.repeat(img[..., :1], 3, 2), img[..., 1:]], 2)
        if img.shape[2] == 3:
            img = np.concatenate([img, np.ones_like(img[..., :1])], 2)
        if size is not None and size != (w, h):
            raise ValueError("views of different sizes in %s: %s and %s" % (split, size, (w, h)))
        size = (w, h)
        o, d = camera_rays(np.asarray(frame["transform_matrix"], np.float64), w, h, angle_x)
        origins.append(o)
        dirs.append(d)
        colours.append(img.reshape(-1, 4))
    cat = lambda v: torch.from_numpy(np.concatenate(v).astype(np.float32))
    return cat(origins), cat(dirs), cat(colours), size, len(meta["frames"])


def focal(w, angle_x):
    return 0.5 * w / math.tan(0.5 * angle_x)


def camera_rays(c2w, w, h, angle_x):
    """Rays through the pixel centres, row-major; unnormalised directions (camera z = -1)."""
    f = focal(w, angle_x)
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5, indexing="xy")
    cam = np.stack([(u - 0.5 * w) / f, -(v - 0.5 * h) / f, -np.ones_like(u)], -1).reshape(-1, 3)
    d = cam @ c2w[:3, :3].T
    o = np.broadcast_to(c2w[:3, 3], d.shape)
    return o, d


def ray_box(o, d, lo, hi):
    """Entry and exit parameters of the rays in the box; near = far = 0 where they miss."""
    safe = torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t0, t1 = (lo - o) / safe, (hi - o) / safe
    near = torch.minimum(t0, t1).amax(1).clamp_min(0.0)
    far = torch.maximum(t0, t1).amin(1)
    hit = far > near
    zero = torch.zeros_like(near)
    return torch.where(hit, near, zero), torch.where(hit, far, zero), hit


def reprojection_error(data, size):
    """Largest distance (world units) between points.json's vertices and the points at
    their stated depth on this script's rays through their stated pixels; None without it."""
    path = os.path.join(data, "points.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        pts = json.load(f)
    if "frames" not in pts or "points" not in pts:
        return None
    world = np.asarray(pts["points"], np.float64)
    worst = 0.0
    for split in ("train", "test"):
        with open(os.path.join(data, "transforms_%s.json" % split)) as f:
            meta = json.load(f)
        w, h = size
        f_px = focal(w, float(meta["camera_angle_x"]))
        by_path = {fr["file_path"]: fr for fr in pts["frames"].get(split, [])}
        for frame in meta["frames"]:
            proj = by_path.get(frame["file_path"])
            if proj is None:
                continue
            c2w = np.asarray(frame["transform_matrix"], np.float64)
            for p, (x, y), depth in zip(world, proj["pixels"], proj["depth"]):
                d = c2w[:3, :3] @ np.array([(x - 0.5 * w) / f_px, -(y - 0.5 * h) / f_px, -1.0])
                worst = max(worst, float(np.linalg.norm(c2w[:3, 3] + depth * d - p)))
    return worst


# ------------------------------------------------------------------ models

class HashNerf(torch.nn.Module):
    """The crate's NeRF with --encoding hash: hash grid over the box, 1 x 64 trunk."""

    def __init__(self, lo, hi, finest, log2=15, width=64, color_width=64):
        super().__init__()
        self.register_buffer("lo", lo.clone())
        self.register_buffer("hi", hi.clone())
        self.grid = HashGrid(levels=16, features=2, log2=log2, base=16.0, finest=finest,
                             lo=-1.0, hi=1.0)
        d = self.grid.table.shape[1] * len(self.grid.levels)
        self.trunk = torch.nn.Sequential(
            torch.nn.Linear(d, width), torch.nn.ReLU(), torch.nn.Linear(width, 1 + width))
        self.head = torch.nn.Sequential(
            torch.nn.Linear(27 + width, color_width), torch.nn.ReLU(),
            torch.nn.Linear(color_width, 3))

    def forward(self, pos, dirs):
        x = (pos - self.lo) / (self.hi - self.lo) * 2.0 - 1.0
        out = self.trunk(self.grid(x))
        sigma = TruncExp.apply(out[:, 0] - 3.0)
        unit = dirs / dirs.norm(dim=1, keepdim=True).clamp_min(1e-12)
        rgb = torch.sigmoid(self.head(torch.cat([freq_encode(unit, 4), out[:, 1:]], 1)))
        return sigma, rgb


# ------------------------------------------------------------------ rendering

def render(net, o, d, near, far, samples, jitter):
    """Colour [R, 3] and opacity [R] of rays that hit the box (black background)."""
    r = o.shape[0]
    j = torch.arange(1, samples, dtype=o.dtype)[None]
    u = torch.rand(r, samples - 1) if jitter else torch.full((r, samples - 1), 0.5)
    inner = (j + u - 0.5) / samples
    frac = torch.cat([torch.zeros(r, 1), inner, torch.ones(r, 1)], 1)
    edges = near[:, None] + (far - near)[:, None] * frac
    starts, ends = edges[:, :-1], edges[:, 1:]
    t = 0.5 * (starts + ends)
    pos = (o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3)
    sigma, rgb = net(pos, d[:, None].expand(r, samples, 3).reshape(-1, 3))
    x = sigma.reshape(r, samples) * (ends - starts) * d.norm(dim=1)[:, None]
    alpha = -torch.expm1(-x)
    trans = torch.exp(-torch.cat([torch.zeros_like(x[:, :1]), torch.cumsum(x, 1)[:, :-1]], 1))
    w = trans * alpha
    return (w[..., None] * rgb.reshape(r, samples, 3)).sum(1), w.sum(1)


def render_on(net, o, d, near, far, hit, bg, samples, jitter):
    """Colour [R, 3] of the rays over background bg [R, 3]; rays missing the box = bg."""
    colour = bg.clone()
    if hit.any():
        c, acc = render(net, o[hit], d[hit], near[hit], far[hit], samples, jitter)
        colour = colour.index_put((hit.nonzero()[:, 0],), c + (1.0 - acc)[:, None] * bg[hit])
    return colour


# ------------------------------------------------------------------ main

def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True)
    p.add_argument("--model", choices=["nerf", "hash"], required=True)
    p.add_argument("--minutes", type=float, required=True)
    p.add_argument("--steps", type=int, default=None)
    p.add_argument("--lr", type=float, required=True)
    p.add_argument("--aabb", type=float, nargs=6, required=True,
                   metavar=("X0", "Y0", "Z0", "X1", "Y1", "Z1"))
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--samples", type=int, default=64)
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--init", choices=["torch", "candle"], default="torch")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    if not (a.minutes > 0 and a.lr > 0 and a.samples > 0 and a.batch > 0
            and (a.steps is None or a.steps > 0)):
        p.error("--minutes, --lr, --samples, --batch and --steps must be positive")
    lo, hi = torch.tensor(a.aabb[:3]), torch.tensor(a.aabb[3:])
    if not bool((lo < hi).all()):
        p.error("--aabb: X0 < X1, Y0 < Y1, Z0 < Z1")
    torch.set_num_threads(a.threads)
    torch.manual_seed(a.seed)
    np.random.seed(a.seed)

    t_load = time.perf_counter()
    o, d, rgba, size, views = load_split(a.data, "train")
    near, far, hit = ray_box(o, d, lo, hi)
    fg = rgba[:, 3] > 0.5
    fg_hit = float(hit[fg].float().mean()) if fg.any() else float("nan")
    bg_hit = float(hit[~fg].float().mean()) if (~fg).any() else float("nan")
    reproj = reprojection_error(a.data, size)
    print("train: %d views %dx%d, %d rays; foreground rays hitting the box %.4f, background "
          "%.4f; points.json reprojection error %s; loaded in %.1f s" % (
              views, size[0], size[1], o.shape[0], fg_hit, bg_hit,
              "n/a" if reproj is None else "%.2e" % reproj, time.perf_counter() - t_load),
          flush=True)
    if fg_hit < 0.99:
        print("warning: %.1f %% of the foreground pixels' rays miss --aabb" % (100 * (1 - fg_hit)),
              flush=True)

    if a.model == "nerf":
        net = Nerf()
    else:
        net = HashNerf(lo, hi, finest=max(5.0 * max(size), 16.0))
    if a.init == "candle":
        candle_init_(net)
    params = sum(q.numel() for q in net.parameters())
    opt = torch.optim.Adam(net.parameters(), lr=a.lr, betas=(0.9, 0.999), eps=1e-8,
                           weight_decay=0.0)

    budget = a.minutes * 60.0
    step, elapsed, last_print, loss_v, lr = 0, 0.0, 0.0, float("nan"), a.lr
    start = time.perf_counter()
    while True:
        elapsed = time.perf_counter() - start
        frac = max(elapsed / budget, step / a.steps if a.steps else 0.0)
        if frac >= 1.0:
            break
        lr = a.lr * 0.1 ** frac
        for g in opt.param_groups:
            g["lr"] = lr
        idx = torch.randint(0, o.shape[0], (a.batch,))
        bg = torch.rand(a.batch, 3)
        px = rgba[idx]
        target = px[:, :3] * px[:, 3:] + bg * (1.0 - px[:, 3:])
        colour = render_on(net, o[idx], d[idx], near[idx], far[idx], hit[idx], bg, a.samples,
                           jitter=True)
        loss = ((colour - target) ** 2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        loss_v = loss.item()
        if elapsed - last_print >= 30.0:
            last_print = elapsed
            print("step %d  loss %.5f  lr %.2e  %.0f s" % (step, loss_v, lr, elapsed), flush=True)
    train_seconds = time.perf_counter() - start
    print("trained %d steps in %.1f s, last loss %.5f (psnr %.2f)" % (
        step, train_seconds, loss_v, -10 * math.log10(max(loss_v, 1e-12))), flush=True)

    to, td, trgba, tsize, tviews = load_split(a.data, "test")
    tnear, tfar, thit = ray_box(to, td, lo, hi)
    per_view = tsize[0] * tsize[1]
    psnrs = []
    with torch.no_grad():
        for v in range(tviews):
            sl = slice(v * per_view, (v + 1) * per_view)
            out = []
            for c in range(sl.start, sl.stop, 4096):
                e = min(c + 4096, sl.stop)
                out.append(render_on(net, to[c:e], td[c:e], tnear[c:e], tfar[c:e], thit[c:e],
                                     torch.ones(e - c, 3), a.samples, jitter=False))
            img = torch.cat(out).clamp(0.0, 1.0)
            px = trgba[sl]
            truth = px[:, :3] * px[:, 3:] + (1.0 - px[:, 3:])
            mse = float(((img - truth) ** 2).mean())
            psnrs.append(-10.0 * math.log10(max(mse, 1e-12)))
    psnr = sum(psnrs) / len(psnrs)
    print("test psnr %.3f dB over %d views (%s, %d steps, %.1f s)" % (
        psnr, tviews, a.model, step, train_seconds), flush=True)

    result = {
        "psnr": psnr, "psnr_per_view": psnrs, "steps": step, "train_seconds": train_seconds,
        "model": a.model, "lr": a.lr, "aabb": a.aabb, "samples": a.samples, "batch": a.batch,
        "threads": a.threads, "data": a.data, "torch_version": torch.__version__,
        "seed": a.seed, "init": a.init, "minutes": a.minutes, "max_steps": a.steps,
        "params": params, "final_loss": loss_v, "foreground_rays_hitting_box": fg_hit,
        "reprojection_error": reproj,
    }
    if a.out and os.path.dirname(a.out):
        os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w") as f:
        json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
