//! Fused CPU compositing op with an O(S)-per-ray analytic backward.
//!
//! One candle [`CustomOp3`] takes `(sigmas, geometry, values)` and returns per ray the
//! accumulated values Σwᵢvᵢₖ for every channel k, then Σwᵢtᵢ (when depths are given),
//! then the opacity Σwᵢ: a single `[R, K + 2]` (or `[R, K + 1]`) tensor.
//! [`crate::volume::composite()`] passes the colours as values, so one pass yields colour, expected
//! depth and opacity, split with `narrow` (views). The geometry comes in one of two
//! forms ([`Geometry`]):
//!
//! - constant intervals (the usual case: samplers return intervals without a graph):
//!   `geometry` is the interval starts, the op holds the ends and the per-ray direction
//!   norms, and each ray's δᵢ = (eᵢ − sᵢ)·‖d‖ and tᵢ = (sᵢ + eᵢ)/2 are formed in a per-thread
//!   buffer as the ray is processed: no per-sample tensor is allocated, and the check that
//!   every δᵢ is finite and ≥ 0 happens in the same pass;
//! - δ and t as tensors (when the intervals or the rays carry a graph): `geometry` is δ;
//!   the depths t are read in place from the op when they are a constant of the graph,
//!   and stacked under δ (`[2, …]`, a contiguous block copy whose backward is a contiguous
//!   split) when they need a gradient.
//!
//! Inputs are passed in their own shapes (no reshape: in candle's backprop every reshape
//! costs a zeros + add pass per gradient). Per-sample weights are not an output; the
//! reference path's weights serve [`crate::volume::render_weights`].
//!
//! The per-ray kernels are specialised at compile time for 1–4 channels (accumulators in
//! registers) with a general path for other counts, and are built three times: for the
//! baseline target, with AVX2 + FMA and with AVX-512, chosen at run time by CPU feature
//! detection (the results differ only by the rounding of fused multiply–adds; all are
//! tested).
//!
//! Forward (per ray, in f64 whatever the storage dtype): xᵢ = min(σᵢδᵢ, X_MAX); αᵢ =
//! −expm1(−xᵢ) and e^{−xᵢ} from one branch-free range-reduced polynomial (vectorised
//! across the ray's samples; full relative accuracy of the storage dtype, see
//! docs/math.md); then the scan Tᵢ₊₁ = Tᵢ·e^{−xᵢ}, wᵢ = Tᵢαᵢ. Once T < 1e-300 the scan
//! stops: the rest of the ray's weights (together below 1e-300, zero in f32) are
//! dropped, an absolute error below 1e-300·max|v| in f64, and denormals stay out of the
//! loop.
//!
//! The scans are blocked by 4 samples: T advances once per block by the product of the
//! block's four decays, and each running sum (Σwᵢvᵢₖ, Σwᵢ, Σwᵢtᵢ, and the backward's
//! suffix sum) once per block by the block's own sum, formed off the dependency chain.
//! A one-sample-at-a-time scan is bound by the latency of that chain (one multiply or
//! fused multiply–add per sample); blocking divides it by 4. The sums are the
//! sequential ones reassociated, so results differ from a sequential scan by rounding.
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
//! parallel on candle's own CPU worker pool (see `super::parallel`), not on a second pool
//! competing for the same cores. The backward is not itself differentiable
//! (no second order), and it only computes the gradients of inputs that are part of the
//! autograd graph.

use super::dispatch::{cpu_op, CpuKernel, Real};
use super::parallel::for_each_init;
use candle_core::{DType, Layout, Shape, Storage, Tensor, WithDType};
use std::mem::MaybeUninit;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// Optical thickness above which xᵢ = σᵢδᵢ is clamped. `exp(−1000)` is exactly zero in
/// f32 and f64, so clamping changes no weight or gradient; it only keeps `+∞` (from
/// overflow of σδ) out of the exclusive sum.
pub const X_MAX: f64 = 1000.0;

/// Transmittance below which a ray is considered spent inside the kernel.
const T_STOP: f64 = 1e-300;

