//! Samplers along rays: stratified intervals in `[near, far]`, importance sampling from a
//! step-function PDF, merging coarse and fine samples, and RegNeRF's annealed near/far.
//!
//! A ray is `r(t) = o + t·d`. Samples are described by [`Intervals`]: per ray `S`
//! intervals `[startsᵢ, endsᵢ]` in ray parameter `t`, sorted along the ray. The field is
//! usually evaluated at the [`Intervals::positions`] (the midpoints) and compositing
//! derives δᵢ = (endsᵢ − startsᵢ)·‖d‖ itself.
//!
//! # Randomness
//! Every random draw comes from the crate's splitmix64 generator
//! ([`crate::rng::SplitMix64`]) seeded by the `seed` argument, generated on the host in f64 and then copied to the inputs' device
//! and converted to their dtype. The same seed gives the same samples on every device
//! and in every dtype (up to the final rounding), which makes runs reproducible; pass a
//! different seed each step (e.g. the step number) for fresh samples. Rays draw from
//! independent streams derived from `(seed, ray index)`.

use super::layout::{host_f64, Intervals, Layout};
use crate::error::{check_float, check_same, check_scalar, check_shape, Dim, Error, Result};
use crate::narrow::from_host;
use crate::rng::SplitMix64;
use candle_core::{Tensor, D};
use rayon::prelude::*;

/// An independent-looking stream for item `index` (a ray, a grid cell chunk) of a
/// computation seeded by `seed`: the seed and index are mixed through one splitmix64
/// step, so that neighbouring indices start far apart in the generator's sequence.
pub(crate) fn stream(seed: u64, index: u64) -> SplitMix64 {
    let mut g = SplitMix64::new(seed ^ index.wrapping_mul(0xD1B5_4A32_D192_ED03));
    SplitMix64::new(g.next_u64() ^ index)
}

/// A density function as [`super::OccupancyGrid::sample`] and [`super::proposal_sample`]
/// take it: positions `[N, 3]` → densities `[N]` (≥ 0), in the positions' dtype and on
/// their device.
pub type DensityFn<'a> = &'a mut dyn FnMut(&Tensor) -> Result<Tensor>;

/// NeRF's padding of the weights in [`sample_pdf`] (added before normalising).
pub const PDF_PADDING: f64 = 1e-5;

/// RegNeRF's initial fraction `p` of the annealed range in [`anneal_near_far`].
pub const ANNEAL_P_START: f64 = 0.5;

/// RegNeRF's position `m` of the annealing centre between near and far in
/// [`anneal_near_far`].
pub const ANNEAL_MID_RATIO: f64 = 0.5;

/// How stratified samples are placed inside their strata.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Jitter {
    /// Deterministic: the `n` intervals split `[near, far]` into equal parts.
    #[default]
    None,
    /// Every interior boundary is drawn independently inside its stratum.
    PerSample,
    /// One draw per ray shifts all interior boundaries together (mip-NeRF 360's
    /// "single jitter").
    SingleJitter,
}

