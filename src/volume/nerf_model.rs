//! The NeRF network: density from the position, colour from a feature and the view
//! direction.

use super::compositing::{background_rows, composite, CompositeConfig};
use super::layout::{Intervals, Layout};
use crate::camera::Rays;
use crate::encoding::RowEncoder;
use crate::encoding::{FrequencyEncoding, PointEncoding};
use crate::error::{check_same, check_shape, Dim, Error, Result};
use crate::field::{ConditionalField, Field};
use crate::kernels::{Density, FusedNerf, FusedNerfLoss};
use crate::nn::{mlp, Activation, Mlp, MlpConfig};
use crate::numerics::{softplus, trunc_exp};
use candle_core::{DType, Tensor};
use candle_nn::VarBuilder;

/// How the raw density output `r` becomes `σ ≥ 0`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DensityActivation {
    /// `σ = trunc_exp(r + shift)` ([`trunc_exp`]: `exp` forward with the exponent capped
    /// at 88 in f32 and 709 in f64, its gradient `exp(clamp(r + shift, −15, 15))`, so that
    /// early large densities cannot produce NaN; instant-NGP and nerfacto).
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
    /// The density activation (default `TruncExp { shift: −3 }`: the density starts
    /// near `e⁻³` ≈ 0.05, so that a ray across a loose scene box starts mostly
    /// transparent. With instant-NGP's −1 (σ ≈ 0.37) such a ray starts nearly opaque
    /// in front of a mostly white background, Adam's first steps drive σ down
    /// everywhere, and at a learning rate of 5e-3 on a box of ±1.5 around an object of
    /// radius 1 the density never came back; −2 still died on one scene of three
    /// (docs/benchmarks.md, "Defaults across the scene suite").
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
            density: DensityActivation::TruncExp { shift: -3.0 },
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
/// use neural_fields::nn::build_seeded;
/// use neural_fields::volume::{nerf, NerfConfig};
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
            // 3-D points, or Gaussians [μ, σ²] for an integrated encoding.
            in_dim: config.position_encoding.in_dim().unwrap_or(3),
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

/// What [`Nerf::color_loss`] returns: the loss, and the opacity the rendering reached,
/// which a training loop watches for a dead model (a density collapsed to zero renders
/// every ray transparent, whatever the loss says).
#[derive(Clone, Debug)]
#[non_exhaustive]
pub struct ColorLoss {
    /// `mean ‖C − C*‖² / 3`, a scalar in the rays' dtype; differentiable as
    /// [`Nerf::color_loss`] says.
    pub loss: Tensor,
    /// The rays' mean opacity `Σᵢ wᵢ` (no graph).
    pub opacity_mean: f64,
    /// The largest opacity of a ray (no graph).
    pub opacity_max: f64,
}

impl Nerf {
    fn activate(&self, raw: &Tensor) -> Result<Tensor> {
        match self.config.density {
            DensityActivation::TruncExp { shift } => trunc_exp(&(raw + shift)?),
            DensityActivation::Softplus { shift } => softplus(&(raw + shift)?, 1.0),
        }
    }

    /// What the colour head sees of `directions: [N, 3]`: the unit vectors, or zeros
    /// without a direction encoding.
    fn unit_directions(&self, directions: &Tensor) -> Result<Tensor> {
        Ok(if self.config.direction_encoding.is_some() {
            // ‖d‖ floored at 1e-12 before the root, so a zero direction has a finite
            // gradient.
            let norm = directions.sqr()?.sum_keepdim(1)?.maximum(1e-24)?.sqrt()?;
            directions.broadcast_div(&norm)?
        } else {
            // No direction encoding: the head sees the zero vector, so the colour does not
            // depend on the view (nor is it differentiable w.r.t. the directions).
            directions.zeros_like()?
        })
    }

    /// The trunk's input rows for `points`: `[N, 3]` points, or for an integrated
    /// position encoding `[N, 6]` Gaussians `[μ, σ²]`, to which `[N, 3]` points are
    /// widened with zero variances.
    fn trunk_input(&self, points: &Tensor) -> Result<Tensor> {
        let width = self.trunk.config().in_dim;
        crate::error::check_float(points, "points")?;
        let dims = check_shape(points, "points", &[Dim::Any("N"), Dim::Any("D")])?;
        match dims[1] {
            d if d == width => Ok(points.clone()),
            3 if width == 6 => Ok(Tensor::cat(&[points, &points.zeros_like()?], 1)?),
            d => Err(Error::invalid(
                "points",
                format!("[N, 3] points or [N, {width}] rows of the position encoding"),
                format!("[N, {d}]"),
            )),
        }
    }

