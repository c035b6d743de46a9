//! The voxel encoder of the Occupancy Network's voxel super-resolution model (Mescheder
//! et al. 2019, §4.3; ONet's `VoxelEncoder`): a 3-D CNN that maps a coarse occupancy grid
//! to the code `c` that conditions the [`OnetDecoder`](super::OnetDecoder).
//!
//! The convolutions run on channels-last grids (`[B, R³, C]`, voxel `(i, j, k)` at row
//! `(i·R + j)·R + k`) as a gather and a matrix product each: the `27·C` inputs of every
//! output voxel are gathered (im2col; voxels outside the grid read zero) and multiplied
//! by the weight as a `[27·C, C']` matrix. A stride-2 convolution gathers only the windows
//! of the voxels it keeps, so it is exactly the stride-1 convolution followed by keeping
//! every other voxel of each axis (tested against the crate's `conv3d` so subsampled,
//! values and gradients) at an eighth of its multiply-adds and memory.
//!
//! On the CPU the whole chain of convolutions, each with its bias and the ReLU before it,
//! is one fused op that gathers and multiplies tile by tile and scatters each input
//! gradient straight into its grid, the intermediate grids and their gradients in buffers
//! the encoder keeps between calls; elsewhere (and with [`VoxelEncoderConfig::force_reference`]) the same
//! function runs as candle's ops: `index_select` of the whole window matrix, a matrix
//! product, and `index_add` for the gradient. (The crate's `conv3d`, candle's 2-D
//! convolution over stacked depth windows, takes about 2.4 times as long as the candle-op
//! path here: candle's CPU gradient of a 2-D convolution w.r.t. its input is a direct
//! loop, `conv_transpose2d`, not a matrix product.)
//!
//! Cost: `cargo bench --bench train_step -- --model onet_voxels` (this encoder at the
//! default width 16, 16 grids of 32³, with the ONet decoder on 16 × 1 024 points) takes
//! about 0.35–0.45 s per training step on a 2-core Intel Xeon with the fused
//! convolutions and the fused decoder, of which about 0.15 s is the encoder's; with
//! candle's convolutions the step took 0.75 s longer (docs/benchmarks.md).

use crate::error::{check_finite, check_float, check_same, Error, Result};
use crate::kernels::{BufferPool, FusedConv, FusedConvStack};
use candle_core::{DType, Device, Tensor};
use candle_nn::{init::Init, linear, Linear, Module, VarBuilder};
use std::sync::Arc;

/// The kernel size of every convolution (ONet's 3, padding 1).
const KERNEL: usize = 3;

/// Settings of [`voxel_encoder`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct VoxelEncoderConfig {
    /// Channels `w` of the first convolution; stage `s` (from 0) has `w·2^{s+1}` output
    /// channels (ONet: 32, so 64, 128, 256, 512; the default: 16).
    pub base_channels: usize,
    /// Number of stride-2 convolutions `S`, each halving the grid (ONet: 4, 32³ → 2³).
    pub stages: usize,
    /// Dimension of the code `c` (ONet's voxel model: 256).
    pub c_dim: usize,
    /// Side `R` of the input grids, a power of two with `R ≥ 2^S` (ONet: 32).
    pub resolution: usize,
    /// Run the convolutions as candle ops even on the CPU, where each otherwise runs,
    /// with its bias and the ReLU before it, as one fused op (the crate's kernel
    /// `FusedConv`, the same function; tests compare the two). Default `false`.
    pub force_reference: bool,
}

impl Default for VoxelEncoderConfig {
    /// ONet's network at half its width: `w = 16` (16 → 32 → 64 → 128 → 256 channels,
    /// about 1.7 M parameters instead of 5.8 M), `S = 4`, `c_dim = 256`, `R = 32`. ONet's
    /// `w = 32` about doubles the encoder's training cost (its largest convolutions have
    /// four times the multiply-adds), which would cut a 30-minute CPU run's steps; set
    /// `base_channels: 32` for ONet's exact layout. `c_dim = 256` is ONet's and the default `code_dim` of
    /// [`OnetConfig`](super::OnetConfig), so the two defaults plug together.
    fn default() -> Self {
        Self {
            base_channels: 16,
            stages: 4,
            c_dim: 256,
            resolution: 32,
            force_reference: false,
        }
    }
}

