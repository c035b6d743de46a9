//! A configurable MLP whose spatial gradient is itself differentiable.
//!
//! ## Math
//! With input `a₀ = [γ(x), z]` (encoded point and optional code), hidden layers
//! `hₗ = Wₗaₗ + bₗ`, `aₗ₊₁ = φ(hₗ)` — and at a skip layer `aₗ ← [aₗ, a₀]/√2` — the output
//! is `y = W_L a_L + b_L`. Forward mode carries, for each of the `D` input coordinates
//! `xⱼ`, the tangent `ȧ = ∂a/∂xⱼ` alongside the value:
//!
//! ```text
//! ȧ₀ = [J_γ(x) eⱼ, 0],   ḣₗ = Wₗ ȧₗ,   ȧₗ₊₁ = φ'(hₗ) ⊙ ḣₗ,   ẏ = W_L ȧ_L
//! ```
//!
//! so `∂y/∂xⱼ = ẏ`. Every step is a candle op, so `∇ₓy` is a node of the graph and
//! `backward()` of any loss on it (eikonal, normal consistency, DVR's implicit step)
//! reaches the weights — which `backward()`-computed input gradients cannot, since candle
//! returns them detached. φ is ReLU (`φ' = 𝟙[h ≥ 0]`, matching candle's own ReLU
//! derivative) or softplus with sharpness β (`φ' = σ(βh)`). See docs/math.md.
//!
//! ## Geometric initialisation (IDR, Atzmon & Lipman)
//! Hidden weights `N(0, √2/√out)`, biases 0, the last layer `N(√π/√in, 10⁻⁴)` with bias
//! `−r`, and the columns for inputs other than the raw coordinates (higher encoding
//! terms, codes) zero at the first layer and in the skip block: the initial field is
//! approximately the SDF of a sphere of radius `r`, `f(x) ≈ ‖x‖ − r`.
//!
//! ```
//! use candle_core::{DType, Device, Tensor};
//! use candle_nn::{VarBuilder, VarMap};
//! use neural_fields::field::ImplicitSurface;
//! use neural_fields::nn::{mlp, Activation, MlpConfig};
//!
//! let varmap = VarMap::new();
//! let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
//! let config = MlpConfig { hidden: 32, depth: 3, activation: Activation::Softplus { beta: 100.0 },
//!                          ..MlpConfig::sdf(0.5) };
//! let net = mlp(&config, vb)?;
//! let p = Tensor::new(&[[0.0f32, 0.0, 0.9]], &Device::Cpu)?;
//! let (f, normal) = net.value_and_grad(&p)?;     // [1], [1, 3]; both trainable
//! assert_eq!(normal.dims(), &[1, 3]);
//! # Ok::<(), neural_fields::Error>(())
//! ```

use super::weight_jvp;
use crate::encoding::PointEncoding;
use crate::error::{check_float, check_points, check_same, check_shape, Dim, Error, Result};
use crate::field::{ConditionalField, Field, ImplicitSurface, Inside};
use crate::kernels::{Act, FusedMlp, FusedMlpJvp, LayerPlan};
use crate::numerics::{sigmoid, softplus};
use candle_core::{DType, Tensor, D};
use candle_nn::{Init, VarBuilder};

/// The hidden activation of an [`Mlp`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Activation {
    /// `max(h, 0)`.
    Relu,
    /// `log(1 + e^{βh})/β` (IDR: β = 100).
    Softplus {
        /// Sharpness β > 0.
        beta: f64,
    },
}

/// The configuration of an [`Mlp`].
#[derive(Clone, Debug)]
pub struct MlpConfig {
    /// Point dimension `D` (3 for fields over space).
    pub in_dim: usize,
    /// Latent code dimension (0 for an unconditional network).
    pub code_dim: usize,
    /// Output channels; channel 0 is the implicit surface's scalar.
    pub out_dim: usize,
    /// Width of the hidden layers.
    pub hidden: usize,
    /// Number of hidden layers (≥ 1).
    pub depth: usize,
    /// Hidden activation.
    pub activation: Activation,
    /// Hidden layer indices `l ∈ 1..depth` whose input is `[aₗ, a₀]/√2`.
    pub skips: Vec<usize>,
    /// Encoding of the points before the first layer.
    pub encoding: PointEncoding,
    /// `Some(r)`: IDR's geometric initialisation to the SDF of a sphere of radius `r`.
    pub geometric_init: Option<f64>,
    /// Which side of channel 0's zero level is inside.
    pub inside: Inside,
    /// Run the layers through candle's ops (the reference path) even on the CPU, where
    /// the fused MLP op would run: for comparing the two. Off the CPU, and for dtypes
    /// other than f32 and f64, the reference path runs regardless. Default `false`.
    pub force_reference: bool,
}

