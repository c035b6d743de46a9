//! The image encoder of the single-view Occupancy Network (Mescheder et al. 2019, §4.2):
//! ResNet-18's layout (He et al. 2016) at a reduced width, ending in a linear map to the
//! code `c` that conditions the [`OnetDecoder`](super::OnetDecoder).
//!
//! On the CPU (f32/f64) the convolutions run on channels-last activations (`[B, h·w, C]`)
//! as one fused op each, which gathers each tile's windows and multiplies them by the
//! weight with the crate's matrix product, forward and backward, and computes no gradient
//! w.r.t. constant images; elsewhere, and with [`ResnetEncoderConfig::force_reference`],
//! they are candle-nn's `Conv2d` on `[B, C, H, W]`. Both compute the same function (the
//! tests compare them); docs/benchmarks.md has the cost of a training step.

use super::onet::running_update;
use crate::error::{check_finite, check_float, check_same, check_shape, Dim, Error, Result};
use crate::kernels::{BufferPool, FusedBatchNorm, FusedConv};
use candle_core::Tensor;
use candle_core::Var;
use candle_nn::{
    batch_norm, conv2d_no_bias, linear, BatchNorm, BatchNormConfig, Conv2d, Conv2dConfig, Linear,
    Module, ModuleT, VarBuilder,
};
use std::sync::{Arc, PoisonError};

/// The smallest image side [`ResnetEncoder::forward`] accepts: the network's total
/// stride, so that the last stage sees at least one cell of image.
const MIN_SIDE: usize = 32;

/// Settings of [`resnet_encoder`].
#[derive(Clone, Debug, PartialEq)]
pub struct ResnetEncoderConfig {
    /// Channels `C` of the input images (3 for RGB).
    pub in_channels: usize,
    /// Base width `w`: channels of the stem and the first stage; the stages have `w`,
    /// `2w`, `4w`, `8w` (ResNet-18: 64).
    pub width: usize,
    /// Basic blocks per stage, each ≥ 1 (ResNet-18: `[2, 2, 2, 2]`).
    pub blocks: [usize; 4],
    /// Dimension of the code `c` (ONet's single-view model: 256).
    pub c_dim: usize,
    /// Running-statistics momentum `m` of the batch normalisation (PyTorch's 0.1).
    pub momentum: f64,
    /// `ε` of the batch normalisation (1e-5).
    pub eps: f64,
    /// Run the convolutions as candle-nn's `Conv2d` on `[B, C, H, W]` tensors even where
    /// the fused channels-last convolution applies (f32/f64 on the CPU; the same
    /// function, tests compare the two). Default `false`.
    pub force_reference: bool,
}

impl Default for ResnetEncoderConfig {
    /// RGB input; ResNet-18's blocks `[2, 2, 2, 2]` at half its width, `w = 32` (about
    /// 2.8 M parameters instead of 11 M and a quarter of the multiply-adds: a training
    /// pass of 32 images at 64 × 64 takes about 0.6 s on one CPU core, 0.17 s at width 16;
    /// docs/benchmarks.md); `c_dim = 256`, ONet's code size for images and the
    /// default `code_dim` of [`OnetConfig`](super::OnetConfig), so the two defaults plug
    /// together.
    fn default() -> Self {
        Self {
            in_channels: 3,
            width: 32,
            blocks: [2, 2, 2, 2],
            c_dim: 256,
            momentum: 0.1,
            eps: 1e-5,
            force_reference: false,
        }
    }
}

/// One basic block: two 3×3 convolutions with batch norm, and the shortcut.
#[derive(Clone, Debug)]
struct BasicBlock {
    conv1: Conv2d,
    bn1: BatchNorm,
    conv2: Conv2d,
    bn2: BatchNorm,
    /// The 1×1 projection and its batch norm where the block changes shape.
    downsample: Option<(Conv2d, BatchNorm)>,
    /// The first convolution's and the projection's stride (1 or 2).
    stride: usize,
}

