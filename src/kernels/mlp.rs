//! The fused MLP op: every layer of an [`crate::nn::Mlp`] on a tile of points in one CPU pass,
//! forward and backward, instead of one candle op (and one allocation) per matmul, bias,
//! activation and concatenation.
//!
//! ## Math
//! The layers are those of [`crate::nn::Mlp`]: `hₗ = Wₗxₗ + bₗ`, `aₗ = φ(hₗ)`, with
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
//! candle's CPU pool ([`super::parallel`]).

use super::activation::{self, Act};
use super::dispatch::{cpu_op, CpuKernel, Real};
use super::parallel::for_each_init;
#[cfg(target_arch = "x86_64")]
use super::simd;
use candle_core::Shape;

/// Rows per tile: the activations of a tile of a 64-wide network (a few tens of KB) stay
/// in the core's L2 cache.
pub(crate) const TILE: usize = 128;
/// Rows per gradient accumulator (fixed, so that the reduction order does not depend on
/// the thread count).
pub(crate) const CHUNK: usize = 2048;

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
    pub(super) layers: Vec<LayerPlan>,
    pub(super) a0: usize,
    pub(super) act: Act,
    /// Offsets of each layer's weight and bias in the flat parameters.
    pub(super) offsets: Vec<(usize, usize)>,
    pub(super) n_params: usize,
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

    pub(super) fn out_dim(&self) -> usize {
        self.layers.last().map_or(0, |l| l.out)
    }

    /// The width of the input of layer `l` that comes from the previous layer (all of it
    /// but `a₀`'s share at a skip layer).
    pub(super) fn prev_width(&self, l: usize) -> usize {
        let layer = &self.layers[l];
        if layer.skip {
            layer.input - self.a0
        } else {
            layer.input
        }
    }

    /// Elements of a tile's hidden pre-activations (and as many activations).
    pub(super) fn hidden_len(&self) -> usize {
        let n = self.layers.len().saturating_sub(1);
        self.layers[..n].iter().map(|l| l.out).sum::<usize>() * TILE
    }

    pub(super) fn max_width(&self) -> usize {
        self.layers
            .iter()
            .map(|l| l.out.max(l.input))
            .max()
            .unwrap_or(0)
            .max(self.a0)
    }
}

/// A strided view of a matrix in a slice: element `(i, j)` at `off + i·rs + j·cs`.
#[derive(Clone, Copy)]
pub(super) struct View {
    pub(super) off: usize,
    pub(super) rs: usize,
    pub(super) cs: usize,
}

impl View {
    pub(super) const fn rows(off: usize, rs: usize) -> Self {
        Self { off, rs, cs: 1 }
    }

    /// The transpose of a row-major matrix with row stride `rs`.
    pub(super) const fn transposed(off: usize, rs: usize) -> Self {
        Self { off, rs: 1, cs: rs }
    }

    /// One past the last element of an `m × n` matrix (0 when empty).
    pub(super) fn end(&self, m: usize, n: usize) -> usize {
        if m == 0 || n == 0 {
            0
        } else {
            self.off + (m - 1) * self.rs + (n - 1) * self.cs + 1
        }
    }
}

/// `dst[m×n] = (acc ? dst : 0) + scale · lhs[m×k] · rhs[k×n]`, one thread.
#[allow(clippy::too_many_arguments)]
pub(super) fn matmul<T: Real>(
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
pub(super) struct Params<'a, T> {
    pub(super) p: &'a [T],
    pub(super) wt: &'a [T],
}

/// The rows of a tile: `values` rows of points, then, for forward-mode tangents,
/// `values · tangents` rows (point-major: the row of point `p`'s tangent `j` is
/// `values + p·tangents + j`), which go through the same products without the bias and
/// through `φ'(h)` of their point instead of `φ`.
#[derive(Clone, Copy, Debug)]
pub(super) struct Rows {
    pub(super) values: usize,
    pub(super) tangents: usize,
}

impl Rows {
    pub(super) fn plain(values: usize) -> Self {
        Self {
            values,
            tangents: 0,
        }
    }