impl Default for MlpConfig {
    /// An occupancy network: 3 → 4 × 64 ReLU → 1 logit, inside positive.
    fn default() -> Self {
        Self {
            in_dim: 3,
            code_dim: 0,
            out_dim: 1,
            hidden: 64,
            depth: 4,
            activation: Activation::Relu,
            skips: Vec::new(),
            encoding: PointEncoding::Identity,
            geometric_init: None,
            inside: Inside::Positive,
            force_reference: false,
        }
    }
}

impl MlpConfig {
    /// An SDF network initialised to a sphere of radius `radius`: softplus(100), inside
    /// negative, geometric initialisation; other fields as [`MlpConfig::default`].
    #[must_use]
    pub fn sdf(radius: f64) -> Self {
        Self {
            activation: Activation::Softplus { beta: 100.0 },
            geometric_init: Some(radius),
            inside: Inside::Negative,
            ..Self::default()
        }
    }
}

/// One affine layer whose weight may be stored in column blocks (so that a block can be
/// zero-initialised through any `VarBuilder`); `W = [W₁ W₂ …]`, joined at every use so
/// that optimiser updates of the block variables take effect.
#[derive(Clone, Debug)]
struct Layer {
    blocks: Vec<Tensor>,
    bias: Tensor,
}

impl Layer {
    fn weight(&self) -> Result<Tensor> {
        match self.blocks.as_slice() {
            [w] => Ok(w.clone()),
            blocks => Ok(Tensor::cat(blocks, 1)?),
        }
    }

    fn forward(&self, a: &Tensor, weight: &Tensor) -> Result<Tensor> {
        Ok(a.matmul(&weight.t()?)?.broadcast_add(&self.bias)?)
    }
}

/// A multilayer perceptron field; build it with [`mlp`].
#[derive(Clone, Debug)]
pub struct Mlp {
    layers: Vec<Layer>,
    config: MlpConfig,
    /// The same layers' shapes for the fused CPU op.
    plan: FusedMlp,
}

/// Gets a weight `[out, in]` as column blocks: the first `keep` input columns use `init`
/// and the rest start at zero (stored as two variables, `{name}` and `{name}_rest`).
fn blocked_weight(
    vb: &VarBuilder,
    name: &str,
    out: usize,
    input: usize,
    keep: usize,
    init: Init,
) -> Result<Vec<Tensor>> {
    if keep >= input {
        return Ok(vec![vb.get_with_hints((out, input), name, init)?]);
    }
    let head = vb.get_with_hints((out, keep), name, init)?;
    let rest = vb.get_with_hints(
        (out, input - keep),
        &format!("{name}_rest"),
        Init::Const(0.0),
    )?;
    Ok(vec![head, rest])
}

