//! Fused CPU compositing op with an O(S)-per-ray analytic backward.
//!
//! One candle [`CustomOp3`] takes `(sigmas, geometry, values)`, where `geometry` is δ, or
//! δ and the sample depths t stacked along a new leading axis (`[2, …]`, a contiguous
//! block copy whose backward is a contiguous split), and returns per ray the accumulated
//! values Σwᵢvᵢₖ for every channel k, then Σwᵢtᵢ (with t), then the opacity Σwᵢ: a single
//! `[R, K + 2]` (or `[R, K + 1]`) tensor. [`composite_fused`] passes the colours as values,
//! so one pass yields colour, expected depth and opacity, split with `narrow` (views).
//! Per-sample weights are not an output; use
//! [`super::composite::render_weights`] when they are needed.
//!
//! Forward (per ray, in f64 whatever the storage dtype): xᵢ = min(σᵢδᵢ, X_MAX); αᵢ =
//! −expm1(−xᵢ) and e^{−xᵢ} from one branch-free range-reduced polynomial (vectorised
//! across the ray's samples; full relative accuracy of the storage dtype, see
//! docs/math.md); then the sequential scan Tᵢ₊₁ = Tᵢ·e^{−xᵢ}, wᵢ = Tᵢαᵢ. Once
//! T < 1e-300 the rest of the ray contributes nothing representable and the scan stops
//! (this also keeps denormals out of the loop).
//!
//! Backward (derivation in docs/math.md, "Volume compositing"): with upstream gradients
//! gₖ for the channels and g_O for the opacity, uᵢ = Σₖ gₖvᵢₖ + g_O and
//!
//! - ∂L/∂vᵢₖ = wᵢgₖ,
//! - ∂L/∂xⱼ = Tⱼ₊₁uⱼ − Σ_{i>j} wᵢuᵢ (0 for an opaque last sample),
//! - ∂L/∂σⱼ = δⱼ·∂L/∂xⱼ, ∂L/∂δⱼ = σⱼ·∂L/∂xⱼ,
//!
//! evaluated by recomputing the forward scan into a per-ray buffer and one reverse scan
//! for the suffix sum: O(S) per ray, no n×n work, no division by α or T. Rays run in
//! parallel with rayon. The backward is not itself differentiable (no second order), and
//! it only computes the gradients of inputs that are part of the autograd graph.

use super::composite::{
    check_composite_inputs, check_composite_inputs_packed, check_sigmas_deltas, finish, Composite,
    CompositeOptions, Packed, X_MAX,
};
use crate::error::{check_same, check_shape, Dim, Error, Result};
use candle_core::{CpuStorage, CustomOp3, DType, Layout, Shape, Storage, Tensor, WithDType};
use rayon::prelude::*;
use std::sync::Arc;

/// Transmittance below which a ray is considered spent inside the kernel.
const T_STOP: f64 = 1e-300;

/// How the flat sample array splits into rays.
#[derive(Clone, Debug)]
enum Segments {
    /// `rays` rays of `s` samples each.
    Uniform { rays: usize, s: usize },
    /// Ray r owns `off[r]..off[r + 1]`.
    Offsets(Arc<[usize]>),
}

impl Segments {
    fn n_rays(&self) -> usize {
        match self {
            Segments::Uniform { rays, .. } => *rays,
            Segments::Offsets(o) => o.len().saturating_sub(1),
        }
    }
    fn n_samples(&self) -> usize {
        match self {
            Segments::Uniform { rays, s } => rays * s,
            Segments::Offsets(o) => o.last().copied().unwrap_or(0),
        }
    }
    fn range(&self, r: usize) -> (usize, usize) {
        match self {
            Segments::Uniform { s, .. } => (r * s, (r + 1) * s),
            Segments::Offsets(o) => (o[r], o[r + 1]),
        }
    }
}

