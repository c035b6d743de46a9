//! Occupancy Flow's velocity field `v(p, t, c)` and the model that carries points along
//! it to decode their occupancy at time 0.

use super::ode::{odeint, Graph, Solver, Trajectory};
use crate::error::{check_points, check_same, check_same_shape, check_shape, Dim, Error, Result};
use crate::field::Field;
use crate::nn::ResnetFc;
use candle_core::{Tensor, D};
use candle_nn::VarBuilder;

/// Settings of [`velocity_field`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct VelocityFieldConfig {
    /// Hidden width (Occupancy Flow: 512, 128 in its point-cloud configuration).
    pub hidden: usize,
    /// Number of ResNet-FC blocks (Occupancy Flow: 5).
    pub blocks: usize,
    /// Dimension of the conditioning code added before every block (0: none).
    pub code_dim: usize,
}

impl Default for VelocityFieldConfig {
    /// Occupancy Flow's point-cloud configuration: width 128, 5 blocks, no code.
    fn default() -> Self {
        Self {
            hidden: 128,
            blocks: 5,
            code_dim: 0,
        }
    }
}

/// Occupancy Flow's velocity field (Niemeyer et al., ICCV 2019): `v: (p, t, c) ↦ ℝ³`,
///
/// ```text
/// h = W_p [p, t] + b_p,
/// for each block i:  h ← h + W_cᵢ c + b_cᵢ  (when code_dim > 0);
///                    h ← h + W₁ᵢ relu(W₀ᵢ relu(h) + b₀ᵢ) + b₁ᵢ,
/// v = W_out relu(h) + b_out,
/// ```
///
/// with `t ∈ [0, 1]` the normalised time, `W₁ᵢ` and the output layer zero at
/// initialisation: the initial field is 0 and the flow the identity. Points move by
/// `dp/dt = v(p, t, c)`; [`VelocityField::carry`] integrates that. Build it with
/// [`velocity_field`]; candle ops on any device, f32 or f64.
///
/// ReLU makes `v` piecewise linear in `(p, t)`: its derivatives jump where a unit
/// switches, so a high-order solver's error estimate is unreliable across those kinks.
/// At Occupancy Flow's tolerance (`rtol 1e-3`) this costs nothing measurable; at
/// `rtol 1e-10` Dormand–Prince rejects about 40 % of its steps on a random field of
/// width 16 and reaches about 2e-8, not 1e-10 (`tests/flow.rs`).
#[derive(Clone, Debug)]
pub struct VelocityField {
    trunk: ResnetFc,
    config: VelocityFieldConfig,
}

/// Builds a [`VelocityField`] from `vb` (`fc_p`, `block{i}.fc0`, `block{i}.fc1`,
/// `code{i}` when `code_dim > 0`, `fc_out`).
///
/// ```
/// use candle_core::{DType, Device, Tensor};
/// use candle_nn::VarMap;
/// use neural_fields::flow::{velocity_field, Graph, Solver, VelocityFieldConfig};
/// use neural_fields::nn::build_seeded;
///
/// let varmap = VarMap::new();
/// let config = VelocityFieldConfig { hidden: 32, ..VelocityFieldConfig::default() };
/// let v = build_seeded(&varmap, DType::F64, &Device::Cpu, 0, |vb| velocity_field(&config, vb))?;
/// let p = Tensor::new(&[[0.1f64, 0.2, 0.3]], &Device::Cpu)?;
/// // At initialisation the field is zero: points stay where they are.
/// let moved = v.carry(&p, &[0.0, 1.0], None, &Solver::Rk4 { steps: 4 }, Graph::Detach)?;
/// assert_eq!(moved.states[1].to_vec2::<f64>()?, p.to_vec2::<f64>()?);
/// # Ok::<(), neural_fields::Error>(())
/// ```
///
/// # Errors
/// A zero `hidden` or `blocks` (naming `config.*`); errors of `vb`.
pub fn velocity_field(config: &VelocityFieldConfig, vb: VarBuilder) -> Result<VelocityField> {
    Ok(VelocityField {
        trunk: ResnetFc::new(4, config.hidden, config.blocks, config.code_dim, 3, &vb)?,
        config: config.clone(),
    })
}

