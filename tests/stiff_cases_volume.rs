//! Stiff cases of `volume`: compositing, samplers, intervals, the occupancy grid,
//! regularisers and the proposal sampler at extreme densities and steps; the NeRF model.

#![cfg(feature = "volume")]

mod common;

use candle_core::{DType, Device, Tensor, Var};

use common::stiff::{var, Expect, Suite, DTYPES};

use neural_fields::camera::{Camera, Convention, Intrinsics, Rays};
use neural_fields::glam::DVec3;
use neural_fields::nn::build_seeded;
use neural_fields::rng::SplitMix64;

#[test]
fn volume_rendering_stays_finite() {
    let mut s = Suite::default();
    sweep_volume(&mut s);
    sweep_cone(&mut s);
    s.finish("volume rendering", VOLUME);
}

#[test]
fn nerf_and_proposal_sampler_stay_finite() {
    let mut s = Suite::default();
    sweep_nerf(&mut s);
    s.finish("nerf and proposal", NERF);
}

#[test]
fn every_public_volume_function_is_swept_or_exempt() {
    common::stiff::check_coverage(
        "stiff_cases_volume",
        &[VOLUME, NERF, CONTRACTION],
        EXEMPT,
        &[],
        &[],
    );
}

/// Items swept by `sweep_volume`.
const VOLUME: &[&str] = &[
    "volume::Composite::normalized_depth",
    "volume::Intervals::deltas",
    "volume::Intervals::directions",
    "volume::Intervals::from_samples",
    "volume::Intervals::midpoints",
    "volume::Intervals::new",
    "volume::Intervals::positions",
    "volume::Intervals::retain",
    "volume::OccupancyGrid::new",
    "volume::OccupancyGrid::sample",
    "volume::OccupancyGrid::update",
    "volume::Packed::from_counts",
    "volume::accumulate",
    "volume::anneal_near_far",
    "volume::composite",
    "volume::conical_frustums",
    "volume::depth_smoothness",
    "volume::distortion_loss",
    "volume::log_linear_schedule",
    "volume::merge_sorted",
    "volume::render_image",
    "volume::render_weights",
    "volume::sample_pdf",
    "volume::stratified",
    "volume::visible_mask",
];

/// Items swept by `sweep_nerf`, `sweep_proposal`.
const NERF: &[&str] = &[
    "volume::Nerf::color_loss",
    "volume::Nerf::density",
    "volume::Nerf::radiance",
    "volume::Nerf::sample_inputs",
    "volume::Spacing::normalize",
    "volume::nerf",
    "volume::Intervals::retain",
    "volume::interlevel_loss",
    "volume::proposal_sample",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    ("volume::ProposalConfig::default", "constant"),
    ("volume::Nerf::forward", "swept through Nerf::density"),
    ("volume::Nerf::out_dim", "constant"),
    ("volume::NerfConfig::default", "constant"),
    (
        "volume::FusedComposite::",
        "CustomOp internals, swept via composite",
    ),
    (
        "nn::FusedNerfLoss::",
        "CustomOp internals, swept via Nerf::color_loss",
    ),
    ("volume::GridConfig::default", "constant"),
    ("volume::GridMarchConfig::default", "constant"),
    ("volume::ImageConfig::default", "constant"),
    (
        "volume::OccupancyGrid::is_occupied",
        "lookup, swept through sample",
    ),
    ("volume::OccupancyGrid::occupied", "getter"),
];

/// Cone casting: far-away thin intervals (t ≈ 1e6, where t₁ − t₀ cancels), intervals at
/// and near t = 0, tiny to huge radii, tiny and huge directions; both covariances, both
/// layouts.
fn sweep_cone(s: &mut Suite) {
    use neural_fields::volume::{conical_frustums, Covariance, Intervals, Layout, Packed};
    let d = Device::Cpu;
    for dtype in DTYPES {
        let (tiny, huge) = if dtype == DType::F32 {
            (1e-30, 1e10)
        } else {
            (1e-300, 1e100)
        };
        // The smallest step at 1e6 (one ulp) and a few more.
        let ulp = if dtype == DType::F32 { 0.0625 } else { 1.2e-10 };
        let rows: [(f64, f64, f64, [f64; 3]); 9] = [
            (1e6, 1e6 + ulp, 1e-3, [0.0, 0.0, 1.0]),
            (1e6, 1e6 + ulp, tiny, [0.3, -0.2, 1.0]),
            (1e6, 1e6 + 4.0 * ulp, 0.0, [1e-3, 0.0, 1.0]),
            (1e6, 1e6, 1e-6, [0.0, 1.0, 1.0]),
            (0.0, 0.0, 1.0, [0.0, 0.0, 1.0]),
            (0.0, tiny, 1.0, [1.0, 1.0, 1.0]),
            (tiny, 2.0 * tiny, huge, [0.0, 0.0, 1.0]),
            (0.0, 1e6, 1e-3, [tiny, tiny, tiny]),
            (1.0, 2.0, 1e-3, [1e3, -1e3, 1e3]),
        ];
        let r = rows.len();
        let starts = var(&rows.map(|x| x.0), &[r, 1], dtype);
        let ends = var(&rows.map(|x| x.1), &[r, 1], dtype);
        let radii = var(&rows.map(|x| x.2), &[r], dtype);
        let dirs = var(&rows.map(|x| x.3).concat(), &[r, 3], dtype);
        let origins = var(&[1e6, -1.0, 0.5].repeat(r), &[r, 3], dtype);
        let rays = Rays::new(origins.as_tensor().clone(), dirs.as_tensor().clone()).unwrap();
        let wrt = [&starts, &ends, &radii, &dirs, &origins];
        for covariance in [Covariance::Diagonal, Covariance::Full] {
            for packed in [false, true] {
                s.case(
                    "volume::conical_frustums",
                    format!("{dtype:?}, {covariance:?}, packed = {packed}, t ≈ 1e6 thin, t ≈ 0"),
                    Expect::Finite,
                    &wrt,
                    || {
                        let layout = if packed {
                            Layout::Packed(Packed::from_counts(&vec![1; r], &d)?)
                        } else {
                            Layout::Batched
                        };
                        let (st, en) = if packed {
                            (starts.flatten_all()?, ends.flatten_all()?)
                        } else {
                            (starts.as_tensor().clone(), ends.as_tensor().clone())
                        };
                        let iv = Intervals::new(st, en, layout)?;
                        let rays = rays.clone().with_radii(radii.as_tensor().clone())?;
                        let g = conical_frustums(&rays, &iv, covariance)?;
                        Ok(vec![g.means, g.covariances])
                    },
                );
            }
        }
    }
}

