//! Image metrics: PSNR and SSIM, with masked variants.

use crate::error::{Error, Result};
use candle_core::{DType, Tensor};

/// An image on the host as `(height, width, channels, values)`.
type Host = (usize, usize, usize, Vec<f64>);

fn host(t: &Tensor, arg: &'static str) -> Result<Host> {
    let (h, w, c) = super::image::image_shape(t, arg)?;
    if !matches!(t.dtype(), DType::F32 | DType::F64) {
        return Err(Error::invalid(
            arg,
            "f32 or f64",
            format!("{:?}", t.dtype()),
        ));
    }
    let v = t.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()?;
    if v.iter().any(|x| !x.is_finite()) {
        return Err(Error::invalid(arg, "finite values", "NaN or ±inf"));
    }
    Ok((h, w, c, v))
}

/// How far past `[0, 1]` a value may lie and still count as in the data range (the
/// rounding of an f32 render composited over a background).
const RANGE_SLACK: f64 = 1e-4;

/// Refuses values outside the data range `[0, 1]` (with [`RANGE_SLACK`]): the metrics
/// assume a peak of 1, and an image in `[0, 255]` would otherwise score −33 dB silently.
fn check_range(v: &[f64], arg: &'static str) -> Result<()> {
    let out = |x: f64| !(-RANGE_SLACK..=1.0 + RANGE_SLACK).contains(&x);
    match v.iter().position(|&x| out(x)) {
        None => Ok(()),
        Some(i) => Err(Error::invalid(
            arg,
            "values in the data range [0, 1]",
            format!("{} at index {i}", v[i]),
        )),
    }
}

fn pair(pred: &Tensor, target: &Tensor) -> Result<(Host, Vec<f64>)> {
    let p = host(pred, "pred")?;
    check_range(&p.3, "pred")?;
    if pred.dims() != target.dims() {
        return Err(Error::invalid(
            "target",
            format!("the shape of pred {:?}", pred.dims()),
            format!("{:?}", target.dims()),
        ));
    }
    let t = host(target, "target")?.3;
    check_range(&t, "target")?;
    Ok((p, t))
}

/// `[H · W]` booleans `mask ≥ 0.5` for a `[H, W]` (or `[H, W, 1]`) mask.
fn mask_of(mask: Option<&Tensor>, h: usize, w: usize) -> Result<Option<Vec<bool>>> {
    let Some(m) = mask else { return Ok(None) };
    let (mh, mw, mc, v) = host(m, "mask")?;
    if (mh, mw, mc) != (h, w, 1) {
        return Err(Error::invalid(
            "mask",
            format!("shape [{h}, {w}]"),
            format!("{:?}", m.dims()),
        ));
    }
    Ok(Some(v.iter().map(|&x| x >= 0.5).collect()))
}

/// Peak signal-to-noise ratio for images with values in `[0, 1]` (data range 1):
/// `PSNR = −10 log₁₀ MSE` in dB, the mean over all pixels and channels, or over the pixels
/// where `mask ≥ 0.5` (a `[H, W]` mask).
///
/// `pred`, `target`: `[H, W]` or `[H, W, C]`, f32 or f64, any device. Identical images give
/// `+∞` (never NaN). Not differentiable (use an MSE loss to train).
///
/// ```
/// use candle_core::{Device, Tensor};
/// let a = Tensor::zeros((4, 4, 3), candle_core::DType::F64, &Device::Cpu)?;
/// let b = (a.clone() + 0.1)?;
/// let p = neural_fields::data::psnr(&a, &b, None)?;
/// assert!((p - 20.0).abs() < 1e-9);
/// assert_eq!(neural_fields::data::psnr(&a, &a, None)?, f64::INFINITY);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `pred` / `target` for another rank, an empty image,
/// another dtype, non-finite values (NaN and ±∞ are refused) or values outside the data
/// range `[0, 1]` (beyond a slack of 10⁻⁴ for rounding; an image in `[0, 255]` used to
/// score −33 dB without a word), `target` for a shape unlike `pred`'s, `mask` for a shape
/// other than `[H, W]`, non-finite values or a mask that selects no pixel.
pub fn psnr(pred: &Tensor, target: &Tensor, mask: Option<&Tensor>) -> Result<f64> {
    let ((h, w, c, p), t) = pair(pred, target)?;
    let keep = mask_of(mask, h, w)?;
    let (mut sum, mut n) = (0.0, 0usize);
    for (i, (a, b)) in p.iter().zip(&t).enumerate() {
        if keep.as_ref().is_none_or(|k| k[i / c]) {
            sum += (a - b) * (a - b);
            n += 1;
        }
    }
    if n == 0 {
        return Err(Error::invalid("mask", "at least one pixel ≥ 0.5", "none"));
    }
    let mse = sum / n as f64;
    if !mse.is_finite() {
        return Err(overflow(mse));
    }
    Ok(if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    })
}

/// The error for values so large (images are in `[0, 1]`) that a metric overflows f64.
fn overflow(got: f64) -> Error {
    Error::invalid(
        "pred",
        "values for which the metric is finite in f64 (images in [0, 1])",
        format!("an intermediate {got}"),
    )
}

