//! Stiff cases of `encoding`: frequency, Fourier and integrated encodings, the
//! coarse-to-fine window, the hash grid, grid sampling and scatter pooling at extreme inputs.

mod common;

use candle_core::{DType, Device, Tensor};

use common::stiff::{magnitudes, var, Expect, Suite, DTYPES};

use neural_fields::encoding::{
    integrated_pe, CoarseToFine, Encoding, FourierFeatures, FrequencyEncoding, PointEncoding,
};

#[test]
fn point_encodings_stay_finite() {
    let mut s = Suite::default();
    sweep_encodings(&mut s);
    s.finish("point encodings", POINT_ENCODINGS);
}

#[test]
fn hash_grid_stays_finite() {
    let mut s = Suite::default();
    sweep_hash_grid(&mut s);
    s.finish("hash grid", HASH_GRID);
}

#[test]
fn grid_sampling_and_scatter_pooling_stay_finite() {
    let mut s = Suite::default();
    sweep_grid_sample(&mut s);
    s.finish("grid sampling", GRID_SAMPLE);
}

#[test]
fn every_public_encoding_function_is_swept_or_exempt() {
    common::stiff::check_coverage(
        "stiff_cases_encoding",
        &[POINT_ENCODINGS, HASH_GRID, GRID_SAMPLE],
        EXEMPT,
        &[],
        &[],
    );
}

/// Items swept by `sweep_encodings`.
const POINT_ENCODINGS: &[&str] = &[
    "encoding::CoarseToFine::forward",
    "encoding::CoarseToFine::forward_jvp",
    "encoding::CoarseToFine::new",
    "encoding::CoarseToFine::set_alpha",
    "encoding::FourierFeatures::from_matrix",
    "encoding::FourierFeatures::new",
    "encoding::FrequencyEncoding::forward_jvp",
    "encoding::PointEncoding::forward",
    "encoding::integrated_pe",
];

/// Items swept by `sweep_hash_grid`.
const HASH_GRID: &[&str] = &[
    "encoding::HashGrid::forward",
    "encoding::HashGrid::forward_jvp",
    "encoding::hash_grid",
];

/// Items swept by `sweep_grid_sample`.
const GRID_SAMPLE: &[&str] = &[
    "encoding::cell_index",
    "encoding::grid_sample",
    "encoding::scatter",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    (
        "encoding::FusedGridSample::",
        "CustomOp internals, swept via grid_sample",
    ),
    (
        "encoding::FusedScatterMax::",
        "CustomOp internals, swept via scatter",
    ),
    ("encoding::CoarseToFine::bands", "getter"),
    ("encoding::CoarseToFine::in_dim", "getter"),
    ("encoding::CoarseToFine::out_dim", "getter"),
    ("encoding::HashGrid::in_dim", "getter"),
    ("encoding::HashGrid::out_dim", "getter"),
    ("encoding::HashGridConfig::default", "constant"),
    (
        "encoding::FusedHashGrid::",
        "CustomOp internals, swept via HashGrid::forward",
    ),
    (
        "encoding::FourierFeatures::forward",
        "swept through PointEncoding::forward_jvp / forward",
    ),
    (
        "encoding::FourierFeatures::forward_jvp",
        "swept through PointEncoding::forward_jvp",
    ),
    ("encoding::FourierFeatures::in_dim", "getter"),
    ("encoding::FourierFeatures::out_dim", "getter"),
    (
        "encoding::FrequencyEncoding::forward",
        "swept through PointEncoding::forward",
    ),
    ("encoding::FrequencyEncoding::in_dim", "getter"),
    ("encoding::FrequencyEncoding::new", "integer arguments"),
    ("encoding::FrequencyEncoding::out_dim", "getter"),
    (
        "encoding::PointEncoding::forward_jvp",
        "swept in the FrequencyEncoding / FourierFeatures cases",
    ),
    (
        "encoding::FusedFrequency::",
        "CustomOp internals, swept via FrequencyEncoding::forward",
    ),
    (
        "encoding::RowEncoder::",
        "the frequency encoding's rows inside the fused NeRF loss, swept via \
         Nerf::color_loss in tests/stiff_cases_volume.rs",
    ),
];

