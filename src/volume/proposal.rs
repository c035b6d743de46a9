//! Proposal sampling (mip-NeRF 360; nerfacc's `PropNetEstimator`): small density networks
//! propose where the samples go, level by level, and the interlevel loss keeps each
//! proposal's weights an upper bound of the next level's.
//!
//! Level 0 places `samples[0]` stratified intervals in `[near, far]`; proposal network `l`
//! gives densities there, [`render_weights`] turns them into weights `ŵ`, and
//! [`sample_pdf`] draws the next level's interval edges from that step function (detached, as
//! in mip-NeRF 360): `n + 1` sorted draws bound `n` intervals, which therefore cover only
//! where the proposal has weight (plus `padding`), not all of `[near, far]`. The last draw gives the intervals the radiance field is evaluated on. The
//! proposals learn only from [`interlevel_loss`] against the final weights (detached), so
//! the radiance field's photometric loss never reaches them.
//!
//! Given the radiance field's density as a closure, [`proposal_sample`] also does what
//! the occupancy grid's sampling does: it evaluates the density (without a graph) on the
//! final intervals, computes the interlevel loss against those weights, and returns only
//! the samples that are visible and not empty, so that the whole network runs on those
//! alone.

use super::compositing::{render_weights, CompositeConfig, DEFAULT_TERMINATION_EPS};
use super::layout::{Intervals, Layout};
use super::sampling::{sample_pdf, stratified, DensityFn, Jitter};
use crate::camera::Rays;
use crate::error::{check_finite, check_float, check_same, check_scalar, Error, Result};
use candle_core::{DType, Tensor};

/// How [`proposal_sample`]'s first level spaces its samples along each ray.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Spacing {
    /// Uniform in `t` over `[near, far]` (a bounded scene).
    #[default]
    Linear,
    /// Uniform in `s = (g(t) − g(near)) / (g(far) − g(near))` with
    /// `g(t) = t/2` for `t < 1` and `1 − 1/(2t)` beyond (nerfacto's piecewise
    /// linear-then-disparity spacing, the unbounded-scene sampler of mip-NeRF 360 in
    /// nerfstudio): linear up to `t = 1`, then uniform in disparity `1/t` to `far`, which
    /// may be huge (1e10). Scale the scene so that the foreground lies within `t ≤ 1` of
    /// the cameras (and within the unit ball of [`super::contract`]). `near ≥ 0`.
    LinearDisparity,
}

/// `g` of [`Spacing::LinearDisparity`] on a tensor: `t/2` below 1, `1 − 1/(2t)` from 1.
fn lin_disp(t: &Tensor) -> Result<Tensor> {
    let below = (t * 0.5)?;
    let above = (t.maximum(1.0)?.recip()? * -0.5)?.affine(1.0, 1.0)?;
    Ok(t.lt(1.0)?.where_cond(&below, &above)?)
}

/// `g⁻¹` of [`Spacing::LinearDisparity`]: `2s` below ½, `1/(2 − 2s)` from ½.
fn lin_disp_inv(s: &Tensor) -> Result<Tensor> {
    let below = (s * 2.0)?;
    // s < 1 for any finite far (g < 1), so 2 − 2s > 0.
    let above = s.minimum(1.0 - 1e-15)?.affine(-2.0, 2.0)?.recip()?;
    Ok(s.lt(0.5)?.where_cond(&below, &above)?)
}

