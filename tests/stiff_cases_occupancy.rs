//! Stiff cases of `occupancy`: inside tests, samplers, metrics, losses, marching cubes
//! and MISE at extreme inputs; the ONet, PointNet, ResNet, voxel and Conv. ONet networks.

#![cfg(feature = "occupancy")]

mod common;

use candle_core::{DType, Device, Tensor, Var};

use common::stiff::{magnitudes, var, Expect, Suite, DTYPES};

use neural_fields::field::{Field, SignedDistance, Sphere};
use neural_fields::nn::build_seeded;

#[test]
fn occupancy_on_meshes_stays_finite() {
    let mut s = Suite::default();
    sweep_occupancy_on_meshes(&mut s);
    s.finish("occupancy on meshes", ON_MESHES);
}

#[test]
fn occupancy_losses_samplers_and_extraction_stay_finite() {
    let mut s = Suite::default();
    sweep_occupancy(&mut s);
    s.finish("occupancy", OCCUPANCY);
}

#[test]
fn onet_networks_stay_finite() {
    let mut s = Suite::default();
    sweep_onet_networks(&mut s);
    s.finish("onet networks", ONET);
}

#[test]
fn conv_onet_stays_finite() {
    let mut s = Suite::default();
    sweep_conv_onet(&mut s);
    s.finish("conv onet", CONV_ONET);
}

#[test]
fn resnet_encoder_stays_finite() {
    let mut s = Suite::default();
    sweep_resnet(&mut s);
    s.finish("resnet encoder", RESNET);
}

#[test]
fn voxel_encoder_stays_finite() {
    let mut s = Suite::default();
    sweep_voxel(&mut s);
    s.finish("voxel encoder", VOXEL);
}

#[test]
fn every_public_occupancy_function_is_swept_or_exempt() {
    common::stiff::check_coverage(
        "stiff_cases_occupancy",
        &[ON_MESHES, OCCUPANCY, ONET, RESNET, VOXEL, CONV_ONET],
        EXEMPT,
        &[],
        UNSEEN,
    );
}

/// The decoders' `ConditionalField` methods, which a macro in src/nn/onet.rs defines.
const UNSEEN: &[&str] = &[
    "occupancy::OnetDecoder::forward_with_code",
    "occupancy::OnetDecoder::value_and_grad_with_code",
    "occupancy::SimpleDecoder::forward_with_code",
    "occupancy::SimpleDecoder::value_and_grad_with_code",
];

/// Items swept by `sweep_occupancy_on_meshes`.
const ON_MESHES: &[&str] = &[
    "occupancy::KdTree::new",
    "occupancy::iou",
    "occupancy::mesh_metrics",
    "occupancy::near_surface",
    "occupancy::surface_metrics",
    "occupancy::winding_numbers",
];

/// Items swept by `sweep_occupancy`.
const OCCUPANCY: &[&str] = &[
    "occupancy::Grid::from_fn",
    "occupancy::Grid::new",
    "occupancy::Grid::sample",
    "occupancy::kl_standard_normal",
    "occupancy::logit_threshold",
    "occupancy::marching_cubes",
    "occupancy::mise",
    "occupancy::reconstruction_loss",
    "occupancy::refine_vertices",
    "occupancy::reparameterize",
    "occupancy::uniform_in_padded_cube",
];

/// Items swept by `sweep_onet_networks`.
const ONET: &[&str] = &[
    "occupancy::OnetDecoder::forward_with_code",
    "occupancy::OnetDecoder::logits",
    "occupancy::OnetDecoder::set_mode",
    "occupancy::OnetDecoder::value_and_grad_with_code",
    "occupancy::PointNetEncoder::forward",
    "occupancy::SimpleDecoder::forward_with_code",
    "occupancy::SimpleDecoder::logits",
    "occupancy::SimpleDecoder::value_and_grad_with_code",
    "occupancy::onet_decoder",
    "occupancy::pointnet_encoder",
    "occupancy::simple_decoder",
];

/// Items swept by `sweep_resnet`.
const RESNET: &[&str] = &[
    "occupancy::ResnetEncoder::forward",
    "occupancy::resnet_encoder",
];

/// Items swept by `sweep_voxel`.
const VOXEL: &[&str] = &[
    "occupancy::VoxelEncoder::forward",
    "occupancy::voxel_encoder",
];