/// The fused compositing op on `(sigmas [M], geometry [G, M], values [M, K])`, where the
/// geometry rows are δ and, when `depth` (G = 2), the sample depths t. Output
/// `[R, K + G]` = (Σwᵢvᵢₖ for each k, Σwᵢtᵢ if `depth`, Σwᵢ).
#[derive(Clone, Debug)]
struct FusedComposite {
    seg: Segments,
    k: usize,
    depth: bool,
    opaque_last: bool,
}

/// ln 2 split for Cody–Waite range reduction (fdlibm constants): `LN2_HI` has trailing
/// zero bits so that `k·LN2_HI` is exact for |k| < 2¹¹.
const LN2_HI: f64 = 6.931_471_803_691_238e-1;
const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
/// 1.5·2⁵²: adding and subtracting it rounds to the nearest integer.
const ROUND_MAGIC: f64 = 6_755_399_441_055_744.0;

/// Taylor coefficients 1/(j+1)! of expm1(r)/r = 1 + r/2 + r²/6 + …, highest first: the
/// last `D` are used: degree D in r, relative truncation |r|^D/(D+2)! at |r| ≤ ln2/2,
/// below 1e-18 for D = 13 (f64) and 2e-9 for D = 7 (f32).
const EXPM1_COEF: [f64; 13] = [
    1.0 / 87_178_291_200.0,
    1.0 / 6_227_020_800.0,
    1.0 / 479_001_600.0,
    1.0 / 39_916_800.0,
    1.0 / 3_628_800.0,
    1.0 / 362_880.0,
    1.0 / 40_320.0,
    1.0 / 5_040.0,
    1.0 / 720.0,
    1.0 / 120.0,
    1.0 / 24.0,
    1.0 / 6.0,
    0.5,
];

/// (α, e^{−x}) = (−expm1(−x), exp(−x)) for x ∈ [0, X_MAX], branch-free (vectorisable).
///
/// Range reduction −x = k·ln2 + r, |r| ≤ ln2/2 (Cody–Waite), q = expm1(r) by a degree-`D`
/// polynomial, then e^{−x} = 2ᵏ(1 + q) and expm1(−x) = 2ᵏq + (2ᵏ − 1). For x < ln2/2,
/// k = 0 and α = −q keeps full relative accuracy (α = x at x = 1e-30); for larger x,
/// α ≥ 0.29 and the sum has no cancellation. e^{−x} is flushed to 0 for x > 708 (below
/// the smallest normal f64).
#[inline(always)]
fn alpha_and_decay<const D: usize>(x: f64) -> (f64, f64) {
    let y = -x.min(708.0);
    let t = y * std::f64::consts::LOG2_E + ROUND_MAGIC;
    let k = (t.to_bits() as i64).wrapping_sub(ROUND_MAGIC.to_bits() as i64);
    let kf = t - ROUND_MAGIC;
    let r = (y - kf * LN2_HI) - kf * LN2_LO;
    let mut p = EXPM1_COEF[13 - D];
    for &c in &EXPM1_COEF[14 - D..] {
        p = p * r + c;
    }
    let q = (p * r + 1.0) * r;
    let scale = f64::from_bits(((k + 1023) as u64) << 52);
    let em = scale * q + (scale - 1.0);
    let decay = scale + scale * q;
    if x > 708.0 {
        (1.0, 0.0)
    } else {
        (-em, decay)
    }
}

/// For each sample: xᵢ = min(σᵢδᵢ, X_MAX), αᵢ = −expm1(−xᵢ) and e^{−xᵢ}, both to full
/// relative accuracy of the storage dtype (f64: degree 13, f32: degree 7). `alpha` and
/// `decay` must have the length of `sig`.
#[inline(always)]
fn alpha_decay<T: WithDType>(sig: &[T], del: &[T], alpha: &mut [f64], decay: &mut [f64]) {
    fn run<T: WithDType, const D: usize>(
        sig: &[T],
        del: &[T],
        alpha: &mut [f64],
        decay: &mut [f64],
    ) {
        for (((s, d), a), e) in sig
            .iter()
            .zip(del)
            .zip(alpha.iter_mut())
            .zip(decay.iter_mut())
        {
            let x = (s.to_f64() * d.to_f64()).min(X_MAX);
            (*a, *e) = alpha_and_decay::<D>(x);
        }
    }
    if T::DTYPE == DType::F32 {
        run::<T, 7>(sig, del, alpha, decay)
    } else {
        run::<T, 13>(sig, del, alpha, decay)
    }
}

