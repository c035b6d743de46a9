//! Motion (feature `flow`): ODE integration with gradients and Occupancy Flow
//! (Niemeyer et al., ICCV 2019).
//!
//! * [`odeint`] with a [`Solver`]: fixed-step RK4 or adaptive Dormand–Prince 5(4), forward
//!   or backward in time, differentiable by backpropagation through the steps
//!   ([`Graph::Keep`]) or detached step by step for evaluation ([`Graph::Detach`]); a step
//!   limit and a finiteness check on every step, so that a stiff or exploding field ends
//!   in an `Err`, not an endless loop.
//! * [`VelocityField`] / [`velocity_field`]: the velocity network `v(p, t, c)`, and
//!   [`VelocityField::carry`], which moves points along it.
//! * [`OccupancyFlow`]: occupancy at any time from a time-0 decoder (points carried back
//!   to time 0) and correspondences (time-0 points carried forward);
//!   [`correspondence_loss`], the mean Euclidean distance.
//! * [`DeformingTorus`]: an analytic motion (a torus that twists, stretches and moves)
//!   with closed-form occupancy, correspondences and velocity at every time, as ground
//!   truth for tests, examples and solver benchmarks.
//!
//! Memory: backpropagating through the solver keeps every stage of every step
//! (`7·N·3` values per Dopri5 step plus the network's activations); the adjoint method,
//! which trades that memory for a second integration, is not implemented.
//!
//! ```
//! use candle_core::{DType, Device, Tensor};
//! use candle_nn::VarMap;
//! use neural_fields::flow::{correspondence_loss, velocity_field, Graph, Solver, VelocityFieldConfig};
//! use neural_fields::nn::build_seeded;
//!
//! let dev = Device::Cpu;
//! let varmap = VarMap::new();
//! let config = VelocityFieldConfig { hidden: 32, blocks: 2, code_dim: 0 };
//! let v = build_seeded(&varmap, DType::F32, &dev, 0, |vb| velocity_field(&config, vb))?;
//! // Learn to translate points by +0.1 in x over one unit of time.
//! let p0 = Tensor::rand(-0.5f32, 0.5, (64, 3), &dev)?;
//! let target = p0.broadcast_add(&Tensor::new(&[0.1f32, 0.0, 0.0], &dev)?)?;
//! let moved = v.carry(&p0, &[0.0, 1.0], None, &Solver::Rk4 { steps: 2 }, Graph::Keep)?;
//! let loss = correspondence_loss(&moved.states[1], &target)?;
//! let grads = loss.backward()?;
//! assert!(varmap.all_vars().iter().any(|w| grads.get(w).is_some()));
//! # Ok::<(), neural_fields::Error>(())
//! ```

mod analytic;
mod ode;
mod velocity;

pub use analytic::DeformingTorus;
pub use ode::{odeint, Graph, Solver, Trajectory};
pub use velocity::{
    correspondence_loss, velocity_field, OccupancyFlow, VelocityField, VelocityFieldConfig,
};
