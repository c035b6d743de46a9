//! The Occupancy Networks decoder (Mescheder et al. 2019, "CBatchNorm" decoder) with
//! conditional normalisation that does not depend on batch composition at inference.
//!
//! `f(p, c)`: `net = W_p p + b_p`; then `blocks` conditional ResNet blocks
//! `net ← net + fc₁(ReLU(CN₁(fc₀(ReLU(CN₀(net, c))), c)))`; then
//! `logit = fc_out(ReLU(CN(net, c)))`. `CN(x, c) = γ(c) ⊙ x̂ + β(c)` with `γ, β` linear
//! in the code (initialised to `γ = 1`, `β = 0`) and `fc₁` initialised to zero, so the
//! network starts as a plain MLP of `p`.
//!
//! `x̂` is where the reference implementation leaks batch statistics into inference
//! (ONet issue #93: results change with how many points are queried together). Here:
//! * [`NormMode::Train`]: `x̂ = (x − μ_B)/√(σ²_B + ε)` with the mean and (biased)
//!   variance over the points of the call, and the running statistics are updated,
//!   `r ← (1 − m) r + m·stat` (unbiased variance, as BatchNorm);
//! * [`NormMode::Eval`] (the default): `x̂ = (x − r_μ)/√(r_σ² + ε)`, a per-point affine
//!   map, so a point's logit is the same whether it is queried alone or with 10 000
//!   others. Linear layers are evaluated on fixed blocks of [`ONET_BLOCK`] rows (the last
//!   one zero-padded), so even the matrix-multiply kernel sees the same shapes; the
//!   result is bit-identical (tested).
//!
//! On the CPU, a training pass without spatial gradients runs the whole decoder as one
//! fused op (every layer's product, bias, normalisation, ReLU and residual sum, and one
//! backward pass through them and the batch statistics), the same function as the candle
//! ops it replaces ([`OnetConfig::force_reference`] keeps those).

use crate::error::{check_points, check_same, check_shape, Dim, Error, Result};
use crate::field::{ConditionalField, Inside};
use crate::kernels::{BufferPool, FusedOnet};
use crate::nn::weight_jvp;
use candle_core::{Tensor, D};
use candle_nn::{Init, VarBuilder};
use std::sync::{Arc, Mutex, PoisonError};

/// Rows per matrix-multiply block in [`NormMode::Eval`].
pub const ONET_BLOCK: usize = 256;

/// Settings of [`onet_decoder`].
#[derive(Clone, Debug, PartialEq)]
pub struct OnetConfig {
    /// Hidden width (ONet: 256).
    pub hidden: usize,
    /// Number of conditional ResNet blocks (ONet: 5).
    pub blocks: usize,
    /// Code dimension `D ≥ 1`.
    pub code_dim: usize,
    /// Running-statistics momentum `m` (BatchNorm's 0.1).
    pub momentum: f64,
    /// `ε` of the normalisation (1e-5).
    pub eps: f64,
    /// Run the training pass as candle ops even on the CPU, where it otherwise runs as
    /// one fused op (the crate's kernel `FusedOnet`, the same function; tests compare the
    /// two). Default `false`.
    pub force_reference: bool,
}

impl Default for OnetConfig {
    fn default() -> Self {
        Self {
            hidden: 256,
            blocks: 5,
            code_dim: 256,
            momentum: 0.1,
            eps: 1e-5,
            force_reference: false,
        }
    }
}

/// Which statistics the conditional normalisation uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NormMode {
    /// Batch statistics of the call; running statistics are updated.
    Train,
    /// Running statistics only (per-point, batch-independent).
    Eval,
}

#[derive(Debug)]
struct Linear {
    weight: Tensor,
    bias: Tensor,
}