/// How the flat sample array splits into rays.
#[derive(Clone, Debug)]
pub(crate) enum Segments {
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

/// What the op's geometry input holds, and where the rest of the geometry comes from.
#[derive(Clone, Debug)]
pub(crate) enum Geometry {
    /// The input is δ; the sample depths t are a constant of the graph, held by the op
    /// and read in place.
    Deltas(Tensor),
    /// The input is δ stacked over t (`[2, …]`): t needs a gradient.
    Stacked,
    /// The input is the (constant) interval starts; the op holds the ends and, when the
    /// directions are not unit, the per-ray direction norms (host f64). δ and t are
    /// formed per ray.
    Intervals {
        ends: Tensor,
        norms: Option<Arc<[f64]>>,
    },
}

/// The fused compositing op on `(sigmas [M], geometry [G, M], values [M, K])`, the
/// geometry as [`Geometry`] says. Output `[R, K + 2]` = (Σwᵢvᵢₖ for each k, Σwᵢtᵢ, Σwᵢ).
#[derive(Clone, Debug)]
pub(crate) struct FusedComposite {
    seg: Segments,
    k: usize,
    geometry: Geometry,
    opaque_last: bool,
    isa: Isa,
    /// Set by the forward when a density is not finite and ≥ 0 or an interval has a
    /// non-finite or negative length.
    bad: Arc<AtomicBool>,
}

impl FusedComposite {
    /// The op on `k` channels in the layout `seg`, with the best kernel build the CPU
    /// supports up to `build`; `bad` is set when a density is not finite and ≥ 0 or an
    /// interval has a non-finite or negative length.
    pub(crate) fn new(
        seg: Segments,
        k: usize,
        geometry: Geometry,
        opaque_last: bool,
        build: KernelBuild,
        bad: Arc<AtomicBool>,
    ) -> Self {
        Self {
            seg,
            k,
            geometry,
            opaque_last,
            isa: Isa::detect(build),
            bad,
        }
    }
}

/// A ray's δ and t, from slices of the inputs or formed from its intervals.
enum Geo<'a, T> {
    Slices {
        del: &'a [T],
        tm: &'a [T],
    },
    Intervals {
        s: &'a [T],
        e: &'a [T],
        norms: Option<&'a [f64]>,
    },
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

/// `a·b + c`: one fused multiply–add (a single rounding) in the kernels built with FMA,
/// a multiply and an add otherwise (a software `fma` call would be far slower there).
#[inline(always)]
fn madd<const FMA: bool>(a: f64, b: f64, c: f64) -> f64 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// (α, e^{−x}) = (−expm1(−x), exp(−x)) for x ∈ [0, X_MAX], branch-free (vectorisable).
///
/// Range reduction −x = k·ln2 + r, |r| ≤ ln2/2 (Cody–Waite), q = expm1(r) by a degree-`D`
/// polynomial, then e^{−x} = 2ᵏ(1 + q) and expm1(−x) = 2ᵏq + (2ᵏ − 1). For x < ln2/2,
/// k = 0 and α = −q keeps full relative accuracy (α = x at x = 1e-30); for larger x,
/// α ≥ 0.29 and the sum has no cancellation. e^{−x} is flushed to 0 for x > 708 (below
/// the smallest normal f64).
#[inline(always)]
fn alpha_and_decay<const D: usize, const FMA: bool>(x: f64) -> (f64, f64) {
    let y = -x.min(708.0);
    let t = madd::<FMA>(y, std::f64::consts::LOG2_E, ROUND_MAGIC);
    let k = (t.to_bits() as i64).wrapping_sub(ROUND_MAGIC.to_bits() as i64);
    let kf = t - ROUND_MAGIC;
    let r = madd::<FMA>(-kf, LN2_LO, madd::<FMA>(-kf, LN2_HI, y));
    let mut p = EXPM1_COEF[13 - D];
    for &c in &EXPM1_COEF[14 - D..] {
        p = madd::<FMA>(p, r, c);
    }
    let q = madd::<FMA>(p, r, 1.0) * r;
    let scale = f64::from_bits(((k + 1023) as u64) << 52);
    let em = madd::<FMA>(scale, q, scale - 1.0);
    let decay = madd::<FMA>(scale, q, scale);
    if x > 708.0 {
        (1.0, 0.0)
    } else {
        (-em, decay)
    }
}

/// For each sample: xᵢ = min(σᵢδᵢ, X_MAX), αᵢ = −expm1(−xᵢ) and e^{−xᵢ}, both to full
/// relative accuracy of the storage dtype (f64: degree 13, f32: degree 7). `alpha` and
/// `decay` must have the length of `sig`. Returns whether every σᵢ is finite and ≥ 0
/// (checked in the same pass, so the entry points need no pass of their own).
#[inline(always)]
fn alpha_decay<T: WithDType, const FMA: bool>(
    sig: &[T],
    del: &[T],
    alpha: &mut [f64],
    decay: &mut [f64],
) -> bool {
    #[inline(always)]
    fn run<T: WithDType, const D: usize, const FMA: bool>(
        sig: &[T],
        del: &[T],
        alpha: &mut [f64],
        decay: &mut [f64],
    ) -> bool {
        let mut ok = true;
        for (((s, d), a), e) in sig
            .iter()
            .zip(del)
            .zip(alpha.iter_mut())
            .zip(decay.iter_mut())
        {
            let s = s.to_f64();
            // NaN fails both comparisons.
            ok &= (0.0..=f64::MAX).contains(&s);
            let x = (s * d.to_f64()).min(X_MAX);
            (*a, *e) = alpha_and_decay::<D, FMA>(x);
        }
        ok
    }
    if T::DTYPE == DType::F32 {
        run::<T, 7, FMA>(sig, del, alpha, decay)
    } else {
        run::<T, 13, FMA>(sig, del, alpha, decay)
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

/// The inputs of one ray: `vals` has `k` entries per sample, `del` and `tm` its δ and t.
struct RayIn<'a, T> {
    sig: &'a [T],
    del: &'a [T],
    tm: &'a [T],
    vals: &'a [T],
    k: usize,
    opaque_last: bool,
    /// Whether `sc.alpha` and `sc.decay` already hold this ray's αᵢ and e^{−xᵢ} (formed
    /// with its δ and t by [`bounds_alpha_decay`]).
    prepared: bool,
}

/// The gradient outputs of one ray (each present only when requested).
///
/// The buffers are uninitialised: the kernel writes every entry (zeros past the ray's
/// live samples), which saves the serial zeroing pass of a fresh allocation.
struct RayGrads<'a, T> {
    sig: Option<&'a mut [MaybeUninit<T>]>,
    del: Option<&'a mut [MaybeUninit<T>]>,
    vals: Option<&'a mut [MaybeUninit<T>]>,
    tm: Option<&'a mut [MaybeUninit<T>]>,
}

/// Accumulated sums of one ray's forward scan.
struct ScanOut {
    /// Samples scanned: after T < T_STOP the rest have zero weight.
    live: usize,
    /// Σwᵢtᵢ (0 in the backward's scan, which does not sum it).
    depth: f64,
    /// Σwᵢ.
    opacity: f64,
    /// Whether every σᵢ was finite and ≥ 0.
    valid: bool,
}

/// Forward scan of one ray with `k` channels (a constant after inlining into a
/// specialised caller; `k = 0` for weights only, as the backward needs). Accumulates
/// Σwᵢvᵢₖ into `acc[..k]` (zeroed here) and, when `store` (the backward), writes
/// `sc.w[i]` = wᵢ and `sc.t_next[i]` = Tᵢ₊₁ instead of accumulating the depth.
#[inline(always)]
fn scan_ray<T: WithDType, const FMA: bool>(
    ray: &RayIn<'_, T>,
    k: usize,
    acc: &mut [f64],
    sc: &mut Scratch,
    store: bool,
) -> ScanOut {
    let n = ray.sig.len();
    let acc = &mut acc[..k];
    acc.fill(0.0);
    sc.alpha.resize(n, 0.0);
    sc.decay.resize(n, 0.0);
    if store {
        sc.w.resize(n, 0.0);
        sc.t_next.resize(n, 0.0);
    }
    let valid =
        ray.prepared || alpha_decay::<T, FMA>(ray.sig, ray.del, &mut sc.alpha, &mut sc.decay);
    if ray.opaque_last && n > 0 {
        sc.alpha[n - 1] = 1.0;
        sc.decay[n - 1] = 0.0;
    }
    // Local slices of exactly n entries: the loop then reloads nothing from `sc` (its
    // stores cannot alias the Vec headers) and needs no bounds checks.
    let (alpha, decay) = (&sc.alpha[..n], &sc.decay[..n]);
    let (w_out, t_out): (&mut [f64], &mut [f64]) = if store {
        (&mut sc.w[..n], &mut sc.t_next[..n])
    } else {
        (&mut [], &mut [])
    };
    // The backward (`store`) needs the weights, not the depth sum.
    let tm = if store { None } else { Some(&ray.tm[..n]) };
    let vals = &ray.vals[..n * k];
    let (mut t, mut opacity, mut depth) = (1.0f64, 0.0f64, 0.0f64);
    let mut live = n;
    // Blocked part: T advances once per block by the block's product of decays
    // (Tᵢ ≤ 1 and every decay ≤ 1, so T only falls and a block whose end stays at or
    // above T_STOP has no sample below it). The block where T falls below T_STOP, and the
    // last n % BLOCK samples, go through the sequential loop below.
    let mut seq_from = n - n % BLOCK;
    for (b, (ab, db)) in alpha
        .chunks_exact(BLOCK)
        .zip(decay.chunks_exact(BLOCK))
        .enumerate()
    {
        let i0 = b * BLOCK;
        let vb = &vals[i0 * k..(i0 + BLOCK) * k];
        let q1 = db[0];
        let q2 = q1 * db[1];
        let q3 = q2 * db[2];
        let t_end = t * (q3 * db[3]);
        if t_end < T_STOP {
            seq_from = i0;
            break;
        }
        let tb = [t, t * q1, t * q2, t * q3];
        let w: [f64; BLOCK] = std::array::from_fn(|j| tb[j] * ab[j]);
        // Block sums as trees (off the dependency chain), then one add each.
        let tree = |x: [f64; BLOCK]| (x[0] + x[1]) + (x[2] + x[3]);
        for (c, a) in acc.iter_mut().enumerate() {
            let wv: [f64; BLOCK] = std::array::from_fn(|j| w[j] * vb[j * k + c].to_f64());
            *a += tree(wv);
        }
        if let Some(tm) = tm {
            let tt = &tm[i0..i0 + BLOCK];
            depth += tree(std::array::from_fn(|j| w[j] * tt[j].to_f64()));
        }
        opacity += tree(w);
        if store {
            w_out[i0..i0 + BLOCK].copy_from_slice(&w);
            t_out[i0..i0 + BLOCK].copy_from_slice(&[tb[1], tb[2], tb[3], t_end]);
        }
        t = t_end;
    }
    for i in seq_from..n {
        let w = t * alpha[i];
        for (a, vv) in acc.iter_mut().zip(&vals[i * k..i * k + k]) {
            *a = madd::<FMA>(w, vv.to_f64(), *a);
        }
        if let Some(tm) = tm {
            depth = madd::<FMA>(w, tm[i].to_f64(), depth);
        }
        opacity += w;
        t *= decay[i];
        if store {
            w_out[i] = w;
            t_out[i] = t;
        }
        if t < T_STOP {
            live = i + 1;
            break;
        }
    }
    ScanOut {
        live,
        depth,
        opacity,
        valid,
    }
}

/// Channel counts with kernels specialised at compile time (accumulators in registers,
/// fixed-stride loops); others take the general path (`K = 0`).
const MAX_FIXED_K: usize = 4;

/// Calls `$f::<T, K, FMA>(args)` with `K` = the ray's channel count when it is at most
/// [`MAX_FIXED_K`], else `K = 0` (general).
macro_rules! specialise_k {
    ($f:ident::<$t:ty, $fma:ident>($k:expr; $($arg:expr),*)) => {
        match $k {
            1 => $f::<$t, 1, $fma>($($arg),*),
            2 => $f::<$t, 2, $fma>($($arg),*),
            3 => $f::<$t, 3, $fma>($($arg),*),
            4 => $f::<$t, 4, $fma>($($arg),*),
            _ => $f::<$t, 0, $fma>($($arg),*),
        }
    };
}

/// Forward of one ray into its output row `o` (`[K + 2]`).
#[inline(always)]
fn forward_ray<T: WithDType, const FMA: bool>(
    ray: &RayIn<'_, T>,
    sc: &mut Scratch,
    o: &mut [T],
) -> bool {
    specialise_k!(forward_ray_k::<T, FMA>(ray.k; ray, sc, o))
}

/// [`forward_ray`] with `K` channels (`K = 0`: `ray.k`, general): the accumulators in a
/// local array when `K > 0` (registers) and in `sc.acc` otherwise.
#[inline(always)]
fn forward_ray_k<T: WithDType, const K: usize, const FMA: bool>(
    ray: &RayIn<'_, T>,
    sc: &mut Scratch,
    o: &mut [T],
) -> bool {
    let k = if K == 0 { ray.k } else { K };
    let mut fixed = [0.0f64; MAX_FIXED_K];
    let mut general = std::mem::take(&mut sc.acc);
    let acc: &mut [f64] = if K == 0 {
        general.resize(k, 0.0);
        &mut general
    } else {
        &mut fixed
    };
    let res = scan_ray::<T, FMA>(ray, k, acc, sc, false);
    for (oo, aa) in o.iter_mut().zip(&acc[..k]) {
        *oo = T::from_f64(*aa);
    }
    o[k] = T::from_f64(res.depth);
    o[k + 1] = T::from_f64(res.opacity);
    sc.acc = general;
    res.valid
}

/// Backward of one ray given its upstream gradient row `grad` (`[K + 2]`).
#[inline(always)]
fn backward_ray<T: WithDType, const FMA: bool>(
    ray: &RayIn<'_, T>,
    grad: &[T],
    sc: &mut Scratch,
    out: &mut RayGrads<'_, T>,
) {
    specialise_k!(backward_ray_k::<T, FMA>(ray.k; ray, grad, sc, out))
}

#[inline(always)]
fn backward_ray_k<T: WithDType, const K: usize, const FMA: bool>(
    ray: &RayIn<'_, T>,
    grad: &[T],
    sc: &mut Scratch,
    out: &mut RayGrads<'_, T>,
) {
    let k = if K == 0 { ray.k } else { K };
    let n = ray.sig.len();
    if n == 0 {
        return;
    }
    let (sig, del, vals) = (ray.sig, ray.del, &ray.vals[..n * k]);
    // The weights and transmittances only: the backward needs no channel sums, so the
    // scan accumulates none (k = 0).
    let live = scan_ray::<T, FMA>(ray, 0, &mut [], sc, true).live;
    // Upstream gradients g_c of the channels, g_D of the depth, g_O of the opacity.
    let mut gk_fixed = [0.0f64; MAX_FIXED_K];
    sc.g.clear();
    let gk: &[f64] = if K == 0 {
        sc.g.extend(grad[..k].iter().map(|x| x.to_f64()));
        &sc.g
    } else {
        for (a, b) in gk_fixed.iter_mut().zip(&grad[..k]) {
            *a = b.to_f64();
        }
        &gk_fixed[..k]
    };
    let g_op = grad[grad.len() - 1].to_f64();
    let g_dep = grad[k].to_f64();
    // Samples at index >= live have zero weight and zero gradient (the buffers start at 0).
    // 1. uⱼ = Σ_c g_c v_jc + g_O + g_D tⱼ (independent per sample: vectorises), stored
    //    in the (now free) alpha buffer.
    let u = &mut sc.alpha[..live];
    if k == 0 {
        u.fill(g_op);
    }
    for (uj, v) in u.iter_mut().zip(vals.chunks_exact(k.max(1))) {
        let mut s = g_op;
        for (g, x) in gk.iter().zip(v) {
            s = madd::<FMA>(*g, x.to_f64(), s);
        }
        *uj = s;
    }
    for (uj, t) in u.iter_mut().zip(ray.tm) {
        *uj = madd::<FMA>(g_dep, t.to_f64(), *uj);
    }
    // 2. Reverse scan: ∂L/∂xⱼ = Tⱼ₊₁uⱼ − Σ_{i>j} wᵢuᵢ, overwriting uⱼ.
    reverse_scan::<FMA>(u, &sc.t_next[..live], &sc.w[..live]);
    if ray.opaque_last && live == n {
        u[n - 1] = 0.0;
    }
    // 3. Independent writes (vectorise); the clamp region x > X_MAX has zero gradient,
    //    ∂L/∂σ = δ·∂L/∂x and ∂L/∂δ = σ·∂L/∂x.
    //    Every entry is written: entries past `live` get 0.
    let gx = |s: f64, d: f64, u: f64| if s * d > X_MAX { 0.0 } else { u };
    let zero = |buf: &mut [MaybeUninit<T>]| {
        for o in buf {
            o.write(T::zero());
        }
    };
    if let Some(gs) = out.sig.as_deref_mut() {
        for (((o, s), d), u) in gs.iter_mut().zip(sig).zip(del).zip(u.iter()) {
            let (s, d) = (s.to_f64(), d.to_f64());
            o.write(T::from_f64(d * gx(s, d, *u)));
        }
        zero(&mut gs[live..]);
    }
    if let Some(gd) = out.del.as_deref_mut() {
        for (((o, s), d), u) in gd.iter_mut().zip(sig).zip(del).zip(u.iter()) {
            let (s, d) = (s.to_f64(), d.to_f64());
            o.write(T::from_f64(s * gx(s, d, *u)));
        }
        zero(&mut gd[live..]);
    }
    let w = &sc.w[..live];
    if let Some(gv) = out.vals.as_deref_mut() {
        for (row, w) in gv[..live * k].chunks_exact_mut(k.max(1)).zip(w) {
            for (o, g) in row.iter_mut().zip(gk) {
                o.write(T::from_f64(w * g));
            }
        }
        zero(&mut gv[live * k..]);
    }
    if let Some(gt) = out.tm.as_deref_mut() {
        for (o, w) in gt.iter_mut().zip(w) {
            o.write(T::from_f64(w * g_dep));
        }
        zero(&mut gt[live..]);
    }
}

/// Samples per block in the blocked scans: the running sum advances once per block, by
/// the block's total computed off the dependency chain, so the chain's latency is paid
/// once per `BLOCK` samples instead of once per sample.
const BLOCK: usize = 4;

/// Reverse scan of one ray: uⱼ ← Tⱼ₊₁uⱼ − Σ_{i>j} wᵢuᵢ for every j (`u`, `t_next`, `w`
/// of equal length).
///
/// Blocked: within a block of [`BLOCK`] samples the partial suffixes ℓⱼ = Σ_{j<i<end}
/// wᵢuᵢ are formed from the block's own products, then added to the suffix S of
/// everything after the block (Σ_{i>j} = S + ℓⱼ), and S grows by the block total. The
/// sums are the sequential ones reassociated (rounding differs by a few ulps of S).
#[inline(always)]
fn reverse_scan<const FMA: bool>(u: &mut [f64], t_next: &[f64], w: &[f64]) {
    let mut suffix = 0.0f64;
    let mut uc = u.rchunks_exact_mut(BLOCK);
    let mut tc = t_next.rchunks_exact(BLOCK);
    let mut wc = w.rchunks_exact(BLOCK);
    for ((ub, tb), wb) in (&mut uc).zip(&mut tc).zip(&mut wc) {
        let v: [f64; BLOCK] = std::array::from_fn(|j| ub[j]);
        let p: [f64; BLOCK] = std::array::from_fn(|j| wb[j] * v[j]);
        // ℓ₃ = 0, ℓ₂ = p₃, ℓ₁ = p₃ + p₂, ℓ₀ = p₃ + p₂ + p₁.
        let l2 = p[3];
        let l1 = l2 + p[2];
        let l0 = l1 + p[1];
        let local = [l0, l1, l2, 0.0];
        for j in 0..BLOCK {
            ub[j] = madd::<FMA>(tb[j], v[j], -(suffix + local[j]));
        }
        suffix += l0 + p[0];
    }
    // The first len % BLOCK samples, last to first.
    for ((uj, tn), wj) in uc
        .into_remainder()
        .iter_mut()
        .zip(tc.remainder())
        .zip(wc.remainder())
        .rev()
    {
        let v = *uj;
        *uj = madd::<FMA>(*tn, v, -suffix);
        suffix = madd::<FMA>(*wj, v, suffix);
    }
}

/// One ray's constant interval bounds and densities, the inputs of
/// [`bounds_alpha_decay`] (slices of the ray's length).
struct BoundsIn<'a, T> {
    sig: &'a [T],
    s: &'a [T],
    e: &'a [T],
    norm: T,
}

