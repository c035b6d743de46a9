//! The PointNet encoder `q_ψ(z | points, occupancies)` of the variational Occupancy
//! Network (Mescheder et al. 2019, §3.3): a shared per-point MLP, a max-pool over the
//! points, and two linear heads for the Gaussian posterior's mean and log-variance.
//!
//! For a shape with `K` labelled points `(pₖ, oₖ)`: `h⁰ₖ = [pₖ, oₖ] ∈ ℝ⁴`,
//! `hˡ⁺¹ₖ = ReLU(Wˡhˡₖ + bˡ)`, `g = maxₖ hᴸₖ` (elementwise), `μ = W_μ g + b_μ`,
//! `log σ² = W_σ g + b_σ`. The max-pool makes the code independent of the order of the
//! points. Train with `occupancy::{reparameterize, kl_standard_normal}`:
//! `z = μ + σ ⊙ ε`, loss `Σ BCE(f(p, z), o) + KL(q ‖ N(0, I))`.
//!
//! The same network encodes points with other per-point features
//! ([`PointNetEncoder::forward`] with `F` features per point): Texture Fields' shape code
//! `c` is the mean head `μ` of a PointNet over surface points with their normals
//! (`point_features: 3`, `h⁰ₖ = [pₖ, nₖ] ∈ ℝ⁶`).

use crate::error::{check_float, check_same, check_shape, Dim, Error, Result};
use candle_core::Tensor;
use candle_nn::{linear, Linear, Module, VarBuilder};

/// Settings of [`pointnet_encoder`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PointNetConfig {
    /// Width of the per-point MLP (ONet: 128).
    pub hidden: usize,
    /// Number of per-point layers (≥ 1).
    pub layers: usize,
    /// Latent dimension `D` of `z`.
    pub latent_dim: usize,
    /// Features per point beside its position (1: the occupancy label of
    /// [`PointNetEncoder::forward`]; 3: normals, for Texture Fields' shape code).
    pub point_features: usize,
}

impl Default for PointNetConfig {
    /// 3 layers of width 128, a 128-dimensional latent code, one feature per point (the
    /// occupancy label).
    fn default() -> Self {
        Self {
            hidden: 128,
            layers: 3,
            latent_dim: 128,
            point_features: 1,
        }
    }
}

/// The encoder; build it with [`pointnet_encoder`].
#[derive(Clone, Debug)]
pub struct PointNetEncoder {
    layers: Vec<Linear>,
    mean: Linear,
    logvar: Linear,
    config: PointNetConfig,
}

/// Builds a [`PointNetEncoder`] from `vb` (`layer{l}`, `mean`, `logvar` linear layers with
/// candle-nn's default initialisation).
///
/// # Errors
/// Naming `config.layers` when the layers' weights (about `hidden²` values each) pass the
/// allocation limit of 2³³ bytes (8 GiB), checked before any layer is built. Also:
/// A zero `hidden`, `layers`, `latent_dim` or `point_features` (naming `config.*`);
/// errors of `vb`.
pub fn pointnet_encoder(config: &PointNetConfig, vb: VarBuilder) -> Result<PointNetEncoder> {
    for (name, v) in [
        ("config.hidden", config.hidden),
        ("config.layers", config.layers),
        ("config.latent_dim", config.latent_dim),
        ("config.point_features", config.point_features),
    ] {
        if v == 0 {
            return Err(Error::invalid(name, "at least 1", "0"));
        }
    }
    let params = config
        .hidden
        .saturating_mul(config.hidden)
        .saturating_mul(2);
    crate::limits::check_layers(
        "config.layers",
        config.layers,
        params,
        vb.dtype().size_in_bytes(),
    )?;
    let mut layers = Vec::with_capacity(config.layers);
    for l in 0..config.layers {
        let input = if l == 0 {
            3 + config.point_features
        } else {
            config.hidden
        };
        layers.push(linear(input, config.hidden, vb.pp(format!("layer{l}")))?);
    }
    Ok(PointNetEncoder {
        layers,
        mean: linear(config.hidden, config.latent_dim, vb.pp("mean"))?,
        logvar: linear(config.hidden, config.latent_dim, vb.pp("logvar"))?,
        config: config.clone(),
    })
}

impl PointNetEncoder {
    /// The posterior parameters `(μ, log σ²)`, each `[B, D]`, of `B` point sets
    /// `points: [B, K, 3]` with per-point `features: [B, K, F]` (`F = point_features`: e.g.
    /// unit normals for Texture Fields' shape encoder), f32 or f64. With `F = 1` the
    /// features may also be `[B, K]`, ONet's occupancy labels in `[0, 1]` (read as
    /// `[B, K, 1]`). Each point's `[x, features]` goes through the shared layers; the
    /// max over the `K` points gives the set's feature, and two linear heads `μ`, `log σ²`.
    ///
    /// Differentiable w.r.t. the encoder's weights, the points and the features (the
    /// max-pool passes gradients to the maximising point of each channel).
    ///
    /// # Errors
    /// `points` not `[B, K, 3]` float with `K ≥ 1`; `features` not `[B, K, F]` (or `[B, K]`
    /// when `F = 1`) of the same dtype and device.
    pub fn forward(&self, points: &Tensor, features: &Tensor) -> Result<(Tensor, Tensor)> {
        let (b, k) = check_point_sets(points)?;
        let f = self.config.point_features;
        check_same(features, "features", points, "points")?;
        let features = if features.rank() == 2 && f == 1 {
            check_shape(features, "features", &[Dim::Is(b), Dim::Is(k)])?;
            features.unsqueeze(2)?
        } else {
            check_shape(features, "features", &[Dim::Is(b), Dim::Is(k), Dim::Is(f)])?;
            features.clone()
        };
        let mut h = Tensor::cat(&[points, &features], 2)?.reshape((b * k, 3 + f))?;
        for layer in &self.layers {
            h = layer.forward(&h)?.relu()?;
        }
        let g = h.reshape((b, k, self.config.hidden))?.max(1)?;
        Ok((self.mean.forward(&g)?, self.logvar.forward(&g)?))
    }
}

/// Checks `points: [B, K, 3]` (f32/f64, `K ≥ 1`); returns `(B, K)`.
fn check_point_sets(points: &Tensor) -> Result<(usize, usize)> {
    check_float(points, "points")?;
    let dims = check_shape(
        points,
        "points",
        &[Dim::Any("B"), Dim::Any("K"), Dim::Is(3)],
    )?;
    if dims[1] == 0 {
        return Err(Error::invalid(
            "points",
            "at least one point per shape (K ≥ 1)",
            "K = 0",
        ));
    }
    Ok((dims[0], dims[1]))
}
