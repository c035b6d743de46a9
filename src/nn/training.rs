//! What a training loop around the crate's models needs beside its optimiser: Adam
//! without weight decay, a guard that stops a run at the first NaN or infinity, and a
//! clock that measures the budget in steps or in training time.

use crate::error::{all_finite, finite_probe, Error, Result};
use crate::kernels::{AdamMoments, AdamUpdate};
use candle_core::backprop::GradStore;
use candle_core::{DType, Tensor, Var};
use candle_nn::{Optimizer, ParamsAdamW, VarMap};
use std::time::Instant;

/// Adam (Kingma & Ba) at learning rate `lr` over every variable of `varmap`, without
/// weight decay (candle-nn's `AdamW` default of 0.01 would shrink every weight by
/// `lr · 0.01` per step) and with the default moments (β₁ = 0.9, β₂ = 0.999, ε = 1e-8):
/// an [`Adam`] with those [`ParamsAdamW`]. For a hash grid's table over an object's box,
/// build [`Adam`] with ε = 1e-15 instead ([`crate::encoding::hash_grid`] says why).
///
/// Works for variables of any device and dtype; the variables present in `varmap` when it
/// is called are the ones it trains.
///
/// ```
/// use candle_core::{DType, Device};
/// use candle_nn::{Optimizer, VarMap};
/// use neural_fields::nn::{adam, build_seeded, mlp, MlpConfig};
///
/// let varmap = VarMap::new();
/// let _net = build_seeded(&varmap, DType::F32, &Device::Cpu, 0, |vb| mlp(&MlpConfig::default(), vb))?;
/// let opt = adam(&varmap, 1e-3)?;
/// assert_eq!(opt.learning_rate(), 1e-3);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// [`Error::InvalidArgument`] naming `lr` unless it is positive and finite.
pub fn adam(varmap: &VarMap, lr: f64) -> Result<Adam> {
    if !(lr > 0.0 && lr.is_finite()) {
        return Err(Error::invalid(
            "lr",
            "a positive, finite learning rate",
            lr.to_string(),
        ));
    }
    let params = ParamsAdamW {
        lr,
        weight_decay: 0.0,
        ..ParamsAdamW::default()
    };
    Ok(Adam::new(varmap.all_vars(), params)?)
}

/// Adam with decoupled weight decay (AdamW), the step of candle-nn's `AdamW` with the
/// same [`ParamsAdamW`], as two in-place passes over each variable where the crate's
/// fused kernels run (the CPU; CUDA with the `cuda` feature) and as candle ops elsewhere.
///
/// At step `t` (from 1), for each variable `θ` with a gradient `g` in the [`GradStore`]
/// (variables without one are left as they are, their moments too):
/// `m ← β₁m + (1 − β₁)g`, `v ← β₂v + (1 − β₂)g²`,
/// `θ ← θ(1 − lr·λ) − lr · (m/(1 − β₁ᵗ)) / (√(v/(1 − β₂ᵗ)) + ε)`, in the variable's
/// dtype (f32 or f64; other dtypes are not trained). The moments live on the variable's
/// device, `2·numel` values per variable. NaN or ∞ in a gradient propagates into the
/// variable ([`FiniteGuard`] reports it).
///
/// Against candle-nn's `AdamW` the fused passes save about a dozen candle ops (each with
/// its allocation) per variable and step, which dominate a small model's update on a GPU.
///
/// ```
/// use candle_core::{DType, Device, Tensor, Var};
/// use candle_nn::{Optimizer, ParamsAdamW};
/// use neural_fields::nn::Adam;
///
/// let x = Var::new(&[1f32, -2.0], &Device::Cpu)?;
/// let mut opt = Adam::new(vec![x.clone()], ParamsAdamW { lr: 0.1, weight_decay: 0.0, ..Default::default() })?;
/// let loss = x.as_tensor().sqr()?.sum_all()?;
/// opt.backward_step(&loss)?;
/// // The first step moves every coordinate by lr against its gradient's sign.
/// let v = x.as_tensor().to_vec1::<f32>()?;
/// assert!((v[0] - 0.9).abs() < 1e-6 && (v[1] + 1.9).abs() < 1e-6);
/// # Ok::<(), candle_core::Error>(())
/// ```
#[derive(Debug)]
pub struct Adam {
    vars: Vec<(Var, Tensor)>,
    params: ParamsAdamW,
    step: i32,
}

impl Optimizer for Adam {
    type Config = ParamsAdamW;