/// The outputs of [`bounds_alpha_decay`] (slices of the ray's length).
struct BoundsOut<'a, T> {
    del: &'a mut [T],
    tm: &'a mut [T],
    alpha: &'a mut [f64],
    decay: &'a mut [f64],
}

/// One ray's geometry from its interval bounds, with its αᵢ and e^{−xᵢ} in the same
/// vectorised pass: `del[i] = (e[i] − s[i])·norm` and `tm[i] = s[i] + (e[i] − s[i])/2`
/// in the storage dtype, exactly as the reference path forms them
/// ([`crate::volume::Intervals::deltas`], [`crate::volume::Intervals::midpoints`]), then α and the decay
/// as [`alpha_decay`] computes them. Returns `false` when some length is NaN, negative or
/// infinite, some start is not finite, or some σ is not finite and ≥ 0 (such a length is
/// stored as 0).
#[inline(always)]
fn bounds_alpha_decay<T: WithDType, const FMA: bool>(
    inp: BoundsIn<'_, T>,
    out: BoundsOut<'_, T>,
) -> bool {
    #[inline(always)]
    fn run<T: WithDType, const D: usize, const FMA: bool>(
        BoundsIn { sig, s, e, norm }: BoundsIn<'_, T>,
        BoundsOut {
            del,
            tm,
            alpha,
            decay,
        }: BoundsOut<'_, T>,
    ) -> bool {
        let half = T::from_f64(0.5);
        let mut ok = true;
        let outs = del
            .iter_mut()
            .zip(tm.iter_mut())
            .zip(alpha.iter_mut().zip(decay.iter_mut()));
        for (((d, t), (al, de)), ((&a, &b), sg)) in outs.zip(s.iter().zip(e).zip(sig)) {
            let span = b - a;
            let len = span * norm;
            let (l, sg) = (len.to_f64(), sg.to_f64());
            // NaN fails every comparison, so NaN and ±∞ bounds or densities are caught.
            let good = (0.0..=f64::MAX).contains(&l) & (a.to_f64().abs() <= f64::MAX);
            ok &= good & (0.0..=f64::MAX).contains(&sg);
            let l = if good { l } else { 0.0 };
            *d = if good { len } else { T::zero() };
            *t = a + span * half;
            (*al, *de) = alpha_and_decay::<D, FMA>((sg * l).min(X_MAX));
        }
        ok
    }
    if T::DTYPE == DType::F32 {
        run::<T, 7, FMA>(inp, out)
    } else {
        run::<T, 13, FMA>(inp, out)
    }
}

