//! Texture networks (feature `texture`): the Texture Fields decoder, IDR's rendering
//! network and DVR's joint shape-and-colour decoder, each a
//! [`TextureField`](crate::texture::TextureField).

use super::input::{TextureField, TextureInput};
use crate::encoding::{Encoding, FrequencyEncoding, PointEncoding};
use crate::error::{Error, Result};
use crate::field::{ConditionalField, Field, ImplicitSurface, Inside};
use crate::nn::{mlp, Activation, Mlp, MlpConfig, ResnetFc};
use crate::numerics::sigmoid;
use candle_core::{Tensor, D};
use candle_nn::VarBuilder;

/// Settings of [`texture_decoder`].
#[derive(Clone, Debug)]
pub struct TextureDecoderConfig {
    /// Width of the point features and the ResNet blocks (Texture Fields: 128).
    pub hidden: usize,
    /// Number of pointwise ResNet blocks (Texture Fields: 5; 7 in the single-view
    /// variant).
    pub blocks: usize,
    /// Dimension `C` of the shape code `c` (0: none is read).
    pub shape_code_dim: usize,
    /// Dimension `Z` of the image code `z` (0: none is read).
    pub image_code_dim: usize,
    /// Encoding of the points before the first layer (Texture Fields: none, the raw
    /// point; a [`PointEncoding::Frequency`] lets one object's texture carry detail
    /// that a ReLU network on raw coordinates smooths away).
    pub encoding: PointEncoding,
}

impl Default for TextureDecoderConfig {
    /// Hidden 128, 5 blocks, no codes (an unconditional texture of one object), raw
    /// points.
    fn default() -> Self {
        Self {
            hidden: 128,
            blocks: 5,
            shape_code_dim: 0,
            image_code_dim: 0,
            encoding: PointEncoding::Identity,
        }
    }
}

/// The Texture Fields decoder (Oechsle et al., ICCV 2019); build it with
/// [`texture_decoder`].
///
/// ```text
/// h = W_p γ(p) + b_p,
/// for each block i:  h ← h + W_cᵢ [c, z] + b_cᵢ;   h ← h + W₁ᵢ relu(W₀ᵢ relu(h) + b₀ᵢ) + b₁ᵢ,
/// rgb = σ(W_out relu(h) + b_out),
/// ```
///
/// with `γ` the configured encoding (the identity in Texture Fields), the codes' map
/// added before *every* block, and the second layer of each block
/// and the output layer starting at zero (so the initial texture is a uniform grey,
/// σ(0) = ½, and the blocks start as identities). Reads `points`, and `shape_code` /
/// `image_code` when their dimensions are not 0; differentiable w.r.t. the parameters,
/// the points and the codes. Candle ops on any device, f32 or f64.
#[derive(Clone, Debug)]
pub struct TextureDecoder {
    trunk: ResnetFc,
    config: TextureDecoderConfig,
}

/// Builds a [`TextureDecoder`] from `vb`: `fc_p`, `block{i}.fc0/fc1`, `code{i}` (when
/// there are codes) and `fc_out` linear layers; `fc0`, `fc_p` and the code maps with
/// candle-nn's default initialisation, `fc1` and `fc_out` zero.
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use candle_nn::VarMap;
/// use neural_fields::nn::build_seeded;
/// use neural_fields::texture::{texture_decoder, TextureDecoderConfig, TextureField, TextureInput};
///
/// let config = TextureDecoderConfig { shape_code_dim: 16, ..TextureDecoderConfig::default() };
/// let varmap = VarMap::new();
/// let net = build_seeded(&varmap, DType::F32, &Device::Cpu, 0, |vb| texture_decoder(&config, vb))?;
/// let p = Tensor::zeros((4, 3), DType::F32, &Device::Cpu)?;
/// let c = Tensor::ones((4, 16), DType::F32, &Device::Cpu)?;
/// let rgb = net.rgb(&TextureInput { shape_code: Some(&c), ..TextureInput::new(&p) })?;
/// assert_eq!(rgb.to_vec2::<f32>()?[0], vec![0.5; 3]); // grey at initialisation
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// `hidden` or `blocks` 0 (naming `config.*`), an encoding of other than 3-D points
/// (naming `config.encoding`); errors of `vb`.
pub fn texture_decoder(config: &TextureDecoderConfig, vb: VarBuilder) -> Result<TextureDecoder> {
    check_point_encoding(&config.encoding, "config.encoding")?;
    Ok(TextureDecoder {
        trunk: ResnetFc::new(
            config.encoding.out_dim_for(3),
            config.hidden,
            config.blocks,
            config.shape_code_dim + config.image_code_dim,
            3,
            &vb,
        )?,
        config: config.clone(),
    })
}

