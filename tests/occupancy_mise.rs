//! MISE against dense marching cubes: the same surface from far fewer evaluations.
#![cfg(feature = "occupancy")]

use candle_core::{DType, Device};
use neural_fields::field::{ImplicitSurface, Inside, SignedDistance, Sphere, Torus};
use neural_fields::occupancy::{
    logit_threshold, marching_cubes, mise, refine_vertices, surface_metrics, Grid, MiseConfig,
    RefineConfig,
};
use std::time::Instant;

fn torus_sdf(p: [f64; 3]) -> f64 {
    let rho = (p[0] * p[0] + p[1] * p[1]).sqrt();
    ((rho - 0.3).powi(2) + p[2] * p[2]).sqrt() - 0.1
}

#[test]
fn mise_matches_dense_marching_cubes_with_far_fewer_evaluations() {
    // Final resolution 128³ here (256³ is in the release-mode example/bench, see
    // docs); same grid points, so the meshes must coincide.
    let dev = Device::Cpu;
    for dtype in [DType::F32, DType::F64] {
        let torus = Torus::new([0.0; 3], 0.3, 0.1, &dev, dtype)
            .unwrap()
            .occupancy(10.0);
        let cfg = MiseConfig {
            resolution0: 16,
            upsampling_steps: 3,
            device: dev.clone(),
            dtype,
            ..MiseConfig::new(32, 2, &Device::Cpu, DType::F32)
        };
        let out = mise(&torus, &cfg).unwrap();
        let np = (cfg.resolution0 << cfg.upsampling_steps) + 1;
        assert_eq!(np, 129);
        let dense = Grid::sample(&torus, [np; 3], cfg.min, cfg.max, 65_536, &dev, dtype).unwrap();
        let dm = marching_cubes(&dense, 0.0, Inside::Positive).unwrap();
        assert!(!out.mesh.faces.is_empty() && out.mesh.edge_report() == (0, 0, 0));
        assert_eq!(out.mesh.faces.len(), dm.faces.len(), "{dtype:?}");
        let m = surface_metrics(&out.mesh.vertices, None, &dm.vertices, None, 1e-6).unwrap();
        assert!(m.chamfer_l1 < 1e-9, "{dtype:?}: {m:?}");
        assert!(
            out.evaluations * 10 < np * np * np,
            "{} evaluations",
            out.evaluations
        );
        assert_eq!(out.active_per_level.len(), 4);
        // Vertices on the exact torus to within a fraction of the final voxel.
        let h = 1.1 / 128.0;
        let worst = out
            .mesh
            .vertices
            .iter()
            .map(|&v| torus_sdf(v).abs())
            .fold(0.0, f64::max);
        assert!(worst < 0.05 * h, "{worst}");
    }
}

#[test]
fn mise_without_upsampling_is_dense_and_thresholds_are_logits() {
    let dev = Device::Cpu;
    let s = Sphere::new([0.0; 3], 0.3, &dev, DType::F32)
        .unwrap()
        .occupancy(20.0);
    let mut cfg = MiseConfig::new(20, 0, &dev, DType::F32);
    cfg.chunk = 100;
    let out = mise(&s, &cfg).unwrap();
    assert_eq!(out.evaluations, 21 * 21 * 21);
    // A higher probability threshold gives a smaller sphere: σ(−20(r − 0.3)) = 0.9 at
    // r = 0.3 − ln 9 / 20.
    let mut cfg = MiseConfig::new(16, 2, &dev, DType::F32);
    cfg.level = Some(logit_threshold(0.9).unwrap());
    let out = mise(&s, &cfg).unwrap();
    let r = 0.3 - 9f64.ln() / 20.0;
    let mean_r = out
        .mesh
        .vertices
        .iter()
        .map(|v| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt())
        .sum::<f64>()
        / out.mesh.vertices.len() as f64;
    assert!((mean_r - r).abs() < 1e-3, "{mean_r} vs {r}");
    assert!(logit_threshold(0.5).unwrap().abs() < 1e-15);
    assert!(logit_threshold(1.0).is_err());
}

#[test]
fn mise_rejects_bad_settings_and_handles_empty_fields() {
    let dev = Device::Cpu;
    let s = Sphere::new([5.0; 3], 0.3, &dev, DType::F32).unwrap().sdf();
    let out = mise(&s, &MiseConfig::new(8, 2, &dev, DType::F32)).unwrap();
    assert!(out.mesh.faces.is_empty());
    assert_eq!(out.evaluations, 9 * 9 * 9);
    assert!(mise(&s, &MiseConfig::new(0, 2, &dev, DType::F32)).is_err());
    assert!(mise(&s, &MiseConfig::new(16, 8, &dev, DType::F32)).is_err());
    let mut c = MiseConfig::new(4, 1, &dev, DType::F32);
    c.chunk = 0;
    assert!(mise(&s, &c).unwrap_err().to_string().starts_with("chunk"));
    let c = MiseConfig::new(4, 1, &dev, DType::U8);
    assert!(mise(&s, &c).is_err());
    let _ = s.level();
}