/// Per-thread scratch for one ray.
#[derive(Default)]
struct Scratch {
    alpha: Vec<f64>,
    decay: Vec<f64>,
    w: Vec<f64>,
    t_next: Vec<f64>,
    acc: Vec<f64>,
    g: Vec<f64>,
}

/// Forward scan of one ray. Fills `sc.acc` with (Σwᵢvᵢₖ for k < K, Σwᵢtᵢ if `tm` is
/// given, Σwᵢ) and, when `store`, `sc.w[i]` = wᵢ and `sc.t_next[i]` = Tᵢ₊₁. Returns the
/// number of samples scanned: after T < T_STOP the rest have zero weight.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn scan_ray<T: WithDType>(
    sig: &[T],
    del: &[T],
    tm: Option<&[T]>,
    vals: &[T],
    k: usize,
    opaque_last: bool,
    sc: &mut Scratch,
    store: bool,
) -> usize {
    let n = sig.len();
    let g = usize::from(tm.is_some());
    sc.acc.clear();
    sc.acc.resize(k + g + 1, 0.0);
    sc.alpha.resize(n, 0.0);
    sc.decay.resize(n, 0.0);
    if store {
        sc.w.resize(n, 0.0);
        sc.t_next.resize(n, 0.0);
    }
    alpha_decay(sig, del, &mut sc.alpha, &mut sc.decay);
    if opaque_last && n > 0 {
        sc.alpha[n - 1] = 1.0;
        sc.decay[n - 1] = 0.0;
    }
    let mut t = 1.0f64;
    let mut op = 0.0f64;
    let mut dep = 0.0f64;
    let mut live = n;
    for i in 0..n {
        let w = t * sc.alpha[i];
        let v = &vals[i * k..(i + 1) * k];
        for (a, vv) in sc.acc[..k].iter_mut().zip(v) {
            *a += w * vv.to_f64();
        }
        if let Some(tm) = tm {
            dep += w * tm[i].to_f64();
        }
        op += w;
        t *= sc.decay[i];
        if store {
            sc.w[i] = w;
            sc.t_next[i] = t;
        }
        if t < T_STOP {
            live = i + 1;
            break;
        }
    }
    if g == 1 {
        sc.acc[k] = dep;
    }
    sc.acc[k + g] = op;
    live
}

/// Mutable per-ray sub-slices of `buf` (`k` entries per sample).
fn split_rays<'a, T>(mut buf: &'a mut [T], seg: &Segments, k: usize) -> Vec<&'a mut [T]> {
    let r = seg.n_rays();
    let mut out = Vec::with_capacity(r);
    for ray in 0..r {
        let (a, b) = seg.range(ray);
        let (head, tail) = std::mem::take(&mut buf).split_at_mut((b - a) * k);
        out.push(head);
        buf = tail;
    }
    out
}

fn cpu_slice<'a, T: WithDType>(
    st: &'a Storage,
    l: &Layout,
    what: &str,
) -> candle_core::Result<&'a [T]> {
    match st {
        Storage::Cpu(c) => match l.contiguous_offsets() {
            Some((a, b)) => Ok(&c.as_slice::<T>()?[a..b]),
            None => candle_core::bail!("fused composite: {what} must be contiguous"),
        },
        _ => candle_core::bail!("fused composite: {what} must be on the CPU"),
    }
}

impl FusedComposite {
    fn g(&self) -> usize {
        1 + usize::from(self.depth)
    }