fn check_time(t: f64, arg: &'static str) -> Result<()> {
    if !(0.0..=1.0).contains(&t) {
        return Err(Error::invalid(
            arg,
            "a normalised time in [0, 1]",
            t.to_string(),
        ));
    }
    Ok(())
}

impl VelocityField {
    /// Velocities `[N, 3]` at `points: [N, 3]` (f32 or f64) and time `t ∈ [0, 1]`, with
    /// `code: [D]` (shared) or `[N, D]` (per point) when `code_dim = D > 0`.
    /// Differentiable w.r.t. the parameters, the points and the code.
    ///
    /// # Errors
    /// `t` outside [0, 1] or NaN (naming `t`); wrong shapes, dtypes or devices of
    /// `points` or `code`; a code given to a field without one, or missing (naming
    /// `code`).
    pub fn velocity(&self, points: &Tensor, t: f64, code: Option<&Tensor>) -> Result<Tensor> {
        check_time(t, "t")?;
        let n = check_points(points, "points")?;
        let code = self.code_rows(code, n, points)?;
        self.velocity_unchecked(points, t, code.as_ref())
    }

    /// `v(p, t, c)` for checked arguments, `code` as rows (`[1, D]` or `[N, D]`).
    fn velocity_unchecked(&self, points: &Tensor, t: f64, code: Option<&Tensor>) -> Result<Tensor> {
        let time = points.narrow(1, 0, 1)?.ones_like()?.affine(t, 0.0)?;
        let x = Tensor::cat(&[points, &time], D::Minus1)?;
        self.trunk.forward(&x, code)
    }

    fn code_rows(
        &self,
        code: Option<&Tensor>,
        n: usize,
        points: &Tensor,
    ) -> Result<Option<Tensor>> {
        let d = self.config.code_dim;
        match (code, d) {
            (None, 0) => Ok(None),
            (Some(c), 0) => Err(Error::invalid(
                "code",
                "no code (this velocity field has code_dim 0)",
                format!("{:?}", c.dims()),
            )),
            (None, _) => Err(Error::invalid(
                "code",
                format!("a code [{d}] or [N, {d}]"),
                "none",
            )),
            (Some(c), _) => {
                check_same(c, "code", points, "points")?;
                if c.rank() == 1 {
                    check_shape(c, "code", &[Dim::Is(d)])?;
                    Ok(Some(c.unsqueeze(0)?))
                } else {
                    check_shape(c, "code", &[Dim::Is(n), Dim::Is(d)])?;
                    Ok(Some(c.clone()))
                }
            }
        }
    }

    /// Carries `points: [N, 3]`, given at time `times[0]`, along the flow
    /// `dp/dt = v(p, t, c)` to every time in `times` (all in [0, 1], increasing to go
    /// forward, decreasing to go back; see [`odeint`] for the solver, `graph` and what
    /// the gradient is). `states[i]` is `Φ(points, times[0] → times[i])`, `[N, 3]`.
    /// Differentiable w.r.t. the parameters, the points and the code.
    ///
    /// # Errors
    /// A time outside [0, 1] (naming `times`); the errors of [`VelocityField::velocity`]
    /// and of [`odeint`] (non-monotone times, the step limit, non-finite velocities).
    pub fn carry(
        &self,
        points: &Tensor,
        times: &[f64],
        code: Option<&Tensor>,
        solver: &Solver,
        graph: Graph,
    ) -> Result<Trajectory> {
        for &t in times {
            check_time(t, "times")?;
        }
        let n = check_points(points, "points")?;
        let code = self.code_rows(code, n, points)?;
        // The solver's stage times stay within the times' range (clamped against rounding).
        odeint(
            |t, p| self.velocity_unchecked(p, t.clamp(0.0, 1.0), code.as_ref()),
            points,
            times,
            solver,
            graph,
        )
    }
}