    /// The density `σ: [N]` and the feature `[N, width]` at the trunk's input rows
    /// ([`Nerf::trunk_input`]).
    fn trunk(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        let out = self
            .trunk
            .forward_points(&self.trunk_input(points)?, None)?;
        let sigma = self.activate(&out.narrow(1, 0, 1)?.squeeze(1)?)?;
        Ok((sigma, crate::narrow::narrow(&out, 1, 1, self.config.width)?))
    }

    /// The density `σ: [N]` (≥ 0) at `points: [N, 3]`, without the colour head: for
    /// occupancy-grid updates, proposal targets and meshes. With an integrated position
    /// encoding ([`PointEncoding::Integrated`]) `points` may also be Gaussians
    /// `[μ, σ²]: [N, 6]`; `[N, 3]` points are Gaussians of zero variance, which read
    /// every octave undamped, including those no training cone resolved: query such a
    /// model at the footprint of the query instead (an occupancy grid's cell, variance
    /// `cell²/12` per axis, as `examples/nerf` does). Differentiable w.r.t. the trunk's
    /// parameters and the points.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `points` for a wrong shape or dtype.
    pub fn density(&self, points: &Tensor) -> Result<Tensor> {
        Ok(self.trunk(points)?.0)
    }

    /// Density `σ: [N]` and colour `[N, 3]` at `points: [N, 3]` seen along `directions:
    /// [N, 3]` (normalised here; a zero direction gives the encoding of 0). With an
    /// integrated position encoding, `points` may be Gaussians `[μ, σ²]: [N, 6]`
    /// (as [`Nerf::density`]).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `points` or `directions` for wrong shapes or
    /// dtypes, `directions` for another count than `points`.
    pub fn radiance(&self, points: &Tensor, directions: &Tensor) -> Result<(Tensor, Tensor)> {
        let points = &self.trunk_input(points)?;
        let n = points.dim(0)?;
        check_shape(directions, "directions", &[Dim::Is(n), Dim::Is(3)])?;
        check_same(directions, "directions", points, "points")?;
        let unit = self.unit_directions(directions)?;
        if self.trunk.fused(points) && self.head.fused(points) {
            // Both networks in one CPU op: [N, 4] = raw density, raw colour.
            let ep = self.trunk.config().encoding.forward(points)?.contiguous()?;
            let ed = self.head.config().encoding.forward(&unit)?.contiguous()?;
            let params = self.flat_params()?;
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

impl Nerf {
    /// NeRF's photometric training loss: the mean over rays and colour channels of
    /// `(C(r) − C*(r))²`, where `C(r)` is [`composite()`]'s colour of the
    /// field sampled at the midpoints of `intervals` along `rays`,
    ///
    /// ```text
    /// σᵢ, cᵢ = radiance(o + tᵢd, d),   C = Σᵢ wᵢcᵢ + (1 − Σᵢ wᵢ)·c_bg,
    /// L = (1 / 3R) Σ_r ‖C(r) − C*(r)‖²
    /// ```
    ///
    /// with `wᵢ` the compositing weights of `σᵢ` over the lengths `δᵢ = (endᵢ − startᵢ)·‖d‖`
    /// and `config`'s `opaque_last` and background. With an integrated position encoding
    /// ([`PointEncoding::Integrated`], mip-NeRF) and rays that carry cone radii
    /// ([`Rays::with_radii`]), the field sees each interval's conical frustum
    /// ([`super::conical_frustums`], diagonal covariances) instead of its midpoint.
    ///
    /// Shapes: `rays` of `R` rays, `intervals` batched `[R, S]` or packed, `target: [R, 3]`;
    /// f32 or f64, all one dtype and device. Returns the loss, a scalar `[]`, with the
    /// rays' mean and largest opacity ([`ColorLoss`]), which both paths compute anyway.
    ///
    /// Differentiable w.r.t. the network's parameters. On the CPU, when the rays,
    /// intervals, target and background are constants (no gradient flows to them) and the
    /// encodings are frequencies (`2ᵏπ`) or the identity, it runs as one fused op that
    /// evaluates, composites and differentiates each tile of rays while its activations
    /// are in cache (the crate's kernel `FusedNerfLoss`; 1.5× the speed of
    /// [`Nerf::radiance`], [`composite()`] and the loss from candle ops).
    /// The gradient is then computed in the forward pass and kept until `backward`, so
    /// for evaluation without training render with [`Nerf::radiance`] instead. Otherwise
    /// (another device, `force_reference`, other encodings, or rays, intervals, target
    /// or background that carry gradients) it is composed of exactly those calls and is
    /// differentiable w.r.t. whatever they are.
    ///
    /// ```
    /// use candle_core::{DType, Device, Tensor};
    /// use candle_nn::VarMap;
    /// use neural_fields::camera::Rays;
    /// use neural_fields::nn::build_seeded;
    /// use neural_fields::volume::{nerf, stratified, CompositeConfig, Jitter, NerfConfig};
    ///
    /// let dev = Device::Cpu;
    /// let varmap = VarMap::new();
    /// let net = build_seeded(&varmap, DType::F32, &dev, 0, |vb| nerf(&NerfConfig::default(), vb))?;
    /// let rays = Rays::new(
    ///     Tensor::new(&[[0f32, 0., -4.], [0., 0.5, -4.]], &dev)?,
    ///     Tensor::new(&[[0f32, 0., 1.], [0., 0., 1.]], &dev)?,
    /// )?;
    /// let near = Tensor::full(2f32, 2, &dev)?;
    /// let far = Tensor::full(6f32, 2, &dev)?;
    /// let intervals = stratified(&near, &far, 32, Jitter::PerSample, 0)?;
    /// let target = Tensor::new(&[[1f32, 0., 0.], [0., 1., 0.]], &dev)?;
    /// let out = net.color_loss(&rays, &intervals, &target, &CompositeConfig::default())?;
    /// let grads = out.loss.backward()?;
    /// assert!((0.0..=1.0).contains(&out.opacity_mean) && out.opacity_max <= 1.0);
    /// assert!(varmap.all_vars().iter().all(|v| grads.get(v).is_some()));
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `target` for another shape than `[R, 3]`, no
    /// rays, a dtype or device unlike the rays', or a non-finite value; `rays` when their
    /// count differs from the intervals'; those of [`Nerf::radiance`] and
    /// [`composite()`] (`config.background`'s shape, a non-finite density
    /// or colour: in the fused op, an error naming the network's raw output).
    pub fn color_loss(
        &self,
        rays: &Rays,
        intervals: &Intervals,
        target: &Tensor,
        config: &CompositeConfig,
    ) -> Result<ColorLoss> {
        let r = intervals.n_rays();
        if r == 0 {
            return Err(Error::invalid("target", "at least one ray", "0 rays"));
        }
        check_shape(target, "target", &[Dim::Is(r), Dim::Is(3)])?;
        check_same(target, "target", rays.origins(), "rays")?;
        crate::error::check_finite(target, "target")?;
        let positions = self.sample_inputs(rays, intervals)?;
        if let Some(loss) = self.fused_color_loss(rays, intervals, &positions, target, config)? {
            return Ok(loss);
        }
        let directions = intervals.directions(rays)?.reshape(((), 3))?;
        let (sigma, rgb) = self.radiance(&positions, &directions)?;
        let (sigma, rgb) = match &intervals.layout {
            Layout::Batched => {
                let s = positions.dim(0)? / r;
                (sigma.reshape((r, s))?, rgb.reshape((r, s, 3))?)
            }
            Layout::Packed(_) => (sigma, rgb),
        };
        let out = composite(&sigma, &rgb, intervals, Some(rays), config)?;
        let opacity = out.opacity.detach().to_dtype(DType::F64)?;
        Ok(ColorLoss {
            loss: (out.color - target)?.sqr()?.mean_all()?,
            opacity_mean: opacity.mean_all()?.to_scalar::<f64>()?,
            opacity_max: opacity.max_all()?.to_scalar::<f64>()?,
        })
    }

    /// What the network evaluates for each interval along `rays`, the `points` of
    /// [`Nerf::radiance`]: the midpoints `o + t̄ᵢd`, `[M, 3]`; or, for an integrated
    /// position encoding ([`PointEncoding::Integrated`]) and rays that carry cone radii
    /// ([`Rays::with_radii`]), the Gaussians of the intervals' conical frustums
    /// ([`super::conical_frustums`]) as rows `[μ, diag Σ]`, `[M, 6]` (mip-NeRF). `M` is
    /// `R·S` for batched intervals `[R, S]` (row-major) or the packed count. Differentiable
    /// as [`super::conical_frustums`] and [`Intervals::positions`] are.
    ///
    /// ```
    /// use candle_core::{DType, Device, Tensor};
    /// use candle_nn::VarMap;
    /// use neural_fields::camera::Rays;
    /// use neural_fields::encoding::PointEncoding;
    /// use neural_fields::nn::build_seeded;
    /// use neural_fields::volume::{nerf, stratified, Jitter, NerfConfig};
    ///
    /// let dev = Device::Cpu;
    /// let config = NerfConfig {
    ///     position_encoding: PointEncoding::Integrated { dim: 3, min_deg: 0, max_deg: 12 },
    ///     ..NerfConfig::default()
    /// };
    /// let net = build_seeded(&VarMap::new(), DType::F32, &dev, 0, |vb| nerf(&config, vb))?;
    /// let rays = Rays::new(
    ///     Tensor::new(&[[0f32, 0., -4.]], &dev)?,
    ///     Tensor::new(&[[0f32, 0., 1.]], &dev)?,
    /// )?
    /// .with_radii(Tensor::new(&[2e-3f32], &dev)?)?;
    /// let (near, far) = (Tensor::new(&[2f32], &dev)?, Tensor::new(&[6f32], &dev)?);
    /// let intervals = stratified(&near, &far, 16, Jitter::None, 0)?;
    /// let inputs = net.sample_inputs(&rays, &intervals)?; // [16, 6]: means, variances
    /// let dirs = intervals.directions(&rays)?.reshape(((), 3))?;
    /// let (sigma, rgb) = net.radiance(&inputs, &dirs)?;
    /// assert_eq!((sigma.dims(), rgb.dims()), (&[16][..], &[16, 3][..]));
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// Naming `rays` when their count, dtype or device differs from the intervals'.
    pub fn sample_inputs(&self, rays: &Rays, intervals: &Intervals) -> Result<Tensor> {
        let integrated = matches!(
            self.config.position_encoding,
            PointEncoding::Integrated { .. }
        );
        if integrated && rays.radii().is_some() {
            let g = super::conical_frustums(rays, intervals, super::Covariance::Diagonal)?;
            return Ok(Tensor::cat(
                &[g.means.reshape(((), 3))?, g.covariances.reshape(((), 3))?],
                1,
            )?);
        }
        Ok(intervals.positions(rays)?.reshape(((), 3))?)
    }

    /// Both networks' parameters as one flat tensor `[P]` (trunk, then head; the fused
    /// ops' order), concatenated in one step.
    fn flat_params(&self) -> Result<Tensor> {
        let mut parts = self.trunk.flat_parts()?;
        parts.extend(self.head.flat_parts()?);
        Ok(Tensor::cat(&parts, 0)?)
    }

    /// [`Nerf::color_loss`] as the fused op, or `None` where it does not apply.
    fn fused_color_loss(
        &self,
        rays: &Rays,
        intervals: &Intervals,
        positions: &Tensor,
        target: &Tensor,
        config: &CompositeConfig,
    ) -> Result<Option<ColorLoss>> {
        // The checks that need no tensor op come first, so that a fallback to the composed
        // path has computed nothing here.
        let constant = [positions, rays.directions(), target]
            .iter()
            .copied()
            .chain(config.background.as_ref())
            .all(|t| !t.track_op());
        // The fused loss runs on the CPU and (feature `cuda`) on CUDA.
        let device = crate::kernels::fused_on(positions.device());
        if !constant
            || !device
            || !self.trunk.plan_applies(positions)
            || !self.head.plan_applies(positions)
        {
            return Ok(None);
        }
        let r = intervals.n_rays();
        let offsets: std::sync::Arc<[usize]> = match &intervals.layout {
            Layout::Batched => {
                let s = positions.dim(0)? / r;
                (0..=r).map(|i| i * s).collect()
            }
            Layout::Packed(p) => p.offsets_arc(),
        };
        let density = match self.config.density {
            DensityActivation::TruncExp { shift } => Density::TruncExp(shift),
            DensityActivation::Softplus { shift } => Density::Softplus(shift),
        };
        let nets = FusedNerf {
            trunk: self.trunk.plan().clone(),
            head: self.head.plan().clone(),
        };
        let encoders = (
            RowEncoder::new(&self.trunk.config().encoding, 3),
            RowEncoder::new(&self.head.config().encoding, 3),
        );
        let (Some(position), Some(direction)) = encoders else {
            return Ok(None);
        };
        let Some(op) = FusedNerfLoss::new(
            nets,
            (position, direction),
            density,
            offsets,
            config.opaque_last,
        ) else {
            return Ok(None);
        };
        let deltas = intervals.deltas(Some(rays))?.flatten_all()?;
        if deltas.track_op() {
            return Ok(None);
        }
        let background = match &config.background {
            None => target.zeros_like()?,
            Some(bg) => {
                background_rows(bg, "config.background", target, "target")?.broadcast_as((r, 3))?
            }
        };
        let samples = Tensor::cat(&[positions, &deltas.unsqueeze(1)?], 1)?;
        let unit = self.unit_directions(rays.directions())?;
        let per_ray = Tensor::cat(&[&unit, target, &background], 1)?;
        let params = self.flat_params()?;
        let slot = op.opacity_slot();
        let loss = samples.apply_op3(&per_ray, &params, op)?;
        let [opacity_mean, opacity_max] =
            slot.lock().ok().and_then(|o| *o).ok_or_else(|| {
                Error::invalid("rays", "a forward pass of the fused loss", "none")
            })?;
        Ok(Some(ColorLoss {
            loss,
            opacity_mean,
            opacity_max,
        }))
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