impl Spacing {
    /// The normalised coordinate `s ∈ [0, 1]` of ray parameters `t` between `near` and
    /// `far` (`[R]`, broadcast over the trailing axis of `t: [R, S]`): `(t − near)/(far −
    /// near)` for [`Spacing::Linear`], `(g(t) − g(near))/(g(far) − g(near))` for
    /// [`Spacing::LinearDisparity`]. The space in which this spacing is uniform, where
    /// mip-NeRF 360 computes its [`super::distortion_loss`] (so that the loss does not
    /// depend on the scene's units). Differentiable w.r.t. `t`; a ray with `near = far`
    /// gives `s = 0`.
    ///
    /// ```
    /// use candle_core::{Device, Tensor};
    /// use neural_fields::volume::Spacing;
    ///
    /// let dev = Device::Cpu;
    /// let (near, far) = (Tensor::new(&[0.0f64], &dev)?, Tensor::new(&[1e10f64], &dev)?);
    /// let t = Tensor::new(&[[0.0f64, 0.5, 1.0, 2.0, 1e10]], &dev)?;
    /// let s = Spacing::LinearDisparity.normalize(&t, &near, &far)?.to_vec2::<f64>()?;
    /// // Linear to t = 1 (s = ½), then in disparity: t = 2 is halfway to infinity.
    /// for (a, b) in s[0].iter().zip([0.0, 0.25, 0.5, 0.75, 1.0]) {
    ///     assert!((a - b).abs() < 1e-9);
    /// }
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// Naming `t` unless it is `[R, S]` with `near`'s dtype and device and `R` rows, and
    /// `near`/`far` unless `[R]`.
    pub fn normalize(&self, t: &Tensor, near: &Tensor, far: &Tensor) -> Result<Tensor> {
        let r = super::sampling::check_near_far(near, far)?;
        check_float(t, "t")?;
        check_same(t, "t", near, "near")?;
        if t.rank() != 2 || t.dim(0)? != r {
            return Err(Error::invalid(
                "t",
                format!("[{r}, S] (a row per ray)"),
                format!("shape {:?}", t.dims()),
            ));
        }
        let (lo, hi, t) = match self {
            Spacing::Linear => (near.clone(), far.clone(), t.clone()),
            Spacing::LinearDisparity => (lin_disp(near)?, lin_disp(far)?, lin_disp(t)?),
        };
        let span = (&hi - &lo)?;
        // Rays with near = far: s = 0 (span 1 instead of 0).
        let span = (&span + span.eq(0.0)?.to_dtype(span.dtype())?)?;
        Ok(t.broadcast_sub(&lo.unsqueeze(1)?)?
            .broadcast_div(&span.unsqueeze(1)?)?)
    }

    /// Stratified intervals of `n` samples between `near` and `far`, uniform in this
    /// spacing's `s`.
    fn stratified(
        &self,
        near: &Tensor,
        far: &Tensor,
        n: usize,
        jitter: Jitter,
        seed: u64,
    ) -> Result<Intervals> {
        match self {
            Spacing::Linear => stratified(near, far, n, jitter, seed),
            Spacing::LinearDisparity => {
                if scalar_min(near)? < 0.0 {
                    return Err(Error::invalid(
                        "near",
                        "≥ 0 for the linear-then-disparity spacing",
                        "a negative near",
                    ));
                }
                let (lo, hi) = (lin_disp(near)?, lin_disp(far)?);
                let s = stratified(&lo, &hi, n, jitter, seed)?;
                // Back to t, pinned to [near, far] against the round trip's rounding.
                let to_t = |x: &Tensor| -> Result<Tensor> {
                    Ok(lin_disp_inv(x)?
                        .broadcast_maximum(&near.unsqueeze(1)?)?
                        .broadcast_minimum(&far.unsqueeze(1)?)?)
                };
                Intervals::new(to_t(&s.starts)?, to_t(&s.ends)?, Layout::Batched)
            }
        }
    }
}

/// The smallest value of `t` (0 for an empty tensor).
fn scalar_min(t: &Tensor) -> Result<f64> {
    if t.elem_count() == 0 {
        return Ok(0.0);
    }
    Ok(t.min_all()?.to_dtype(DType::F64)?.to_scalar::<f64>()?)
}