impl Intervals {
    /// Intervals around sorted sample positions `t: [R, S]`: interval boundaries at the
    /// midpoints between consecutive samples, the first interval starting at `near` and
    /// the last ending at `far` (both `[R]`). Used after [`merge_sorted`] to re-derive
    /// intervals from merged coarse and fine samples. Differentiable w.r.t. `t`, `near`
    /// and `far`.
    ///
    /// ```
    /// use candle_core::{Device, Tensor};
    /// use neural_fields::volume::Intervals;
    ///
    /// let dev = Device::Cpu;
    /// let t = Tensor::new(&[[1.0f64, 2.0, 4.0]], &dev)?;                  // sorted samples
    /// let (near, far) = (Tensor::new(&[0.0f64], &dev)?, Tensor::new(&[5.0f64], &dev)?);
    /// let iv = Intervals::from_samples(&t, &near, &far)?;
    /// assert_eq!(iv.starts.to_vec2::<f64>()?, vec![vec![0.0, 1.5, 3.0]]);
    /// assert_eq!(iv.ends.to_vec2::<f64>()?, vec![vec![1.5, 3.0, 5.0]]);
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// Naming `samples` for a wrong shape, dtype or device, unsorted rows, or samples
    /// outside `[near, far]`; naming `near`/`far` as [`stratified`] does.
    pub fn from_samples(samples: &Tensor, near: &Tensor, far: &Tensor) -> Result<Self> {
        let r = check_near_far(near, far)?;
        check_same(samples, "samples", near, "near")?;
        let dims = check_shape(samples, "samples", &[Dim::Is(r), Dim::Any("S")])?;
        let s = dims[1];
        if s == 0 {
            return Err(Error::invalid(
                "samples",
                "at least one sample per ray",
                "S = 0",
            ));
        }
        let host = host_f64(samples)?;
        let nh = host_f64(near)?;
        let fh = host_f64(far)?;
        for ray in 0..r {
            let row = &host[ray * s..(ray + 1) * s];
            if row.iter().any(|x| !x.is_finite()) {
                return Err(Error::invalid(
                    "samples",
                    "finite values",
                    "NaN or infinity",
                ));
            }
            if row.windows(2).any(|w| w[0] > w[1]) {
                return Err(Error::invalid(
                    "samples",
                    "rows sorted in increasing order",
                    format!("an unsorted row at ray {ray}"),
                ));
            }
            if row[0] < nh[ray] || row[s - 1] > fh[ray] {
                return Err(Error::invalid(
                    "samples",
                    "samples inside [near, far]",
                    format!(
                        "[{}, {}] outside [{}, {}] at ray {ray}",
                        row[0],
                        row[s - 1],
                        nh[ray],
                        fh[ray]
                    ),
                ));
            }
        }
        let near_c = near.unsqueeze(1)?;
        let far_c = far.unsqueeze(1)?;
        if s == 1 {
            return Ok(Intervals {
                starts: near_c,
                ends: far_c,
                layout: Layout::Batched,
            });
        }
        let mids = ((samples.narrow(1, 0, s - 1)? + samples.narrow(1, 1, s - 1)?)? * 0.5)?;
        let starts = Tensor::cat(&[&near_c, &mids], 1)?;
        let ends = Tensor::cat(&[&mids, &far_c], 1)?;
        Ok(Intervals {
            starts,
            ends,
            layout: Layout::Batched,
        })
    }
}

/// Checks `near` and `far`: `[R]` float tensors on one device with one dtype, finite,
/// `near ≤ far` element-wise. Returns `R`.
pub(crate) fn check_near_far(near: &Tensor, far: &Tensor) -> Result<usize> {
    check_float(near, "near")?;
    let r = check_shape(near, "near", &[Dim::Any("R")])?[0];
    check_same(far, "far", near, "near")?;
    check_shape(far, "far", &[Dim::Is(r)])?;
    let nh = host_f64(near)?;
    let fh = host_f64(far)?;
    for (i, (&n, &f)) in nh.iter().zip(&fh).enumerate() {
        if !n.is_finite() {
            return Err(Error::invalid(
                "near",
                "finite values",
                format!("{n} at ray {i}"),
            ));
        }
        if !f.is_finite() {
            return Err(Error::invalid(
                "far",
                "finite values",
                format!("{f} at ray {i}"),
            ));
        }
        if n > f {
            return Err(Error::invalid(
                "near",
                "near ≤ far for every ray",
                format!("near {n} > far {f} at ray {i}"),
            ));
        }
    }
    Ok(r)
}

