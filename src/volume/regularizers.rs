//! Regularisers used with volume rendering: mip-NeRF 360's distortion loss and
//! RegNeRF's depth smoothness on patches, with RegNeRF's weight schedule.

use crate::error::{check_float, check_same, check_shape, Dim, Error, Result};
use crate::volume::layout::{host_f64, Intervals, Layout};
use candle_core::{Tensor, D};

/// Exclusive prefix sum along the last dimension: `out_k = Σ_{j<k} x_j`.
fn exclusive_cumsum(x: &Tensor) -> Result<Tensor> {
    let s = x.dim(D::Minus1)?;
    let inclusive = x.cumsum(D::Minus1)?;
    if s <= 1 {
        return Ok(x.zeros_like()?);
    }
    let zero = x.narrow(D::Minus1, 0, 1)?.zeros_like()?;
    Ok(Tensor::cat(
        &[&zero, &inclusive.narrow(D::Minus1, 0, s - 1)?],
        D::Minus1,
    )?)
}

/// Distortion loss of mip-NeRF 360, per ray:
///
/// `L = Σᵢ Σⱼ wᵢ wⱼ |mᵢ − mⱼ| + ⅓ Σᵢ wᵢ² δᵢ`,
///
/// with midpoints `mᵢ = (sᵢ + eᵢ)/2` and lengths `δᵢ = eᵢ − sᵢ`. It is evaluated in its
/// O(S) form: for intervals sorted along the ray, `Σᵢⱼ wᵢwⱼ|mᵢ − mⱼ| =
/// 2 Σᵢ wᵢ (mᵢ Aᵢ − Bᵢ)` with the exclusive prefix sums `Aᵢ = Σ_{j<i} wⱼ` and
/// `Bᵢ = Σ_{j<i} wⱼmⱼ`. (candle's `cumsum` is itself a matmul with a triangle, so the
/// device cost is that of two `[R, S] × [S, S]` products.)
///
/// The loss is meant for **normalised** intervals: pass `t` mapped to `[0, 1]` (e.g.
/// `(t − near)/(far − near)`, or mip-NeRF 360's s-space), so that its scale does not
/// depend on the scene's units.
///
/// * `weights`: `[R, S]`; `intervals`: batched `[R, S]` (starts `sᵢ`, ends `eᵢ`); f32 or
///   f64, same device; returns `[R]`.
///
/// Differentiable w.r.t. `weights`, `starts` and `ends`; the gradients
/// (docs/math.md, "Distortion loss") are `∂L/∂w_k = 2 Σⱼ wⱼ|m_k − mⱼ| + ⅔ w_k δ_k`,
/// `∂L/∂m_k = 2 w_k (Σ_{j<k} wⱼ − Σ_{j>k} wⱼ)` and `∂L/∂δ_k = ⅓ w_k²`.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::volume::{distortion_loss, Intervals, Layout};
///
/// let dev = Device::Cpu;
/// let iv = Intervals::new(Tensor::new(&[[0.0f64, 0.5]], &dev)?, Tensor::new(&[[0.5f64, 1.0]], &dev)?, Layout::Batched)?;
/// // All weight in the first interval: only its ⅓·w²·δ term remains.
/// let l = distortion_loss(&Tensor::new(&[[1.0f64, 0.0]], &dev)?, &iv)?;   // [R = 1]
/// assert!((l.to_vec1::<f64>()?[0] - 0.5 / 3.0).abs() < 1e-15);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// Naming `weights`, `starts` or `ends` for wrong shapes, dtypes or devices; `starts`
/// when the intervals are inverted or unsorted along a ray (read back on the host: the
/// O(S) form is only valid for sorted midpoints); `intervals` when they are packed.
pub fn distortion_loss(weights: &Tensor, intervals: &Intervals) -> Result<Tensor> {
    if matches!(intervals.layout, Layout::Packed(_)) {
        return Err(Error::invalid(
            "intervals",
            "the batched layout",
            "packed intervals",
        ));
    }
    let (starts, ends) = (&intervals.starts, &intervals.ends);
    check_float(weights, "weights")?;
    let dims = check_shape(weights, "weights", &[Dim::Any("R"), Dim::Any("S")])?;
    check_same(starts, "starts", weights, "weights")?;
    check_same(ends, "ends", weights, "weights")?;
    check_shape(starts, "starts", &[Dim::Is(dims[0]), Dim::Is(dims[1])])?;
    check_shape(ends, "ends", &[Dim::Is(dims[0]), Dim::Is(dims[1])])?;
    if let Some(s) = std::num::NonZeroUsize::new(dims[1]) {
        let s = s.get();
        let sh = host_f64(starts)?;
        let eh = host_f64(ends)?;
        for (i, (&a, &b)) in sh.iter().zip(&eh).enumerate() {
            if a.is_nan() || b.is_nan() || a > b {
                return Err(Error::invalid(
                    "starts",
                    "finite intervals with start ≤ end",
                    format!("[{a}, {b}] at ray {}, sample {}", i / s, i % s),
                ));
            }
            if i % s + 1 < s && sh[i + 1] < a {
                return Err(Error::invalid(
                    "starts",
                    "intervals sorted along each ray",
                    format!("start {} after {a} at ray {}", sh[i + 1], i / s),
                ));
            }
        }
    }
    let mids = ((starts + ends)? * 0.5)?;
    let deltas = (ends - starts)?;
    let a = exclusive_cumsum(weights)?;
    let wm = (weights * &mids)?;
    let b = exclusive_cumsum(&wm)?;
    let inter = ((weights * ((&mids * &a)? - &b)?)?.sum(D::Minus1)? * 2.0)?;
    let intra = ((weights.sqr()? * &deltas)?.sum(D::Minus1)? / 3.0)?;
    Ok((inter + intra)?)
}

