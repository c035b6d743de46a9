//! Stiff cases of `nn`: the MLP and its Jacobian at extreme inputs.

mod common;

use candle_core::{DType, Device, Tensor, Var};

use common::stiff::{var, Expect, Suite, DTYPES};

use neural_fields::encoding::{FrequencyEncoding, PointEncoding};
use neural_fields::field::Field;
use neural_fields::nn::{build_seeded, mlp, Activation, MlpConfig};

#[test]
fn mlp_stays_finite() {
    let mut s = Suite::default();
    sweep_mlp(&mut s);
    s.finish("mlp", MLP);
}

#[test]
fn every_public_nn_function_is_swept_or_exempt() {
    common::stiff::check_coverage("stiff_cases_nn", &[MLP], EXEMPT, &[], &[]);
}

/// Items swept by `sweep_mlp`.
const MLP: &[&str] = &[
    "nn::Mlp::forward",
    "nn::Mlp::forward_with_jacobian",
    "nn::MlpConfig::sdf",
    "nn::mlp",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    ("nn::SeededBackend::", "private"),
    (
        "nn::adam",
        "one scalar, refused unless positive and finite (tests/nn_training.rs)",
    ),
    (
        "nn::Adam::",
        "swept in tests/nn_training.rs (adam_fused_passes_match_candle_nn_adamw): zero, \
         1e-30 and 1e18 (f32) / 1e30 (f64) gradients of both signs, weight decay and a \
         learning-rate change, every value asserted finite and equal to candle-nn's AdamW",
    ),
    (
        "nn::Clock::",
        "wall time and step counts; a budget of minutes is refused unless positive and \
         finite (tests/nn_training.rs)",
    ),
    (
        "nn::FiniteGuard::",
        "its input is checked for NaN and infinity, which it reports by name \
         (tests/nn_training.rs feeds it both)",
    ),
    (
        "nn::Budget",
        "an enum of a count or minutes, checked by Clock::start",
    ),
    (
        "nn::build_seeded",
        "integer seed; its draws are swept via the Mlp cases",
    ),
    (
        "nn::Mlp::forward_with_code",
        "the ConditionalField forward: the Field forward with codes (swept as Mlp::forward)",
    ),
    ("nn::Mlp::inside", "getter"),
    ("nn::Mlp::out_dim", "getter"),
    ("nn::Mlp::value", "forwards to Field::forward"),
    ("nn::Mlp::code_dim", "getter"),
    (
        "nn::Mlp::value_and_grad",
        "forwards to forward_with_jacobian",
    ),
    ("nn::MlpConfig::default", "constant"),
    (
        "kernels::",
        "crate-private fused CPU kernels (CustomOp internals, their f32/f64 slices and \
         activation slices, the latter also tested against the standard library in their \
         module), swept via the public functions that run them: Mlp::forward, \
         Mlp::forward_with_jacobian and Mlp::value_and_grad here, Nerf::radiance, \
         Nerf::color_loss and composite in tests/stiff_cases_volume.rs",
    ),
];

fn sweep_mlp(s: &mut Suite) {
    let d = Device::Cpu;
    for dtype in DTYPES {
        let big = if dtype == DType::F32 { 1e8 } else { 1e100 };
        let x = var(
            &[
                0.0, 0.0, 0.0, 1e-30, 0.0, 0.0, big, -big, big, 1e4, 1.0, -1e4,
            ],
            &[4, 3],
            dtype,
        );
        for (activation, radius, tag) in [
            (Activation::Relu, None, "ReLU"),
            (
                Activation::Softplus { beta: 100.0 },
                Some(0.5),
                "softplus(100), geometric init",
            ),
            (Activation::Softplus { beta: 1e-3 }, None, "softplus(1e-3)"),
        ] {
            let config = MlpConfig {
                hidden: 16,
                depth: 3,
                skips: vec![2],
                activation,
                geometric_init: radius,
                encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 4).unwrap()),
                ..MlpConfig::default()
            };
            let varmap = candle_nn::VarMap::new();
            let net = build_seeded(&varmap, dtype, &d, 3, |vb| mlp(&config, vb)).unwrap();
            let label = format!("{dtype:?}, {tag}, |x| up to {big:e}");
            let vars = varmap.all_vars();
            let mut wrt: Vec<&Var> = vars.iter().collect();
            wrt.push(&x);
            s.case("nn::mlp", &label, Expect::Finite, &[], || Ok(vec![]));
            s.case(
                "nn::Mlp::forward_with_jacobian",
                &label,
                Expect::Finite,
                &wrt,
                || {
                    let (y, j) = net.forward_with_jacobian(x.as_tensor(), None)?;
                    Ok(vec![y, j])
                },
            );
            s.case("nn::Mlp::forward", &label, Expect::Finite, &wrt, || {
                Ok(vec![Field::forward(&net, x.as_tensor())?])
            });
            s.case("nn::MlpConfig::sdf", &label, Expect::Finite, &[], || {
                Ok(vec![Tensor::new(
                    MlpConfig::sdf(1e-30).geometric_init.unwrap_or(0.0),
                    &d,
                )?])
            });
        }
    }
}
