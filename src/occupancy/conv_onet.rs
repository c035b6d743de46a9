//! Convolutional Occupancy Networks (Peng et al., ECCV 2020); documented on
//! [`ConvOnetEncoder`].

use crate::encoding::{cell_index, grid_sample, scatter, GridSampleConfig, Pooling, ScatterConfig};
use crate::error::{check_float, check_points, check_same, check_shape, Dim, Error, Result};
use crate::field::Field;
use crate::nn::ResnetFc;
use candle_core::{DType, Device, Tensor};
use candle_nn::{Init, Linear, Module, VarBuilder};

/// The planes' coordinate pairs: `xz`, `xy`, `yz` (first: columns, second: rows).
const PLANES: [[u32; 2]; 3] = [[0, 2], [0, 1], [1, 2]];

/// Where the encoder pools its features.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FeatureLayout {
    /// Three planes `xz`, `xy`, `yz` of `resolution²` cells (published: 64).
    Planes {
        /// Cells per side.
        resolution: usize,
    },
    /// One grid of `resolution³` cells (published: 32).
    Grid {
        /// Cells per side.
        resolution: usize,
    },
}

/// Settings of the U-Net over the feature planes or grid.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UnetConfig {
    /// Levels (≥ 1; published: 4 for planes, 3 for the grid). The resolution must be
    /// divisible by `2^(depth − 1)`.
    pub depth: usize,
    /// Channels of the first level, doubled at each level (published: 32).
    pub start_filters: usize,
}

impl Default for UnetConfig {
    /// Depth 4 (published), 8 start filters (published: 32): sized for two CPU cores. In
    /// examples/scene_occupancy (64² planes, 3000 input and 2048 query points, one
    /// thread on a shared 2-core machine) a training step takes 0.6 s with 8 filters and
    /// 1.55 s with 16, nearly all of it in the U-Net.
    fn default() -> Self {
        Self {
            depth: 4,
            start_filters: 8,
        }
    }
}

/// Settings of [`conv_onet_encoder`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConvOnetConfig {
    /// Planes (default, 64²) or grid.
    pub layout: FeatureLayout,
    /// Hidden width `h` of the point network (published: 32).
    pub hidden: usize,
    /// ResNet-FC blocks of the point network (published: 5; ≥ 1).
    pub blocks: usize,
    /// Feature channels `C` of the planes or grid (published: 32).
    pub feature_dim: usize,
    /// Box padding (published: 0.1): the scene box is `[−(1 + pad)/2, (1 + pad)/2]³`.
    pub padding: f64,
    /// The U-Net over the pooled features.
    pub unet: UnetConfig,
}

impl Default for ConvOnetConfig {
    /// The published three-plane model (64², `h = C = 32`, 5 blocks, padding 0.1) with
    /// the CPU-sized [`UnetConfig::default`].
    fn default() -> Self {
        Self {
            layout: FeatureLayout::Planes { resolution: 64 },
            hidden: 32,
            blocks: 5,
            feature_dim: 32,
            padding: 0.1,
            unet: UnetConfig::default(),
        }
    }
}

/// The encoded scene: three feature planes `[B, C, R, R]` or one grid `[B, C, R, R, R]`.
#[derive(Clone, Debug)]
pub enum LocalFeatures {
    /// Planes `xz` (rows `z`, columns `x`), `xy` (rows `y`), `yz` (rows `z`, columns `y`).
    Planes {
        /// `[B, C, R, R]`.
        xz: Tensor,
        /// `[B, C, R, R]`.
        xy: Tensor,
        /// `[B, C, R, R]`.
        yz: Tensor,
    },
    /// `[B, C, R, R, R]` indexed `[b, c, z, y, x]`.
    Grid(Tensor),
}

impl LocalFeatures {
    /// The tensors (three planes or the grid).
    fn tensors(&self) -> Vec<&Tensor> {
        match self {
            LocalFeatures::Planes { xz, xy, yz } => vec![xz, xy, yz],
            LocalFeatures::Grid(g) => vec![g],
        }
    }

    /// Batch size `B` and channels `C`.
    #[must_use]
    pub(crate) fn batch_and_channels(&self) -> (usize, usize) {
        let t = self.tensors()[0];
        let d = t.dims();
        (d[0], d[1])
    }

    /// `Σ` over the planes of the bilinear samples (or the trilinear grid sample) at
    /// normalised coordinates `u: [B, M, 3]` → `[B, M, C]`.
    fn sample(&self, u: &Tensor) -> Result<Tensor> {
        match self {
            LocalFeatures::Grid(g) => grid_sample(g, u, &GridSampleConfig::default()),
            LocalFeatures::Planes { xz, xy, yz } => {
                let mut sum: Option<Tensor> = None;
                for (plane, cols) in [xz, xy, yz].into_iter().zip(PLANES) {
                    let idx = Tensor::new(&cols, u.device())?;
                    let s = grid_sample(
                        plane,
                        &u.index_select(&idx, 2)?,
                        &GridSampleConfig::default(),
                    )?;
                    sum = Some(match sum {
                        Some(acc) => (acc + s)?,
                        None => s,
                    });
                }
                sum.ok_or_else(|| Error::invalid("features", "three planes", "none"))
            }
        }
    }
}

/// The normalised coordinates `p / (1 + pad + 10⁻⁶) + 0.5`.
fn normalise(points: &Tensor, padding: f64) -> Result<Tensor> {
    Ok(points.affine(1.0 / (1.0 + padding + 1e-6), 0.5)?)
}