impl TextureField for TextureDecoder {
    fn rgb(&self, input: &TextureInput) -> Result<Tensor> {
        input.check_points()?;
        let mut codes = Vec::new();
        for (given, arg, dim) in [
            (input.shape_code, "shape_code", self.config.shape_code_dim),
            (input.image_code, "image_code", self.config.image_code_dim),
        ] {
            if dim > 0 {
                codes.push(input.required(given, arg, Some(dim), "this texture decoder")?);
            }
        }
        let code = match codes.as_slice() {
            [] => None,
            [c] => Some((*c).clone()),
            _ => Some(Tensor::cat(&codes, 1)?),
        };
        let x = self.config.encoding.forward(input.points)?;
        sigmoid(&self.trunk.forward(&x, code.as_ref())?)
    }
}

/// Settings of [`rendering_net`] (IDR's rendering network).
#[derive(Clone, Debug)]
pub struct RenderingNetConfig {
    /// Dimension `F` of the geometry network's feature vector (IDR: 256; 0: none read).
    pub feature_dim: usize,
    /// `Some(L)`: read the viewing direction, unit-normalised and encoded with `L`
    /// frequencies (IDR: 4); `None`: IDR's mode without the view direction (no
    /// view-dependent effects).
    pub view_frequencies: Option<usize>,
    /// Read the normals (IDR: yes; `false` is IDR's mode without the normal).
    pub use_normals: bool,
    /// Width of the hidden layers (IDR: 512).
    pub hidden: usize,
    /// Number of hidden layers (IDR: 4).
    pub depth: usize,
    /// Run the layers through candle's ops even on the CPU (see
    /// [`MlpConfig::force_reference`]).
    pub force_reference: bool,
    /// Encoding `γₚ` of the surface point (IDR: none, the raw point). A hash grid or a
    /// frequency encoding lets the colour carry texture detail that the geometry's
    /// feature vector and a ReLU network on raw coordinates smooth away; the colour's
    /// gradient w.r.t. `p̂` then also runs through the encoding.
    pub point_encoding: PointEncoding,
}

impl Default for RenderingNetConfig {
    /// IDR's: a 256-d feature, view direction with 4 frequencies, normals, 4 × 512 ReLU,
    /// the raw point.
    fn default() -> Self {
        Self {
            feature_dim: 256,
            view_frequencies: Some(4),
            use_normals: true,
            hidden: 512,
            depth: 4,
            force_reference: false,
            point_encoding: PointEncoding::Identity,
        }
    }
}

/// Checks that `encoding` reads 3-D points (an identity reads any).
fn check_point_encoding(encoding: &PointEncoding, arg: &'static str) -> Result<()> {
    let enc_in = encoding.in_dim().unwrap_or(3);
    if enc_in != 3 {
        return Err(Error::invalid(
            arg,
            "an encoding of 3-D points",
            format!("one of {enc_in}-D inputs"),
        ));
    }
    Ok(())
}

/// IDR's rendering network (Yariv et al. 2020); build it with [`rendering_net`].
///
/// ```text
/// rgb = σ(MLP([γₚ(p), γ(v/‖v‖), n, f]))
/// ```
///
/// with `p` the surface point (`γₚ` the configured point encoding, IDR's identity), `v` the viewing direction (encoded by `L` frequencies,
/// input included), `n` the normal as given (IDR feeds the SDF's unnormalised gradient)
/// and `f` the geometry network's feature vector; a ReLU MLP whose output goes through a
/// sigmoid (IDR's tanh mapped to `[0, 1]`). With `n = ∇f(p̂)` from
/// [`crate::nn::Mlp::forward_with_jacobian`] at [`crate::dvr::SurfacePoints::points`],
/// the colour reaches the geometry's parameters through `p̂`, through the normal and
/// through the feature. The layers are an [`Mlp`] whose latent code is `[γ(v), n, f]`, so
/// they run as the fused CPU op.
///
/// Reads `points`, and `view_dirs`, `normals`, `features` as configured; differentiable
/// w.r.t. the parameters and all of them.
#[derive(Clone, Debug)]
pub struct RenderingNet {
    mlp: Mlp,
    view: Option<FrequencyEncoding>,
    config: RenderingNetConfig,
}

