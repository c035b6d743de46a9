//! The fused MLP op: every layer of an [`super::Mlp`] on a tile of points in one CPU pass,
//! forward and backward, instead of one candle op (and one allocation) per matmul, bias,
//! activation and concatenation.
//!
//! ## Math
//! The layers are those of [`super::Mlp`]: `hₗ = Wₗxₗ + bₗ`, `aₗ = φ(hₗ)`, with
//! `x₀ = a₀`, `xₗ = aₗ₋₁` or, at a skip layer, `xₗ = [aₗ₋₁, a₀]/√2`, and the output
//! `y = h_L`. The backward pass, for an upstream gradient `ḡ_y = ∂L/∂y`, runs
//!
//! ```text
//! ḡ_{h_L} = ḡ_y,   ∂L/∂Wₗ = Σ_rows ḡ_{hₗ} xₗᵀ,   ∂L/∂bₗ = Σ_rows ḡ_{hₗ},
//! ḡ_{xₗ} = Wₗᵀ ḡ_{hₗ},   ḡ_{hₗ₋₁} = φ'(hₗ₋₁) ⊙ ḡ_{aₗ₋₁}
//! ```
//!
//! with a skip layer's `ḡ_{xₗ}` split between `aₗ₋₁` and `a₀` (each scaled by 1/√2), and
//! `∂L/∂a₀` the sum of the first layer's and every skip layer's share. φ' is `𝟙[h ≥ 0]`
//! for ReLU (candle's own ReLU derivative, so the fused and reference paths agree at the
//! kink) and `σ(βh)` for softplus.
//!
//! ## Execution
//! The parameters travel as one flat tensor (each layer's row-major `[out, in]` weight,
//! then its bias), joined by [`candle_core::Tensor::cat`] from the network's variables so
//! that candle routes each slice of the parameter gradient back to its variable. Points are
//! split into tiles of [`TILE`] rows whose activations stay in cache; each layer of a tile
//! is one `gemm` call (the crate candle's own CPU matmul uses, with its runtime choice of
//! SIMD kernels). The backward pass recomputes the tile's forward (cheaper than keeping
//! every activation of the step alive between the passes) and accumulates the parameter
//! gradient of [`CHUNK`] rows in one buffer per chunk; the chunks are summed in their
//! order, so the gradient is the same bit for bit at any thread count. Tiles run on
//! candle's CPU pool ([`crate::parallel`]).

mod activation;
#[cfg(feature = "volume")]
pub(crate) mod nerf_loss;
#[cfg(target_arch = "x86_64")]
mod simd;

use crate::parallel::{cpu_slice, for_each_init};
use candle_core::{CpuStorage, CustomOp2, CustomOp3, DType, Layout, Shape, Tensor, WithDType};

/// Rows per tile: the activations of a tile of a 64-wide network (a few tens of KB) stay
/// in the core's L2 cache.
pub(crate) const TILE: usize = 128;
/// Rows per gradient accumulator (fixed, so that the reduction order does not depend on
/// the thread count).
pub(crate) const CHUNK: usize = 2048;

/// The hidden activation.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Act {
    Relu,
    Softplus(f64),
}

/// One affine layer of the plan.
#[derive(Clone, Debug)]
pub(crate) struct LayerPlan {
    /// Input columns: the previous activation's width (or `a₀`'s at layer 0), plus `a₀`'s
    /// width at a skip layer.
    pub input: usize,
    /// Output rows.
    pub out: usize,
    /// Whether the input is `[aₗ₋₁, a₀]/√2`.
    pub skip: bool,
}

/// The shapes of the network the op runs.
#[derive(Clone, Debug)]
pub(crate) struct FusedMlp {
    layers: Vec<LayerPlan>,
    a0: usize,
    act: Act,
    /// Offsets of each layer's weight and bias in the flat parameters.
    offsets: Vec<(usize, usize)>,
    n_params: usize,
}

impl FusedMlp {
    /// The plan for `layers` (the last is the linear output layer) on inputs of width `a0`.
    pub(crate) fn new(layers: Vec<LayerPlan>, a0: usize, act: Act) -> Self {
        let mut offsets = Vec::with_capacity(layers.len());
        let mut n = 0;
        for l in &layers {
            offsets.push((n, n + l.out * l.input));
            n += l.out * l.input + l.out;
        }
        Self {
            layers,
            a0,
            act,
            offsets,
            n_params: n,
        }
    }

    fn out_dim(&self) -> usize {
        self.layers.last().map_or(0, |l| l.out)
    }

    /// The width of the input of layer `l` that comes from the previous layer (all of it
    /// but `a₀`'s share at a skip layer).
    fn prev_width(&self, l: usize) -> usize {
        let layer = &self.layers[l];
        if layer.skip {
            layer.input - self.a0
        } else {
            layer.input
        }
    }

    /// Elements of a tile's hidden pre-activations (and as many activations).
    fn hidden_len(&self) -> usize {
        let n = self.layers.len().saturating_sub(1);
        self.layers[..n].iter().map(|l| l.out).sum::<usize>() * TILE
    }

    fn max_width(&self) -> usize {
        self.layers
            .iter()
            .map(|l| l.out.max(l.input))
            .max()
            .unwrap_or(0)
            .max(self.a0)
    }
}

/// The scalar types the op runs on (the products' kernels exist for these two).
pub(crate) trait Real: WithDType + activation::Precision {}
impl Real for f32 {}
impl Real for f64 {}

/// A strided view of a matrix in a slice: element `(i, j)` at `off + i·rs + j·cs`.
#[derive(Clone, Copy)]
struct View {
    off: usize,
    rs: usize,
    cs: usize,
}

impl View {
    const fn rows(off: usize, rs: usize) -> Self {
        Self { off, rs, cs: 1 }
    }

    /// The transpose of a row-major matrix with row stride `rs`.
    const fn transposed(off: usize, rs: usize) -> Self {
        Self { off, rs: 1, cs: rs }
    }

    /// One past the last element of an `m × n` matrix (0 when empty).
    fn end(&self, m: usize, n: usize) -> usize {
        if m == 0 || n == 0 {
            0
        } else {
            self.off + (m - 1) * self.rs + (n - 1) * self.cs + 1
        }
    }
}