/// A ResNet-FC block `x ↦ shortcut(x) + fc₁(ReLU(fc₀(ReLU(x))))` (`fc₁`'s weight starts at
/// zero; the shortcut is a bias-free linear map when the widths differ, else identity).
#[derive(Clone, Debug)]
struct ResnetBlock {
    fc0: Linear,
    fc1: Linear,
    shortcut: Option<Linear>,
}

impl ResnetBlock {
    fn new(input: usize, out: usize, vb: VarBuilder) -> Result<Self> {
        let hidden = input.min(out);
        let bound = 1.0 / (hidden as f64).sqrt();
        let w1 = vb
            .pp("fc1")
            .get_with_hints((out, hidden), "weight", Init::Const(0.0))?;
        let b1 = vb.pp("fc1").get_with_hints(
            out,
            "bias",
            Init::Uniform {
                lo: -bound,
                up: bound,
            },
        )?;
        let shortcut = if input == out {
            None
        } else {
            Some(candle_nn::linear_no_bias(input, out, vb.pp("shortcut"))?)
        };
        Ok(Self {
            fc0: candle_nn::linear(input, hidden, vb.pp("fc0"))?,
            fc1: Linear::new(w1, Some(b1)),
            shortcut,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let h = self.fc0.forward(&x.relu()?)?;
        let dx = self.fc1.forward(&h.relu()?)?;
        let xs = match &self.shortcut {
            Some(s) => s.forward(x)?,
            None => x.clone(),
        };
        Ok((xs + dx)?)
    }
}

/// A convolution's weight `[out, in, k…]` and bias `[out]` (candle-nn's initialisation:
/// Kaiming-normal weights, biases uniform in `±1/√fan_in`).
#[derive(Clone, Debug)]
struct Conv {
    weight: Tensor,
    bias: Tensor,
    padding: usize,
}

impl Conv {
    fn new(dims: usize, input: usize, out: usize, k: usize, vb: VarBuilder) -> Result<Self> {
        let mut shape = vec![out, input];
        shape.extend(std::iter::repeat_n(k, dims));
        let weight = vb.get_with_hints(
            shape.as_slice(),
            "weight",
            candle_nn::init::DEFAULT_KAIMING_NORMAL,
        )?;
        let bound = 1.0 / ((input * k.pow(dims as u32)) as f64).sqrt();
        let bias = vb.get_with_hints(
            out,
            "bias",
            Init::Uniform {
                lo: -bound,
                up: bound,
            },
        )?;
        Ok(Self {
            weight,
            bias,
            padding: k / 2,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let y = if x.rank() == 5 {
            conv3d(x, &self.weight, self.padding)?
        } else {
            x.conv2d(&self.weight, self.padding, 1, 1, 1)?
        };
        let mut bshape = vec![1, self.bias.dim(0)?];
        bshape.extend(std::iter::repeat_n(1, x.rank() - 2));
        Ok(y.broadcast_add(&self.bias.reshape(bshape)?)?)
    }
}

/// A 3-D convolution (stride 1, zero padding `padding` on every spatial side) built from
/// candle's 2-D one: `input: [B, Cᵢ, D, H, W]`, `weight: [Cₒ, Cᵢ, K_D, K_H, K_W]` →
/// `[B, Cₒ, D', H', W']` with `D' = D + 2·padding − K_D + 1` (likewise `H'`, `W'`),
///
/// `y[b, o, z, y, x] = Σ_{i, a, β, γ} w[o, i, a, β, γ] · x_pad[b, i, z + a, y + β, x + γ]`.
///
/// How: the depth-padded input's `K_D` shifted depth windows `x_pad[:, :, a : a + D']` are
/// stacked on the channel axis (`[B, K_D·Cᵢ, D', H, W]`, channel `a·Cᵢ + i`), the depth
/// axis is folded into the batch (`[B·D', K_D·Cᵢ, H, W]`), and one `conv2d` with the weight
/// rearranged to `[Cₒ, K_D·Cᵢ, K_H, K_W]` (the same channel order) sums over `a`, `i`, `β`,
/// `γ` at once. Memory: `K_D` copies of the input. Candle ops only (any device, f32/f64),
/// differentiable w.r.t. `input` and `weight`.
///
/// # Errors
/// `input` not float rank 5; `weight` not `[Cₒ, Cᵢ, K_D, K_H, K_W]` of the input's dtype
/// and device with every kernel size ≥ 1 and at most the padded input's; candle's.
pub(crate) fn conv3d(input: &Tensor, weight: &Tensor, padding: usize) -> Result<Tensor> {
    check_float(input, "input")?;
    let d = check_shape(
        input,
        "input",
        &[
            Dim::Any("B"),
            Dim::Any("C"),
            Dim::Any("D"),
            Dim::Any("H"),
            Dim::Any("W"),
        ],
    )?;
    check_same(weight, "weight", input, "input")?;
    let w = check_shape(
        weight,
        "weight",
        &[
            Dim::Any("O"),
            Dim::Is(d[1]),
            Dim::Any("KD"),
            Dim::Any("KH"),
            Dim::Any("KW"),
        ],
    )?;
    if (0..3).any(|a| w[2 + a] == 0 || w[2 + a] > d[2 + a] + 2 * padding) {
        return Err(Error::invalid(
            "weight",
            "kernel sizes from 1 to the padded input's sizes",
            format!("shape {w:?} for input {d:?} with padding {padding}"),
        ));
    }
    let (b, ci, depth) = (d[0], d[1], d[2]);
    let (co, kd) = (w[0], w[2]);
    let xp = if padding > 0 {
        input.pad_with_zeros(2, padding, padding)?
    } else {
        input.clone()
    };
    let dout = depth + 2 * padding + 1 - kd;
    let windows: Vec<Tensor> = (0..kd)
        .map(|a| xp.narrow(2, a, dout))
        .collect::<candle_core::Result<_>>()?;
    let stacked = Tensor::cat(&windows, 1)?; // [B, KD·Ci, D', H, W]
    let folded = stacked
        .permute((0, 2, 1, 3, 4))?
        .reshape((b * dout, kd * ci, d[3], d[4]))?;
    let w2 = weight
        .permute((0, 2, 1, 3, 4))?
        .reshape((co, kd * ci, w[3], w[4]))?;
    let y = folded.conv2d(&w2, padding, 1, 1, 1)?; // [B·D', Co, H', W']
    let (ho, wo) = (y.dim(2)?, y.dim(3)?);
    Ok(y.reshape((b, dout, co, ho, wo))?.permute((0, 2, 1, 3, 4))?)
}

/// 2× max-pooling over every spatial axis (even sizes).
fn pool(x: &Tensor) -> Result<Tensor> {
    if x.rank() == 4 {
        return Ok(x.max_pool2d(2)?);
    }
    let (b, c, d, h, w) = x.dims5()?;
    Ok(x.reshape(vec![b, c, d / 2, 2, h / 2, 2, w / 2, 2])?
        .max(7)?
        .max(5)?
        .max(3)?)
}

/// Nearest-neighbour 2× upsampling over every spatial axis.
fn upsample(x: &Tensor) -> Result<Tensor> {
    if x.rank() == 4 {
        let (_, _, h, w) = x.dims4()?;
        return Ok(x.upsample_nearest2d(2 * h, 2 * w)?);
    }
    let (b, c, d, h, w) = x.dims5()?;
    let hw = x
        .reshape((b, c * d, h, w))?
        .upsample_nearest2d(2 * h, 2 * w)?
        .reshape((b, c, d, 1, 4 * h * w))?;
    Ok(hw
        .broadcast_as((b, c, d, 2, 4 * h * w))?
        .reshape((b, c, 2 * d, 2 * h, 2 * w))?)
}

/// The U-Net (2-D or 3-D by the rank of its input).
#[derive(Clone, Debug)]
struct Unet {
    down: Vec<(Conv, Conv)>,
    up: Vec<(Conv, Conv, Conv)>,
    out: Conv,
}

impl Unet {
    fn new(dims: usize, channels: usize, config: &UnetConfig, vb: VarBuilder) -> Result<Self> {
        let f = |l: usize| config.start_filters << l;
        let mut down = Vec::with_capacity(config.depth);
        for l in 0..config.depth {
            let input = if l == 0 { channels } else { f(l - 1) };
            let lvb = vb.pp(format!("down{l}"));
            down.push((
                Conv::new(dims, input, f(l), 3, lvb.pp("conv0"))?,
                Conv::new(dims, f(l), f(l), 3, lvb.pp("conv1"))?,
            ));
        }
        let mut up = Vec::with_capacity(config.depth.saturating_sub(1));
        for l in (0..config.depth.saturating_sub(1)).rev() {
            let lvb = vb.pp(format!("up{l}"));
            up.push((
                Conv::new(dims, f(l + 1), f(l), 1, lvb.pp("upconv"))?,
                Conv::new(dims, 2 * f(l), f(l), 3, lvb.pp("conv0"))?,
                Conv::new(dims, f(l), f(l), 3, lvb.pp("conv1"))?,
            ));
        }
        Ok(Self {
            down,
            up,
            out: Conv::new(dims, f(0), channels, 1, vb.pp("out"))?,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut skips = Vec::with_capacity(self.down.len());
        let mut h = x.clone();
        for (l, (c0, c1)) in self.down.iter().enumerate() {
            if l > 0 {
                h = pool(&h)?;
            }
            h = c1.forward(&c0.forward(&h)?.relu()?)?.relu()?;
            skips.push(h.clone());
        }
        skips.pop();
        for (upconv, c0, c1) in &self.up {
            let skip = skips
                .pop()
                .ok_or_else(|| Error::invalid("config.unet.depth", "matching levels", "none"))?;
            let u = upconv.forward(&upsample(&h)?)?;
            let cat = Tensor::cat(&[&u, &skip], 1)?;
            h = c1.forward(&c0.forward(&cat)?.relu()?)?.relu()?;
        }
        self.out.forward(&h)
    }
}

/// Convolutional Occupancy Networks (Peng et al., ECCV 2020): a local PointNet encoder
/// that pools point features into three feature planes or one feature grid, a U-Net over
/// them, and a decoder that reads each query point's local feature by bilinear or
/// trilinear interpolation.
///
/// **Coordinates.** A point `p` of the scene box `[−(1 + pad)/2, (1 + pad)/2]³` has the
/// normalised coordinates `u = p / (1 + pad + 10⁻⁶) + 0.5` (pad: `padding`, 0.1), which
/// index cells by [`cell_index`] (clamped into `[0, 1 − 10⁻⁶]`) and feature samples by
/// [`grid_sample`] (clamped into `[0, 1]`, `align_corners = True`). Plane `xz` is read at
/// `(u_x, u_z)` (columns `x`, rows `z`), `xy` at `(u_x, u_y)`, `yz` at `(u_y, u_z)`; the grid
/// at `(u_x, u_y, u_z)` (`[B, C, z, y, x]`).
///
/// **Encoder** ([`ConvOnetEncoder`]): `net = fc_pos(p)` (`3 → 2h`), ResNet-FC block
/// `2h → h`; then for each further block, the per-cell maximum of `net` over the points of
/// each cell ([`scatter`] with [`Pooling::Max`]) is read back at every point's cell, summed over the planes,
/// concatenated to `net` (`2h`) and passed through the block (`2h → h`); `c = fc_c(net)`
/// (`h → C`); the per-cell mean of `c` ([`scatter`] with [`Pooling::Mean`]) forms each plane `[B, C, R, R]`
/// (or the grid `[B, C, R, R, R]`), empty cells 0, and a U-Net maps it to the features.
///
/// **U-Net** ([`UnetConfig`]): `depth` levels of two 3×3 (3×3×3) convolutions with ReLU,
/// `start_filters · 2ˡ` channels at level `l`, 2× max-pooling between levels; on the way
/// up, nearest-neighbour 2× upsampling and a 1×1 convolution halving the channels (the
/// published U-Net's `up_mode = "upsample"`), concatenation with the skip, two 3×3
/// convolutions with ReLU; a final 1×1 convolution back to `C` channels. The three planes
/// share one U-Net (stacked on the batch axis). Planes use candle's `conv2d`; the grid
/// uses a 3-D convolution built from it (the padded input's shifted depth windows stacked
/// on the channel axis, the depth folded into the batch, one `conv2d`).
///
/// **Decoder** ([`LocalDecoder`]): `c(p) = Σ_planes bilinear(plane, u)` (or trilinear in
/// the grid); then the pointwise ResNet trunk `net = fc_p(p)`,
/// `net ← block_i(net + fc_cᵢ(c(p)))` (5 blocks of width 32), `logit = fc_out(ReLU(net))`.
///
/// Gradients reach every parameter of the encoder, the U-Net and the decoder through
/// candle's autograd (the fused sampling and pooling ops included). Shapes: points
/// `[B, N, 3]` → [`LocalFeatures`] with batch `B`; queries `[B, M, 3]` → logits `[B, M]`.
/// Dtype and device are those of the `VarBuilder` the modules were built from (f32 or
/// f64, any device: off the CPU the sampling and pooling run their reference paths).
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use candle_nn::{VarBuilder, VarMap};
/// use neural_fields::occupancy::{conv_onet_encoder, local_decoder, ConvOnetConfig, FeatureLayout, LocalDecoderConfig, UnetConfig};
///
/// let varmap = VarMap::new();
/// let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
/// let config = ConvOnetConfig {
///     layout: FeatureLayout::Planes { resolution: 8 },
///     unet: UnetConfig { depth: 2, start_filters: 4 },
///     ..ConvOnetConfig::default()
/// };
/// let encoder = conv_onet_encoder(&config, vb.pp("encoder"))?;
/// let decoder = local_decoder(&LocalDecoderConfig::default(), vb.pp("decoder"))?;
/// let cloud = Tensor::rand(-0.5f32, 0.5, (1, 100, 3), &Device::Cpu)?;
/// let features = encoder.forward(&cloud)?;
/// let queries = Tensor::rand(-0.55f32, 0.55, (1, 64, 3), &Device::Cpu)?;
/// assert_eq!(decoder.logits(&queries, &features)?.dims(), &[1, 64]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// Build it with [`conv_onet_encoder`].
#[derive(Clone, Debug)]
pub struct ConvOnetEncoder {
    fc_pos: Linear,
    blocks: Vec<ResnetBlock>,
    fc_c: Linear,
    unet: Unet,
    config: ConvOnetConfig,
    device: Device,
    dtype: DType,
}

/// Builds a [`ConvOnetEncoder`] from `vb` (variables `fc_pos`, `block{i}.{fc0,fc1,
/// shortcut}`, `fc_c`, `unet.*`) in `vb`'s dtype and device.
///
/// ```
/// use candle_core::{DType, Device};
/// use candle_nn::{VarBuilder, VarMap};
/// use neural_fields::mesh::{points_to_tensor, PointCloud};
/// use neural_fields::occupancy::{conv_onet_encoder, ConvOnetConfig, FeatureLayout, LocalFeatures, UnetConfig};
///
/// let varmap = VarMap::new();
/// let vb = VarBuilder::from_varmap(&varmap, DType::F64, &Device::Cpu);
/// let config = ConvOnetConfig {
///     layout: FeatureLayout::Grid { resolution: 4 },
///     unet: UnetConfig { depth: 2, start_filters: 2 },
///     ..ConvOnetConfig::default()
/// };
/// let encoder = conv_onet_encoder(&config, vb)?;
/// let cloud = PointCloud::new(vec![[0.1, 0.2, -0.3], [-0.4, 0.0, 0.25]], None, None)?;
/// let batch = points_to_tensor(cloud.points(), &Device::Cpu, DType::F64)?.unsqueeze(0)?;
/// let LocalFeatures::Grid(grid) = encoder.forward(&batch)? else { unreachable!() };
/// assert_eq!(grid.dims(), &[1, 32, 4, 4, 4]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// Naming `config.blocks` when the layers' weights (about `hidden²` values each) pass the
/// allocation limit of 2³³ bytes (8 GiB), checked before any layer is built. Also:
/// A zero `hidden`, `blocks`, `feature_dim`, resolution, `unet.depth` or
/// `unet.start_filters`; a resolution not divisible by `2^(depth − 1)` or whose cells do
/// not fit 32-bit ids; a negative or non-finite `padding` (each naming `config.*`); errors
/// of `vb`.
pub fn conv_onet_encoder(config: &ConvOnetConfig, vb: VarBuilder) -> Result<ConvOnetEncoder> {
    let (dims, res) = match config.layout {
        FeatureLayout::Planes { resolution } => (2, resolution),
        FeatureLayout::Grid { resolution } => (3, resolution),
    };
    for (name, v) in [
        ("config.hidden", config.hidden),
        ("config.blocks", config.blocks),
        ("config.feature_dim", config.feature_dim),
        ("config.layout.resolution", res),
        ("config.unet.depth", config.unet.depth),
        ("config.unet.start_filters", config.unet.start_filters),
    ] {
        if v == 0 {
            return Err(Error::invalid(name, "at least 1", "0"));
        }
    }
    let step = 1usize
        .checked_shl(config.unet.depth as u32 - 1)
        .filter(|&s| s <= res && res % s == 0);
    if step.is_none() || config.unet.depth > 16 {
        return Err(Error::invalid(
            "config.layout.resolution",
            format!(
                "a multiple of 2^(unet.depth − 1) = 2^{}",
                config.unet.depth - 1
            ),
            res.to_string(),
        ));
    }
    if (res as u128).pow(dims as u32) > u128::from(u32::MAX) {
        return Err(Error::invalid(
            "config.layout.resolution",
            "fewer than 2³² cells",
            res.to_string(),
        ));
    }
    if !(config.padding.is_finite() && config.padding >= 0.0) {
        return Err(Error::invalid(
            "config.padding",
            "a finite number ≥ 0",
            config.padding.to_string(),
        ));
    }
    let h = config.hidden;
    let params = h.saturating_mul(h).saturating_mul(2);
    crate::limits::check_layers(
        "config.blocks",
        config.blocks,
        params,
        vb.dtype().size_in_bytes(),
    )?;
    let mut blocks = Vec::with_capacity(config.blocks);
    for i in 0..config.blocks {
        blocks.push(ResnetBlock::new(2 * h, h, vb.pp(format!("block{i}")))?);
    }
    Ok(ConvOnetEncoder {
        fc_pos: candle_nn::linear(3, 2 * h, vb.pp("fc_pos"))?,
        blocks,
        fc_c: candle_nn::linear(h, config.feature_dim, vb.pp("fc_c"))?,
        unet: Unet::new(dims, config.feature_dim, &config.unet, vb.pp("unet"))?,
        config: *config,
        device: vb.device().clone(),
        dtype: vb.dtype(),
    })
}

impl ConvOnetEncoder {
    /// Encodes `B` point clouds `points: [B, N, 3]` (the encoder's dtype and device,
    /// `N ≥ 1`, coordinates in the padded box; points outside fall in the border cells).
    /// Differentiable w.r.t. every parameter (and the points through the point network).
    ///
    /// # Errors
    /// `points` not `[B, N, 3]` of the encoder's dtype and device, `N = 0`, or a NaN
    /// coordinate (naming `points`).
    pub fn forward(&self, points: &Tensor) -> Result<LocalFeatures> {
        check_float(points, "points")?;
        let d = check_shape(
            points,
            "points",
            &[Dim::Any("B"), Dim::Any("N"), Dim::Is(3)],
        )?;
        let (b, n) = (d[0], d[1]);
        if n == 0 {
            return Err(Error::invalid(
                "points",
                "at least one point per cloud (N ≥ 1)",
                "N = 0",
            ));
        }
        if points.dtype() != self.dtype || !points.device().same_device(&self.device) {
            return Err(Error::invalid(
                "points",
                format!("the encoder's dtype {:?} and device", self.dtype),
                format!("{:?} on {:?}", points.dtype(), points.device().location()),
            ));
        }
        let u = normalise(points, self.config.padding)?;
        let (res, cells, views): (usize, usize, Vec<Tensor>) = match self.config.layout {
            FeatureLayout::Planes { resolution } => {
                let mut v = Vec::with_capacity(3);
                for cols in PLANES {
                    v.push(u.index_select(&Tensor::new(&cols, u.device())?, 2)?);
                }
                (resolution, resolution * resolution, v)
            }
            FeatureLayout::Grid { resolution } => {
                (resolution, resolution * resolution * resolution, vec![u])
            }
        };
        let index = views
            .iter()
            .map(|v| cell_index(v, res).map_err(rename_coords))
            .collect::<Result<Vec<_>>>()?;
        // Flat ids b·cells + id, to read the pooled features back at the points.
        let offsets = (Tensor::arange(0u32, b as u32, points.device())?.to_dtype(DType::F64)?
            * cells as f64)?
            .unsqueeze(1)?;
        let flat = index
            .iter()
            .map(|i| -> Result<Tensor> {
                Ok(i.to_dtype(DType::F64)?
                    .broadcast_add(&offsets)?
                    .to_dtype(DType::U32)?
                    .flatten_all()?)
            })
            .collect::<Result<Vec<_>>>()?;
        let h = self.config.hidden;
        let mut net = self.fc_pos.forward(points)?;
        for (i, block) in self.blocks.iter().enumerate() {
            if i > 0 {
                let mut pooled: Option<Tensor> = None;
                for (idx, fl) in index.iter().zip(&flat) {
                    let max = ScatterConfig {
                        pooling: Pooling::Max,
                        ..ScatterConfig::default()
                    };
                    let m = scatter(&net, idx, cells, &max)?.reshape((b * cells, h))?;
                    let back = m.index_select(fl, 0)?.reshape((b, n, h))?;
                    pooled = Some(match pooled {
                        Some(p) => (p + back)?,
                        None => back,
                    });
                }
                if let Some(p) = pooled {
                    net = Tensor::cat(&[&net, &p], 2)?;
                }
            }
            net = block.forward(&net)?;
        }
        let c = self.fc_c.forward(&net)?;
        let ch = self.config.feature_dim;
        let mut grids = Vec::with_capacity(index.len());
        for idx in &index {
            let m = scatter(&c, idx, cells, &ScatterConfig::default())?.transpose(1, 2)?; // [B, C, cells]
            grids.push(match self.config.layout {
                FeatureLayout::Planes { .. } => m.reshape((b, ch, res, res))?,
                FeatureLayout::Grid { .. } => m.reshape((b, ch, res, res, res))?,
            });
        }
        // The planes share the U-Net: one call on the planes stacked on the batch axis.
        let stacked = Tensor::cat(&grids, 0)?;
        let out = self.unet.forward(&stacked)?;
        Ok(match self.config.layout {
            FeatureLayout::Planes { .. } => LocalFeatures::Planes {
                xz: out.narrow(0, 0, b)?,
                xy: out.narrow(0, b, b)?,
                yz: out.narrow(0, 2 * b, b)?,
            },
            FeatureLayout::Grid { .. } => LocalFeatures::Grid(out),
        })
    }
}

/// `cell_index` names its argument `coords`; here it is the encoder's `points`.
fn rename_coords(e: Error) -> Error {
    match e {
        Error::InvalidArgument {
            arg: "coords",
            expected,
            got,
        } => Error::InvalidArgument {
            arg: "points",
            expected,
            got,
        },
        other => other,
    }
}

/// Settings of [`local_decoder`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalDecoderConfig {
    /// Hidden width (published: 32).
    pub hidden: usize,
    /// ResNet-FC blocks (published: 5).
    pub blocks: usize,
    /// Feature channels `C` of the planes or grid it reads (the encoder's `feature_dim`).
    pub feature_dim: usize,
    /// Box padding; must equal the encoder's.
    pub padding: f64,
}

impl Default for LocalDecoderConfig {
    /// The published decoder: width 32, 5 blocks, 32 feature channels, padding 0.1.
    fn default() -> Self {
        Self {
            hidden: 32,
            blocks: 5,
            feature_dim: 32,
            padding: 0.1,
        }
    }
}

/// The local decoder; build it with [`local_decoder`]. Its trunk is the crate's
/// pointwise ResNet with a code added before every block, the code here being the
/// interpolated local feature.
#[derive(Clone, Debug)]
pub struct LocalDecoder {
    trunk: ResnetFc,
    config: LocalDecoderConfig,
}

/// Builds a [`LocalDecoder`] from `vb` (variables `fc_p`, `block{i}.{fc0,fc1}`,
/// `code{i}`, `fc_out`; the output layer starts at zero, so the first logits are 0).
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use candle_nn::{VarBuilder, VarMap};
/// use neural_fields::occupancy::{local_decoder, LocalDecoderConfig, LocalFeatures};
///
/// let varmap = VarMap::new();
/// let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
/// let decoder = local_decoder(&LocalDecoderConfig::default(), vb)?;
/// let grid = LocalFeatures::Grid(Tensor::zeros((1, 32, 8, 8, 8), DType::F32, &Device::Cpu)?);
/// let q = Tensor::zeros((1, 5, 3), DType::F32, &Device::Cpu)?;
/// assert_eq!(decoder.logits(&q, &grid)?.dims(), &[1, 5]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// Naming `config.blocks` when the layers' weights (about `hidden²` values each) pass the
/// allocation limit of 2³³ bytes (8 GiB), checked before any layer is built. Also:
/// A zero `hidden`, `blocks` or `feature_dim`, a negative or non-finite `padding`
/// (naming `config.*`); errors of `vb`.
pub fn local_decoder(config: &LocalDecoderConfig, vb: VarBuilder) -> Result<LocalDecoder> {
    if config.feature_dim == 0 {
        return Err(Error::invalid("config.feature_dim", "at least 1", "0"));
    }
    if !(config.padding.is_finite() && config.padding >= 0.0) {
        return Err(Error::invalid(
            "config.padding",
            "a finite number ≥ 0",
            config.padding.to_string(),
        ));
    }
    Ok(LocalDecoder {
        trunk: ResnetFc::new(3, config.hidden, config.blocks, config.feature_dim, 1, &vb)?,
        config: *config,
    })
}

impl LocalDecoder {
    /// Occupancy logits `[B, M]` (inside where positive) at query points `points:
    /// [B, M, 3]` of the scenes encoded in `features` (batch `B`, the decoder's
    /// `feature_dim` channels, the points' dtype and device). Differentiable w.r.t. the
    /// decoder's parameters and the features (hence the encoder's parameters).
    ///
    /// # Errors
    /// `points` not float `[B, M, 3]` with `B` the features' batch, or of another dtype
    /// or device than the features, or holding a NaN (naming `points`); features with
    /// another channel count (naming `features`).
    pub fn logits(&self, points: &Tensor, features: &LocalFeatures) -> Result<Tensor> {
        let (b, c) = features.batch_and_channels();
        check_float(points, "points")?;
        let d = check_shape(points, "points", &[Dim::Is(b), Dim::Any("M"), Dim::Is(3)])?;
        check_same(points, "points", features.tensors()[0], "features")?;
        if c != self.config.feature_dim {
            return Err(Error::invalid(
                "features",
                format!("{} channels (config.feature_dim)", self.config.feature_dim),
                format!("{c}"),
            ));
        }
        let m = d[1];
        let u = normalise(points, self.config.padding)?;
        let feat = features.sample(&u).map_err(rename_coords)?; // [B, M, C]
        let y = self.trunk.forward(
            &points.reshape((b * m, 3))?,
            Some(&feat.reshape((b * m, c))?),
        )?;
        Ok(y.reshape((b, m))?)
    }

    /// Binds one encoded scene (batch 1) so that the decoder is a [`Field`] of the
    /// points (`[N, 3]` → logits `[N, 1]`).
    ///
    /// # Errors
    /// `features` with a batch other than 1 (naming `features`).
    pub fn bind(&self, features: LocalFeatures) -> Result<SceneField<'_>> {
        let (b, _) = features.batch_and_channels();
        if b != 1 {
            return Err(Error::invalid(
                "features",
                "one encoded scene (batch 1)",
                format!("batch {b}"),
            ));
        }
        Ok(SceneField {
            decoder: self,
            features,
        })
    }
}

/// A [`LocalDecoder`] bound to one encoded scene: a [`Field`] with one output channel
/// (the occupancy logit, inside where positive). Build it with [`LocalDecoder::bind`].
#[derive(Clone, Debug)]
pub struct SceneField<'a> {
    decoder: &'a LocalDecoder,
    features: LocalFeatures,
}

impl Field for SceneField<'_> {
    fn out_dim(&self) -> usize {
        1
    }

    /// Logits `[N, 1]` at `points: [N, 3]`; differentiable as [`LocalDecoder::logits`].
    fn forward(&self, points: &Tensor) -> Result<Tensor> {
        let n = check_points(points, "points")?;
        Ok(self
            .decoder
            .logits(&points.unsqueeze(0)?, &self.features)?
            .reshape((n, 1))?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;
    use crate::test_host::v64;
    use candle_core::Var;

    fn arg_of(e: Error) -> String {
        match e {
            Error::InvalidArgument { arg, .. } => arg.to_string(),
            other => panic!("expected an invalid argument, got {other}"),
        }
    }

    /// `y[b, o, z, y, x] = Σ w[o, i, a, β, γ] x_pad[b, i, z + a, y + β, x + γ]` by loops,
    /// and its adjoints (the gradients of `Σ G ⊙ y` w.r.t. `x` and `w`).
    #[allow(clippy::type_complexity)]
    fn naive(
        x: &[f64],
        xd: [usize; 5],
        w: &[f64],
        wd: [usize; 5],
        pad: usize,
        g: Option<&[f64]>,
    ) -> (Vec<f64>, [usize; 5], Vec<f64>, Vec<f64>) {
        let [b, ci, d, h, wi] = xd;
        let [co, _, kd, kh, kw] = wd;
        let (od, oh, ow) = (
            d + 2 * pad + 1 - kd,
            h + 2 * pad + 1 - kh,
            wi + 2 * pad + 1 - kw,
        );
        let od5 = [b, co, od, oh, ow];
        let mut y = vec![0.0; b * co * od * oh * ow];
        let mut gx = vec![0.0; x.len()];
        let mut gw = vec![0.0; w.len()];
        for n in 0..b {
            for o in 0..co {
                for z in 0..od {
                    for yy in 0..oh {
                        for xx in 0..ow {
                            let yi = (((n * co + o) * od + z) * oh + yy) * ow + xx;
                            let gy = g.map_or(0.0, |g| g[yi]);
                            for i in 0..ci {
                                for a in 0..kd {
                                    for be in 0..kh {
                                        for ga in 0..kw {
                                            let (pz, py, px) = (z + a, yy + be, xx + ga);
                                            if pz < pad || py < pad || px < pad {
                                                continue;
                                            }
                                            let (sz, sy, sx) = (pz - pad, py - pad, px - pad);
                                            if sz >= d || sy >= h || sx >= wi {
                                                continue;
                                            }
                                            let xi = (((n * ci + i) * d + sz) * h + sy) * wi + sx;
                                            let wi_ = (((o * ci + i) * kd + a) * kh + be) * kw + ga;
                                            y[yi] += w[wi_] * x[xi];
                                            gx[xi] += w[wi_] * gy;
                                            gw[wi_] += x[xi] * gy;
                                        }
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
        (y, od5, gx, gw)
    }

    #[test]
    fn conv3d_matches_the_direct_sum_in_values_and_gradients() {
        let mut rng = SplitMix64::new(9);
        for (xd, wd, pad) in [
            ([2usize, 3, 4, 5, 3], [4usize, 3, 3, 3, 3], 1usize),
            ([1, 2, 5, 4, 6], [3, 2, 2, 3, 1], 0),
            ([1, 2, 3, 3, 3], [2, 2, 1, 1, 1], 0),
            ([1, 1, 2, 3, 2], [2, 1, 3, 2, 3], 2),
        ] {
            let xv: Vec<f64> = (0..xd.iter().product())
                .map(|_| rng.uniform() - 0.5)
                .collect();
            let wv: Vec<f64> = (0..wd.iter().product())
                .map(|_| rng.uniform() - 0.5)
                .collect();
            let x = Var::from_vec(xv.clone(), xd.as_slice(), &Device::Cpu).unwrap();
            let w = Var::from_vec(wv.clone(), wd.as_slice(), &Device::Cpu).unwrap();
            let y = conv3d(x.as_tensor(), w.as_tensor(), pad).unwrap();
            let (want, od, _, _) = naive(&xv, xd, &wv, wd, pad, None);
            assert_eq!(y.dims(), od.as_slice());
            let got = v64(&y);
            let err = got
                .iter()
                .zip(&want)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(err < 1e-12, "{xd:?} {wd:?} pad {pad}: {err}");
            let gy: Vec<f64> = (0..want.len())
                .map(|i| ((i * 31) % 7) as f64 - 3.0)
                .collect();
            let gt = Tensor::from_vec(gy.clone(), od.as_slice(), &Device::Cpu).unwrap();
            let grads = (y * gt).unwrap().sum_all().unwrap().backward().unwrap();
            let (_, _, gx, gw) = naive(&xv, xd, &wv, wd, pad, Some(&gy));
            for (name, got, want) in [
                ("input", v64(grads.get(x.as_tensor()).unwrap()), gx),
                ("weight", v64(grads.get(w.as_tensor()).unwrap()), gw),
            ] {
                let err = got
                    .iter()
                    .zip(&want)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                assert!(err < 1e-11, "{name} {xd:?} {wd:?} pad {pad}: {err}");
            }
        }
    }

    /// Extreme inputs under unit weights and extreme weights under unit inputs (from 0 to
    /// 1e30 in f32, 1e300 in f64, both signs): finite values and gradients.
    #[test]
    fn conv3d_stays_finite_at_extreme_magnitudes() -> Result<()> {
        for dtype in [DType::F32, DType::F64] {
            let top = if dtype == DType::F32 { 1e30 } else { 1e300 };
            let mut mags = vec![
                0.0, 1e-45, 1e-30, 1e-12, 1e-6, 0.5, 1.0, 88.0, 1e4, 1e10, top,
            ];
            if dtype == DType::F64 {
                mags.extend([1e-300, 1e30]);
            }
            let neg: Vec<f64> = mags.iter().map(|x| -x).collect();
            mags.extend(neg);
            let extreme: Vec<f64> = (0..2 * 27).map(|i| mags[(i * 5) % mags.len()]).collect();
            let unit: Vec<f64> = (0..2 * 27).map(|i| ((i % 7) as f64 - 3.0) / 3.0).collect();
            for (x, w, tag) in [(&extreme, &unit, "inputs"), (&unit, &extreme, "weights")] {
                let var = |v: &[f64]| -> Result<Var> {
                    let t = Tensor::from_slice(v, (1, 2, 3, 3, 3), &Device::Cpu)?;
                    Ok(Var::from_tensor(&t.to_dtype(dtype)?)?)
                };
                let (x, w) = (var(x)?, var(w)?);
                for padding in [1, 0] {
                    let y = conv3d(x.as_tensor(), w.as_tensor(), padding)?;
                    let label = format!("{dtype:?}, extreme {tag}, padding {padding}");
                    assert!(v64(&y).iter().all(|a| a.is_finite()), "{label}");
                    let grads = y.sum_all()?.backward()?;
                    for v in [&x, &w] {
                        let g = grads.get(v.as_tensor()).expect("a gradient");
                        assert!(v64(g).iter().all(|a| a.is_finite()), "{label}: gradient");
                    }
                }
            }
        }
        Ok(())
    }

    #[test]
    fn features_report_their_batch_and_channels() -> Result<()> {
        let plane = || Tensor::zeros((2, 6, 8, 8), DType::F32, &Device::Cpu);
        let planes = LocalFeatures::Planes {
            xz: plane()?,
            xy: plane()?,
            yz: plane()?,
        };
        assert_eq!(planes.batch_and_channels(), (2, 6));
        let grid = LocalFeatures::Grid(Tensor::zeros((2, 6, 4, 4, 4), DType::F32, &Device::Cpu)?);
        assert_eq!(grid.batch_and_channels(), (2, 6));
        Ok(())
    }

    #[test]
    fn an_interior_voxel_sums_its_window() -> Result<()> {
        let x = Tensor::ones((1, 2, 4, 4, 4), DType::F64, &Device::Cpu)?;
        let w = Tensor::ones((3, 2, 3, 3, 3), DType::F64, &Device::Cpu)?;
        let y = conv3d(&x, &w, 1)?;
        assert_eq!(y.dims(), &[1, 3, 4, 4, 4]);
        // An interior voxel sees 2 channels × 27 ones.
        let v = y
            .get(0)?
            .get(0)?
            .get(1)?
            .get(1)?
            .get(1)?
            .to_scalar::<f64>()?;
        assert_eq!(v, 54.0);
        Ok(())
    }

    #[test]
    fn bad_conv3d_inputs_are_errors_naming_the_argument() {
        let d = Device::Cpu;
        let x = Tensor::zeros((1, 2, 3, 3, 3), DType::F64, &d).unwrap();
        assert_eq!(
            arg_of(
                conv3d(
                    &x,
                    &Tensor::zeros((1, 3, 3, 3, 3), DType::F64, &d).unwrap(),
                    1
                )
                .unwrap_err()
            ),
            "weight"
        );
        assert_eq!(
            arg_of(
                conv3d(
                    &x,
                    &Tensor::zeros((1, 2, 6, 3, 3), DType::F64, &d).unwrap(),
                    1
                )
                .unwrap_err()
            ),
            "weight"
        );
        assert_eq!(
            arg_of(conv3d(&x.flatten_all().unwrap(), &x, 1).unwrap_err()),
            "input"
        );
    }
}