/// Samples per level of a [`proposal_sample`] and the draw's settings.
#[derive(Clone, Debug, PartialEq)]
pub struct ProposalConfig {
    /// How the first level spaces its samples (default [`Spacing::Linear`];
    /// [`Spacing::LinearDisparity`] for unbounded scenes).
    pub spacing: Spacing,
    /// Samples per ray at each proposal level, coarse first (one entry per proposal
    /// network). Default `[64, 32]` (nerfacc's Blender recipe uses `[256, 96]` on a GPU).
    pub samples: Vec<usize>,
    /// Samples per ray for the radiance field. Default 32.
    pub final_samples: usize,
    /// Weight added to every proposal bin before the draw, so that no bin is starved
    /// (mip-NeRF 360's resampling padding). Default 0.01.
    pub padding: f64,
    /// With the field's density given: samples behind a transmittance below this are
    /// dropped. Default 1e-4 ([`DEFAULT_TERMINATION_EPS`], nerfacc's `early_stop_eps`).
    pub early_stop_eps: f64,
    /// With the field's density given: samples of opacity `1 − e^{−σδ}` below this are
    /// dropped (nerfacc's `alpha_thre`). Default 0 (none dropped for being faint).
    pub alpha_threshold: f64,
}

impl Default for ProposalConfig {
    fn default() -> Self {
        Self {
            spacing: Spacing::Linear,
            samples: vec![64, 32],
            final_samples: 32,
            padding: 0.01,
            early_stop_eps: DEFAULT_TERMINATION_EPS,
            alpha_threshold: 0.0,
        }
    }
}

/// The result of [`proposal_sample`].
#[derive(Clone, Debug)]
#[non_exhaustive]
pub struct ProposalSamples {
    /// The intervals for the radiance field (detached): `[R, final_samples]` (batched)
    /// without the field's density; with it, the packed `[M]` subset of those that are
    /// visible and not empty.
    pub intervals: Intervals,
    /// Per proposal level: its intervals and its weights `[R, S_l]`, the weights
    /// differentiable w.r.t. the proposal network's parameters (for [`interlevel_loss`]).
    pub levels: Vec<(Intervals, Tensor)>,
    /// With the field's density: the [`interlevel_loss`] of every level, summed, against
    /// the field's weights on all `[R, final_samples]` intervals (a scalar,
    /// differentiable w.r.t. the proposals); `None` without (then compute it from
    /// `levels` and the rendered weights).
    pub interlevel: Option<Tensor>,
}

