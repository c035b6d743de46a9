"""PyTorch twin of benches/train_step.rs: the same models, batches, losses and optimiser.

    python3 -m venv venv && venv/bin/pip install torch numpy
    venv/bin/python benches/torch/train_step.py --model nerf --steps 20 [--phases] \
        [--device cuda] [--compile]

Threads: torch.set_num_threads(N) with N = --threads (default: the machine's cores, as
candle's CPU pool). `--device cuda` builds every tensor on the first GPU and waits for it
at the end of every timed phase; `--compile` runs the loss through `torch.compile`
(compiled during the warm-up steps). Prints one JSON line in the format of the Rust
bench, with `params`, the number of trainable values.

The onet_* models (examples/shape_prior's conditional occupancy network) are written
layer for layer after src/occupancy/{onet,pointnet,voxel,resnet,losses}.rs and
initialised as candle-nn initialises the crate's layers (candle_init_), not with
PyTorch's defaults; the random draws differ, the distributions match.
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
    scales = (2.0 ** torch.arange(n_freqs, dtype=x.dtype, device=x.device)) * math.pi
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
    """NeRF's 4 x 64 model on the frequency encoding; with `encoder` (the hash grid of
    benches/train_step.rs's nerf_hash, whose width is `d_in`) a 1 x 64 trunk on it."""

    def __init__(self, width=64, depth=4, color_width=64, encoder=None, d_in=63):
        super().__init__()
        self.encoder = encoder
        layers, d = [], d_in
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
        out = self.trunk(freq_encode(pos, 10) if self.encoder is None else self.encoder(pos))
        sigma = TruncExp.apply(out[:, 0] - 3.0)
        unit = dirs / dirs.norm(dim=1, keepdim=True).clamp_min(1e-12)
        rgb = torch.sigmoid(self.head(torch.cat([freq_encode(unit, 4), out[:, 1:]], 1)))
        return sigma, rgb


class SdfNet(torch.nn.Module):
    """4 x 64 softplus(beta = 100) on the frequency encoding L = 4, IDR's geometric
    initialisation to the SDF of a sphere of radius 0.35 (as MlpConfig::sdf)."""

    def __init__(self, width=64, depth=4, radius=0.35):
        super().__init__()
        dims = [27] + [width] * depth
        self.layers = torch.nn.ModuleList(
            [torch.nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:])])
        self.out = torch.nn.Linear(width, 1)
        with torch.no_grad():
            for i, lin in enumerate(self.layers):
                torch.nn.init.normal_(lin.weight, 0.0, math.sqrt(2.0) / math.sqrt(lin.out_features))
                torch.nn.init.zeros_(lin.bias)
                if i == 0:
                    lin.weight[:, 3:] = 0.0  # only the raw coordinates at initialisation
            torch.nn.init.normal_(self.out.weight, math.sqrt(math.pi) / math.sqrt(width), 1e-4)
            self.out.bias.fill_(-radius)
        self.act = torch.nn.Softplus(beta=100)

    def forward(self, x):
        h = freq_encode(x, 4)
        for lin in self.layers:
            h = self.act(lin(h))
        return self.out(h)[:, 0]


