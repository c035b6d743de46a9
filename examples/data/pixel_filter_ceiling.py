"""The held-out PSNR a perfect radiance field would reach under each evaluation protocol.

The committed images were rendered by Cycles with its default pixel filter: each pixel is
the mean of radiance samples whose offsets from the pixel centre are drawn, per axis, from
a Blackman-Harris window of support +-1.5 px (``filter_width`` 1.5; Cycles' table builder
doubles the width it is given for this filter), summed in linear light and then encoded
as sRGB. A field evaluated with one ray through each pixel centre, or with the mean of
k x k rays on a sub-pixel grid (``examples/nerf --eval-supersample k``), renders a
different quantity. This script measures the gap with the scene itself standing in for a
perfect field: it reads the same cameras rendered with a point filter (``--filter-width
0.01``) at ``f`` times the resolution, so that the centres of each pixel's f x f
sub-pixels are exact ray positions, and scores each protocol against the committed test
images composited on white (what ``examples/nerf`` compares with).

    blender -b -P examples/data/render_dataset.py -- --out /tmp/wu_pt300 --seed 0 \\
        --resolution 300 --samples 128 --filter-width 0.01
    blender -b -P examples/data/render_dataset.py -- --out /tmp/wu_pt200 --seed 0 \\
        --resolution 200 --samples 128 --filter-width 0.01
    python3 examples/data/pixel_filter_ceiling.py examples/data/wuson /tmp/wu_pt300 /tmp/wu_pt200

Needs numpy. Prints one line per protocol: mean PSNR over the test views (and min / max).
"""

import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from render_dataset import png_read  # noqa: E402


def rgba(path):
    """An RGBA PNG as float64 [H, W, 4] in [0, 1] (colour sRGB-encoded, straight alpha)."""
    w, h, ch, rows = png_read(path)
    if ch != 4:
        raise ValueError("%s: expected RGBA, got %d channels" % (path, ch))
    return np.frombuffer(b"".join(rows), dtype=np.uint8).reshape(h, w, 4) / 255.0


def on_white(img):
    """Straight-alpha RGBA composited on white, as the data module does."""
    return img[..., :3] * img[..., 3:] + (1.0 - img[..., 3:])


def film(filtered_premultiplied):
    """Cycles' film: filtered premultiplied linear RGBA -> straight sRGB colour and
    alpha, each rounded to 8 bits as in the PNG, composited on white."""
    a = filtered_premultiplied[..., 3:]
    lin = np.where(a > 0, filtered_premultiplied[..., :3] / np.maximum(a, 1e-12), 0.0)
    out = np.concatenate([to_srgb(lin), a], axis=-1)
    return on_white(np.round(out * 255.0) / 255.0)


def premultiplied_linear(img):
    return np.concatenate([to_linear(img[..., :3]) * img[..., 3:], img[..., 3:]], axis=-1)


def to_linear(c):
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def to_srgb(c):
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def blackman_harris(x, half_support):
    """Cycles' filter_func_blackman_harris with the doubled width: support [-h, h]."""
    v = 2 * np.pi * (x / (2 * half_support) + 0.5)
    w = 0.35875 - 0.48829 * np.cos(v) + 0.14128 * np.cos(2 * v) - 0.01168 * np.cos(3 * v)
    return np.where(np.abs(x) < half_support, w, 0.0)


def separable(img, taps, f, outside=1.0):
    """Filter a fine image ([f*H, f*W, C]) with the 1-D taps along both axes (`outside`
    beyond the border), then take each coarse pixel's centre sub-pixel (f odd)."""
    r = len(taps) // 2
    pad = np.pad(img, ((r, r), (r, r), (0, 0)), constant_values=outside)
    rows = sum(t * pad[i:i + img.shape[0], :, :] for i, t in enumerate(taps))
    cols = sum(t * rows[:, i:i + img.shape[1], :] for i, t in enumerate(taps))
    c = f // 2
    return cols[c::f, c::f, :]


def box(img, f):
    h, w = img.shape[0] // f, img.shape[1] // f
    return img.reshape(h, f, w, f, img.shape[2]).mean(axis=(1, 3))


def psnr(a, b):
    return -10.0 * np.log10(np.mean((a - b) ** 2))


def main():
    if len(sys.argv) != 4:
        raise SystemExit(__doc__)
    truth_dir, fine3_dir, fine2_dir = sys.argv[1:]
    names = sorted(os.listdir(os.path.join(truth_dir, "test")),
                   key=lambda n: int(n[2:-4]))
    rows = {}
    for name in names:
        truth = on_white(rgba(os.path.join(truth_dir, "test", name)))
        r3 = rgba(os.path.join(fine3_dir, "test", name))
        f3, f2 = on_white(r3), on_white(rgba(os.path.join(fine2_dir, "test", name)))
        if f3.shape[0] != 3 * truth.shape[0] or f2.shape[0] != 2 * truth.shape[0]:
            raise ValueError("%s: the fine renders must be 3x and 2x the truth's size" % name)
        # Blackman-Harris taps at the 1/3-px sub-pixel spacing, normalised.
        x = np.arange(-4, 5) / 3.0
        taps = blackman_harris(x, 1.5)
        taps /= taps.sum()
        protocols = {
            "1 ray at the pixel centre (--eval-supersample 1)": f3[1::3, 1::3],
            "mean of 2 x 2 sub-pixel rays, sRGB (--eval-supersample 2)": box(f2, 2),
            "mean of 3 x 3 sub-pixel rays, sRGB (--eval-supersample 3)": box(f3, 3),
            "Blackman-Harris +-1.5 px on 1/3-px rays, sRGB on white": separable(f3, taps, 3),
            "Blackman-Harris +-1.5 px, premultiplied linear light (Cycles' film)":
                film(separable(premultiplied_linear(r3), taps, 3, outside=0.0)),
            "mean of 3 x 3 sub-pixel rays, premultiplied linear light":
                film(box(premultiplied_linear(r3), 3)),
        }
        for k, img in protocols.items():
            rows.setdefault(k, []).append(psnr(img, truth))
    print("%d test views; PSNR against the committed images on white (mean, min, max):"
          % len(names))
    for k, v in rows.items():
        v = np.array(v)
        print("  %-72s %6.2f dB  (%.2f .. %.2f)" % (k, v.mean(), v.min(), v.max()))


if __name__ == "__main__":
    main()
