//! The sample layouts and the checks shared by every compositing path.
//!
//! This module sits below the reference path (candle ops) and the fused CPU kernel, both
//! crate-private, and the entry points ([`super::composite()`]): it
//! imports none of them.
//!
//! Samples along rays are described by [`Intervals`]: per sample an interval
//! `[start, end]` in ray parameter `t`, in one of two [`Layout`]s:
//!
//! - **batched**: `starts`, `ends`: `[R, S]`, every ray has `S` samples;
//! - **packed**: `starts`, `ends`: `[M]`, stored ray by ray, ray `r` owning samples
//!   `offsets[r]..offsets[r + 1]` of a [`Packed`] (rays may have no sample at all; the
//!   occupancy grid emits this layout).
//!
//! Compositing derives the interval lengths δᵢ = (endsᵢ − startsᵢ)·‖d_r‖ and the sample
//! depths tᵢ = (startsᵢ + endsᵢ)/2 from the intervals itself, so that the two can never be
//! swapped.

use crate::camera::Rays;
use crate::error::{check_float, check_same, check_shape, Dim, Error, Result};
use crate::kernels::for_each_init;
use candle_core::{DType, Device, Storage, Tensor, D};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// Packed layout: `M` samples stored flat, ray by ray, with per-ray counts.
///
/// Ray r owns samples `offsets[r] .. offsets[r + 1]`; rays may have zero samples.
/// The host copy of the offsets is kept alongside the device tensors so that the fused
/// CPU op and the padding used by the reference path need no device read-back.
///
/// ```
/// use candle_core::Device;
/// use neural_fields::volume::Packed;
///
/// let packed = Packed::from_counts(&[2, 0, 3], &Device::Cpu)?; // 3 rays, 5 samples
/// assert_eq!(packed.offsets.to_vec1::<u32>()?, vec![0, 2, 2, 5]);
/// assert_eq!(packed.ray_indices.to_vec1::<u32>()?, vec![0, 0, 2, 2, 2]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct Packed {
    /// `[M]` u32: the ray of each sample (non-decreasing).
    pub ray_indices: Tensor,
    /// `[R + 1]` u32: `offsets[r]` is the first sample of ray r, `offsets[R] = M`.
    pub offsets: Tensor,
    /// Number of rays `R`.
    pub n_rays: usize,
    offsets_host: Arc<[usize]>,
}

impl Packed {
    /// Builds the layout from per-ray sample counts (`counts[r]` samples for ray r, zero
    /// allowed), with its index tensors on `device`.
    ///
    /// # Errors
    /// `counts` when the total does not fit in u32; candle errors on allocation.
    pub fn from_counts(counts: &[usize], device: &Device) -> Result<Self> {
        let mut offsets_host = Vec::with_capacity(counts.len() + 1);
        let mut acc = 0usize;
        offsets_host.push(0);
        for &c in counts {
            acc = acc.saturating_add(c);
            offsets_host.push(acc);
        }
        if acc > u32::MAX as usize {
            return Err(Error::invalid(
                "counts",
                "a total sample count that fits in u32",
                format!("{acc}"),
            ));
        }
        let mut ray_idx = Vec::with_capacity(acc);
        for (r, &c) in counts.iter().enumerate() {
            ray_idx.extend(std::iter::repeat_n(r as u32, c));
        }
        let off_u32: Vec<u32> = offsets_host.iter().map(|&o| o as u32).collect();
        Ok(Self {
            ray_indices: crate::narrow::from_vec(ray_idx, acc, device)?,
            offsets: Tensor::from_vec(off_u32, counts.len() + 1, device)?,
            n_rays: counts.len(),
            offsets_host: offsets_host.into(),
        })
    }