/// One 3×3×3 convolution with bias, zero padding 1, stride 1 or 2, on channels-last
/// grids of side `side` (see the module docs).
#[derive(Clone, Debug)]
struct Conv3 {
    /// `[Cₒ, Cᵢ, 3, 3, 3]`, PyTorch's `Conv3d` layout.
    weight: Tensor,
    bias: Tensor,
    /// `u32[n³·27]`: for output voxel `o` and tap `t = (a·3 + b)·3 + c`, the row of its
    /// input voxel, or `side³` (the zero row) where the tap falls in the padding.
    index: Tensor,
    /// Side of the input grid.
    side: usize,
    /// Side of the output grid `n = side / stride`.
    out_side: usize,
}

impl Conv3 {
    /// Kaiming-normal weights (candle-nn's, fan-in `27·Cᵢ`) and biases uniform in
    /// `±1/√(27·Cᵢ)`, as the Conv. ONet grid's convolutions.
    fn new(input: usize, out: usize, side: usize, stride: usize, vb: VarBuilder) -> Result<Self> {
        let weight = vb.get_with_hints(
            (out, input, KERNEL, KERNEL, KERNEL),
            "weight",
            candle_nn::init::DEFAULT_KAIMING_NORMAL,
        )?;
        let bound = 1.0 / ((input * KERNEL.pow(3)) as f64).sqrt();
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
            index: gather_index(side, stride, vb.device())?,
            side,
            out_side: side / stride,
        })
    }

    /// `x: [B, side³, Cᵢ]` → `[B, n³, Cₒ]`:
    /// `y[b, o, j] = bias[j] + Σ_{t, i} w[j, i, t] · a(x_pad)[b, s·o + t − 1, i]`, with `a`
    /// the ReLU when `relu_input` (else the identity). On the CPU (unless `reference`) one
    /// fused op; else candle's ops.
    fn forward(&self, x: &Tensor, relu_input: bool, reference: bool) -> Result<Tensor> {
        let (b, side3, ci) = x.dims3()?;
        if !reference && crate::kernels::cpu_fused_for(x) {
            if side3 != self.side.pow(3) {
                return Err(Error::invalid(
                    "x",
                    format!("{} voxels per grid", self.side.pow(3)),
                    format!("{side3}"),
                ));
            }
            let op = FusedConv::cubic(
                b,
                self.side,
                self.side / self.out_side,
                [ci, self.weight.dim(0)?],
                relu_input,
            );
            return Ok(x.contiguous()?.apply_op3(&self.weight, &self.bias, op)?);
        }
        let x = if relu_input { x.relu()? } else { x.clone() };
        let co = self.weight.dim(0)?;
        let taps = KERNEL.pow(3);
        let n3 = self.out_side.pow(3);
        let zero = Tensor::zeros((b, 1, ci), x.dtype(), x.device())?;
        let cols = Tensor::cat(&[&x, &zero], 1)?
            .index_select(&self.index, 1)? // [B, n³·27, Cᵢ]
            .reshape((b * n3, taps * ci))?;
        // Column t·Cᵢ + i of the weight matrix is tap t of input channel i.
        let w = self
            .weight
            .permute((0, 2, 3, 4, 1))?
            .reshape((co, taps * ci))?;
        let y = cols.matmul(&w.t()?)?.broadcast_add(&self.bias)?;
        Ok(y.reshape((b, n3, co))?)
    }
}

/// The gather index of a 3×3×3 convolution with padding 1 and stride `stride` on a grid
/// of side `side` (see [`Conv3::index`]); `side³ < 2³²` is checked by the caller.
fn gather_index(side: usize, stride: usize, device: &Device) -> Result<Tensor> {
    let n = side / stride;
    let zero = side.pow(3);
    // The input coordinate of output coordinate `o` at tap offset `a`, if inside.
    let along = move |o: usize, a: usize| (stride * o + a).checked_sub(1).filter(|&p| p < side);
    let index: Vec<u32> = (0..n.pow(3))
        .flat_map(|o| {
            let (i, j, k) = (o / (n * n), (o / n) % n, o % n);
            (0..KERNEL.pow(3)).map(move |t| {
                let (a, b, c) = (t / 9, (t / 3) % 3, t % 3);
                let row = match (along(i, a), along(j, b), along(k, c)) {
                    (Some(p), Some(q), Some(r)) => (p * side + q) * side + r,
                    _ => zero,
                };
                row as u32
            })
        })
        .collect();
    let len = index.len();
    Ok(Tensor::from_vec(index, len, device)?)
}