impl BasicBlock {
    fn forward(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        let x = &if self.stride == 2 {
            even(x)?
        } else {
            x.clone()
        };
        let h = self.bn1.forward_t(&self.conv1.forward(x)?, train)?.relu()?;
        let h = self.bn2.forward_t(&self.conv2.forward(&h)?, train)?;
        let shortcut = match &self.downsample {
            Some((conv, bn)) => bn.forward_t(&conv.forward(x)?, train)?,
            None => x.clone(),
        };
        Ok((h + shortcut)?.relu()?)
    }

    /// [`BasicBlock::forward`] on channels-last images `x: [B, h·w, C]` of `h × w` pixels,
    /// with the fused convolution: `([B, h'·w', C'], [h', w'])`.
    fn forward_cl(
        &self,
        x: &Tensor,
        hw: [usize; 2],
        train: bool,
        pool: &Arc<BufferPool>,
    ) -> Result<(Tensor, [usize; 2])> {
        let (h, out) = conv_cl(&self.conv1, x, hw, self.stride, pool)?;
        let h = bn_cl(&self.bn1, &h, train, true)?;
        let (h, _) = conv_cl(&self.conv2, &h, out, 1, pool)?;
        let h = bn_cl(&self.bn2, &h, train, false)?;
        let shortcut = match &self.downsample {
            Some((conv, bn)) => {
                let (y, _) = conv_cl(conv, x, hw, self.stride, pool)?;
                bn_cl(bn, &y, train, false)?
            }
            None => x.clone(),
        };
        Ok(((h + shortcut)?.relu()?, out))
    }
}

/// A convolution of `conv`'s weight (no bias, padding `⌊k/2⌋`, stride `stride`) of
/// channels-last images `x: [B, h·w, Cᵢ]` of `h × w` pixels, as the fused op with its
/// buffers in `pool`: `([B, h'·w', Cₒ], [h', w'])`.
fn conv_cl(
    conv: &Conv2d,
    x: &Tensor,
    [h, w]: [usize; 2],
    stride: usize,
    pool: &Arc<BufferPool>,
) -> Result<(Tensor, [usize; 2])> {
    let weight = conv.weight();
    let (co, ci, k, _) = weight.dims4()?;
    let op = FusedConv::square(x.dim(0)?, [h, w], k, stride, [ci, co]).with_pool(Arc::clone(pool));
    let out = op.out_size().ok_or_else(|| {
        Error::invalid(
            "images",
            "a side of at least the kernel",
            format!("{h} × {w}"),
        )
    })?;
    let bias = Tensor::zeros(co, x.dtype(), x.device())?;
    let y = x.contiguous()?.apply_op3(weight, &bias, op)?;
    Ok((y, [out[1], out[2]]))
}

/// `bn` on channels-last images `x: [B, n, C]`, followed by a ReLU where `relu`: the
/// statistics per channel over the batch and the pixels, as on `[B, C, H, W]`. In
/// training one fused op on the `B·n` rows, whose batch statistics then update `bn`'s
/// running ones as candle-nn's `BatchNorm` does (`r ← (1 − m)·r + m·stat`, the variance
/// unbiased); in inference candle-nn's.
fn bn_cl(bn: &BatchNorm, x: &Tensor, train: bool, relu: bool) -> Result<Tensor> {
    let (b, n, c) = x.dims3()?;
    let rows = x.reshape((b * n, c))?;
    let Some((gamma, beta)) = bn.weight_and_bias().filter(|_| train) else {
        let y = bn.forward_t(&rows, train)?.reshape((b, n, c))?;
        return Ok(if relu { y.relu()? } else { y });
    };
    let op = FusedBatchNorm::new(b * n, c, bn.eps(), relu);
    // The op's batch statistics, kept for its backward pass and read here.
    let saved = op.saved();
    let y = rows.contiguous()?.apply_op3(gamma, beta, op)?;
    let stats = saved
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .clone()
        .ok_or_else(|| Error::invalid("images", "a batch-norm pass with statistics", "none"))?;
    let (rm, rv) = (bn.running_mean(), bn.running_var());
    let column = |v: Vec<f64>| -> Result<Tensor> {
        Ok(Tensor::from_vec(v, c, rm.device())?.to_dtype(rm.dtype())?)
    };
    let batch = (&column(stats.mean)?, &column(stats.var)?);
    let (mean, var) = running_update((rm, rv), batch, b * n, bn.momentum())?;
    Var::from_tensor(rm)?.set(&mean)?;
    Var::from_tensor(rv)?.set(&var)?;
    Ok(y.reshape((b, n, c))?)
}