/// `dst[m×n] = (acc ? dst : 0) + scale · lhs[m×k] · rhs[k×n]`, one thread.
#[allow(clippy::too_many_arguments)]
fn matmul<T: Real>(
    (m, n, k): (usize, usize, usize),
    dst: &mut [T],
    d: View,
    acc: bool,
    lhs: &[T],
    a: View,
    rhs: &[T],
    b: View,
    scale: T,
) {
    if m == 0 || n == 0 {
        return;
    }
    // invariant: every caller derives the views from the plan's shapes and the buffers'
    // sizes; this check is what makes the unsafe call below sound.
    assert!(
        d.end(m, n) <= dst.len() && a.end(m, k) <= lhs.len() && b.end(k, n) <= rhs.len(),
        "fused MLP: a matrix view exceeds its buffer"
    );
    #[cfg(target_arch = "x86_64")]
    if std::any::TypeId::of::<T>() == std::any::TypeId::of::<f32>()
        && b.cs == 1
        && d.cs == 1
        && simd::available()
    {
        // SAFETY: T is f32 (checked above), so the casts are identity casts; the assertion
        // keeps every access inside the slices; `available()` checked the CPU.
        unsafe {
            simd::matmul_f32(
                (m, n, k),
                dst.as_mut_ptr().add(d.off).cast::<f32>(),
                d.rs,
                acc,
                lhs.as_ptr().add(a.off).cast::<f32>(),
                (a.rs, a.cs),
                rhs.as_ptr().add(b.off).cast::<f32>(),
                b.rs,
                scale.to_f64() as f32,
            );
        }
        return;
    }
    // SAFETY: the assertion above keeps every access inside the three slices; `dst` is a
    // unique borrow and does not alias `lhs` or `rhs`.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr().add(d.off),
            d.cs as isize,
            d.rs as isize,
            acc,
            lhs.as_ptr().add(a.off),
            a.cs as isize,
            a.rs as isize,
            rhs.as_ptr().add(b.off),
            b.cs as isize,
            b.rs as isize,
            T::from_f64(1.0),
            scale,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// The flat parameters and, at the same offsets, every weight transposed (`[in, out]`,
/// row-major; the bias slots unused), so that every product of the forward pass reads both
/// operands by rows.
#[derive(Clone, Copy)]
struct Params<'a, T> {
    p: &'a [T],
    wt: &'a [T],
}

/// The rows of a tile: `values` rows of points, then, for forward-mode tangents,
/// `values · tangents` rows (point-major: the row of point `p`'s tangent `j` is
/// `values + p·tangents + j`), which go through the same products without the bias and
/// through `φ'(h)` of their point instead of `φ`.
#[derive(Clone, Copy, Debug)]
struct Rows {
    values: usize,
    tangents: usize,
}

impl Rows {
    fn plain(values: usize) -> Self {
        Self {
            values,
            tangents: 0,
        }
    }

    fn total(self) -> usize {
        self.values * (1 + self.tangents)
    }

    /// The point of tangent row `r ≥ values`.
    fn point(self, r: usize) -> usize {
        (r - self.values) / self.tangents
    }
}

/// Per-worker scratch: a tile's pre-activations and activations of every hidden layer,
/// and two gradient buffers.
struct Scratch<T> {
    h: Vec<T>,
    a: Vec<T>,
    g: Vec<T>,
    gx: Vec<T>,
}

impl FusedMlp {
    fn scratch<T: Real>(&self) -> Scratch<T> {
        let hidden = self.hidden_len();
        let w = self.max_width() * TILE;
        Scratch {
            h: vec![T::from_f64(0.0); hidden],
            a: vec![T::from_f64(0.0); hidden],
            g: vec![T::from_f64(0.0); w],
            gx: vec![T::from_f64(0.0); w],
        }
    }

    /// Runs the layers on the `rows` rows of `a0`, keeping the hidden pre-activations and
    /// activations in `sc` (layer `l`'s at offset `TILE · Σ_{j<l} out_j`, row-major) and
    /// writing the output rows to `y`.
    fn forward_tile<T: Real>(
        &self,
        a0: &[T],
        params: Params<'_, T>,
        tile: Rows,
        sc: &mut Scratch<T>,
        y: &mut [T],
    ) {
        let rows = tile.total();
        let inv_sqrt2 = T::from_f64(std::f64::consts::FRAC_1_SQRT_2);
        let last = self.layers.len() - 1;
        let mut off = 0;
        let mut prev: Option<(usize, usize)> = None; // (offset in sc.a, width)
        for (l, layer) in self.layers.iter().enumerate() {
            let (w, b) = self.offsets[l];
            let bias = &params.p[b..b + layer.out];
            let (dst, dst_off) = if l == last {
                (&mut *y, 0)
            } else {
                (&mut sc.h[..], off)
            };
            for r in 0..rows {
                let o = dst_off + r * layer.out;
                if r < tile.values {
                    dst[o..o + layer.out].copy_from_slice(bias);
                } else {
                    dst[o..o + layer.out].fill(T::from_f64(0.0));
                }
            }
            let d = View::rows(dst_off, layer.out);
            // Rows `col..` of Wᵀ ([in, out], row-major at W's offset).
            let weight_t = |col: usize| View::rows(w + col * layer.out, layer.out);
            match prev {
                None => matmul(
                    (rows, layer.out, self.a0),
                    dst,
                    d,
                    true,
                    a0,
                    View::rows(0, self.a0),
                    params.wt,
                    weight_t(0),
                    T::from_f64(1.0),
                ),
                Some((p_off, p_w)) => {
                    let scale = if layer.skip {
                        inv_sqrt2
                    } else {
                        T::from_f64(1.0)
                    };
                    matmul(
                        (rows, layer.out, p_w),
                        dst,
                        d,
                        true,
                        &sc.a,
                        View::rows(p_off, p_w),
                        params.wt,
                        weight_t(0),
                        scale,
                    );
                    if layer.skip {
                        matmul(
                            (rows, layer.out, self.a0),
                            dst,
                            d,
                            true,
                            a0,
                            View::rows(0, self.a0),
                            params.wt,
                            weight_t(p_w),
                            scale,
                        );
                    }
                }
            }
            if l < last {
                let (o, n) = (layer.out, tile.values * layer.out);
                activation::activate(self.act, &sc.h[off..off + n], &mut sc.a[off..off + n]);
                // Tangent rows: ȧ = φ'(h of the point) ⊙ ḣ.
                for r in tile.values..rows {
                    let (hp, tr) = (off + tile.point(r) * o, off + r * o);
                    activation::slope_times(
                        self.act,
                        &sc.h[hp..hp + o],
                        &sc.h[tr..tr + o],
                        &mut sc.a[tr..tr + o],
                    );
                }
                prev = Some((off, layer.out));
                off += TILE * layer.out;
            }
        }
    }