impl Linear {
    fn new(vb: &VarBuilder, name: &str, input: usize, out: usize, zero: bool) -> Result<Self> {
        let vb = vb.pp(name);
        let bound = 1.0 / (input as f64).sqrt();
        let winit = if zero {
            Init::Const(0.0)
        } else {
            candle_nn::init::DEFAULT_KAIMING_NORMAL
        };
        Ok(Self {
            weight: vb.get_with_hints((out, input), "weight", winit)?,
            bias: vb.get_with_hints(
                out,
                "bias",
                Init::Uniform {
                    lo: -bound,
                    up: bound,
                },
            )?,
        })
    }

    fn with(vb: &VarBuilder, name: &str, input: usize, out: usize, bias: f64) -> Result<Self> {
        let vb = vb.pp(name);
        Ok(Self {
            weight: vb.get_with_hints((out, input), "weight", Init::Const(0.0))?,
            bias: vb.get_with_hints(out, "bias", Init::Const(bias))?,
        })
    }

    fn forward(&self, x: &Tensor, blocked: bool) -> Result<Tensor> {
        let wt = self.weight.t()?;
        let n = x.dim(0)?;
        if !blocked || n == 0 {
            return Ok(x.matmul(&wt)?.broadcast_add(&self.bias)?);
        }
        let mut parts = Vec::with_capacity(n.div_ceil(ONET_BLOCK));
        let mut start = 0;
        while start < n {
            let len = ONET_BLOCK.min(n - start);
            let mut blk = x.narrow(0, start, len)?;
            if len < ONET_BLOCK {
                let pad = Tensor::zeros((ONET_BLOCK - len, x.dim(1)?), x.dtype(), x.device())?;
                blk = Tensor::cat(&[&blk, &pad], 0)?;
            }
            parts.push(blk.matmul(&wt)?.narrow(0, 0, len)?);
            start += len;
        }
        Ok(Tensor::cat(&parts, 0)?.broadcast_add(&self.bias)?)
    }
}

#[derive(Debug)]
struct CondNorm {
    gamma: Linear,
    beta: Linear,
    running_mean: Mutex<Tensor>,
    running_var: Mutex<Tensor>,
}

#[derive(Debug)]
struct Block {
    norm0: CondNorm,
    fc0: Linear,
    norm1: CondNorm,
    fc1: Linear,
}

/// The ONet decoder; build it with [`onet_decoder`].
///
/// As a [`ConditionalField`] it has one output channel (the occupancy logit, inside where
/// positive) and spatial gradients by forward-mode tangents; in [`NormMode::Train`] the
/// batch statistics are treated as constants of that propagation.
///
/// Memory: a fused training pass on the CPU keeps about `2·blocks + 4` row buffers of
/// `N × hidden` values (each block's input and hidden rows, and the gradients in flight;
/// about 120 MB in f32 at the shape prior's 16 384 points, width 128, 5 blocks), and the
/// decoder holds them between calls for the next pass instead of returning them to the
/// allocator.
#[derive(Debug)]
pub struct OnetDecoder {
    fc_p: Linear,
    blocks: Vec<Block>,
    norm_out: CondNorm,
    fc_out: Linear,
    config: OnetConfig,
    mode: Mutex<NormMode>,
    /// The fused training pass's row buffers, kept between steps.
    scratch: Arc<BufferPool>,
}