/// SSIM's window: a Gaussian of σ = 1.5 truncated at 3.5σ (radius 5, 11 taps), normalised.
fn gaussian_taps() -> [f64; 11] {
    let mut taps: [f64; 11] = std::array::from_fn(|i| {
        let x = i as f64 - 5.0;
        (-0.5 * x * x / (1.5 * 1.5)).exp()
    });
    let s: f64 = taps.iter().sum();
    taps.iter_mut().for_each(|t| *t /= s);
    taps
}

/// Separable 11-tap Gaussian filter of one `h × w` plane with half-sample-symmetric
/// ("reflect": `d c b a | a b c d | d c b a`) borders, as `scipy.ndimage.gaussian_filter`:
/// a pass along the rows, then one along the columns.
fn blur(x: &[f64], h: usize, w: usize, taps: &[f64; 11]) -> Vec<f64> {
    let reflect = |i: isize, n: usize| -> usize {
        let n = n as isize;
        let period = 2 * n;
        let mut j = i.rem_euclid(period);
        if j >= n {
            j = period - 1 - j;
        }
        j as usize
    };
    // One pass: element (r, c) is the weighted sum of its neighbours along columns
    // (`along_rows`) or along rows.
    let pass = |x: &[f64], along_rows: bool| -> Vec<f64> {
        let mut out = vec![0.0; h * w];
        for r in 0..h {
            for c in 0..w {
                out[r * w + c] = taps
                    .iter()
                    .enumerate()
                    .map(|(k, t)| {
                        let off = k as isize - 5;
                        let i = if along_rows {
                            r * w + reflect(c as isize + off, w)
                        } else {
                            reflect(r as isize + off, h) * w + c
                        };
                        t * x[i]
                    })
                    .sum();
            }
        }
        out
    };
    pass(&pass(x, true), false)
}

/// Structural similarity (Wang et al. 2004) of images with values in `[0, 1]`, as
/// scikit-image's `structural_similarity(pred, target, gaussian_weights=True, sigma=1.5,
/// use_sample_covariance=True, data_range=1)` computes it:
///
/// local means `μ`, variances `σ²` and covariance `σ_pt` under an 11×11 Gaussian window
/// (σ = 1.5, reflected borders), the variances scaled by `N/(N−1)` with `N = 121`, and
/// `S = (2μ_pμ_t + C₁)(2σ_pt + C₂) / ((μ_p² + μ_t² + C₁)(σ_p² + σ_t² + C₂))` with
/// `C₁ = (0.01)²`, `C₂ = (0.03)²`; SSIM is the mean of `S` over the pixels at least 5 from
/// every border (and, with a `[H, W]` mask, where `mask ≥ 0.5`), then over channels.
///
/// `pred`, `target`: `[H, W]` or `[H, W, C]` with `H, W ≥ 11`; f32 or f64; any device
/// (computed on the host in f64). Not differentiable.
///
/// # Errors
/// Those of [`psnr`] (values outside `[0, 1]` and NaN or ±∞ included), and `pred` if a
/// side is below 11 pixels; `mask` if it leaves no pixel inside the border.
pub fn ssim(pred: &Tensor, target: &Tensor, mask: Option<&Tensor>) -> Result<f64> {
    let ((h, w, c, p), t) = pair(pred, target)?;
    if h < 11 || w < 11 {
        return Err(Error::invalid(
            "pred",
            "an image of at least 11 × 11 pixels (the SSIM window)",
            format!("{w} × {h}"),
        ));
    }
    let keep = mask_of(mask, h, w)?;
    let taps = gaussian_taps();
    let cov_norm = 121.0 / 120.0;
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    let mut total = 0.0;
    for ch in 0..c {
        let plane = |v: &[f64]| -> Vec<f64> { v.iter().skip(ch).step_by(c).copied().collect() };
        let (a, b) = (plane(&p), plane(&t));
        let prod =
            |x: &[f64], y: &[f64]| -> Vec<f64> { x.iter().zip(y).map(|(x, y)| x * y).collect() };
        let (ua, ub) = (blur(&a, h, w, &taps), blur(&b, h, w, &taps));
        let uaa = blur(&prod(&a, &a), h, w, &taps);
        let ubb = blur(&prod(&b, &b), h, w, &taps);
        let uab = blur(&prod(&a, &b), h, w, &taps);
        let (mut sum, mut n) = (0.0, 0usize);
        for r in 5..h - 5 {
            for col in 5..w - 5 {
                let i = r * w + col;
                if keep.as_ref().is_some_and(|k| !k[i]) {
                    continue;
                }
                let va = cov_norm * (uaa[i] - ua[i] * ua[i]);
                let vb = cov_norm * (ubb[i] - ub[i] * ub[i]);
                let vab = cov_norm * (uab[i] - ua[i] * ub[i]);
                let s = ((2.0 * ua[i] * ub[i] + c1) * (2.0 * vab + c2))
                    / ((ua[i] * ua[i] + ub[i] * ub[i] + c1) * (va + vb + c2));
                sum += s;
                n += 1;
            }
        }
        if n == 0 {
            return Err(Error::invalid(
                "mask",
                "at least one pixel ≥ 0.5 five or more pixels from the border",
                "none",
            ));
        }
        total += sum / n as f64;
    }
    let mean = total / c as f64;
    if !mean.is_finite() {
        return Err(overflow(mean));
    }
    Ok(mean)
}
