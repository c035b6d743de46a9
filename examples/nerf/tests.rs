//! The nerf example's end-to-end tests: shortened runs with every sampler, encoding and
//! filter, the flags' contract, and the runs that must fail naming their cause.

use super::*;

fn metrics(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap()
}

/// The committed dataset at a quarter of its resolution, its test split cut to its first
/// two views, written in the Blender layout to `dir`: a run's final evaluation renders
/// every test view, which at twenty views took most of these runs' time.
fn quarter_scene_two_test_views(dir: &Path) -> PathBuf {
    use neural_fields::data::{write_blender, Dataset};
    for (split, keep) in [(Split::Train, usize::MAX), (Split::Test, 2)] {
        let config = LoadConfig {
            split,
            downscale: 4,
            ..LoadConfig::default()
        };
        let source = load(Path::new("examples/data/wuson"), &config).unwrap();
        let views = source.views().iter().take(keep).cloned().collect();
        let cut = Dataset::new(views, source.background(), source.bounds()).unwrap();
        write_blender(dir, split, &cut).unwrap();
    }
    dir.to_path_buf()
}

/// A few steps on the committed dataset at a quarter of its resolution (two test views):
/// the whole pipeline runs, writes every output with the documented keys, and resumes.
#[test]
fn a_shortened_run_trains_writes_its_outputs_and_resumes() {
    let root = std::env::temp_dir().join(format!("nerf-example-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let out = root.join("run");
    let mut args = Args {
        data: quarter_scene_two_test_views(&root.join("data")),
        steps: Some(4),
        out: out.clone(),
        seed: 1,
        rays: 128,
        samples: 16,
        eval_every: 2,
        eval_views: 1,
        pictures: 1,
        ..Args::default()
    };
    run(&args).unwrap();
    let m = metrics(&out);
    for key in ["psnr", "ssim", "train_seconds", "steps", "samples_per_ray"] {
        assert!(m[key].as_f64().is_some_and(f64::is_finite), "{key}: {m}");
    }
    assert_eq!(m["steps"], 4);
    assert!(m["stalled_until"].is_null(), "{m}");
    // The Blender layout states no bounds: the box is the silhouettes' visual hull (the
    // mesh lies in the unit ball), not the ±1.5 cube.
    let scene_box: Vec<f64> = serde_json::from_value(m["scene_box"].clone()).unwrap();
    let train = load(&args.data, &LoadConfig::default()).unwrap();
    let hull = train.visual_hull(0.05).unwrap().unwrap();
    assert_eq!(scene_box, hull);
    assert!(hull.iter().all(|v| v.abs() < 1.2), "{hull:?}");
    let curve = std::fs::read_to_string(out.join("curve.csv")).unwrap();
    assert_eq!(curve.lines().next(), Some("step,train_seconds,psnr"));
    assert_eq!(curve.lines().count(), 1 + 2 + 1); // header, steps 2 and 4, final
    for file in [
        "view_0.png",
        "depth_0.png",
        "opacity_0.png",
        "weights.safetensors",
    ] {
        assert!(out.join(file).is_file(), "{file}");
    }
    // Resuming from the saved weights, with the stratified sampler.
    args.resume = Some(out.join("weights.safetensors"));
    args.sampler = Some(Sampler::Stratified);
    args.steps = Some(2);
    run(&args).unwrap();
    // The proposal sampler from scratch (its networks are not in the saved weights),
    // skipping empty samples (the default) and keeping them all, under a window.
    args.resume = None;
    args.sampler = Some(Sampler::Proposal);
    run(&args).unwrap();
    args.alpha_threshold = 0.0;
    args.coarse_to_fine = Some((0.0, 2.0));
    args.view_dependence = false;
    run(&args).unwrap();
    let m = metrics(&out);
    assert_eq!(m["alpha_threshold"], 0.0);
    assert_eq!(m["coarse_to_fine"], serde_json::json!([0.0, 2.0]));
    assert_eq!(m["view_dependence"], false);
    assert_eq!(m["proposal_samples"], serde_json::json!([16, 8]));
    args.coarse_to_fine = None;
    args.view_dependence = true;
    // The hash-grid encoding, with box-filtered training rays and (its default) a
    // jittered march.
    args.sampler = Some(Sampler::Grid);
    args.encoding = Some(Encoding::Hash);
    args.train_supersample = 2;
    run(&args).unwrap();
    let m = metrics(&out);
    assert_eq!(m["encoding"], "hash");
    assert_eq!(m["sampler"], "grid");
    assert_eq!(m["train_supersample"], 2);
    assert_eq!(m["march_jitter"], true);
    assert_eq!(m["adam_eps"], 1e-15);
    // Cycles' pixel filter in training (jittered rays) and in a 3 × 3 evaluation.
    args.train_supersample = 1;
    args.jitter = true;
    args.pixel_filter = Filter::Cycles;
    args.eval_supersample = 3;
    run(&args).unwrap();
    let m = metrics(&out);
    assert_eq!(m["pixel_filter"], "cycles");
    assert!(m["psnr"].as_f64().is_some_and(f64::is_finite));
    // mip-NeRF: cone casting with the integrated encoding, jittered sub-pixel rays and
    // 2 × 2 evaluation (rays with a half-pixel radius).
    args.encoding = Some(Encoding::Ipe);
    args.eval_supersample = 2;
    run(&args).unwrap();
    let m = metrics(&out);
    assert_eq!(m["encoding"], "ipe");
    let scales = m["psnr_per_scale"].as_array().unwrap();
    assert_eq!(scales.len(), 1);
    assert_eq!(scales[0]["width"], 25);
    assert!(scales[0]["psnr"].as_f64().is_some_and(f64::is_finite));
    // An unbounded scene: contracted space with the proposal sampler (its default) and
    // with the cascaded grid, with each encoding; stratified samples are refused.
    args.scene = Scene::Unbounded;
    for (sampler, encoding) in [
        (None, Encoding::Ipe),
        (None, Encoding::Pe),
        (None, Encoding::Hash),
        (Some(Sampler::Grid), Encoding::Pe),
        (Some(Sampler::Grid), Encoding::Ipe),
    ] {
        (args.sampler, args.encoding) = (sampler, Some(encoding));
        run(&args).unwrap();
        let m = metrics(&out);
        let name = if sampler.is_some() {
            "grid"
        } else {
            "proposal"
        };
        assert_eq!(
            (m["scene"].as_str(), m["sampler"].as_str()),
            (Some("unbounded"), Some(name))
        );
        assert!(m["psnr"].as_f64().is_some_and(f64::is_finite));
    }
    args.sampler = Some(Sampler::Stratified);
    let e = run(&args).unwrap_err().to_string();
    assert!(e.contains("--scene unbounded"), "{e}");
    let _ = std::fs::remove_dir_all(&root);
}

/// The gradient scaling of unbounded scenes leaves values alone and multiplies each
/// sample's gradient by its scale, broadcast over the colour channels.
#[test]
fn scale_gradient_scales_only_the_gradient() {
    use candle_core::Var;
    let dev = Device::Cpu;
    let x = Var::from_tensor(&Tensor::new(&[[1.0f64, 2.0, 3.0], [4.0, 5.0, 6.0]], &dev).unwrap())
        .unwrap();
    let s = Tensor::new(&[0.25f64, 1.0], &dev).unwrap();
    let y = scale_gradient(x.as_tensor(), &s.unsqueeze(1).unwrap()).unwrap();
    assert_eq!(y.to_vec2::<f64>().unwrap(), x.to_vec2::<f64>().unwrap());
    let grads = (y.sqr().unwrap().sum_all().unwrap() * 0.5)
        .unwrap()
        .backward()
        .unwrap();
    let g = grads.get(&x).unwrap().to_vec2::<f64>().unwrap();
    assert_eq!(g, vec![vec![0.25, 0.5, 0.75], vec![4.0, 5.0, 6.0]]);
}

/// The depth pictures' range: quantiles of the finite values only, none when they agree.
#[test]
fn percentiles_skip_non_finite_values() {
    let dev = Device::Cpu;
    let mut v: Vec<f64> = (1..=100).map(f64::from).collect();
    v.extend([f64::NAN, f64::INFINITY]);
    let x = Tensor::new(v.as_slice(), &dev).unwrap();
    assert_eq!(percentiles(&x, 0.02, 0.98).unwrap(), Some((3.0, 98.0)));
    let flat = Tensor::new(&[2.0f32, 2.0, f32::NAN], &dev).unwrap();
    assert_eq!(percentiles(&flat, 0.02, 0.98).unwrap(), None);
    let empty = Tensor::new(&[f32::NAN], &dev).unwrap();
    assert_eq!(percentiles(&empty, 0.02, 0.98).unwrap(), None);
}

/// Regression: an object filling a third of its box kept the coarse march all run.
#[test]
fn coarse_march_ends_with_the_warm_up_even_in_a_full_grid() {
    let diag = 2.56;
    assert_eq!(march_step(diag, 0.9, 0.0), diag / 64.0);
    assert_eq!(march_step(diag, 0.2, 0.0), diag / 256.0);
    assert_eq!(march_step(diag, 0.3, 0.5), diag / 256.0);
}

/// The command line keeps the flags, spellings and defaults of earlier versions.
#[test]
fn flags_parse_as_documented() {
    let a = Args::default();
    assert_eq!(a.out, PathBuf::from("target/nerf"));
    let counts = (a.rays, a.samples, a.eval_every, a.eval_views, a.pictures);
    assert_eq!(counts, (1024, 64, 250, 4, 8));
    assert_eq!((a.sampler(), a.encoding()), (Sampler::Grid, Encoding::Pe));
    assert_eq!(a.learning_rate(), 5e-3);
    assert_eq!(a.scene, Scene::Object);
    // An unbounded scene's defaults: the hash grid, the proposal sampler, lr 1e-2; the
    // frequency encoding there at 1e-3 (its density collapsed at 5e-3).
    let u = Args::parse_from("nerf --scene unbounded".split_whitespace());
    let defaults = (u.sampler(), u.encoding(), u.learning_rate());
    assert_eq!(defaults, (Sampler::Proposal, Encoding::Hash, 1e-2));
    // The hash grid marches jittered lattices unless told otherwise.
    let h = Args::parse_from("nerf --encoding hash".split_whitespace());
    assert!(h.march_jitter());
    let h = Args::parse_from("nerf --encoding hash --march-jitter off".split_whitespace());
    assert!(!h.march_jitter());
    assert!(
        !u.march_jitter(),
        "the unbounded scene's cascaded grid keeps its fixed march"
    );
    // Adam's ε: 1e-15 for the hash grid in an object scene (at 1e-8 its table stalled
    // over a tight box), 1e-8 elsewhere; the flag overrides it, within (0, 1e-4].
    assert_eq!(
        (h.adam_eps(), u.adam_eps(), a.adam_eps()),
        (1e-15, 1e-8, 1e-8)
    );
    let e = Args::parse_from("nerf --encoding hash --adam-eps 1e-8".split_whitespace());
    assert_eq!(e.adam_eps(), 1e-8);
    for bad in ["0", "-1e-8", "1e-3", "nan"] {
        assert!(
            Args::try_parse_from(["nerf", "--adam-eps", bad]).is_err(),
            "{bad}"
        );
    }
    let u = Args::parse_from("nerf --scene unbounded --encoding pe".split_whitespace());
    assert_eq!(u.learning_rate(), 1e-3);
    let c = Args::parse_from("nerf --scene unbounded --encoding ipe".split_whitespace());
    assert_eq!((c.scene, c.encoding()), (Scene::Unbounded, Encoding::Ipe));
    assert_eq!(
        (a.regnerf_weight, a.proposal_samples),
        ([400.0, 0.1], [16, 8])
    );
    assert!(a.view_dependence && !a.jitter && !a.march_jitter() && !a.regnerf);
    assert!(a.gradient_scaling);
    assert_eq!(a.budget().unwrap(), Budget::Minutes(10.0));
    let flags = "nerf --sampler proposal --frames 0,17,34 --jitter on --coarse-to-fine 0,3.5 \
        --pixel-filter cycles --background black --proposal-samples 32,16 --steps 7";
    let b = Args::parse_from(flags.split_whitespace());
    assert_eq!(
        (b.frames.clone(), b.proposal_samples),
        (Some(vec![0, 17, 34]), [32, 16])
    );
    assert_eq!(
        (b.coarse_to_fine, b.budget().unwrap()),
        (Some((0.0, 3.5)), Budget::Steps(7))
    );
    for bad in [
        "--steps 1 --minutes 2",
        "--jitter yes",
        "--coarse-to-fine 0.5,0.2",
        "--lr 10",
        "--lr 0",
    ] {
        let flags = std::iter::once("nerf").chain(bad.split_whitespace());
        assert!(Args::try_parse_from(flags).is_err(), "{bad}");
    }
    assert!(Args {
        rays: 0,
        ..Args::default()
    }
    .budget()
    .is_err());
}

/// Regression (transparent dataset): a training split whose every pixel is
/// transparent used to train to an empty scene and report a high PSNR; it is refused
/// before training, naming the cause.
#[test]
fn a_transparent_dataset_is_refused_before_training() {
    use neural_fields::data::{write_blender, Dataset, Image, View};
    let out = std::env::temp_dir().join(format!("nerf-transparent-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let data = out.join("data");
    for split in [Split::Train, Split::Test] {
        let config = LoadConfig {
            split,
            downscale: 4,
            ..LoadConfig::default()
        };
        let source = load(Path::new("examples/data/wuson"), &config).unwrap();
        let views = source
            .views()
            .iter()
            .map(|v| {
                let (w, h, _) = v.image().size();
                let clear = Image::new(w, h, 4, vec![0; w * h * 4]).unwrap();
                View::new(*v.camera(), clear, None, v.name().into()).unwrap()
            })
            .collect();
        let clear = Dataset::new(views, source.background(), source.bounds()).unwrap();
        assert_eq!(clear.coverage(), Some(0.0));
        write_blender(&data, split, &clear).unwrap();
    }
    let args = Args {
        data,
        steps: Some(2),
        out: out.join("run"),
        downscale: 1,
        rays: 64,
        samples: 8,
        ..Args::default()
    };
    let e = run(&args).unwrap_err().to_string();
    assert!(e.contains("transparent"), "{e}");
    let _ = std::fs::remove_dir_all(&out);
}

/// Regression (a hash run stalled for 15 000 steps unreported): a run whose held-out
/// PSNR is still within `STALL_DB` of an empty scene's after `STALL_STEPS` steps (here a
/// learning rate too small to move the weights) says so in metrics.json's `stalled_until`,
/// and finishes.
#[test]
fn a_run_that_learns_nothing_reports_its_stall() {
    let out = std::env::temp_dir().join(format!("nerf-stall-{}", std::process::id()));
    let every = STALL_STEPS / 2;
    let args = Args {
        steps: Some(STALL_STEPS + every),
        out: out.clone(),
        downscale: 4,
        rays: 16,
        samples: 8,
        sampler: Some(Sampler::Stratified),
        eval_every: every,
        eval_views: 1,
        pictures: 0,
        lr: Some(1e-12),
        ..Args::default()
    };
    run(&args).unwrap();
    let m = metrics(&out);
    assert!(m["empty_psnr"].as_f64().is_some_and(f64::is_finite), "{m}");
    assert_eq!(m["stalled_until"], STALL_STEPS + every, "{m}");
    let _ = std::fs::remove_dir_all(&out);
}

/// Regression (collapsed run): a run whose every training ray stays without opacity
/// (here a scene box far smaller than the object, so that nothing is inside it) stops
/// after `DEAD_STEPS` steps with an error naming the steps and the likely causes,
/// instead of finishing with an empty scene.
#[test]
fn a_run_without_opacity_stops_naming_the_cause() {
    let out = std::env::temp_dir().join(format!("nerf-dead-{}", std::process::id()));
    let args = Args {
        steps: Some(DEAD_STEPS + 20),
        out: out.clone(),
        downscale: 4,
        rays: 64,
        samples: 8,
        sampler: Some(Sampler::Stratified),
        aabb: Some(1e-4),
        eval_every: 1000,
        // At the default 5e-3 the density inside the tiny box grows fast enough to make
        // the rays opaque within the window; this test is about the detection.
        lr: Some(1e-3),
        ..Args::default()
    };
    let e = run(&args).unwrap_err().to_string();
    assert!(e.contains("collapsed") && e.contains("--aabb"), "{e}");
    assert!(e.contains(&format!("to {}", DEAD_STEPS - 1)), "{e}");
    let _ = std::fs::remove_dir_all(&out);
}
