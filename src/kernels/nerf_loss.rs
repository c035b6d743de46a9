//! NeRF's photometric training loss as one CPU op ([`crate::volume::Nerf::color_loss`]):
//! for a tile of whole rays, the encodings, both networks, the density and colour
//! activations, compositing, the squared error and the backward pass of all of them run
//! while the tile's activations are still in cache, so the backward pass needs no second
//! forward pass of the networks and no per-sample tensor (encodings, raw outputs,
//! densities, colours, weights) is ever allocated.
//!
//! ## Math
//! Per ray with samples `i` (raw outputs `ρᵢ`, `ςᵢ ∈ ℝ³`, lengths `δᵢ`), as
//! [`crate::volume::Nerf::radiance`] and [`crate::volume::composite()`] compute them:
//!
//! ```text
//! σᵢ = act(ρᵢ + shift),  cᵢ = sigmoid(ςᵢ),  xᵢ = min(σᵢδᵢ, X_MAX),
//! αᵢ = 1 − e^{−xᵢ} (1 for the last sample with opaque_last),  Tᵢ = exp(−Σ_{k<i} xₖ),
//! wᵢ = Tᵢαᵢ,  C = Σᵢ wᵢcᵢ + (1 − Σᵢ wᵢ)·c_bg,  L = Σ_rays ‖C − C*‖² / (3R)
//! ```
//!
//! and backward, with `ḡ_C = 2(C − C*)/(3R)` and `uᵢ = ḡ_C·(cᵢ − c_bg)`:
//!
//! ```text
//! ∂L/∂cᵢ = wᵢ ḡ_C,   ∂L/∂xⱼ = uⱼ Tⱼ ∂αⱼ/∂xⱼ − Σ_{i>j} uᵢwᵢ   (∂αⱼ/∂xⱼ = e^{−xⱼ}, or 0),
//! ∂L/∂σⱼ = δⱼ ∂L/∂xⱼ where σⱼδⱼ < X_MAX (else 0),
//! ∂L/∂ρⱼ = act'(ρⱼ + shift)·∂L/∂σⱼ,   ∂L/∂ςⱼ = cⱼ(1 − cⱼ)·∂L/∂cⱼ
//! ```
//!
//! (`act'` is trunc-exp's clamped slope or softplus's sigmoid, as the activations'
//! own backward passes define them). The compositing runs in f64 for both dtypes; the
//! networks in the storage dtype.
//!
//! ## Execution
//! The op computes the loss and the parameter gradient in its forward pass and keeps the
//! gradient; its backward pass scales it by the loss's upstream gradient. Rays are
//! grouped into tiles of at most [`TILE`] samples (a longer ray is a tile of its own,
//! whose sub-tiles are run forward, composited, then recomputed in the backward pass)
//! and into chunks of at most [`CHUNK`] samples with one gradient accumulator each,
//! summed in chunk order: the result does not depend on the thread count.

use super::composite::X_MAX;
use super::dispatch::{cpu_fwd, CpuKernel, Real};
use super::mlp::{sum_chunks, Params, Rows, CHUNK, TILE};
use super::nerf::{FusedNerf, NerfScratch};
use super::parallel::for_each_init;
use crate::numerics::{scalar_sigmoid, scalar_softplus, trunc_exp_slope, trunc_exp_value};
use candle_core::{CpuStorage, CustomOp3, Layout, Shape, Tensor, WithDType};
use std::sync::{Arc, Mutex};

/// The density activation of [`crate::volume::DensityActivation`], with its shift.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Density {
    TruncExp(f64),
    Softplus(f64),
}

/// Columns of the op's per-ray input: unit direction, target colour, background colour.
pub(crate) const RAY_COLUMNS: usize = 9;
/// Columns of the op's per-sample input: position, length δ.
pub(crate) const SAMPLE_COLUMNS: usize = 4;