#[test]
#[ignore = "timing: run in release, cargo test --release --test occupancy_mise -- --ignored"]
fn mise_256_against_dense_256_on_a_torus() {
    let dev = Device::Cpu;
    let torus = Torus::new([0.0; 3], 0.3, 0.1, &dev, DType::F32)
        .unwrap()
        .occupancy(10.0);
    let cfg = MiseConfig::new(32, 3, &dev, DType::F32);
    let t = Instant::now();
    let out = mise(&torus, &cfg).unwrap();
    let t_mise = t.elapsed().as_secs_f64();
    let np = (cfg.resolution0 << cfg.upsampling_steps) + 1;
    let t = Instant::now();
    let dense = Grid::sample(&torus, [np; 3], cfg.min, cfg.max, 65_536, &dev, DType::F32).unwrap();
    let dm = marching_cubes(&dense, 0.0, Inside::Positive).unwrap();
    let t_dense = t.elapsed().as_secs_f64();
    let m = surface_metrics(&out.mesh.vertices, None, &dm.vertices, None, 1e-6).unwrap();
    let dense_evals = np * np * np;
    println!(
        "MISE 32×2³: {} evals, {t_mise:.3} s; dense 257³: {dense_evals} evals, {t_dense:.3} s; chamfer {:e}",
        out.evaluations, m.chamfer_l1
    );
    assert!(m.chamfer_l1 <= 1e-4 * 1.1);
    assert!(out.evaluations * 10 <= dense_evals);
    assert!(t_mise * 5.0 <= t_dense, "{t_mise} vs {t_dense}");
}

#[test]
#[ignore = "timing: run in release, cargo test --release --test occupancy_mise -- --ignored"]
fn mise_256_against_dense_256_on_a_trained_mlp() {
    use candle_nn::{Optimizer, VarMap};
    use neural_fields::encoding::{FrequencyEncoding, PointEncoding};
    use neural_fields::nn::{adam, build_seeded, mlp, MlpConfig};
    use neural_fields::numerics::bce_with_logits;
    use neural_fields::rng::SplitMix64;
    let dev = Device::Cpu;
    let dtype = DType::F32;
    let shape = Torus::new([0.0; 3], 0.3, 0.12, &dev, dtype)
        .unwrap()
        .occupancy(1.0);
    let config = MlpConfig {
        hidden: 64,
        depth: 4,
        encoding: PointEncoding::Frequency(FrequencyEncoding::new(3, 4).unwrap()),
        ..MlpConfig::default()
    };
    let vm = VarMap::new();
    let net = build_seeded(&vm, dtype, &dev, 0, |vb| mlp(&config, vb)).unwrap();
    let mut opt = adam(&vm, 2e-3).unwrap();
    let mut rng = SplitMix64::new(1);
    for _ in 0..300 {
        let p = rng
            .uniform_tensor(&[4096, 3], -0.55, 0.55, dtype, &dev)
            .unwrap();
        let y = shape
            .value(&p)
            .unwrap()
            .gt(0.0)
            .unwrap()
            .to_dtype(dtype)
            .unwrap();
        let loss = bce_with_logits(&net.value(&p).unwrap(), &y)
            .unwrap()
            .mean_all()
            .unwrap();
        opt.backward_step(&loss).unwrap();
    }
    let cfg = MiseConfig {
        resolution0: 32,
        upsampling_steps: 3,
        device: dev.clone(),
        dtype,
        ..MiseConfig::new(32, 2, &Device::Cpu, DType::F32)
    };
    let t = Instant::now();
    let out = mise(&net, &cfg).unwrap();
    let t_mise = t.elapsed().as_secs_f64();
    let np = (cfg.resolution0 << cfg.upsampling_steps) + 1;
    let t = Instant::now();
    let dense = Grid::sample(&net, [np; 3], cfg.min, cfg.max, 65_536, &dev, dtype).unwrap();
    let dm = marching_cubes(&dense, 0.0, Inside::Positive).unwrap();
    let t_dense = t.elapsed().as_secs_f64();
    let m = neural_fields::occupancy::mesh_metrics(&out.mesh, &dm, 100_000, 1e-3, 0).unwrap();
    let v = surface_metrics(&out.mesh.vertices, None, &dm.vertices, None, 1e-6).unwrap();
    let dense_evals = np * np * np;
    println!(
        "trained MLP, MISE 32×2³: {} evals, {t_mise:.3} s; dense 257³: {dense_evals} evals, {t_dense:.3} s; vertex chamfer {:e}; faces {} vs {}; sampled chamfer {:e} (sampling floor)",
        out.evaluations, v.chamfer_l1, out.mesh.faces.len(), dm.faces.len(), m.chamfer_l1
    );
    assert!(v.chamfer_l1 <= 1.1e-4);
    assert!(out.evaluations * 10 <= dense_evals);
    assert!(t_mise * 5.0 <= t_dense, "{t_mise} vs {t_dense}");
}