/// Builds a [`RenderingNet`] from `vb` (the layers of an [`Mlp`], `layer{i}.*`).
///
/// # Errors
/// `hidden` or `depth` 0, `view_frequencies` too large for
/// [`FrequencyEncoding::new`], a point encoding of other than 3-D points (naming
/// `config.point_encoding`); errors of `vb`.
pub fn rendering_net(config: &RenderingNetConfig, vb: VarBuilder) -> Result<RenderingNet> {
    check_point_encoding(&config.point_encoding, "config.point_encoding")?;
    let view = config
        .view_frequencies
        .map(|l| FrequencyEncoding::new(3, l))
        .transpose()?;
    let code_dim = view.as_ref().map_or(0, Encoding::out_dim)
        + if config.use_normals { 3 } else { 0 }
        + config.feature_dim;
    let mlp_config = MlpConfig {
        in_dim: 3,
        code_dim,
        out_dim: 3,
        hidden: config.hidden,
        depth: config.depth,
        activation: Activation::Relu,
        skips: Vec::new(),
        encoding: config.point_encoding.clone(),
        geometric_init: None,
        inside: Inside::Positive,
        force_reference: config.force_reference,
    };
    Ok(RenderingNet {
        mlp: mlp(&mlp_config, vb)?,
        view,
        config: config.clone(),
    })
}

impl TextureField for RenderingNet {
    fn rgb(&self, input: &TextureInput) -> Result<Tensor> {
        input.check_points()?;
        const WHO: &str = "this rendering network";
        let mut code = Vec::new();
        if let Some(enc) = &self.view {
            let v = input.required(input.view_dirs, "view_dirs", Some(3), WHO)?;
            let len = v
                .sqr()?
                .sum_keepdim(1)?
                .clamp(1e-30, f64::INFINITY)?
                .sqrt()?;
            code.push(enc.forward(&v.broadcast_div(&len)?)?);
        }
        if self.config.use_normals {
            code.push(
                input
                    .required(input.normals, "normals", Some(3), WHO)?
                    .clone(),
            );
        }
        if self.config.feature_dim > 0 {
            code.push(
                input
                    .required(
                        input.features,
                        "features",
                        Some(self.config.feature_dim),
                        WHO,
                    )?
                    .clone(),
            );
        }
        let y = if code.is_empty() {
            Field::forward(&self.mlp, input.points)?
        } else {
            self.mlp
                .forward_with_code(input.points, &Tensor::cat(&code, 1)?)?
        };
        sigmoid(&y)
    }
}

/// DVR's decoder: one trunk with four outputs, channel 0 the occupancy logit (an
/// [`ImplicitSurface`], inside positive) and channels 1–3 the colour through a sigmoid
/// (a [`TextureField`] that reads only the points); build it with [`joint_decoder`].
///
/// The trunk is an [`Mlp`] (fused on the CPU, forward-mode normals), where DVR uses ResNet
/// blocks of width 512; with no latent code the two are the same family of functions.
#[derive(Clone, Debug)]
pub struct JointDecoder {
    mlp: Mlp,
}

/// Builds a [`JointDecoder`] whose trunk is the [`Mlp`] of `config` with `out_dim`
/// replaced by 4 (and an unconditional `code_dim` of 0 kept as given).
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use candle_nn::VarMap;
/// use neural_fields::field::ImplicitSurface;
/// use neural_fields::nn::{build_seeded, MlpConfig};
/// use neural_fields::texture::{joint_decoder, TextureField, TextureInput};
///
/// let varmap = VarMap::new();
/// let net = build_seeded(&varmap, DType::F32, &Device::Cpu, 0, |vb| {
///     joint_decoder(&MlpConfig::default(), vb)
/// })?;
/// let p = Tensor::zeros((2, 3), DType::F32, &Device::Cpu)?;
/// let logit = net.value(&p)?;                          // [2]
/// let rgb = net.rgb(&TextureInput::new(&p))?;          // [2, 3]
/// assert_eq!((logit.dims(), rgb.dims()), (&[2][..], &[2, 3][..]));
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// As [`mlp`].
pub fn joint_decoder(config: &MlpConfig, vb: VarBuilder) -> Result<JointDecoder> {
    let config = MlpConfig {
        out_dim: 4,
        ..config.clone()
    };
    Ok(JointDecoder {
        mlp: mlp(&config, vb)?,
    })
}

impl Field for JointDecoder {
    fn out_dim(&self) -> usize {
        4
    }

    /// The raw outputs `[N, 4]`: logit and the colour's pre-sigmoid values.
    fn forward(&self, points: &Tensor) -> Result<Tensor> {
        Field::forward(&self.mlp, points)
    }
}

impl ImplicitSurface for JointDecoder {
    fn value(&self, points: &Tensor) -> Result<Tensor> {
        self.mlp.value(points)
    }

    fn value_and_grad(&self, points: &Tensor) -> Result<(Tensor, Tensor)> {
        self.mlp.value_and_grad(points)
    }

    fn inside(&self) -> Inside {
        ImplicitSurface::inside(&self.mlp)
    }
}

impl TextureField for JointDecoder {
    fn rgb(&self, input: &TextureInput) -> Result<Tensor> {
        input.check_points()?;
        let y = Field::forward(&self.mlp, input.points)?;
        sigmoid(&crate::narrow::narrow(&y, D::Minus1, 1, 3)?)
    }
}
