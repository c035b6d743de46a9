//! Ordinary differential equations `dy/dt = f(t, y)` integrated with candle ops, so that
//! gradients reach `y₀` and every parameter `f` reads by backpropagation through the
//! solver's steps.

use crate::error::{check_finite, check_float, Error, Result};
use candle_core::Tensor;

/// How [`odeint`] steps.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Solver {
    /// The classical fourth-order Runge–Kutta method with a fixed step: `steps` steps per
    /// unit of time, an interval `Δt` between two requested times taking
    /// `⌈|Δt|·steps⌉` equal steps (at least one). Global error `O(h⁴)`, `h = 1/steps`;
    /// four evaluations of `f` per step.
    Rk4 {
        /// Steps per unit of time (at least 1).
        steps: usize,
    },
    /// The Dormand–Prince 5(4) pair with adaptive steps (the `dopri5` of Occupancy Flow),
    /// first-same-as-last (six new evaluations per attempted step). A step is accepted
    /// when the RMS over all elements of `e / (atol + rtol·max(|y|, |y_new|))` is at most
    /// 1, `e` being the difference of the fifth- and fourth-order solutions; the next
    /// step is `h·clamp(0.9·err^(−1/5), 0.2, 10)`. The first step follows Hairer, Nørsett
    /// and Wanner (II.4). Steps are shortened to land on every requested time.
    Dopri5 {
        /// Relative tolerance (> 0; Occupancy Flow: 1e-3).
        rtol: f64,
        /// Absolute tolerance (> 0; Occupancy Flow: 1e-5).
        atol: f64,
        /// The most steps, accepted and rejected together, before [`odeint`] gives up
        /// with an error (a stiff or exploding field would otherwise step for ever).
        max_steps: usize,
    },
}

impl Default for Solver {
    /// Occupancy Flow's solver: Dormand–Prince with `rtol = 1e-3`, `atol = 1e-5`, and
    /// at most 10 000 steps.
    fn default() -> Self {
        Self::Dopri5 {
            rtol: 1e-3,
            atol: 1e-5,
            max_steps: 10_000,
        }
    }
}

impl Solver {
    fn check(&self) -> Result<()> {
        match *self {
            Self::Rk4 { steps: 0 } => Err(Error::invalid(
                "solver.steps",
                "at least 1 step per unit of time",
                "0",
            )),
            Self::Dopri5 {
                rtol,
                atol,
                max_steps,
            } => {
                for (arg, v) in [("solver.rtol", rtol), ("solver.atol", atol)] {
                    if !(v.is_finite() && v > 0.0) {
                        return Err(Error::invalid(arg, "a finite tolerance > 0", v.to_string()));
                    }
                }
                if max_steps == 0 {
                    return Err(Error::invalid("solver.max_steps", "at least 1", "0"));
                }
                Ok(())
            }
            Self::Rk4 { .. } => Ok(()),
        }
    }
}

/// Whether [`odeint`] keeps the computation graph of its steps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Graph {
    /// Keep it: the states are differentiable w.r.t. `y₀` and what `f` reads. Memory and
    /// the graph's depth grow with the number of steps; candle's backward pass and the
    /// graph's release recurse over that depth, so run long differentiable solves (many
    /// hundreds of steps) on a thread with a large stack.
    Keep,
    /// Detach the state after every step: memory and depth stay constant and the states
    /// have no gradient. For evaluation (meshes over time, metrics).
    Detach,
}

/// The states of [`odeint`] at the requested times, and what the solve cost.
#[derive(Clone, Debug)]
pub struct Trajectory {
    /// `y(tᵢ)` for every requested time, shaped like `y₀` (`states[0]` is `y₀` itself).
    pub states: Vec<Tensor>,
    /// Evaluations of `f`.
    pub evaluations: usize,
    /// Accepted steps.
    pub accepted: usize,
    /// Rejected steps (always 0 for RK4).
    pub rejected: usize,
}