    /// Adam over `vars` (the f32/f64 ones) with zero moments.
    fn new(vars: Vec<Var>, params: ParamsAdamW) -> candle_core::Result<Self> {
        let vars = vars
            .into_iter()
            .filter(|v| matches!(v.dtype(), DType::F32 | DType::F64))
            .map(|v| {
                let moments = Tensor::zeros((2, v.elem_count()), v.dtype(), v.device())?;
                Ok((v, moments))
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok(Self {
            vars,
            params,
            step: 0,
        })
    }

    fn step(&mut self, grads: &GradStore) -> candle_core::Result<()> {
        self.step = self.step.saturating_add(1);
        let p = &self.params;
        let moments = AdamMoments {
            beta1: p.beta1,
            beta2: p.beta2,
        };
        let update = AdamUpdate {
            lr: p.lr,
            decay: p.lr * p.weight_decay,
            eps: p.eps,
            scale_m: 1.0 / (1.0 - p.beta1.powi(self.step)),
            scale_v: 1.0 / (1.0 - p.beta2.powi(self.step)),
        };
        for (var, mv) in &self.vars {
            let Some(g) = grads.get(var) else { continue };
            let theta = var.as_tensor();
            if crate::kernels::fused_on(theta.device()) && theta.is_contiguous() {
                let g = g.flatten_all()?.contiguous()?.to_dtype(theta.dtype())?;
                mv.inplace_op2(&g, &moments)?;
                theta.inplace_op2(mv, &update)?;
            } else {
                // The reference path: the same arithmetic as candle ops.
                let g = g.flatten_all()?;
                let m = mv.get(0)?;
                let v = mv.get(1)?;
                let m = ((m * moments.beta1)? + (&g * (1.0 - moments.beta1))?)?;
                let v = ((v * moments.beta2)? + (g.sqr()? * (1.0 - moments.beta2))?)?;
                let step =
                    ((&m * update.scale_m)? / ((&v * update.scale_v)?.sqrt()? + update.eps)?)?;
                let next = ((theta.flatten_all()? * (1.0 - update.decay))? - (step * update.lr)?)?;
                var.set(&next.reshape(theta.shape())?)?;
                mv.slice_set(&Tensor::stack(&[m, v], 0)?, 0, 0)?;
            }
        }
        Ok(())
    }

    fn learning_rate(&self) -> f64 {
        self.params.lr
    }

    fn set_learning_rate(&mut self, lr: f64) {
        self.params.lr = lr;
    }
}

/// Stops a training run at the first NaN or infinity, with an error that names the step
/// and the tensor: the loss, the gradient of a variable, or a variable's value.
///
/// It holds the variables of a [`VarMap`] with their names, sorted by name (a guard made
/// after the model is built sees all of its variables). A tensor is finite when `Σ 0·x`
/// is (0 unless an element is NaN or ±∞, whatever the magnitudes); the check sums `0·x`
/// over each tensor in its own dtype, reads the sums back from the device as one vector,
/// tensor by tensor only to name the first bad one, and needs no gradient.
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use candle_nn::VarMap;
/// use neural_fields::field::ImplicitSurface;
/// use neural_fields::nn::{build_seeded, mlp, FiniteGuard, MlpConfig};
///
/// let varmap = VarMap::new();
/// let net = build_seeded(&varmap, DType::F32, &Device::Cpu, 0, |vb| mlp(&MlpConfig::default(), vb))?;
/// let guard = FiniteGuard::new(&varmap);
/// let points = Tensor::zeros((4, 3), DType::F32, &Device::Cpu)?;
/// let loss = net.value(&points)?.sqr()?.mean_all()?;
/// let grads = loss.backward()?;
/// guard.check(0, &loss, Some(&grads))?;
/// let nan = Tensor::new(f32::NAN, &Device::Cpu)?;
/// let err = guard.check(7, &nan, None).unwrap_err().to_string();
/// assert!(err.contains("the loss at step 7"), "{err}");
/// # Ok::<(), neural_fields::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct FiniteGuard {
    vars: Vec<(String, Var)>,
}

impl FiniteGuard {
    /// A guard over the variables of `varmap` as it is now. A lock poisoned by a thread
    /// that panicked while holding it still holds whole variables, which are read.
    #[must_use]
    pub fn new(varmap: &VarMap) -> Self {
        let data = varmap
            .data()
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let mut vars: Vec<_> = data.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        Self { vars }
    }