/// The image encoder; build it with [`resnet_encoder`].
///
/// For images `x: [B, C, H, W]` with base width `w`:
/// * stem: `relu(BN(conv₇ₓ₇,stride 2,pad 3(x)))`, then a 3×3 max-pool with stride 2 and
///   padding 1: `[B, w, ⌈H/4⌉, ⌈W/4⌉]`;
/// * four stages of basic blocks, `w`, `2w`, `4w`, `8w` channels, the first block of
///   stages 2–4 with stride 2: `y = relu(BN(conv₃ₓ₃(relu(BN(conv₃ₓ₃(x))))) + s(x))`,
///   the shortcut `s` the identity, or `BN(conv₁ₓ₁,stride 2(x))` where the block changes
///   shape; after the last stage `[B, 8w, ⌈H/32⌉, ⌈W/32⌉]`;
/// * global average pool over the pixels, and `c = W_fc g + b_fc`: `[B, c_dim]`.
///
/// The stem is ResNet-18's 7×7 stride-2 convolution and max-pool, not the 3×3 stride-1
/// stem of small-image ResNets: it keeps the layout (and torchvision's variable names)
/// of the network ONet used, and it divides the pixels the four stages see by 16, which
/// is what makes a 64 × 64 batch affordable on a CPU — a stride-1 stem would run the first
/// stage on 16 times as many pixels. At 64 × 64 the last stage still sees 2 × 2 cells.
///
/// Batch normalisation is candle-nn's [`BatchNorm`] (its variables and its function; in
/// training on the CPU one fused op per layer computes it). With `train = true` it
/// normalises each channel by the mean and biased variance over the batch and the pixels, and
/// updates its running statistics in place, `r ← (1 − m)·r + m·stat` (the variance
/// unbiased, as PyTorch); with `train = false` it uses the running statistics only, so
/// an image's code does not depend on the other images of the batch. The running
/// statistics are variables of the `VarBuilder`'s map (`running_mean`, `running_var`):
/// they are saved and loaded with the weights, and receive no gradient, so optimisers
/// that skip variables without one (candle-nn's, [`crate::nn::adam`]) leave them alone.
#[derive(Clone, Debug)]
pub struct ResnetEncoder {
    conv1: Conv2d,
    bn1: BatchNorm,
    blocks: Vec<BasicBlock>,
    fc: Linear,
    config: ResnetEncoderConfig,
    /// The fused convolutions' weight matrices and partial sums between calls.
    scratch: Arc<BufferPool>,
}