    fn check_len(&self, m_sig: usize, m_geo: usize, m_val: usize) -> candle_core::Result<()> {
        let m = self.seg.n_samples();
        if m_sig != m || m_geo != m * self.g() || m_val != m * self.k {
            candle_core::bail!(
                "fused composite: expected {m} samples with {} channels, got {m_sig}, {m_geo}, {m_val}",
                self.k
            );
        }
        Ok(())
    }

    /// (δ, t) slices of the geometry input for samples `a..b`.
    fn geo<'a, T>(&self, geo: &'a [T], a: usize, b: usize) -> (&'a [T], Option<&'a [T]>) {
        let m = self.seg.n_samples();
        let tm = self.depth.then(|| &geo[m + a..m + b]);
        (&geo[a..b], tm)
    }

    fn forward<T: WithDType>(&self, sig: &[T], geo: &[T], vals: &[T]) -> Vec<T> {
        let (k, r, width) = (self.k, self.seg.n_rays(), self.k + self.g());
        let mut out = vec![T::zero(); r * width];
        out.par_chunks_mut(width)
            .enumerate()
            .with_min_len(16)
            .for_each_init(Scratch::default, |sc, (ray, o)| {
                let (a, b) = self.seg.range(ray);
                let (del, tm) = self.geo(geo, a, b);
                scan_ray(
                    &sig[a..b],
                    del,
                    tm,
                    &vals[a * k..b * k],
                    k,
                    self.opaque_last,
                    sc,
                    false,
                );
                for (oo, aa) in o.iter_mut().zip(sc.acc.iter()) {
                    *oo = T::from_f64(*aa);
                }
            });
        out
    }

    /// Gradients with respect to (sigmas, geometry, values) given `grad` `[R, K + G]`;
    /// `need` says which of the three to produce (the others are returned empty and not
    /// computed, saving their allocation and writes).
    fn backward<T: WithDType>(
        &self,
        sig: &[T],
        geo: &[T],
        vals: &[T],
        grad: &[T],
        need: [bool; 3],
    ) -> (Vec<T>, Vec<T>, Vec<T>) {
        let (k, width) = (self.k, self.k + self.g());
        let m = self.seg.n_samples();
        let alloc = |on: bool, len: usize| if on { vec![T::zero(); len] } else { Vec::new() };
        let mut gs = alloc(need[0], m);
        let mut ggeo = alloc(need[1], m * self.g());
        let mut gv = alloc(need[2], m * k);
        let r = self.seg.n_rays();
        let none = || (0..r).map(|_| None).collect::<Vec<Option<&mut [T]>>>();
        let seg = &self.seg;
        fn some<'a, T>(buf: &'a mut [T], seg: &Segments, k: usize) -> Vec<Option<&'a mut [T]>> {
            split_rays(buf, seg, k).into_iter().map(Some).collect()
        }
        let (gd_rays, gt_rays) = if need[1] {
            let (gd, gt) = ggeo.split_at_mut(m);
            (
                some(gd, seg, 1),
                if self.depth { some(gt, seg, 1) } else { none() },
            )
        } else {
            (none(), none())
        };
        let gs_rays = if need[0] {
            some(&mut gs, seg, 1)
        } else {
            none()
        };
        let gv_rays = if need[2] {
            some(&mut gv, seg, k)
        } else {
            none()
        };
        let rays: Vec<_> = gs_rays
            .into_iter()
            .zip(gd_rays)
            .zip(gv_rays)
            .zip(gt_rays)
            .enumerate()
            .collect();
        rays.into_par_iter().with_min_len(16).for_each_init(
            Scratch::default,
            |sc: &mut Scratch, (ray, (((mut gs_r, mut gd_r), mut gv_r), mut gt_r))| {
                let (a, b) = self.seg.range(ray);
                let n = b - a;
                if n == 0 {
                    return;
                }
                let (del, tm) = self.geo(geo, a, b);
                let (sig, vals) = (&sig[a..b], &vals[a * k..b * k]);
                let live = scan_ray(sig, del, tm, vals, k, self.opaque_last, sc, true);
                sc.g.clear();
                sc.g.extend(
                    grad[ray * width..(ray + 1) * width]
                        .iter()
                        .map(|x| x.to_f64()),
                );
                let g_op = sc.g[width - 1];
                let g_dep = if self.depth { sc.g[k] } else { 0.0 };
                // Samples at index >= live have zero weight and zero gradient (already 0).
                // 1. uⱼ = Σ_c g_c v_jc + g_O + g_D tⱼ (independent per sample: vectorises),
                //    stored in the (now free) alpha buffer.
                let u = &mut sc.alpha[..live];
                let gk = &sc.g[..k];
                if k == 3 {
                    let (g0, g1, g2) = (gk[0], gk[1], gk[2]);
                    for (uj, v) in u.iter_mut().zip(vals.chunks_exact(3)) {
                        *uj = g_op + g0 * v[0].to_f64() + g1 * v[1].to_f64() + g2 * v[2].to_f64();
                    }
                } else {
                    for (j, uj) in u.iter_mut().enumerate() {
                        let v = &vals[j * k..(j + 1) * k];
                        *uj = g_op + gk.iter().zip(v).map(|(g, x)| g * x.to_f64()).sum::<f64>();
                    }
                }
                if let Some(tm) = tm {
                    for (uj, t) in u.iter_mut().zip(tm) {
                        *uj += g_dep * t.to_f64();
                    }
                }
                // 2. Reverse scan: ∂L/∂xⱼ = Tⱼ₊₁uⱼ − Σ_{i>j} wᵢuᵢ, overwriting uⱼ.
                let mut suffix = 0.0f64;
                for j in (0..live).rev() {
                    let uj = u[j];
                    u[j] = sc.t_next[j] * uj - suffix;
                    suffix += sc.w[j] * uj;
                }
                if self.opaque_last && live == n {
                    u[n - 1] = 0.0;
                }
                // 3. Independent writes (vectorise); the clamp region has zero gradient.
                let gx = |j: usize| {
                    let (s, d) = (sig[j].to_f64(), del[j].to_f64());
                    if s * d > X_MAX {
                        0.0
                    } else {
                        u[j]
                    }
                };
                if let Some(gs_r) = gs_r.as_deref_mut() {
                    for (j, o) in gs_r[..live].iter_mut().enumerate() {
                        *o = T::from_f64(del[j].to_f64() * gx(j));
                    }
                }
                if let Some(gd_r) = gd_r.as_deref_mut() {
                    for (j, o) in gd_r[..live].iter_mut().enumerate() {
                        *o = T::from_f64(sig[j].to_f64() * gx(j));
                    }
                }
                if let Some(gv_r) = gv_r.as_deref_mut() {
                    for (row, w) in gv_r[..live * k].chunks_exact_mut(k).zip(&sc.w[..live]) {
                        for (o, g) in row.iter_mut().zip(gk) {
                            *o = T::from_f64(w * g);
                        }
                    }
                }
                if let Some(gt_r) = gt_r.as_deref_mut() {
                    for (o, w) in gt_r[..live].iter_mut().zip(&sc.w[..live]) {
                        *o = T::from_f64(w * g_dep);
                    }
                }
            },
        );
        (gs, ggeo, gv)
    }
}