/// The voxel encoder; build it with [`voxel_encoder`].
///
/// For occupancy grids `x: [B, 1, R, R, R]` with base width `w` and `S` stages
/// (ReLU `σ`, every convolution 3×3×3 with zero padding 1 and a bias):
/// * `h₀ = conv_in(x)`, stride 1: `[B, w, R, R, R]`;
/// * `h_{s+1} = conv_s(σ(h_s))`, stride 2, for `s = 0 … S − 1`: `[B, w·2^{s+1}, R/2^{s+1},
///   R/2^{s+1}, R/2^{s+1}]`;
/// * `c = W_fc σ(flatten(h_S)) + b_fc`: `[B, c_dim]`, with `flatten` in channel-major
///   order (`[B, w·2^S·(R/2^S)³]`, PyTorch's `view` of the same tensor).
///
/// At ONet's sizes (`w = 32`, the default's 16 halves every width): 32³ → 32 channels
/// at 32³ → 64 at 16³ → 128 at 8³ → 256 at 4³ → 512 at 2³ → 4096 features → 256.
///
/// The stride-2 convolutions are computed exactly at the kept voxels, by gathering their
/// windows (see the module docs): the same as a stride-1 convolution followed by keeping
/// every other voxel of each axis, at an eighth of its multiply-adds; stage `s` costs
/// `27·C_s·C_{s+1}·(R/2^{s+1})³` multiply-adds per grid, with `C_s = w·2^s`. No
/// normalisation layer: the code of a grid does not depend on the rest of its batch.
#[derive(Clone, Debug)]
pub struct VoxelEncoder {
    conv_in: Conv3,
    stages: Vec<Conv3>,
    fc: Linear,
    config: VoxelEncoderConfig,
    /// The fused convolutions' grids and gradients, kept between calls.
    pool: Arc<BufferPool>,
}

/// Builds a [`VoxelEncoder`] from `vb`, with ONet's variable names: `conv_in`,
/// `conv_{0..S−1}` (each `weight: [Cₒ, Cᵢ, 3, 3, 3]` and `bias: [Cₒ]`, PyTorch's `Conv3d`
/// layout) and `fc` (`weight: [c_dim, w·2^S·(R/2^S)³]`, `bias`). Convolution weights
/// have candle-nn's Kaiming-normal initialisation and biases are uniform in
/// `±1/√(27·Cᵢ)`; `fc` is candle-nn's [`linear()`]. The dtype and device are `vb`'s (f32
/// or f64). Each convolution's gather index (`27·n³` u32 for an output side `n`) is
/// built here, once.
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use candle_nn::VarMap;
/// use neural_fields::nn::build_seeded;
/// use neural_fields::occupancy::{voxel_encoder, VoxelEncoderConfig};
///
/// let config = VoxelEncoderConfig { base_channels: 4, c_dim: 16, ..VoxelEncoderConfig::default() };
/// let varmap = VarMap::new();
/// let enc = build_seeded(&varmap, DType::F32, &Device::Cpu, 0, |vb| voxel_encoder(&config, vb))?;
/// let voxels = Tensor::zeros((2, 32, 32, 32), DType::F32, &Device::Cpu)?;
/// assert_eq!(enc.forward(&voxels)?.dims(), &[2, 16]);
/// // ONet's names and shapes: 4 → 8 → 16 → 32 → 64 channels, 64 · 2³ features.
/// let vars = varmap.data().lock().map_err(|e| candle_core::Error::Msg(e.to_string()))?;
/// assert_eq!(vars["conv_in.weight"].dims(), &[4, 1, 3, 3, 3]);
/// assert_eq!(vars["conv_3.weight"].dims(), &[64, 32, 3, 3, 3]);
/// assert_eq!(vars["fc.weight"].dims(), &[16, 512]);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// A zero `base_channels` or `c_dim` (naming `config.*`); a `resolution` that is not a
/// power of two (`config.resolution`); more stages than the resolution can halve,
/// `2^S > R` (`config.stages`); weights or gather indices past the allocation limit of
/// 2³³ bytes (8 GiB), checked before any layer is built: the first convolution's index of
/// `27·R³` entries and the flattened features (`config.resolution`, so `R ≤ 256`), the
/// convolutions (`config.base_channels`), the final linear map (`config.c_dim`); errors
/// of `vb`.
pub fn voxel_encoder(config: &VoxelEncoderConfig, vb: VarBuilder) -> Result<VoxelEncoder> {
    for (name, v) in [
        ("config.base_channels", config.base_channels),
        ("config.c_dim", config.c_dim),
    ] {
        if v == 0 {
            return Err(Error::invalid(name, "at least 1", "0"));
        }
    }
    let r = config.resolution;
    if !r.is_power_of_two() {
        return Err(Error::invalid(
            "config.resolution",
            "a power of two",
            format!("{r}"),
        ));
    }
    let halvings = r.trailing_zeros() as usize;
    if config.stages > halvings {
        return Err(Error::invalid(
            "config.stages",
            format!("at most log₂(resolution) = {halvings} (2^stages ≤ resolution {r})"),
            format!("{}", config.stages),
        ));
    }
    check_weights(config, vb.dtype().size_in_bytes())?;
    let w = config.base_channels;
    let conv_in = Conv3::new(1, w, r, 1, vb.pp("conv_in"))?;
    let stages = (0..config.stages)
        .map(|s| Conv3::new(w << s, w << (s + 1), r >> s, 2, vb.pp(format!("conv_{s}"))))
        .collect::<Result<Vec<_>>>()?;
    let features = feature_count(config);
    Ok(VoxelEncoder {
        conv_in,
        stages,
        fc: linear(features, config.c_dim, vb.pp("fc"))?,
        config: config.clone(),
        pool: Arc::default(),
    })
}