/// Builds a [`ResnetEncoder`] from `vb`, with torchvision's variable names: `conv1`,
/// `bn1`, `layer{1..4}.{i}.{conv1,bn1,conv2,bn2}`, `layer{s}.0.downsample.{0,1}` (the
/// projection shortcuts) and `fc`. Convolutions have no bias and candle-nn's Kaiming
/// initialisation; batch norms start at `γ = 1, β = 0` with running mean 0 and variance
/// 1; `fc` is candle-nn's [`linear()`]. The dtype and device are `vb`'s (f32 or f64).
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use candle_nn::VarMap;
/// use neural_fields::nn::build_seeded;
/// use neural_fields::occupancy::{resnet_encoder, ResnetEncoderConfig};
///
/// let config = ResnetEncoderConfig { width: 8, c_dim: 16, ..ResnetEncoderConfig::default() };
/// let varmap = VarMap::new();
/// let enc = build_seeded(&varmap, DType::F32, &Device::Cpu, 0, |vb| resnet_encoder(&config, vb))?;
/// let images = Tensor::zeros((2, 3, 64, 64), DType::F32, &Device::Cpu)?;
/// assert_eq!(enc.forward(&images, false)?.dims(), &[2, 16]);
/// // Weights, biases and the batch norms' running statistics, named as torchvision's.
/// let vars = varmap.data().lock().map_err(|e| candle_core::Error::Msg(e.to_string()))?;
/// assert!(vars.contains_key("layer2.0.downsample.1.running_var"));
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// A zero `in_channels`, `width`, `c_dim` or stage of `blocks` (naming `config.*`);
/// `momentum ∉ [0, 1]`; `eps ≤ 0` or not finite; naming `config.width`, `config.blocks`
/// or `config.c_dim` when the weights pass the allocation limit of 2³³ bytes (8 GiB),
/// checked before any layer is built; errors of `vb`.
pub fn resnet_encoder(config: &ResnetEncoderConfig, vb: VarBuilder) -> Result<ResnetEncoder> {
    for (name, v) in [
        ("config.in_channels", config.in_channels),
        ("config.width", config.width),
        ("config.c_dim", config.c_dim),
    ] {
        if v == 0 {
            return Err(Error::invalid(name, "at least 1", "0"));
        }
    }
    if config.blocks.contains(&0) {
        return Err(Error::invalid(
            "config.blocks",
            "at least one block per stage",
            format!("{:?}", config.blocks),
        ));
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
            "a finite number > 0",
            format!("{}", config.eps),
        ));
    }
    check_weights(config, vb.dtype().size_in_bytes())?;
    let w = config.width;
    let bn_config = BatchNormConfig {
        eps: config.eps,
        momentum: config.momentum,
        ..BatchNormConfig::default()
    };
    let conv = |input: usize, out: usize, k: usize, stride: usize, vb: VarBuilder| {
        let cfg = Conv2dConfig {
            padding: k / 2,
            stride,
            ..Conv2dConfig::default()
        };
        conv2d_no_bias(input, out, k, cfg, vb)
    };
    let conv1 = conv(config.in_channels, w, 7, 2, vb.pp("conv1"))?;
    let bn1 = batch_norm(w, bn_config, vb.pp("bn1"))?;
    let mut blocks = Vec::new();
    let mut channels = w;
    for (s, &count) in config.blocks.iter().enumerate() {
        let out = w << s;
        for i in 0..count {
            let bvb = vb.pp(format!("layer{}.{i}", s + 1));
            let stride = if s > 0 && i == 0 { 2 } else { 1 };
            let downsample = if stride != 1 || channels != out {
                Some((
                    conv(channels, out, 1, stride, bvb.pp("downsample.0"))?,
                    batch_norm(out, bn_config, bvb.pp("downsample.1"))?,
                ))
            } else {
                None
            };
            blocks.push(BasicBlock {
                conv1: conv(channels, out, 3, stride, bvb.pp("conv1"))?,
                bn1: batch_norm(out, bn_config, bvb.pp("bn1"))?,
                conv2: conv(out, out, 3, 1, bvb.pp("conv2"))?,
                bn2: batch_norm(out, bn_config, bvb.pp("bn2"))?,
                downsample,
                stride,
            });
            channels = out;
        }
    }
    Ok(ResnetEncoder {
        conv1,
        bn1,
        blocks,
        fc: linear(channels, config.c_dim, vb.pp("fc"))?,
        config: config.clone(),
        scratch: Arc::default(),
    })
}