impl CustomOp3 for FusedComposite {
    fn name(&self) -> &'static str {
        "nf-fused-composite"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let shape = Shape::from((self.seg.n_rays(), self.k + self.g()));
        let (Some((a1, b1)), Some((a2, b2)), Some((a3, b3))) = (
            l1.contiguous_offsets(),
            l2.contiguous_offsets(),
            l3.contiguous_offsets(),
        ) else {
            candle_core::bail!("fused composite: inputs must be contiguous")
        };
        match (s1, s2, s3) {
            (CpuStorage::F32(s), CpuStorage::F32(d), CpuStorage::F32(v)) => {
                let (s, d, v) = (&s[a1..b1], &d[a2..b2], &v[a3..b3]);
                self.check_len(s.len(), d.len(), v.len())?;
                Ok((CpuStorage::F32(self.forward(s, d, v)), shape))
            }
            (CpuStorage::F64(s), CpuStorage::F64(d), CpuStorage::F64(v)) => {
                let (s, d, v) = (&s[a1..b1], &d[a2..b2], &v[a3..b3]);
                self.check_len(s.len(), d.len(), v.len())?;
                Ok((CpuStorage::F64(self.forward(s, d, v)), shape))
            }
            _ => candle_core::bail!("fused composite: inputs must all be f32 or all f64"),
        }
    }

    fn bwd(
        &self,
        sig: &Tensor,
        geo: &Tensor,
        vals: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        // Only inputs that are part of the graph need a gradient.
        let need = [sig.track_op(), geo.track_op(), vals.track_op()];
        let (ss, sl) = sig.storage_and_layout();
        let (ds, dl) = geo.storage_and_layout();
        let (vs, vl) = vals.storage_and_layout();
        let (gs, gl) = grad.storage_and_layout();
        let dev = sig.device();
        macro_rules! run {
            ($t:ty) => {{
                let s = cpu_slice::<$t>(&ss, sl, "sigmas")?;
                let d = cpu_slice::<$t>(&ds, dl, "geometry")?;
                let v = cpu_slice::<$t>(&vs, vl, "values")?;
                let g = cpu_slice::<$t>(&gs, gl, "grad")?;
                self.check_len(s.len(), d.len(), v.len())?;
                let (a, b, c) = self.backward(s, d, v, g, need);
                let wrap =
                    |on: bool, v: Vec<$t>, t: &Tensor| -> candle_core::Result<Option<Tensor>> {
                        if on {
                            Ok(Some(Tensor::from_vec(v, t.shape(), dev)?))
                        } else {
                            Ok(None)
                        }
                    };
                (
                    wrap(need[0], a, sig)?,
                    wrap(need[1], b, geo)?,
                    wrap(need[2], c, vals)?,
                )
            }};
        }
        let (a, b, c) = match sig.dtype() {
            DType::F32 => run!(f32),
            DType::F64 => run!(f64),
            other => candle_core::bail!("fused composite: unsupported dtype {other:?}"),
        };
        Ok((a, b, c))
    }
}