/// An encoding the op evaluates row by row inside its tiles (implemented by the encoding
/// module's row encoder: the identity, or frequencies `2ᵏπ`).
pub(crate) trait RowEncode: Clone + Send + Sync {
    /// Output columns per row.
    fn out_dim(&self) -> usize;
    /// Encodes the rows `x: [rows, in]` into `out: [rows, out_dim]`.
    fn encode<T: WithDType>(&mut self, x: &[T], out: &mut [T]);
    /// The encoding as the CUDA kernels evaluate it: `(L, include_input)` of the
    /// frequencies `2ᵏπ`, `k < L`; the identity is `(0, true)`.
    #[cfg_attr(not(feature = "cuda"), allow(dead_code))]
    fn frequency_spec(&self) -> (usize, bool);
}

/// The op on `(samples [M, 4], rays [R, 9], params)`; output the loss, shape `[]`.
pub(crate) struct FusedNerfLoss<E> {
    nets: FusedNerf,
    position: E,
    direction: E,
    density: Density,
    /// Ray `r`'s samples are rows `offsets[r]..offsets[r + 1]`.
    offsets: Arc<[usize]>,
    opaque_last: bool,
    /// The parameter gradient the forward pass computed, for the backward pass.
    grad: Mutex<Option<CpuStorage>>,
    /// The same, computed by the CUDA path.
    #[cfg(feature = "cuda")]
    grad_cuda: Mutex<Option<candle_core::CudaStorage>>,
    /// The rays' mean and largest opacity `Σᵢ wᵢ` in the last forward pass, for the
    /// caller (shared: the op itself moves into candle's graph).
    opacity: Arc<Mutex<Option<[f64; 2]>>>,
}

/// What one chunk of rays contributes: its loss (not yet divided by 3R), whether every
/// raw output was finite, and the sum and the largest of its rays' opacities.
#[derive(Clone, Copy)]
struct ChunkLoss {
    loss: f64,
    finite: bool,
    opacity_sum: f64,
    opacity_max: f64,
}

impl Default for ChunkLoss {
    fn default() -> Self {
        Self {
            loss: 0.0,
            finite: true,
            opacity_sum: 0.0,
            opacity_max: 0.0,
        }
    }
}

/// Per-worker scratch.
struct LossScratch<T, E> {
    nets: NerfScratch<T>,
    position: E,
    direction: E,
    /// A sub-tile's encoded positions and its rows' encoded directions.
    ep: Vec<T>,
    ed: Vec<T>,
    /// The group's rays' unit directions and their encodings.
    dirs: Vec<T>,
    ed_rays: Vec<T>,
    /// The group's raw outputs (4 per sample) and their gradients.
    raw: Vec<f64>,
    gy: Vec<T>,
    /// Per-sample compositing quantities of one ray.
    ray: RayScratch,
}

#[derive(Default)]
struct RayScratch {
    delta: Vec<f64>,
    sigma: Vec<f64>,
    slope: Vec<f64>,
    t: Vec<f64>,
    w: Vec<f64>,
    decay: Vec<f64>,
    colour: Vec<f64>,
}

/// Greedy groups of consecutive rays of `offsets` whose samples total at most `cap`
/// (a ray longer than `cap` alone): `(first ray, end ray)` pairs covering `rays`.
fn groups(offsets: &[usize], rays: std::ops::Range<usize>, cap: usize) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut start = rays.start;
    for r in rays.clone() {
        if r > start && offsets[r + 1] - offsets[start] > cap {
            out.push((start, r));
            start = r;
        }
    }
    if start < rays.end {
        out.push((start, rays.end));
    }
    out
}

impl<E: RowEncode> FusedNerfLoss<E> {
    /// The op for `nets` with encoders of its positions and unit directions, `None` when
    /// their widths are not the networks' input widths.
    pub(crate) fn new(
        nets: FusedNerf,
        (position, direction): (E, E),
        density: Density,
        offsets: Arc<[usize]>,
        opaque_last: bool,
    ) -> Option<Self> {
        let (dd, _, _) = nets.widths();
        (position.out_dim() == nets.trunk.a0 && direction.out_dim() == dd).then(|| Self {
            nets,
            position,
            direction,
            density,
            offsets,
            opaque_last,
            grad: Mutex::new(None),
            #[cfg(feature = "cuda")]
            grad_cuda: Mutex::new(None),
            opacity: Arc::default(),
        })
    }