/// `w·2^S·(R/2^S)³`, the length of the flattened last feature grid (saturating).
fn feature_count(config: &VoxelEncoderConfig) -> usize {
    let side = config.resolution >> config.stages;
    (config.base_channels << config.stages)
        .saturating_mul(side)
        .saturating_mul(side)
        .saturating_mul(side)
}

/// Refuses a configuration whose weights or gather indices pass the allocation limit
/// (`stages ≤ log₂(resolution) < 64` already checked): the first convolution's index and
/// the flattened features (naming `config.resolution`), all convolutions
/// (`config.base_channels`), the final linear map (`config.c_dim`).
fn check_weights(config: &VoxelEncoderConfig, elem_bytes: usize) -> Result<()> {
    // The first convolution's gather index, 27·R³ u32 (which also keeps R³ below 2³²).
    let r = config.resolution;
    crate::limits::check_bytes("config.resolution", &[KERNEL.pow(3), r, r, r], 4)?;
    let w = config.base_channels;
    let scaled = |s: usize| w.saturating_mul(1usize << s);
    let convs = (0..config.stages).fold(w.saturating_mul(27), |acc, s| {
        acc.saturating_add(scaled(s).saturating_mul(scaled(s + 1)).saturating_mul(27))
    });
    crate::limits::check_bytes("config.base_channels", &[convs], elem_bytes)?;
    let side = config.resolution >> config.stages;
    let features = crate::limits::check_bytes(
        "config.resolution",
        &[scaled(config.stages), side, side, side],
        elem_bytes,
    )?;
    crate::limits::check_bytes("config.c_dim", &[features, config.c_dim], elem_bytes)?;
    Ok(())
}