/// Builds an [`Mlp`] from `config`, taking its variables from `vb` (`layer{i}.weight`,
/// `layer{i}.bias`, and `layer{i}.weight_rest` for zero-initialised blocks).
///
/// Default initialisation: Kaiming-normal weights and `U(−1/√in, 1/√in)` biases, as
/// candle-nn's `linear`; IDR's geometric initialisation with `geometric_init`.
///
/// # Errors
/// Naming `config.depth` when the layers' weights (about `hidden²` values each) pass the
/// allocation limit of 2³³ bytes (8 GiB), checked before any layer is built. Also:
/// `depth == 0`, `hidden == 0`, `in_dim == 0`, `out_dim == 0`, a skip index outside
/// `1..depth`, a softplus β that is not finite and positive (`config.activation`), an
/// encoding whose input dimension is not `in_dim`, geometric
/// initialisation with a non-positive radius or an encoding that does not lead with the
/// raw input; errors of the `VarBuilder`.
pub fn mlp(config: &MlpConfig, vb: VarBuilder) -> Result<Mlp> {
    for (name, v) in [
        ("config.depth", config.depth),
        ("config.hidden", config.hidden),
        ("config.in_dim", config.in_dim),
        ("config.out_dim", config.out_dim),
    ] {
        if v == 0 {
            return Err(Error::invalid(name, "at least 1", "0"));
        }
    }
    if let Some(&s) = config.skips.iter().find(|&&s| s == 0 || s >= config.depth) {
        return Err(Error::invalid(
            "config.skips",
            format!("hidden layer indices in 1..{}", config.depth),
            format!("{s}"),
        ));
    }
    if let Activation::Softplus { beta } = config.activation {
        if !(beta.is_finite() && beta > 0.0) {
            return Err(Error::invalid(
                "config.activation",
                "softplus with a finite beta > 0",
                format!("beta = {beta}"),
            ));
        }
    }
    let enc_dim = config.encoding.out_dim_for(config.in_dim);
    let enc_in = config.encoding.in_dim().unwrap_or(config.in_dim);
    if enc_in != config.in_dim {
        return Err(Error::invalid(
            "config.encoding",
            format!("an encoding of {}-dimensional points", config.in_dim),
            format!("one of {enc_in}-dimensional inputs"),
        ));
    }
    let a0 = enc_dim + config.code_dim;
    let h = config.hidden;
    let geometric = match config.geometric_init {
        Some(r) if !(r.is_finite() && r > 0.0) => {
            return Err(Error::invalid(
                "config.geometric_init",
                "a radius > 0",
                format!("{r}"),
            ))
        }
        Some(_) if !config.encoding.leads_with_input() => {
            return Err(Error::invalid(
                "config.encoding",
                "an encoding that starts with the raw input (geometric initialisation)",
                "Fourier features",
            ))
        }
        g => g,
    };

    let elem = vb.dtype().size_in_bytes();
    crate::limits::check_layers(
        "config.depth",
        config.depth.saturating_add(1),
        h.saturating_mul(h),
        elem,
    )?;
    let mut layers = Vec::with_capacity(config.depth + 1);
    let mut plan = Vec::with_capacity(config.depth + 1);
    for l in 0..=config.depth {
        let input = match l {
            0 => a0,
            l if config.skips.contains(&l) => h + a0,
            _ => h,
        };
        let out = if l == config.depth { config.out_dim } else { h };
        plan.push(LayerPlan {
            input,
            out,
            skip: config.skips.contains(&l),
        });
        let lvb = vb.pp(format!("layer{l}"));
        let (weight, bias) = match geometric {
            None => {
                let bound = 1.0 / (input as f64).sqrt();
                (
                    vec![lvb.get_with_hints(
                        (out, input),
                        "weight",
                        candle_nn::init::DEFAULT_KAIMING_NORMAL,
                    )?],
                    lvb.get_with_hints(
                        out,
                        "bias",
                        Init::Uniform {
                            lo: -bound,
                            up: bound,
                        },
                    )?,
                )
            }
            Some(radius) if l == config.depth => {
                let mean = std::f64::consts::PI.sqrt() / (input as f64).sqrt();
                (
                    vec![lvb.get_with_hints(
                        (out, input),
                        "weight",
                        Init::Randn { mean, stdev: 1e-4 },
                    )?],
                    lvb.get_with_hints(out, "bias", Init::Const(-radius))?,
                )
            }
            Some(_) => {
                let init = Init::Randn {
                    mean: 0.0,
                    stdev: 2f64.sqrt() / (out as f64).sqrt(),
                };
                // Keep only the raw coordinates of a₀ at initialisation.
                let keep = match l {
                    0 => config.in_dim,
                    l if config.skips.contains(&l) => h + config.in_dim,
                    _ => input,
                };
                (
                    blocked_weight(&lvb, "weight", out, input, keep, init)?,
                    lvb.get_with_hints(out, "bias", Init::Const(0.0))?,
                )
            }
        };
        layers.push(Layer {
            blocks: weight,
            bias,
        });
    }
    let act = match config.activation {
        Activation::Relu => Act::Relu,
        Activation::Softplus { beta } => Act::Softplus(beta),
    };
    Ok(Mlp {
        layers,
        config: config.clone(),
        plan: FusedMlp::new(plan, a0, act),
    })
}

impl Mlp {
    /// The configuration the network was built with.
    #[must_use]
    #[cfg_attr(not(feature = "volume"), allow(dead_code))] // the NeRF model reads its encodings
    pub(crate) fn config(&self) -> &MlpConfig {
        &self.config
    }

    fn check_inputs(&self, points: &Tensor, codes: Option<&Tensor>) -> Result<usize> {
        check_float(points, "points")?;
        let n = check_shape(
            points,
            "points",
            &[Dim::Any("N"), Dim::Is(self.config.in_dim)],
        )?[0];
        match (codes, self.config.code_dim) {
            (None, 0) => {}
            (None, d) => {
                return Err(Error::invalid(
                    "codes",
                    format!(
                    "[N, {d}] latent codes for this conditional network (see field::Conditioned)"
                ),
                    "none",
                ))
            }
            (Some(c), d) => {
                check_same(c, "codes", points, "points")?;
                check_shape(c, "codes", &[Dim::Is(n), Dim::Is(d)])?;
            }
        }
        Ok(n)
    }

