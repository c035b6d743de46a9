//! The training loop's companions: Adam without weight decay, the NaN/Inf guard that
//! names the step and the tensor, and the budget clock.

use candle_core::Var;
use candle_core::{DType, Device, Tensor};
use candle_nn::{AdamW, Init, Optimizer, ParamsAdamW, VarMap};
use neural_fields::nn::{adam, Adam, Budget, Clock, FiniteGuard};
use neural_fields::rng::SplitMix64;
use neural_fields::{Error, Result};
use std::time::Duration;

const DEV: Device = Device::Cpu;

fn message(r: Result<()>) -> String {
    match r {
        Err(
            e @ Error::InvalidArgument {
                arg: "training", ..
            },
        ) => e.to_string(),
        other => panic!("expected an error naming training, got {other:?}"),
    }
}

#[test]
fn adam_descends_and_does_not_decay_weights() -> Result<()> {
    let varmap = VarMap::new();
    let a = varmap.get(3, "a", Init::Const(0.0), DType::F64, &DEV)?;
    let b = varmap.get(2, "b", Init::Const(1.5), DType::F64, &DEV)?;
    let mut opt = adam(&varmap, 0.05)?;
    for _ in 0..400 {
        // (a − 3)² pulls `a` to 3; `b` has a zero gradient: AdamW's default decay of 0.01
        // would shrink it, Adam leaves it.
        let loss = (a.affine(1.0, -3.0)?.sqr()?.sum_all()? + b.affine(0.0, 0.0)?.sum_all()?)?;
        opt.backward_step(&loss)?;
    }
    for x in a.to_vec1::<f64>()? {
        assert!((x - 3.0).abs() < 1e-2, "{x}");
    }
    assert_eq!(b.to_vec1::<f64>()?, vec![1.5, 1.5]);
    for lr in [0.0, -1e-3, f64::NAN, f64::INFINITY] {
        assert!(
            matches!(
                adam(&varmap, lr),
                Err(Error::InvalidArgument { arg: "lr", .. })
            ),
            "{lr}"
        );
    }
    Ok(())
}

/// Gradients for step `k` of variable `i`: ordinary values, then stiff ones (zeros,
/// 1e-30, 1e30 in f64 / 1e18 in f32, alternating signs) in later steps.
fn stiff_grad(rng: &mut SplitMix64, n: usize, k: usize, dtype: DType) -> Result<Tensor> {
    let big = if dtype == DType::F32 { 1e18 } else { 1e30 };
    let v: Vec<f64> = (0..n)
        .map(|j| {
            let u = 2.0 * rng.uniform() - 1.0;
            match (k + j) % 5 {
                0 if k >= 3 => 0.0,
                1 if k >= 3 => u * 1e-30,
                2 if k >= 6 => u * big,
                _ => u,
            }
        })
        .collect();
    Ok(Tensor::from_vec(v, n, &DEV)?.to_dtype(dtype)?)
}

#[test]
fn adam_fused_passes_match_candle_nn_adamw() -> Result<()> {
    for dtype in [DType::F32, DType::F64] {
        for (lr, weight_decay) in [(1e-3, 0.0), (0.05, 0.01), (1.0, 0.0)] {
            let params = ParamsAdamW {
                lr,
                weight_decay,
                ..ParamsAdamW::default()
            };
            let init = |i: usize| -> Result<Var> {
                let mut rng = SplitMix64::new(i as u64);
                Ok(Var::from_tensor(&rng.uniform_tensor(
                    &[3 + 5 * i, 2],
                    -1.0,
                    1.0,
                    dtype,
                    &DEV,
                )?)?)
            };
            let ours: Vec<Var> = (0..3).map(init).collect::<Result<_>>()?;
            let theirs: Vec<Var> = (0..3).map(init).collect::<Result<_>>()?;
            let mut a = Adam::new(ours.clone(), params.clone())?;
            let mut b = AdamW::new(theirs.clone(), params.clone())?;
            let mut rng = SplitMix64::new(7);
            for k in 0..12 {
                if k == 8 {
                    a.set_learning_rate(lr / 2.0);
                    b.set_learning_rate(lr / 2.0);
                }
                // Variable 2 has no gradient at odd steps: left as it is by both.
                let (mut ga, mut gb) = (Vec::new(), Vec::new());
                for (i, (x, y)) in ours.iter().zip(&theirs).enumerate() {
                    if i == 2 && k % 2 == 1 {
                        continue;
                    }
                    let g = stiff_grad(&mut rng, x.elem_count(), k, dtype)?.reshape(x.shape())?;
                    ga.push((x.as_tensor() * &g)?.sum_all()?);
                    gb.push((y.as_tensor() * &g)?.sum_all()?);
                }
                a.step(&Tensor::stack(&ga, 0)?.sum_all()?.backward()?)?;
                b.step(&Tensor::stack(&gb, 0)?.sum_all()?.backward()?)?;
                for (x, y) in ours.iter().zip(&theirs) {
                    let x = x.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()?;
                    let y = y.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()?;
                    let tol = if dtype == DType::F32 { 1e-6 } else { 1e-13 };
                    for (p, q) in x.iter().zip(&y) {
                        assert!(p.is_finite(), "{dtype:?} lr {lr} step {k}: {p}");
                        assert!(
                            (p - q).abs() <= tol * (1.0 + q.abs()),
                            "{dtype:?} lr {lr} decay {weight_decay} step {k}: {p} vs candle-nn {q}"
                        );
                    }
                }
            }
            assert_eq!(a.learning_rate(), lr / 2.0);
        }
    }
    Ok(())
}