    pub(super) fn total(self) -> usize {
        self.values * (1 + self.tangents)
    }

    /// The point of tangent row `r ≥ values`.
    pub(super) fn point(self, r: usize) -> usize {
        (r - self.values) / self.tangents
    }
}

/// Per-worker scratch: a tile's pre-activations and activations of every hidden layer,
/// and two gradient buffers.
pub(super) struct Scratch<T> {
    pub(super) h: Vec<T>,
    pub(super) a: Vec<T>,
    pub(super) g: Vec<T>,
    pub(super) gx: Vec<T>,
}

impl FusedMlp {
    pub(super) fn scratch<T: Real>(&self) -> Scratch<T> {
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
    pub(super) fn forward_tile<T: Real>(
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
    pub(super) fn backward_tile<T: Real>(
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
    pub(super) fn transposed<T: Real>(&self, p: &[T]) -> Vec<T> {
        let mut wt = p.to_vec();
        for (layer, &(w, _)) in self.layers.iter().zip(&self.offsets) {
            let len = layer.out * layer.input;
            transpose(&p[w..w + len], layer.out, &mut wt[w..w + len]);
        }
        wt
    }

    pub(super) fn forward<T: Real>(&self, a0: &[T], params: &[T], n: usize) -> Vec<T> {
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
    pub(super) fn backward<T: Real>(
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
        let ga0_chunks = chunk_rows(ga0.as_deref_mut(), self.a0, chunks);
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

    pub(super) fn check(&self, n_a0: usize, n_params: usize) -> candle_core::Result<usize> {
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

/// `dst = wᵀ` for a row-major `w` of `rows` rows (`dst` as long as `w`, row-major with
/// `w.len() / rows` rows).
pub(super) fn transpose<T: Copy>(w: &[T], rows: usize, dst: &mut [T]) {
    let cols = w.len() / rows.max(1);
    for (r, row) in w.chunks(cols.max(1)).enumerate().take(rows) {
        for (c, &v) in row.iter().enumerate() {
            dst[c * rows + r] = v;
        }
    }
}

/// Per-chunk row blocks of a per-point gradient buffer of width `w` (or `chunks` Nones).
pub(super) fn chunk_rows<T>(g: Option<&mut [T]>, w: usize, chunks: usize) -> Vec<Option<&mut [T]>> {
    match g {
        Some(g) => g.chunks_mut(CHUNK * w).map(Some).collect(),
        None => (0..chunks).map(|_| None).collect(),
    }
}

/// Sums the per-chunk parameter gradients (`n` each) into the first, in chunk order, and
/// keeps only it.
pub(super) fn sum_chunks<T: Real>(gp: &mut Vec<T>, n: usize) {
    let (first, rest) = gp.split_at_mut(n);
    for chunk in rest.chunks(n) {
        for (a, &b) in first.iter_mut().zip(chunk) {
            *a += b;
        }
    }
    gp.truncate(n);
}

impl CpuKernel<2> for FusedMlp {
    const NAME: &'static str = "fused MLP";

    /// Inputs `(a₀ [N, A], params)`; output `[N, out]`.
    fn forward<T: Real>(&self, [x, p]: [&[T]; 2]) -> candle_core::Result<(Vec<T>, Shape)> {
        let n = self.check(x.len(), p.len())?;
        Ok((
            FusedMlp::forward(self, x, p, n),
            Shape::from((n, self.out_dim())),
        ))
    }

    fn backward<T: Real>(
        &self,
        [x, p]: [&[T]; 2],
        g: &[T],
        [want_a0, _]: [bool; 2],
    ) -> candle_core::Result<[Option<Vec<T>>; 2]> {
        let n = self.check(x.len(), p.len())?;
        if g.len() != n * self.out_dim() {
            candle_core::bail!("fused MLP: gradient of {} elements", g.len())
        }
        let (ga0, gp) = FusedMlp::backward(self, x, p, g, n, want_a0);
        Ok([ga0, Some(gp)])
    }
}
cpu_op!(FusedMlp, 2, "nf-fused-mlp");