/// The instruction-set builds of the per-ray kernels, in increasing order. The same
/// code is compiled once per build and chosen at run time by CPU feature detection, so
/// the results differ only by the rounding of fused multiply–adds (the baseline build
/// multiplies and adds separately). Each call names the best build it may use (the
/// entry points pass [`KernelBuild::Avx512`], plain detection); the tests pass each
/// build in turn.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) enum KernelBuild {
    /// The build's baseline target (SSE2 on x86-64; every non-x86 target).
    Baseline,
    /// AVX2 + FMA: 4 f64 lanes for the exp polynomial and the per-sample passes.
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    Avx2Fma,
    /// AVX-512 (F, VL) + FMA: 8 f64 lanes.
    Avx512,
}

/// Runtime CPU dispatch to one [`KernelBuild`].
#[derive(Clone, Copy, Debug)]
struct Isa(KernelBuild);

impl Isa {
    /// The best build the CPU supports that is not above `max`.
    fn detect(max: KernelBuild) -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::is_x86_feature_detected as has;
            let avx2_fma = has!("avx2") && has!("fma");
            if max >= KernelBuild::Avx512 && avx2_fma && has!("avx512f") && has!("avx512vl") {
                return Isa(KernelBuild::Avx512);
            }
            if max >= KernelBuild::Avx2Fma && avx2_fma {
                return Isa(KernelBuild::Avx2Fma);
            }
        }
        let _ = max;
        Isa(KernelBuild::Baseline)
    }

    #[inline(always)]
    fn forward<T: WithDType>(self, ray: &RayIn<'_, T>, sc: &mut Scratch, o: &mut [T]) -> bool {
        match self.0 {
            // SAFETY: `detect` picks these builds only when the running CPU reports
            // every feature they are compiled with.
            #[cfg(target_arch = "x86_64")]
            KernelBuild::Avx512 => unsafe { x86::forward_ray_avx512(ray, sc, o) },
            #[cfg(target_arch = "x86_64")]
            KernelBuild::Avx2Fma => unsafe { x86::forward_ray_avx2(ray, sc, o) },
            _ => forward_ray::<T, false>(ray, sc, o),
        }
    }

    /// [`bounds_alpha_decay`] in this build, into `buf` (δ, t) and `sc` (α, decays)
    /// resized to the ray's length.
    #[inline(always)]
    fn prepare<T: WithDType>(
        self,
        sig: &[T],
        (s, e, norm): (&[T], &[T], T),
        buf: &mut (Vec<T>, Vec<T>),
        sc: &mut Scratch,
    ) -> bool {
        let n = sig.len();
        buf.0.resize(n, T::zero());
        buf.1.resize(n, T::zero());
        sc.alpha.resize(n, 0.0);
        sc.decay.resize(n, 0.0);
        let inp = BoundsIn { sig, s, e, norm };
        let out = BoundsOut {
            del: &mut buf.0[..n],
            tm: &mut buf.1[..n],
            alpha: &mut sc.alpha[..n],
            decay: &mut sc.decay[..n],
        };
        match self.0 {
            // SAFETY: as in `forward`.
            #[cfg(target_arch = "x86_64")]
            KernelBuild::Avx512 => unsafe { x86::prepare_avx512(inp, out) },
            #[cfg(target_arch = "x86_64")]
            KernelBuild::Avx2Fma => unsafe { x86::prepare_avx2(inp, out) },
            _ => bounds_alpha_decay::<T, false>(inp, out),
        }
    }

    #[inline(always)]
    fn backward<T: WithDType>(
        self,
        ray: &RayIn<'_, T>,
        grad: &[T],
        sc: &mut Scratch,
        out: &mut RayGrads<'_, T>,
    ) {
        match self.0 {
            // SAFETY: as in `forward`.
            #[cfg(target_arch = "x86_64")]
            KernelBuild::Avx512 => unsafe { x86::backward_ray_avx512(ray, grad, sc, out) },
            #[cfg(target_arch = "x86_64")]
            KernelBuild::Avx2Fma => unsafe { x86::backward_ray_avx2(ray, grad, sc, out) },
            _ => backward_ray::<T, false>(ray, grad, sc, out),
        }
    }
}