impl VoxelEncoder {
    /// The codes `c: [B, c_dim]` of occupancy grids `voxels: [B, R, R, R]` or
    /// `[B, 1, R, R, R]` (`R = config.resolution`, axes in the caller's order, e.g.
    /// `[x, y, z]`), occupancies in `[0, 1]` (ONet's voxel input is binary; fractional
    /// coverage works as well), f32 or f64 like the encoder's weights. The map is given
    /// in [`VoxelEncoder`]; each grid's code depends on that grid only.
    ///
    /// Differentiable w.r.t. the weights (every convolution's weight and bias, `fc`) and
    /// the voxels. At a ReLU input of exactly 0, candle passes the gradient through
    /// (subgradient 1).
    ///
    /// ```
    /// use candle_core::{DType, Device, Tensor, Var};
    /// use candle_nn::VarMap;
    /// use neural_fields::nn::build_seeded;
    /// use neural_fields::occupancy::{voxel_encoder, VoxelEncoderConfig};
    ///
    /// // A small network on 8³ grids: 4 → 8 → 16 channels at 8³ → 4³ → 2³.
    /// let config = VoxelEncoderConfig { base_channels: 4, stages: 2, c_dim: 3, resolution: 8, force_reference: false };
    /// let varmap = VarMap::new();
    /// let dev = Device::Cpu;
    /// let enc = build_seeded(&varmap, DType::F64, &dev, 1, |vb| voxel_encoder(&config, vb))?;
    /// let voxels = Var::from_tensor(&Tensor::rand(0.0, 1.0, (3, 1, 8, 8, 8), &dev)?.round()?)?;
    /// let codes = enc.forward(voxels.as_tensor())?;
    /// assert_eq!(codes.dims(), &[3, 3]);
    /// let grads = codes.sqr()?.sum_all()?.backward()?;
    /// let vars = varmap.data().lock().map_err(|e| candle_core::Error::Msg(e.to_string()))?;
    /// assert!(grads.get(&vars["conv_1.weight"]).is_some());
    /// assert_eq!(grads.get(voxels.as_tensor()).map(|g| g.dims().to_vec()), Some(vec![3, 1, 8, 8, 8]));
    /// // Each grid's code is its own: the first grid alone gets the same one.
    /// let alone = enc.forward(&voxels.as_tensor().narrow(0, 0, 1)?.squeeze(1)?)?;
    /// let gap = (codes.get(0)? - alone.get(0)?)?.abs()?.max(0)?.to_scalar::<f64>()?;
    /// assert!(gap < 1e-12);
    /// # Ok::<(), neural_fields::Error>(())
    /// ```
    ///
    /// # Errors
    /// Naming `voxels`: not f32/f64 or not the weights' dtype and device; not
    /// `[B, R, R, R]` or `[B, 1, R, R, R]` with the configured `R`; an empty batch; a NaN
    /// or infinite value, or one outside `[0, 1]`; activations that would pass the
    /// allocation limit of 2³³ bytes (the first two convolutions' gathered windows and
    /// outputs, `B·R³·max(27, 4w)` values, bound them).
    pub fn forward(&self, voxels: &Tensor) -> Result<Tensor> {
        check_float(voxels, "voxels")?;
        check_same(voxels, "voxels", self.fc.weight(), "the encoder's weights")?;
        let r = self.config.resolution;
        let b = match *voxels.dims() {
            [b, x, y, z] if [x, y, z] == [r; 3] => b,
            [b, 1, x, y, z] if [x, y, z] == [r; 3] => b,
            _ => {
                return Err(Error::invalid(
                    "voxels",
                    format!("shape [B, {r}, {r}, {r}] or [B, 1, {r}, {r}, {r}]"),
                    format!("shape {:?}", voxels.dims()),
                ))
            }
        };
        if b == 0 {
            return Err(Error::invalid(
                "voxels",
                "at least one grid (B ≥ 1)",
                "B = 0",
            ));
        }
        let per_voxel = 27usize.max(self.config.base_channels.saturating_mul(4));
        crate::limits::check_bytes(
            "voxels",
            &[b, r, r, r, per_voxel],
            voxels.dtype().size_in_bytes(),
        )?;
        check_finite(voxels, "voxels")?;
        let flat = voxels.detach().flatten_all()?.to_dtype(DType::F64)?;
        let (lo, hi) = (
            flat.min(0)?.to_scalar::<f64>()?,
            flat.max(0)?.to_scalar::<f64>()?,
        );
        if lo < 0.0 || hi > 1.0 {
            return Err(Error::invalid(
                "voxels",
                "occupancies in [0, 1]",
                format!("values from {lo} to {hi}"),
            ));
        }
        let x = voxels.reshape((b, r * r * r, 1))?; // channels last
        let reference = self.config.force_reference;
        let h = if !reference && crate::kernels::cpu_fused_for(&x) {
            // The whole chain as one op: its grids and their gradients in kept buffers.
            let (mut layers, mut params, mut ci) = (Vec::new(), Vec::new(), 1);
            for (i, conv) in std::iter::once(&self.conv_in)
                .chain(&self.stages)
                .enumerate()
            {
                let co = conv.weight.dim(0)?;
                let stride = conv.side / conv.out_side;
                layers.push(FusedConv::cubic(b, conv.side, stride, [ci, co], i > 0));
                params.push(conv.weight.flatten_all()?);
                params.push(conv.bias.clone());
                ci = co;
            }
            let op = FusedConvStack::new(layers, Arc::clone(&self.pool));
            x.contiguous()?.apply_op2(&Tensor::cat(&params, 0)?, op)?
        } else {
            let mut h = self.conv_in.forward(&x, false, reference)?;
            for conv in &self.stages {
                h = conv.forward(&h, true, reference)?;
            }
            h
        };
        // [B, n³, C] → PyTorch's channel-major flattening of [B, C, n, n, n].
        let hidden = h
            .transpose(1, 2)?
            .reshape((b, feature_count(&self.config)))?;
        Ok(self.fc.forward(&hidden.relu()?)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::occupancy::conv_onet::conv3d;
    use crate::rng::SplitMix64;
    use candle_core::Var;

    fn gap(a: &Tensor, b: &Tensor) -> Result<f64> {
        Ok((a - b)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f64>()?)
    }

    /// The gathered convolution, both the fused op and candle's ops, equals the crate's
    /// `conv3d` (candle's 2-D convolution over depth windows; an independent formulation,
    /// itself tested against the direct sum) at stride 1, and `conv3d` at every other voxel
    /// of each axis at stride 2: the same values and, for the same cotangent on the kept
    /// voxels, the same gradients w.r.t. the input, the weight and the bias; at the grid's
    /// faces and corners (the padding) as well as inside; with and without the ReLU on the
    /// input; over batches that span several of the fused op's tiles and work items; with
    /// one input channel (computed by lines, without the window matrix, in blocks of
    /// cells: lines shorter than a block, of whole blocks and of a partial one) and with
    /// several.
    #[test]
    fn gathered_convolution_is_conv3d_at_stride_1_and_conv3d_subsampled_at_stride_2() -> Result<()>
    {
        let d = Device::Cpu;
        let mut rng = SplitMix64::new(3);
        for (b, ci, co, side, stride) in [
            (2, 3, 4, 4, 1),
            (1, 1, 2, 2, 1),
            (2, 3, 4, 8, 2),
            (1, 2, 3, 4, 2),
            (1, 2, 2, 2, 2),
            (10, 2, 3, 8, 1),
            (9, 40, 5, 4, 2),
            // One input channel (the fused op's line path): strides 1 and 2, output
            // channels not a multiple of the vector width, several work items.
            (3, 1, 5, 8, 2),
            (2, 1, 17, 4, 1),
            (10, 1, 3, 8, 1),
            (2, 1, 32, 4, 2),
            // Lines of whole blocks of cells and a partial one (10 and 9 outputs).
            (2, 1, 16, 10, 1),
            (1, 1, 16, 18, 2),
        ] {
            let mut random = |shape: &[usize]| -> Result<Var> {
                let v: Vec<f64> = (0..shape.iter().product())
                    .map(|_| rng.uniform() - 0.5)
                    .collect();
                Ok(Var::from_vec(v, shape, &d)?)
            };
            let x = random(&[b, ci, side, side, side])?; // channels first
            let weight = random(&[co, ci, 3, 3, 3])?;
            let bias = random(&[co])?;
            let conv = Conv3 {
                weight: weight.as_tensor().clone(),
                bias: bias.as_tensor().clone(),
                index: gather_index(side, stride, &d)?,
                side,
                out_side: side / stride,
            };
            let rows = x
                .as_tensor()
                .reshape((b, ci, side.pow(3)))?
                .transpose(1, 2)?
                .contiguous()?;
            let n = side / stride;
            let g: Vec<f64> = (0..b * co * n.pow(3))
                .map(|_| rng.uniform() - 0.5)
                .collect();
            let g = Tensor::from_vec(g, (b, co, n, n, n), &d)?;
            for relu in [false, true] {
                let input = if relu {
                    x.as_tensor().relu()?
                } else {
                    x.as_tensor().clone()
                };
                let mut want = conv3d(&input, weight.as_tensor(), 1)?
                    .broadcast_add(&bias.as_tensor().reshape((1, co, 1, 1, 1))?)?;
                for axis in 2..5 {
                    let kept: Vec<u32> = (0..side).step_by(stride).map(|i| i as u32).collect();
                    let kept = Tensor::new(kept.as_slice(), &d)?;
                    want = want.contiguous()?.index_select(&kept, axis)?;
                }
                let gb = (&want * &g)?.sum_all()?.backward()?;
                for reference in [true, false] {
                    let got = conv
                        .forward(&rows, relu, reference)?
                        .transpose(1, 2)?
                        .reshape((b, co, n, n, n))?;
                    let label = format!(
                        "B {b}, {ci} → {co}, side {side}, stride {stride}, relu {relu}, reference {reference}"
                    );
                    assert_eq!(got.dims(), want.dims(), "{label}");
                    assert!(gap(&got, &want)? < 1e-13, "{label}");
                    let ga = (got * &g)?.sum_all()?.backward()?;
                    for (name, v) in [("input", &x), ("weight", &weight), ("bias", &bias)] {
                        let (a, b) = (ga.get(v.as_tensor()), gb.get(v.as_tensor()));
                        let (Some(a), Some(b)) = (a, b) else {
                            panic!("{label}: no gradient for the {name}");
                        };
                        assert!(gap(a, b)? < 1e-12, "{label}: gradient w.r.t. the {name}");
                    }
                }
            }
        }
        Ok(())
    }

    /// In f32 the fused op and candle's ops agree to round-off, values and gradients, on
    /// the default encoder's first stage shape (16 → 32 channels, 32³ → 16³, with the
    /// ReLU), and the fused op leaves the input's gradient out when the input is not part
    /// of the graph.
    #[test]
    fn fused_convolution_matches_the_reference_in_f32() -> Result<()> {
        let d = Device::Cpu;
        let (b, ci, co, side) = (2usize, 16usize, 32usize, 32usize);
        let x = Var::from_tensor(&Tensor::randn(0f32, 1.0, (b, side.pow(3), ci), &d)?)?;
        let weight = Var::from_tensor(&Tensor::randn(0f32, 0.1, (co, ci, 3, 3, 3), &d)?)?;
        let bias = Var::from_tensor(&Tensor::randn(0f32, 0.1, co, &d)?)?;
        let conv = Conv3 {
            weight: weight.as_tensor().clone(),
            bias: bias.as_tensor().clone(),
            index: gather_index(side, 2, &d)?,
            side,
            out_side: side / 2,
        };
        let g = Tensor::randn(0f32, 1.0, (b, (side / 2).pow(3), co), &d)?;
        let run = |reference: bool| -> Result<(Tensor, candle_core::backprop::GradStore)> {
            let y = conv.forward(x.as_tensor(), true, reference)?;
            let grads = (&y * &g)?.sum_all()?.backward()?;
            Ok((y, grads))
        };
        let ((ya, ga), (yb, gb)) = (run(false)?, run(true)?);
        let rel = |a: &Tensor, b: &Tensor| -> Result<f64> {
            let a = a.to_dtype(DType::F64)?;
            let b = b.to_dtype(DType::F64)?;
            let scale = b.abs()?.flatten_all()?.max(0)?.to_scalar::<f64>()?;
            Ok(gap(&a, &b)? / scale.max(1e-30))
        };
        assert!(rel(&ya, &yb)? < 1e-5);
        for v in [&x, &weight, &bias] {
            let (Some(a), Some(b)) = (ga.get(v.as_tensor()), gb.get(v.as_tensor())) else {
                panic!("a gradient is missing");
            };
            assert!(rel(a, b)? < 1e-5);
        }
        let detached = conv.forward(&x.as_tensor().detach(), true, false)?;
        let grads = (&detached * &g)?.sum_all()?.backward()?;
        assert!(grads.get(weight.as_tensor()).is_some());
        assert!(grads.get(x.as_tensor()).is_none());
        Ok(())
    }

    /// Taps in the padding read the zero row `side³`; the others their own voxel.
    #[test]
    fn the_gather_index_points_into_the_grid_or_at_the_zero_row() -> Result<()> {
        let index = gather_index(4, 2, &Device::Cpu)?.to_vec1::<u32>()?;
        assert_eq!(index.len(), 8 * 27);
        // Output voxel 0 reads input −1…1 per axis: only the taps with every offset ≥ 1
        // are inside; tap (1, 1, 1) is voxel 0, tap (2, 2, 2) voxel (1, 1, 1) = 21.
        assert_eq!(index[13], 0);
        assert_eq!(index[26], 21);
        assert_eq!(index[0], 64);
        // The last output voxel (1, 1, 1) reads input 1…3: all inside.
        let last = &index[7 * 27..];
        assert!(last.iter().all(|&i| i < 64));
        assert_eq!(last[0], 21);
        assert_eq!(last[26], 63);
        Ok(())
    }
}