fn sweep_encodings(s: &mut Suite) {
    let d = Device::Cpu;
    for dtype in DTYPES {
        let big = if dtype == DType::F32 { 1e20 } else { 1e100 };
        let vals = [0.0, 1e-30, -1e-30, 1.0, -3.0, 1e10, -1e10, big, -big];
        let x = var(&vals, &[3, 3], dtype);
        let t = x.as_tensor();
        let dx = Tensor::ones((3, 2, 3), dtype, &d).unwrap();
        let label = format!("{dtype:?}, |x| up to {big:e}");
        for l in [0usize, 4, 10] {
            s.case(
                "encoding::FrequencyEncoding::forward_jvp",
                format!("{label}, L = {l}"),
                Expect::Finite,
                &[&x],
                || {
                    let mut pe = FrequencyEncoding::new(3, l)?;
                    pe.use_pi = false;
                    let enc = PointEncoding::Frequency(pe);
                    let (v, j) = enc.forward_jvp(t, &dx)?;
                    Ok(vec![v, j, enc.forward(t)?])
                },
            );
        }
        for scale in [1e-10, 1.0, 100.0] {
            s.case(
                "encoding::FourierFeatures::new",
                format!("{label}, s = {scale}"),
                Expect::Finite,
                &[&x],
                || {
                    let enc =
                        PointEncoding::Fourier(FourierFeatures::new(3, 8, scale, 1, &d, dtype)?);
                    let (v, j) = enc.forward_jvp(t, &dx)?;
                    Ok(vec![v, j])
                },
            );
        }
        s.case(
            "encoding::FourierFeatures::from_matrix",
            &label,
            Expect::Finite,
            &[&x],
            || {
                let b = Tensor::from_slice(&[1e-20, 1.0, 0.0, 3.0, -1e3, 0.5], (2, 3), &d)?
                    .to_dtype(dtype)?;
                let enc = PointEncoding::Fourier(FourierFeatures::from_matrix(b)?);
                Ok(vec![enc.forward(t)?])
            },
        );
        s.case(
            "encoding::PointEncoding::forward",
            &label,
            Expect::Finite,
            &[&x],
            || Ok(vec![PointEncoding::Identity.forward(t)?]),
        );
        let var_vals = [0.0, 1e-30, 1e30f64.min(big), 1.0, 0.0, 5.0, 1e-10, 2.0, 0.0];
        let v = var(&var_vals, &[3, 3], dtype);
        s.case(
            "encoding::integrated_pe",
            &label,
            Expect::Finite,
            &[&x, &v],
            || Ok(vec![integrated_pe(t, v.as_tensor(), 0, 16)?]),
        );
        // BARF's window at α below, inside and beyond the bands, over the same inputs.
        for alpha in [f64::NEG_INFINITY, -1e300, 0.0, 2.5, 1e300, f64::INFINITY] {
            for item in [
                "encoding::CoarseToFine::forward",
                "encoding::CoarseToFine::forward_jvp",
                "encoding::CoarseToFine::new",
                "encoding::CoarseToFine::set_alpha",
            ] {
                s.case(
                    item,
                    format!("{label}, α = {alpha:e}"),
                    Expect::Finite,
                    &[&x],
                    || {
                        let mut pe = FrequencyEncoding::new(3, 4)?;
                        pe.use_pi = false;
                        let c = CoarseToFine::new(PointEncoding::Frequency(pe))?;
                        c.set_alpha(alpha)?;
                        let (v, j) = c.forward_jvp(t, &dx)?;
                        Ok(vec![c.forward(t)?, v, j])
                    },
                );
            }
        }
        let neg = var(&[-1.0; 9], &[3, 3], dtype);
        // Negative variances are not a Gaussian: growing terms, documented as data; must not be NaN.
        s.case(
            "encoding::integrated_pe",
            format!("{dtype:?}, negative variances"),
            Expect::FiniteOrErr,
            &[&neg],
            || {
                Ok(vec![integrated_pe(
                    &Tensor::zeros((3, 3), dtype, &d)?,
                    neg.as_tensor(),
                    0,
                    4,
                )?])
            },
        );
    }
}