/// Items swept by `sweep_conv_onet`.
const CONV_ONET: &[&str] = &[
    "occupancy::ConvOnetEncoder::forward",
    "occupancy::LocalDecoder::bind",
    "occupancy::LocalDecoder::logits",
    "occupancy::SceneField::forward",
    "occupancy::conv_onet_encoder",
    "occupancy::local_decoder",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    (
        "occupancy::MiseConfig::new",
        "stores settings; mise checks them and is swept with them",
    ),
    (
        "occupancy::RefineConfig::new",
        "stores settings; refine_vertices checks them and is swept with them",
    ),
    (
        "occupancy::chamfer_icp",
        "mesh_metrics after align_similarity's iterations, both swept",
    ),
    ("occupancy::ConvOnetConfig::default", "constant"),
    ("occupancy::MiseConfig::default", "constant"),
    ("occupancy::RefineConfig::default", "constant"),
    ("occupancy::UnetConfig::default", "constant"),
    ("occupancy::LocalDecoderConfig::default", "constant"),
    ("occupancy::SceneField::out_dim", "constant"),
    ("occupancy::SimpleDecoderConfig::default", "constant"),
    ("occupancy::SimpleDecoder::code_dim", "getter"),
    ("occupancy::SimpleDecoder::inside", "getter"),
    ("occupancy::SimpleDecoder::out_dim", "getter"),
    ("occupancy::PointNetConfig::default", "constant"),
    ("occupancy::ResnetEncoderConfig::default", "constant"),
    ("occupancy::VoxelEncoderConfig::default", "constant"),
    ("occupancy::OnetConfig::default", "constant"),
    ("occupancy::OnetDecoder::code_dim", "getter"),
    ("occupancy::OnetDecoder::inside", "getter"),
    ("occupancy::OnetDecoder::out_dim", "getter"),
    ("occupancy::KdTree::nearest", "swept through KdTree::new"),
];