    fn first_input(&self, enc: Tensor, codes: Option<&Tensor>) -> Result<Tensor> {
        match codes {
            Some(c) if self.config.code_dim > 0 => Ok(Tensor::cat(&[&enc, c], 1)?),
            _ => Ok(enc),
        }
    }

    fn activate(&self, h: &Tensor) -> Result<Tensor> {
        match self.config.activation {
            Activation::Relu => Ok(h.relu()?),
            Activation::Softplus { beta } => softplus(h, beta),
        }
    }

    fn activation_slope(&self, h: &Tensor) -> Result<Tensor> {
        match self.config.activation {
            Activation::Relu => Ok(h.ge(0.0)?.to_dtype(h.dtype())?),
            Activation::Softplus { beta } => sigmoid(&h.affine(beta, 0.0)?),
        }
    }

    /// Runs the layers on `a₀` (and tangents `ȧ₀` if given).
    fn run(&self, a0: &Tensor, da0: Option<&Tensor>) -> Result<(Tensor, Option<Tensor>)> {
        let inv_sqrt2 = std::f64::consts::FRAC_1_SQRT_2;
        let (mut a, mut da) = (a0.clone(), da0.cloned());
        let Some((last, hidden)) = self.layers.split_last() else {
            return Err(Error::invalid("mlp", "at least one layer", "none"));
        };
        for (l, layer) in hidden.iter().chain(std::iter::once(last)).enumerate() {
            if self.config.skips.contains(&l) {
                a = Tensor::cat(&[&a, a0], 1)?.affine(inv_sqrt2, 0.0)?;
                if let (Some(t), Some(t0)) = (da.as_ref(), da0) {
                    da = Some(Tensor::cat(&[t, t0], 2)?.affine(inv_sqrt2, 0.0)?);
                }
            }
            let weight = layer.weight()?;
            let h = layer.forward(&a, &weight)?;
            let dh = da.as_ref().map(|t| weight_jvp(&weight, t)).transpose()?;
            if l == hidden.len() {
                return Ok((h, dh));
            }
            a = self.activate(&h)?;
            if let Some(dh) = dh {
                da = Some(dh.broadcast_mul(&self.activation_slope(&h)?.unsqueeze(1)?)?);
            }
        }
        Err(Error::invalid("mlp", "an output layer", "none"))
    }

    /// The parameters as one flat tensor, in the fused op's order (each layer's
    /// row-major weight, then its bias); differentiable, so the op's parameter gradient
    /// reaches every variable.
    pub(crate) fn flat_params(&self) -> Result<Tensor> {
        Ok(Tensor::cat(&self.flat_parts()?, 0)?)
    }

    /// The pieces of [`Mlp::flat_params`] (each layer's flattened weight, then its bias),
    /// for one concatenation over several networks: one level of concatenation on the
    /// graph, so the backward pass splits the parameter gradient once.
    pub(crate) fn flat_parts(&self) -> Result<Vec<Tensor>> {
        let mut parts = Vec::with_capacity(2 * self.layers.len());
        for layer in &self.layers {
            parts.push(layer.weight()?.flatten_all()?);
            parts.push(layer.bias.clone());
        }
        Ok(parts)
    }

    /// The layers' shapes for the fused op.
    #[cfg_attr(not(feature = "volume"), allow(dead_code))] // the NeRF model's fused ops
    pub(crate) fn plan(&self) -> &FusedMlp {
        &self.plan
    }

    /// Whether [`Mlp::run`]'s forward pass may run as the fused CPU op on `a0`.
    pub(crate) fn fused(&self, a0: &Tensor) -> bool {
        self.plan_applies(a0) && a0.device().is_cpu()
    }

    /// Whether a fused op may run this network's layer plan on inputs like `a0` (on a
    /// device that has the op): not forced to the reference path, f32 or f64 throughout.
    pub(crate) fn plan_applies(&self, a0: &Tensor) -> bool {
        !self.config.force_reference
            && matches!(a0.dtype(), DType::F32 | DType::F64)
            && self.layers.iter().all(|l| l.bias.dtype() == a0.dtype())
    }