/// The hash grid on extreme positions (clamped into the box), both paths, f32 and f64,
/// with gradients to the positions and the table; a NaN position must be an `Err`.
fn sweep_hash_grid(s: &mut Suite) {
    use neural_fields::encoding::{hash_grid, Encoding, HashGridConfig};
    let d = Device::Cpu;
    for dtype in DTYPES {
        let big = if dtype == DType::F32 { 1e30 } else { 1e300 };
        let vals = [0.0, 1e-30, -1e-30, 1.0, -1.0, 1e10, -big, big, 0.999_999];
        let x = var(&vals, &[3, 3], dtype);
        let t = x.as_tensor();
        let label = format!("{dtype:?}, |x| up to {big:e}");
        let varmap = candle_nn::VarMap::new();
        let vb = candle_nn::VarBuilder::from_varmap(&varmap, dtype, &d);
        let config = HashGridConfig {
            levels: 4,
            log2_table_size: 8,
            finest_resolution: 1e6,
            ..HashGridConfig::default()
        };
        let grid = hash_grid(&config, vb).unwrap();
        // The same table on the reference path.
        let reference = HashGridConfig {
            force_reference: true,
            ..config
        };
        let vb = candle_nn::VarBuilder::from_varmap(&varmap, dtype, &d);
        let reference = hash_grid(&reference, vb).unwrap();
        let table = varmap.all_vars().remove(0);
        s.case(
            "encoding::hash_grid",
            format!("{dtype:?}, resolutions 16 to 1e6"),
            Expect::Finite,
            &[],
            || Ok(vec![table.as_tensor().clone()]),
        );
        s.case(
            "encoding::HashGrid::forward",
            &label,
            Expect::Finite,
            &[&x, &table],
            || Ok(vec![grid.forward(t)?]),
        );
        s.case(
            "encoding::HashGrid::forward",
            format!("{label}, reference path"),
            Expect::Finite,
            &[&x, &table],
            || Ok(vec![reference.forward(t)?]),
        );
        let dx = Tensor::ones((3, 2, 3), dtype, &d).unwrap();
        s.case(
            "encoding::HashGrid::forward_jvp",
            &label,
            Expect::Finite,
            &[&x, &table],
            || {
                let (v, j) = grid.forward_jvp(t, &dx)?;
                Ok(vec![v, j])
            },
        );
        let nan = Tensor::from_slice(&[f64::NAN, 0.0, 0.0], (1, 3), &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        if grid.forward(&nan).is_ok() || reference.forward(&nan).is_ok() {
            s.failures.push(format!(
                "HashGrid::forward [{dtype:?}]: a NaN position gave Ok"
            ));
        }
    }
}

/// Bilinear/trilinear sampling at coordinates far outside, on and just inside the border,
/// of features of every magnitude; scatter pooling of extreme values with ties.
fn sweep_grid_sample(s: &mut Suite) {
    use neural_fields::encoding::{
        cell_index, grid_sample, scatter, GridSampleConfig, Pooling, ScatterConfig,
    };
    let fused = GridSampleConfig::default();
    let reference = GridSampleConfig {
        force_reference: true,
    };
    let d = Device::Cpu;
    for dtype in DTYPES {
        let mags = magnitudes(dtype);
        let big = if dtype == DType::F32 { 1e30 } else { 1e300 };
        let coords_1d = [
            0.0, 1e-30, -1e-30, 0.5, 1.0, -1.0, 0.999_999, 1.000_001, big, -big, 1e10, -0.25,
        ];
        for k in [2usize, 3] {
            let n = coords_1d.len();
            let coord_values: Vec<f64> =
                (0..n * k).map(|i| coords_1d[(i * 5 + i / k) % n]).collect();
            let coords = var(&coord_values, &[1, n, k], dtype);
            let spatial = vec![3usize; k];
            let cells: usize = spatial.iter().product();
            let feat_values: Vec<f64> =
                (0..2 * cells).map(|i| mags[(i * 7) % mags.len()]).collect();
            let mut shape = vec![1usize, 2];
            shape.extend(&spatial);
            let features = var(&feat_values, &shape, dtype);
            let label = format!("{dtype:?}, k = {k}, features and coordinates up to {big:e}");
            s.case(
                "encoding::grid_sample",
                &label,
                Expect::Finite,
                &[&features, &coords],
                || {
                    Ok(vec![grid_sample(
                        features.as_tensor(),
                        coords.as_tensor(),
                        &fused,
                    )?])
                },
            );
            s.case(
                "encoding::grid_sample",
                format!("{label}, reference path"),
                Expect::Finite,
                &[&features, &coords],
                || {
                    Ok(vec![grid_sample(
                        features.as_tensor(),
                        coords.as_tensor(),
                        &reference,
                    )?])
                },
            );
            s.case("encoding::cell_index", &label, Expect::Finite, &[], || {
                Ok(vec![cell_index(coords.as_tensor(), 4)?])
            });
            let nan = coords
                .as_tensor()
                .slice_assign(
                    &[0..1, 0..1, 0..1],
                    &Tensor::full(f64::NAN, (1, 1, 1), &d)
                        .unwrap()
                        .to_dtype(dtype)
                        .unwrap(),
                )
                .unwrap();
            if grid_sample(features.as_tensor(), &nan, &fused).is_ok()
                || grid_sample(features.as_tensor(), &nan, &reference).is_ok()
                || cell_index(&nan, 4).is_ok()
            {
                s.failures.push(format!(
                    "grid_sample / cell_index [{dtype:?}, k = {k}]: a NaN coordinate gave Ok"
                ));
            }
            // Scatter pooling of extreme values into the cells of those coordinates; the
            // repeated magnitudes make ties for the maximum.
            let Ok(index) = cell_index(coords.as_tensor(), 2) else {
                continue;
            };
            let values: Vec<f64> = (0..n * 3).map(|i| mags[(i * 3) % mags.len()]).collect();
            let values = var(&values, &[1, n, 3], dtype);
            let cells = 1usize << k;
            for (pooling, force_reference) in [
                (Pooling::Mean, false),
                (Pooling::Max, false),
                (Pooling::Max, true),
            ] {
                let config = ScatterConfig {
                    pooling,
                    force_reference,
                };
                let path = if force_reference {
                    ", reference path"
                } else {
                    ""
                };
                s.case(
                    "encoding::scatter",
                    format!("{label}, {pooling:?}{path}"),
                    Expect::Finite,
                    &[&values],
                    || Ok(vec![scatter(values.as_tensor(), &index, cells, &config)?]),
                );
            }
        }
    }
}
