"""Reference SSIM / PSNR values from scikit-image for small 8-bit PNG pairs.

    python3 tests/data/metrics/make_reference.py

Deterministically (numpy seed 20240611) writes the PNG pairs next to this file,
loads them back from the PNG files as float64 in [0, 1] (value / 255) and
records skimage.metrics.structural_similarity (Gaussian weights, sigma 1.5,
sample covariance, data_range 1) and peak_signal_noise_ratio (data_range 1)
for each pair in expected.json.
"""

import json
import os
import platform

import numpy as np
import scipy
import scipy.ndimage as ndi
import skimage
import PIL
from PIL import Image
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

HERE = os.path.dirname(os.path.abspath(__file__))
SEED = 20240611
SSIM_KWARGS = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=True, data_range=1.0)


def to_u8(x):
    return np.clip(np.rint(np.asarray(x) * 255.0), 0, 255).astype(np.uint8)


def smooth_rgb(rng, w, h):
    """Smooth colour image: per-channel gradients and low-frequency sinusoids."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    u, v = x / (w - 1), y / (h - 1)
    chans = []
    for c in range(3):
        fx, fy, ph = rng.uniform(0.5, 2.0), rng.uniform(0.5, 2.0), rng.uniform(0, 2 * np.pi)
        g = 0.5 + 0.25 * np.sin(2 * np.pi * (fx * u + fy * v) + ph) + 0.2 * (u - v) * (c - 1)
        chans.append(g)
    return np.clip(np.stack(chans, -1), 0.02, 0.98)


def textured_rgb(rng, w, h):
    """A smoothed random field plus a bright disc and a dark bar: edges and texture."""
    base = np.stack([ndi.gaussian_filter(rng.uniform(0, 1, (h, w)), 2.0, mode="reflect")
                     for _ in range(3)], -1)
    base = (base - base.min()) / (base.max() - base.min())
    y, x = np.mgrid[0:h, 0:w]
    disc = (x - 0.3 * w) ** 2 + (y - 0.5 * h) ** 2 < (0.2 * h) ** 2
    base[disc] = [0.95, 0.85, 0.2]
    base[(x > 0.6 * w) & (x < 0.7 * w)] *= 0.3
    return base


def shift_right_one(img):
    """Shift by one pixel to the right; the first column repeats the old first column."""
    out = np.empty_like(img)
    out[:, 1:] = img[:, :-1]
    out[:, 0] = img[:, 0]
    return out


def make_pairs(rng):
    pairs = []
    # (a) RGB 40x32: smooth image vs blurred + noisy version
    a = to_u8(smooth_rgb(rng, 40, 32))
    deg = np.stack([ndi.gaussian_filter(a[..., c].astype(np.float64) / 255.0, 1.0, mode="reflect")
                    for c in range(3)], -1)
    deg += rng.normal(0.0, 0.03, deg.shape)
    pairs.append(("rgb_smooth_vs_blur_noise", "rgb40x32_a.png", "rgb40x32_b.png", a, to_u8(deg),
                  "a: smooth gradients/sinusoids; b: a blurred (Gaussian sigma 1 px, reflect) "
                  "plus N(0, 0.03) noise, clipped and rounded to 8 bit"))
    # (b) grayscale 23x17 (odd sizes): smooth vs noisy
    y, x = np.mgrid[0:17, 0:23].astype(np.float64)
    g = 0.5 + 0.3 * np.sin(x / 3.0) * np.cos(y / 4.0) + 0.1 * (x / 22.0)
    ga = to_u8(g)
    gb = to_u8(ga / 255.0 + rng.normal(0.0, 0.05, ga.shape))
    pairs.append(("gray_odd_noise", "gray23x17_a.png", "gray23x17_b.png", ga, gb,
                  "a: smooth sinusoid pattern; b: a plus N(0, 0.05) noise, clipped, 8 bit"))
    # (c) RGB 64x48: textured image vs itself shifted right by one pixel
    ta = to_u8(textured_rgb(rng, 64, 48))
    tb = shift_right_one(ta)
    pairs.append(("rgb_shift_one_pixel", "rgb64x48_a.png", "rgb64x48_b.png", ta, tb,
                  "a: smoothed random field with a disc and a dark bar; b: a shifted right by "
                  "one pixel (column 0 repeated)"))
    # (d) identical pair (RGB 16x12)
    ia = to_u8(rng.uniform(0, 1, (12, 16, 3)))
    pairs.append(("identical", "identical16x12_a.png", "identical16x12_b.png", ia, ia.copy(),
                  "a: uniform random RGB; b: the same pixels"))
    return pairs


def load(path):
    return np.asarray(Image.open(path), dtype=np.float64) / 255.0


def main():
    rng = np.random.default_rng(SEED)
    entries = []
    for name, fa, fb, a, b, note in make_pairs(rng):
        Image.fromarray(a).save(os.path.join(HERE, fa), optimize=True)
        Image.fromarray(b).save(os.path.join(HERE, fb), optimize=True)
        xa, xb = load(os.path.join(HERE, fa)), load(os.path.join(HERE, fb))
        assert xa.shape == xb.shape and xa.dtype == np.float64
        rgb = xa.ndim == 3
        ssim = structural_similarity(xa, xb, channel_axis=-1 if rgb else None, **SSIM_KWARGS)
        with np.errstate(divide="ignore"):  # identical pair: mse 0 -> inf
            psnr = peak_signal_noise_ratio(xa, xb, data_range=1.0)
        entries.append({
            "name": name,
            "a": fa,
            "b": fb,
            "width": int(xa.shape[1]),
            "height": int(xa.shape[0]),
            "channels": int(xa.shape[2]) if rgb else 1,
            "channel_axis": -1 if rgb else None,
            "description": note,
            "mse": float(np.mean((xa - xb) ** 2)),
            "ssim": float(ssim),
            "psnr": "inf" if np.isinf(psnr) else float(psnr),
        })
        print("%-26s ssim %.10f  psnr %s" % (name, ssim, entries[-1]["psnr"]))
    doc = {
        "generator": "python3 tests/data/metrics/make_reference.py",
        "seed": SEED,
        "loading": "PNG -> float64 value / 255 (H x W x 3 for RGB, H x W for gray)",
        "ssim_call": "skimage.metrics.structural_similarity(a, b, gaussian_weights=True, sigma=1.5, "
                     "use_sample_covariance=True, data_range=1.0, channel_axis=-1 (RGB) / None (gray))",
        "psnr_call": "skimage.metrics.peak_signal_noise_ratio(a, b, data_range=1.0); 'inf' for "
                     "identical images",
        "versions": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "scipy": scipy.__version__,
            "scikit-image": skimage.__version__,
            "pillow": PIL.__version__,
        },
        "pairs": entries,
    }
    with open(os.path.join(HERE, "expected.json"), "w") as f:
        json.dump(doc, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()
