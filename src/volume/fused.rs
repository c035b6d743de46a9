//! Fused CPU compositing op with an O(S)-per-ray analytic backward.
//!
//! One candle [`CustomOp3`] takes `(sigmas, deltas, values)` and returns, per ray, the
//! accumulated values Σwᵢvᵢₖ for every channel k followed by the opacity Σwᵢ: a single
//! `[R, K + 1]` tensor. [`composite_fused`] feeds it `values = [colors | t_mids]`
//! (`K = C + 1`), so one pass yields colour, expected depth and opacity; it then splits
//! the output with `narrow` (views, no copies).
//!
//! Forward (per ray, in f64 whatever the storage dtype): xᵢ = min(σᵢδᵢ, X_MAX),
//! αᵢ = −expm1(−xᵢ), Tᵢ₊₁ = Tᵢ·e^{−xᵢ} with e^{−xᵢ} = 1 + expm1(−xᵢ) for xᵢ < ½ and
//! `exp(−xᵢ)` above (one transcendental per sample, full relative accuracy in both), and
//! wᵢ = Tᵢαᵢ. Once T < 1e-300 the rest of the ray contributes nothing representable and
//! the scan stops (this also keeps denormals out of the loop).
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
//! parallel with rayon. The backward is not itself differentiable (no second order).

use super::composite::{
    check_composite_inputs, check_composite_inputs_packed, finish, Composite, CompositeOptions,
    Packed, X_MAX,
};
use crate::error::{Error, Result};
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

/// The fused compositing op: `(sigmas [M], deltas [M], values [M, K])` → `[R, K + 1]`.
#[derive(Clone, Debug)]
struct FusedComposite {
    seg: Segments,
    k: usize,
    opaque_last: bool,
}

/// αᵢ and e^{−xᵢ} from one transcendental, both to full relative accuracy.
#[inline(always)]
fn alpha_and_decay(x: f64) -> (f64, f64) {
    if x < 0.5 {
        let em = (-x).exp_m1();
        (-em, 1.0 + em)
    } else {
        let e = (-x).exp();
        (1.0 - e, e)
    }
}