/// Builds an [`OnetDecoder`] from `vb` (variables `fc_p`, `block{i}.{fc0,fc1,norm0,norm1}`,
/// `norm_out`, `fc_out`; running statistics are plain tensors, not variables). Starts in
/// [`NormMode::Eval`].
///
/// # Errors
/// Naming `config.blocks` when the layers' weights (about `hidden²` values each) pass the
/// allocation limit of 2³³ bytes (8 GiB), checked before any layer is built. Also:
/// A zero `hidden`, `blocks` or `code_dim`; `momentum ∉ [0, 1]`; `eps ≤ 0`; errors of
/// the `VarBuilder`.
pub fn onet_decoder(config: &OnetConfig, vb: VarBuilder) -> Result<OnetDecoder> {
    for (name, v) in [
        ("config.hidden", config.hidden),
        ("config.blocks", config.blocks),
        ("config.code_dim", config.code_dim),
    ] {
        if v == 0 {
            return Err(Error::invalid(name, "at least 1", "0"));
        }
    }
    if !(0.0..=1.0).contains(&config.momentum) {
        return Err(Error::invalid(
            "config.momentum",
            "a number in [0, 1]",
            format!("{}", config.momentum),
        ));
    }
    if !(config.eps > 0.0 && config.eps.is_finite()) {
        return Err(Error::invalid(
            "config.eps",
            "a number > 0",
            format!("{}", config.eps),
        ));
    }
    let (h, d) = (config.hidden, config.code_dim);
    let norm = |name: &str| -> Result<CondNorm> {
        let nvb = vb.pp(name);
        Ok(CondNorm {
            gamma: Linear::with(&nvb, "gamma", d, h, 1.0)?,
            beta: Linear::with(&nvb, "beta", d, h, 0.0)?,
            running_mean: Mutex::new(Tensor::zeros(h, vb.dtype(), vb.device())?),
            running_var: Mutex::new(Tensor::ones(h, vb.dtype(), vb.device())?),
        })
    };
    let params = config
        .hidden
        .saturating_mul(config.hidden)
        .saturating_mul(2);
    crate::limits::check_layers(
        "config.blocks",
        config.blocks,
        params,
        vb.dtype().size_in_bytes(),
    )?;
    let mut blocks = Vec::with_capacity(config.blocks);
    for b in 0..config.blocks {
        let bvb = vb.pp(format!("block{b}"));
        let nb = |name: &str| -> Result<CondNorm> {
            let nvb = bvb.pp(name);
            Ok(CondNorm {
                gamma: Linear::with(&nvb, "gamma", d, h, 1.0)?,
                beta: Linear::with(&nvb, "beta", d, h, 0.0)?,
                running_mean: Mutex::new(Tensor::zeros(h, vb.dtype(), vb.device())?),
                running_var: Mutex::new(Tensor::ones(h, vb.dtype(), vb.device())?),
            })
        };
        blocks.push(Block {
            norm0: nb("norm0")?,
            fc0: Linear::new(&bvb, "fc0", h, h, false)?,
            norm1: nb("norm1")?,
            fc1: Linear::new(&bvb, "fc1", h, h, true)?,
        });
    }
    Ok(OnetDecoder {
        fc_p: Linear::new(&vb, "fc_p", 3, h, false)?,
        blocks,
        norm_out: norm("norm_out")?,
        fc_out: Linear::new(&vb, "fc_out", h, 1, false)?,
        config: config.clone(),
        mode: Mutex::new(NormMode::Eval),
        scratch: Arc::default(),
    })
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl OnetDecoder {
    /// Switches between batch statistics (training) and running statistics (inference).
    pub fn set_mode(&self, mode: NormMode) {
        *lock(&self.mode) = mode;
    }

    /// The current [`NormMode`].
    fn mode(&self) -> NormMode {
        *lock(&self.mode)
    }

    /// The batch mean and (biased) variance `[H]` of rows `x: [N, H]`, and the running
    /// statistics updated with them (`r ← (1 − m) r + m·stat`, the variance unbiased).
    fn batch_stats(&self, n: &CondNorm, x: &Tensor) -> Result<(Tensor, Tensor)> {
        let mean = x.mean(0)?;
        let var = x.broadcast_sub(&mean)?.sqr()?.mean(0)?;
        self.update_running(n, &mean.detach(), &var.detach(), x.dim(0)?)?;
        Ok((mean, var))
    }

    /// `r ← (1 − m) r + m·stat` for the batch `mean` and biased `var` (`[H]`) of `rows`
    /// rows, the variance made unbiased.
    fn update_running(&self, n: &CondNorm, mean: &Tensor, var: &Tensor, rows: usize) -> Result<()> {
        let (mut rm, mut rv) = (lock(&n.running_mean), lock(&n.running_var));
        (*rm, *rv) = running_update((&rm, &rv), (mean, var), rows, self.config.momentum)?;
        Ok(())
    }

    /// `x̂` and the per-feature scale `∂x̂/∂x` (`[H]`) of one normalisation layer.
    fn normalize(&self, n: &CondNorm, x: &Tensor, mode: NormMode) -> Result<(Tensor, Tensor)> {
        let (mean, var) = match mode {
            NormMode::Eval => (lock(&n.running_mean).clone(), lock(&n.running_var).clone()),
            NormMode::Train => self.batch_stats(n, x)?,
        };
        let inv = (var + self.config.eps)?.sqrt()?.recip()?;
        Ok((x.broadcast_sub(&mean)?.broadcast_mul(&inv)?, inv))
    }

    /// Whether the training pass on `points` runs as the fused CPU op.
    fn fused(&self, points: &Tensor, mode: NormMode) -> bool {
        mode == NormMode::Train
            && !self.config.force_reference
            && crate::kernels::cpu_fused_for(points)
            && points.dim(0).is_ok_and(|n| n > 0)
    }

    /// The normalisation layers in the fused op's order: each block's two, then the
    /// output's.
    fn norms(&self) -> Vec<&CondNorm> {
        self.blocks
            .iter()
            .flat_map(|b| [&b.norm0, &b.norm1])
            .chain([&self.norm_out])
            .collect()
    }

    /// The training pass's logits `[N]` as the fused op ([`FusedOnet`]), one code per
    /// `group` points; the batch statistics then update the running ones.
    fn fused_logits(&self, points: &Tensor, codes: &Tensor, group: usize) -> Result<Tensor> {
        let n = points.dim(0)?;
        let norms = self.norms();
        let mut cond = Vec::with_capacity(2 * norms.len());
        for nm in &norms {
            cond.push(nm.gamma.forward(codes, false)?);
            cond.push(nm.beta.forward(codes, false)?);
        }
        let cond = Tensor::cat(&cond, 0)?.contiguous()?;
        let linears = [&self.fc_p]
            .into_iter()
            .chain(self.blocks.iter().flat_map(|b| [&b.fc0, &b.fc1]))
            .chain([&self.fc_out]);
        let mut params = Vec::new();
        for l in linears {
            params.push(l.weight.flatten_all()?);
            params.push(l.bias.clone());
        }
        let params = Tensor::cat(&params, 0)?.contiguous()?;
        let op = FusedOnet::new(
            (n, self.config.hidden, self.config.blocks),
            group,
            self.config.eps,
            Arc::clone(&self.scratch),
        );
        let saved = op.saved();
        let logits = points.contiguous()?.apply_op3(&cond, &params, op)?;
        let column = |v: Vec<f64>| -> Result<Tensor> {
            Ok(Tensor::from_vec(v, self.config.hidden, points.device())?
                .to_dtype(points.dtype())?)
        };
        for (nm, st) in norms.into_iter().zip(saved) {
            let stats = lock(&st).clone();
            if let Some(st) = stats {
                self.update_running(nm, &column(st.mean)?, &column(st.var)?, n)?;
            }
        }
        Ok(logits)
    }

    /// Conditional normalisation and ReLU, with forward-mode tangents `dx: [3, N, H]`.
    fn cn_relu(
        &self,
        n: &CondNorm,
        x: &Tensor,
        dx: Option<&Tensor>,
        (codes, group): (&Tensor, usize),
        mode: NormMode,
        blocked: bool,
    ) -> Result<(Tensor, Option<Tensor>)> {
        let (xh, inv) = self.normalize(n, x, mode)?;
        // γ(c) and β(c) once per code, then repeated over its `group` points.
        let per_point = |t: Tensor| -> Result<Tensor> {
            if group == 1 {
                return Ok(t);
            }
            let (g, h) = t.dims2()?;
            Ok(t.unsqueeze(1)?
                .broadcast_as((g, group, h))?
                .reshape((g * group, h))?)
        };
        let gamma = per_point(n.gamma.forward(codes, blocked)?)?;
        let beta = per_point(n.beta.forward(codes, blocked)?)?;
        let y = ((xh * &gamma)? + beta)?;
        let mask = y.gt(0.0)?.to_dtype(y.dtype())?;
        let out = y.relu()?;
        let dout = match dx {
            Some(dx) => {
                let scale = (gamma.broadcast_mul(&inv)? * &mask)?;
                Some(dx.broadcast_mul(&scale.unsqueeze(0)?)?)
            }
            None => None,
        };
        Ok((out, dout))
    }

    fn run(
        &self,
        points: &Tensor,
        codes: &Tensor,
        tangents: bool,
    ) -> Result<(Tensor, Option<Tensor>)> {
        // A code broadcast from one row (stride 0 along the points, as `Conditioned`
        // binds a `[D]` code) enters once: γ(c), β(c) from one row, not N equal ones.
        let n = points.dims().first().copied().unwrap_or(0);
        if n > 1 && codes.rank() == 2 && codes.dim(0)? == n && codes.stride()[0] == 0 {
            return self.run_grouped(points, &codes.narrow(0, 0, 1)?, n, tangents);
        }
        self.run_grouped(points, codes, 1, tangents)
    }

    /// [`OnetDecoder::run`] with one code per `group` consecutive points: `codes`
    /// `[N / group, D]`.
    fn run_grouped(
        &self,
        points: &Tensor,
        codes: &Tensor,
        group: usize,
        tangents: bool,
    ) -> Result<(Tensor, Option<Tensor>)> {
        let n = check_points(points, "points")?;
        check_same(codes, "codes", points, "points")?;
        if group == 0 || !n.is_multiple_of(group) {
            return Err(Error::invalid(
                "points",
                format!("a multiple of {group} points (one code per {group})"),
                n.to_string(),
            ));
        }
        check_shape(
            codes,
            "codes",
            &[Dim::Is(n / group), Dim::Is(self.config.code_dim)],
        )?;
        let mode = self.mode();
        if !tangents && self.fused(points, mode) {
            return Ok((self.fused_logits(points, codes, group)?, None));
        }
        let blocked = mode == NormMode::Eval;
        let lin_t = |l: &Linear, d: &Tensor| weight_jvp(&l.weight, d);
        let mut net = self.fc_p.forward(points, blocked)?;
        let mut dnet = if tangents {
            // ∂(W p)/∂p_j = column j of W, for every point: [3, N, H].
            let w = self.fc_p.weight.t()?; // [3, H]
            Some(
                w.unsqueeze(1)?
                    .broadcast_as((3, n, self.config.hidden))?
                    .contiguous()?,
            )
        } else {
            None
        };
        for b in &self.blocks {
            let (a, da) =
                self.cn_relu(&b.norm0, &net, dnet.as_ref(), (codes, group), mode, blocked)?;
            let hmid = b.fc0.forward(&a, blocked)?;
            let dh = match &da {
                Some(d) => Some(lin_t(&b.fc0, d)?),
                None => None,
            };
            let (a2, da2) =
                self.cn_relu(&b.norm1, &hmid, dh.as_ref(), (codes, group), mode, blocked)?;
            net = (net + b.fc1.forward(&a2, blocked)?)?;
            dnet = match (dnet, &da2) {
                (Some(dn), Some(d)) => Some((dn + lin_t(&b.fc1, d)?)?),
                _ => None,
            };
        }
        let (a, da) = self.cn_relu(
            &self.norm_out,
            &net,
            dnet.as_ref(),
            (codes, group),
            mode,
            blocked,
        )?;
        let logit = self.fc_out.forward(&a, blocked)?.squeeze(D::Minus1)?;
        let grad = match da {
            Some(d) => Some(lin_t(&self.fc_out, &d)?.squeeze(2)?.t()?.contiguous()?),
            None => None,
        };
        Ok((logit, grad))
    }

    /// Occupancy logits in either layout, same dtype (f32/f64) and device throughout:
    /// - **per point**: `points: [N, 3]` with `codes: [N, D]`, logits `[N]`;
    /// - **per shape**: `points: [B, Q, 3]` with one code per shape, `codes: [B, D]`,
    ///   logits `[B, Q]`: the per-point logits of the points with each shape's code
    ///   repeated, but the conditional normalisation's `γ(c)`, `β(c)` computed once per
    ///   shape (ONet's batches: `2·(2·blocks + 1)` products of `[B, D]·[D, H]` instead of
    ///   `[B·Q, D]·[D, H]`).
    ///
    /// The normalisation's batch statistics run over all the points (`N`, or `B·Q`); in
    /// [`NormMode::Train`] the call updates the running statistics. Differentiable w.r.t.
    /// the parameters, the points and the codes.
    ///
    /// ```
    /// use candle_core::{DType, Device, Tensor};
    /// use candle_nn::VarMap;
    /// use neural_fields::nn::build_seeded;
    /// use neural_fields::occupancy::{onet_decoder, OnetConfig};
    ///
    /// let config = OnetConfig { hidden: 16, blocks: 2, code_dim: 8, ..OnetConfig::default() };
    /// let dec = build_seeded(&VarMap::new(), DType::F64, &Device::Cpu, 0, |vb| onet_decoder(&config, vb))?;
    /// let points = Tensor::rand(-0.5, 0.5, (2, 5, 3), &Device::Cpu)?;
    /// let codes = Tensor::rand(-1.0, 1.0, (2, 8), &Device::Cpu)?;
    /// let per_shape = dec.logits(&points, &codes)?; // [2, 5]
    /// let repeated = codes.unsqueeze(1)?.broadcast_as((2, 5, 8))?.reshape((10, 8))?;
    /// let per_point = dec.logits(&points.reshape((10, 3))?, &repeated)?.reshape((2, 5))?;
    /// assert!((per_shape - per_point)?.abs()?.max_all()?.to_scalar::<f64>()? < 1e-12);
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// `points` neither `[N, 3]` nor `[B, Q, 3]` with `Q ≥ 1`; `codes` not `[N, D]`
    /// (respectively `[B, D]`); dtypes or devices unlike.
    pub fn logits(&self, points: &Tensor, codes: &Tensor) -> Result<Tensor> {
        if points.rank() != 3 {
            return Ok(self.run(points, codes, false)?.0);
        }
        let d = check_shape(
            points,
            "points",
            &[Dim::Any("B"), Dim::Any("Q"), Dim::Is(3)],
        )?;
        if d[1] == 0 {
            return Err(Error::invalid(
                "points",
                "at least one point per shape",
                "Q = 0",
            ));
        }
        let flat = points.reshape((d[0] * d[1], 3))?;
        Ok(self
            .run_grouped(&flat, codes, d[1], false)?
            .0
            .reshape((d[0], d[1]))?)
    }
}

/// `ConditionalField` for a decoder with `config.code_dim` and a
/// `run(points, codes, tangents) -> (logits [N], Option<∇ logits [N, 3]>)`: one output
/// channel (the occupancy logit), inside where it is positive, spatial gradients by
/// forward-mode tangents.
macro_rules! logit_decoder_field {
    ($decoder:ty) => {
        impl ConditionalField for $decoder {
            fn code_dim(&self) -> usize {
                self.config.code_dim
            }

            fn out_dim(&self) -> usize {
                1
            }

            fn forward_with_code(&self, points: &Tensor, codes: &Tensor) -> Result<Tensor> {
                Ok(self.run(points, codes, false)?.0.unsqueeze(1)?)
            }

            fn value_and_grad_with_code(
                &self,
                points: &Tensor,
                codes: &Tensor,
            ) -> Result<(Tensor, Tensor)> {
                let (v, g) = self.run(points, codes, true)?;
                let g = g.ok_or_else(|| Error::invalid("points", "tangents", "none"))?;
                Ok((v, g))
            }

            fn inside(&self) -> Inside {
                Inside::Positive
            }
        }
    };
}

logit_decoder_field!(OnetDecoder);

/// Settings of [`simple_decoder`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SimpleDecoderConfig {
    /// Hidden width (ONet: 128).
    pub hidden: usize,
    /// Number of ResNet-FC blocks (ONet: 5).
    pub blocks: usize,
    /// Code dimension `D ≥ 1`.
    pub code_dim: usize,
}

