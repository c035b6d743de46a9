//! Stiff cases of `flow`: the ODE solvers on stiff systems, the velocity field and
//! Occupancy Flow at extreme inputs.

#![cfg(feature = "flow")]

mod common;

use candle_core::{DType, Device, Tensor, Var};

use common::stiff::{magnitudes, var, Expect, Suite, DTYPES};

use neural_fields::nn::{build_seeded, mlp, MlpConfig};

#[test]
fn flow_stays_finite() {
    let mut s = Suite::default();
    sweep_flow(&mut s);
    s.finish("flow", FLOW);
}

#[test]
fn every_public_flow_function_is_swept_or_exempt() {
    common::stiff::check_coverage("stiff_cases_flow", &[FLOW], EXEMPT, &[], &[]);
}

/// Items swept by `sweep_flow`.
const FLOW: &[&str] = &[
    "flow::OccupancyFlow::correspondences",
    "flow::OccupancyFlow::logits",
    "flow::VelocityField::carry",
    "flow::VelocityField::velocity",
    "flow::correspondence_loss",
    "flow::odeint",
    "flow::velocity_field",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    (
        "flow::DeformingTorus::",
        "an analytic motion on host values for tests and examples, checked against odeint \
         along its own velocity in tests/flow.rs",
    ),
    ("flow::Solver::default", "constant"),
    ("flow::VelocityFieldConfig::default", "constant"),
];