    /// The backward pass of one tile: recomputes its forward (unless `recompute` is
    /// false: `sc` then holds this tile's [`FusedMlp::forward_tile`]), then accumulates
    /// the parameter gradient into `gp` and writes `∂L/∂a₀` of its rows into `ga0` (when
    /// given).
    #[allow(clippy::too_many_arguments)]
    fn backward_tile<T: Real>(
        &self,
        a0: &[T],
        params: Params<'_, T>,
        gy: &[T],
        tile: Rows,
        sc: &mut Scratch<T>,
        gp: &mut [T],
        mut ga0: Option<&mut [T]>,
        recompute: bool,
    ) {
        let rows = tile.total();
        let inv_sqrt2 = T::from_f64(std::f64::consts::FRAC_1_SQRT_2);
        let last = self.layers.len() - 1;
        if recompute {
            // The output goes to the gradient scratch (overwritten below).
            let mut y = std::mem::take(&mut sc.g);
            self.forward_tile(a0, params, tile, sc, &mut y);
            sc.g = y;
        }
        let out = self.layers[last].out;
        sc.g[..rows * out].copy_from_slice(&gy[..rows * out]);
        if let Some(g) = ga0.as_deref_mut() {
            g.fill(T::from_f64(0.0));
        }
        // Offsets of each hidden layer's buffers in sc.h / sc.a.
        let mut offs = Vec::with_capacity(last);
        let mut off = 0;
        for layer in &self.layers[..last] {
            offs.push(off);
            off += TILE * layer.out;
        }
        for l in (0..=last).rev() {
            let layer = &self.layers[l];
            let (w, b) = self.offsets[l];
            let (o, i) = (layer.out, layer.input);
            let scale = if layer.skip {
                inv_sqrt2
            } else {
                T::from_f64(1.0)
            };
            let g_view = View::rows(0, o);
            // ∂L/∂b = Σ_rows ḡ_h over the value rows (tangents carry no bias).
            for r in 0..tile.values {
                for (acc, &g) in gp[b..b + o].iter_mut().zip(&sc.g[r * o..r * o + o]) {
                    *acc += g;
                }
            }
            // ∂L/∂W = ḡ_hᵀ x (per input part).
            let p_w = self.prev_width(l);
            if l == 0 {
                matmul(
                    (o, self.a0, rows),
                    gp,
                    View::rows(w, i),
                    true,
                    &sc.g,
                    View::transposed(0, o),
                    a0,
                    View::rows(0, self.a0),
                    T::from_f64(1.0),
                );
            } else {
                matmul(
                    (o, p_w, rows),
                    gp,
                    View::rows(w, i),
                    true,
                    &sc.g,
                    View::transposed(0, o),
                    &sc.a,
                    View::rows(offs[l - 1], p_w),
                    scale,
                );
                if layer.skip {
                    matmul(
                        (o, self.a0, rows),
                        gp,
                        View::rows(w + p_w, i),
                        true,
                        &sc.g,
                        View::transposed(0, o),
                        a0,
                        View::rows(0, self.a0),
                        scale,
                    );
                }
            }
            // ḡ_x = ḡ_h W, split into the previous layer's part and a₀'s.
            if l == 0 {
                if let Some(g) = ga0.as_deref_mut() {
                    matmul(
                        (rows, self.a0, o),
                        g,
                        View::rows(0, self.a0),
                        true,
                        &sc.g,
                        g_view,
                        params.p,
                        View::rows(w, i),
                        T::from_f64(1.0),
                    );
                }
                break;
            }
            if layer.skip {
                if let Some(g) = ga0.as_deref_mut() {
                    matmul(
                        (rows, self.a0, o),
                        g,
                        View::rows(0, self.a0),
                        true,
                        &sc.g,
                        g_view,
                        params.p,
                        View::rows(w + p_w, i),
                        scale,
                    );
                }
            }
            matmul(
                (rows, p_w, o),
                &mut sc.gx,
                View::rows(0, p_w),
                false,
                &sc.g,
                g_view,
                params.p,
                View::rows(w, i),
                scale,
            );
            // ḡ_h of the layer below: φ'(h) ⊙ ḡ_a on value rows, plus, from the tangents
            // ȧ_j = φ'(h) ⊙ ḣ_j, Σ_j φ''(h) ⊙ ḣ_j ⊙ ḡ_ȧj; φ'(h of the point) ⊙ ḡ_ȧ on
            // tangent rows.
            let base = offs[l - 1];
            let h = &sc.h[base..base + rows * p_w];
            for r in 0..rows {
                let hp = if r < tile.values { r } else { tile.point(r) };
                activation::slope_times(
                    self.act,
                    &h[hp * p_w..(hp + 1) * p_w],
                    &sc.gx[r * p_w..(r + 1) * p_w],
                    &mut sc.g[r * p_w..(r + 1) * p_w],
                );
            }
            if let Act::Softplus(beta) = self.act {
                // ReLU's φ'' is 0 (the reference path's slope 𝟙[h ≥ 0] is a constant of the
                // graph), so only softplus has this term.
                for r in tile.values..rows {
                    let p = tile.point(r);
                    for c in 0..p_w {
                        let k = activation::softplus_curvature(h[p * p_w + c].to_f64(), beta);
                        sc.g[p * p_w + c] += T::from_f64(k) * h[r * p_w + c] * sc.gx[r * p_w + c];
                    }
                }
            }
        }
    }