class HashGrid(torch.nn.Module):
    """instant-NGP's multiresolution hash encoding as encoding::HashGrid (default
    configuration): levels dense while (N + 1)^3 vertices fit 2^T rows, else the XOR of
    the vertex coordinates times the primes (wrapping 32-bit) masked to 2^T; trilinear
    weights; the table gradient by autograd (index_select's backward is an index_add)."""

    PRIMES = (1, 2654435761, 805459861)

    def __init__(self, levels=16, features=2, log2=15, base=16.0, finest=2048.0, lo=-1.0, hi=1.0):
        super().__init__()
        growth = (math.log(finest) - math.log(base)) / (levels - 1)
        cap = 1 << log2
        self.levels, offset = [], 0
        for l in range(levels):
            n = int(min(max(math.floor(base * math.exp(growth * l)), 1.0), finest))
            vertices = (n + 1) ** 3
            dense = vertices <= cap
            rows = vertices if dense else cap
            self.levels.append((n, offset, dense))
            offset += rows
        self.mask, self.lo, self.hi, self.features = cap - 1, lo, hi, features
        self.table = torch.nn.Parameter(torch.empty(offset, features).uniform_(-1e-4, 1e-4))
        corners = torch.tensor([[(c >> k) & 1 for k in range(3)] for c in range(8)])
        self.register_buffer("corners", corners)  # [8, 3]

    def forward(self, x):
        t = ((x - self.lo) / (self.hi - self.lo)).clamp(0.0, 1.0)
        outs = []
        for n, offset, dense in self.levels:
            u = t * n
            i = torch.floor(u).clamp(max=n - 1)
            w = u - i  # [N, 3], differentiable
            v = i.long()[:, None, :] + self.corners[None]  # [N, 8, 3]
            if dense:
                side = n + 1
                idx = v[..., 0] + v[..., 1] * side + v[..., 2] * side * side
            else:
                h = [(v[..., k] * p) & 0xFFFFFFFF for k, p in enumerate(self.PRIMES)]
                idx = torch.bitwise_xor(torch.bitwise_xor(h[0], h[1]), h[2]) & self.mask
            c = self.corners[None].to(w.dtype)
            weights = torch.where(c > 0, w[:, None, :], 1.0 - w[:, None, :]).prod(2)  # [N, 8]
            feats = self.table.index_select(0, (idx + offset).reshape(-1))
            feats = feats.reshape(x.shape[0], 8, self.features)
            outs.append((feats * weights[..., None]).sum(1))
        return torch.cat(outs, 1)


def candle_init_(module):
    """candle-nn's initialisation, as the crate's layers get it: every linear and
    convolution weight Kaiming-normal (fan-in, gain sqrt 2), every bias uniform in
    +-1/sqrt(fan-in); batch norms at gamma = 1, beta = 0 (PyTorch's default already)."""
    with torch.no_grad():
        for m in module.modules():
            if isinstance(m, (torch.nn.Linear, torch.nn.Conv2d, torch.nn.Conv3d)):
                fan_in = m.weight[0].numel()
                torch.nn.init.normal_(m.weight, 0.0, math.sqrt(2.0 / fan_in))
                if m.bias is not None:
                    bound = 1.0 / math.sqrt(fan_in)
                    torch.nn.init.uniform_(m.bias, -bound, bound)
    return module


class CBatchNorm(torch.nn.Module):
    """occupancy::onet's conditional normalisation: gamma(c) * x_hat + beta(c), x_hat the
    batch norm without affine over all B*Q points (training mode: biased variance in
    x_hat, running statistics updated with the unbiased one, momentum 0.1, eps 1e-5);
    gamma, beta linear in the code, starting at gamma = 1, beta = 0."""

    def __init__(self, c_dim, f_dim, momentum=0.1, eps=1e-5):
        super().__init__()
        self.gamma = torch.nn.Linear(c_dim, f_dim)
        self.beta = torch.nn.Linear(c_dim, f_dim)
        self.register_buffer("running_mean", torch.zeros(f_dim))
        self.register_buffer("running_var", torch.ones(f_dim))
        self.momentum, self.eps = momentum, eps

    def reset_(self):
        with torch.no_grad():
            for lin, bias in ((self.gamma, 1.0), (self.beta, 0.0)):
                lin.weight.zero_()
                lin.bias.fill_(bias)

    def forward(self, x, c):
        # x: [B, Q, H], c: [B, D]; gamma(c), beta(c) once per shape.
        b, q, h = x.shape
        xh = torch.nn.functional.batch_norm(
            x.reshape(b * q, h), self.running_mean, self.running_var, training=True,
            momentum=self.momentum, eps=self.eps).reshape(b, q, h)
        return self.gamma(c)[:, None] * xh + self.beta(c)[:, None]


class CBlock(torch.nn.Module):
    """net + fc1(relu(CN1(fc0(relu(CN0(net, c))), c))), fc1's weight starting at zero."""

    def __init__(self, c_dim, h):
        super().__init__()
        self.norm0, self.fc0 = CBatchNorm(c_dim, h), torch.nn.Linear(h, h)
        self.norm1, self.fc1 = CBatchNorm(c_dim, h), torch.nn.Linear(h, h)

    def forward(self, x, c):
        a = self.fc0(torch.relu(self.norm0(x, c)))
        return x + self.fc1(torch.relu(self.norm1(a, c)))