/// RegNeRF's depth smoothness on rendered depth patches, per patch:
///
/// `L_p = 1/((k−1)²) · Σ_{i<k−1} Σ_{j<k−1} m[i,j] · ((d[i,j] − d[i,j+1])² + (d[i,j] − d[i+1,j])²)`,
///
/// the mean over the `(k−1)×(k−1)` top-left pixels of each `k×k` patch, as RegNeRF's code
/// computes it (`compute_tv_norm(depth, weighting).mean()`; both differences are taken
/// from the same pixel), so that RegNeRF's weight,
/// [`log_linear_schedule`]`(step, 400.0, 0.1, 512)`, applies as published. `m = 1`
/// without `weights`; RegNeRF's DTU configuration weights each pixel by its rendered
/// opacity, detached (`weights = Some(&opacity.detach())`), so that pixels that see
/// nothing do not pull their neighbours' depth. RegNeRF uses 8×8 patches; take the mean
/// over patches.
///
/// * `depth`: `[P, k, k]` (square or not: `[P, H, W]` with `H, W ≥ 2`), f32 or f64;
///   `weights`: `None` or the same shape, dtype and device (only the top-left
///   `(H−1)×(W−1)` entries are used); returns `[P]`. Differentiable w.r.t. `depth` and
///   `weights`.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::volume::depth_smoothness;
///
/// let flat = Tensor::full(3.0f32, (1, 8, 8), &Device::Cpu)?;          // one 8×8 patch
/// assert_eq!(depth_smoothness(&flat, None)?.to_vec1::<f32>()?, vec![0.0]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// Naming `depth` for a wrong rank or dtype or a patch side below 2; `weights` for another
/// shape, dtype or device than `depth`'s.
pub fn depth_smoothness(depth: &Tensor, weights: Option<&Tensor>) -> Result<Tensor> {
    check_float(depth, "depth")?;
    let dims = check_shape(
        depth,
        "depth",
        &[Dim::Any("P"), Dim::Any("k"), Dim::Any("k")],
    )?;
    let (h, w) = (dims[1], dims[2]);
    if h < 2 || w < 2 {
        return Err(Error::invalid(
            "depth",
            "patches of at least 2×2 pixels",
            format!("shape {dims:?}"),
        ));
    }
    let d00 = depth.narrow(1, 0, h - 1)?.narrow(2, 0, w - 1)?;
    let d01 = depth.narrow(1, 0, h - 1)?.narrow(2, 1, w - 1)?;
    let d10 = depth.narrow(1, 1, h - 1)?.narrow(2, 0, w - 1)?;
    let mut l = ((&d00 - &d01)?.sqr()? + (&d00 - &d10)?.sqr()?)?;
    if let Some(m) = weights {
        check_same(m, "weights", depth, "depth")?;
        check_shape(m, "weights", &[Dim::Is(dims[0]), Dim::Is(h), Dim::Is(w)])?;
        l = (l * m.narrow(1, 0, h - 1)?.narrow(2, 0, w - 1)?)?;
    }
    Ok(l.flatten_from(1)?.mean(1)?)
}

/// Log-linear schedule from `start` to `end` over `n_steps`:
/// `start^(1 − τ) · end^τ = exp((1 − τ) ln start + τ ln end)` with
/// `τ = min(step / n_steps, 1)` (`τ = 1` when `n_steps = 0`); exactly `start` at `τ = 0`
/// and `end` at `τ = 1`.
///
/// `start` and `end` are `≥ 0`. A zero endpoint gives the curve's limit, not NaN: with
/// `end = 0` the value is `start` at `τ = 0` and 0 after, with `start = 0` it is 0 until
/// `τ = 1` (a learning rate of 0 freezes what it drives). Negative endpoints give NaN.
///
/// ```
/// use neural_fields::volume::log_linear_schedule;
/// assert_eq!(log_linear_schedule(0, 1e-3, 1e-4, 100), 1e-3);
/// assert!((log_linear_schedule(50, 1e-2, 1e-4, 100) - 1e-3).abs() < 1e-15);
/// assert_eq!(log_linear_schedule(0, 0.0, 0.0, 100), 0.0);
/// ```
#[must_use]
pub fn log_linear_schedule(step: usize, start: f64, end: f64, n_steps: usize) -> f64 {
    let tau = if n_steps == 0 {
        1.0
    } else {
        (step as f64 / n_steps as f64).min(1.0)
    };
    match tau {
        t if t <= 0.0 => start,
        t if t >= 1.0 => end,
        // powf, not exp∘ln: 0^t = 0 where 0·ln 0 would be NaN.
        t => start.powf(1.0 - t) * end.powf(t),
    }
}