    /// Builds the layout from a `[R, S]` visibility mask (u8, nonzero = keep), e.g. from
    /// [`super::visible_mask`]. Returns the layout and the `[M]` u32 flat indices (into
    /// the `R·S` samples, row-major) of the kept samples, for `index_select` on flattened
    /// per-sample tensors ([`Intervals::retain`] for batched intervals).
    ///
    /// # Errors
    /// `mask` when it is not a 2-D u8 tensor.
    pub(crate) fn from_mask(mask: &Tensor) -> Result<(Self, Tensor)> {
        let dims = check_shape(mask, "mask", &[Dim::Any("R"), Dim::Any("S")])?;
        if mask.dtype() != DType::U8 {
            return Err(Error::invalid(
                "mask",
                "dtype u8",
                format!("{:?}", mask.dtype()),
            ));
        }
        let (r, s) = (dims[0], dims[1]);
        let host = mask.flatten_all()?.to_vec1::<u8>()?;
        let mut counts = vec![0usize; r];
        let mut keep = Vec::new();
        for (i, &m) in host.iter().enumerate() {
            if m != 0 {
                counts[i / s.max(1)] += 1;
                keep.push(i as u32);
            }
        }
        let n = keep.len();
        let packed = Self::from_counts(&counts, mask.device())?;
        Ok((packed, crate::narrow::from_vec(keep, n, mask.device())?))
    }

    /// Total number of samples `M`.
    #[must_use]
    pub(crate) fn n_samples(&self) -> usize {
        self.offsets_host.last().copied().unwrap_or(0)
    }

    /// Host copy of the offsets (`R + 1` entries).
    #[must_use]
    pub(crate) fn offsets_host(&self) -> &[usize] {
        &self.offsets_host
    }

    /// Shared host copy of the offsets (cheap to clone).
    pub(crate) fn offsets_arc(&self) -> Arc<[usize]> {
        self.offsets_host.clone()
    }

    /// Largest per-ray sample count.
    pub(crate) fn max_count(&self) -> usize {
        self.offsets_host
            .windows(2)
            .map(|w| w[1] - w[0])
            .max()
            .unwrap_or(0)
    }
}

/// How per-sample tensors are laid out: `[R, S, …]` (batched) or `[M, …]` ray by ray
/// (packed).
#[derive(Clone, Debug)]
pub enum Layout {
    /// Every ray has the same number `S` of samples: per-sample tensors are `[R, S, …]`.
    Batched,
    /// Rays own `offsets[r]..offsets[r + 1]` of `M` flat samples: per-sample tensors are
    /// `[M, …]`.
    Packed(Packed),
}

/// Sample intervals along a batch of rays: `starts` and `ends` in ray parameter `t`,
/// `[R, S]` in the batched [`Layout`] or `[M]` in the packed one, with
/// `startsᵢ ≤ endsᵢ ≤ startsᵢ₊₁` along each ray.
///
/// Built by [`super::stratified`], [`Intervals::from_samples`], the occupancy grid's
/// [`super::OccupancyGrid::sample`], or from your own tensors with [`Intervals::new`]
/// (which validates them, in either layout).
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::camera::Rays;
/// use neural_fields::volume::{Intervals, Layout};
///
/// let dev = Device::Cpu;
/// let iv = Intervals::new(
///     Tensor::new(&[[0.0f32, 1.0], [2.0, 3.0]], &dev)?,   // starts [R = 2, S = 2]
///     Tensor::new(&[[1.0f32, 2.0], [3.0, 5.0]], &dev)?,   // ends
///     Layout::Batched,
/// )?;
/// let rays = Rays::new(
///     Tensor::zeros((2, 3), candle_core::DType::F32, &dev)?,
///     Tensor::new(&[[0.0f32, 0.0, 2.0], [0.0, 1.0, 0.0]], &dev)?, // |d| = 2 and 1
/// )?;
/// assert_eq!(iv.midpoints()?.to_vec2::<f32>()?, vec![vec![0.5, 1.5], vec![2.5, 4.0]]);
/// assert_eq!(iv.deltas(Some(&rays))?.to_vec2::<f32>()?, vec![vec![2.0, 2.0], vec![1.0, 2.0]]);
/// assert_eq!(iv.positions(&rays)?.dims(), &[2, 2, 3]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct Intervals {
    /// Interval starts, `[R, S]` (batched) or `[M]` (packed).
    pub starts: Tensor,
    /// Interval ends, the shape of `starts`.
    pub ends: Tensor,
    /// The layout of `starts` and `ends`, and of every per-sample tensor composited with
    /// them.
    pub layout: Layout,
}