class OnetDecoder(torch.nn.Module):
    """occupancy::onet_decoder (ONet's CBatchNorm decoder) in training mode: fc_p, the
    blocks, norm_out, ReLU, fc_out; logits [B, Q] of points [B, Q, 3], codes [B, D]."""

    def __init__(self, hidden=128, blocks=5, code_dim=128):
        super().__init__()
        self.fc_p = torch.nn.Linear(3, hidden)
        self.blocks = torch.nn.ModuleList([CBlock(code_dim, hidden) for _ in range(blocks)])
        self.norm_out = CBatchNorm(code_dim, hidden)
        self.fc_out = torch.nn.Linear(hidden, 1)
        candle_init_(self)
        for m in self.modules():
            if isinstance(m, CBatchNorm):
                m.reset_()
        with torch.no_grad():
            for blk in self.blocks:
                blk.fc1.weight.zero_()

    def forward(self, p, c):
        net = self.fc_p(p)
        for blk in self.blocks:
            net = blk(net, c)
        return self.fc_out(torch.relu(self.norm_out(net, c)))[..., 0]


class PointNetEncoder(torch.nn.Module):
    """occupancy::pointnet_encoder's forward with F features: [points, features] through 3 x 128
    ReLU layers, a max over the points, the mean and log-variance heads."""

    def __init__(self, features=1, hidden=128, layers=3, latent=128):
        super().__init__()
        dims = [3 + features] + [hidden] * layers
        self.layers = torch.nn.ModuleList(
            [torch.nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:])])
        self.mean = torch.nn.Linear(hidden, latent)
        self.logvar = torch.nn.Linear(hidden, latent)
        candle_init_(self)

    def forward(self, points, features):
        h = torch.cat([points, features], 2)
        for lin in self.layers:
            h = torch.relu(lin(h))
        g = h.max(1).values
        return self.mean(g), self.logvar(g)


class VoxelEncoder(torch.nn.Module):
    """occupancy::voxel_encoder at its default width: conv_in (1 -> 16, 3^3, stride 1),
    then 4 stride-2 3^3 convolutions after a ReLU each (16 -> 32 -> 64 -> 128 -> 256,
    32^3 -> 2^3), all with padding 1 and a bias; fc of the ReLU of the channel-major
    flattening (2048 -> c_dim)."""

    def __init__(self, base=16, stages=4, c_dim=128, resolution=32):
        super().__init__()
        self.conv_in = torch.nn.Conv3d(1, base, 3, padding=1)
        self.convs = torch.nn.ModuleList([
            torch.nn.Conv3d(base << s, base << (s + 1), 3, stride=2, padding=1)
            for s in range(stages)])
        side = resolution >> stages
        self.fc = torch.nn.Linear((base << stages) * side ** 3, c_dim)
        candle_init_(self)

    def forward(self, x):
        h = self.conv_in(x[:, None])
        for conv in self.convs:
            h = conv(torch.relu(h))
        return self.fc(torch.relu(h.flatten(1)))


class BasicBlock(torch.nn.Module):
    def __init__(self, cin, cout, stride):
        super().__init__()
        bn = lambda c: torch.nn.BatchNorm2d(c, eps=1e-5, momentum=0.1)
        self.conv1 = torch.nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = bn(cout)
        self.conv2 = torch.nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = bn(cout)
        self.downsample = None
        if stride != 1 or cin != cout:
            self.downsample = torch.nn.Sequential(
                torch.nn.Conv2d(cin, cout, 1, stride, 0, bias=False), bn(cout))

    def forward(self, x):
        h = torch.relu(self.bn1(self.conv1(x)))
        h = self.bn2(self.conv2(h))
        return torch.relu(h + (x if self.downsample is None else self.downsample(x)))