    /// The weights of `p` transposed, at their offsets ([`Params::wt`]).
    fn transposed<T: Real>(&self, p: &[T]) -> Vec<T> {
        let mut wt = p.to_vec();
        for (layer, &(w, _)) in self.layers.iter().zip(&self.offsets) {
            for o in 0..layer.out {
                for i in 0..layer.input {
                    wt[w + i * layer.out + o] = p[w + o * layer.input + i];
                }
            }
        }
        wt
    }

    fn forward<T: Real>(&self, a0: &[T], params: &[T], n: usize) -> Vec<T> {
        let wt = self.transposed(params);
        let params = Params { p: params, wt: &wt };
        let out = self.out_dim();
        let mut y = vec![T::from_f64(0.0); n * out];
        let items: Vec<_> = y
            .chunks_mut(TILE * out)
            .zip(a0.chunks(TILE * self.a0))
            .collect();
        for_each_init(
            items,
            || self.scratch::<T>(),
            |sc, (y, a0)| {
                let rows = y.len() / out;
                self.forward_tile(a0, params, Rows::plain(rows), sc, y);
            },
        );
        y
    }

    /// `(∂L/∂a₀ if wanted, ∂L/∂params)`.
    fn backward<T: Real>(
        &self,
        a0: &[T],
        params: &[T],
        gy: &[T],
        n: usize,
        want_a0: bool,
    ) -> (Option<Vec<T>>, Vec<T>) {
        let wt = self.transposed(params);
        let params = Params { p: params, wt: &wt };
        let out = self.out_dim();
        let chunks = n.div_ceil(CHUNK);
        let mut gp = vec![T::from_f64(0.0); chunks.max(1) * self.n_params];
        let mut ga0 = want_a0.then(|| vec![T::from_f64(0.0); n * self.a0]);
        let ga0_chunks = chunk_rows(ga0.as_mut(), self.a0, chunks);
        let items: Vec<_> = gp
            .chunks_mut(self.n_params)
            .zip(a0.chunks(CHUNK * self.a0))
            .zip(gy.chunks(CHUNK * out))
            .zip(ga0_chunks)
            .collect();
        for_each_init(
            items,
            || self.scratch::<T>(),
            |sc, (((gp, a0), gy), mut ga0)| {
                let rows = gy.len() / out;
                for t in (0..rows).step_by(TILE) {
                    let r = TILE.min(rows - t);
                    let ga = ga0
                        .as_deref_mut()
                        .map(|g| &mut g[t * self.a0..(t + r) * self.a0]);
                    self.backward_tile(
                        &a0[t * self.a0..(t + r) * self.a0],
                        params,
                        &gy[t * out..(t + r) * out],
                        Rows::plain(r),
                        sc,
                        gp,
                        ga,
                        true,
                    );
                }
            },
        );
        // Sum the chunks' parameter gradients in chunk order.
        sum_chunks(&mut gp, self.n_params);
        (ga0, gp)
    }

    fn check(&self, n_a0: usize, n_params: usize) -> candle_core::Result<usize> {
        if n_params != self.n_params {
            candle_core::bail!(
                "fused MLP: expected {} parameters, got {n_params}",
                self.n_params
            )
        }
        if self.a0 == 0 || !n_a0.is_multiple_of(self.a0) {
            candle_core::bail!(
                "fused MLP: input length {n_a0} is not a multiple of {}",
                self.a0
            )
        }
        Ok(n_a0 / self.a0)
    }
}

/// Per-chunk row blocks of a per-point gradient buffer of width `w` (or `chunks` Nones).
fn chunk_rows<T>(g: Option<&mut Vec<T>>, w: usize, chunks: usize) -> Vec<Option<&mut [T]>> {
    match g {
        Some(g) => g.chunks_mut(CHUNK * w).map(Some).collect(),
        None => (0..chunks).map(|_| None).collect(),
    }
}

/// Sums the per-chunk parameter gradients (`n` each) into the first, in chunk order, and
/// keeps only it.
fn sum_chunks<T: Real>(gp: &mut Vec<T>, n: usize) {
    let (first, rest) = gp.split_at_mut(n);
    for chunk in rest.chunks(n) {
        for (a, &b) in first.iter_mut().zip(chunk) {
            *a += b;
        }
    }
    gp.truncate(n);
}

impl CustomOp2 for FusedMlp {
    fn name(&self) -> &'static str {
        "nf-fused-mlp"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let [(a1, b1), (a2, b2)] = crate::parallel::contiguous([l1, l2], "fused MLP")?;
        let (storage, n) = match (s1, s2) {
            (CpuStorage::F32(x), CpuStorage::F32(p)) => {
                let (x, p) = (&x[a1..b1], &p[a2..b2]);
                let n = self.check(x.len(), p.len())?;
                (CpuStorage::F32(self.forward(x, p, n)), n)
            }
            (CpuStorage::F64(x), CpuStorage::F64(p)) => {
                let (x, p) = (&x[a1..b1], &p[a2..b2]);
                let n = self.check(x.len(), p.len())?;
                (CpuStorage::F64(self.forward(x, p, n)), n)
            }
            _ => candle_core::bail!("fused MLP: inputs must both be f32 or both f64"),
        };
        Ok((storage, Shape::from((n, self.out_dim()))))
    }

    fn bwd(
        &self,
        a0: &Tensor,
        params: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let want_a0 = a0.track_op();
        let (xs, xl) = a0.storage_and_layout();
        let (ps, pl) = params.storage_and_layout();
        let (gs, gl) = grad.storage_and_layout();
        let dev = a0.device();
        macro_rules! run {
            ($t:ty) => {{
                let x = cpu_slice::<$t>(&xs, xl, "fused MLP", "input")?;
                let p = cpu_slice::<$t>(&ps, pl, "fused MLP", "parameters")?;
                let g = cpu_slice::<$t>(&gs, gl, "fused MLP", "gradient")?;
                let n = self.check(x.len(), p.len())?;
                if g.len() != n * self.out_dim() {
                    candle_core::bail!("fused MLP: gradient of {} elements", g.len())
                }
                let (ga0, gp) = self.backward(x, p, g, n, want_a0);
                let ga0 = match ga0 {
                    Some(v) => Some(Tensor::from_vec(v, a0.shape(), dev)?),
                    None => None,
                };
                (ga0, Some(Tensor::from_vec(gp, params.shape(), dev)?))
            }};
        }
        Ok(match a0.dtype() {
            DType::F32 => run!(f32),
            DType::F64 => run!(f64),
            other => candle_core::bail!("fused MLP: unsupported dtype {other:?}"),
        })
    }
}