/// Checks that every `(start, end)` pair is finite with `start ≤ end` and that each
/// ray's intervals are sorted (`endsᵢ ≤ startsᵢ₊₁`); `ray_of(i)` names the ray of flat
/// index `i`, `next_same_ray(i)` says whether `i + 1` belongs to the same ray.
fn check_sorted(
    s: &[f64],
    e: &[f64],
    ray_of: impl Fn(usize) -> usize,
    next_same_ray: impl Fn(usize) -> bool,
) -> Result<()> {
    for (i, (&a, &b)) in s.iter().zip(e).enumerate() {
        if !a.is_finite() || !b.is_finite() {
            return Err(Error::invalid(
                "starts",
                "finite intervals",
                format!("NaN or infinity at ray {}", ray_of(i)),
            ));
        }
        if a > b {
            return Err(Error::invalid(
                "ends",
                "ends ≥ starts for every interval",
                format!("start {a} > end {b} at ray {}", ray_of(i)),
            ));
        }
        if next_same_ray(i) && b > s[i + 1] {
            return Err(Error::invalid(
                "starts",
                "intervals sorted along each ray (endsᵢ ≤ startsᵢ₊₁)",
                format!("end {b} > next start {} at ray {}", s[i + 1], ray_of(i)),
            ));
        }
    }
    Ok(())
}

impl Intervals {
    /// Intervals from `starts` and `ends` in `layout`: `[R, S]` for [`Layout::Batched`],
    /// `[M]` with `M` the samples of `packed` for [`Layout::Packed`] (ray `r` owning
    /// `offsets[r]..offsets[r + 1]`); f32 or f64, one dtype and device.
    ///
    /// Reads the values back to check that every interval has `start ≤ end` and that
    /// intervals are sorted along each ray (`endsᵢ ≤ startsᵢ₊₁`).
    ///
    /// # Errors
    /// Naming `starts` or `ends` on a dtype, shape (against `packed` when packed) or
    /// device mismatch, on non-finite values, or when the intervals are inverted or
    /// unsorted.
    pub fn new(starts: Tensor, ends: Tensor, layout: Layout) -> Result<Self> {
        check_float(&starts, "starts")?;
        let packed = match layout {
            Layout::Batched => {
                let dims = check_shape(&starts, "starts", &[Dim::Any("R"), Dim::Any("S")])?;
                check_same(&ends, "ends", &starts, "starts")?;
                check_shape(&ends, "ends", &[Dim::Is(dims[0]), Dim::Is(dims[1])])?;
                let n = dims[1];
                check_sorted(
                    &host_f64(&starts)?,
                    &host_f64(&ends)?,
                    |i| i / n,
                    |i| i % n + 1 < n,
                )?;
                return Ok(Intervals {
                    starts,
                    ends,
                    layout: Layout::Batched,
                });
            }
            Layout::Packed(packed) => packed,
        };
        let m = packed.n_samples();
        check_shape(&starts, "starts", &[Dim::Is(m)])?;
        check_same(&ends, "ends", &starts, "starts")?;
        check_shape(&ends, "ends", &[Dim::Is(m)])?;
        let off = packed.offsets_host();
        let mut ray = vec![0usize; m];
        for r in 0..packed.n_rays {
            ray[off[r]..off[r + 1]].fill(r);
        }
        check_sorted(
            &host_f64(&starts)?,
            &host_f64(&ends)?,
            |i| ray[i],
            |i| i + 1 < m && ray[i + 1] == ray[i],
        )?;
        Ok(Intervals {
            starts,
            ends,
            layout: Layout::Packed(packed),
        })
    }