class ResnetEncoder(torch.nn.Module):
    """occupancy::resnet_encoder: ResNet-18's layout at width 32 (7x7 stride-2 stem, batch
    norm, ReLU, 3x3 stride-2 max-pool; stages of 2 basic blocks at 32, 64, 128, 256
    channels, the first of stages 2-4 with stride 2 and a 1x1 projection shortcut), the
    mean over the pixels and fc (256 -> c_dim)."""

    def __init__(self, width=32, blocks=(2, 2, 2, 2), c_dim=128):
        super().__init__()
        self.conv1 = torch.nn.Conv2d(3, width, 7, 2, 3, bias=False)
        self.bn1 = torch.nn.BatchNorm2d(width, eps=1e-5, momentum=0.1)
        layers, cin = [], width
        for s, count in enumerate(blocks):
            cout = width << s
            for i in range(count):
                layers.append(BasicBlock(cin, cout, 2 if s > 0 and i == 0 else 1))
                cin = cout
        self.blocks = torch.nn.Sequential(*layers)
        self.fc = torch.nn.Linear(cin, c_dim)
        candle_init_(self)

    def forward(self, x):
        x = torch.nn.functional.max_pool2d(torch.relu(self.bn1(self.conv1(x))), 3, 2, 1)
        return self.fc(self.blocks(x).mean((2, 3)))


class Onet(torch.nn.Module):
    def __init__(self, encoder, decoder):
        super().__init__()
        self.encoder, self.decoder = encoder, decoder


def ray_box(o, d, lo=-0.55, hi=0.55):
    inv = 1.0 / d
    t0, t1 = (lo - o) * inv, (hi - o) * inv
    near = torch.minimum(t0, t1).amax(1).clamp_min(0.0)
    far = torch.maximum(t0, t1).amin(1)
    return near, far