impl Default for SimpleDecoderConfig {
    /// ONet's simple decoder: width 128, 5 blocks, 128-dimensional code.
    fn default() -> Self {
        Self {
            hidden: 128,
            blocks: 5,
            code_dim: 128,
        }
    }
}

/// ONet's simple decoder: the code is added once at the input,
/// `net = W_p p + W_c c + b`, then ResNet-FC blocks
/// `net ← net + W₁ ReLU(W₀ ReLU(net) + b₀) + b₁` (`W₁` zero-initialised, so each block
/// starts as the identity), then `logit = w_out · ReLU(net) + b_out`.
///
/// It has no normalisation, so a point's output does not depend on the other points
/// of the call (up to the rounding of the matrix products). Spatial gradients come by
/// forward mode (ReLU masks on the tangents) and are differentiable w.r.t. the weights;
/// being a ReLU network with an additive code, `∇ₚf` is piecewise constant in the code,
/// so a loss on normals gives the code no gradient (losses on values do). Build it with
/// [`simple_decoder`].
#[derive(Clone, Debug)]
pub struct SimpleDecoder {
    fc_p: candle_nn::Linear,
    fc_c: candle_nn::Linear,
    blocks: Vec<(candle_nn::Linear, candle_nn::Linear)>,
    fc_out: candle_nn::Linear,
    config: SimpleDecoderConfig,
}

