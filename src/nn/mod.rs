//! Building blocks of neural fields, made the candle-nn way: small types constructed by
//! free functions from a [`candle_nn::VarBuilder`].
//!
//! * [`Mlp`] / [`mlp`]: configurable MLP field with forward-mode spatial gradients
//!   ([`Mlp::forward_with_jacobian`]), a fused CPU op on the CPU and candle ops elsewhere.
//! * [`build_seeded`]: reproducible initialisation (candle's CPU generator cannot be
//!   seeded; this draws every variable's initial value from a `u64` seed instead).
//! * The training loop's companions: [`adam`] (Adam without weight decay over a
//!   `VarMap`, an [`Adam`]: candle-nn's `AdamW` step as two fused passes per variable), [`FiniteGuard`] (stops at the first NaN or infinity in the loss, a
//!   gradient or a weight, naming the step and the tensor) and [`Clock`] (a [`Budget`]
//!   of steps or minutes, with evaluations kept off the clock).
//!
//! The models built from them live beside the feature they serve: NeRF's radiance field
//! in `volume` (`volume::Nerf`), the ONet decoder and the PointNet and Convolutional ONet
//! encoders in `occupancy`, the texture networks in `texture`. The pointwise ResNet trunk
//! they share and the tangent of a linear layer are crate-private blocks here.

mod mlp;
mod resnet_fc;
mod training;

pub use mlp::{mlp, Activation, Mlp, MlpConfig};
#[allow(unused_imports)] // for the feature modules' models (occupancy, texture, flow)
pub(crate) use resnet_fc::ResnetFc;
pub use training::{adam, Adam, Budget, Clock, FiniteGuard};

use crate::error::{Error, Result};
use crate::rng::SplitMix64;
use candle_core::{DType, Device, Shape, Tensor, Var};
use candle_nn::init::NormalOrUniform;
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarBuilder, VarMap};
use std::sync::{Arc, Mutex};

/// The tangent of a linear layer: `Wȧ` for tangents `ȧ: [A, B, in]` and
/// `weight: [out, in]` → `[A, B, out]` (the bias drops out). Shared by the forward-mode
/// passes of the networks built on these blocks.
pub(crate) fn weight_jvp(weight: &Tensor, da: &Tensor) -> Result<Tensor> {
    let (a, b, i) = da.dims3()?;
    Ok(da
        .reshape((a * b, i))?
        .matmul(&weight.t()?)?
        .reshape((a, b, weight.dim(0)?))?)
}

/// A `VarBuilder` backend that draws each requested tensor from a seeded generator,
/// following the requested [`Init`], and records it.
struct SeededBackend {
    rng: Mutex<SplitMix64>,
    made: Arc<Mutex<Vec<(String, Tensor)>>>,
}

impl SeededBackend {
    fn draw(
        &self,
        shape: &Shape,
        init: Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let mut rng = self
            .rng
            .lock()
            .map_err(|_| candle_core::Error::Msg("seeded initialiser poisoned".into()))?;
        let dims = shape.dims();
        match init {
            Init::Const(c) => Tensor::ones(shape, dtype, dev)?.affine(c, 0.0),
            Init::Randn { mean, stdev } => rng.normal_tensor(dims, mean, stdev, dtype, dev),
            Init::Uniform { lo, up } => rng.uniform_tensor(dims, lo, up, dtype, dev),
            Init::Kaiming {
                dist,
                fan,
                non_linearity,
            } => {
                let std = non_linearity.gain() / (fan.for_shape(shape) as f64).sqrt();
                match dist {
                    NormalOrUniform::Normal => rng.normal_tensor(dims, 0.0, std, dtype, dev),
                    NormalOrUniform::Uniform => {
                        let b = 3f64.sqrt() * std;
                        rng.uniform_tensor(dims, -b, b, dtype, dev)
                    }
                }
            }
        }
    }
}

impl SimpleBackend for SeededBackend {
    fn get(
        &self,
        s: Shape,
        name: &str,
        h: Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let t = self.draw(&s, h, dtype, dev)?;
        self.made
            .lock()
            .map_err(|_| candle_core::Error::Msg("seeded initialiser poisoned".into()))?
            .push((name.to_string(), t.clone()));
        Ok(t)
    }

    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> candle_core::Result<Tensor> {
        Err(candle_core::Error::Msg(format!(
            "{name}: a seeded initialiser needs the shape"
        )))
    }

    fn contains_tensor(&self, _: &str) -> bool {
        true
    }
}

/// Builds a model whose variables live in `varmap` (so an optimiser can train them) with
/// initial values drawn from `seed`, reproducibly on every machine.
///
/// `build` is called twice: once with a recording backend that draws each requested
/// variable from [`SplitMix64`] following its [`Init`] (constant, normal, uniform,
/// Kaiming), after which the draws are inserted into `varmap`; then with
/// `VarBuilder::from_varmap`, which finds the variables already present and returns the
/// trainable model. Variables already in `varmap` are left as they are.
///
/// ```
/// use candle_core::{DType, Device};
/// use candle_nn::VarMap;
/// use neural_fields::nn::{build_seeded, mlp, MlpConfig};
///
/// let (a, b) = (VarMap::new(), VarMap::new());
/// let config = MlpConfig::default();
/// let _net_a = build_seeded(&a, DType::F32, &Device::Cpu, 7, |vb| mlp(&config, vb))?;
/// let _net_b = build_seeded(&b, DType::F32, &Device::Cpu, 7, |vb| mlp(&config, vb))?;
/// let weight = |m: &VarMap| -> candle_core::Result<Vec<Vec<f32>>> {
///     let vars = m.data().lock().map_err(|e| candle_core::Error::Msg(e.to_string()))?;
///     vars["layer0.weight"].as_tensor().to_vec2::<f32>()
/// };
/// let (wa, wb) = (weight(&a)?, weight(&b)?);
/// assert_eq!(wa, wb);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// Errors of `build`.
pub fn build_seeded<T>(
    varmap: &VarMap,
    dtype: DType,
    device: &Device,
    seed: u64,
    build: impl Fn(VarBuilder) -> Result<T>,
) -> Result<T> {
    let made = Arc::new(Mutex::new(Vec::new()));
    let backend: Box<dyn SimpleBackend> = Box::new(SeededBackend {
        rng: Mutex::new(SplitMix64::new(seed)),
        made: Arc::clone(&made),
    });
    // Recording pass: its result holds plain tensors, not variables, and is dropped.
    drop(build(VarBuilder::from_backend(
        backend,
        dtype,
        device.clone(),
    ))?);
    let made =
        std::mem::take(&mut *made.lock().map_err(|_| {
            Error::invalid("build", "a model builder that does not panic", "a panic")
        })?);
    {
        let mut data = varmap
            .data()
            .lock()
            .map_err(|_| Error::invalid("varmap", "an unpoisoned lock", "a poisoned one"))?;
        for (name, t) in made {
            data.entry(name).or_insert(Var::from_tensor(&t)?);
        }
    }
    build(VarBuilder::from_varmap(varmap, dtype, device))
}