    /// The intervals where `mask` (u8, nonzero = keep; the intervals' sample shape, `[R, S]`
    /// or `[M]`) is set, in the packed layout over the same `R` rays, and the `[K]` u32 flat
    /// indices of the kept samples (into the row-major flattening of the sample shape) for
    /// `index_select` on per-sample tensors. With [`super::visible_mask`] this is early
    /// termination: evaluate the density, keep the visible samples, evaluate the colour
    /// (and the graph) only there.
    ///
    /// ```
    /// use candle_core::{Device, Tensor};
    /// use neural_fields::volume::{stratified, Jitter, Layout};
    ///
    /// let dev = Device::Cpu;
    /// let iv = stratified(&Tensor::new(&[0.0f32, 0.0], &dev)?, &Tensor::new(&[1.0f32, 1.0], &dev)?, 3, Jitter::None, 0)?;
    /// let mask = Tensor::new(&[[1u8, 1, 0], [0, 0, 0]], &dev)?;
    /// let (kept, idx) = iv.retain(&mask)?;
    /// assert_eq!(idx.to_vec1::<u32>()?, vec![0, 1]);
    /// assert_eq!(kept.starts.dims(), &[2]); // two samples kept, of the same two rays
    /// assert!(matches!(&kept.layout, Layout::Packed(p) if p.n_rays == 2));
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `mask` unless u8 of the intervals' sample shape.
    pub fn retain(&self, mask: &Tensor) -> Result<(Intervals, Tensor)> {
        if mask.dtype() != DType::U8 || mask.dims() != self.starts.dims() {
            return Err(Error::invalid(
                "mask",
                format!("u8 of the samples' shape {:?}", self.starts.dims()),
                format!("{:?} {:?}", mask.dtype(), mask.dims()),
            ));
        }
        let (packed, keep) = match &self.layout {
            Layout::Batched => Packed::from_mask(mask)?,
            Layout::Packed(p) => {
                let host = mask.to_vec1::<u8>()?;
                let off = p.offsets_host();
                let mut counts = vec![0usize; p.n_rays];
                let mut keep = Vec::new();
                for (r, count) in counts.iter_mut().enumerate() {
                    for (i, &m) in host.iter().enumerate().take(off[r + 1]).skip(off[r]) {
                        if m != 0 {
                            *count += 1;
                            keep.push(i as u32);
                        }
                    }
                }
                let n = keep.len();
                (
                    Packed::from_counts(&counts, mask.device())?,
                    crate::narrow::from_vec(keep, n, mask.device())?,
                )
            }
        };
        let pick = |t: &Tensor| -> Result<Tensor> { Ok(t.flatten_all()?.index_select(&keep, 0)?) };
        let kept = Intervals {
            starts: pick(&self.starts)?,
            ends: pick(&self.ends)?,
            layout: Layout::Packed(packed),
        };
        Ok((kept, keep))
    }

    /// The number of rays `R`.
    #[must_use]
    pub(crate) fn n_rays(&self) -> usize {
        match &self.layout {
            Layout::Batched => self.starts.dims().first().copied().unwrap_or(0),
            Layout::Packed(p) => p.n_rays,
        }
    }

    /// Midpoints `mᵢ = startsᵢ + (endsᵢ − startsᵢ)/2`, the shape of `starts`, where the
    /// field is usually evaluated and the depth each sample contributes to the expected
    /// depth (compositing forms them the same way, on every path). The intervals' dtype
    /// and device; differentiable w.r.t. `starts` and `ends`.
    ///
    /// # Errors
    /// Only candle errors.
    pub fn midpoints(&self) -> Result<Tensor> {
        self.midpoints_of(&self.span()?)
    }

    /// Interval lengths in world units: `δᵢ = (endsᵢ − startsᵢ)·‖d_r‖` for the ray `r`
    /// of each sample, the shape of `starts`.
    ///
    /// With `rays: Some(..)` the lengths in `t` are scaled by each ray's direction norm,
    /// so that unnormalised directions (the camera module returns directions with unit
    /// z, not unit length) give physical distances; with `None` the directions are taken
    /// to be unit vectors. Differentiable w.r.t. the intervals and the directions.
    ///
    /// # Errors
    /// Naming `rays` when their count differs from the intervals' or their dtype or
    /// device differs.
    pub fn deltas(&self, rays: Option<&Rays>) -> Result<Tensor> {
        self.deltas_of(self.span()?, self.direction_norms(rays)?.as_ref())
    }

    /// The lengths in `t`, `endsᵢ − startsᵢ`, from which [`Intervals::deltas`] and
    /// [`Intervals::midpoints`] are both formed.
    pub(crate) fn span(&self) -> Result<Tensor> {
        Ok((&self.ends - &self.starts)?)
    }

    /// `startsᵢ + spanᵢ/2`.
    pub(crate) fn midpoints_of(&self, span: &Tensor) -> Result<Tensor> {
        Ok((&self.starts + span.affine(0.5, 0.0)?)?)
    }

    /// `spanᵢ·‖d_r‖` for per-ray norms `[R]` (`span` as is without them).
    pub(crate) fn deltas_of(&self, span: Tensor, norms: Option<&Tensor>) -> Result<Tensor> {
        match norms {
            None => Ok(span),
            Some(norms) => Ok(span.broadcast_mul(&self.per_sample(norms)?)?),
        }
    }