/// Builds a [`SimpleDecoder`] from `vb` (`fc_p`, `fc_c`, `block{i}.fc_0`, `block{i}.fc_1`,
/// `fc_out`).
///
/// # Errors
/// Naming `config.blocks` when the layers' weights (about `hidden²` values each) pass the
/// allocation limit of 2³³ bytes (8 GiB), checked before any layer is built. Also:
/// A zero `hidden`, `blocks` or `code_dim` (naming `config.*`); errors of `vb`.
pub fn simple_decoder(config: &SimpleDecoderConfig, vb: VarBuilder) -> Result<SimpleDecoder> {
    for (name, v) in [
        ("config.hidden", config.hidden),
        ("config.blocks", config.blocks),
        ("config.code_dim", config.code_dim),
    ] {
        if v == 0 {
            return Err(Error::invalid(name, "at least 1", "0"));
        }
    }
    let h = config.hidden;
    let zero_linear = |vb: VarBuilder| -> Result<candle_nn::Linear> {
        let w = vb.get_with_hints((h, h), "weight", Init::Const(0.0))?;
        let b = vb.get_with_hints(h, "bias", Init::Const(0.0))?;
        Ok(candle_nn::Linear::new(w, Some(b)))
    };
    let params = config
        .hidden
        .saturating_mul(config.hidden)
        .saturating_mul(2);
    crate::limits::check_layers(
        "config.blocks",
        config.blocks,
        params,
        vb.dtype().size_in_bytes(),
    )?;
    let mut blocks = Vec::with_capacity(config.blocks);
    for i in 0..config.blocks {
        let bvb = vb.pp(format!("block{i}"));
        blocks.push((
            candle_nn::linear(h, h, bvb.pp("fc_0"))?,
            zero_linear(bvb.pp("fc_1"))?,
        ));
    }
    Ok(SimpleDecoder {
        fc_p: candle_nn::linear(3, h, vb.pp("fc_p"))?,
        fc_c: candle_nn::linear_no_bias(config.code_dim, h, vb.pp("fc_c"))?,
        blocks,
        fc_out: candle_nn::linear(h, 1, vb.pp("fc_out"))?,
        config: config.clone(),
    })
}