/// Largest |‖p‖ − r| over the vertices: the distance of a sphere mesh from the sphere.
fn sphere_error(vertices: &[[f64; 3]], r: f64) -> f64 {
    vertices
        .iter()
        .map(|v| ((v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt() - r).abs())
        .fold(0.0, f64::max)
}

#[test]
fn newton_refinement_moves_vertices_onto_the_level_set() {
    let dev = Device::Cpu;
    let r = 0.37;
    // f32 stops at its rounding of the field (|p| ≈ 0.4: ulp ≈ 3e-8, the grid's
    // interpolation error at 32³ is ~1e-3); f64 reaches rounding of the field too.
    for (dtype, tol) in [(DType::F32, 1e-6), (DType::F64, 1e-13)] {
        let sphere = Sphere::new([0.0; 3], r, &dev, dtype).unwrap();
        for field in [
            Box::new(sphere.clone().sdf()) as Box<dyn ImplicitSurface>,
            Box::new(sphere.occupancy(20.0)),
        ] {
            let mut mesh = mise(
                field.as_ref(),
                &MiseConfig {
                    resolution0: 16,
                    upsampling_steps: 1,
                    device: dev.clone(),
                    dtype,
                    ..MiseConfig::new(32, 2, &Device::Cpu, DType::F32)
                },
            )
            .unwrap()
            .mesh;
            mesh.normals = Some(mesh.vertex_normals().unwrap());
            let faces = mesh.faces.clone();
            let coarse = sphere_error(&mesh.vertices, r);
            let h = 1.1 / 32.0;
            let (before, after) = refine_vertices(
                field.as_ref(),
                &mut mesh,
                &RefineConfig {
                    max_shift: 0.5 * h,
                    device: dev.clone(),
                    dtype,
                    ..RefineConfig::new(0.005, &Device::Cpu, DType::F32)
                },
            )
            .unwrap();
            let fine = sphere_error(&mesh.vertices, r);
            assert!(
                coarse > 1e-4,
                "{dtype:?}: the grid must leave an error ({coarse})"
            );
            assert!(fine < tol, "{dtype:?}: {coarse:e} -> {fine:e}");
            assert!(
                after < 1e-3 * before,
                "{dtype:?}: residual {before:e} -> {after:e}"
            );
            assert_eq!(mesh.faces, faces, "topology is kept");
            assert!(!mesh.faces.is_empty() && mesh.edge_report() == (0, 0, 0));
            let n = mesh.normals.as_ref().unwrap();
            // Recomputed normals point outwards along the position on a sphere.
            let worst = mesh
                .vertices
                .iter()
                .zip(n)
                .map(|(v, n)| {
                    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                    (v[0] * n[0] + v[1] * n[1] + v[2] * n[2]) / l
                })
                .fold(1.0, f64::min);
            assert!(worst > 0.99, "{dtype:?}: normal/position cosine {worst}");
        }
    }
}

#[test]
fn newton_refinement_clamps_the_shift_and_names_bad_settings() {
    let dev = Device::Cpu;
    let sphere = Sphere::new([0.0; 3], 0.3, &dev, DType::F64).unwrap().sdf();
    let mut mesh = mise(&sphere, &MiseConfig::new(8, 1, &dev, DType::F64))
        .unwrap()
        .mesh;
    let start = mesh.vertices.clone();
    // A field whose level set is a sphere of radius 0.2: every vertex wants to move
    // 0.1, but may move only 0.01.
    let small = Sphere::new([0.0; 3], 0.2, &dev, DType::F64).unwrap().sdf();
    let mut cfg = RefineConfig {
        max_shift: 0.01,
        device: dev.clone(),
        dtype: DType::F64,
        ..RefineConfig::new(0.005, &Device::Cpu, DType::F32)
    };
    cfg.steps = 5;
    refine_vertices(&small, &mut mesh, &cfg).unwrap();
    for (a, b) in start.iter().zip(&mesh.vertices) {
        let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
        assert!(d <= 0.01 + 1e-12, "moved {d}");
    }
    // Zero steps change nothing; bad settings name the argument.
    let mut copy = mesh.clone();
    cfg.steps = 0;
    refine_vertices(&small, &mut copy, &cfg).unwrap();
    assert_eq!(copy.vertices, mesh.vertices);
    for (bad, arg) in [
        (
            RefineConfig {
                max_shift: 0.0,
                device: dev.clone(),
                dtype: DType::F64,
                ..RefineConfig::new(0.005, &Device::Cpu, DType::F32)
            },
            "max_shift",
        ),
        (
            RefineConfig {
                max_shift: f64::NAN,
                device: dev.clone(),
                dtype: DType::F64,
                ..RefineConfig::new(0.005, &Device::Cpu, DType::F32)
            },
            "max_shift",
        ),
        (
            RefineConfig {
                chunk: 0,
                max_shift: 0.1,
                device: dev.clone(),
                dtype: DType::F64,
                ..RefineConfig::new(0.005, &Device::Cpu, DType::F32)
            },
            "chunk",
        ),
        (
            RefineConfig {
                max_shift: 0.1,
                device: dev.clone(),
                dtype: DType::U8,
                ..RefineConfig::new(0.005, &Device::Cpu, DType::F32)
            },
            "dtype",
        ),
    ] {
        let e = refine_vertices(&small, &mut copy, &bad)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with(arg), "{e}");
    }
}