/// The per-ray kernels compiled with AVX2 + FMA and with AVX-512 enabled.
#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{BoundsIn, BoundsOut, RayGrads, RayIn, Scratch};
    use candle_core::WithDType;

    /// The forward, backward and interval-geometry entry points compiled with
    /// `$features`.
    macro_rules! kernel_build {
        ($features:literal, $fwd:ident, $bwd:ident, $fill:ident) => {
            #[target_feature(enable = $features)]
            pub(super) fn $fill<T: WithDType>(inp: BoundsIn<'_, T>, out: BoundsOut<'_, T>) -> bool {
                super::bounds_alpha_decay::<T, true>(inp, out)
            }

            #[target_feature(enable = $features)]
            pub(super) fn $fwd<T: WithDType>(
                ray: &RayIn<'_, T>,
                sc: &mut Scratch,
                o: &mut [T],
            ) -> bool {
                super::forward_ray::<T, true>(ray, sc, o)
            }

            #[target_feature(enable = $features)]
            pub(super) fn $bwd<T: WithDType>(
                ray: &RayIn<'_, T>,
                grad: &[T],
                sc: &mut Scratch,
                out: &mut RayGrads<'_, T>,
            ) {
                super::backward_ray::<T, true>(ray, grad, sc, out)
            }
        };
    }

    kernel_build!(
        "avx2,fma",
        forward_ray_avx2,
        backward_ray_avx2,
        prepare_avx2
    );
    kernel_build!(
        "avx2,fma,avx512f,avx512vl",
        forward_ray_avx512,
        backward_ray_avx512,
        prepare_avx512
    );
}