/// Integrates `dy/dt = f(t, y)` from `y(times[0]) = y0` and returns `y` at every time in
/// `times` (increasing, or decreasing to integrate backward in time).
///
/// - `f(t, y)` returns a tensor shaped like `y`; `y0` is any shape, f32 or f64, on any
///   device (the steps are candle ops).
/// - With [`Graph::Keep`], differentiable w.r.t. `y0` and everything `f` reads (its
///   parameters, a code): the gradient is that of the discrete solver, by
///   backpropagation through its steps (memory grows with the number of steps).
///   Dopri5's step sizes are chosen from detached error estimates and are constants to
///   the gradient, as in torchdiffeq. With [`Graph::Detach`], no gradient and constant
///   memory.
///
/// ```
/// use candle_core::{Device, Tensor};
/// use neural_fields::flow::{odeint, Graph, Solver};
///
/// // y' = −y from y(0) = 1: y(1) = e⁻¹.
/// let y0 = Tensor::new(&[1.0f64], &Device::Cpu)?;
/// let solver = Solver::Dopri5 { rtol: 1e-8, atol: 1e-10, max_steps: 1000 };
/// let out = odeint(|_t, y| Ok(y.neg()?), &y0, &[0.0, 1.0], &solver, Graph::Keep)?;
/// let y1 = out.states[1].to_vec1::<f64>()?[0];
/// assert!((y1 - (-1.0f64).exp()).abs() < 1e-7);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// `times` empty, non-finite or not strictly monotone (naming `times`); a non-float or
/// non-finite `y0` (naming `y0`); invalid solver settings (naming `solver.*`); `f`
/// returning a tensor of another shape, or values that make the state non-finite (naming
/// `f`, with the time); Dopri5 needing more than `max_steps` steps, or a step shorter
/// than 1e-12 of the interval (naming `solver.max_steps`, with the time reached);
/// errors of `f`.
pub fn odeint<F>(
    f: F,
    y0: &Tensor,
    times: &[f64],
    solver: &Solver,
    graph: Graph,
) -> Result<Trajectory>
where
    F: Fn(f64, &Tensor) -> Result<Tensor>,
{
    solver.check()?;
    check_times(times)?;
    check_float(y0, "y0")?;
    check_finite(y0, "y0")?;
    let mut run = Run {
        f: &f,
        detach: graph == Graph::Detach,
        shape: y0.dims().to_vec(),
        evaluations: 0,
        accepted: 0,
        rejected: 0,
    };
    let mut states = vec![y0.clone()];
    let mut y = run.keep(y0.clone());
    match *solver {
        Solver::Rk4 { steps } => {
            for w in times.windows(2) {
                y = run.rk4(&y, w[0], w[1], steps)?;
                states.push(y.clone());
            }
        }
        Solver::Dopri5 {
            rtol,
            atol,
            max_steps,
        } => {
            let tol = Tolerance { rtol, atol };
            if times.len() > 1 {
                let mut k1 = run.eval(times[0], &y)?;
                k1 = run.keep(k1);
                let mut h = run.initial_step(&y, &k1, times[0], times[times.len() - 1], tol)?;
                for w in times.windows(2) {
                    (y, k1, h) = run.dopri5(y, k1, h, w[0], w[1], tol, max_steps)?;
                    states.push(y.clone());
                }
            }
        }
    }
    Ok(Trajectory {
        states,
        evaluations: run.evaluations,
        accepted: run.accepted,
        rejected: run.rejected,
    })
}

fn check_times(times: &[f64]) -> Result<()> {
    if times.is_empty() {
        return Err(Error::invalid("times", "at least one time", "none"));
    }
    if let Some(t) = times.iter().find(|t| !t.is_finite()) {
        return Err(Error::invalid("times", "finite times", t.to_string()));
    }
    let increasing = times.windows(2).all(|w| w[1] > w[0]);
    let decreasing = times.windows(2).all(|w| w[1] < w[0]);
    if !(increasing || decreasing) {
        return Err(Error::invalid(
            "times",
            "strictly increasing or strictly decreasing times",
            format!("{times:?}"),
        ));
    }
    Ok(())
}

/// Whether every element of `t` is finite. (A maximum of `|t|` would not do: candle's
/// max reduction skips a NaN, which let a NaN state through the RK4 step check.)
fn all_finite(t: &Tensor) -> Result<bool> {
    match check_finite(t, "y") {
        Ok(()) => Ok(true),
        Err(Error::InvalidArgument { .. }) => Ok(false),
        Err(e) => Err(e),
    }
}

/// Root mean square of all elements of `x` (detached), as f64; 0 for an empty tensor.
fn rms(x: &Tensor) -> Result<f64> {
    let n = x.elem_count();
    if n == 0 {
        return Ok(0.0);
    }
    let s = x.detach().sqr()?.flatten_all()?.sum(0)?;
    let s = s.to_dtype(candle_core::DType::F64)?.to_scalar::<f64>()?;
    Ok((s / n as f64).sqrt())
}