/// Refuses a configuration whose weights pass the allocation limit: one block of the
/// widest stage (naming `config.width`), all blocks (naming `config.blocks`), the final
/// linear map (naming `config.c_dim`).
fn check_weights(config: &ResnetEncoderConfig, elem_bytes: usize) -> Result<()> {
    let widest = config.width.saturating_mul(8);
    // Two 3×3 convolutions and a 1×1 projection of the widest stage, and the stem.
    let block = widest
        .saturating_mul(widest)
        .saturating_mul(19)
        .saturating_add(
            config
                .in_channels
                .saturating_mul(config.width)
                .saturating_mul(49),
        );
    crate::limits::check_bytes("config.width", &[block], elem_bytes)?;
    let count = config
        .blocks
        .iter()
        .fold(0usize, |acc, &b| acc.saturating_add(b));
    crate::limits::check_layers("config.blocks", count, block, elem_bytes)?;
    crate::limits::check_bytes("config.c_dim", &[widest, config.c_dim], elem_bytes)?;
    Ok(())
}

impl ResnetEncoder {
    /// The codes `c: [B, c_dim]` of `images: [B, C, H, W]` (`C = in_channels`,
    /// `H, W ≥ 32`, any other size: 64 × 64 and 128 × 128 are typical), f32 or f64 like
    /// the encoder's weights. Pixels are used as given; standardise them (e.g. to zero
    /// mean and unit variance per channel over the data set) as for any ResNet.
    ///
    /// `train = true` normalises with the batch's statistics and updates the running
    /// statistics (see [`ResnetEncoder`]); it needs at least two values per channel
    /// at the last stage, `B·⌈H/32⌉·⌈W/32⌉ ≥ 2`. `train = false` uses the running
    /// statistics: each image's code is independent of the rest of the batch.
    ///
    /// Differentiable w.r.t. the weights (convolutions, batch-norm `γ, β`, `fc`) and the
    /// images. Max-pool and ReLU pass the subgradient: where several entries of a pooling
    /// window tie, they share its gradient.
    ///
    /// ```
    /// use candle_core::{DType, Device, Tensor};
    /// use candle_nn::VarMap;
    /// use neural_fields::nn::build_seeded;
    /// use neural_fields::occupancy::{resnet_encoder, ResnetEncoderConfig};
    ///
    /// let config = ResnetEncoderConfig {
    ///     width: 8,
    ///     blocks: [1; 4],
    ///     c_dim: 4,
    ///     ..ResnetEncoderConfig::default()
    /// };
    /// let varmap = VarMap::new();
    /// let dev = Device::Cpu;
    /// let enc = build_seeded(&varmap, DType::F64, &dev, 1, |vb| resnet_encoder(&config, vb))?;
    /// let images = Tensor::rand(0.0, 1.0, (3, 3, 32, 48), &dev)?;
    /// let codes = enc.forward(&images, true)?; // batch statistics, running ones updated
    /// assert_eq!(codes.dims(), &[3, 4]);
    /// let grads = codes.sqr()?.sum_all()?.backward()?;
    /// let vars = varmap.data().lock().map_err(|e| candle_core::Error::Msg(e.to_string()))?;
    /// assert!(grads.get(&vars["conv1.weight"]).is_some());
    /// assert!(grads.get(&vars["bn1.running_mean"]).is_none()); // statistics, not weights
    /// // Inference: running statistics, so the first image alone gets the same code.
    /// let all = enc.forward(&images, false)?.get(0)?;
    /// let one = enc.forward(&images.narrow(0, 0, 1)?, false)?.get(0)?;
    /// let gap = (all - one)?.abs()?.max(0)?.to_scalar::<f64>()?;
    /// assert!(gap < 1e-12);
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// Naming `images`: not f32/f64 or not the weights' dtype and device; not rank 4 with
    /// `C` channels; an empty batch; `H` or `W` below 32; a NaN or infinite pixel; in
    /// training, fewer than two values per channel at the last stage; activations that
    /// would pass the allocation limit of 2³³ bytes (the stem's im2col buffer,
    /// `B·⌈H/2⌉·⌈W/2⌉·max(49·C, 9·w)` values, bounds them).
    pub fn forward(&self, images: &Tensor, train: bool) -> Result<Tensor> {
        check_float(images, "images")?;
        check_same(images, "images", self.fc.weight(), "the encoder's weights")?;
        let dims = check_shape(
            images,
            "images",
            &[
                Dim::Any("B"),
                Dim::Is(self.config.in_channels),
                Dim::Any("H"),
                Dim::Any("W"),
            ],
        )?;
        let (b, h, w) = (dims[0], dims[2], dims[3]);
        if b == 0 {
            return Err(Error::invalid(
                "images",
                "at least one image (B ≥ 1)",
                "B = 0",
            ));
        }
        if h < MIN_SIDE || w < MIN_SIDE {
            return Err(Error::invalid(
                "images",
                format!("height and width of at least {MIN_SIDE} pixels"),
                format!("{h} × {w}"),
            ));
        }
        let last = b * h.div_ceil(MIN_SIDE) * w.div_ceil(MIN_SIDE);
        if train && last < 2 {
            return Err(Error::invalid(
                "images",
                "in training, at least two values per channel at the last stage \
                 (B·⌈H/32⌉·⌈W/32⌉ ≥ 2) for the batch statistics",
                format!("{b} image of {h} × {w}"),
            ));
        }
        let per_pixel = (49 * self.config.in_channels).max(9 * self.config.width);
        crate::limits::check_bytes(
            "images",
            &[b, h.div_ceil(2), w.div_ceil(2), per_pixel],
            images.dtype().size_in_bytes(),
        )?;
        check_finite(images, "images")?;
        if !self.config.force_reference && crate::kernels::cpu_fused_for(images) {
            return self.forward_cl(images, train);
        }
        let x = self
            .bn1
            .forward_t(&self.conv1.forward(&even(images)?)?, train)?;
        let mut x = max_pool_3x3_stride_2(&x.relu()?, [2, 3])?;
        for block in &self.blocks {
            x = block.forward(&x, train)?;
        }
        let pooled = x.mean(3)?.mean(2)?;
        Ok(self.fc.forward(&pooled)?)
    }