/// The first `len` entries of `v`'s spare capacity when `on`.
fn spare<T>(v: &mut Vec<T>, on: bool, len: usize) -> Option<&mut [MaybeUninit<T>]> {
    on.then(|| &mut v.spare_capacity_mut()[..len])
}

/// Mutable per-ray sub-slices of `buf` (`k` entries per sample), or `None` for every
/// ray when the buffer is not requested.
fn split_rays<'a, T>(
    buf: Option<&'a mut [T]>,
    seg: &Segments,
    k: usize,
) -> Vec<Option<&'a mut [T]>> {
    let r = seg.n_rays();
    let Some(mut buf) = buf else {
        return (0..r).map(|_| None).collect();
    };
    let mut out = Vec::with_capacity(r);
    for ray in 0..r {
        let (a, b) = seg.range(ray);
        let (head, tail) = std::mem::take(&mut buf).split_at_mut((b - a) * k);
        out.push(Some(head));
        buf = tail;
    }
    out
}

/// The `m` samples of a tensor the op holds (t or the interval ends).
fn captured_slice<'a, T: WithDType>(
    st: &'a Storage,
    l: &Layout,
    m: usize,
) -> candle_core::Result<&'a [T]> {
    let x = cpu_slice::<T>(st, l, "geometry")?;
    if x.len() != m {
        candle_core::bail!("fused composite: expected {m} samples, got {}", x.len());
    }
    Ok(x)
}