    /// Where the forward pass leaves the rays' mean and largest opacity.
    pub(crate) fn opacity_slot(&self) -> Arc<Mutex<Option<[f64; 2]>>> {
        Arc::clone(&self.opacity)
    }

    fn n_rays(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    fn scratch<T: Real>(&self) -> LossScratch<T, E> {
        let (dd, _, _) = self.nets.widths();
        let z = T::from_f64(0.0);
        LossScratch {
            nets: self.nets.scratch(),
            position: self.position.clone(),
            direction: self.direction.clone(),
            ep: vec![z; TILE * self.nets.trunk.a0],
            ed: vec![z; TILE * dd],
            dirs: Vec::new(),
            ed_rays: Vec::new(),
            raw: Vec::new(),
            gy: Vec::new(),
            ray: RayScratch::default(),
        }
    }

    /// Encodes sub-tile rows `rows` (group-relative, the group starting at ray `g0`) into
    /// `sc.ep`, `sc.ed`, and runs the trunk on them (leaving its activations and the
    /// head's input in `sc.nets`).
    fn trunk_rows<T: Real>(
        &self,
        samples: &[T],
        (g0, base): (usize, usize),
        rows: std::ops::Range<usize>,
        pt: Params<'_, T>,
        sc: &mut LossScratch<T, E>,
    ) {
        let (dd, _, _) = self.nets.widths();
        let a0p = self.nets.trunk.a0;
        let r = rows.len();
        let mut xyz = [T::from_f64(0.0); 3 * TILE];
        for (i, row) in rows.clone().enumerate() {
            let s = &samples[(base + row) * SAMPLE_COLUMNS..];
            xyz[3 * i..3 * i + 3].copy_from_slice(&s[..3]);
        }
        sc.position.encode(&xyz[..3 * r], &mut sc.ep[..r * a0p]);
        let mut ray = g0;
        for (i, row) in rows.enumerate() {
            while self.offsets[ray + 1] <= base + row {
                ray += 1;
            }
            let k = ray - g0;
            sc.ed[i * dd..(i + 1) * dd].copy_from_slice(&sc.ed_rays[k * dd..(k + 1) * dd]);
        }
        self.nets
            .trunk_tile(&sc.ep[..r * a0p], &sc.ed[..r * dd], pt, &mut sc.nets);
    }

    /// The loss (not yet divided by 3R) and the parameter gradient of the rays `rays`,
    /// accumulated into `gp`; `false` in the second place when some raw output was not
    /// finite; the sum and the largest of the rays' opacities.
    fn chunk<T: Real>(
        &self,
        samples: &[T],
        ray_data: &[T],
        (pt, ph): (Params<'_, T>, Params<'_, T>),
        rays: std::ops::Range<usize>,
        sc: &mut LossScratch<T, E>,
        gp: &mut [T],
    ) -> ChunkLoss {
        let (dd, t_out, _) = self.nets.widths();
        let inv = 1.0 / (3 * self.n_rays()) as f64;
        let (gpt, gph) = gp.split_at_mut(self.nets.trunk.n_params);
        let mut out = ChunkLoss::default();
        for (g0, g1) in groups(&self.offsets, rays, TILE) {
            let base = self.offsets[g0];
            let rows = self.offsets[g1] - base;
            // The rays' encoded directions.
            sc.dirs.clear();
            for r in g0..g1 {
                sc.dirs
                    .extend_from_slice(&ray_data[r * RAY_COLUMNS..r * RAY_COLUMNS + 3]);
            }
            sc.ed_rays.resize((g1 - g0) * dd, T::from_f64(0.0));
            sc.direction.encode(&sc.dirs, &mut sc.ed_rays);
            // Forward, sub-tile by sub-tile.
            sc.raw.resize(4 * rows, 0.0);
            sc.gy.resize(4 * rows, T::from_f64(0.0));
            for s in (0..rows).step_by(TILE) {
                let r = TILE.min(rows - s);
                self.trunk_rows(samples, (g0, base), s..s + r, pt, sc);
                let nets = &mut sc.nets;
                self.nets.head.forward_tile(
                    &nets.ha0,
                    ph,
                    Rows::plain(r),
                    &mut nets.head,
                    &mut nets.yh,
                );
                for i in 0..r {
                    let o = &mut sc.raw[4 * (s + i)..4 * (s + i + 1)];
                    o[0] = nets.yt[i * t_out].to_f64();
                    for k in 0..3 {
                        o[1 + k] = nets.yh[3 * i + k].to_f64();
                    }
                }
            }
            out.finite &= sc.raw.iter().all(|v| v.is_finite());
            // Compositing, the loss and the raw outputs' gradients, ray by ray.
            for ray in g0..g1 {
                let (a, b) = (self.offsets[ray] - base, self.offsets[ray + 1] - base);
                let data = &ray_data[ray * RAY_COLUMNS..(ray + 1) * RAY_COLUMNS];
                sc.ray.delta.clear();
                sc.ray
                    .delta
                    .extend((a..b).map(|i| samples[(base + i) * SAMPLE_COLUMNS + 3].to_f64()));
                let (loss, opacity) = self.ray_loss(
                    &sc.raw[4 * a..4 * b],
                    data,
                    inv,
                    &mut sc.ray,
                    &mut sc.gy[4 * a..4 * b],
                );
                out.loss += loss;
                out.opacity_sum += opacity;
                out.opacity_max = out.opacity_max.max(opacity);
            }
            // Backward, sub-tile by sub-tile (a single sub-tile's forward pass is still in
            // the scratch).
            let single = rows <= TILE;
            for s in (0..rows).step_by(TILE) {
                let r = TILE.min(rows - s);
                if !single {
                    self.trunk_rows(samples, (g0, base), s..s + r, pt, sc);
                }
                let LossScratch { nets, ep, gy, .. } = sc;
                self.nets.backward_tile(
                    &ep[..r * self.nets.trunk.a0],
                    (pt, ph),
                    &gy[4 * s..4 * (s + r)],
                    nets,
                    (&mut *gpt, &mut *gph),
                    (None, None),
                    !single,
                );
            }
        }
        out
    }

    /// One ray's squared error `‖C − C*‖²` and its opacity `Σᵢ wᵢ`, and the gradient of
    /// `inv·‖C − C*‖²` w.r.t. its raw outputs `raw: [S, 4]`, written to `gy` (module
    /// docs).
    fn ray_loss<T: Real>(
        &self,
        raw: &[f64],
        data: &[T],
        inv: f64,
        sc: &mut RayScratch,
        gy: &mut [T],
    ) -> (f64, f64) {
        let n = sc.delta.len();
        let f32_out = std::mem::size_of::<T>() == 4;
        let target: [f64; 3] = std::array::from_fn(|k| data[3 + k].to_f64());
        let bg: [f64; 3] = std::array::from_fn(|k| data[6 + k].to_f64());
        sc.sigma.resize(n, 0.0);
        sc.slope.resize(n, 0.0);
        sc.t.resize(n, 0.0);
        sc.w.resize(n, 0.0);
        sc.decay.resize(n, 0.0);
        sc.colour.resize(3 * n, 0.0);
        let mut colour = [0.0; 3];
        let (mut optical, mut opacity) = (0.0f64, 0.0f64);
        for i in 0..n {
            let (sigma, slope) = self.activate(raw[4 * i], f32_out);
            (sc.sigma[i], sc.slope[i]) = (sigma, slope);
            let x = (sigma * sc.delta[i]).min(X_MAX);
            let last = self.opaque_last && i + 1 == n;
            let alpha = if last { 1.0 } else { -(-x).exp_m1() };
            sc.t[i] = (-optical).exp();
            sc.decay[i] = if last { 0.0 } else { (-x).exp() };
            optical += x;
            let w = sc.t[i] * alpha;
            sc.w[i] = w;
            opacity += w;
            for k in 0..3 {
                let c = 1.0 / (1.0 + (-raw[4 * i + 1 + k]).exp());
                sc.colour[3 * i + k] = c;
                colour[k] += w * c;
            }
        }
        let mut g_colour = [0.0; 3];
        let mut loss = 0.0;
        for k in 0..3 {
            let d = colour[k] + (1.0 - opacity) * bg[k] - target[k];
            loss += d * d;
            g_colour[k] = 2.0 * d * inv;
        }
        let mut suffix = 0.0;
        for j in (0..n).rev() {
            let c = &sc.colour[3 * j..3 * j + 3];
            let u: f64 = (0..3).map(|k| g_colour[k] * (c[k] - bg[k])).sum();
            let gx = u * sc.t[j] * sc.decay[j] - suffix;
            suffix += u * sc.w[j];
            let g_sigma = if sc.sigma[j] * sc.delta[j] < X_MAX {
                gx * sc.delta[j]
            } else {
                0.0
            };
            let g = &mut gy[4 * j..4 * j + 4];
            g[0] = T::from_f64(g_sigma * sc.slope[j]);
            for k in 0..3 {
                g[1 + k] = T::from_f64(sc.w[j] * g_colour[k] * c[k] * (1.0 - c[k]));
            }
        }
        (loss, opacity)
    }

    /// `(σ, ∂σ/∂ρ)` at raw output `ρ`, the shifted argument rounded to the storage dtype
    /// as the composed path rounds it. Trunc-exp's value and slope are
    /// [`crate::numerics::trunc_exp`]'s scalar rule evaluated in the storage dtype, as the
    /// composed path evaluates them.
    fn activate(&self, raw: f64, f32_out: bool) -> (f64, f64) {
        let round = |v: f64| if f32_out { f64::from(v as f32) } else { v };
        match self.density {
            Density::TruncExp(shift) => {
                let z = round(raw + round(shift));
                if f32_out {
                    let z = z as f32;
                    (f64::from(trunc_exp_value(z)), f64::from(trunc_exp_slope(z)))
                } else {
                    (trunc_exp_value(z), trunc_exp_slope(z))
                }
            }
            Density::Softplus(shift) => {
                let z = round(raw + round(shift));
                (round(scalar_softplus!(z, 1.0)), scalar_sigmoid!(z))
            }
        }
    }

    /// The loss and the parameter gradient.
    fn run<T: Real>(
        &self,
        samples: &[T],
        ray_data: &[T],
        params: &[T],
    ) -> candle_core::Result<(T, Vec<T>, [f64; 2])> {
        let wt = self.nets.transposed(params);
        let (pt, ph) = self.nets.split(params, &wt);
        let np = params.len();
        let chunks = groups(&self.offsets, 0..self.n_rays(), CHUNK);
        let mut gp = vec![T::from_f64(0.0); chunks.len().max(1) * np];
        let mut partial = vec![ChunkLoss::default(); chunks.len()];
        let items: Vec<_> = gp.chunks_mut(np).zip(&mut partial).zip(chunks).collect();
        for_each_init(
            items,
            || self.scratch::<T>(),
            |sc, ((gp, out), (a, b))| {
                *out = self.chunk(samples, ray_data, (pt, ph), a..b, sc, gp);
            },
        );
        if partial.iter().any(|p| !p.finite) {
            candle_core::bail!(
                "fused NeRF loss: the network's raw output is not finite (NaN or infinite parameters?)"
            )
        }
        sum_chunks(&mut gp, np);
        let loss: f64 = partial.iter().map(|p| p.loss).sum();
        let opacity_sum: f64 = partial.iter().map(|p| p.opacity_sum).sum();
        let opacity_max = partial.iter().map(|p| p.opacity_max).fold(0.0, f64::max);
        let opacity = [opacity_sum / self.n_rays().max(1) as f64, opacity_max];
        Ok((
            T::from_f64(loss / (3 * self.n_rays()).max(1) as f64),
            gp,
            opacity,
        ))
    }

    fn check(&self, n_samples: usize, n_rays: usize, n_params: usize) -> candle_core::Result<()> {
        let m = self.offsets.last().copied().unwrap_or(0);
        if n_samples != m * SAMPLE_COLUMNS
            || n_rays != self.n_rays() * RAY_COLUMNS
            || n_params != self.nets.trunk.n_params + self.nets.head.n_params
        {
            candle_core::bail!(
                "fused NeRF loss: {n_samples} sample values, {n_rays} ray values or {n_params} parameters do not match {m} samples on {} rays",
                self.n_rays()
            )
        }
        Ok(())
    }
}

impl<E: RowEncode> CpuKernel<3> for FusedNerfLoss<E> {
    const NAME: &'static str = "fused NeRF loss";