    /// Sample positions `o_r + mᵢ·d_r` at the midpoints: `[R, S, 3]` (batched) or
    /// `[M, 3]` (packed), the rays' dtype. Differentiable w.r.t. the intervals and the
    /// rays.
    ///
    /// # Errors
    /// Naming `rays` when their count differs from the intervals' or their dtype or
    /// device differs.
    pub fn positions(&self, rays: &Rays) -> Result<Tensor> {
        let d = self.directions(rays)?;
        let m = self.midpoints()?.unsqueeze(D::Minus1)?;
        let o = match &self.layout {
            Layout::Batched => rays.origins().unsqueeze(1)?,
            Layout::Packed(p) => rays.origins().index_select(&p.ray_indices, 0)?,
        };
        Ok(o.broadcast_add(&d.broadcast_mul(&m)?)?)
    }

    /// Each sample's ray direction `d_r`, the shape of [`Intervals::positions`]:
    /// `[R, S, 3]` (batched; a broadcast view, nothing copied) or `[M, 3]` (packed,
    /// gathered). What a radiance field reads beside the positions; flatten both with
    /// `reshape(((), 3))` for an `[N, 3]` network. The rays' dtype; differentiable w.r.t.
    /// the directions.
    ///
    /// ```
    /// use candle_core::{Device, Tensor};
    /// use neural_fields::camera::Rays;
    /// use neural_fields::volume::{stratified, Jitter};
    /// # fn main() -> neural_fields::Result<()> {
    /// let dev = Device::Cpu;
    /// let origins = Tensor::zeros((2, 3), candle_core::DType::F32, &dev)?;
    /// let dirs = Tensor::new(&[[0f32, 0., 1.], [1., 0., 0.]], &dev)?;
    /// let rays = Rays::new(origins, dirs)?;
    /// let near = Tensor::new(&[1f32, 1.], &dev)?;
    /// let far = Tensor::new(&[2f32, 2.], &dev)?;
    /// let iv = stratified(&near, &far, 4, Jitter::None, 0)?;
    /// let d = iv.directions(&rays)?;
    /// assert_eq!(d.dims(), &[2, 4, 3]);
    /// assert_eq!(d.reshape(((), 3))?.to_vec2::<f32>()?[5], vec![1., 0., 0.]);
    /// # Ok(())
    /// # }
    /// ```
    ///
    /// # Errors
    /// Naming `rays` when their count differs from the intervals' or their dtype or
    /// device differs.
    pub fn directions(&self, rays: &Rays) -> Result<Tensor> {
        self.check_rays(rays)?;
        Ok(match &self.layout {
            Layout::Batched => {
                let (r, s) = self.starts.dims2()?;
                rays.directions().unsqueeze(1)?.broadcast_as((r, s, 3))?
            }
            Layout::Packed(p) => rays.directions().index_select(&p.ray_indices, 0)?,
        })
    }

    /// Interval edges `[R, S + 1]` of batched intervals: the starts followed by the last
    /// end. This describes the intervals exactly when they are contiguous
    /// (`endsᵢ = startsᵢ₊₁`), as those of [`super::stratified`] are; they are the
    /// bins of [`super::sample_pdf`]. The intervals' dtype and device; differentiable
    /// w.r.t. `starts` and the last `ends`.
    ///
    /// # Errors
    /// Naming `intervals` when they are packed, `starts` when there are no samples per
    /// ray.
    pub(crate) fn edges(&self) -> Result<Tensor> {
        if matches!(self.layout, Layout::Packed(_)) {
            return Err(Error::invalid(
                "intervals",
                "the batched layout",
                "packed intervals",
            ));
        }
        let s = self.starts.dims().get(1).copied().unwrap_or(0);
        if s == 0 {
            return Err(Error::invalid(
                "starts",
                "at least one interval per ray",
                "S = 0",
            ));
        }
        Ok(Tensor::cat(
            &[
                &self.starts,
                &crate::narrow::narrow(&self.ends, 1, s - 1, 1)?,
            ],
            1,
        )?)
    }

