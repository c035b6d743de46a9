//! What a training loop around the crate's models needs beside its optimiser: Adam
//! without weight decay, a guard that stops a run at the first NaN or infinity, and a
//! clock that measures the budget in steps or in training time.

use crate::error::{Error, Result};
use candle_core::backprop::GradStore;
use candle_core::{DType, Tensor, Var};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarMap};
use std::time::Instant;

/// Adam (Kingma & Ba) at learning rate `lr` over every variable of `varmap`: candle-nn's
/// [`AdamW`] with `weight_decay = 0` (its default of 0.01 would shrink every weight by
/// `lr · 0.01` per step) and its default moments (β₁ = 0.9, β₂ = 0.999, ε = 1e-8).
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
pub fn adam(varmap: &VarMap, lr: f64) -> Result<AdamW> {
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
    Ok(AdamW::new(varmap.all_vars(), params)?)
}

/// Stops a training run at the first NaN or infinity, with an error that names the step
/// and the tensor: the loss, the gradient of a variable, or a variable's value.
///
/// It holds the variables of a [`VarMap`] with their names, sorted by name (a guard made
/// after the model is built sees all of its variables). A tensor is finite when
/// `Σ |x|`, summed in the tensor's dtype and read as f64, is finite; the check reads one
/// scalar back from the device per tensor, and needs no gradient.
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
    /// bounds the cost, one reduction per variable).
    ///
    /// # Errors
    /// [`Error::InvalidArgument`] naming `training`, with the step and the tensor (`the
    /// loss`, `the gradient of NAME`, `the weight NAME`), at the first tensor that holds a
    /// NaN or an infinity; candle's errors if a tensor cannot be read.
    pub fn check(&self, step: usize, loss: &Tensor, grads: Option<&GradStore>) -> Result<()> {
        finite(loss, step, || "the loss".into())?;
        if let Some(grads) = grads {
            for (name, var) in &self.vars {
                if let Some(g) = grads.get(var) {
                    finite(g, step, || format!("the gradient of {name}"))?;
                }
            }
            for (name, var) in &self.vars {
                finite(var.as_tensor(), step, || format!("the weight {name}"))?;
            }
        }
        Ok(())
    }
}

/// `Ok` if `t` holds no NaN or infinity; else the error naming `what()` and `step`.
fn finite(t: &Tensor, step: usize, what: impl FnOnce() -> String) -> Result<()> {
    let s = t
        .abs()?
        .sum_all()?
        .to_dtype(DType::F64)?
        .to_scalar::<f64>()?;
    if s.is_finite() {
        Ok(())
    } else {
        Err(Error::invalid(
            "training",
            "finite losses, gradients and weights",
            format!("a NaN or infinity in {} at step {step}", what()),
        ))
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