fn require_cpu(sigmas: &Tensor) -> Result<()> {
    if sigmas.device().is_cpu() {
        Ok(())
    } else {
        Err(Error::invalid(
            "sigmas",
            "a CPU tensor (the fused op has only a CPU kernel; use composite or composite_reference)",
            format!("{:?}", sigmas.device()),
        ))
    }
}

/// Applies the fused op; `geo` is δ alone or δ and t stacked along a new leading axis
/// (a contiguous block copy, and its backward is a contiguous split). Returns
/// `[R, K + G]`.
fn apply(
    sig: &Tensor,
    del: &Tensor,
    tm: Option<&Tensor>,
    values: &Tensor,
    op: FusedComposite,
) -> Result<Tensor> {
    // No reshapes around the op: each would add a zeros + add pass per gradient in
    // candle's backprop. The kernel reads the contiguous data flat.
    let sig = sig.contiguous()?;
    let geo = match tm {
        Some(t) => Tensor::stack(&[del, t], 0)?,
        None => del.contiguous()?,
    };
    let values = values.contiguous()?;
    Ok(sig.apply_op3(&geo, &values, op)?)
}

/// Splits `[R, C + 2]` = (colour, depth, opacity) and adds the background.
fn split_out(out: &Tensor, c: usize, opts: &CompositeOptions) -> Result<Composite> {
    let color = out.narrow(1, 0, c)?;
    let depth = out.narrow(1, c, 1)?.squeeze(1)?;
    let opacity = out.narrow(1, c + 1, 1)?.squeeze(1)?;
    finish(color, opacity, depth, opts)
}