/// `ReLU(x)` and its tangent `ȧ ⊙ 𝟙[x ≥ 0]` (candle's ReLU derivative convention).
fn relu_jvp(x: &Tensor, dx: Option<&Tensor>) -> Result<(Tensor, Option<Tensor>)> {
    let dy = match dx {
        Some(dx) => Some(dx.broadcast_mul(&x.ge(0.0)?.to_dtype(x.dtype())?.unsqueeze(1)?)?),
        None => None,
    };
    Ok((x.relu()?, dy))
}

impl SimpleDecoder {
    fn run(
        &self,
        points: &Tensor,
        codes: &Tensor,
        tangents: bool,
    ) -> Result<(Tensor, Option<Tensor>)> {
        let n = check_points(points, "points")?;
        check_same(codes, "codes", points, "points")?;
        check_shape(codes, "codes", &[Dim::Is(n), Dim::Is(self.config.code_dim)])?;
        let mut net = (candle_nn::Module::forward(&self.fc_p, points)?
            + candle_nn::Module::forward(&self.fc_c, codes)?)?;
        let mut dnet = if tangents {
            let eye = Tensor::eye(3, points.dtype(), points.device())?
                .unsqueeze(0)?
                .broadcast_as((n, 3, 3))?
                .contiguous()?;
            Some(weight_jvp(self.fc_p.weight(), &eye)?)
        } else {
            None
        };
        for (fc0, fc1) in &self.blocks {
            let (a0, da0) = relu_jvp(&net, dnet.as_ref())?;
            let h = candle_nn::Module::forward(fc0, &a0)?;
            let dh = da0.map(|t| weight_jvp(fc0.weight(), &t)).transpose()?;
            let (a1, da1) = relu_jvp(&h, dh.as_ref())?;
            net = (net + candle_nn::Module::forward(fc1, &a1)?)?;
            if let (Some(d), Some(t)) = (dnet.as_ref(), da1) {
                dnet = Some((d + weight_jvp(fc1.weight(), &t)?)?);
            }
        }
        let (a, da) = relu_jvp(&net, dnet.as_ref())?;
        let logit = candle_nn::Module::forward(&self.fc_out, &a)?.squeeze(1)?;
        let grad = da
            .map(|t| -> Result<Tensor> { Ok(weight_jvp(self.fc_out.weight(), &t)?.squeeze(2)?) })
            .transpose()?;
        Ok((logit, grad))
    }