/// NeRF's two networks as one op ([`crate::volume::Nerf`]): the trunk on the encoded position
/// `[N, E_p]` gives the raw density and a feature `[N, W]`; the colour head runs on
/// `[encoded direction, feature]`. Output `[N, 4]`: the raw density and the raw colour
/// (activations are applied outside). Parameters: the trunk's flat parameters, then the
/// head's. The feature never leaves the tile, so the pass allocates nothing per point
/// beyond its output, and the backward pass hands the head's input gradient straight to
/// the trunk.
#[derive(Clone, Debug)]
pub(crate) struct FusedNerf {
    pub trunk: FusedMlp,
    pub head: FusedMlp,
}

/// Per-worker scratch of [`FusedNerf`]: each network's, the trunk's output, the head's
/// input and output, and their gradients.
struct NerfScratch<T> {
    trunk: Scratch<T>,
    head: Scratch<T>,
    yt: Vec<T>,
    ha0: Vec<T>,
    yh: Vec<T>,
    g_ha0: Vec<T>,
    g_yt: Vec<T>,
}

impl FusedNerf {
    /// Output columns: the raw density and the raw colour.
    fn width(&self) -> usize {
        4
    }

    /// Widths: encoded direction, trunk output (1 + feature), head input.
    fn widths(&self) -> (usize, usize, usize) {
        let t_out = self.trunk.out_dim();
        let h_in = self.head.a0;
        (h_in + 1 - t_out, t_out, h_in)
    }

    fn scratch<T: Real>(&self) -> NerfScratch<T> {
        let (_, t_out, h_in) = self.widths();
        let z = T::from_f64(0.0);
        NerfScratch {
            trunk: self.trunk.scratch(),
            head: self.head.scratch(),
            yt: vec![z; TILE * t_out],
            ha0: vec![z; TILE * h_in],
            yh: vec![z; TILE * self.head.out_dim()],
            g_ha0: vec![z; TILE * h_in],
            g_yt: vec![z; TILE * t_out],
        }
    }

    /// The trunk and the head's input of one tile (left in `sc`); returns the rows.
    fn trunk_tile<T: Real>(
        &self,
        ep: &[T],
        ed: &[T],
        pt: Params<'_, T>,
        sc: &mut NerfScratch<T>,
    ) -> usize {
        let (dd, t_out, h_in) = self.widths();
        let rows = ep.len() / self.trunk.a0;
        self.trunk
            .forward_tile(ep, pt, Rows::plain(rows), &mut sc.trunk, &mut sc.yt);
        for r in 0..rows {
            let row = &mut sc.ha0[r * h_in..(r + 1) * h_in];
            row[..dd].copy_from_slice(&ed[r * dd..(r + 1) * dd]);
            row[dd..].copy_from_slice(&sc.yt[r * t_out + 1..(r + 1) * t_out]);
        }
        rows
    }

