//! The MLP with forward-mode tangents as one CPU op: the value and the tangents of a
//! [`FusedMlp`] through the same products.

use super::dispatch::{cpu_op, CpuKernel, Real};
use super::mlp::{chunk_rows, sum_chunks, FusedMlp, Params, Rows, Scratch, CHUNK, TILE};
use super::parallel::for_each_init;
use candle_core::Shape;

/// The MLP with forward-mode tangents as one op ([`crate::nn::Mlp::forward_with_jacobian`]):
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
pub(super) struct JvpScratch<T> {
    net: Scratch<T>,
    x0: Vec<T>,
    y: Vec<T>,
    gx0: Vec<T>,
}

impl FusedMlpJvp {
    /// Points per tile: the tile's `TILE` rows hold each point's value and its tangents.
    pub(super) fn points_per_tile(&self) -> usize {
        (TILE / (1 + self.tangents)).max(1)
    }

    pub(super) fn scratch<T: Real>(&self) -> JvpScratch<T> {
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
    pub(super) fn gather<T: Real>(&self, a0: &[T], da0: &[T], x0: &mut [T]) -> Rows {
        let a = self.mlp.a0;
        let values = a0.len() / a;
        x0[..a0.len()].copy_from_slice(a0);
        x0[a0.len()..a0.len() + da0.len()].copy_from_slice(da0);
        Rows {
            values,
            tangents: self.tangents,
        }
    }

    pub(super) fn width(&self) -> usize {
        (1 + self.tangents) * self.mlp.out_dim()
    }

    pub(super) fn forward<T: Real>(&self, a0: &[T], da0: &[T], params: &[T], n: usize) -> Vec<T> {
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
    pub(super) fn backward<T: Real>(
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
                chunk_rows(ga0.as_deref_mut(), a, chunks)
                    .into_iter()
                    .zip(chunk_rows(gda0.as_deref_mut(), k * a, chunks)),
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

    pub(super) fn check(
        &self,
        n_a0: usize,
        n_da0: usize,
        n_params: usize,
    ) -> candle_core::Result<usize> {
        let n = self.mlp.check(n_a0, n_params)?;
        if n_da0 != n * self.tangents * self.mlp.a0 {
            candle_core::bail!("fused MLP tangents: {n_da0} tangent entries for {n} points")
        }
        Ok(n)
    }
}

impl CpuKernel<3> for FusedMlpJvp {
    const NAME: &'static str = "fused MLP tangents";

    /// Inputs `(a₀ [N, A], ȧ₀ [N, K, A], params)`; output `[N, (1 + K)·out]`.
    fn forward<T: Real>(&self, [x, y, p]: [&[T]; 3]) -> candle_core::Result<(Vec<T>, Shape)> {
        let n = self.check(x.len(), y.len(), p.len())?;
        Ok((
            FusedMlpJvp::forward(self, x, y, p, n),
            Shape::from((n, self.width())),
        ))
    }

    fn backward<T: Real>(
        &self,
        [x, y, p]: [&[T]; 3],
        g: &[T],
        [want_x, want_y, _]: [bool; 3],
    ) -> candle_core::Result<[Option<Vec<T>>; 3]> {
        let n = self.check(x.len(), y.len(), p.len())?;
        if g.len() != n * self.width() {
            candle_core::bail!("{}: gradient of {} elements", Self::NAME, g.len())
        }
        let (gx, gy, gp) = FusedMlpJvp::backward(self, x, y, p, g, n, (want_x, want_y));
        Ok([gx, gy, Some(gp)])
    }
}
cpu_op!(FusedMlpJvp, 3, "nf-fused-mlp-jvp");
