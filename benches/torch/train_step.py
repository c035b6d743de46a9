"""PyTorch twin of benches/train_step.rs: the same models, batches, losses and optimiser.

    python3 -m venv venv && venv/bin/pip install torch numpy
    venv/bin/python benches/torch/train_step.py --model nerf --steps 20 [--phases]

Threads: torch.set_num_threads(N) with N = --threads (default: the machine's cores, as
candle's CPU pool). Prints one JSON line in the format of the Rust bench.
"""
import argparse
import json
import math
import os
import time

import torch


def freq_encode(x, n_freqs):
    # [x, sin(2^k pi x), cos(2^k pi x)] for k < n_freqs, grouped as the crate's
    # FrequencyEncoding (input, then all sines, then all cosines).
    scales = (2.0 ** torch.arange(n_freqs, dtype=x.dtype)) * math.pi
    y = (x[:, None, :] * scales[None, :, None]).reshape(x.shape[0], -1)
    return torch.cat([x, torch.sin(y), torch.cos(y)], dim=1)


class TruncExp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(max=15.0))


class Nerf(torch.nn.Module):
    def __init__(self, width=64, depth=4, color_width=64):
        super().__init__()
        layers, d = [], 63
        for _ in range(depth):
            layers += [torch.nn.Linear(d, width), torch.nn.ReLU()]
            d = width
        layers += [torch.nn.Linear(width, 1 + width)]
        self.trunk = torch.nn.Sequential(*layers)
        self.head = torch.nn.Sequential(
            torch.nn.Linear(27 + width, color_width),
            torch.nn.ReLU(),
            torch.nn.Linear(color_width, 3),
        )
        self.width = width

    def forward(self, pos, dirs):
        out = self.trunk(freq_encode(pos, 10))
        sigma = TruncExp.apply(out[:, 0] - 1.0)
        unit = dirs / dirs.norm(dim=1, keepdim=True).clamp_min(1e-12)
        rgb = torch.sigmoid(self.head(torch.cat([freq_encode(unit, 4), out[:, 1:]], 1)))
        return sigma, rgb


def composite(sigma, rgb, starts, ends, norms):
    # sigma [R, S], rgb [R, S, 3]; w_i = T_i (1 - exp(-sigma_i delta_i)).
    delta = (ends - starts) * norms[:, None]
    x = sigma * delta
    alpha = -torch.expm1(-x)
    trans = torch.exp(-torch.cat([torch.zeros_like(x[:, :1]), torch.cumsum(x, 1)[:, :-1]], 1))
    w = trans * alpha
    return (w[..., None] * rgb).sum(1)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--model", default="nerf", choices=["nerf", "occupancy"])
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--phases", action="store_true")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    if a.model == "nerf":
        net = Nerf()
        r, s = 1024, 64
        target = torch.rand(r, 3)
        aim = torch.rand(r, 3) - 0.5
        origins = torch.rand(r, 3) * 2 - 1
        origins = 4 * origins / origins.norm(dim=1, keepdim=True)
        dirs = aim - origins
        dirs = dirs / dirs.norm(dim=1, keepdim=True)
        near, far = 2.0, 6.0

        def forward(step):
            # jittered stratified edges: interior edge j in stratum j, as the crate's
            u = torch.rand(r, s - 1)
            inner = (torch.arange(1, s, dtype=torch.float32)[None] + u - 0.5) / s
            edges = near + (far - near) * torch.cat(
                [torch.zeros(r, 1), inner, torch.ones(r, 1)], 1)
            starts, ends = edges[:, :-1], edges[:, 1:]
            t = 0.5 * (starts + ends)
            pos = (origins[:, None] + t[..., None] * dirs[:, None]).reshape(-1, 3)
            d = dirs[:, None].expand(r, s, 3).reshape(-1, 3)
            sigma, rgb = net(pos, d)
            color = composite(sigma.reshape(r, s), rgb.reshape(r, s, 3), starts, ends,
                              dirs.norm(dim=1))
            return ((color - target) ** 2).mean()
    else:
        layers, d = [], 3
        for _ in range(4):
            layers += [torch.nn.Linear(d, 64), torch.nn.ReLU()]
            d = 64
        layers += [torch.nn.Linear(64, 1)]
        net = torch.nn.Sequential(*layers)
        points = torch.rand(1 << 16, 3) * 1.1 - 0.55
        labels = ((points ** 2).sum(1) <= 0.16).float()

        def forward(step):
            logits = net(points)[:, 0]
            return torch.nn.functional.binary_cross_entropy_with_logits(logits, labels)

    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    total, fwd, bwd, upd = [], [], [], []
    for step in range(a.warmup + a.steps):
        t0 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        loss = forward(step)
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        opt.step()
        t3 = time.perf_counter()
        last = loss.item()
        if step >= a.warmup:
            total.append(t3 - t0)
            fwd.append(t1 - t0)
            bwd.append(t2 - t1)
            upd.append(t3 - t2)
    med = lambda v: sorted(v)[len(v) // 2]
    print(json.dumps({
        "impl": "pytorch-" + torch.__version__, "model": a.model, "steps": a.steps,
        "median_s": round(med(total), 5), "forward_s": round(med(fwd), 5),
        "backward_s": round(med(bwd), 5), "update_s": round(med(upd), 5),
        "final_loss": round(last, 6), "threads": a.threads,
    }))


if __name__ == "__main__":
    main()