    /// `y = f(points, codes)`: `points: [N, in_dim]`, `codes: [N, code_dim]` or `None`
    /// (only when `code_dim == 0`) → `[N, out_dim]`. Differentiable w.r.t. the weights,
    /// the points and the codes. f32 or f64, any device: on the CPU the layers run as one
    /// fused op (the crate's kernel `FusedMlpJvp`), elsewhere (or with
    /// [`MlpConfig::force_reference`]) as candle ops. Users reach it through
    /// [`Field::forward`] and [`ConditionalField::forward_with_code`].
    pub(crate) fn forward_points(&self, points: &Tensor, codes: Option<&Tensor>) -> Result<Tensor> {
        self.check_inputs(points, codes)?;
        let a0 = self.first_input(self.config.encoding.forward(points)?, codes)?;
        if self.fused(&a0) {
            let params = self.flat_params()?;
            return Ok(a0.contiguous()?.apply_op2(&params, self.plan.clone())?);
        }
        Ok(self.run(&a0, None)?.0)
    }

    /// `y = f(points, codes)` and its Jacobian w.r.t. the points by forward mode:
    /// `[N, out_dim]` and `[N, in_dim, out_dim]` with `J[n, j, c] = ∂y[n, c]/∂points[n, j]`.
    ///
    /// Both outputs are differentiable w.r.t. the weights and the codes (and the points).
    /// On the CPU (f32/f64) values and tangents run as one fused op, elsewhere (or with
    /// [`MlpConfig::force_reference`]) as candle ops.
    ///
    /// # Errors
    /// Shapes, dtypes or devices that do not match the configuration.
    pub fn forward_with_jacobian(
        &self,
        points: &Tensor,
        codes: Option<&Tensor>,
    ) -> Result<(Tensor, Tensor)> {
        let n = self.check_inputs(points, codes)?;
        let d = self.config.in_dim;
        let eye = Tensor::eye(d, points.dtype(), points.device())?
            .unsqueeze(0)?
            .broadcast_as((n, d, d))?
            .contiguous()?;
        let (enc, denc) = self.config.encoding.forward_jvp(points, &eye)?;
        let a0 = self.first_input(enc, codes)?;
        let da0 = match codes {
            Some(c) if self.config.code_dim > 0 => {
                let zeros = Tensor::zeros((n, d, c.dim(1)?), points.dtype(), points.device())?;
                Tensor::cat(&[&denc, &zeros], 2)?
            }
            _ => denc,
        };
        if self.fused(&a0) {
            // Values and tangents through the fused op: [N, (1 + D)·out].
            let out = self.config.out_dim;
            let op = FusedMlpJvp {
                mlp: self.plan.clone(),
                tangents: d,
            };
            let yj = a0
                .contiguous()?
                .apply_op3(&da0.contiguous()?, &self.flat_params()?, op)?;
            let y = yj.narrow(1, 0, out)?;
            let dy = crate::narrow::narrow(&yj, 1, out, d * out)?.reshape((n, d, out))?;
            return Ok((y, dy));
        }
        let (y, dy) = self.run(&a0, Some(&da0))?;
        // invariant: tangents were passed in, so run() returns them.
        let dy = dy.ok_or_else(|| Error::invalid("tangents", "propagated", "none"))?;
        Ok((y, dy))
    }

    fn channel0_and_grad(
        &self,
        points: &Tensor,
        codes: Option<&Tensor>,
    ) -> Result<(Tensor, Tensor)> {
        let (y, j) = self.forward_with_jacobian(points, codes)?;
        Ok((
            y.narrow(1, 0, 1)?.squeeze(1)?,
            j.narrow(D::Minus1, 0, 1)?.squeeze(D::Minus1)?,
        ))
    }
}

impl Field for Mlp {
    fn out_dim(&self) -> usize {
        self.config.out_dim
    }

    fn forward(&self, points: &Tensor) -> Result<Tensor> {
        check_points(points, "points")?;
        self.forward_points(points, None)
    }
}

impl ImplicitSurface for Mlp {
    fn value(&self, points: &Tensor) -> Result<Tensor> {
        Ok(Field::forward(self, points)?.narrow(1, 0, 1)?.squeeze(1)?)
    }

    fn value_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        check_points(points, "points")?;
        self.channel0_and_grad(points, None)
    }

    fn inside(&self) -> Inside {
        self.config.inside
    }
}

impl ConditionalField for Mlp {
    fn code_dim(&self) -> usize {
        self.config.code_dim
    }

    fn out_dim(&self) -> usize {
        self.config.out_dim
    }

    fn forward_with_code(&self, points: &Tensor, codes: &Tensor) -> Result<Tensor> {
        check_points(points, "points")?;
        self.forward_points(points, Some(codes))
    }

    fn value_and_grad_with_code(
        &self,
        points: &Tensor,
        codes: &Tensor,
    ) -> Result<(Tensor, Tensor)> {
        check_points(points, "points")?;
        self.channel0_and_grad(points, Some(codes))
    }

    fn inside(&self) -> Inside {
        self.config.inside
    }
}
