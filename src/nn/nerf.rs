//! The NeRF network: density from the position, colour from a feature and the view
//! direction.

use super::fused_mlp::FusedNerf;
use super::mlp::{mlp, Activation, Mlp, MlpConfig};
use crate::encoding::{FrequencyEncoding, PointEncoding};
use crate::error::{check_points, check_same, check_shape, Dim, Error, Result};
use crate::field::{ConditionalField, Field};
use candle_core::Tensor;
use candle_nn::VarBuilder;

/// How the raw density output `r` becomes `σ ≥ 0`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DensityActivation {
    /// `σ = trunc_exp(r + shift)` ([`crate::volume::trunc_exp`]: `exp` forward, its
    /// gradient's exponent clamped, so that early large densities cannot produce NaN;
    /// instant-NGP and nerfacto). Needs the `volume` feature for the fused op; without it
    /// the same function is formed from candle ops.
    TruncExp {
        /// Added to `r` (instant-NGP's −1 starts the density near `e⁻¹`).
        shift: f64,
    },
    /// `σ = softplus(r + shift)` (mip-NeRF; smooth, linear for large `r`).
    Softplus {
        /// Added to `r` (mip-NeRF uses −1).
        shift: f64,
    },
}

/// The configuration of a [`Nerf`].
#[derive(Clone, Debug)]
pub struct NerfConfig {
    /// Encoding of the positions (NeRF: frequencies with L = 10, input included).
    pub position_encoding: PointEncoding,
    /// Encoding of the unit view directions; `None` makes the colour view-independent
    /// (NeRF: L = 4).
    pub direction_encoding: Option<PointEncoding>,
    /// Hidden layers of the density trunk (NeRF: 8; default 4 for the CPU).
    pub depth: usize,
    /// Width of the trunk's hidden layers and of the feature (NeRF: 256; default 64).
    pub width: usize,
    /// Trunk layers `l ∈ 1..depth` that see the encoded position again (NeRF: `[4]`).
    pub skips: Vec<usize>,
    /// Width of the colour head's hidden layer (NeRF: 128; default 64).
    pub color_width: usize,
    /// The density activation (default `TruncExp { shift: −1 }`).
    pub density: DensityActivation,
    /// Run both networks through candle's ops instead of the fused MLP op
    /// ([`MlpConfig::force_reference`]). Default `false`.
    pub force_reference: bool,
}

impl Default for NerfConfig {
    /// NeRF's encodings (L = 10 for positions, 4 for directions) on a 4 × 64 trunk and a
    /// 64-wide colour head: the model that trains in minutes on a CPU.
    fn default() -> Self {
        // invariant: 3-D inputs with 10 and 4 frequencies are valid encodings.
        Self {
            position_encoding: PointEncoding::Frequency(
                FrequencyEncoding::new(3, 10).expect("3-D, 10 frequencies"), // invariant
            ),
            direction_encoding: Some(PointEncoding::Frequency(
                FrequencyEncoding::new(3, 4).expect("3-D, 4 frequencies"), // invariant
            )),
            depth: 4,
            width: 64,
            skips: Vec::new(),
            color_width: 64,
            density: DensityActivation::TruncExp { shift: -1.0 },
            force_reference: false,
        }
    }
}

/// A NeRF radiance field; build it with [`nerf`].
///
/// `radiance(p, d)`: `[N, 3]` positions and `[N, 3]` view directions (any length; they are
/// normalised) → density `σ: [N]` (≥ 0) and colour `[N, 3]` in `(0, 1)` (sigmoid). The
/// trunk, an [`Mlp`] on the encoded position, outputs `1 + width` channels: the raw
/// density and a feature; the colour head, an [`Mlp`] with one hidden layer, takes the
/// encoded direction and the feature. As a [`Field`] it is the density alone (`[N, 1]`),
/// for occupancy-grid updates and mesh extraction.
///
/// Differentiable with respect to its parameters, the positions and the directions.
#[derive(Clone, Debug)]
pub struct Nerf {
    trunk: Mlp,
    head: Mlp,
    config: NerfConfig,
}

/// Builds a [`Nerf`] from `config` with variables under `vb`: the trunk's under `trunk.`,
/// the colour head's under `color.` (the names of [`mlp`]).
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use candle_nn::VarMap;
/// use neural_fields::nn::{build_seeded, nerf, NerfConfig};
///
/// let varmap = VarMap::new();
/// let net = build_seeded(&varmap, DType::F32, &Device::Cpu, 0, |vb| nerf(&NerfConfig::default(), vb))?;
/// let points = Tensor::zeros((5, 3), DType::F32, &Device::Cpu)?;
/// let dirs = Tensor::ones((5, 3), DType::F32, &Device::Cpu)?;
/// let (sigma, rgb) = net.radiance(&points, &dirs)?;
/// assert_eq!((sigma.dims(), rgb.dims()), (&[5][..], &[5, 3][..]));
/// // Save and restore the weights with candle's own safetensors support:
/// // varmap.save("nerf.safetensors")?; varmap.load("nerf.safetensors")?;
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `config.width` / `config.color_width` if 0, and those
/// of [`mlp`] for the trunk (depth, skips, encoding); errors of the `VarBuilder`.
pub fn nerf(config: &NerfConfig, vb: VarBuilder) -> Result<Nerf> {
    if config.width == 0 {
        return Err(Error::invalid("config.width", "> 0", "0"));
    }
    if config.color_width == 0 {
        return Err(Error::invalid("config.color_width", "> 0", "0"));
    }
    let trunk = mlp(
        &MlpConfig {
            out_dim: 1 + config.width,
            hidden: config.width,
            depth: config.depth,
            activation: Activation::Relu,
            skips: config.skips.clone(),
            encoding: config.position_encoding.clone(),
            force_reference: config.force_reference,
            ..MlpConfig::default()
        },
        vb.pp("trunk"),
    )?;
    let head = mlp(
        &MlpConfig {
            code_dim: config.width,
            out_dim: 3,
            hidden: config.color_width,
            depth: 1,
            activation: Activation::Relu,
            encoding: config
                .direction_encoding
                .clone()
                .unwrap_or(PointEncoding::Identity),
            force_reference: config.force_reference,
            ..MlpConfig::default()
        },
        vb.pp("color"),
    )?;
    Ok(Nerf {
        trunk,
        head,
        config: config.clone(),
    })
}