/// Draws samples along `rays` through proposal networks (see the module docs).
///
/// `near`, `far`: `[R]` (f32 or f64); `proposals[l]` maps positions `[N, 3]` to densities
/// `[N]` (≥ 0) of level `l` — one per entry of `config.samples`. `seed`: `Some` jitters the
/// stratified level and draws the resampling at random (training), `None` is
/// deterministic (evaluation). `sigma_fn`: the radiance field's density (positions
/// `[N, 3]` → `[N]`, read without a graph); with it, the result keeps only the final
/// samples with transmittance ≥ `config.early_stop_eps` and opacity ≥
/// `config.alpha_threshold`, in the packed layout, and carries the interlevel loss.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::camera::Rays;
/// use neural_fields::volume::{proposal_sample, ProposalConfig};
///
/// let dev = Device::Cpu;
/// let rays = Rays::new(Tensor::new(&[[0.0f64, 0.0, -3.0]], &dev)?, Tensor::new(&[[0.0f64, 0.0, 1.0]], &dev)?)?;
/// let (near, far) = (Tensor::new(&[1.0f64], &dev)?, Tensor::new(&[5.0f64], &dev)?);
/// // A proposal that sees a slab around z = 0 (t = 3).
/// let mut slab = |p: &Tensor| -> neural_fields::Result<Tensor> {
///     Ok((p.narrow(1, 2, 1)?.squeeze(1)?.abs()?.affine(-10.0, 2.0)?.relu()? * 50.0)?)
/// };
/// let config = ProposalConfig { samples: vec![64], final_samples: 8, padding: 0.0, ..ProposalConfig::default() };
/// let out = proposal_sample(&rays, &near, &far, &mut [&mut slab], &config, None, None)?;
/// let t = out.intervals.midpoints()?.to_vec2::<f64>()?;
/// assert!(t[0].iter().all(|&t| (2.7..3.3).contains(&t)));     // all samples in the slab
/// // With the field's density (an opaque wall z ≥ −0.15) and an opacity threshold, only
/// // the first sample in the wall remains: those in front are empty, those behind hidden.
/// let mut wall = |p: &Tensor| -> neural_fields::Result<Tensor> {
///     Ok((p.narrow(1, 2, 1)?.squeeze(1)?.ge(-0.15)?.to_dtype(p.dtype())? * 1e3)?)
/// };
/// let culling = ProposalConfig { alpha_threshold: 1e-2, ..config };
/// let culled = proposal_sample(&rays, &near, &far, &mut [&mut slab], &culling, None, Some(&mut wall))?;
/// assert_eq!(culled.intervals.starts.dims(), &[1]);                // packed: one sample
/// assert!(culled.interlevel.is_some());
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `proposals` if their number is not
/// `config.samples.len()` (≥ 1), `config` for a zero sample count, `config.samples` or
/// `config.final_samples` for a level whose `R·(n + 1)` positions pass the allocation limit
/// of 2³³ bytes (8 GiB, counted at 8 bytes a coordinate), before anything is sampled,
/// `config.padding`,
/// `config.early_stop_eps`, `config.alpha_threshold` unless finite and ≥ 0; `sigma_fn`
/// for densities of the wrong shape, dtype or device, or not finite; those of
/// [`stratified`], [`render_weights`] (a proposal returning a wrong shape or negative
/// density) and [`sample_pdf`].
pub fn proposal_sample(
    rays: &Rays,
    near: &Tensor,
    far: &Tensor,
    proposals: &mut [DensityFn<'_>],
    config: &ProposalConfig,
    seed: Option<u64>,
    sigma_fn: Option<DensityFn<'_>>,
) -> Result<ProposalSamples> {
    if config.samples.is_empty() || proposals.len() != config.samples.len() {
        return Err(Error::invalid(
            "proposals",
            format!(
                "one proposal network per level of config.samples ({}, at least 1)",
                config.samples.len()
            ),
            proposals.len().to_string(),
        ));
    }
    if config.final_samples == 0 || config.samples.contains(&0) {
        return Err(Error::invalid(
            "config",
            "at least one sample per level",
            format!("{:?} then {}", config.samples, config.final_samples),
        ));
    }
    // Each level's positions ([R, n + 1, 3] at most) against the allocation limit, before
    // the first level is sampled.
    let rays_n = near.dims().first().copied().unwrap_or(0);
    for (&n, name) in config
        .samples
        .iter()
        .zip(std::iter::repeat("config.samples"))
        .chain([(&config.final_samples, "config.final_samples")])
    {
        crate::limits::check_bytes(name, &[rays_n, n.saturating_add(1), 3], 8)?;
    }
    for (value, name) in [
        (config.padding, "config.padding"),
        (config.early_stop_eps, "config.early_stop_eps"),
        (config.alpha_threshold, "config.alpha_threshold"),
    ] {
        check_scalar(value, name, false)?;
        if value < 0.0 {
            return Err(Error::invalid(name, "≥ 0", value.to_string()));
        }
    }
    let jitter = if seed.is_some() {
        Jitter::PerSample
    } else {
        Jitter::None
    };
    let seed_of = |l: usize| seed.unwrap_or(0).wrapping_add(0x9E37_79B9 * (l as u64 + 1));
    let mut intervals =
        config
            .spacing
            .stratified(near, far, config.samples[0], jitter, seed_of(0))?;
    let mut levels = Vec::with_capacity(proposals.len());
    for (l, proposal) in proposals.iter_mut().enumerate() {
        let (r, s) = intervals.starts.dims2()?;
        let positions = intervals.positions(rays)?.reshape((r * s, 3))?;
        let sigma = proposal(&positions)?.reshape((r, s))?;
        let weights =
            render_weights(&sigma, &intervals, Some(rays), &CompositeConfig::default())?.weights;
        let n = config
            .samples
            .get(l + 1)
            .copied()
            .unwrap_or(config.final_samples);
        // n + 1 sorted draws are the edges of the next level's n intervals (mip-NeRF 360
        // resamples interval edges), so every interval lies where the proposal has weight.
        let t = sample_pdf(
            &intervals,
            &weights.detach(),
            n + 1,
            seed.is_none(),
            seed_of(l + 1),
            config.padding,
        )?;
        let next = Intervals::new(
            t.narrow(1, 0, n)?.contiguous()?,
            crate::narrow::narrow(&t, 1, 1, n)?.contiguous()?,
            Layout::Batched,
        )?;
        levels.push((intervals, weights));
        intervals = next;
    }
    let Some(sigma_fn) = sigma_fn else {
        return Ok(ProposalSamples {
            intervals,
            levels,
            interlevel: None,
        });
    };
    // The field's weights without a graph: the interlevel loss's target, and which
    // samples are worth the whole network.
    let (r, s) = intervals.starts.dims2()?;
    let sigma = sigma_fn(&intervals.positions(rays)?.reshape((r * s, 3))?)?;
    if sigma.elem_count() != r * s || sigma.rank() > 2 {
        return Err(Error::invalid(
            "sigma_fn",
            format!("densities of shape [{}]", r * s),
            format!("shape {:?}", sigma.dims()),
        ));
    }
    check_same(&sigma, "sigma_fn", &intervals.starts, "near")?;
    let sigma = sigma.detach().reshape((r, s))?;
    check_finite(&sigma, "sigma_fn")?;
    let w = render_weights(
        &sigma.relu()?,
        &intervals,
        Some(rays),
        &CompositeConfig::default(),
    )?;
    let mut interlevel = Tensor::zeros((), sigma.dtype(), sigma.device())?;
    for level in &levels {
        interlevel = (interlevel + interlevel_loss(level, &intervals, &w.weights)?)?;
    }
    let visible = w.transmittance.ge(config.early_stop_eps)?;
    let mask = (visible * w.alphas.ge(config.alpha_threshold)?)?;
    Ok(ProposalSamples {
        intervals: intervals.retain(&mask)?.0,
        levels,
        interlevel: Some(interlevel),
    })
}

/// The pairs `(i, j)` of fine interval `i` and coarse interval `j` of the same ray that
/// intersect in an open set (`ŝⱼ < eᵢ` and `êⱼ > sᵢ`), as two u32 index tensors `[P]` into
/// the flattened `[R·S]` fine and `[R·Ŝ]` coarse intervals, fine index ascending. Both sets
/// are sorted along each ray and disjoint within a set (what [`stratified`] and
/// [`sample_pdf`] produce), so the pairs form a staircase: at most `S + Ŝ − 1` per ray,
/// found by a two-pointer sweep (no `[R, S, Ŝ]` overlap matrix).
fn overlap_pairs(fine: &Intervals, coarse: &Intervals) -> Result<(Tensor, Tensor)> {
    let (r, s) = fine.starts.dims2()?;
    let (r2, sc) = coarse.starts.dims2()?;
    if r != r2 {
        return Err(Error::invalid(
            "proposal",
            format!("intervals of the same {r} rays"),
            format!("{r2} rays"),
        ));
    }
    let host = |t: &Tensor| -> Result<Vec<f64>> {
        Ok(t.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?)
    };
    let (fs, fe) = (host(&fine.starts)?, host(&fine.ends)?);
    let (cs, ce) = (host(&coarse.starts)?, host(&coarse.ends)?);
    if r.saturating_mul(s.max(sc)) > u32::MAX as usize {
        return Err(Error::invalid(
            "proposal",
            "fewer than 2³² intervals",
            format!("{r} rays × {}", s.max(sc)),
        ));
    }
    let (mut fine_idx, mut coarse_idx) = (Vec::new(), Vec::new());
    for ray in 0..r {
        let mut first = 0; // the first coarse interval that may still overlap
        for i in 0..s {
            let (a, b) = (fs[ray * s + i], fe[ray * s + i]);
            while first < sc && ce[ray * sc + first] <= a {
                first += 1;
            }
            let mut j = first;
            while j < sc && cs[ray * sc + j] < b {
                // Always true for disjoint coarse intervals; kept for any sorted-by-start
                // input, whose pairs are then no longer a staircase.
                if ce[ray * sc + j] > a {
                    // invariant: both indices are below 2³², checked above.
                    fine_idx.push((ray * s + i) as u32);
                    coarse_idx.push((ray * sc + j) as u32);
                }
                j += 1;
            }
        }
    }
    let dev = fine.starts.device();
    let p = fine_idx.len();
    Ok((
        crate::narrow::from_vec(fine_idx, p, dev)?,
        crate::narrow::from_vec(coarse_idx, p, dev)?,
    ))
}

/// mip-NeRF 360's interlevel (proposal) loss between a proposal level and the final
/// weights:
///
/// `L = mean_r Σᵢ max(0, wᵢ − boundᵢ)² / (wᵢ + ε)`, `boundᵢ = Σⱼ ŵⱼ·[ĵ overlaps i]`,
///
/// the squared amount by which the final weight `wᵢ` of interval `i` exceeds the proposal
/// weight that covers it, with `ε = 1e-7`. Minimising it makes every proposal an upper
/// envelope of the final weights, so that resampling from it misses no surface.
///
/// * `proposal`: one of [`ProposalSamples::levels`] — intervals `[R, Ŝ]` and weights `ŵ:
///   [R, Ŝ]`; the loss is differentiable w.r.t. `ŵ` (and so the proposal network);
/// * `intervals`, `weights`: the final intervals `[R, S]` and the radiance field's weights
///   `w: [R, S]`, **detached** inside (the proposal learns from the field, not the other
///   way round, as in mip-NeRF 360 and nerfacc).
///
/// Both layouts must be batched (what [`proposal_sample`] produces). Returns a scalar in
/// the weights' dtype.
///
/// # Errors
/// [`Error::InvalidArgument`] naming `proposal` for packed intervals, other rays or a
/// weight shape unlike its intervals', and `weights` likewise, or for another dtype.
pub fn interlevel_loss(
    proposal: &(Intervals, Tensor),
    intervals: &Intervals,
    weights: &Tensor,
) -> Result<Tensor> {
    let (coarse, w_hat) = proposal;
    for (iv, w, arg) in [(coarse, w_hat, "proposal"), (intervals, weights, "weights")] {
        check_float(w, arg)?;
        if !matches!(iv.layout, Layout::Batched) || w.dims() != iv.starts.dims() {
            return Err(Error::invalid(
                arg,
                format!(
                    "batched intervals and weights of their shape {:?}",
                    iv.starts.dims()
                ),
                format!("weights {:?}", w.dims()),
            ));
        }
    }
    if weights.dtype() != w_hat.dtype() {
        return Err(Error::invalid(
            "weights",
            format!("{:?} like the proposal's", w_hat.dtype()),
            format!("{:?}", weights.dtype()),
        ));
    }
    let (fine_idx, coarse_idx) = overlap_pairs(intervals, coarse)?;
    let (r, s) = weights.dims2()?;
    // boundᵢ = Σ ŵⱼ over the overlapping pairs: a gather and an index-add, exact sums in
    // O(R·(S + Ŝ)) memory, differentiable w.r.t. ŵ.
    let gathered = w_hat.flatten_all()?.index_select(&coarse_idx, 0)?;
    let bound = Tensor::zeros(r * s, w_hat.dtype(), w_hat.device())?
        .index_add(&fine_idx, &gathered, 0)?
        .reshape((r, s))?;
    let w = weights.detach();
    let excess = (&w - &bound)?.relu()?;
    let per = (excess.sqr()? / (w + 1e-7)?)?;
    Ok((per.sum_all()? / r.max(1) as f64)?)
}