    /// [`ResnetEncoder::forward`] on channels-last activations (`[B, h·w, C]`) with the
    /// fused convolution, for checked `images`.
    fn forward_cl(&self, images: &Tensor, train: bool) -> Result<Tensor> {
        let (b, c, h, w) = images.dims4()?;
        let x = images.permute((0, 2, 3, 1))?.reshape((b, h * w, c))?;
        let (x, [h, w]) = conv_cl(&self.conv1, &x, [h, w], 2, &self.scratch)?;
        let x = bn_cl(&self.bn1, &x, train, true)?;
        let channels = x.dim(2)?;
        let x = max_pool_3x3_stride_2(&x.reshape((b, h, w, channels))?, [1, 2])?;
        let (h, w) = (x.dim(1)?, x.dim(2)?);
        let mut x = x.reshape((b, h * w, channels))?;
        let mut hw = [h, w];
        for block in &self.blocks {
            (x, hw) = block.forward_cl(&x, hw, train, &self.scratch)?;
        }
        Ok(self.fc.forward(&x.mean(1)?)?)
    }
}

/// `x: [B, C, h, w]` with a zero row appended where `h` is odd and a zero column where
/// `w` is odd. A convolution with stride 2, an odd kernel `k` and padding `⌊k/2⌋` never
/// reads past row `h` of an odd-sized input, so its output is unchanged; but candle's
/// convolution gradient takes the transposed convolution's output padding from the
/// height alone, and fails with a shape mismatch where the height and the width differ in
/// parity. Every stride-2 convolution here sees even sides.
fn even(x: &Tensor) -> Result<Tensor> {
    let (h, w) = (x.dim(2)?, x.dim(3)?);
    let x = if h % 2 == 1 {
        x.pad_with_zeros(2, 0, 1)?
    } else {
        x.clone()
    };
    Ok(if w % 2 == 1 {
        x.pad_with_zeros(3, 0, 1)?
    } else {
        x
    })
}