impl Nerf {
    /// The configuration.
    #[must_use]
    pub fn config(&self) -> &NerfConfig {
        &self.config
    }

    fn activate(&self, raw: &Tensor) -> Result<Tensor> {
        match self.config.density {
            DensityActivation::TruncExp { shift } => {
                #[cfg(feature = "volume")]
                {
                    crate::volume::trunc_exp(&(raw + shift)?)
                }
                #[cfg(not(feature = "volume"))]
                {
                    // exp with the exponent capped where f32 overflows; same forward as
                    // the fused op below the cap.
                    Ok((raw + shift)?.minimum(88.0)?.exp()?)
                }
            }
            DensityActivation::Softplus { shift } => {
                crate::numerics::softplus(&(raw + shift)?, 1.0)
            }
        }
    }

    /// The density `σ: [N]` and the feature `[N, width]` at `points: [N, 3]`.
    fn trunk(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        let out = Field::forward(&self.trunk, points)?;
        let sigma = self.activate(&out.narrow(1, 0, 1)?.squeeze(1)?)?;
        Ok((sigma, crate::narrow::narrow(&out, 1, 1, self.config.width)?))
    }

    /// The density `σ: [N]` (≥ 0) at `points: [N, 3]`, without the colour head: for
    /// occupancy-grid updates, proposal targets and meshes. Differentiable w.r.t. the
    /// trunk's parameters and the points.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `points` for a wrong shape or dtype.
    pub fn density(&self, points: &Tensor) -> Result<Tensor> {
        check_points(points, "points")?;
        Ok(self.trunk(points)?.0)
    }

    /// Density `σ: [N]` and colour `[N, 3]` at `points: [N, 3]` seen along `directions:
    /// [N, 3]` (normalised here; a zero direction gives the encoding of 0).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `points` or `directions` for wrong shapes or
    /// dtypes, `directions` for another count than `points`.
    pub fn radiance(&self, points: &Tensor, directions: &Tensor) -> Result<(Tensor, Tensor)> {
        let n = check_points(points, "points")?;
        check_shape(directions, "directions", &[Dim::Is(n), Dim::Is(3)])?;
        check_same(directions, "directions", points, "points")?;
        let unit = if self.config.direction_encoding.is_some() {
            // ‖d‖ floored at 1e-12 before the root, so a zero direction has a finite
            // gradient.
            let norm = directions.sqr()?.sum_keepdim(1)?.maximum(1e-24)?.sqrt()?;
            directions.broadcast_div(&norm)?
        } else {
            // No direction encoding: the head sees the zero vector, so the colour does not
            // depend on the view (nor is it differentiable w.r.t. the directions).
            directions.zeros_like()?
        };
        if self.trunk.fused(points) && self.head.fused(points) {
            // Both networks in one CPU op: [N, 4] = raw density, raw colour.
            let ep = self.trunk.config().encoding.forward(points)?.contiguous()?;
            let ed = self.head.config().encoding.forward(&unit)?.contiguous()?;
            let params = Tensor::cat(&[self.trunk.flat_params()?, self.head.flat_params()?], 0)?;
            let op = FusedNerf {
                trunk: self.trunk.plan().clone(),
                head: self.head.plan().clone(),
            };
            let out = ep.apply_op3(&ed, &params, op)?;
            let sigma = self.activate(&out.narrow(1, 0, 1)?.squeeze(1)?)?;
            return Ok((
                sigma,
                candle_nn::ops::sigmoid(&crate::narrow::narrow(&out, 1, 1, 3)?)?,
            ));
        }
        let (sigma, feature) = self.trunk(points)?;
        let raw = self.head.forward_with_code(&unit, &feature)?;
        Ok((sigma, candle_nn::ops::sigmoid(&raw)?))
    }
}

impl Field for Nerf {
    /// 1: the density.
    fn out_dim(&self) -> usize {
        1
    }

    /// The density as `[N, 1]` ([`Nerf::density`]).
    fn forward(&self, points: &Tensor) -> Result<Tensor> {
        Ok(self.density(points)?.unsqueeze(1)?)
    }
}