/// The ODE solvers on stiff linear systems (decay rates up to 1e8, where RK4 blows up and
/// Dormand–Prince runs out of steps: both must end in `Err`, not in a non-finite state),
/// and with a right-hand side that returns NaN; the velocity field, carried points and
/// Occupancy Flow at extreme points, times and codes; the correspondence loss at zero
/// and extreme distances.
fn sweep_flow(s: &mut Suite) {
    use neural_fields::flow::{
        correspondence_loss, odeint, velocity_field, Graph, OccupancyFlow, Solver,
        VelocityFieldConfig,
    };
    let d = Device::Cpu;
    let solvers = [
        Solver::Rk4 { steps: 8 },
        Solver::Dopri5 {
            rtol: 1e-3,
            atol: 1e-5,
            max_steps: 200,
        },
    ];
    for dtype in DTYPES {
        let mags = magnitudes(dtype);
        let y0 = var(&mags, &[mags.len()], dtype);
        for solver in &solvers {
            for rate in [0.0, 1e-30, 1.0, 1e3, 1e8] {
                // Stiff rates may end in Err (step limit, non-finite state); mild ones may not.
                let expect = if rate <= 1.0 {
                    Expect::Finite
                } else {
                    Expect::FiniteOrErr
                };
                s.case(
                    "flow::odeint",
                    format!("{dtype:?}, {solver:?}, y' = -{rate:e} y, |y0| up to 1e30+"),
                    expect,
                    &[&y0],
                    || {
                        let out = odeint(
                            |_, y| Ok(y.affine(-rate, 0.0)?),
                            y0.as_tensor(),
                            &[0.0, 0.5, 1.0],
                            solver,
                            Graph::Keep,
                        )?;
                        Ok(out.states)
                    },
                );
            }
            let nan = odeint(
                |_, y| Ok((y * f64::NAN)?),
                y0.as_tensor(),
                &[0.0, 1.0],
                solver,
                Graph::Keep,
            );
            if nan.is_ok() {
                s.failures.push(format!(
                    "odeint [{dtype:?}, {solver:?}]: a right-hand side returning NaN gave Ok"
                ));
            }
        }

        let big = if dtype == DType::F32 { 1e8 } else { 1e100 };
        let p = var(
            &[
                0.0, 0.0, 0.0, 1e-30, 0.0, 0.0, big, -big, big, 1e4, 1.0, -1e4, 0.5, 0.5, 0.5,
            ],
            &[5, 3],
            dtype,
        );
        let code = var(
            &[0.0, big, -1e-30, 1.0, 0.5, -big, 1e4, 0.0, 2.0, -3.0],
            &[5, 2],
            dtype,
        );
        let config = VelocityFieldConfig {
            hidden: 8,
            blocks: 2,
            code_dim: 2,
        };
        let vm = candle_nn::VarMap::new();
        let v = build_seeded(&vm, dtype, &d, 4, |vb| velocity_field(&config, vb)).unwrap();
        let mut wrt: Vec<Var> = vm.all_vars();
        wrt.push(p.clone());
        wrt.push(code.clone());
        let wrt: Vec<&Var> = wrt.iter().collect();
        let label = format!("{dtype:?}, |p| and |code| up to {big:e}");
        s.case("flow::velocity_field", &label, Expect::Finite, &[], || {
            Ok(vec![])
        });
        for t in [0.0, 1e-30, 0.5, 1.0] {
            s.case(
                "flow::VelocityField::velocity",
                format!("{label}, t = {t:e}"),
                Expect::Finite,
                &wrt,
                || {
                    Ok(vec![v.velocity(
                        p.as_tensor(),
                        t,
                        Some(code.as_tensor()),
                    )?])
                },
            );
        }
        for solver in &solvers {
            // |v| grows with |p|: Dormand–Prince may run out of steps on the huge points.
            s.case(
                "flow::VelocityField::carry",
                format!("{label}, {solver:?}"),
                Expect::FiniteOrErr,
                &wrt,
                || {
                    Ok(v.carry(
                        p.as_tensor(),
                        &[1.0, 0.25, 0.0],
                        Some(code.as_tensor()),
                        solver,
                        Graph::Keep,
                    )?
                    .states)
                },
            );
        }
        let dm = candle_nn::VarMap::new();
        let decoder_config = MlpConfig {
            hidden: 8,
            depth: 2,
            ..MlpConfig::default()
        };
        let decoder = build_seeded(&dm, dtype, &d, 5, |vb| mlp(&decoder_config, vb)).unwrap();
        let small = var(
            &[
                0.0, 0.0, 0.0, 1e-30, 0.0, 0.0, 0.5, -0.5, 0.5, 1.0, 1.0, -1.0, 0.2, 0.1, 0.0,
            ],
            &[5, 3],
            dtype,
        );
        let shared = code.as_tensor().get(1).unwrap();
        let flow = OccupancyFlow {
            decoder: &decoder,
            velocity: &v,
            code: Some(&shared),
            solver: Solver::default(),
            graph: Graph::Keep,
        };
        let mut fwrt: Vec<Var> = vm.all_vars();
        fwrt.extend(dm.all_vars());
        fwrt.push(small.clone());
        let fwrt: Vec<&Var> = fwrt.iter().collect();
        let flabel = format!("{dtype:?}, code up to {big:e}");
        for t in [0.0, 1e-30, 0.5, 1.0] {
            s.case(
                "flow::OccupancyFlow::logits",
                format!("{flabel}, t = {t:e}"),
                Expect::FiniteOrErr,
                &fwrt,
                || Ok(vec![flow.logits(small.as_tensor(), t)?]),
            );
        }
        s.case(
            "flow::OccupancyFlow::correspondences",
            &flabel,
            Expect::FiniteOrErr,
            &fwrt,
            || flow.correspondences(small.as_tensor(), &[0.0, 1e-30, 0.5, 1.0]),
        );
        // A moderate code: Occupancy Flow must succeed.
        let unit = Tensor::new(&[0.3, -0.2], &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let moderate = OccupancyFlow {
            code: Some(&unit),
            ..flow
        };
        s.case(
            "flow::OccupancyFlow::logits",
            format!("{dtype:?}, moderate code, t = 0.75"),
            Expect::Finite,
            &fwrt,
            || Ok(vec![moderate.logits(small.as_tensor(), 0.75)?]),
        );
        s.case(
            "flow::OccupancyFlow::correspondences",
            format!("{dtype:?}, moderate code"),
            Expect::Finite,
            &fwrt,
            || moderate.correspondences(small.as_tensor(), &[0.25, 1.0]),
        );
        // Zero distances (the norm's kink) and extreme ones.
        let top = if dtype == DType::F32 { 1e18 } else { 1e150 };
        let pred = var(
            &[
                0.0, 0.0, 0.0, 1.0, 2.0, 3.0, top, -top, top, 1e-30, 0.0, 0.0,
            ],
            &[4, 3],
            dtype,
        );
        let target = var(
            &[0.0, 0.0, 0.0, 1.0, 2.0, 3.0, -top, top, 0.0, 0.0, 0.0, 0.0],
            &[4, 3],
            dtype,
        );
        s.case(
            "flow::correspondence_loss",
            format!("{dtype:?}, distances 0 to {top:e}"),
            Expect::Finite,
            &[&pred, &target],
            || {
                Ok(vec![correspondence_loss(
                    pred.as_tensor(),
                    target.as_tensor(),
                )?])
            },
        );
    }
}