/// Inside/outside tests, near-surface samples and metrics on meshes at three scales, and
/// IoU of empty and disjoint sets.
fn sweep_occupancy_on_meshes(s: &mut Suite) {
    use neural_fields::mesh::Mesh;
    use neural_fields::occupancy::{
        iou, mesh_metrics, near_surface, surface_metrics, winding_numbers, KdTree, WindingConfig,
    };
    let d = Device::Cpu;
    let flat = |v: Vec<[f64; 3]>| Tensor::from_vec(v.concat(), v.len() * 3, &d);
    let vt = |v: Vec<f64>| Tensor::from_vec(v.clone(), v.len(), &d);
    // A tetrahedron at three scales: tiny, unit, huge.
    let tet = |scale: f64| {
        Mesh::new(
            vec![
                [0.0, 0.0, 0.0],
                [scale, 0.0, 0.0],
                [0.0, scale, 0.0],
                [0.0, 0.0, scale],
            ],
            vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
    };
    for scale in [1e-6, 1.0, 1e6] {
        let label = format!("tetrahedron of size {scale:e}");
        let mesh = tet(scale).unwrap();
        let q = vec![
            [0.1 * scale, 0.1 * scale, 0.1 * scale],
            [10.0 * scale, 0.0, 0.0],
            [0.0, 0.0, 0.0],
            [1e-30, 0.0, 0.0],
        ];
        s.case(
            "occupancy::winding_numbers",
            &label,
            Expect::Finite,
            &[],
            || {
                Ok(vec![vt(winding_numbers(
                    &mesh,
                    &q,
                    &WindingConfig::default(),
                )?)?])
            },
        );
        s.case(
            "occupancy::winding_numbers",
            format!("{label}, reference path"),
            Expect::Finite,
            &[],
            || {
                let exact = WindingConfig {
                    force_reference: true,
                };
                Ok(vec![vt(winding_numbers(&mesh, &q, &exact)?)?])
            },
        );
        for sigma in [0.0, 1e-30, 1e3] {
            s.case(
                "occupancy::near_surface",
                format!("{label}, σ = {sigma:e}"),
                Expect::FiniteOrErr,
                &[],
                || Ok(vec![flat(near_surface(&mesh, 32, sigma, 2)?)?]),
            );
        }
        s.case(
            "occupancy::KdTree::new",
            &label,
            Expect::Finite,
            &[],
            || {
                let tree = KdTree::new(&mesh.vertices)?;
                Ok(vec![vt(q
                    .iter()
                    .map(|p| tree.nearest(*p).map_or(f64::NAN, |n| n.1))
                    .collect())?])
            },
        );
        // 0.1's `nearest_distances(queries, reference)`.
        s.case(
            "occupancy::KdTree::new",
            format!("{label}, nearest distances"),
            Expect::Finite,
            &[],
            || {
                let tree = KdTree::new(&mesh.vertices)?;
                Ok(vec![vt(q
                    .iter()
                    .map(|&p| tree.nearest(p))
                    .map(|n| n.map_or(f64::NAN, |(_, dist)| dist))
                    .collect())?])
            },
        );
        s.case(
            "occupancy::surface_metrics",
            &label,
            Expect::Finite,
            &[],
            || {
                let m = surface_metrics(&q, None, &mesh.vertices, None, 0.01 * scale)?;
                Ok(vec![vt(vec![
                    m.accuracy,
                    m.completeness,
                    m.chamfer_l1,
                    m.normal_consistency.unwrap_or(0.0),
                    m.f_score,
                ])?])
            },
        );
        s.case(
            "occupancy::mesh_metrics",
            &label,
            Expect::Finite,
            &[],
            || {
                let m = mesh_metrics(&mesh, &tet(scale * 1.01)?, 256, 0.01 * scale, 3)?;
                Ok(vec![vt(vec![
                    m.accuracy,
                    m.completeness,
                    m.chamfer_l1,
                    m.normal_consistency.unwrap_or(0.0),
                    m.f_score,
                ])?])
            },
        );
    }
    s.case(
        "occupancy::iou",
        "empty union and disjoint sets",
        Expect::FiniteOrErr,
        &[],
        || {
            Ok(vec![vt(vec![
                iou(&[false, false], &[false, false])?,
                iou(&[true, false], &[false, true])?,
            ])?])
        },
    );
}

/// Occupancy losses at extreme logits, means and log-variances; samplers; marching cubes
/// on grids of extreme values and extents; MISE on analytic fields.
fn sweep_occupancy(s: &mut Suite) {
    use neural_fields::field::Inside;

    use neural_fields::mesh::{points_from_tensor, points_to_tensor, Mesh};
    use neural_fields::occupancy::{
        kl_standard_normal, logit_threshold, marching_cubes, mise, reconstruction_loss,
        refine_vertices, reparameterize, uniform_in_padded_cube, Grid, MiseConfig, RefineConfig,
    };
    let d = Device::Cpu;
    let flat = |v: Vec<[f64; 3]>| Tensor::from_vec(v.concat(), v.len() * 3, &d);
    let _vt = |v: Vec<f64>| Tensor::from_vec(v.clone(), v.len(), &d);
    // A tetrahedron at three scales: tiny, unit, huge.
    let _tet = |scale: f64| {
        Mesh::new(
            vec![
                [0.0, 0.0, 0.0],
                [scale, 0.0, 0.0],
                [0.0, scale, 0.0],
                [0.0, 0.0, scale],
            ],
            vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
    };
    for dtype in DTYPES {
        let tag = format!("{dtype:?}");
        // Losses at extreme logits, means and log-variances.
        let xs = magnitudes(dtype);
        let n = xs.len();
        let logits = var(&xs, &[1, n], dtype);
        let targets = Tensor::full(1.0f64, (1, n), &d)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        s.case(
            "occupancy::reconstruction_loss",
            format!("{tag}, logits up to max"),
            Expect::Finite,
            &[&logits],
            || Ok(vec![reconstruction_loss(logits.as_tensor(), &targets)?]),
        );
        let mean = var(&[0.0, 1e-30, 1e3, -1e3], &[1, 4], dtype);
        let logvar = var(&[0.0, -50.0, 50.0, -1e-30], &[1, 4], dtype);
        s.case(
            "occupancy::kl_standard_normal",
            format!("{tag}, log-variances ±50"),
            Expect::Finite,
            &[&mean, &logvar],
            || {
                Ok(vec![kl_standard_normal(
                    mean.as_tensor(),
                    logvar.as_tensor(),
                )?])
            },
        );
        s.case(
            "occupancy::reparameterize",
            format!("{tag}, log-variances ±50"),
            Expect::Finite,
            &[&mean, &logvar],
            || {
                Ok(vec![reparameterize(
                    mean.as_tensor(),
                    logvar.as_tensor(),
                    4,
                )?])
            },
        );
        for pad in [0.0, 0.1, 1e6] {
            s.case(
                "occupancy::uniform_in_padded_cube",
                format!("{tag}, padding {pad}"),
                Expect::Finite,
                &[],
                || {
                    let p = uniform_in_padded_cube(64, pad, 1, &d, dtype)?;
                    Ok(vec![
                        points_to_tensor(&points_from_tensor(&p)?, &d, dtype)?,
                        p,
                    ])
                },
            );
        }
        // Grids of extreme values and extents, and MISE on analytic fields.
        for (ext, amp) in [(1e-6, 1e-30), (1.0, 1.0), (1e6, 1e30)] {
            let gl = format!("{tag}, box ±{ext}, values ±{amp:e}");
            let f = move |p: [f64; 3]| {
                amp * ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 0.5 * ext)
            };
            s.case("occupancy::Grid::from_fn", &gl, Expect::Finite, &[], || {
                let g = Grid::from_fn([9, 9, 9], [-ext; 3], [ext; 3], f)?;
                let sp: [f64; 3] =
                    std::array::from_fn(|c| (g.max[c] - g.min[c]) / (g.dims[c] - 1) as f64);
                Ok(vec![
                    flat(marching_cubes(&g, 0.0, Inside::Negative)?.vertices)?,
                    // x of grid point (1, 2, 3).
                    Tensor::new(&[sp[0], g.min[0] + sp[0]], &d)?,
                ])
            });
            s.case(
                "occupancy::marching_cubes",
                &gl,
                Expect::Finite,
                &[],
                || {
                    Ok(vec![flat(
                        marching_cubes(
                            &Grid::from_fn([9, 9, 9], [-ext; 3], [ext; 3], f)?,
                            0.0,
                            Inside::Negative,
                        )?
                        .vertices,
                    )?])
                },
            );
            s.case(
                "occupancy::Grid::new",
                &gl,
                Expect::FiniteOrErr,
                &[],
                || {
                    let vals: Vec<f32> = (0..27)
                        .map(|i| if i == 13 { -(amp as f32) } else { amp as f32 })
                        .collect();
                    Ok(vec![flat(
                        marching_cubes(
                            &Grid::new(vals, [3, 3, 3], [-ext; 3], [ext; 3])?,
                            0.0,
                            Inside::Negative,
                        )?
                        .vertices,
                    )?])
                },
            );
            s.case("occupancy::Grid::sample", &gl, Expect::Finite, &[], || {
                let sphere = Sphere::new([0.0; 3], 0.5 * ext, &d, dtype)?.sdf();
                Ok(vec![flat(
                    marching_cubes(
                        &Grid::sample(&sphere, [9, 9, 9], [-ext; 3], [ext; 3], 64, &d, dtype)?,
                        0.0,
                        Inside::Negative,
                    )?
                    .vertices,
                )?])
            });
            s.case("occupancy::mise", &gl, Expect::Finite, &[], || {
                let sphere = Sphere::new([0.0; 3], 0.5 * ext, &d, dtype)?.occupancy(100.0 / ext);
                let mut cfg = MiseConfig {
                    resolution0: 8,
                    upsampling_steps: 2,
                    device: d.clone(),
                    dtype,
                    ..MiseConfig::new(32, 2, &Device::Cpu, DType::F32)
                };
                cfg.min = [-ext; 3];
                cfg.max = [ext; 3];
                let out = mise(&sphere, &cfg)?;
                Ok(vec![
                    flat(out.mesh.vertices)?,
                    Tensor::new(out.evaluations as f64, &d)?,
                ])
            });
            s.case(
                "occupancy::refine_vertices",
                &gl,
                Expect::Finite,
                &[],
                || {
                    let sphere =
                        Sphere::new([0.0; 3], 0.5 * ext, &d, dtype)?.occupancy(100.0 / ext);
                    let mut cfg = MiseConfig {
                        resolution0: 8,
                        upsampling_steps: 1,
                        device: d.clone(),
                        dtype,
                        ..MiseConfig::new(32, 2, &Device::Cpu, DType::F32)
                    };
                    cfg.min = [-ext; 3];
                    cfg.max = [ext; 3];
                    let mut mesh = mise(&sphere, &cfg)?.mesh;
                    let (before, after) = refine_vertices(
                        &sphere,
                        &mut mesh,
                        &RefineConfig {
                            max_shift: 0.1 * ext,
                            device: d.clone(),
                            dtype,
                            ..RefineConfig::new(0.005, &Device::Cpu, DType::F32)
                        },
                    )?;
                    Ok(vec![
                        flat(mesh.vertices)?,
                        Tensor::new(&[before, after], &d)?,
                    ])
                },
            );
        }
        for p in [0.0, 1e-30, 0.5, 1.0 - 1e-12, 1.0] {
            s.case(
                "occupancy::logit_threshold",
                format!("p = {p}"),
                Expect::FiniteOrErr,
                &[],
                || Ok(vec![Tensor::new(logit_threshold(p)?, &d)?]),
            );
        }
    }
}

/// The PointNet encoder and the ONet decoders at extreme points, labels and codes.
fn sweep_onet_networks(s: &mut Suite) {
    use neural_fields::mesh::Mesh;
    use neural_fields::occupancy::{onet_decoder, NormMode, OnetConfig};
    let d = Device::Cpu;
    let _flat = |v: Vec<[f64; 3]>| Tensor::from_vec(v.concat(), v.len() * 3, &d);
    let _vt = |v: Vec<f64>| Tensor::from_vec(v.clone(), v.len(), &d);
    // A tetrahedron at three scales: tiny, unit, huge.
    let _tet = |scale: f64| {
        Mesh::new(
            vec![
                [0.0, 0.0, 0.0],
                [scale, 0.0, 0.0],
                [0.0, scale, 0.0],
                [0.0, 0.0, scale],
            ],
            vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
    };
    for dtype in DTYPES {
        let tag = format!("{dtype:?}");
        // PointNet encoder on extreme points and labels.
        {
            use neural_fields::occupancy::{pointnet_encoder, PointNetConfig};
            let cfg = PointNetConfig {
                hidden: 8,
                layers: 2,
                latent_dim: 3,
                point_features: 1,
            };
            let vm = candle_nn::VarMap::new();
            let enc = build_seeded(&vm, dtype, &d, 2, |vb| pointnet_encoder(&cfg, vb)).unwrap();
            let big = if dtype == DType::F32 { 1e15 } else { 1e100 };
            let p = var(
                &[
                    0.0, 0.0, 0.0, 1e-30, -1.0, 1.0, big, -big, big, 0.5, 0.5, 0.5,
                ],
                &[1, 4, 3],
                dtype,
            );
            let o = var(&[0.0, 1.0, 1e-30, 0.5], &[1, 4], dtype);
            let el = format!("{tag}, |p| up to {big:e}");
            s.case(
                "occupancy::pointnet_encoder",
                &el,
                Expect::Finite,
                &[&p, &o],
                || {
                    let (m, l) = enc.forward(p.as_tensor(), o.as_tensor())?;
                    Ok(vec![m, l])
                },
            );
            s.case(
                "occupancy::PointNetEncoder::forward",
                &el,
                Expect::Finite,
                &[&p, &o],
                || {
                    let (m, l) = enc.forward(p.as_tensor(), o.as_tensor())?;
                    Ok(vec![m, l])
                },
            );
            // Points with extreme per-point features (Texture Fields' normals).
            let cfg3 = PointNetConfig {
                point_features: 3,
                ..cfg.clone()
            };
            let vm3 = candle_nn::VarMap::new();
            let enc3 = build_seeded(&vm3, dtype, &d, 3, |vb| pointnet_encoder(&cfg3, vb)).unwrap();
            let nrm = var(
                &[
                    0.0, 0.0, 0.0, 1.0, 0.0, 0.0, -big, big, 1e-30, 0.5, -0.5, 0.5,
                ],
                &[1, 4, 3],
                dtype,
            );
            s.case(
                "occupancy::PointNetEncoder::forward",
                format!("{el}, F = 3 features up to {big:e}"),
                Expect::Finite,
                &[&p, &nrm],
                || {
                    let (m, l) = enc3.forward(p.as_tensor(), nrm.as_tensor())?;
                    Ok(vec![m, l])
                },
            );
        }
        // ONet's simple decoder on extreme points and codes.
        {
            use neural_fields::occupancy::{simple_decoder, SimpleDecoderConfig};
            let cfg = SimpleDecoderConfig {
                hidden: 8,
                blocks: 2,
                code_dim: 4,
            };
            let vm = candle_nn::VarMap::new();
            let dec = build_seeded(&vm, dtype, &d, 6, |vb| simple_decoder(&cfg, vb)).unwrap();
            let big = if dtype == DType::F32 { 1e15 } else { 1e100 };
            let p = var(
                &[0.0, 0.0, 0.0, 1e-30, 1.0, -1.0, big, -big, big],
                &[3, 3],
                dtype,
            );
            let c = var(
                &[
                    0.0, 1e-30, 1.0, -1.0, 1e3, -1e3, 0.5, 0.0, big, 0.0, 0.0, 0.0,
                ],
                &[3, 4],
                dtype,
            );
            let sl = format!("{tag}, |p|, |z| up to {big:e}");
            s.case(
                "occupancy::simple_decoder",
                &sl,
                Expect::Finite,
                &[&p, &c],
                || Ok(vec![dec.logits(p.as_tensor(), c.as_tensor())?]),
            );
            s.case(
                "occupancy::SimpleDecoder::logits",
                &sl,
                Expect::Finite,
                &[&p, &c],
                || Ok(vec![dec.logits(p.as_tensor(), c.as_tensor())?]),
            );
            s.case(
                "occupancy::SimpleDecoder::value_and_grad_with_code",
                &sl,
                Expect::Finite,
                &[&p, &c],
                || {
                    let (v, g) = neural_fields::field::ConditionalField::value_and_grad_with_code(
                        &dec,
                        p.as_tensor(),
                        c.as_tensor(),
                    )?;
                    Ok(vec![v, g])
                },
            );
            s.case(
                "occupancy::SimpleDecoder::forward_with_code",
                &sl,
                Expect::Finite,
                &[&p, &c],
                || {
                    Ok(vec![
                        neural_fields::field::ConditionalField::forward_with_code(
                            &dec,
                            p.as_tensor(),
                            c.as_tensor(),
                        )?,
                    ])
                },
            );
        }
        // ONet decoder on extreme points and codes, both norm modes.
        let config = OnetConfig {
            hidden: 16,
            blocks: 2,
            code_dim: 4,
            ..OnetConfig::default()
        };
        let varmap = candle_nn::VarMap::new();
        let net = build_seeded(&varmap, dtype, &d, 1, |vb| onet_decoder(&config, vb)).unwrap();
        let big = if dtype == DType::F32 { 1e6 } else { 1e100 };
        let pts = var(
            &[0.0, 0.0, 0.0, 1e-30, 1.0, -1.0, big, -big, big],
            &[3, 3],
            dtype,
        );
        let codes = var(
            &[
                0.0, 1e-30, 1.0, -1.0, 1e3, -1e3, 0.5, 0.0, big, 0.0, 0.0, 0.0,
            ],
            &[3, 4],
            dtype,
        );
        for mode in [NormMode::Train, NormMode::Eval] {
            let ol = format!("{tag}, |p|, |z| up to {big:e}, {mode:?}");
            net.set_mode(mode);
            s.case(
                "occupancy::onet_decoder",
                &ol,
                Expect::Finite,
                &[&pts, &codes],
                || Ok(vec![net.logits(pts.as_tensor(), codes.as_tensor())?]),
            );
            s.case(
                "occupancy::OnetDecoder::logits",
                &ol,
                Expect::Finite,
                &[&pts, &codes],
                || Ok(vec![net.logits(pts.as_tensor(), codes.as_tensor())?]),
            );
            s.case(
                "occupancy::OnetDecoder::logits",
                format!("{ol}, one code per shape"),
                Expect::Finite,
                &[&pts, &codes],
                || {
                    let p = pts.as_tensor().unsqueeze(0)?;
                    let c = codes.as_tensor().narrow(0, 0, 1)?;
                    Ok(vec![net.logits(&p, &c)?])
                },
            );
            s.case(
                "occupancy::OnetDecoder::set_mode",
                &ol,
                Expect::Finite,
                &[],
                || Ok(vec![]),
            );
            s.case(
                "occupancy::OnetDecoder::forward_with_code",
                &ol,
                Expect::Finite,
                &[&pts, &codes],
                || {
                    Ok(vec![
                        neural_fields::field::ConditionalField::forward_with_code(
                            &net,
                            pts.as_tensor(),
                            codes.as_tensor(),
                        )?,
                    ])
                },
            );
            s.case(
                "occupancy::OnetDecoder::value_and_grad_with_code",
                &ol,
                Expect::Finite,
                &[&pts, &codes],
                || {
                    let (v, g) = neural_fields::field::ConditionalField::value_and_grad_with_code(
                        &net,
                        pts.as_tensor(),
                        codes.as_tensor(),
                    )?;
                    Ok(vec![v, g])
                },
            );
        }
    }
}

/// The ResNet image encoder on images of extreme pixel values (zero, tiny, huge, one
/// huge pixel among ordinary ones), in training (batch statistics) and inference
/// (running statistics), with gradients w.r.t. the pixels.
fn sweep_resnet(s: &mut Suite) {
    use neural_fields::occupancy::{resnet_encoder, ResnetEncoderConfig};
    let d = Device::Cpu;
    let cfg = ResnetEncoderConfig {
        width: 4,
        blocks: [1, 1, 1, 1],
        c_dim: 3,
        ..ResnetEncoderConfig::default()
    };
    for dtype in DTYPES {
        let vm = candle_nn::VarMap::new();
        let enc = build_seeded(&vm, dtype, &d, 4, |vb| resnet_encoder(&cfg, vb)).unwrap();
        let big = if dtype == DType::F32 { 1e15 } else { 1e100 };
        let n = 2 * 3 * 32 * 32;
        let ramp = |scale: f64| -> Vec<f64> {
            (0..n)
                .map(|i| scale * (((i * 37) % 101) as f64 / 50.0 - 1.0))
                .collect()
        };
        let mut spike = ramp(1.0);
        spike[n / 2] = big;
        let cases: Vec<(String, Vec<f64>)> = vec![
            ("zero images".into(), vec![0.0; n]),
            ("constant images".into(), vec![0.5; n]),
            ("pixels ~1e-30".into(), ramp(1e-30)),
            ("pixels ~1".into(), ramp(1.0)),
            (format!("pixels ~{big:e}"), ramp(big)),
            (format!("one pixel {big:e}"), spike),
        ];
        for (label, values) in cases {
            let x = var(&values, &[2, 3, 32, 32], dtype);
            for train in [true, false] {
                let el = format!("{dtype:?}, {label}, train {train}");
                s.case(
                    "occupancy::ResnetEncoder::forward",
                    &el,
                    Expect::Finite,
                    &[&x],
                    || Ok(vec![enc.forward(x.as_tensor(), train)?]),
                );
            }
        }
        s.case(
            "occupancy::resnet_encoder",
            format!("{dtype:?}, a fresh network on pixels ~{big:e}"),
            Expect::Finite,
            &[],
            || {
                let vm = candle_nn::VarMap::new();
                let enc = build_seeded(&vm, dtype, &d, 5, |vb| resnet_encoder(&cfg, vb))?;
                let x = var(&ramp(big), &[2, 3, 32, 32], dtype);
                Ok(vec![enc.forward(x.as_tensor(), false)?])
            },
        );
    }
}

/// The voxel encoder on grids at the ends of its input range and just inside them (empty,
/// full, occupancies ~1e-30 and the dtype's smallest subnormal, one voxel, a
/// checkerboard, a full grid but one voxel), with gradients w.r.t. the voxels; and a fresh
/// network whose weights are scaled to ~1e10 (f32) or ~1e100 (f64) on a full grid.
fn sweep_voxel(s: &mut Suite) {
    use neural_fields::occupancy::{voxel_encoder, VoxelEncoderConfig};
    let d = Device::Cpu;
    let cfg = VoxelEncoderConfig {
        base_channels: 4,
        stages: 3,
        c_dim: 3,
        resolution: 8,
        force_reference: false,
    };
    let n = 2 * 512;
    for dtype in DTYPES {
        let vm = candle_nn::VarMap::new();
        let enc = build_seeded(&vm, dtype, &d, 6, |vb| voxel_encoder(&cfg, vb)).unwrap();
        let tiny = if dtype == DType::F32 { 1e-45 } else { 5e-324 };
        let mut one = vec![0.0; n];
        one[3 * 64 + 4 * 8 + 5] = 1.0;
        let mut all_but_one = vec![1.0; n];
        all_but_one[512 + 7 * 64] = 0.0;
        let cases: Vec<(&str, Vec<f64>)> = vec![
            ("empty grids", vec![0.0; n]),
            ("full grids", vec![1.0; n]),
            ("occupancies 1e-30", vec![1e-30; n]),
            ("smallest subnormal occupancies", vec![tiny; n]),
            ("one voxel", one),
            (
                "checkerboard",
                (0..n).map(|i| ((i / 64 + i / 8 + i) % 2) as f64).collect(),
            ),
            ("full but one voxel", all_but_one),
        ];
        for (label, values) in cases {
            let x = var(&values, &[2, 8, 8, 8], dtype);
            s.case(
                "occupancy::VoxelEncoder::forward",
                format!("{dtype:?}, {label}"),
                Expect::Finite,
                &[&x],
                || Ok(vec![enc.forward(x.as_tensor())?]),
            );
        }
        let big = if dtype == DType::F32 { 1e10 } else { 1e100 };
        s.case(
            "occupancy::voxel_encoder",
            format!("{dtype:?}, a fresh network with weights ~{big:e} on full grids"),
            Expect::Finite,
            &[],
            || {
                let vm = candle_nn::VarMap::new();
                let enc = build_seeded(&vm, dtype, &d, 7, |vb| voxel_encoder(&cfg, vb))?;
                for v in vm.all_vars() {
                    // Only the first layer large: the product over four layers stays
                    // within range while every activation is huge.
                    if v.dims().len() == 5 && v.dims()[1] == 1 {
                        v.set(&v.as_tensor().affine(big, 0.0)?)?;
                    }
                }
                let x = var(&vec![1.0; n], &[2, 8, 8, 8], dtype);
                Ok(vec![enc.forward(x.as_tensor())?])
            },
        );
    }
}

/// Conv. ONet on point clouds with coordinates from 0 to far outside the padded box (in
/// both layouts), and the decoder at such points.
fn sweep_conv_onet(s: &mut Suite) {
    use neural_fields::mesh::{points_to_tensor, PointCloud};
    use neural_fields::occupancy::{
        conv_onet_encoder, local_decoder, ConvOnetConfig, FeatureLayout, LocalDecoderConfig,
        UnetConfig,
    };
    let d = Device::Cpu;
    for dtype in DTYPES {
        let big = if dtype == DType::F32 { 1e8 } else { 1e100 };
        let rows: Vec<[f64; 3]> = vec![
            [0.0, 0.0, 0.0],
            [1e-30, 0.0, 0.0],
            [0.5, 0.5, 0.5],
            [-0.55, 0.55, 0.0],
            [big, -big, big],
            [1e4, 1.0, -1e4],
        ];
        let n = rows.len();
        let p = var(&rows.concat(), &[1, n, 3], dtype);
        for layout in [
            FeatureLayout::Planes { resolution: 4 },
            FeatureLayout::Grid { resolution: 4 },
        ] {
            let config = ConvOnetConfig {
                layout,
                hidden: 8,
                blocks: 2,
                feature_dim: 4,
                unet: UnetConfig {
                    depth: 2,
                    start_filters: 4,
                },
                ..ConvOnetConfig::default()
            };
            let dconfig = LocalDecoderConfig {
                hidden: 8,
                blocks: 2,
                feature_dim: 4,
                padding: config.padding,
            };
            let vm = candle_nn::VarMap::new();
            let (enc, dec) = build_seeded(&vm, dtype, &d, 6, |vb| {
                Ok((
                    conv_onet_encoder(&config, vb.pp("enc"))?,
                    local_decoder(&dconfig, vb.pp("dec"))?,
                ))
            })
            .unwrap();
            let mut wrt: Vec<Var> = vm.all_vars();
            wrt.push(p.clone());
            let wrt: Vec<&Var> = wrt.iter().collect();
            let label = format!("{dtype:?}, {layout:?}, |p| up to {big:e}");
            for item in ["occupancy::conv_onet_encoder", "occupancy::local_decoder"] {
                s.case(item, &label, Expect::Finite, &[], || Ok(vec![]));
            }
            s.case(
                "occupancy::ConvOnetEncoder::forward",
                &label,
                Expect::Finite,
                &wrt,
                || {
                    let f = enc.forward(p.as_tensor())?;
                    Ok(match f {
                        neural_fields::occupancy::LocalFeatures::Planes { xz, xy, yz } => {
                            vec![xz, xy, yz]
                        }
                        neural_fields::occupancy::LocalFeatures::Grid(g) => vec![g],
                    })
                },
            );
            s.case(
                "occupancy::LocalDecoder::logits",
                &label,
                Expect::Finite,
                &wrt,
                || {
                    let f = enc.forward(p.as_tensor())?;
                    Ok(vec![dec.logits(p.as_tensor(), &f)?])
                },
            );
            let cloud = PointCloud::new(rows.clone(), None, None).unwrap();
            for item in [
                "occupancy::LocalDecoder::bind",
                "occupancy::SceneField::forward",
            ] {
                s.case(item, &label, Expect::Finite, &wrt, || {
                    let one = points_to_tensor(cloud.points(), &d, dtype)?.unsqueeze(0)?;
                    let field = dec.bind(enc.forward(&one)?)?;
                    Ok(vec![field.forward(&p.as_tensor().squeeze(0)?)?])
                });
            }
        }
    }
}