fn cpu_slice<'a, T: WithDType>(
    st: &'a Storage,
    l: &Layout,
    what: &str,
) -> candle_core::Result<&'a [T]> {
    super::dispatch::cpu_slice(st, l, "fused composite", what)
}

impl FusedComposite {
    /// Rows of the geometry input: δ (or the starts), and t when stacked.
    fn geo_rows(&self) -> usize {
        1 + usize::from(matches!(self.geometry, Geometry::Stacked))
    }

    /// Output columns: K values, depth, opacity.
    fn width(&self) -> usize {
        self.k + 2
    }

    fn check_len(&self, m_sig: usize, m_geo: usize, m_val: usize) -> candle_core::Result<()> {
        let m = self.seg.n_samples();
        if m_sig != m || m_geo != m * self.geo_rows() || m_val != m * self.k {
            candle_core::bail!(
                "fused composite: expected {m} samples with {} channels, got {m_sig}, {m_geo}, {m_val}",
                self.k
            );
        }
        Ok(())
    }

    /// Calls `f` with the geometry of all samples: slices of δ and t taken from the
    /// geometry input or the captured t tensor, or the interval starts (the input), ends
    /// and norms (captured).
    fn with_geometry<T: WithDType, R>(
        &self,
        geo: &[T],
        f: impl FnOnce(Geo<'_, T>) -> candle_core::Result<R>,
    ) -> candle_core::Result<R> {
        let m = self.seg.n_samples();
        match &self.geometry {
            Geometry::Stacked => f(Geo::Slices {
                del: &geo[..m],
                tm: &geo[m..],
            }),
            Geometry::Deltas(t) => {
                let (st, l) = t.storage_and_layout();
                let tm = captured_slice::<T>(&st, l, m)?;
                f(Geo::Slices { del: geo, tm })
            }
            Geometry::Intervals { ends, norms } => {
                let (st, l) = ends.storage_and_layout();
                let e = captured_slice::<T>(&st, l, m)?;
                f(Geo::Intervals {
                    s: geo,
                    e,
                    norms: norms.as_deref(),
                })
            }
        }
    }

    /// The inputs of ray `r`; for constant intervals its δ and t are formed in `buf` and
    /// its α and decays in `sc` (flagging invalid values in `bad`).
    fn ray<'a, T: WithDType>(
        &self,
        r: usize,
        sig: &'a [T],
        geo: &Geo<'a, T>,
        vals: &'a [T],
        buf: &'a mut (Vec<T>, Vec<T>),
        sc: &mut Scratch,
    ) -> RayIn<'a, T> {
        let (a, b) = self.seg.range(r);
        let sig = &sig[a..b];
        let (del, tm, prepared): (&[T], &[T], bool) = match geo {
            Geo::Slices { del, tm } => (&del[a..b], &tm[a..b], false),
            Geo::Intervals { s, e, norms } => {
                let norm = T::from_f64(norms.map_or(1.0, |n| n[r]));
                if !self.isa.prepare(sig, (&s[a..b], &e[a..b], norm), buf, sc) {
                    self.bad.store(true, Ordering::Relaxed);
                }
                (&buf.0[..], &buf.1[..], true)
            }
        };
        RayIn {
            sig,
            del,
            tm,
            vals: &vals[a * self.k..b * self.k],
            k: self.k,
            opaque_last: self.opaque_last,
            prepared,
        }
    }

    fn forward<T: WithDType>(&self, sig: &[T], geo: Geo<'_, T>, vals: &[T]) -> Vec<T> {
        let (r, width) = (self.seg.n_rays(), self.width());
        let isa = self.isa;
        let mut out = vec![T::zero(); r * width];
        let rows: Vec<_> = out.chunks_mut(width).enumerate().collect();
        let init = || (Scratch::default(), (Vec::new(), Vec::new()));
        for_each_init(rows, init, |(sc, buf), (ray, o)| {
            let input = self.ray(ray, sig, &geo, vals, buf, sc);
            if !isa.forward(&input, sc, o) {
                self.bad.store(true, Ordering::Relaxed);
            }
        });
        out
    }

    /// Gradients with respect to (sigmas, geometry, values) given `grad` `[R, K + 2]`;
    /// `need` says which of the three to produce (the others are returned empty and not
    /// computed, saving their allocation and writes).
    fn backward<T: WithDType>(
        &self,
        sig: &[T],
        geo: Geo<'_, T>,
        vals: &[T],
        grad: &[T],
        need: [bool; 3],
    ) -> (Vec<T>, Vec<T>, Vec<T>) {
        let (k, width, m) = (self.k, self.width(), self.seg.n_samples());
        // Uninitialised buffers (capacity `len` when requested, else empty): the kernels
        // write every entry, see `RayGrads`.
        let alloc = |on: bool, len: usize| Vec::<T>::with_capacity(if on { len } else { 0 });
        let lens = [m, m * self.geo_rows(), m * k];
        let (mut gs, mut ggeo, mut gv) = (
            alloc(need[0], lens[0]),
            alloc(need[1], lens[1]),
            alloc(need[2], lens[2]),
        );
        let seg = &self.seg;
        let (gd, gt) = match spare(&mut ggeo, need[1], lens[1]) {
            Some(g) => {
                let (gd, gt) = g.split_at_mut(m);
                (Some(gd), (!gt.is_empty()).then_some(gt))
            }
            None => (None, None),
        };
        let rays: Vec<_> = split_rays(spare(&mut gs, need[0], lens[0]), seg, 1)
            .into_iter()
            .zip(split_rays(gd, seg, 1))
            .zip(split_rays(spare(&mut gv, need[2], lens[2]), seg, k))
            .zip(split_rays(gt, seg, 1))
            .enumerate()
            .collect();
        let isa = self.isa;
        let init = || (Scratch::default(), (Vec::new(), Vec::new()));
        for_each_init(rays, init, |(sc, buf), (ray, (((gs, gd), gv), gt))| {
            let mut out = RayGrads {
                sig: gs,
                del: gd,
                vals: gv,
                tm: gt,
            };
            let g = &grad[ray * width..(ray + 1) * width];
            let input = self.ray(ray, sig, &geo, vals, buf, sc);
            isa.backward(&input, g, sc, &mut out);
        });
        for (v, (on, len)) in [&mut gs, &mut ggeo, &mut gv]
            .into_iter()
            .zip(need.iter().zip(lens))
        {
            if *on {
                // SAFETY: `split_rays` partitioned the first `len` spare entries of `v` among
                // the rays (the segments cover all m samples: `check_len` and `Segments`
                // ensure `(b − a)·k` slices sum to `len`), `for_each_init` returned normally,
                // so every ray's kernel ran, and `backward_ray_k` writes every entry of its
                // slices (values before `live`, zeros after; an empty ray has empty slices).
                unsafe { v.set_len(len) };
            }
        }
        (gs, ggeo, gv)
    }
}