    /// The trunk's and the head's [`Params`] views of `params`, with `wt` holding both
    /// networks' transposed weights.
    fn split<'a, T: Real>(&self, params: &'a [T], wt: &'a [T]) -> (Params<'a, T>, Params<'a, T>) {
        let (pt, ph) = params.split_at(self.trunk.n_params);
        let (wtt, wth) = wt.split_at(self.trunk.n_params);
        (Params { p: pt, wt: wtt }, Params { p: ph, wt: wth })
    }

    /// Both networks' transposed weights, trunk then head.
    fn transposed<T: Real>(&self, params: &[T]) -> Vec<T> {
        let (pt, ph) = params.split_at(self.trunk.n_params);
        let mut wt = self.trunk.transposed(pt);
        wt.extend(self.head.transposed(ph));
        wt
    }

    fn forward<T: Real>(&self, ep: &[T], ed: &[T], params: &[T], n: usize) -> Vec<T> {
        let (dd, _, _) = self.widths();
        let wt = self.transposed(params);
        let (pt, ph) = self.split(params, &wt);
        let mut y = vec![T::from_f64(0.0); n * 4];
        let items: Vec<_> = y
            .chunks_mut(TILE * 4)
            .zip(ep.chunks(TILE * self.trunk.a0))
            .zip(ed.chunks(TILE * dd))
            .collect();
        let t_out = self.trunk.out_dim();
        for_each_init(
            items,
            || self.scratch::<T>(),
            |sc, ((y, ep), ed)| {
                let rows = self.trunk_tile(ep, ed, pt, sc);
                let (ha0, yh) = (&sc.ha0, &mut sc.yh);
                self.head
                    .forward_tile(ha0, ph, Rows::plain(rows), &mut sc.head, yh);
                for r in 0..rows {
                    y[4 * r] = sc.yt[r * t_out];
                    y[4 * r + 1..4 * r + 4].copy_from_slice(&sc.yh[3 * r..3 * r + 3]);
                }
            },
        );
        y
    }

    /// `(∂L/∂enc_pos, ∂L/∂enc_dir)` where wanted, and `∂L/∂params`.
    #[allow(clippy::type_complexity)]
    fn backward<T: Real>(
        &self,
        ep: &[T],
        ed: &[T],
        params: &[T],
        gy: &[T],
        n: usize,
        want: (bool, bool),
    ) -> (Option<Vec<T>>, Option<Vec<T>>, Vec<T>) {
        let (dd, _, _) = self.widths();
        let wt = self.transposed(params);
        let (pt, ph) = self.split(params, &wt);
        let (a0p, np) = (self.trunk.a0, params.len());
        let chunks = n.div_ceil(CHUNK);
        let mut gp = vec![T::from_f64(0.0); chunks.max(1) * np];
        let mut gep = want.0.then(|| vec![T::from_f64(0.0); n * a0p]);
        let mut ged = want.1.then(|| vec![T::from_f64(0.0); n * dd]);
        let items: Vec<_> = gp
            .chunks_mut(np)
            .zip(ep.chunks(CHUNK * a0p))
            .zip(ed.chunks(CHUNK * dd))
            .zip(gy.chunks(CHUNK * 4))
            .zip(
                chunk_rows(gep.as_mut(), a0p, chunks)
                    .into_iter()
                    .zip(chunk_rows(ged.as_mut(), dd, chunks)),
            )
            .collect();
        for_each_init(
            items,
            || self.scratch::<T>(),
            |sc, ((((gp, ep), ed), gy), (mut gep, mut ged))| {
                let (gpt, gph) = gp.split_at_mut(self.trunk.n_params);
                let rows = gy.len() / 4;
                for t in (0..rows).step_by(TILE) {
                    let r = TILE.min(rows - t);
                    self.trunk_tile(
                        &ep[t * a0p..(t + r) * a0p],
                        &ed[t * dd..(t + r) * dd],
                        pt,
                        sc,
                    );
                    self.backward_tile(
                        &ep[t * a0p..(t + r) * a0p],
                        (pt, ph),
                        &gy[4 * t..4 * (t + r)],
                        sc,
                        (gpt, gph),
                        (
                            gep.as_deref_mut().map(|g| &mut g[t * a0p..(t + r) * a0p]),
                            ged.as_deref_mut().map(|g| &mut g[t * dd..(t + r) * dd]),
                        ),
                        true,
                    );
                }
            },
        );
        sum_chunks(&mut gp, np);
        (gep, ged, gp)
    }

    /// The backward pass of one tile after [`FusedNerf::trunk_tile`] on it (which left
    /// the trunk's activations and the head's input in `sc`): the head (recomputing its
    /// forward pass when `head_recompute`; else `sc` holds it), then the trunk. `gy: [r,
    /// 4]` is the gradient of the op's output rows; the parameter gradients accumulate
    /// into `gp` (trunk, head) and the encoded inputs' gradients, where given, are
    /// written to `ga` (position, direction).
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    fn backward_tile<T: Real>(
        &self,
        ep: &[T],
        (pt, ph): (Params<'_, T>, Params<'_, T>),
        gy: &[T],
        sc: &mut NerfScratch<T>,
        (gpt, gph): (&mut [T], &mut [T]),
        (gep, mut ged): (Option<&mut [T]>, Option<&mut [T]>),
        head_recompute: bool,
    ) {
        let (dd, t_out, h_in) = self.widths();
        let r = gy.len() / 4;
        for i in 0..r {
            sc.yh[3 * i..3 * i + 3].copy_from_slice(&gy[4 * i + 1..4 * i + 4]);
        }
        let (ha0, yh, g_ha0) = (&sc.ha0, &sc.yh, &mut sc.g_ha0[..r * h_in]);
        self.head.backward_tile(
            ha0,
            ph,
            yh,
            Rows::plain(r),
            &mut sc.head,
            gph,
            Some(g_ha0),
            head_recompute,
        );
        for i in 0..r {
            sc.g_yt[i * t_out] = gy[4 * i];
            sc.g_yt[i * t_out + 1..(i + 1) * t_out]
                .copy_from_slice(&sc.g_ha0[i * h_in + dd..(i + 1) * h_in]);
            if let Some(g) = ged.as_deref_mut() {
                g[i * dd..(i + 1) * dd].copy_from_slice(&sc.g_ha0[i * h_in..i * h_in + dd]);
            }
        }
        self.trunk.backward_tile(
            ep,
            pt,
            &sc.g_yt,
            Rows::plain(r),
            &mut sc.trunk,
            gpt,
            gep,
            false,
        );
    }

    fn check(&self, n_ep: usize, n_ed: usize, n_params: usize) -> candle_core::Result<usize> {
        let (dd, _, _) = self.widths();
        let n = self.trunk.check(n_ep, self.trunk.n_params)?;
        if n_params != self.trunk.n_params + self.head.n_params || n_ed != n * dd {
            candle_core::bail!("fused NeRF: {n_ed} direction features or {n_params} parameters do not match {n} points")
        }
        Ok(n)
    }
}

/// The MLP with forward-mode tangents as one op ([`super::Mlp::forward_with_jacobian`]):
/// inputs `a₀: [N, A]`, their tangents `ȧ₀: [N, K, A]` (K directions per point) and the
/// flat parameters; output `[N, (1 + K)·out]`, per point the value `y` and then the K
/// tangents `ẏⱼ = J_y ȧ₀ⱼ`. The tangents run through the same products as extra rows of
/// the tile (no bias; `φ'(h)` of their point instead of `φ`), and the backward pass
/// differentiates both, the value rows receiving `Σⱼ φ''(h) ⊙ ḣⱼ ⊙ ḡ_ȧⱼ` from the
/// tangents: normals and eikonal losses reach the weights through this op as through the
/// reference path.
#[derive(Clone, Debug)]
pub(crate) struct FusedMlpJvp {
    pub mlp: FusedMlp,
    pub tangents: usize,
}

/// Per-worker scratch of [`FusedMlpJvp`]: the network's, the tile's input rows, output
/// rows, output gradient rows and input gradient rows.
struct JvpScratch<T> {
    net: Scratch<T>,
    x0: Vec<T>,
    y: Vec<T>,
    gx0: Vec<T>,
}

impl FusedMlpJvp {
    /// Points per tile: the tile's `TILE` rows hold each point's value and its tangents.
    fn points_per_tile(&self) -> usize {
        (TILE / (1 + self.tangents)).max(1)
    }

    fn scratch<T: Real>(&self) -> JvpScratch<T> {
        let z = T::from_f64(0.0);
        let rows = self.points_per_tile() * (1 + self.tangents);
        JvpScratch {
            net: self.mlp.scratch(),
            x0: vec![z; rows * self.mlp.a0],
            y: vec![z; rows * self.mlp.out_dim()],
            gx0: vec![z; rows * self.mlp.a0],
        }
    }