/// Occupancy Flow: the occupancy of a point `p` at time `t` is the time-0 decoder's at
/// the point carried back to time 0, `o(p, t) = f(Φ(p, t → 0))`, where `Φ` integrates
/// the velocity field backward in time; correspondences come from carrying time-0
/// points forward.
///
/// `decoder` is any one-channel [`Field`] of occupancy logits (an [`crate::nn::Mlp`], or a
/// conditional decoder with its code bound by [`crate::field::Conditioned`]).
#[derive(Clone, Copy, Debug)]
pub struct OccupancyFlow<'a, F: ?Sized> {
    /// The occupancy decoder at time 0, `[N, 3] → [N, 1]` logits.
    pub decoder: &'a F,
    /// The velocity field.
    pub velocity: &'a VelocityField,
    /// The code of the velocity field (`[D]` or `[N, D]`), when it has one.
    pub code: Option<&'a Tensor>,
    /// The solver for every integration.
    pub solver: Solver,
    /// Whether the integrations keep their graph (training) or not (evaluation).
    pub graph: Graph,
}

impl<F: Field + ?Sized> OccupancyFlow<'_, F> {
    /// Occupancy logits `[N]` of `points: [N, 3]` at time `t ∈ [0, 1]`: the decoder at
    /// `Φ(points, t → 0)` (no integration at `t = 0`). Differentiable w.r.t. both
    /// networks' parameters, the points and the code.
    ///
    /// # Errors
    /// A decoder with other than one channel (naming `decoder`); the errors of
    /// [`VelocityField::carry`] and of the decoder.
    pub fn logits(&self, points: &Tensor, t: f64) -> Result<Tensor> {
        if self.decoder.out_dim() != 1 {
            return Err(Error::invalid(
                "decoder",
                "a one-channel field of occupancy logits",
                format!("{} channels", self.decoder.out_dim()),
            ));
        }
        check_time(t, "t")?;
        let at_zero = if t == 0.0 {
            points.clone()
        } else {
            let back =
                self.velocity
                    .carry(points, &[t, 0.0], self.code, &self.solver, self.graph)?;
            back.states[1].clone()
        };
        Ok(self.decoder.forward(&at_zero)?.squeeze(1)?)
    }

    /// Carries time-0 `points: [N, 3]` forward to every time in `times` (increasing,
    /// in [0, 1]; `times[0]` need not be 0 but the points are taken to be at time 0):
    /// `states[i] = Φ(points, 0 → times[i])`, the correspondences of Occupancy Flow.
    ///
    /// # Errors
    /// The errors of [`VelocityField::carry`].
    pub fn correspondences(&self, points: &Tensor, times: &[f64]) -> Result<Vec<Tensor>> {
        let mut all = vec![0.0];
        all.extend(times.iter().copied().filter(|&t| t != 0.0));
        let out = self
            .velocity
            .carry(points, &all, self.code, &self.solver, self.graph)?;
        // states[0] is time 0; the non-zero times follow in order.
        let mut next = 0;
        Ok(times
            .iter()
            .map(|&t| {
                if t != 0.0 {
                    next += 1;
                }
                out.states[if t == 0.0 { 0 } else { next }].clone()
            })
            .collect())
    }
}

/// Occupancy Flow's correspondence loss: the mean Euclidean distance
/// `(1/N) Σᵢ ‖pᵢ − qᵢ‖₂` (not squared) between `predicted: [N, 3]` and `target: [N, 3]`,
/// a scalar. Differentiable w.r.t. both; where `pᵢ = qᵢ` the norm's gradient, undefined
/// there, is taken as 0 (the squared distance is floored at the dtype's smallest normal
/// number before the square root, so no NaN reaches the gradient).
///
/// # Errors
/// Shapes other than `[N, 3]` with `N ≥ 1`, or mismatched shapes, dtypes or devices
/// (naming `predicted` / `target`).
pub fn correspondence_loss(predicted: &Tensor, target: &Tensor) -> Result<Tensor> {
    let n = check_points(predicted, "predicted")?;
    check_same(target, "target", predicted, "predicted")?;
    check_same_shape(target, "target", predicted, "predicted")?;
    if n == 0 {
        return Err(Error::invalid("predicted", "at least one point", "none"));
    }
    let tiny = match predicted.dtype() {
        candle_core::DType::F32 => f64::from(f32::MIN_POSITIVE),
        _ => f64::MIN_POSITIVE,
    };
    let sq = (predicted - target)?.sqr()?.sum(D::Minus1)?;
    let floor = Tensor::full(tiny, n, predicted.device())?.to_dtype(sq.dtype())?;
    Ok(sq.maximum(&floor)?.sqrt()?.mean_all()?)
}