    /// Occupancy logits `[N]` for `points: [N, 3]` and `codes: [N, D]`, f32 or f64.
    /// Differentiable w.r.t. the weights, points and codes.
    ///
    /// # Errors
    /// Wrong shapes, dtypes or devices (naming `points` / `codes`).
    pub fn logits(&self, points: &Tensor, codes: &Tensor) -> Result<Tensor> {
        Ok(self.run(points, codes, false)?.0)
    }
}

logit_decoder_field!(SimpleDecoder);

/// Running statistics `(mean, var)` (`[H]` each) after one batch of `rows` rows:
/// `r ← (1 − m)·r + m·stat` for the batch `mean` and the biased batch `var` made
/// unbiased (times `rows/(rows − 1)` where `rows > 1`), as PyTorch's and candle-nn's batch
/// norms update theirs. Shared by the decoder's conditional norms and the image encoder's
/// fused batch norms.
pub(crate) fn running_update(
    (running_mean, running_var): (&Tensor, &Tensor),
    (mean, var): (&Tensor, &Tensor),
    rows: usize,
    m: f64,
) -> Result<(Tensor, Tensor)> {
    let unbiased = if rows > 1 {
        rows as f64 / (rows - 1) as f64
    } else {
        1.0
    };
    Ok((
        ((running_mean * (1.0 - m))? + (mean * m)?)?,
        ((running_var * (1.0 - m))? + (var * (m * unbiased))?)?,
    ))
}