    /// Copies the tile's values and tangents into the row layout of [`Rows`].
    fn gather<T: Real>(&self, a0: &[T], da0: &[T], x0: &mut [T]) -> Rows {
        let a = self.mlp.a0;
        let values = a0.len() / a;
        x0[..a0.len()].copy_from_slice(a0);
        x0[a0.len()..a0.len() + da0.len()].copy_from_slice(da0);
        Rows {
            values,
            tangents: self.tangents,
        }
    }

    fn width(&self) -> usize {
        (1 + self.tangents) * self.mlp.out_dim()
    }

    fn forward<T: Real>(&self, a0: &[T], da0: &[T], params: &[T], n: usize) -> Vec<T> {
        let wt = self.mlp.transposed(params);
        let params = Params { p: params, wt: &wt };
        let (a, k, o, ppt) = (
            self.mlp.a0,
            self.tangents,
            self.mlp.out_dim(),
            self.points_per_tile(),
        );
        let mut y = vec![T::from_f64(0.0); n * self.width()];
        let items: Vec<_> = y
            .chunks_mut(ppt * self.width())
            .zip(a0.chunks(ppt * a))
            .zip(da0.chunks(ppt * k * a))
            .collect();
        for_each_init(
            items,
            || self.scratch::<T>(),
            |sc, ((y, a0), da0)| {
                let tile = self.gather(a0, da0, &mut sc.x0);
                let mut out = std::mem::take(&mut sc.y);
                self.mlp
                    .forward_tile(&sc.x0, params, tile, &mut sc.net, &mut out);
                for p in 0..tile.values {
                    let dst = &mut y[p * (1 + k) * o..(p + 1) * (1 + k) * o];
                    dst[..o].copy_from_slice(&out[p * o..(p + 1) * o]);
                    let t0 = (tile.values + p * k) * o;
                    dst[o..].copy_from_slice(&out[t0..t0 + k * o]);
                }
                sc.y = out;
            },
        );
        y
    }

    /// `(∂L/∂a₀, ∂L/∂ȧ₀)` where wanted, and `∂L/∂params`.
    ///
    /// When no tangent output receives a gradient (the loss uses the values only, as DVR's
    /// implicit depth does), every tangent row's gradient is zero — they are linear in
    /// `ḡ_ẏ`, the second-order term included — so the pass runs the value rows alone.
    #[allow(clippy::type_complexity)]
    fn backward<T: Real>(
        &self,
        a0: &[T],
        da0: &[T],
        params: &[T],
        gy: &[T],
        n: usize,
        want: (bool, bool),
    ) -> (Option<Vec<T>>, Option<Vec<T>>, Vec<T>) {
        let (o, w) = (self.mlp.out_dim(), self.width());
        let zero = T::from_f64(0.0);
        if gy.chunks(w).all(|row| row[o..].iter().all(|&g| g == zero)) {
            let values: Vec<T> = gy
                .chunks(w)
                .flat_map(|row| row[..o].iter().copied())
                .collect();
            let (ga0, gp) = self.mlp.backward(a0, params, &values, n, want.0);
            let gda0 = want.1.then(|| vec![zero; da0.len()]);
            return (ga0, gda0, gp);
        }
        let wt = self.mlp.transposed(params);
        let params = Params { p: params, wt: &wt };
        let (a, k, o, ppt) = (
            self.mlp.a0,
            self.tangents,
            self.mlp.out_dim(),
            self.points_per_tile(),
        );
        let np = self.mlp.n_params;
        let chunks = n.div_ceil(CHUNK);
        let mut gp = vec![T::from_f64(0.0); chunks.max(1) * np];
        let mut ga0 = want.0.then(|| vec![T::from_f64(0.0); n * a]);
        let mut gda0 = want.1.then(|| vec![T::from_f64(0.0); n * k * a]);
        let items: Vec<_> = gp
            .chunks_mut(np)
            .zip(a0.chunks(CHUNK * a))
            .zip(da0.chunks(CHUNK * k * a))
            .zip(gy.chunks(CHUNK * self.width()))
            .zip(
                chunk_rows(ga0.as_mut(), a, chunks)
                    .into_iter()
                    .zip(chunk_rows(gda0.as_mut(), k * a, chunks)),
            )
            .collect();
        let need_x = want.0 || want.1;
        for_each_init(
            items,
            || self.scratch::<T>(),
            |sc, ((((gp, a0), da0), gy), (mut ga0, mut gda0))| {
                let points = a0.len() / a;
                for t in (0..points).step_by(ppt) {
                    let r = ppt.min(points - t);
                    let tile = self.gather(
                        &a0[t * a..(t + r) * a],
                        &da0[t * k * a..(t + r) * k * a],
                        &mut sc.x0,
                    );
                    // The output gradient in the row layout.
                    for p in 0..r {
                        let src = &gy[(t + p) * (1 + k) * o..(t + p + 1) * (1 + k) * o];
                        sc.y[p * o..(p + 1) * o].copy_from_slice(&src[..o]);
                        let t0 = (r + p * k) * o;
                        sc.y[t0..t0 + k * o].copy_from_slice(&src[o..]);
                    }
                    let rows = tile.total();
                    let gx = need_x.then_some(&mut sc.gx0[..rows * a]);
                    let (x0, y) = (&sc.x0, &sc.y);
                    self.mlp
                        .backward_tile(x0, params, y, tile, &mut sc.net, gp, gx, true);
                    if let Some(g) = ga0.as_deref_mut() {
                        g[t * a..(t + r) * a].copy_from_slice(&sc.gx0[..r * a]);
                    }
                    if let Some(g) = gda0.as_deref_mut() {
                        g[t * k * a..(t + r) * k * a].copy_from_slice(&sc.gx0[r * a..rows * a]);
                    }
                }
            },
        );
        sum_chunks(&mut gp, np);
        (ga0, gda0, gp)
    }

    fn check(&self, n_a0: usize, n_da0: usize, n_params: usize) -> candle_core::Result<usize> {
        let n = self.mlp.check(n_a0, n_params)?;
        if n_da0 != n * self.tangents * self.mlp.a0 {
            candle_core::bail!("fused MLP tangents: {n_da0} tangent entries for {n} points")
        }
        Ok(n)
    }
}