/// Stratified sample intervals in `[near, far]` along each ray.
///
/// The `n` intervals of ray `r` have edges `e₀ = near`, `eₙ = far` and, for
/// `0 < k < n`, `e_k = near + (far − near)·(k + u_k − ½)/n` with `u_k ∈ [0, 1)`:
/// `u_k = ½` for [`Jitter::None`] (equal intervals with midpoints
/// `near + (far − near)(k + ½)/n`), independent uniform draws for
/// [`Jitter::PerSample`], and one draw per ray for [`Jitter::SingleJitter`]. Each
/// interior edge stays inside its own stratum, so the intervals are sorted, contiguous,
/// cover `[near, far]` exactly and every edge lies in `[near, far]` (interior edges are
/// clamped to `far` against rounding).
///
/// * `near`, `far`: `[R]`, f32 or f64, same device; the outputs follow them.
/// * returns [`Intervals`] with `starts`, `ends`: `[R, n]`.
///
/// Differentiable w.r.t. `near` and `far` (the edges are affine in them).
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::volume::{stratified, Jitter};
///
/// let dev = Device::Cpu;
/// let (near, far) = (Tensor::new(&[2.0f32, 0.0], &dev)?, Tensor::new(&[6.0f32, 1.0], &dev)?);
/// let iv = stratified(&near, &far, 4, Jitter::None, 0)?;             // [R = 2, S = 4]
/// assert_eq!(iv.starts.to_vec2::<f32>()?[0], vec![2.0, 3.0, 4.0, 5.0]);
/// let jittered = stratified(&near, &far, 4, Jitter::PerSample, 7)?;  // a new seed per step
/// assert_eq!(jittered.ends.to_vec2::<f32>()?[1][3], 1.0);            // still ends at far
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// Naming `near`/`far` for wrong shapes or dtypes, non-finite values (NaN or ±∞ are
/// refused, not propagated) or `near > far`; naming `n` for `n = 0` or for `R·(n + 1)`
/// edges past the allocation limit of 2³³ bytes (8 GiB, counted at 8 bytes a value),
/// before anything is allocated.
pub fn stratified(
    near: &Tensor,
    far: &Tensor,
    n: usize,
    jitter: Jitter,
    seed: u64,
) -> Result<Intervals> {
    let r = check_near_far(near, far)?;
    if n == 0 {
        return Err(Error::invalid("n", "at least one sample per ray", "0"));
    }
    crate::limits::check_bytes("n", &[r, n.saturating_add(1)], 8)?;
    let near_c = near.unsqueeze(1)?;
    let far_c = far.unsqueeze(1)?;
    let edges = if n == 1 {
        Tensor::cat(&[&near_c, &far_c], 1)?
    } else {
        let m = n - 1;
        let mut frac = vec![0f64; r * m];
        frac.par_chunks_mut(m).enumerate().for_each(|(ray, row)| {
            let mut rng = stream(seed, ray as u64);
            let single = match jitter {
                Jitter::SingleJitter => rng.uniform(),
                _ => 0.5,
            };
            for (j, f) in row.iter_mut().enumerate() {
                let u = match jitter {
                    Jitter::None => 0.5,
                    Jitter::PerSample => rng.uniform(),
                    Jitter::SingleJitter => single,
                };
                *f = ((j + 1) as f64 + u - 0.5) / n as f64;
            }
        });
        let frac = from_host(frac, &[r, m], near.dtype(), near.device())?;
        let span = (far - near)?.unsqueeze(1)?;
        let interior = near_c
            .broadcast_add(&span.broadcast_mul(&frac)?)?
            .broadcast_minimum(&far_c)?;
        Tensor::cat(&[&near_c, &interior, &far_c], 1)?
    };
    Ok(Intervals {
        starts: edges.narrow(1, 0, n)?,
        ends: crate::narrow::narrow(&edges, 1, 1, n)?,
        layout: Layout::Batched,
    })
}

/// The CDF of one ray's step function at its `S + 1` bin edges (see [`sample_pdf`]).
fn host_cdf(wr: &[f64], padding: f64) -> Vec<f64> {
    let s = wr.len();
    let mut total: f64 = wr.iter().map(|x| x + padding).sum();
    let uniform = total.is_nan() || total <= 0.0;
    if uniform {
        total = s as f64;
    }
    let mut cdf = Vec::with_capacity(s + 1);
    cdf.push(0.0);
    let mut acc = 0.0;
    for wi in &wr[..s.saturating_sub(1)] {
        acc += if uniform { 1.0 } else { wi + padding };
        cdf.push((acc / total).min(1.0));
    }
    cdf.push(1.0);
    cdf
}

