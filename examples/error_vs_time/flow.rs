//! ODE solver error against run time: the deforming torus of the Occupancy Flow example,
//! whose flow is known in closed form, integrated by RK4 at several step counts and by
//! Dormand–Prince at several tolerances.

use crate::report::{median_seconds, v64, Row, Table, TIME_PER_CALL};
use candle_core::{DType, Device, Tensor};
use neural_fields::flow::{odeint, DeformingTorus, Graph, Solver};
use neural_fields::mesh::points_to_tensor;
use neural_fields::rng::SplitMix64;

/// Mean Euclidean distance between the solver's points at t = 1 and the exact ones.
fn mean_error(got: &Tensor, exact: &[[f64; 3]]) -> f64 {
    let g = v64(got);
    let total: f64 = exact
        .iter()
        .enumerate()
        .map(|(i, e)| {
            (0..3)
                .map(|k| (g[3 * i + k] - e[k]).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .sum();
    total / exact.len() as f64
}

pub fn run(quick: bool) -> Vec<Table> {
    let n = if quick { 256 } else { 4096 };
    let reps = if quick { 1 } else { 5 };
    let motion = DeformingTorus::default();
    let mut rng = SplitMix64::new(7);
    let start = motion
        .surface(n, &mut rng)
        .expect("the default torus and a small count are valid"); // invariant
    let exact: Vec<[f64; 3]> = start.iter().map(|&p| motion.carry(p, 0.0, 1.0)).collect();
    let mut rows = Vec::new();
    let mut solvers: Vec<(String, f64, Solver)> = [1usize, 2, 4, 8, 16, 32, 64]
        .into_iter()
        .map(|steps| {
            (
                "RK4 (knob: steps)".to_string(),
                steps as f64,
                Solver::Rk4 { steps },
            )
        })
        .collect();
    solvers.extend(
        [1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8]
            .into_iter()
            .map(|rtol| {
                (
                    "Dormand–Prince 5(4) (knob: rtol; atol = rtol/100)".to_string(),
                    rtol,
                    Solver::Dopri5 {
                        rtol,
                        atol: rtol / 100.0,
                        max_steps: 100_000,
                    },
                )
            }),
    );
    for dtype in [DType::F32, DType::F64] {
        let p0 = points_to_tensor(&start, &Device::Cpu, dtype).unwrap();
        for (series, knob, solver) in &solvers {
            let solve = || {
                odeint(
                    |t, p| motion.velocity(p, t),
                    &p0,
                    &[0.0, 1.0],
                    solver,
                    Graph::Detach,
                )
                .unwrap()
            };
            let out = solve();
            let seconds = median_seconds(reps, || drop(solve()));
            rows.push(Row {
                series: format!("{series}, {dtype:?}"),
                knob: *knob,
                error: mean_error(&out.states[1], &exact),
                seconds,
                work: out.evaluations as f64,
            });
        }
    }
    vec![Table {
        title: "ODE solver error vs steps and tolerance".into(),
        description: format!(
            "Occupancy Flow's integration on the twisting, stretching, moving torus of `examples/occupancy_flow` (`flow::DeformingTorus`, closed-form flow Φ): {n} surface points carried from t = 0 to 1 by `flow::odeint` along the analytic velocity (candle ops), without graph (`Graph::Detach`); error = mean ‖Φ̂(p, 1) − Φ(p, 1)‖ over the points; time = median of {reps} solves on CPU; work = evaluations of the velocity. RK4's knob is steps per unit of time, Dormand–Prince's the relative tolerance (Occupancy Flow trains with rtol 1e-3, atol 1e-5). The example trains with RK4 at 4 steps and evaluates with Dormand–Prince at 1e-5."
        ),
        knob: "steps or rtol".into(),
        error_name: "mean ‖Φ̂ − Φ‖ at t = 1".into(),
        work_unit: "velocity evaluations".into(),
        time_name: TIME_PER_CALL.into(),
        rows,
    }]
}