/// A fused op over `(x, y, parameters)`, all f32 or all f64 on the CPU, whose output has
/// `width()` columns per point: [`FusedNerf`] and [`FusedMlpJvp`] share their candle
/// plumbing (contiguity, dtype dispatch, which inputs want a gradient) through it.
trait Fused3: Send + Sync {
    const NAME: &'static str;
    /// Output columns per point.
    fn width(&self) -> usize;
    /// The number of points, after checking the three inputs' lengths.
    fn points(&self, n_x: usize, n_y: usize, n_params: usize) -> candle_core::Result<usize>;
    fn run_forward<T: Real>(&self, x: &[T], y: &[T], params: &[T], n: usize) -> Vec<T>;
    /// `(∂L/∂x, ∂L/∂y)` where wanted, and `∂L/∂params`.
    #[allow(clippy::type_complexity)]
    fn run_backward<T: Real>(
        &self,
        x: &[T],
        y: &[T],
        params: &[T],
        grad: &[T],
        n: usize,
        want: (bool, bool),
    ) -> (Option<Vec<T>>, Option<Vec<T>>, Vec<T>);
}

/// [`Fused3`] for a type with inherent `forward`, `backward`, `check` and `width`.
macro_rules! fused3 {
    ($ty:ty, $name:literal) => {
        impl Fused3 for $ty {
            const NAME: &'static str = $name;

            fn width(&self) -> usize {
                <$ty>::width(self)
            }

            fn points(&self, n_x: usize, n_y: usize, n_p: usize) -> candle_core::Result<usize> {
                self.check(n_x, n_y, n_p)
            }

            fn run_forward<T: Real>(&self, x: &[T], y: &[T], params: &[T], n: usize) -> Vec<T> {
                self.forward(x, y, params, n)
            }

            fn run_backward<T: Real>(
                &self,
                x: &[T],
                y: &[T],
                params: &[T],
                grad: &[T],
                n: usize,
                want: (bool, bool),
            ) -> (Option<Vec<T>>, Option<Vec<T>>, Vec<T>) {
                self.backward(x, y, params, grad, n, want)
            }
        }
    };
}
fused3!(FusedNerf, "fused NeRF");
fused3!(FusedMlpJvp, "fused MLP tangents");

/// The candle side of every [`Fused3`] op.
macro_rules! custom_op3 {
    ($ty:ty, $name:literal) => {
        impl CustomOp3 for $ty {
            fn name(&self) -> &'static str {
                $name
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
                fused3_cpu_fwd(self, (s1, l1), (s2, l2), (s3, l3))
            }

            fn bwd(
                &self,
                x: &Tensor,
                y: &Tensor,
                params: &Tensor,
                _res: &Tensor,
                grad: &Tensor,
            ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
                fused3_bwd(self, x, y, params, grad)
            }
        }
    };
}
custom_op3!(FusedNerf, "nf-fused-nerf");
custom_op3!(FusedMlpJvp, "nf-fused-mlp-jvp");

fn fused3_cpu_fwd<K: Fused3>(
    k: &K,
    (s1, l1): (&CpuStorage, &Layout),
    (s2, l2): (&CpuStorage, &Layout),
    (s3, l3): (&CpuStorage, &Layout),
) -> candle_core::Result<(CpuStorage, Shape)> {
    let [(a1, b1), (a2, b2), (a3, b3)] = crate::parallel::contiguous([l1, l2, l3], K::NAME)?;
    let (storage, n) = match (s1, s2, s3) {
        (CpuStorage::F32(x), CpuStorage::F32(y), CpuStorage::F32(p)) => {
            let (x, y, p) = (&x[a1..b1], &y[a2..b2], &p[a3..b3]);
            let n = k.points(x.len(), y.len(), p.len())?;
            (CpuStorage::F32(k.run_forward(x, y, p, n)), n)
        }
        (CpuStorage::F64(x), CpuStorage::F64(y), CpuStorage::F64(p)) => {
            let (x, y, p) = (&x[a1..b1], &y[a2..b2], &p[a3..b3]);
            let n = k.points(x.len(), y.len(), p.len())?;
            (CpuStorage::F64(k.run_forward(x, y, p, n)), n)
        }
        _ => candle_core::bail!("{}: inputs must all be f32 or all f64", K::NAME),
    };
    Ok((storage, Shape::from((n, k.width()))))
}

fn fused3_bwd<K: Fused3>(
    k: &K,
    x: &Tensor,
    y: &Tensor,
    params: &Tensor,
    grad: &Tensor,
) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
    let grad = grad.contiguous()?;
    let want = (x.track_op(), y.track_op());
    let (xs, xl) = x.storage_and_layout();
    let (ys, yl) = y.storage_and_layout();
    let (ps, pl) = params.storage_and_layout();
    let (gs, gl) = grad.storage_and_layout();
    let dev = x.device();
    macro_rules! run {
        ($t:ty) => {{
            let xv = cpu_slice::<$t>(&xs, xl, K::NAME, "first input")?;
            let yv = cpu_slice::<$t>(&ys, yl, K::NAME, "second input")?;
            let pv = cpu_slice::<$t>(&ps, pl, K::NAME, "parameters")?;
            let gv = cpu_slice::<$t>(&gs, gl, K::NAME, "gradient")?;
            let n = k.points(xv.len(), yv.len(), pv.len())?;
            if gv.len() != n * k.width() {
                candle_core::bail!("{}: gradient of {} elements", K::NAME, gv.len())
            }
            let (a, b, c) = k.run_backward(xv, yv, pv, gv, n, want);
            let wrap = |v: Option<Vec<$t>>, t: &Tensor| -> candle_core::Result<Option<Tensor>> {
                v.map(|v| Tensor::from_vec(v, t.shape(), dev)).transpose()
            };
            (
                wrap(a, x)?,
                wrap(b, y)?,
                Some(Tensor::from_vec(c, params.shape(), dev)?),
            )
        }};
    }
    Ok(match x.dtype() {
        DType::F32 => run!(f32),
        DType::F64 => run!(f64),
        other => candle_core::bail!("{}: unsupported dtype {other:?}", K::NAME),
    })
}