/// Checks `weights: [R, S]` (S ≥ 1, finite, ≥ 0) and `padding`; returns the host
/// weights and `(R, S)`.
fn check_weights(weights: &Tensor, padding: f64) -> Result<(Vec<f64>, usize, usize)> {
    check_float(weights, "weights")?;
    let dims = check_shape(weights, "weights", &[Dim::Any("R"), Dim::Any("S")])?;
    let (r, s) = (dims[0], dims[1]);
    if s == 0 {
        return Err(Error::invalid(
            "weights",
            "at least one bin per ray",
            "S = 0",
        ));
    }
    check_scalar(padding, "padding", false)?;
    if padding < 0.0 {
        return Err(Error::invalid(
            "padding",
            "a number ≥ 0",
            format!("{padding}"),
        ));
    }
    let w = host_f64(weights)?;
    if let Some((i, x)) = w
        .iter()
        .enumerate()
        .find(|(_, x)| !(x.is_finite() && **x >= 0.0))
    {
        return Err(Error::invalid(
            "weights",
            "finite values ≥ 0",
            format!("{x} at ray {}, bin {}", i / s, i % s),
        ));
    }
    Ok((w, r, s))
}

/// Importance samples from the step-function PDF given by `weights` on the bins of
/// `intervals`: bin `i` of a ray is `[bᵢ, bᵢ₊₁]` with `b` the interval starts followed by
/// the last end ([`stratified`]'s intervals are contiguous, so the bins are exactly the
/// intervals).
///
/// Per ray, with `w̃ᵢ = wᵢ + padding` and `W = Σ w̃ᵢ` (a ray whose `W` is 0 is sampled
/// uniformly), the CDF at the bin edges is `F₀ = 0`, `F_k = min(1, Σ_{i<k} w̃ᵢ / W)`
/// for `0 < k < S` and `F_S = 1` exactly. The `n` samples invert the CDF at sorted
/// `u_k`: `u_k = (k + ½)/n` when `deterministic`, else `u_k = (k + ξ_k)/n` with
/// `ξ_k ~ U[0, 1)` (jittered stratified u). With `F_i ≤ u < F_{i+1}`,
/// `t = bᵢ + (u − Fᵢ)/(F_{i+1} − Fᵢ)·(b_{i+1} − bᵢ)`, clamped to `[bᵢ, b_{i+1}]`, so
/// a sample never leaves the bin it was drawn in and bins of zero probability are never
/// drawn from (with `padding = 0`, samples of a one-hot PDF lie exactly in that bin).
///
/// * `intervals`: batched `[R, S]`; `weights`: `[R, S]`, `≥ 0`; f32 or f64, same device. `padding ≥ 0` (NeRF uses `1e-5`, [`PDF_PADDING`]).
/// * returns `[R, n]`, sorted along each ray, same device and dtype, **detached**: no
///   gradient flows to the intervals or `weights` (NeRF's stop-gradient on resampled points).
///
/// The inversion runs on the host in f64 (the result carries no graph, so nothing is
/// lost): it reads `R·(2S + 1)` values back and copies `R·n` to the device.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::volume::{sample_pdf, stratified, Jitter};
///
/// let dev = Device::Cpu;
/// let (near, far) = (Tensor::new(&[0.0f32], &dev)?, Tensor::new(&[4.0f32], &dev)?);
/// let coarse = stratified(&near, &far, 4, Jitter::None, 0)?;          // bins [0,1] … [3,4]
/// let w = Tensor::new(&[[0.0f32, 0.0, 1.0, 0.0]], &dev)?;             // all weight in [2, 3]
/// let fine = sample_pdf(&coarse, &w, 8, true, 0, 0.0)?;               // [R = 1, 8], detached
/// assert!(fine.to_vec2::<f32>()?[0].iter().all(|&t| (2.0..=3.0).contains(&t)));
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// Naming `weights` for a wrong shape or dtype, negative or non-finite values; `intervals`
/// for a shape other than `[R, S + 1]`, a different dtype or device, non-finite or
/// unsorted edges; `n` for `n = 0` or for `R·n` samples past the allocation limit of 2³³
/// bytes (8 GiB, counted at 8 bytes a value), before anything is allocated; `padding` for
/// a negative or non-finite value. NaN or ±∞ in `weights` or the edges are refused.
pub fn sample_pdf(
    intervals: &Intervals,
    weights: &Tensor,
    n: usize,
    deterministic: bool,
    seed: u64,
    padding: f64,
) -> Result<Tensor> {
    let (w, r, s) = check_weights(weights, padding)?;
    let bins = &intervals.edges()?;
    check_same(bins, "intervals", weights, "weights")?;
    check_shape(bins, "intervals", &[Dim::Is(r), Dim::Is(s + 1)])?;
    if n == 0 {
        return Err(Error::invalid("n", "at least one sample per ray", "0"));
    }
    crate::limits::check_bytes("n", &[r, n], 8)?;
    let b = host_f64(bins)?;
    for ray in 0..r {
        let row = &b[ray * (s + 1)..(ray + 1) * (s + 1)];
        if row.iter().any(|x| !x.is_finite()) {
            return Err(Error::invalid(
                "intervals",
                "finite edges",
                format!("NaN or ∞ at ray {ray}"),
            ));
        }
        if row.windows(2).any(|p| p[0] > p[1]) {
            return Err(Error::invalid(
                "intervals",
                "edges sorted in increasing order",
                format!("unsorted edges at ray {ray}"),
            ));
        }
    }
    let u_max = 1.0 - f64::EPSILON / 2.0;
    let mut out = vec![0f64; r * n];
    out.par_chunks_mut(n).enumerate().for_each(|(ray, row)| {
        let br = &b[ray * (s + 1)..(ray + 1) * (s + 1)];
        let cdf = host_cdf(&w[ray * s..(ray + 1) * s], padding);
        let mut rng = stream(seed, ray as u64);
        let mut i = 0usize;
        for (k, t) in row.iter_mut().enumerate() {
            let xi = if deterministic { 0.5 } else { rng.uniform() };
            let u = ((k as f64 + xi) / n as f64).min(u_max);
            while i + 1 < s && cdf[i + 1] <= u {
                i += 1;
            }
            let denom = cdf[i + 1] - cdf[i];
            let frac = if denom > 0.0 {
                ((u - cdf[i]) / denom).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let (lo, hi) = (br[i], br[i + 1]);
            *t = (lo + frac * (hi - lo)).clamp(lo, hi);
        }
    });
    Ok(from_host(out, &[r, n], weights.dtype(), weights.device())?)
}

/// Merges two sets of sorted samples per ray into one sorted set:
/// `coarse: [R, S₁]`, `fine: [R, S₂]` → `[R, S₁ + S₂]` (concatenate, then sort each
/// row). Use it to combine coarse samples (e.g. stratified midpoints) with importance
/// samples, then [`Intervals::from_samples`] to re-derive intervals.
///
/// f32 or f64, any device. Differentiable w.r.t. both inputs (the sort is a gather; the
/// fine samples of [`sample_pdf`] are detached already). On CUDA, candle's sort limits a
/// row to the sizes its bitonic kernel supports.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::volume::merge_sorted;
///
/// let dev = Device::Cpu;
/// let m = merge_sorted(&Tensor::new(&[[0.5f32, 2.5]], &dev)?, &Tensor::new(&[[1.0f32, 3.0]], &dev)?)?;
/// assert_eq!(m.to_vec2::<f32>()?, vec![vec![0.5, 1.0, 2.5, 3.0]]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// Naming `coarse` or `fine` for wrong shapes, dtypes or devices.
pub fn merge_sorted(coarse: &Tensor, fine: &Tensor) -> Result<Tensor> {
    check_float(coarse, "coarse")?;
    let r = check_shape(coarse, "coarse", &[Dim::Any("R"), Dim::Any("S1")])?[0];
    check_same(fine, "fine", coarse, "coarse")?;
    check_shape(fine, "fine", &[Dim::Is(r), Dim::Any("S2")])?;
    let all = Tensor::cat(&[coarse, fine], D::Minus1)?.contiguous()?;
    if all.dims()[1] == 0 {
        return Ok(all);
    }
    let idx = all.arg_sort_last_dim(true)?;
    Ok(all.gather(&idx, D::Minus1)?)
}

/// RegNeRF's scene-space annealing of the sampling range.
///
/// With `mid = near + m·(far − near)` (`m = mid_ratio`) and the progress
/// `w = min(step / n_t, 1)` (`w = 1` when `n_t = 0`), the range is
/// `near' = mid + s·(near − mid)`, `far' = mid + s·(far − mid)` with
/// `s = p + w·(1 − p)` (`p = p_start`): it starts at
/// `[mid + p(near − mid), mid + p(far − mid)]` and grows linearly to `[near, far]`
/// over `n_t` steps (RegNeRF on DTU: `n_t = 256`, `p = 0.5`, `m = 0.5`: [`ANNEAL_P_START`],
/// [`ANNEAL_MID_RATIO`]). Once `w = 1`
/// the inputs are returned unchanged; before, the result is clamped to `[near, far]`
/// against rounding.
///
/// `near`, `far`: `[R]`; the outputs have the same shape, device and dtype, and are
/// differentiable w.r.t. `near` and `far`.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::volume::{anneal_near_far, ANNEAL_MID_RATIO, ANNEAL_P_START};
///
/// let dev = Device::Cpu;
/// let (near, far) = (Tensor::new(&[0.0f64], &dev)?, Tensor::new(&[4.0f64], &dev)?);
/// let (n0, f0) = anneal_near_far(&near, &far, 0, 256, ANNEAL_P_START, ANNEAL_MID_RATIO)?;
/// assert_eq!((n0.to_vec1::<f64>()?, f0.to_vec1::<f64>()?), (vec![1.0], vec![3.0])); // step 0
/// let (n1, f1) = anneal_near_far(&near, &far, 256, 256, ANNEAL_P_START, ANNEAL_MID_RATIO)?;
/// assert_eq!((n1.to_vec1::<f64>()?, f1.to_vec1::<f64>()?), (vec![0.0], vec![4.0])); // done
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// Naming `near`/`far` as [`stratified`] does; `p_start` or `mid_ratio` outside
/// `[0, 1]`.
pub fn anneal_near_far(
    near: &Tensor,
    far: &Tensor,
    step: usize,
    n_t: usize,
    p_start: f64,
    mid_ratio: f64,
) -> Result<(Tensor, Tensor)> {
    check_near_far(near, far)?;
    if !(0.0..=1.0).contains(&p_start) {
        return Err(Error::invalid(
            "p_start",
            "a number in [0, 1]",
            format!("{p_start}"),
        ));
    }
    if !(0.0..=1.0).contains(&mid_ratio) {
        return Err(Error::invalid(
            "mid_ratio",
            "a number in [0, 1]",
            format!("{mid_ratio}"),
        ));
    }
    let w = if n_t == 0 {
        1.0
    } else {
        (step as f64 / n_t as f64).min(1.0)
    };
    let scale = p_start + w * (1.0 - p_start);
    if w >= 1.0 || scale >= 1.0 {
        return Ok((near.clone(), far.clone()));
    }
    let mid = (near + ((far - near)? * mid_ratio)?)?;
    let n2 = (&mid + ((near - &mid)? * scale)?)?.maximum(near)?;
    let f2 = (&mid + ((far - &mid)? * scale)?)?.minimum(far)?;
    Ok((n2, f2))
}

#[cfg(test)]
mod tests {
    use super::host_cdf;

    /// The CDF that `sample_pdf` inverts starts at exactly 0, ends at exactly 1, is
    /// monotone and at most 1, for weights as f32 and f64 tensors hold them, and is
    /// uniform for all-zero weights without padding.
    #[test]
    fn cdf_starts_at_exactly_zero_and_ends_at_exactly_one() {
        // Weights whose running sum rounds above the total in floating point.
        let w = [0.1, 0.2, 0.3, 0.1, 0.2, 0.1, 1e-9, 0.7];
        for rounded in [
            w.map(|x: f64| f64::from(x as f32)),
            w, // f64
        ] {
            for pad in [0.0, 1e-5, 1.0] {
                let c = host_cdf(&rounded, pad);
                assert_eq!(c.len(), 9);
                assert_eq!(c[0], 0.0);
                assert_eq!(c[8], 1.0);
                assert!(c.windows(2).all(|p| p[0] <= p[1]));
                assert!(c.iter().all(|x| *x <= 1.0));
            }
        }
        assert_eq!(host_cdf(&[0.0; 4], 0.0), vec![0.0, 0.25, 0.5, 0.75, 1.0]);
        assert_eq!(host_cdf(&[1.0, 1.0, 2.0], 0.0), vec![0.0, 0.25, 0.5, 1.0]);
    }
}