#[derive(Clone, Copy)]
struct Tolerance {
    rtol: f64,
    atol: f64,
}

impl Tolerance {
    /// `atol + rtol·max(|a|, |b|)`, detached.
    fn scale(self, a: &Tensor, b: &Tensor) -> Result<Tensor> {
        let m = a.detach().abs()?.maximum(&b.detach().abs()?)?;
        Ok(m.affine(self.rtol, self.atol)?)
    }
}

/// `y + h·Σ cᵢ kᵢ` over the non-zero coefficients.
fn combine(y: &Tensor, h: f64, coefs: &[f64], ks: &[Tensor]) -> Result<Tensor> {
    let mut acc = y.clone();
    for (c, k) in coefs.iter().zip(ks) {
        if *c != 0.0 {
            acc = (acc + k.affine(h * c, 0.0)?)?;
        }
    }
    Ok(acc)
}

// The Dormand–Prince 5(4) tableau: nodes, stages, and the error weights b₅ − b₄.
const C: [f64; 5] = [0.2, 0.3, 0.8, 8.0 / 9.0, 1.0];
const A: [&[f64]; 6] = [
    &[0.2],
    &[3.0 / 40.0, 9.0 / 40.0],
    &[44.0 / 45.0, -56.0 / 15.0, 32.0 / 9.0],
    &[
        19372.0 / 6561.0,
        -25360.0 / 2187.0,
        64448.0 / 6561.0,
        -212.0 / 729.0,
    ],
    &[
        9017.0 / 3168.0,
        -355.0 / 33.0,
        46732.0 / 5247.0,
        49.0 / 176.0,
        -5103.0 / 18656.0,
    ],
    // The fifth-order solution (first same as last: the next step's first stage).
    &[
        35.0 / 384.0,
        0.0,
        500.0 / 1113.0,
        125.0 / 192.0,
        -2187.0 / 6784.0,
        11.0 / 84.0,
    ],
];
const E: [f64; 7] = [
    71.0 / 57600.0,
    0.0,
    -71.0 / 16695.0,
    71.0 / 1920.0,
    -17253.0 / 339200.0,
    22.0 / 525.0,
    -1.0 / 40.0,
];

struct Run<'a, F> {
    f: &'a F,
    detach: bool,
    shape: Vec<usize>,
    evaluations: usize,
    accepted: usize,
    rejected: usize,
}