/// Fused [`super::composite::composite_reference`]: the same results (to rounding) from
/// one CPU pass per ray, with the O(S) analytic backward.
///
/// Math: C = Σwᵢcᵢ + (1 − Σwᵢ)·c_bg, opacity Σwᵢ, depth Σwᵢtᵢ, with wᵢ as in
/// [`super::composite::render_weights`]; accumulated in f64 for f32 and f64 inputs.
///
/// Shapes: `sigmas, deltas, t_mids: [R, S]`, `colors: [R, S, C]` → `color: [R, C]`,
/// `opacity, depth: [R]`. CPU only, f32 or f64. Differentiable (first order) with respect
/// to `sigmas`, `deltas`, `colors`, `t_mids` and the background.
///
/// # Errors
/// As [`super::composite::composite_reference`]; `sigmas` when not on the CPU.
pub fn composite_fused(
    sigmas: &Tensor,
    colors: &Tensor,
    deltas: &Tensor,
    t_mids: &Tensor,
    opts: &CompositeOptions,
) -> Result<Composite> {
    check_composite_inputs(sigmas, colors, deltas, t_mids)?;
    require_cpu(sigmas)?;
    let (r, s) = sigmas.dims2()?;
    let c = colors.dim(2)?;
    let op = FusedComposite {
        seg: Segments::Uniform { rays: r, s },
        k: c,
        depth: true,
        opaque_last: opts.opaque_last,
    };
    let out = apply(
        sigmas,
        deltas,
        Some(t_mids),
        &colors.reshape((r * s, c))?,
        op,
    )?;
    split_out(&out, c, opts)
}

/// Packed-layout [`composite_fused`]: `sigmas, deltas, t_mids: [M]`, `colors: [M, C]`
/// → `color: [R, C]`, `opacity, depth: [R]`; rays with no samples get opacity 0, depth 0
/// and the background colour.
///
/// # Errors
/// As [`super::composite::composite_packed_reference`]; `sigmas` when not on the CPU.
pub fn composite_packed_fused(
    sigmas: &Tensor,
    colors: &Tensor,
    deltas: &Tensor,
    t_mids: &Tensor,
    packed: &Packed,
    opts: &CompositeOptions,
) -> Result<Composite> {
    check_composite_inputs_packed(sigmas, colors, deltas, t_mids, packed)?;
    require_cpu(sigmas)?;
    let c = colors.dim(1)?;
    let op = FusedComposite {
        seg: Segments::Offsets(packed.offsets_arc()),
        k: c,
        depth: true,
        opaque_last: opts.opaque_last,
    };
    let out = apply(sigmas, deltas, Some(t_mids), colors, op)?;
    split_out(&out, c, opts)
}

/// Fused accumulation of arbitrary per-sample values with the weights of
/// `(sigmas, deltas)`: returns `[R, K + 1]` = (Σwᵢvᵢₖ for each k, Σwᵢ).
///
/// Shapes: `sigmas, deltas: [R, S]`, `values: [R, S, K]`. CPU, f32/f64. Differentiable
/// (first order) with respect to all three.
///
/// # Errors
/// `sigmas`/`deltas` as in [`super::composite::render_weights`]; `values` on a shape,
/// dtype or device mismatch; `sigmas` when not on the CPU.
pub fn accumulate_fused(
    sigmas: &Tensor,
    deltas: &Tensor,
    values: &Tensor,
    opaque_last: bool,
) -> Result<Tensor> {
    let d = check_shape(sigmas, "sigmas", &[Dim::Any("R"), Dim::Any("S")])?;
    check_same(values, "values", sigmas, "sigmas")?;
    let dv = check_shape(
        values,
        "values",
        &[Dim::Is(d[0]), Dim::Is(d[1]), Dim::Any("K")],
    )?;
    check_sigmas_deltas(sigmas, deltas)?;
    require_cpu(sigmas)?;
    let op = FusedComposite {
        seg: Segments::Uniform {
            rays: d[0],
            s: d[1],
        },
        k: dv[2],
        depth: false,
        opaque_last,
    };
    apply(
        sigmas,
        deltas,
        None,
        &values.reshape((d[0] * d[1], dv[2]))?,
        op,
    )
}