/// ResNet's 3×3 max-pool with stride 2 and padding 1 over the two pixel axes `axes` of
/// `x` (`[2, 3]` of `[B, C, h, w]`, `[1, 2]` of channels-last `[B, h, w, C]`) with `x ≥ 0`
/// (it follows a ReLU, so zero padding is the same as −∞ padding): each axis of `n`
/// pixels becomes `⌈n/2⌉`. candle's max-pool has no padding, and no gradient where the window is
/// larger than the stride, so it is composed of strided views and `maximum`, per axis.
fn max_pool_3x3_stride_2(x: &Tensor, [ax, ay]: [usize; 2]) -> Result<Tensor> {
    let along = |x: &Tensor, axis: usize| -> Result<Tensor> {
        let n = x.dim(axis)?;
        let out = n.div_ceil(2);
        // Rows −1 … 2·out: one zero row before, one or two after.
        let padded = x.pad_with_zeros(axis, 1, 2 * out + 1 - n)?;
        let mut dims = padded.dims().to_vec();
        dims[axis] = out;
        dims.insert(axis + 1, 2);
        let take = |offset: usize| -> Result<Tensor> {
            // Entries offset, offset + 2, …, offset + 2·(out − 1).
            Ok(padded
                .narrow(axis, offset, 2 * out)?
                .reshape(dims.as_slice())?
                .narrow(axis + 1, 0, 1)?
                .squeeze(axis + 1)?)
        };
        Ok(take(0)?.maximum(&take(1)?)?.maximum(&take(2)?)?)
    };
    along(&along(x, ax)?, ay)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// The composed pool equals the definition (max over the window, padding ignored)
    /// for even and odd sides; `even` leaves a stride-2 convolution's output unchanged.
    #[test]
    fn max_pool_and_even_padding_match_their_definitions() -> Result<()> {
        let d = Device::Cpu;
        for (h, w) in [(6, 6), (7, 5), (5, 8), (1, 2)] {
            let x = Tensor::rand(0.0f64, 1.0, (2, 3, h, w), &d)?;
            let got = max_pool_3x3_stride_2(&x, [2, 3])?;
            let (ho, wo) = (h.div_ceil(2), w.div_ceil(2));
            assert_eq!(got.dims(), &[2, 3, ho, wo]);
            let xv = x.flatten_all()?.to_vec1::<f64>()?;
            let gv = got.flatten_all()?.to_vec1::<f64>()?;
            for nc in 0..6 {
                for oy in 0..ho {
                    for ox in 0..wo {
                        let mut m = f64::NEG_INFINITY;
                        for y in (2 * oy).saturating_sub(1)..(2 * oy + 2).min(h) {
                            for x in (2 * ox).saturating_sub(1)..(2 * ox + 2).min(w) {
                                m = m.max(xv[(nc * h + y) * w + x]);
                            }
                        }
                        assert_eq!(gv[(nc * ho + oy) * wo + ox], m);
                    }
                }
            }
            for (k, p) in [(7, 3), (3, 1), (1, 0)] {
                let kernel = Tensor::rand(-1.0f64, 1.0, (4, 3, k, k), &d)?;
                let plain = x.conv2d(&kernel, p, 2, 1, 1)?;
                let padded = even(&x)?.conv2d(&kernel, p, 2, 1, 1)?;
                let gap = (plain - padded)?.abs()?.max_all()?.to_scalar::<f64>()?;
                assert_eq!(gap, 0.0, "{h} × {w}, kernel {k}");
            }
        }
        Ok(())
    }
}