    /// Checks `loss` at training step `step`, and with `grads` also the gradient of
    /// every variable that has one in `grads` and the value of every variable (call it
    /// after `backward`, before the optimiser's step; passing `grads` every k steps
    /// bounds the cost: one copy of every variable and its gradient, and one reduction).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `training`, with the step and the tensor (`the
    /// loss`, `the gradient of NAME`, `the weight NAME`), at the first tensor that holds a
    /// NaN or an infinity; candle's errors if a tensor cannot be read.
    pub fn check(&self, step: usize, loss: &Tensor, grads: Option<&GradStore>) -> Result<()> {
        // (tensor, what it is, the variable's name)
        let mut checked = vec![(loss.clone(), "the loss", "")];
        if let Some(grads) = grads {
            for (name, var) in &self.vars {
                if let Some(g) = grads.get(var) {
                    checked.push((g.clone(), "the gradient of ", name.as_str()));
                }
            }
            for (name, var) in &self.vars {
                checked.push((var.as_tensor().clone(), "the weight ", name.as_str()));
            }
        }
        // Where all share a dtype and a device, each tensor's probe is stacked and read
        // back at once (a GPU then synchronises once per step, not once per tensor, and
        // no tensor is concatenated or converted); only then tensor by tensor, to name one.
        let tensors: Vec<&Tensor> = checked
            .iter()
            .map(|(t, ..)| t)
            .filter(|t| t.elem_count() > 0)
            .collect();
        let alike = tensors
            .iter()
            .all(|t| t.dtype() == loss.dtype() && t.device().same_device(loss.device()));
        if alike && loss.dtype().is_float() && !tensors.is_empty() {
            let probes: Vec<Tensor> = tensors
                .iter()
                .map(|t| finite_probe(t))
                .collect::<Result<_>>()?;
            if all_finite(&Tensor::stack(&probes, 0)?)? {
                return Ok(());
            }
        }
        for (t, what, name) in &checked {
            if t.elem_count() > 0 && !all_finite(t)? {
                return Err(Error::invalid(
                    "training",
                    "finite losses, gradients and weights",
                    format!("a NaN or infinity in {what}{name} at step {step}"),
                ));
            }
        }
        Ok(())
    }
}

/// A training budget: a number of optimiser steps, or minutes of training.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Budget {
    /// This many steps (0 trains nothing).
    Steps(usize),
    /// This many minutes of training time ([`Clock::pause`] keeps evaluations out).
    Minutes(f64),
}

/// A training run's clock: how much of its [`Budget`] is spent, with the time spent in
/// evaluations taken out.
///
/// ```
/// use neural_fields::nn::{Budget, Clock};
///
/// let clock = Clock::start(Budget::Steps(200))?;
/// let mut step = 0;
/// while clock.progress(step) < 1.0 {
///     step += 1; // one optimiser step
/// }
/// assert_eq!(step, 200);
/// # Ok::<(), neural_fields::Error>(())
/// ```
#[derive(Clone, Debug)]
pub struct Clock {
    budget: Budget,
    start: Instant,
    paused: f64,
}

impl Clock {
    /// Starts the clock now.
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `budget` for minutes that are not positive and
    /// finite.
    pub fn start(budget: Budget) -> Result<Self> {
        if let Budget::Minutes(m) = budget {
            if !(m > 0.0 && m.is_finite()) {
                return Err(Error::invalid(
                    "budget",
                    "a positive, finite number of minutes",
                    m.to_string(),
                ));
            }
        }
        Ok(Self {
            budget,
            start: Instant::now(),
            paused: 0.0,
        })
    }

    /// Seconds of training since [`Clock::start`]: wall time less the time spent inside
    /// [`Clock::pause`].
    #[must_use]
    pub fn train_seconds(&self) -> f64 {
        self.start.elapsed().as_secs_f64() - self.paused
    }

    /// The fraction of the budget spent when `step` steps are done: `step / steps`, or
    /// training seconds over the budget's seconds (then `step` is not used); 1 or more
    /// means the run is over (`Budget::Steps(0)` is over at once).
    #[must_use]
    pub fn progress(&self, step: usize) -> f64 {
        match self.budget {
            Budget::Steps(0) => 1.0,
            Budget::Steps(n) => step as f64 / n as f64,
            Budget::Minutes(m) => self.train_seconds() / (60.0 * m),
        }
    }

    /// Runs `f` (an evaluation, a checkpoint) off the training clock: its wall time is
    /// not counted in [`Clock::train_seconds`] nor in the budget.
    pub fn pause<T>(&mut self, f: impl FnOnce() -> T) -> T {
        let t = Instant::now();
        let out = f();
        self.paused += t.elapsed().as_secs_f64();
        out
    }
}