impl<F> Run<'_, F>
where
    F: Fn(f64, &Tensor) -> Result<Tensor>,
{
    /// The state as the graph setting keeps it.
    fn keep(&self, y: Tensor) -> Tensor {
        if self.detach {
            y.detach()
        } else {
            y
        }
    }

    fn eval(&mut self, t: f64, y: &Tensor) -> Result<Tensor> {
        self.evaluations += 1;
        let k = (self.f)(t, y)?;
        if k.dims() != self.shape.as_slice() {
            return Err(Error::invalid(
                "f",
                format!("a derivative shaped like y0, {:?}", self.shape),
                format!("{:?} at t = {t}", k.dims()),
            ));
        }
        Ok(k)
    }

    fn non_finite(t: f64) -> Error {
        Error::invalid(
            "f",
            "finite derivatives",
            format!("a NaN or infinity in the state at t = {t}"),
        )
    }

    fn rk4(&mut self, y: &Tensor, t0: f64, t1: f64, steps: usize) -> Result<Tensor> {
        let n = (((t1 - t0).abs() * steps as f64).ceil() as usize).max(1);
        let h = (t1 - t0) / n as f64;
        let mut y = y.clone();
        for i in 0..n {
            let t = t0 + h * i as f64;
            let k1 = self.eval(t, &y)?;
            let k2 = self.eval(
                t + 0.5 * h,
                &combine(&y, 0.5 * h, &[1.0], std::slice::from_ref(&k1))?,
            )?;
            let k3 = self.eval(
                t + 0.5 * h,
                &combine(&y, 0.5 * h, &[1.0], std::slice::from_ref(&k2))?,
            )?;
            let k4 = self.eval(t + h, &combine(&y, h, &[1.0], std::slice::from_ref(&k3))?)?;
            y = self.keep(combine(
                &y,
                h / 6.0,
                &[1.0, 2.0, 2.0, 1.0],
                &[k1, k2, k3, k4],
            )?);
            self.accepted += 1;
            if !all_finite(&y)? {
                return Err(Self::non_finite(t + h));
            }
        }
        Ok(y)
    }

    /// Hairer, Nørsett and Wanner's first step (Solving ODEs I, II.4), signed toward `t_end`.
    fn initial_step(
        &mut self,
        y: &Tensor,
        k1: &Tensor,
        t0: f64,
        t_end: f64,
        tol: Tolerance,
    ) -> Result<f64> {
        let span = (t_end - t0).abs();
        let dir = (t_end - t0).signum();
        let scale = tol.scale(y, y)?;
        let d0 = rms(&y.detach().div(&scale)?)?;
        let d1 = rms(&k1.detach().div(&scale)?)?;
        if !d1.is_finite() {
            return Err(Self::non_finite(t0));
        }
        let h0 = if d0 < 1e-5 || d1 < 1e-5 {
            1e-6
        } else {
            0.01 * d0 / d1
        }
        .min(span);
        let y1 = combine(&y.detach(), dir * h0, &[1.0], &[k1.detach()])?;
        let k2 = self.eval(t0 + dir * h0, &y1)?.detach();
        let d2 = rms(&(k2 - k1.detach())?.div(&scale)?)? / h0;
        let h1 = if d1.max(d2) <= 1e-15 {
            (h0 * 1e-3).max(1e-6)
        } else {
            (0.01 / d1.max(d2)).powf(0.2)
        };
        Ok(dir * (100.0 * h0).min(h1).min(span))
    }

    /// Adaptive steps from `t0` to exactly `t1`; returns the state there, the derivative
    /// there (first same as last) and the step to try next.
    #[allow(clippy::too_many_arguments)]
    fn dopri5(
        &mut self,
        mut y: Tensor,
        mut k1: Tensor,
        mut h: f64,
        t0: f64,
        t1: f64,
        tol: Tolerance,
        max_steps: usize,
    ) -> Result<(Tensor, Tensor, f64)> {
        let dir = (t1 - t0).signum();
        let min_step = 1e-12 * (t1 - t0).abs();
        let mut t = t0;
        if h * dir <= 0.0 || !h.is_finite() {
            h = dir * (t1 - t0).abs();
        }
        while (t1 - t) * dir > 0.0 {
            if self.accepted + self.rejected >= max_steps {
                return Err(Error::invalid(
                    "solver.max_steps",
                    format!("a solve within {max_steps} steps"),
                    format!("the limit reached at t = {t} (a stiff or exploding field?)"),
                ));
            }
            // Land exactly on t1 (and do not leave a sliver behind).
            let last = (t + h - t1) * dir >= -1e-12 * (t1 - t0).abs();
            let step = if last { t1 - t } else { h };
            // Stages 2–6, then the fifth-order solution, whose derivative is stage 7.
            let mut ks = vec![k1.clone()];
            for (c, a) in C.iter().zip(A.iter()) {
                let yi = combine(&y, step, a, &ks)?;
                ks.push(self.eval(t + c * step, &yi)?);
            }
            let y_new = combine(&y, step, A[5], &ks)?;
            let k7 = self.eval(t + step, &y_new)?;
            ks.push(k7.clone());
            let detached: Vec<Tensor> = ks.iter().map(Tensor::detach).collect();
            let err_vec = combine(&y.zeros_like()?, step, &E, &detached)?;
            let err = rms(&err_vec.div(&tol.scale(&y, &y_new)?)?)?;
            if !err.is_finite() {
                return Err(Self::non_finite(t + step));
            }
            let factor = if err == 0.0 {
                10.0
            } else {
                (0.9 * err.powf(-0.2)).clamp(0.2, 10.0)
            };
            if err <= 1.0 {
                self.accepted += 1;
                t = if last { t1 } else { t + step };
                y = self.keep(y_new);
                k1 = self.keep(k7);
                // Do not let a short landing step shrink the next regular step.
                h = if last {
                    dir * h.abs().max((step * factor).abs())
                } else {
                    step * factor
                };
            } else {
                self.rejected += 1;
                h = step * factor;
                if h.abs() < min_step {
                    return Err(Error::invalid(
                        "solver.max_steps",
                        "a step longer than 1e-12 of the interval",
                        format!("a step of {h:e} at t = {t} (a stiff or exploding field?)"),
                    ));
                }
            }
        }
        Ok((y, k1, h))
    }
}