impl CpuKernel<3> for FusedComposite {
    const NAME: &'static str = "fused composite";

    /// Inputs `(sigmas [M], geometry [G, M], values [M, K])`; output `[R, K + 2]`.
    fn forward<T: Real>(&self, [s, d, v]: [&[T]; 3]) -> candle_core::Result<(Vec<T>, Shape)> {
        let shape = Shape::from((self.seg.n_rays(), self.width()));
        self.check_len(s.len(), d.len(), v.len())?;
        let out = self.with_geometry(d, |geo| Ok(FusedComposite::forward(self, s, geo, v)))?;
        Ok((out, shape))
    }

    /// Only inputs that are part of the graph get a gradient.
    fn backward<T: Real>(
        &self,
        [s, d, v]: [&[T]; 3],
        g: &[T],
        need: [bool; 3],
    ) -> candle_core::Result<[Option<Vec<T>>; 3]> {
        self.check_len(s.len(), d.len(), v.len())?;
        let (a, b, c) = self.with_geometry(d, |geo| {
            Ok(FusedComposite::backward(self, s, geo, v, g, need))
        })?;
        let keep = |on: bool, v: Vec<T>| on.then_some(v);
        Ok([keep(need[0], a), keep(need[1], b), keep(need[2], c)])
    }
}
cpu_op!(FusedComposite, 3, "nf-fused-composite", cuda);

#[cfg(feature = "cuda")]
#[path = "cuda/composite.rs"]
mod cuda;