    /// Inputs `(samples [M, 4], rays [R, 9], params)`; output the loss `[]`. The
    /// parameter gradient is kept for [`CustomOp3::bwd`].
    fn forward<T: Real>(&self, [x, y, p]: [&[T]; 3]) -> candle_core::Result<(Vec<T>, Shape)> {
        self.check(x.len(), y.len(), p.len())?;
        let (loss, gp, opacity) = self.run(x, y, p)?;
        *self
            .opacity
            .lock()
            .map_err(|_| candle_core::Error::Msg("fused NeRF loss: poisoned".into()))? =
            Some(opacity);
        let mut slot = self
            .grad
            .lock()
            .map_err(|_| candle_core::Error::Msg("fused NeRF loss: poisoned".into()))?;
        *slot = Some(T::storage(gp));
        Ok((vec![loss], Shape::from(())))
    }
}

impl<E: RowEncode> CustomOp3 for FusedNerfLoss<E> {
    fn name(&self) -> &'static str {
        "nf-fused-nerf-loss"
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
        cpu_fwd(self, [(s1, l1), (s2, l2), (s3, l3)])
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> candle_core::Result<(candle_core::CudaStorage, Shape)> {
        self.cuda_loss([(s1, l1), (s2, l2), (s3, l3)])
    }