    /// Checks that `rays` match these intervals: as many rays, same dtype and device.
    pub(crate) fn check_rays(&self, rays: &Rays) -> Result<()> {
        let r = self.n_rays();
        if rays.len() != r {
            return Err(Error::invalid(
                "rays",
                format!("{r} rays (those of the intervals)"),
                format!("{}", rays.len()),
            ));
        }
        check_same(rays.origins(), "rays", &self.starts, "intervals")
    }

    /// `‖d_r‖` per ray, `[R]`, or `None` without rays.
    pub(crate) fn direction_norms(&self, rays: Option<&Rays>) -> Result<Option<Tensor>> {
        let Some(rays) = rays else {
            return Ok(None);
        };
        self.check_rays(rays)?;
        Ok(Some(rays.directions().sqr()?.sum(1)?.sqrt()?))
    }

    /// A per-ray `[R]` tensor broadcast to the samples: `[R, 1]` (batched) or `[M]`
    /// (packed, gathered).
    pub(crate) fn per_sample(&self, per_ray: &Tensor) -> Result<Tensor> {
        Ok(match &self.layout {
            Layout::Batched => per_ray.unsqueeze(1)?,
            Layout::Packed(p) => per_ray.index_select(&p.ray_indices, 0)?,
        })
    }
}

/// Per-sample compositing quantities returned by [`super::render_weights`]. All have the
/// shape of the input densities (`[R, S]` or `[M]`) and its dtype.
#[derive(Clone, Debug)]
#[non_exhaustive]
pub struct Weights {
    /// wᵢ = Tᵢαᵢ.
    pub weights: Tensor,
    /// Tᵢ = exp(−Σ_{j<i} σⱼδⱼ), the transmittance before sample i (T₀ = 1).
    pub transmittance: Tensor,
    /// αᵢ = 1 − exp(−σᵢδᵢ) (1 for the last sample under `opaque_last`).
    pub alphas: Tensor,
}

impl Weights {
    pub(crate) fn new(weights: Tensor, transmittance: Tensor, alphas: Tensor) -> Self {
        Weights {
            weights,
            transmittance,
            alphas,
        }
    }
}

/// Reads a float tensor back to the host as f64 values (row-major).
pub(crate) fn host_f64(t: &Tensor) -> Result<Vec<f64>> {
    Ok(t.detach()
        .to_dtype(DType::F64)?
        .flatten_all()?
        .to_vec1::<f64>()?)
}

/// Index and value of the first element outside [`lo`, `max`] (NaN included), or
/// `None`. A branch-free (vectorisable) pass finds whether one exists; only then is it
/// located. This check runs on every compositing call, so slices of at least
/// 2·[`PARALLEL_CHECK_LEN`] elements are checked in chunks of that length on candle's
/// CPU pool.
fn first_bad<T>(xs: &[T], lo: T, max: T) -> Option<(usize, f64)>
where
    T: Copy + PartialOrd + Into<f64> + Sync,
{
    let ok = |v: T| (v >= lo) & (v <= max);
    let all_ok = |c: &[T]| {
        c.chunks(1024)
            .all(|c| c.iter().fold(true, |acc, &v| acc & ok(v)))
    };
    let fine = if xs.len() < 2 * PARALLEL_CHECK_LEN {
        all_ok(xs)
    } else {
        let failed = AtomicBool::new(false);
        let chunks = xs.chunks(PARALLEL_CHECK_LEN).collect();
        for_each_init(
            chunks,
            || (),
            |_, c| {
                if !all_ok(c) {
                    failed.store(true, Ordering::Relaxed);
                }
            },
        );
        !failed.load(Ordering::Relaxed)
    };
    if fine {
        return None;
    }
    xs.iter().position(|&v| !ok(v)).map(|i| (i, xs[i].into()))
}

/// Chunk length of the parallel input check in [`first_bad`].
const PARALLEL_CHECK_LEN: usize = 1 << 16;

/// Checks that every element of `t` is finite and `≥ 0` (densities, interval lengths);
/// the error names `arg`.
pub(crate) fn check_nonneg_finite(t: &Tensor, arg: &'static str) -> Result<()> {
    check_in_range(t, arg, true)
}

/// Checks that every element of `t` is finite (colours and other values); the error names
/// `arg`.
pub(crate) fn check_all_finite(t: &Tensor, arg: &'static str) -> Result<()> {
    check_in_range(t, arg, false)
}