/// Forward scan of one ray: writes wᵢ and Tᵢ₊₁ into `w` / `t_next` when given, and
/// returns (through `acc`) Σwᵢvᵢₖ and Σwᵢ. Returns the number of samples scanned (the
/// rest have zero weight).
#[inline(always)]
fn scan_ray<T: WithDType>(
    sig: &[T],
    del: &[T],
    vals: &[T],
    k: usize,
    opaque_last: bool,
    acc: &mut [f64],
    mut store: Option<(&mut [f64], &mut [f64])>,
) -> usize {
    let n = sig.len();
    acc.iter_mut().for_each(|a| *a = 0.0);
    let mut t = 1.0f64;
    let mut op = 0.0f64;
    for i in 0..n {
        let x = (sig[i].to_f64() * del[i].to_f64()).min(X_MAX);
        let (alpha, decay) = if opaque_last && i + 1 == n {
            (1.0, 0.0)
        } else {
            alpha_and_decay(x)
        };
        let w = t * alpha;
        let v = &vals[i * k..(i + 1) * k];
        for (a, vv) in acc.iter_mut().zip(v) {
            *a += w * vv.to_f64();
        }
        op += w;
        t *= decay;
        if let Some((ws, ts)) = store.as_mut() {
            ws[i] = w;
            ts[i] = t;
        }
        if t < T_STOP {
            acc[k] = op;
            return i + 1;
        }
    }
    acc[k] = op;
    n
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
    fn check_len(&self, m_sig: usize, m_del: usize, m_val: usize) -> candle_core::Result<()> {
        let m = self.seg.n_samples();
        if m_sig != m || m_del != m || m_val != m * self.k {
            candle_core::bail!(
                "fused composite: expected {m} samples with {} channels, got {m_sig}, {m_del}, {m_val}",
                self.k
            );
        }
        Ok(())
    }

    fn forward<T: WithDType>(&self, sig: &[T], del: &[T], vals: &[T]) -> Vec<T> {
        let (k, r) = (self.k, self.seg.n_rays());
        let mut out = vec![T::zero(); r * (k + 1)];
        out.par_chunks_mut(k + 1)
            .enumerate()
            .with_min_len(8)
            .for_each_init(
                || vec![0.0f64; k + 1],
                |acc, (ray, o)| {
                    let (a, b) = self.seg.range(ray);
                    scan_ray(
                        &sig[a..b],
                        &del[a..b],
                        &vals[a * k..b * k],
                        k,
                        self.opaque_last,
                        acc,
                        None,
                    );
                    for (oo, aa) in o.iter_mut().zip(acc.iter()) {
                        *oo = T::from_f64(*aa);
                    }
                },
            );
        out
    }

    /// Gradients with respect to (sigmas, deltas, values) given `grad` `[R, K + 1]`.
    fn backward<T: WithDType>(
        &self,
        sig: &[T],
        del: &[T],
        vals: &[T],
        grad: &[T],
    ) -> (Vec<T>, Vec<T>, Vec<T>) {
        let k = self.k;
        let m = self.seg.n_samples();
        let mut gs = vec![T::zero(); m];
        let mut gd = vec![T::zero(); m];
        let mut gv = vec![T::zero(); m * k];
        let rays: Vec<_> = split_rays(&mut gs, &self.seg, 1)
            .into_iter()
            .zip(split_rays(&mut gd, &self.seg, 1))
            .zip(split_rays(&mut gv, &self.seg, k))
            .enumerate()
            .collect();
        rays.into_par_iter().with_min_len(8).for_each_init(
            || {
                (
                    vec![0.0f64; k + 1],
                    Vec::<f64>::new(),
                    Vec::<f64>::new(),
                    vec![0.0f64; k + 1],
                )
            },
            |(acc, wbuf, tbuf, g), (ray, ((gs_r, gd_r), gv_r))| {
                let (a, b) = self.seg.range(ray);
                let n = b - a;
                if n == 0 {
                    return;
                }
                wbuf.resize(n, 0.0);
                tbuf.resize(n, 0.0);
                let (sig, del, vals) = (&sig[a..b], &del[a..b], &vals[a * k..b * k]);
                let live = scan_ray(sig, del, vals, k, self.opaque_last, acc, Some((wbuf, tbuf)));
                for (gg, x) in g.iter_mut().zip(&grad[ray * (k + 1)..(ray + 1) * (k + 1)]) {
                    *gg = x.to_f64();
                }
                let g_op = g[k];
                // Samples at index >= live have zero weight and zero gradient (already 0).
                let mut suffix = 0.0f64;
                for j in (0..live).rev() {
                    let v = &vals[j * k..(j + 1) * k];
                    let w = wbuf[j];
                    let mut u = g_op;
                    for c in 0..k {
                        u += g[c] * v[c].to_f64();
                        gv_r[j * k + c] = T::from_f64(w * g[c]);
                    }
                    let gx = if self.opaque_last && j + 1 == n {
                        0.0
                    } else {
                        tbuf[j] * u - suffix
                    };
                    suffix += w * u;
                    let (s, d) = (sig[j].to_f64(), del[j].to_f64());
                    let (gsj, gdj) = if s * d > X_MAX {
                        (0.0, 0.0)
                    } else {
                        (d * gx, s * gx)
                    };
                    gs_r[j] = T::from_f64(gsj);
                    gd_r[j] = T::from_f64(gdj);
                }
            },
        );
        (gs, gd, gv)
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
        let shape = Shape::from((self.seg.n_rays(), self.k + 1));
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
        del: &Tensor,
        vals: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let (ss, sl) = sig.storage_and_layout();
        let (ds, dl) = del.storage_and_layout();
        let (vs, vl) = vals.storage_and_layout();
        let (gs, gl) = grad.storage_and_layout();
        let dev = sig.device();
        macro_rules! run {
            ($t:ty) => {{
                let s = cpu_slice::<$t>(&ss, sl, "sigmas")?;
                let d = cpu_slice::<$t>(&ds, dl, "deltas")?;
                let v = cpu_slice::<$t>(&vs, vl, "values")?;
                let g = cpu_slice::<$t>(&gs, gl, "grad")?;
                self.check_len(s.len(), d.len(), v.len())?;
                let (a, b, c) = self.backward(s, d, v, g);
                (
                    Tensor::from_vec(a, sig.shape(), dev)?,
                    Tensor::from_vec(b, del.shape(), dev)?,
                    Tensor::from_vec(c, vals.shape(), dev)?,
                )
            }};
        }
        let (a, b, c) = match sig.dtype() {
            DType::F32 => run!(f32),
            DType::F64 => run!(f64),
            other => candle_core::bail!("fused composite: unsupported dtype {other:?}"),
        };
        Ok((Some(a), Some(b), Some(c)))
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

/// Applies the fused op to flat inputs; returns `[R, K + 1]`.
fn apply(sig: &Tensor, del: &Tensor, values: &Tensor, op: FusedComposite) -> Result<Tensor> {
    let sig = sig.contiguous()?;
    let del = del.contiguous()?;
    let values = values.contiguous()?;
    Ok(sig.apply_op3(&del, &values, op)?)
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
    let values = Tensor::cat(&[colors, &t_mids.unsqueeze(2)?], 2)?;
    let op = FusedComposite {
        seg: Segments::Uniform { rays: r, s },
        k: c + 1,
        opaque_last: opts.opaque_last,
    };
    let out = apply(sigmas, deltas, &values, op)?;
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
    let values = Tensor::cat(&[colors, &t_mids.unsqueeze(1)?], 1)?;
    let op = FusedComposite {
        seg: Segments::Offsets(packed.offsets_arc()),
        k: c + 1,
        opaque_last: opts.opaque_last,
    };
    let out = apply(sigmas, deltas, &values, op)?;
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
    let d = crate::error::check_shape(
        sigmas,
        "sigmas",
        &[crate::error::Dim::Any("R"), crate::error::Dim::Any("S")],
    )?;
    crate::error::check_same(values, "values", sigmas, "sigmas")?;
    let dv = crate::error::check_shape(
        values,
        "values",
        &[
            crate::error::Dim::Is(d[0]),
            crate::error::Dim::Is(d[1]),
            crate::error::Dim::Any("K"),
        ],
    )?;
    super::composite::check_sigmas_deltas(sigmas, deltas)?;
    require_cpu(sigmas)?;
    let op = FusedComposite {
        seg: Segments::Uniform {
            rays: d[0],
            s: d[1],
        },
        k: dv[2],
        opaque_last,
    };
    apply(sigmas, deltas, values, op)
}