    fn bwd(
        &self,
        _samples: &Tensor,
        _rays: &Tensor,
        params: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        #[cfg(feature = "cuda")]
        if params.device().is_cuda() {
            let gp = self
                .grad_cuda
                .lock()
                .map_err(|_| candle_core::Error::Msg("fused NeRF loss: poisoned".into()))?
                .take()
                .ok_or_else(|| {
                    candle_core::Error::Msg(
                        "fused NeRF loss: backward pass before the forward pass".into(),
                    )
                })?;
            let gp = Tensor::from_storage(
                candle_core::Storage::Cuda(gp),
                params.shape().clone(),
                candle_core::op::BackpropOp::none(),
                false,
            );
            let gp = gp.broadcast_mul(&grad.to_dtype(params.dtype())?)?;
            return Ok((None, None, Some(gp)));
        }
        let slot = self
            .grad
            .lock()
            .map_err(|_| candle_core::Error::Msg("fused NeRF loss: poisoned".into()))?;
        let gp = match slot.as_ref() {
            Some(CpuStorage::F32(v)) => Tensor::from_slice(v, params.shape(), params.device())?,
            Some(CpuStorage::F64(v)) => Tensor::from_slice(v, params.shape(), params.device())?,
            _ => candle_core::bail!("fused NeRF loss: backward pass before the forward pass"),
        };
        let gp = gp.broadcast_mul(&grad.to_dtype(params.dtype())?)?;
        Ok((None, None, Some(gp)))
    }
}

#[cfg(feature = "cuda")]
#[path = "cuda/nerf_loss.rs"]
mod cuda;