#[test]
fn finite_guard_names_the_step_and_the_first_bad_tensor() -> Result<()> {
    let mut varmap = VarMap::new();
    let a = varmap.get(2, "a", Init::Const(0.0), DType::F32, &DEV)?;
    let b = varmap.get(2, "b", Init::Const(1.0), DType::F32, &DEV)?;
    let guard = FiniteGuard::new(&varmap);
    // A finite loss with finite gradients and weights passes.
    let loss = (a.sqr()?.sum_all()? + b.sqr()?.sum_all()?)?;
    guard.check(3, &loss, Some(&loss.backward()?))?;
    // A NaN loss is named first.
    let nan = Tensor::new(f32::NAN, &DEV)?;
    let m = message(guard.check(4, &nan, None));
    assert!(m.contains("the loss at step 4"), "{m}");
    // √a at a = 0: a finite loss whose gradient is infinite.
    let loss = (a.sqrt()?.sum_all()? + b.sum_all()?)?;
    let grads = loss.backward()?;
    guard.check(5, &loss, None)?; // without gradients only the loss is checked
    let m = message(guard.check(5, &loss, Some(&grads)));
    assert!(m.contains("the gradient of a at step 5"), "{m}");
    // An infinite weight, with finite gradients.
    varmap.set_one("b", Tensor::new(&[1.0f32, f32::INFINITY], &DEV)?)?;
    let loss = a.sum_all()?;
    let m = message(guard.check(6, &loss, Some(&loss.backward()?)));
    assert!(m.contains("the weight b at step 6"), "{m}");
    // Read back at once, still named in order: a bad gradient (of a) before a bad
    // weight (b, still infinite).
    let loss = a.sqrt()?.sum_all()?;
    let m = message(guard.check(7, &loss, Some(&loss.backward()?)));
    assert!(m.contains("the gradient of a at step 7"), "{m}");
    // Finite weights whose Σ|x| overflows f32 are finite (only NaN and ±∞ stop a run).
    varmap.set_one("b", Tensor::new(&[3e38f32, 3e38], &DEV)?)?;
    let loss = a.sum_all()?;
    guard.check(8, &loss, Some(&loss.backward()?))?;
    // A loss in another dtype than the variables' is checked with them.
    varmap.set_one("b", Tensor::new(&[1.0f32, 2.0], &DEV)?)?;
    let loss = a.sum_all()?;
    let grads = loss.backward()?;
    guard.check(8, &loss.to_dtype(DType::F64)?, Some(&grads))?;
    let m = message(guard.check(9, &Tensor::new(f64::INFINITY, &DEV)?, Some(&grads)));
    assert!(m.contains("the loss at step 9"), "{m}");
    Ok(())
}

#[test]
fn clock_counts_steps_or_training_time_without_pauses() -> Result<()> {
    let clock = Clock::start(Budget::Steps(4))?;
    assert_eq!(clock.progress(0), 0.0);
    assert_eq!(clock.progress(2), 0.5);
    assert_eq!(clock.progress(4), 1.0);
    assert_eq!(Clock::start(Budget::Steps(0))?.progress(0), 1.0);
    let mut clock = Clock::start(Budget::Minutes(1.0))?;
    let wall = std::time::Instant::now();
    let x = clock.pause(|| {
        std::thread::sleep(Duration::from_millis(200));
        7
    });
    assert_eq!(x, 7);
    let (train, wall) = (clock.train_seconds(), wall.elapsed().as_secs_f64());
    assert!(train >= 0.0 && train < wall - 0.15, "{train} of {wall}");
    // Minutes: the step does not count, the training seconds do.
    let p = clock.progress(1_000_000);
    assert!(p >= 0.0 && p < 0.15 / 60.0 + train / 60.0 + 0.01, "{p}");
    for m in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        assert!(
            matches!(
                Clock::start(Budget::Minutes(m)),
                Err(Error::InvalidArgument { arg: "budget", .. })
            ),
            "{m}"
        );
    }
    Ok(())
}