def march(net, o, d, near, far, n=64, secant=8):
    """DVR's march without a graph: n samples with both ends, the first crossing from
    outside (f > 0) to inside, refined by secant steps. Returns the depth and a hit mask."""
    with torch.no_grad():
        r = o.shape[0]
        t = near[:, None] + (far - near)[:, None] * torch.linspace(0, 1, n)[None]
        f = net((o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3)).reshape(r, n)
        cross = (f[:, :-1] > 0) & (f[:, 1:] <= 0)
        hit = cross.any(1) & (f[:, 0] > 0)
        i = cross.float().argmax(1)
        ta, tb = t.gather(1, i[:, None])[:, 0], t.gather(1, i[:, None] + 1)[:, 0]
        fa, fb = f.gather(1, i[:, None])[:, 0], f.gather(1, i[:, None] + 1)[:, 0]
        ta, tb, fa, fb = ta[hit], tb[hit], fa[hit], fb[hit]
        oh, dh = o[hit], d[hit]
        for _ in range(secant):
            tm = ta - fa * (tb - ta) / (fb - fa)
            fm = net(oh + tm[:, None] * dh)
            inside = fm <= 0
            tb, fb = torch.where(inside, tm, tb), torch.where(inside, fm, fb)
            ta, fa = torch.where(inside, ta, tm), torch.where(inside, fa, fm)
        return ta - fa * (tb - ta) / (fb - fa), hit


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
    p.add_argument("--model", default="nerf", choices=[
        "nerf", "nerf_hash", "occupancy", "dvr", "hash_grid", "onet_points", "onet_voxels", "onet_image"])
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--phases", action="store_true")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--compile", action="store_true")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    torch.set_default_device(a.device)
    sync = torch.cuda.synchronize if a.device == "cuda" else (lambda: None)
    torch.manual_seed(0)
    if a.model in ("nerf", "nerf_hash"):
        if a.model == "nerf":
            net = Nerf()
        else:
            grid = HashGrid(lo=-2.0, hi=2.0)
            net = Nerf(depth=1, encoder=grid, d_in=grid.table.shape[1] * len(grid.levels))
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
            # (every tensor with its device: torch.compile does not apply the default one)
            dev = target.device
            u = torch.rand(r, s - 1, device=dev)
            inner = (torch.arange(1, s, dtype=torch.float32, device=dev)[None] + u - 0.5) / s
            edges = near + (far - near) * torch.cat(
                [torch.zeros(r, 1, device=dev), inner, torch.ones(r, 1, device=dev)], 1)
            starts, ends = edges[:, :-1], edges[:, 1:]
            t = 0.5 * (starts + ends)
            pos = (origins[:, None] + t[..., None] * dirs[:, None]).reshape(-1, 3)
            d = dirs[:, None].expand(r, s, 3).reshape(-1, 3)
            sigma, rgb = net(pos, d)
            color = composite(sigma.reshape(r, s), rgb.reshape(r, s, 3), starts, ends,
                              dirs.norm(dim=1))
            return ((color - target) ** 2).mean()
    elif a.model == "dvr":
        net = SdfNet()
        r = 2048
        o = torch.rand(r, 3) * 2 - 1
        o = 1.5 * o / o.norm(dim=1, keepdim=True)
        d = (torch.rand(r, 3) * 0.3 - 0.15) - o
        d = d / d.norm(dim=1, keepdim=True)
        near, far = ray_box(o, d)
        # Depth of the sphere of radius 0.3 that every ray meets (the target).
        b = (o * d).sum(1)
        truth = -b - torch.sqrt(b * b - (o * o).sum(1) + 0.09)

        def forward(step):
            t, hit = march(net, o, d, near, far)
            oh, dh = o[hit], d[hit]
            p = (oh + t[:, None] * dh).requires_grad_(True)
            f = net(p)
            (g,) = torch.autograd.grad(f.sum(), p, retain_graph=True)
            # The implicit depth: value t, gradient -(df/dtheta) / (grad f . d).
            t_hat = t - (f - f.detach()) / (g * dh).sum(1).detach()
            return (t_hat - truth[hit]).abs().mean()
    elif a.model == "hash_grid":
        net = HashGrid()
        points = torch.rand(1 << 18, 3) * 2 - 1
        c = torch.rand(net.table.shape[1] * len(net.levels), 1) * 2 - 1

        def forward(step):
            return ((net(points) @ c) ** 2).mean()
    elif a.model.startswith("onet_"):
        # examples/shape_prior's step: 16 shapes (spheres of radius 0.3 about centres in
        # [-0.15, 0.15]^3) x 1024 labelled uniform points, code size 128.
        b, q, code = 16, 1024, 128
        centres = (torch.rand(b, 3) * 0.3 - 0.15)[:, None]
        inside = lambda p: (((p - centres) ** 2).sum(2) <= 0.09).float()
        points = torch.rand(b, q, 3) * 1.1 - 0.55
        labels = inside(points)
        if a.model == "onet_points":
            encoder = PointNetEncoder(latent=code)
            x = torch.rand(b, 300, 3) - 0.5
            # The code is the mean head (features: ones, as the example's).
            encode = lambda x: encoder(x, torch.ones_like(x[..., :1]))[0]
        elif a.model == "onet_voxels":
            encoder = VoxelEncoder(c_dim=code)
            r = 32
            c = (torch.arange(r, dtype=torch.float32) + 0.5) / r - 0.5
            cells = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), -1).reshape(1, -1, 3)
            x = inside(cells).reshape(b, r, r, r)
            encode = encoder
        else:
            encoder = ResnetEncoder(c_dim=code)
            x = torch.rand(b, 3, 64, 64)
            encode = encoder
        net = Onet(encoder, OnetDecoder(hidden=128, blocks=5, code_dim=code))
        net.train()

        def forward(step):
            logits = net.decoder(points, encode(x))
            return torch.nn.functional.binary_cross_entropy_with_logits(
                logits, labels, reduction="sum") / logits.shape[0]
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

    if a.compile:
        forward = torch.compile(forward)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    total, fwd, bwd, upd = [], [], [], []
    for step in range(a.warmup + a.steps):
        t0 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        loss = forward(step)
        if a.phases:
            sync()
        t1 = time.perf_counter()
        loss.backward()
        if a.phases:
            sync()
        t2 = time.perf_counter()
        opt.step()
        sync()
        t3 = time.perf_counter()
        last = loss.item()
        if step >= a.warmup:
            total.append(t3 - t0)
            fwd.append(t1 - t0)
            bwd.append(t2 - t1)
            upd.append(t3 - t2)
    med = lambda v: sorted(v)[len(v) // 2]
    print(json.dumps({
        "impl": "pytorch-" + torch.__version__ + ("-" + a.device if a.device != "cpu" else "")
        + ("-compile" if a.compile else ""), "model": a.model, "steps": a.steps,
        "median_s": round(med(total), 5), "forward_s": round(med(fwd), 5),
        "backward_s": round(med(bwd), 5), "update_s": round(med(upd), 5),
        "final_loss": round(last, 6), "threads": a.threads,
        "params": sum(p.numel() for p in net.parameters()),
    }))


if __name__ == "__main__":
    main()