fn sweep_volume(s: &mut Suite) {
    use neural_fields::volume::{
        accumulate, anneal_near_far, composite, depth_smoothness, distortion_loss,
        log_linear_schedule, merge_sorted, render_image, render_weights, sample_pdf, stratified,
        visible_mask, Composite, CompositeConfig, GridConfig, GridMarchConfig, ImageConfig,
        Intervals, Jitter, Layout, OccupancyGrid, Packed,
    };
    let d = Device::Cpu;
    let (r, n) = (7usize, 5usize);
    let occupied_fraction = |g: &OccupancyGrid| {
        g.occupied().iter().filter(|&&o| o).count() as f64 / g.occupied().len() as f64
    };
    for dtype in DTYPES {
        let huge = if dtype == DType::F32 { 1e30 } else { 1e300 };
        // Whole images: per-pixel means of a renderer's tiny to huge outputs.
        let cam = Camera::look_at(
            Intrinsics::from_fov_y(4, 3, 0.8).unwrap(),
            DVec3::new(0.0, 0.0, 3.0),
            DVec3::ZERO,
            DVec3::Y,
            Convention::OpenGl,
        )
        .unwrap();
        for x in [0.0, 1e-30, 1.0, huge] {
            s.case(
                "volume::render_image",
                format!("{dtype:?}, outputs {x:e}"),
                Expect::Finite,
                &[],
                || {
                    let config = ImageConfig {
                        supersample: 2,
                        ..ImageConfig::default()
                    };
                    let [image] = render_image(&cam, &config, &d, dtype, |rays| {
                        Ok([(rays.directions().ones_like()? * x)?])
                    })?;
                    Ok(vec![image])
                },
            );
        }
        // Rows: empty, tiny, huge, one opaque slab, f32 transmittance underflow along a long
        // ray (σδ summing to 5e5), mixed extremes, huge steps.
        let sig = [
            [0.0; 5],
            [1e-30; 5],
            [huge; 5],
            [0.0, 0.0, 1e10, 0.0, 0.0],
            [100.0; 5],
            [1e-10, 1e10, 0.0, 1e-30, huge],
            [1.0; 5],
        ]
        .concat();
        let del = [
            [0.1; 5],
            [1e-30; 5],
            [1e-30; 5],
            [0.2; 5],
            [1e3; 5],
            [1e-30, 1e10, 0.0, 1.0, 1e-10],
            [1e10; 5],
        ]
        .concat();
        let sigmas = var(&sig, &[r, n], dtype);
        // The intervals with lengths δ, each ray starting at t = 0 (the depths t are their
        // midpoints, up to 5e10); learnable, so gradients reach starts and ends.
        let (st_h, en_h) = common::intervals::starts_ends(&del, &[n; 7]);
        let starts = var(&st_h, &[r, n], dtype);
        let ends = var(&en_h, &[r, n], dtype);
        let iv = Intervals::new(
            starts.as_tensor().clone(),
            ends.as_tensor().clone(),
            Layout::Batched,
        )
        .unwrap();
        let mut rng = SplitMix64::new(5);
        let colors =
            Var::from_tensor(&rng.uniform_tensor(&[r, n, 3], 0.0, 1.0, dtype, &d).unwrap())
                .unwrap();
        // Directions of norm 2 (δ doubled) for the cases with rays.
        let dirs = var(&[0.0, 0.0, 2.0].repeat(r), &[r, 3], dtype);
        let rays = Rays::new(
            Tensor::zeros((r, 3), dtype, &d).unwrap(),
            dirs.as_tensor().clone(),
        )
        .unwrap();
        let wrt = [&sigmas, &starts, &ends, &colors];
        let wrt_rays = [&sigmas, &starts, &ends, &colors, &dirs];
        for opaque_last in [false, true] {
            let label = format!("{dtype:?}, σ 0…{huge:e}, δ 0…1e10, opaque_last = {opaque_last}");
            let bg = Tensor::ones(3, dtype, &d).unwrap();
            let cfg = CompositeConfig {
                opaque_last,
                background: Some(bg),
                force_reference: false,
            };
            let reference = CompositeConfig {
                force_reference: true,
                ..cfg.clone()
            };
            let no_bg = CompositeConfig {
                opaque_last,
                ..CompositeConfig::default()
            };
            let (st, ct) = (sigmas.as_tensor(), colors.as_tensor());
            let out = |c: Composite| -> neural_fields::Result<Vec<Tensor>> {
                let nd = c.normalized_depth(1e-10)?;
                Ok(vec![c.color, c.opacity, c.depth, nd])
            };
            // On the CPU `composite` runs the fused kernel (0.1's `composite_fused`).
            s.case("volume::composite", &label, Expect::Finite, &wrt, || {
                out(composite(st, ct, &iv, None, &cfg)?)
            });
            s.case(
                "volume::composite",
                format!("{label}, reference path"),
                Expect::Finite,
                &wrt,
                || out(composite(st, ct, &iv, None, &reference)?),
            );
            s.case(
                "volume::composite",
                format!("{label}, rays with |d| = 2"),
                Expect::Finite,
                &wrt_rays,
                || out(composite(st, ct, &iv, Some(&rays), &cfg)?),
            );
            s.case(
                "volume::composite",
                format!("{label}, rays with |d| = 2, reference path"),
                Expect::Finite,
                &wrt_rays,
                || out(composite(st, ct, &iv, Some(&rays), &reference)?),
            );
            s.case(
                "volume::Composite::normalized_depth",
                &label,
                Expect::Finite,
                &wrt,
                || out(composite(st, ct, &iv, None, &reference)?),
            );
            s.case(
                "volume::render_weights",
                &label,
                Expect::Finite,
                &[&sigmas, &starts, &ends],
                || {
                    let w = render_weights(st, &iv, None, &cfg)?;
                    Ok(vec![w.weights, w.transmittance, w.alphas])
                },
            );
            s.case(
                "volume::render_weights",
                format!("{label}, rays with |d| = 2"),
                Expect::Finite,
                &[&sigmas, &starts, &ends, &dirs],
                || {
                    let w = render_weights(st, &iv, Some(&rays), &cfg)?;
                    Ok(vec![w.weights, w.transmittance, w.alphas])
                },
            );
            s.case(
                "volume::accumulate",
                &label,
                Expect::Finite,
                &[&sigmas, &colors],
                || {
                    Ok(vec![accumulate(
                        &render_weights(st, &iv, None, &cfg)?.weights,
                        ct,
                        &Layout::Batched,
                    )?])
                },
            );
            // 0.1's `accumulate_fused`: Σwᵢvᵢ and Σwᵢ by the fused kernel, no background.
            s.case(
                "volume::composite",
                format!("{label}, no background (Σwv, Σw)"),
                Expect::Finite,
                &wrt,
                || {
                    let c = composite(st, ct, &iv, None, &no_bg)?;
                    Ok(vec![c.color, c.opacity])
                },
            );
            // Packed: the same samples as rays of 5, 0, 3, 5, 0, 12, 10 samples, each ray
            // starting at t = 0.
            let counts = [5usize, 0, 3, 5, 0, 12, 10];
            let packed = Packed::from_counts(&counts, &d).unwrap();
            let (pst_h, pen_h) = common::intervals::starts_ends(&del, &counts);
            let pstarts = var(&pst_h, &[r * n], dtype);
            let pends = var(&pen_h, &[r * n], dtype);
            let piv = Intervals::new(
                pstarts.as_tensor().clone(),
                pends.as_tensor().clone(),
                Layout::Packed(packed.clone()),
            )
            .unwrap();
            let (ps, pc) = (st.flatten_all().unwrap(), ct.reshape((r * n, 3)).unwrap());
            let pwrt = [&sigmas, &pstarts, &pends, &colors];
            let plabel = format!("{label}, packed with empty rays");
            s.case(
                "volume::Packed::from_counts",
                &plabel,
                Expect::Finite,
                &pwrt,
                || {
                    let p = Packed::from_counts(&counts, &d)?;
                    let iv = Intervals::new(
                        pstarts.as_tensor().clone(),
                        pends.as_tensor().clone(),
                        Layout::Packed(p),
                    )?;
                    out(composite(&ps, &pc, &iv, None, &cfg)?)
                },
            );
            s.case(
                "volume::Intervals::new",
                &plabel,
                Expect::Finite,
                &pwrt,
                || out(composite(&ps, &pc, &piv, None, &cfg)?),
            );
            s.case(
                "volume::composite",
                format!("{plabel}, reference path"),
                Expect::Finite,
                &pwrt,
                || out(composite(&ps, &pc, &piv, None, &reference)?),
            );
            s.case(
                "volume::render_weights",
                &plabel,
                Expect::Finite,
                &[&sigmas, &pstarts, &pends],
                || {
                    let w = render_weights(&ps, &piv, None, &cfg)?;
                    Ok(vec![w.weights, w.transmittance])
                },
            );
            s.case(
                "volume::accumulate",
                &plabel,
                Expect::Finite,
                &[&sigmas, &colors],
                || {
                    Ok(vec![accumulate(
                        &render_weights(&ps, &piv, None, &cfg)?.weights,
                        &pc,
                        &piv.layout,
                    )?])
                },
            );
        }
        let label = format!("{dtype:?}");
        for eps in [1e-30, 1e-4, 1.0] {
            s.case(
                "volume::visible_mask",
                format!("{label}, eps = {eps}"),
                Expect::Finite,
                &[],
                || Ok(vec![visible_mask(sigmas.as_tensor(), &iv, None, eps)?]),
            );
        }
        s.case(
            "volume::Intervals::retain",
            format!("{label}, visible samples"),
            Expect::Finite,
            &[],
            || {
                let mask = visible_mask(sigmas.as_tensor(), &iv, None, 1e-4)?;
                let (kept, idx) = iv.retain(&mask)?;
                Ok(vec![kept.starts, kept.ends, idx.to_dtype(DType::F64)?])
            },
        );
        // Samplers over tiny, huge and far-away ranges.
        let big = if dtype == DType::F32 { 1e6 } else { 1e100 };
        let near = var(&[0.0, 1e-30, big, 0.0], &[4], dtype);
        let far = var(&[1e-20, 2e-30, big * 1.5, 1e10], &[4], dtype);
        let dirs = var(
            &[
                1e-20, 0.0, 0.0, 0.0, 1.0, 0.0, 1e10, 1e10, 1e10, 0.0, 0.0, 1.0,
            ],
            &[4, 3],
            dtype,
        );
        let sampler_rays = Rays::new(
            Tensor::zeros((4, 3), dtype, &d).unwrap(),
            dirs.as_tensor().clone(),
        )
        .unwrap();
        for jitter in [Jitter::None, Jitter::PerSample, Jitter::SingleJitter] {
            let jl = format!("{label}, ranges 1e-30…{big:e}, {jitter:?}");
            s.case(
                "volume::stratified",
                &jl,
                Expect::Finite,
                &[&near, &far],
                || {
                    let iv = stratified(near.as_tensor(), far.as_tensor(), 16, jitter, 3)?;
                    Ok(vec![iv.starts.clone(), iv.ends.clone()])
                },
            );
        }
        let iv = stratified(near.as_tensor(), far.as_tensor(), 16, Jitter::PerSample, 3).unwrap();
        let il = format!("{label}, ranges 1e-30…{big:e}");
        s.case(
            "volume::Intervals::midpoints",
            &il,
            Expect::Finite,
            &[&near, &far],
            || Ok(vec![iv.midpoints()?]),
        );
        s.case(
            "volume::Intervals::deltas",
            &il,
            Expect::Finite,
            &[&near, &far, &dirs],
            || Ok(vec![iv.deltas(Some(&sampler_rays))?, iv.deltas(None)?]),
        );
        s.case(
            "volume::Intervals::positions",
            format!("{il}, |d| 1e-20…1e10"),
            Expect::Finite,
            &[&near, &far, &dirs],
            || Ok(vec![iv.positions(&sampler_rays)?]),
        );
        s.case(
            "volume::Intervals::directions",
            format!("{il}, |d| 1e-20…1e10"),
            Expect::Finite,
            &[&dirs],
            || Ok(vec![iv.directions(&sampler_rays)?]),
        );
        s.case("volume::Intervals::new", &il, Expect::Finite, &[], || {
            Ok(vec![Intervals::new(
                iv.starts.clone(),
                iv.ends.clone(),
                Layout::Batched,
            )?
            .midpoints()?])
        });
        let w_rows = [[0.0; 16], [1e-30; 16], [huge; 16], {
            let mut one_hot = [0.0; 16];
            one_hot[7] = 1e30f64.min(huge);
            one_hot
        }]
        .concat();
        let weights = var(&w_rows, &[4, 16], dtype);
        for deterministic in [true, false] {
            let sl = format!("{il}, weights 0…{huge:e}, deterministic = {deterministic}");
            s.case("volume::sample_pdf", &sl, Expect::Finite, &[], || {
                Ok(vec![sample_pdf(
                    &iv,
                    weights.as_tensor(),
                    32,
                    deterministic,
                    9,
                    1e-5,
                )?])
            });
        }
        let fine = sample_pdf(&iv, weights.as_tensor(), 32, false, 9, 1e-5).unwrap();
        s.case(
            "volume::merge_sorted",
            &il,
            Expect::Finite,
            &[&near, &far],
            || Ok(vec![merge_sorted(&iv.midpoints()?, &fine)?]),
        );
        s.case(
            "volume::Intervals::from_samples",
            &il,
            Expect::Finite,
            &[&near, &far],
            || {
                let iv2 = Intervals::from_samples(
                    &merge_sorted(&iv.midpoints()?, &fine)?,
                    near.as_tensor(),
                    far.as_tensor(),
                )?;
                Ok(vec![iv2.starts, iv2.ends])
            },
        );
        for step in [0usize, 128, 10_000] {
            s.case(
                "volume::anneal_near_far",
                format!("{il}, step {step}"),
                Expect::Finite,
                &[&near, &far],
                || {
                    let (a, b) =
                        anneal_near_far(near.as_tensor(), far.as_tensor(), step, 256, 0.5, 0.5)?;
                    Ok(vec![a, b])
                },
            );
        }
        // Regularisers on normalised intervals with extreme weights.
        let dl_w = var(
            &[
                [0.0; 8],
                [1e-30; 8],
                [1.0; 8],
                [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
            ]
            .concat(),
            &[4, 8],
            dtype,
        );
        let edges: Vec<f64> = (0..=8).map(|i| f64::from(i) / 8.0).collect();
        let st = Tensor::from_slice(&edges[..8], (1, 8), &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap()
            .repeat((4, 1))
            .unwrap();
        let en = Tensor::from_slice(&edges[1..], (1, 8), &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap()
            .repeat((4, 1))
            .unwrap();
        let dl_iv = Intervals::new(st, en, Layout::Batched).unwrap();
        s.case(
            "volume::distortion_loss",
            format!("{label}, weights 0…1"),
            Expect::Finite,
            &[&dl_w],
            || Ok(vec![distortion_loss(dl_w.as_tensor(), &dl_iv)?]),
        );
        let dbig = if dtype == DType::F32 { 1e15 } else { 1e150 };
        let depth = var(
            &[0.0, 1e-30, dbig, -dbig, 1.0, 2.0, 3.0, 4.0, 5.0],
            &[1, 3, 3],
            dtype,
        );
        s.case(
            "volume::depth_smoothness",
            format!("{label}, depths ±{dbig:e}"),
            Expect::Finite,
            &[&depth],
            || Ok(vec![depth_smoothness(depth.as_tensor(), None)?]),
        );
        // (400, 0.1, 512) is 0.1's `depth_smoothness_weight`.
        for (a, b) in [(400.0, 0.1), (1e-30, 1e30)] {
            s.case(
                "volume::log_linear_schedule",
                format!("{a} → {b}"),
                Expect::Finite,
                &[],
                || {
                    Ok(vec![Tensor::new(
                        &[
                            log_linear_schedule(0, a, b, 512),
                            log_linear_schedule(10_000, a, b, 512),
                            log_linear_schedule(7, 400.0, 0.1, 512),
                        ],
                        &d,
                    )?])
                },
            );
        }
        s.case(
            "volume::log_linear_schedule",
            format!("{label}, depth smoothness weight at step 100 000"),
            Expect::Finite,
            &[],
            || {
                Ok(vec![Tensor::new(
                    log_linear_schedule(100_000, 400.0, 0.1, 512),
                    &d,
                )?])
            },
        );
        // Occupancy grid over tiny and huge boxes with extreme densities.
        for (half, sigma) in [(1e-3, 1e30), (1.0, 1e-30), (1e4, 10.0)] {
            let gl = format!("{label}, box ±{half}, σ = {sigma:e}");
            let mut grid = OccupancyGrid::new(GridConfig {
                aabb: [-half, -half, -half, half, half, half],
                resolution: 16,
                levels: 2,
                ..GridConfig::default()
            })
            .unwrap();
            s.case(
                "volume::OccupancyGrid::new",
                &gl,
                Expect::Finite,
                &[],
                || Ok(vec![Tensor::new(occupied_fraction(&grid), &d)?]),
            );
            s.case(
                "volume::OccupancyGrid::update",
                &gl,
                Expect::Finite,
                &[],
                || {
                    grid.update(0, 1, &d, dtype, |p: &Tensor| {
                        let r2 = p.sqr()?.sum(1)?;
                        let inside = r2.lt(half * half * 0.25)?;
                        Ok(inside
                            .where_cond(&r2.ones_like()?.affine(sigma, 0.0)?, &r2.zeros_like()?)?)
                    })?;
                    Ok(vec![Tensor::new(occupied_fraction(&grid), &d)?])
                },
            );
            let o = Tensor::from_slice(&[-3.0 * half, 0.0, 0.0, 0.0, 0.0, 0.0], (2, 3), &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let w = Tensor::from_slice(&[1.0, 0.0, 0.0, 0.0, 1e-3, 1.0], (2, 3), &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let grid_rays = Rays::new(o, w).unwrap();
            for cone in [0.0, 1e-2] {
                let cl = format!("{gl}, cone {cone}");
                let march = GridMarchConfig {
                    far: 6.0 * half,
                    step_size: half / 64.0,
                    cone_angle: cone,
                    alpha_threshold: 1e-3,
                    ..GridMarchConfig::default()
                };
                s.case(
                    "volume::OccupancyGrid::sample",
                    format!("{cl}, density {sigma:e} everywhere"),
                    Expect::Finite,
                    &[],
                    || {
                        let mut density = |p: &Tensor| Ok((p.sum(1)?.ones_like()? * sigma)?);
                        let gs = grid.sample(&grid_rays, &march, Some(&mut density))?;
                        Ok(vec![gs.intervals.starts, gs.intervals.ends])
                    },
                );
                s.case(
                    "volume::OccupancyGrid::sample",
                    &cl,
                    Expect::Finite,
                    &[],
                    || {
                        let gs = grid.sample(&grid_rays, &march, None)?;
                        let iv = &gs.intervals;
                        Ok(vec![
                            iv.midpoints()?,
                            iv.deltas(Some(&grid_rays))?,
                            iv.positions(&grid_rays)?,
                        ])
                    },
                );
                s.case(
                    "volume::OccupancyGrid::sample",
                    format!("{cl}, jittered"),
                    Expect::Finite,
                    &[],
                    || {
                        let gs = grid.sample(
                            &grid_rays,
                            &GridMarchConfig {
                                jitter: Some(u64::MAX),
                                ..march
                            },
                            None,
                        )?;
                        let iv = &gs.intervals;
                        Ok(vec![
                            iv.deltas(Some(&grid_rays))?,
                            iv.positions(&grid_rays)?,
                        ])
                    },
                );
                let gs = grid.sample(&grid_rays, &march, None).unwrap();
                s.case(
                    "volume::Intervals::midpoints",
                    format!("{cl}, grid samples"),
                    Expect::Finite,
                    &[],
                    || Ok(vec![gs.intervals.midpoints()?]),
                );
                s.case(
                    "volume::Intervals::deltas",
                    format!("{cl}, grid samples"),
                    Expect::Finite,
                    &[],
                    || Ok(vec![gs.intervals.deltas(Some(&grid_rays))?]),
                );
                s.case(
                    "volume::Intervals::positions",
                    format!("{cl}, grid samples"),
                    Expect::Finite,
                    &[],
                    || Ok(vec![gs.intervals.positions(&grid_rays)?]),
                );
            }
        }
        s.case(
            "volume::OccupancyGrid::new",
            format!("{label}, empty box"),
            Expect::FiniteOrErr,
            &[],
            || {
                let g = OccupancyGrid::new(GridConfig {
                    aabb: [0.0; 6],
                    resolution: 8,
                    levels: 1,
                    ..GridConfig::default()
                })?;
                Ok(vec![Tensor::new(occupied_fraction(&g), &d)?])
            },
        );
    }
}

fn sweep_nerf(s: &mut Suite) {
    use neural_fields::volume::{nerf, DensityActivation, NerfConfig};
    let d = Device::Cpu;
    for dtype in DTYPES {
        let big = if dtype == DType::F32 { 1e8 } else { 1e100 };
        let pts = [
            0.0, 0.0, 0.0, 1e-30, 0.0, 0.0, big, -big, big, 1e4, 1.0, -1e4,
        ];
        // Directions: zero, tiny, huge, ordinary.
        let dirs = [
            0.0, 0.0, 0.0, 1e-30, 0.0, 0.0, big, big, -big, 0.3, -0.4, 0.5,
        ];
        for (density, tag) in [
            (DensityActivation::TruncExp { shift: -1.0 }, "trunc_exp"),
            (DensityActivation::Softplus { shift: -1.0 }, "softplus"),
        ] {
            let config = NerfConfig {
                density,
                width: 16,
                color_width: 8,
                ..NerfConfig::default()
            };
            let varmap = candle_nn::VarMap::new();
            let label = format!("{dtype:?}, {tag}, |x| up to {big:e}");
            s.case("volume::nerf", &label, Expect::Finite, &[], || {
                build_seeded(&varmap, dtype, &d, 5, |vb| nerf(&config, vb))?;
                Ok(vec![])
            });
            let net = build_seeded(&varmap, dtype, &d, 5, |vb| nerf(&config, vb)).unwrap();
            let vars = varmap.all_vars();
            let (x, v) = (var(&pts, &[4, 3], dtype), var(&dirs, &[4, 3], dtype));
            let mut wrt: Vec<&Var> = vars.iter().collect();
            wrt.push(&x);
            s.case(
                "volume::Nerf::density",
                &label,
                Expect::Finite,
                &wrt,
                || Ok(vec![net.density(x.as_tensor())?]),
            );
            wrt.push(&v);
            s.case(
                "volume::Nerf::radiance",
                &label,
                Expect::Finite,
                &wrt,
                || {
                    let (sigma, rgb) = net.radiance(x.as_tensor(), v.as_tensor())?;
                    Ok(vec![sigma, rgb])
                },
            );
            // The fused training loss: rays from the origin, from ±big and from 1e-30,
            // along tiny, huge and ordinary directions (rays have none of length 0), over [0, 1], [0, big] and
            // [1e-30, 2e-30]; targets in [0, 1].
            #[cfg(feature = "volume")]
            {
                use neural_fields::camera::Rays;
                use neural_fields::volume::{stratified, CompositeConfig, Jitter};
                let t = |v: &[f64], shape: &[usize]| {
                    Tensor::from_slice(v, shape, &d)
                        .unwrap()
                        .to_dtype(dtype)
                        .unwrap()
                };
                let mut ray_dirs = dirs;
                ray_dirs[2] = 1.0;
                let rays = Rays::new(t(&pts, &[4, 3]), t(&ray_dirs, &[4, 3])).unwrap();
                let near = t(&[0.0, 0.0, 1e-30, 0.0], &[4]);
                let far = t(&[1.0, big, 2e-30, 1.0], &[4]);
                let target = t(
                    &[0.0, 0.5, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.2, 0.3, 0.4],
                    &[4, 3],
                );
                let wrt: Vec<&Var> = vars.iter().collect();
                s.case(
                    "volume::Nerf::color_loss",
                    &label,
                    Expect::FiniteOrErr,
                    &wrt,
                    || {
                        let iv = stratified(&near, &far, 150, Jitter::PerSample, 0)?;
                        Ok(vec![
                            net.color_loss(&rays, &iv, &target, &CompositeConfig::default())?
                                .loss,
                        ])
                    },
                );
            }
        }
    }
    // mip-NeRF: the integrated encoding on conical frustums of radii 0, 1e-30, huge and
    // ordinary, from rays at the origin, at ±big and along tiny directions.
    #[cfg(feature = "volume")]
    for dtype in DTYPES {
        use neural_fields::camera::Rays;
        use neural_fields::encoding::PointEncoding;
        use neural_fields::volume::{stratified, CompositeConfig, Jitter, Spacing};
        let big = if dtype == DType::F32 { 1e8 } else { 1e100 };
        let config = NerfConfig {
            position_encoding: PointEncoding::Integrated {
                dim: 3,
                min_deg: 0,
                max_deg: 16,
            },
            width: 16,
            color_width: 8,
            ..NerfConfig::default()
        };
        let varmap = candle_nn::VarMap::new();
        let net = build_seeded(&varmap, dtype, &d, 5, |vb| nerf(&config, vb)).unwrap();
        let vars = varmap.all_vars();
        let o = var(
            &[
                0.0, 0.0, 0.0, big, -big, big, 1e-30, 0.0, 0.0, 0.3, 0.2, -4.0,
            ],
            &[4, 3],
            dtype,
        );
        let w = var(
            &[
                0.0, 0.0, 1.0, 1e-30, 0.0, 1.0, 0.0, big, 0.0, 0.1, -0.2, 1.0,
            ],
            &[4, 3],
            dtype,
        );
        let radii = var(&[0.0, 1e-30, big, 2e-3], &[4], dtype);
        let t = |v: &[f64]| {
            Tensor::from_slice(v, 4, &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap()
        };
        let (near, far) = (t(&[0.0, 0.0, 1e-30, 2.0]), t(&[1.0, big, 2e-30, 6.0]));
        let target = Tensor::full(0.5, (4, 3), &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let label = format!("{dtype:?}, integrated encoding, radii 0…{big:e}");
        let rays = || -> neural_fields::Result<Rays> {
            Rays::new(o.as_tensor().clone(), w.as_tensor().clone())?
                .with_radii(radii.as_tensor().clone())
        };
        s.case(
            "volume::Nerf::sample_inputs",
            &label,
            Expect::Finite,
            &[&o, &w, &radii],
            || {
                let iv = stratified(&near, &far, 32, Jitter::None, 0)?;
                Ok(vec![net.sample_inputs(&rays()?, &iv)?])
            },
        );
        // The spacings' normalised coordinate at t = 0, 1e-30, 1 (the disparity piece's
        // joint) and far out, for near 0 and far up to `big`.
        let ts = var(&[0.0, 1e-30, 1.0, big], &[1, 4], dtype);
        let (n0, f0) = (
            t(&[0.0; 4]).narrow(0, 0, 1).unwrap(),
            t(&[big; 4]).narrow(0, 0, 1).unwrap(),
        );
        for spacing in [Spacing::Linear, Spacing::LinearDisparity] {
            s.case(
                "volume::Spacing::normalize",
                format!("{label}, {spacing:?}"),
                Expect::Finite,
                &[&ts],
                || Ok(vec![spacing.normalize(ts.as_tensor(), &n0, &f0)?]),
            );
        }
        let mut wrt: Vec<&Var> = vars.iter().collect();
        wrt.push(&radii);
        s.case(
            "volume::Nerf::color_loss",
            &label,
            Expect::FiniteOrErr,
            &wrt,
            || {
                let iv = stratified(&near, &far, 32, Jitter::PerSample, 0)?;
                let out = net.color_loss(&rays()?, &iv, &target, &CompositeConfig::default())?;
                Ok(vec![out.loss])
            },
        );
    }
    #[cfg(feature = "volume")]
    for dtype in DTYPES {
        use neural_fields::volume::{stratified, Jitter};
        let top = if dtype == DType::F32 { 1e30 } else { 1e300 };
        let near = Tensor::new(&[0.0, -top, 1e-30], &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let far = Tensor::new(&[1.0, top, 2e-30], &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        s.case(
            "volume::Intervals::retain",
            format!("{dtype:?}, ±{top:e}"),
            Expect::FiniteOrErr,
            &[],
            || {
                let iv = stratified(&near, &far, 4, Jitter::None, 0)?;
                let mask = Tensor::new(&[[1u8, 0, 1, 0], [1, 1, 1, 1], [0, 0, 0, 1]], &d)?;
                let (kept, idx) = iv.retain(&mask)?;
                let (again, _) = kept.retain(&Tensor::ones(kept.starts.dims(), DType::U8, &d)?)?;
                Ok(vec![
                    kept.starts,
                    kept.ends,
                    again.midpoints()?,
                    idx.to_dtype(DType::F64)?,
                ])
            },
        );
        sweep_proposal(s, dtype, top);
    }
}

fn sweep_proposal(s: &mut Suite, dtype: DType, top: f64) {
    use neural_fields::volume::{interlevel_loss, proposal_sample, ProposalConfig};
    let d = Device::Cpu;
    // Proposal sampling over extreme ranges and densities, and its loss's gradient.
    for (range, density) in [(1e-6, 1e6), (1.0, 0.0), (1e4, 1e-6), (top / 1e10, 1.0)] {
        let label = format!("{dtype:?}, range {range:e}, density {density:e}");
        let rays = Rays::new(
            Tensor::new(&[[0.0, 0.0, -1.0], [1.0, 2.0, 3.0]], &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap(),
            Tensor::new(&[[0.0, 0.0, 1.0], [1e-3, 0.0, -2.0]], &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap(),
        )
        .unwrap();
        let near = Tensor::zeros(2, dtype, &d).unwrap();
        let far = Tensor::full(range, 2, &d).unwrap().to_dtype(dtype).unwrap();
        let mut field = |p: &Tensor| -> neural_fields::Result<Tensor> {
            Ok((p.narrow(1, 0, 1)?.squeeze(1)?.abs()?.affine(0.0, 1.0)? * density)?)
        };
        let config = ProposalConfig {
            samples: vec![16],
            final_samples: 8,
            padding: 0.01,
            ..ProposalConfig::default()
        };
        let out = proposal_sample(
            &rays,
            &near,
            &far,
            &mut [&mut field],
            &config,
            Some(3),
            None,
        );
        let first = out.as_ref().map(|o| o.clone()).map_err(|e| e.to_string());
        s.case(
            "volume::proposal_sample",
            &label,
            Expect::FiniteOrErr,
            &[],
            || {
                let out = first.map_err(|e| neural_fields::Error::InvalidArgument {
                    arg: "proposal",
                    expected: String::new(),
                    got: e,
                })?;
                Ok(vec![
                    out.intervals.starts,
                    out.intervals.ends,
                    out.levels[0].1.clone(),
                ])
            },
        );
        // With the field's density (the same density as the proposal): culled, packed
        // samples and the interlevel loss, finite or refused.
        let culling = ProposalConfig {
            alpha_threshold: 1e-2,
            ..config.clone()
        };
        s.case(
            "volume::proposal_sample",
            format!("{label}, culled by the field's density"),
            Expect::FiniteOrErr,
            &[],
            || {
                let mut proposal = |p: &Tensor| -> neural_fields::Result<Tensor> {
                    Ok((p.narrow(1, 0, 1)?.squeeze(1)?.abs()?.affine(0.0, 1.0)? * density)?)
                };
                let mut sigma = |p: &Tensor| -> neural_fields::Result<Tensor> {
                    Ok((p.narrow(1, 0, 1)?.squeeze(1)?.abs()?.affine(0.0, 1.0)? * density)?)
                };
                let mut proposals: [neural_fields::volume::DensityFn; 1] = [&mut proposal];
                let out = proposal_sample(
                    &rays,
                    &near,
                    &far,
                    &mut proposals,
                    &culling,
                    Some(3),
                    Some(&mut sigma),
                )?;
                let interlevel = out.interlevel.expect("a loss with the field's density");
                Ok(vec![out.intervals.starts, out.intervals.ends, interlevel])
            },
        );
        if let Ok(out) = out {
            let w_hat = Var::from_tensor(&out.levels[0].1).unwrap();
            let (r, n) = out.intervals.starts.dims2().unwrap();
            let w = Tensor::full(0.5, (r, n), &d)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            s.case(
                "volume::interlevel_loss",
                &label,
                Expect::Finite,
                &[&w_hat],
                || {
                    let level = (out.levels[0].0.clone(), w_hat.as_tensor().clone());
                    Ok(vec![interlevel_loss(&level, &out.intervals, &w)?])
                },
            );
        }
    }
}

#[test]
fn scene_contraction_stays_finite() {
    let mut s = Suite::default();
    sweep_contraction(&mut s);
    s.finish("scene contraction", CONTRACTION);
}

/// Items swept by `sweep_contraction`.
const CONTRACTION: &[&str] = &["volume::contract"];

fn sweep_contraction(s: &mut Suite) {
    for dtype in DTYPES {
        let (tiny, huge) = if dtype == DType::F32 {
            (1e-38, 1e30)
        } else {
            (1e-300, 1e300)
        };
        // The origin, the tiny, both sides of the unit sphere (1 ± 1e-12 rounds to 1 in
        // f32) and the huge, on an axis and on a diagonal.
        for r in [0.0, tiny, 1.0 - 1e-12, 1.0, 1.0 + 1e-12, 2.0, huge] {
            let c = r / 3f64.sqrt();
            let label = format!("{dtype:?}, |x| = {r:e}");
            let points = var(&[r, 0.0, 0.0, c, -c, c], &[2, 3], dtype);
            s.case(
                "volume::contract",
                &label,
                Expect::Finite,
                &[&points],
                || Ok(vec![contract_points(points.as_tensor())?]),
            );
            for sigma in [tiny, 1.0, huge] {
                let diag = var(&[sigma; 6], &[2, 3], dtype);
                let eye = [sigma, 0.0, 0.0, 0.0, sigma, 0.0, 0.0, 0.0, sigma];
                let full = var(&[eye, eye].concat(), &[2, 3, 3], dtype);
                for cov in [&diag, &full] {
                    s.case(
                        "volume::contract",
                        format!("{label}, Σ = {sigma:e}·I, {:?}", cov.dims()),
                        Expect::Finite,
                        &[&points, cov],
                        || {
                            let (m, v) = contract_both(points.as_tensor(), cov.as_tensor())?;
                            Ok(vec![m, v])
                        },
                    );
                }
            }
        }
        // ±∞ and NaN are refused (naming `points` / `means`, tests/volume_contraction.rs).
        for bad in [f64::INFINITY, f64::NEG_INFINITY, f64::NAN] {
            let points = var(&[bad, 0.0, 0.0], &[1, 3], dtype);
            let cov = var(&[1.0; 3], &[1, 3], dtype);
            s.case(
                "volume::contract",
                format!("{dtype:?}, x = {bad}"),
                Expect::FiniteOrErr,
                &[],
                || Ok(vec![contract_points(points.as_tensor())?]),
            );
            s.case(
                "volume::contract",
                format!("{dtype:?}, mean = {bad}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let (m, v) = contract_both(points.as_tensor(), cov.as_tensor())?;
                    Ok(vec![m, v])
                },
            );
        }
    }
}

/// [`contract`](neural_fields::volume::contract) of points.
fn contract_points(points: &Tensor) -> neural_fields::Result<Tensor> {
    Ok(neural_fields::volume::contract(points, None)?.0)
}

/// [`contract`](neural_fields::volume::contract) of Gaussians.
fn contract_both(means: &Tensor, cov: &Tensor) -> neural_fields::Result<(Tensor, Tensor)> {
    let (m, c) = neural_fields::volume::contract(means, Some(cov))?;
    Ok((m, c.expect("covariances in, covariances out")))
}