/// Every element finite, and `≥ 0` if `nonneg`: one parallel pass over contiguous CPU
/// storage, candle reductions elsewhere.
fn check_in_range(t: &Tensor, arg: &'static str, nonneg: bool) -> Result<()> {
    let expected = if nonneg {
        "finite values >= 0"
    } else {
        "finite values"
    };
    if t.elem_count() == 0 {
        return Ok(());
    }
    {
        let (st, layout) = t.storage_and_layout();
        if let (Storage::Cpu(cpu), Some((a, b))) = (&*st, layout.contiguous_offsets()) {
            let bad = match t.dtype() {
                DType::F32 => {
                    let lo = if nonneg { 0.0 } else { -f32::MAX };
                    first_bad(&cpu.as_slice::<f32>()?[a..b], lo, f32::MAX)
                }
                DType::F64 => {
                    let lo = if nonneg { 0.0 } else { -f64::MAX };
                    first_bad(&cpu.as_slice::<f64>()?[a..b], lo, f64::MAX)
                }
                other => {
                    return Err(Error::invalid(
                        arg,
                        "dtype f32 or f64",
                        format!("{other:?}"),
                    ))
                }
            };
            return match bad {
                None => Ok(()),
                Some((i, v)) => Err(Error::invalid(
                    arg,
                    expected,
                    format!("{v} at flat index {i}"),
                )),
            };
        }
    }
    let x = t.detach().to_dtype(DType::F64)?.flatten_all()?;
    // x − x is NaN exactly for NaN and ±∞.
    let probe = x.sub(&x)?.sum_all()?.to_scalar::<f64>()?;
    if !probe.is_finite() {
        return Err(Error::invalid(arg, expected, "NaN or infinity"));
    }
    if nonneg {
        let min = x.min(0)?.to_scalar::<f64>()?;
        if min < 0.0 {
            return Err(Error::invalid(arg, expected, format!("minimum {min}")));
        }
    }
    Ok(())
}

/// The error for intervals with a non-finite bound or `end < start` (or a non-finite
/// length once scaled by the ray's direction norm).
pub(crate) fn bad_intervals() -> Error {
    Error::invalid(
        "intervals",
        "finite intervals with ends ≥ starts (and finite lengths once scaled by |d|)",
        "a NaN, infinite or inverted interval",
    )
}

/// Checks the shapes of `sigmas` against the intervals' layout (`[R, S]` or `[M]`,
/// float, same dtype and device) and, when given, `values` as `[R, S, C]` / `[M, C]`
/// (`arg` names them). Returns the channel count `C` (0 without values). The values of
/// `sigmas` (finite, ≥ 0) are checked by the caller: by [`check_nonneg_finite`] on the
/// reference path, inside the fused kernel's own pass on the CPU.
pub(crate) fn check_samples(
    sigmas: &Tensor,
    values: Option<(&Tensor, &'static str)>,
    intervals: &Intervals,
) -> Result<usize> {
    check_float(sigmas, "sigmas")?;
    check_same(&intervals.starts, "intervals", sigmas, "sigmas")?;
    check_same(&intervals.ends, "intervals", sigmas, "sigmas")?;
    let sample_dims: Vec<Dim> = intervals
        .starts
        .dims()
        .iter()
        .map(|&d| Dim::Is(d))
        .collect();
    if intervals.ends.dims() != intervals.starts.dims() {
        return Err(Error::invalid(
            "intervals",
            format!("ends of the shape of starts {:?}", intervals.starts.dims()),
            format!("{:?}", intervals.ends.dims()),
        ));
    }
    match &intervals.layout {
        Layout::Batched => {
            check_shape(
                &intervals.starts,
                "intervals",
                &[Dim::Any("R"), Dim::Any("S")],
            )?;
        }
        Layout::Packed(p) => {
            check_shape(&intervals.starts, "intervals", &[Dim::Is(p.n_samples())])?;
        }
    }
    check_shape(sigmas, "sigmas", &sample_dims)?;
    let mut c = 0;
    if let Some((v, arg)) = values {
        check_same(v, arg, sigmas, "sigmas")?;
        let mut pattern = sample_dims.clone();
        pattern.push(Dim::Any("C"));
        c = *check_shape(v, arg, &pattern)?.last().unwrap_or(&0);
    }
    Ok(c)
}
