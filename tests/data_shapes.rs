//! The procedural shape collection: determinism, labels against the analytic SDF, surface
//! points and normals, voxels against labels, every category inside the cube with a
//! non-trivial volume, the write → load round trip (with views), and hostile folders.
#![cfg(feature = "data")]

use candle_core::{DType, Device, Tensor};
use neural_fields::camera::{Camera, Convention, Intrinsics};
use neural_fields::data::{
    generate_shape, load_shape_collection, write_shape_collection, write_shape_views,
    ShapeCategory, ShapeCollection, ShapeCollectionConfig, ShapeLoadConfig, Split,
};
use neural_fields::field::SignedDistance;
use neural_fields::glam::DVec3;
use neural_fields::Error;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// An empty scratch directory unique to this process and `name`.
fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir()
        .join("neural-fields-tests")
        .join(format!("shapes-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A small collection: every category, `n` shapes each.
fn small(seed: u64, n: usize) -> ShapeCollectionConfig {
    ShapeCollectionConfig {
        seed,
        shapes_per_category: n,
        uniform_points: 2_000,
        near_points: 500,
        surface_points: 1_000,
        voxel_resolution: 16,
        ..ShapeCollectionConfig::default()
    }
}

fn load_all(dir: &Path) -> ShapeCollection {
    load_shape_collection(dir, &ShapeLoadConfig::default()).unwrap()
}

/// Every file under `dir`, by relative path, with its bytes.
fn files(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p.strip_prefix(dir).unwrap().to_string_lossy().into_owned();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

/// `d` at flat points `[N·3]`, from the shape rebuilt in `dtype`.
fn distances(category: ShapeCategory, seed: u64, points: &[f32], dtype: DType) -> Vec<f64> {
    let shape = generate_shape(category, seed, &Device::Cpu, dtype).unwrap();
    let p = Tensor::from_slice(points, (points.len() / 3, 3), &Device::Cpu)
        .unwrap()
        .to_dtype(dtype)
        .unwrap();
    let (d, _) = shape.distance_and_grad(&p).unwrap();
    d.to_dtype(DType::F64).unwrap().to_vec1::<f64>().unwrap()
}

/// The format error's `(path, field)`, or a panic naming what came instead.
fn format_error<T>(result: neural_fields::Result<T>) -> (String, String, String) {
    match result {
        Err(Error::Format {
            path, field, got, ..
        }) => (path, field, got),
        Err(other) => panic!("expected a format error, got {other}"),
        Ok(_) => panic!("expected a format error, got Ok"),
    }
}

#[test]
fn same_seed_same_bytes_other_seed_other_bytes() {
    let (a, b, c) = (scratch("seed-a"), scratch("seed-b"), scratch("seed-c"));
    let infos = write_shape_collection(&a, &small(3, 2)).unwrap();
    assert_eq!(infos.len(), 10);
    write_shape_collection(&b, &small(3, 2)).unwrap();
    write_shape_collection(&c, &small(4, 2)).unwrap();
    let (fa, fb, fc) = (files(&a), files(&b), files(&c));
    assert_eq!(fa.len(), 11, "{:?}", fa.keys());
    assert_eq!(fa, fb, "the same seed wrote different bytes");
    assert_eq!(fa.keys().collect::<Vec<_>>(), fc.keys().collect::<Vec<_>>());
    for (name, bytes) in &fa {
        assert_ne!(bytes, &fc[name], "{name} is the same under another seed");
    }
}

#[test]
fn labels_agree_with_the_sdf_sign() {
    let dir = scratch("labels");
    write_shape_collection(&dir, &small(11, 2)).unwrap();
    let data = load_all(&dir);
    assert_eq!(data.shapes.len(), 10);
    for s in &data.shapes {
        let (cat, seed) = (s.info.category, s.info.seed);
        for (points, labels) in [
            (&s.uniform_points, &s.uniform_occupancy),
            (&s.near_points, &s.near_occupancy),
        ] {
            // Exactly the f32 evaluation the format fixes …
            let d32 = distances(cat, seed, points, DType::F32);
            for (i, (&d, &l)) in d32.iter().zip(labels.iter()).enumerate() {
                assert_eq!(l, u8::from(d < 0.0), "{cat} {seed}: point {i}, d = {d}");
            }
            // … and the f64 sign wherever the point is not within rounding of the surface.
            let d64 = distances(cat, seed, points, DType::F64);
            for (i, (&d, &l)) in d64.iter().zip(labels.iter()).enumerate() {
                if d.abs() > 1e-5 {
                    assert_eq!(l, u8::from(d < 0.0), "{cat} {seed}: point {i}, d = {d}");
                }
            }
        }
        let inside = s.near_occupancy.iter().filter(|&&l| l == 1).count();
        let frac = inside as f64 / s.near_occupancy.len() as f64;
        assert!(
            (0.2..0.8).contains(&frac),
            "{cat} {seed}: {frac} of the near points inside"
        );
    }
}

#[test]
fn surface_points_lie_on_the_surface_with_outward_unit_normals() {
    let dir = scratch("surface");
    write_shape_collection(&dir, &small(5, 2)).unwrap();
    for s in &load_all(&dir).shapes {
        let (cat, seed) = (s.info.category, s.info.seed);
        let shape = generate_shape(cat, seed, &Device::Cpu, DType::F64).unwrap();
        let n = s.surface_points.len() / 3;
        assert_eq!(n, 1_000);
        let p = Tensor::from_slice(&s.surface_points, (n, 3), &Device::Cpu)
            .unwrap()
            .to_dtype(DType::F64)
            .unwrap();
        let normals = Tensor::from_slice(&s.surface_normals, (n, 3), &Device::Cpu)
            .unwrap()
            .to_dtype(DType::F64)
            .unwrap();
        let (d, g) = shape.distance_and_grad(&p).unwrap();
        let d = d.to_vec1::<f64>().unwrap();
        let g = g.to_vec2::<f64>().unwrap();
        let nv = normals.to_vec2::<f64>().unwrap();
        for i in 0..n {
            assert!(d[i].abs() < 2e-4, "{cat} {seed}: point {i}: d = {}", d[i]);
            let len = nv[i].iter().map(|x| x * x).sum::<f64>().sqrt();
            assert!((len - 1.0).abs() < 1e-5, "{cat} {seed}: |n| = {len}");
            let gl = g[i].iter().map(|x| x * x).sum::<f64>().sqrt();
            let cos = (0..3).map(|a| nv[i][a] * g[i][a]).sum::<f64>() / gl;
            assert!(cos > 0.99, "{cat} {seed}: point {i}: n·∇d/‖∇d‖ = {cos}");
            assert!(s.surface_points[3 * i..3 * i + 3]
                .iter()
                .all(|x| x.abs() <= 0.5 + 1e-4));
        }
        // Outward: a step along the normal leaves the shape, a step against it enters.
        let eps = 1e-3;
        let out = (&p + (&normals * eps).unwrap()).unwrap();
        let inw = (&p - (&normals * eps).unwrap()).unwrap();
        let d_out = shape
            .distance_and_grad(&out)
            .unwrap()
            .0
            .to_vec1::<f64>()
            .unwrap();
        let d_in = shape
            .distance_and_grad(&inw)
            .unwrap()
            .0
            .to_vec1::<f64>()
            .unwrap();
        let wrong = (0..n)
            .filter(|&i| d_out[i] <= 0.0 || d_in[i] >= 0.0)
            .count();
        assert!(
            wrong == 0,
            "{cat} {seed}: {wrong} of {n} normals not outward"
        );
    }
}

#[test]
fn voxels_agree_with_the_labels() {
    let dir = scratch("voxels");
    let config = small(9, 2);
    write_shape_collection(&dir, &config).unwrap();
    let r = config.voxel_resolution;
    let voxel = |p: &[f32]| -> Option<usize> {
        let idx: Vec<usize> = p
            .iter()
            .map(|&x| ((f64::from(x) + 0.5) * r as f64).floor())
            .filter(|&i| (0.0..r as f64).contains(&i))
            .map(|i| i as usize)
            .collect();
        (idx.len() == 3).then(|| (idx[0] * r + idx[1]) * r + idx[2])
    };
    for s in &load_all(&dir).shapes {
        assert_eq!(s.voxels.len(), r * r * r);
        // Every inside point, and every surface point, lies in an occupied cell.
        for (points, labels) in [
            (&s.uniform_points, &s.uniform_occupancy),
            (&s.near_points, &s.near_occupancy),
        ] {
            for (i, p) in points.chunks(3).enumerate() {
                if labels[i] == 1 {
                    let v = voxel(p).expect("inside points lie in the unit cube");
                    assert_eq!(
                        s.voxels[v], 1,
                        "{}: inside point {p:?} in an empty cell",
                        s.info.category
                    );
                }
            }
        }
        for p in s.surface_points.chunks(3) {
            if let Some(v) = voxel(p) {
                assert_eq!(s.voxels[v], 1, "surface point {p:?} in an empty cell");
            }
        }
        // Cells whose centre is inside are occupied; cells far outside are empty.
        let centre = |i: usize| (-0.5 + (i as f64 + 0.5) / r as f64) as f32;
        let mut centres = Vec::new();
        for i in 0..r {
            for j in 0..r {
                for k in 0..r {
                    centres.extend([centre(i), centre(j), centre(k)]);
                }
            }
        }
        let d = distances(s.info.category, s.info.seed, &centres, DType::F32);
        let half_diagonal = 0.5 * 3f64.sqrt() / r as f64;
        for (v, &dv) in d.iter().enumerate() {
            if dv < 0.0 {
                assert_eq!(s.voxels[v], 1);
            }
            if dv > half_diagonal + 1e-6 {
                assert_eq!(s.voxels[v], 0);
            }
        }
        // The voxel fraction is near the inside fraction of the uniform points in the cube.
        let filled = s.voxels.iter().filter(|&&v| v == 1).count() as f64 / (r * r * r) as f64;
        assert!(filled > 0.0 && filled < 0.9, "{filled}");
    }
}

#[test]
fn every_category_fits_the_cube_with_a_nontrivial_volume() {
    let dir = scratch("volume");
    let config = ShapeCollectionConfig {
        seed: 21,
        shapes_per_category: 40,
        uniform_points: 4_000,
        near_points: 0,
        surface_points: 400,
        voxel_resolution: 8,
        ..ShapeCollectionConfig::default()
    };
    write_shape_collection(&dir, &config).unwrap();
    let data = load_all(&dir);
    let mut report = BTreeMap::new();
    let mut outside = Vec::new();
    for s in &data.shapes {
        let cat = s.info.category;
        let inside = s.uniform_occupancy.iter().filter(|&&l| l == 1).count();
        let frac = inside as f64 / s.uniform_occupancy.len() as f64;
        let e = report
            .entry(cat.to_string())
            .or_insert((1.0f64, 0.0f64, 9.0f32));
        *e = (e.0.min(frac), e.1.max(frac), e.2);
        if !(0.015..0.6).contains(&frac) {
            outside.push(format!("{cat} (seed {}): {frac}", s.info.seed));
        }
        // Nothing inside the padding: the shape fits [−0.5, 0.5]³.
        for (p, &l) in s.uniform_points.chunks(3).zip(&s.uniform_occupancy) {
            if l == 1 {
                assert!(p.iter().all(|x| x.abs() <= 0.5), "{cat}: {p:?} inside");
            }
        }
        // Normalised: the surface's extent along its longest axis is close to 1.
        let extent = (0..3)
            .map(|a| {
                let v = s.surface_points.iter().skip(a).step_by(3);
                let (lo, hi) = v.fold((f32::MAX, f32::MIN), |(lo, hi), &x| (lo.min(x), hi.max(x)));
                hi - lo
            })
            .fold(0.0f32, f32::max);
        assert!(
            extent > 0.85 && extent <= 1.0 + 1e-3,
            "{cat} (seed {}): extent {extent}",
            s.info.seed
        );
        if let Some(e) = report.get_mut(&cat.to_string()) {
            e.2 = e.2.min(extent);
        }
    }
    println!("occupancy fraction (min, max) and least extent per category: {report:?}");
    assert!(
        outside.is_empty(),
        "occupancy fractions outside [1.5 %, 60 %]: {outside:#?}"
    );
}

#[test]
fn splits_are_seeded_per_category() {
    let config = ShapeCollectionConfig {
        seed: 2,
        shapes_per_category: 10,
        uniform_points: 16,
        near_points: 16,
        surface_points: 16,
        voxel_resolution: 4,
        ..ShapeCollectionConfig::default()
    };
    let dir = scratch("split");
    let infos = write_shape_collection(&dir, &config).unwrap();
    for (c, &cat) in config.categories.iter().enumerate() {
        let of = |s: Split| {
            infos[c * 10..(c + 1) * 10]
                .iter()
                .filter(|i| i.split == s && i.category == cat)
                .count()
        };
        assert_eq!(
            (of(Split::Train), of(Split::Val), of(Split::Test)),
            (7, 1, 2)
        );
    }
    let again = write_shape_collection(&scratch("split-again"), &config).unwrap();
    assert_eq!(infos, again);
    let other = write_shape_collection(
        &scratch("split-other"),
        &ShapeCollectionConfig {
            seed: 3,
            ..config.clone()
        },
    )
    .unwrap();
    assert_ne!(
        infos.iter().map(|i| i.split).collect::<Vec<_>>(),
        other.iter().map(|i| i.split).collect::<Vec<_>>()
    );
    for split in [Split::Train, Split::Val, Split::Test] {
        let part = load_shape_collection(
            &dir,
            &ShapeLoadConfig {
                split,
                ..Default::default()
            },
        )
        .unwrap();
        assert!(part.shapes.iter().all(|s| s.info.split == split));
        assert_eq!(
            part.shapes.len(),
            infos.iter().filter(|i| i.split == split).count()
        );
    }
}

#[test]
fn round_trip_with_views_and_safetensors_readers() {
    let dir = scratch("round-trip");
    let config = small(17, 1);
    let infos = write_shape_collection(&dir, &config).unwrap();
    let k = Intrinsics::new(20.0, 21.0, 6.5, 4.0, 12, 8).unwrap();
    let cams: Vec<Camera> = [(0.0, 2.0), (2.0, 0.5)]
        .iter()
        .map(|&(x, z)| {
            Camera::look_at(
                k,
                DVec3::new(x, 0.7, z),
                DVec3::ZERO,
                DVec3::Y,
                Convention::OpenGl,
            )
            .unwrap()
        })
        .collect();
    let bytes: Vec<u8> = (0..8 * 12 * 3).map(|i| (i * 7 % 256) as u8).collect();
    let u8_image = Tensor::from_vec(bytes.clone(), (8, 12, 3), &Device::Cpu).unwrap();
    let f32_image = (u8_image.to_dtype(DType::F32).unwrap() / 255.0).unwrap();
    write_shape_views(&dir, 3, &[(cams[0], u8_image), (cams[1], f32_image)]).unwrap();
    let data = load_all(&dir);
    assert_eq!(data.config, config);
    assert_eq!(
        data.shapes.iter().map(|s| s.info).collect::<Vec<_>>(),
        infos
    );
    for s in &data.shapes {
        // The arrays equal what candle's own safetensors reader sees in the file.
        let file = dir.join(format!("shapes/{:05}/shape.safetensors", s.info.index));
        let t = candle_core::safetensors::load(&file, &Device::Cpu).unwrap();
        let f = |name: &str| t[name].flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let b = |name: &str| t[name].flatten_all().unwrap().to_vec1::<u8>().unwrap();
        assert_eq!(f("uniform_points"), s.uniform_points);
        assert_eq!(f("near_points"), s.near_points);
        assert_eq!(f("surface_points"), s.surface_points);
        assert_eq!(f("surface_normals"), s.surface_normals);
        assert_eq!(b("uniform_occupancy"), s.uniform_occupancy);
        assert_eq!(b("near_occupancy"), s.near_occupancy);
        assert_eq!(b("voxels"), s.voxels);
        assert_eq!(t["voxels"].dims(), &[16, 16, 16]);
        assert_eq!(s.views.len(), if s.info.index == 3 { 2 } else { 0 });
    }
    let views = &data.shapes[3].views;
    for (v, cam) in views.iter().zip(&cams) {
        assert_eq!(v.image.size(), (12, 8, 3));
        assert_eq!(v.image.data(), &bytes[..]);
        assert_eq!(v.camera.intrinsics(), cam.intrinsics());
        assert_eq!(v.camera.convention(), Convention::OpenGl);
        let (a, b) = (v.camera.cam_to_world(), cam.cam_to_world());
        assert!(a.abs_diff_eq(b, 1e-12), "{a:?} vs {b:?}");
    }
    // Without views, none are read.
    let bare = load_shape_collection(
        &dir,
        &ShapeLoadConfig {
            views: false,
            ..Default::default()
        },
    )
    .unwrap();
    assert!(bare.shapes.iter().all(|s| s.views.is_empty()));
    // Bad views are refused, naming the argument.
    let wrong = Tensor::zeros((8, 11, 3), DType::U8, &Device::Cpu).unwrap();
    for (result, arg) in [
        (write_shape_views(&dir, 3, &[(cams[0], wrong)]), "views"),
        (write_shape_views(&dir, 3, &[]), "views"),
        (write_shape_views(&dir, 99, &[]), "shape"),
    ] {
        match result {
            Err(Error::InvalidArgument { arg: a, .. }) => assert_eq!(a, arg),
            other => panic!("expected an error naming {arg}, got {other:?}"),
        }
    }
}

#[test]
fn bad_parameters_are_refused_by_name() {
    let dir = scratch("bad-params");
    let base = small(1, 1);
    let cases: Vec<(ShapeCollectionConfig, &str)> = vec![
        (
            ShapeCollectionConfig {
                shapes_per_category: 0,
                ..base.clone()
            },
            "config.shapes_per_category",
        ),
        (
            ShapeCollectionConfig {
                categories: vec![],
                ..base.clone()
            },
            "config.categories",
        ),
        (
            ShapeCollectionConfig {
                categories: vec![ShapeCategory::Mug, ShapeCategory::Mug],
                ..base.clone()
            },
            "config.categories",
        ),
        (
            ShapeCollectionConfig {
                near_sigmas: vec![0.01, -1.0],
                ..base.clone()
            },
            "config.near_sigmas",
        ),
        (
            ShapeCollectionConfig {
                near_sigmas: vec![f64::NAN],
                ..base.clone()
            },
            "config.near_sigmas",
        ),
        (
            ShapeCollectionConfig {
                near_sigmas: vec![],
                ..base.clone()
            },
            "config.near_sigmas",
        ),
        (
            ShapeCollectionConfig {
                padding: 2.0,
                ..base.clone()
            },
            "config.padding",
        ),
        (
            ShapeCollectionConfig {
                padding: f64::NAN,
                ..base.clone()
            },
            "config.padding",
        ),
        (
            ShapeCollectionConfig {
                test_fraction: 0.7,
                val_fraction: 0.4,
                ..base.clone()
            },
            "config.test_fraction",
        ),
        (
            ShapeCollectionConfig {
                val_fraction: -0.1,
                ..base.clone()
            },
            "config.val_fraction",
        ),
        (
            ShapeCollectionConfig {
                voxel_resolution: 0,
                ..base.clone()
            },
            "config.voxel_resolution",
        ),
        (
            ShapeCollectionConfig {
                voxel_resolution: 1 << 20,
                ..base.clone()
            },
            "config.voxel_resolution",
        ),
        (
            ShapeCollectionConfig {
                uniform_points: 1 << 40,
                ..base.clone()
            },
            "config.uniform_points",
        ),
        (
            ShapeCollectionConfig {
                surface_points: 0,
                ..base.clone()
            },
            "config.surface_points",
        ),
        (
            ShapeCollectionConfig {
                shapes_per_category: usize::MAX,
                ..base.clone()
            },
            "config.shapes_per_category",
        ),
    ];
    for (config, want) in cases {
        match write_shape_collection(&dir, &config) {
            Err(Error::InvalidArgument { arg, .. }) => assert_eq!(arg, want),
            other => panic!("{want}: expected an error naming it, got {other:?}"),
        }
    }
    assert!(!dir.join("manifest.json").exists());
    match generate_shape(ShapeCategory::Chair, 0, &Device::Cpu, DType::U8) {
        Err(Error::InvalidArgument { arg, .. }) => assert_eq!(arg, "dtype"),
        other => panic!("{other:?}"),
    }
}

/// A one-shape collection (a mug) for the hostile cases, and its shape file.
fn one_mug(name: &str) -> (PathBuf, PathBuf) {
    let dir = scratch(name);
    let config = ShapeCollectionConfig {
        categories: vec![ShapeCategory::Mug],
        shapes_per_category: 1,
        uniform_points: 100,
        near_points: 50,
        surface_points: 50,
        voxel_resolution: 4,
        ..ShapeCollectionConfig::default()
    };
    write_shape_collection(&dir, &config).unwrap();
    let file = dir.join("shapes/00000/shape.safetensors");
    (dir, file)
}

fn edit_json(path: &Path, f: impl FnOnce(&mut serde_json::Value)) {
    let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(path, v.to_string()).unwrap();
}

/// Replaces the JSON header of a safetensors file with `f(header)`, padded to 8 bytes.
fn edit_header(path: &Path, f: impl FnOnce(&mut serde_json::Value)) {
    let bytes = std::fs::read(path).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    f(&mut header);
    let mut text = header.to_string();
    while !text.len().is_multiple_of(8) {
        text.push(' ');
    }
    let mut out = (text.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(text.as_bytes());
    out.extend_from_slice(&bytes[8 + n..]);
    std::fs::write(path, out).unwrap();
}

/// An edit of a JSON file, for the hostile cases.
type Edit<'a> = Box<dyn Fn(&mut serde_json::Value) + 'a>;

fn load_err(dir: &Path) -> (String, String, String) {
    format_error(load_shape_collection(dir, &ShapeLoadConfig::default()))
}

#[test]
fn hostile_truncated_shape_file() {
    let (dir, file) = one_mug("hostile-truncated");
    let bytes = std::fs::read(&file).unwrap();
    std::fs::write(&file, &bytes[..bytes.len() - 10]).unwrap();
    let (path, field, _) = load_err(&dir);
    assert!(path.ends_with("shape.safetensors"), "{path}");
    assert!(
        field.ends_with("data_offsets") || field == "data",
        "{field}"
    );
    // Cut inside the header length itself.
    std::fs::write(&file, &bytes[..5]).unwrap();
    let (path, field, _) = load_err(&dir);
    assert!(
        path.ends_with("shape.safetensors") && field == "header size",
        "{path} {field}"
    );
    // Bytes appended past the arrays.
    let mut longer = bytes.clone();
    longer.extend_from_slice(&[0; 16]);
    std::fs::write(&file, &longer).unwrap();
    let (path, field, _) = load_err(&dir);
    assert!(
        path.ends_with("shape.safetensors") && field == "data",
        "{path} {field}"
    );
}

#[test]
fn hostile_header_claiming_2_pow_40_points() {
    let (dir, file) = one_mug("hostile-huge-header");
    edit_header(&file, |h| {
        h["uniform_points"]["shape"] = serde_json::json!([1u64 << 40, 3]);
        h["uniform_points"]["data_offsets"] = serde_json::json!([0, 12u64 << 40]);
    });
    let (path, field, got) = load_err(&dir);
    assert!(path.ends_with("shape.safetensors"), "{path}");
    assert_eq!(field, "uniform_points.shape");
    assert!(got.contains("1099511627776"), "{got}");
    // Offsets alone lying (shape right, span wrong) are refused too.
    let (dir, file) = one_mug("hostile-offsets");
    edit_header(&file, |h| {
        h["voxels"]["data_offsets"] = serde_json::json!([0, 1u64 << 40]);
    });
    let (path, field, _) = load_err(&dir);
    assert!(
        path.ends_with("shape.safetensors") && field == "voxels.data_offsets",
        "{path} {field}"
    );
    // A header length of 2⁴⁰ bytes.
    let bytes = std::fs::read(&file).unwrap();
    let mut lie = bytes.clone();
    lie[..8].copy_from_slice(&(1u64 << 40).to_le_bytes());
    std::fs::write(&file, lie).unwrap();
    let (path, field, _) = load_err(&dir);
    assert!(
        path.ends_with("shape.safetensors") && field == "header size",
        "{path} {field}"
    );
}

#[test]
fn hostile_manifest_claiming_2_pow_40_points_or_a_budget_overrun() {
    let (dir, _) = one_mug("hostile-huge-manifest");
    let manifest = dir.join("manifest.json");
    edit_json(&manifest, |m| {
        m["uniform_points"] = serde_json::json!(1u64 << 40)
    });
    let (path, field, _) = load_err(&dir);
    assert!(path.ends_with("manifest.json"), "{path}");
    assert_eq!(field, "uniform_points");
    // Within the allocation limit but past the load's budget.
    edit_json(&manifest, |m| {
        m["uniform_points"] = serde_json::json!(1u64 << 29)
    });
    let (path, field, _) = load_err(&dir);
    assert!(
        path.ends_with("manifest.json") && field == "shapes",
        "{path} {field}"
    );
    let (dir, _) = one_mug("hostile-budget");
    let tight = ShapeLoadConfig {
        max_bytes: 1000,
        ..Default::default()
    };
    let (path, field, _) = format_error(load_shape_collection(&dir, &tight));
    assert!(
        path.ends_with("manifest.json") && field == "shapes",
        "{path} {field}"
    );
}

#[test]
fn hostile_paths_escaping_the_folder() {
    let (dir, file) = one_mug("hostile-escape");
    // A copy of the shape file beside the folder, named by `..`.
    let outside = dir
        .parent()
        .unwrap()
        .join(format!("escaped-{}.safetensors", std::process::id()));
    std::fs::copy(&file, &outside).unwrap();
    let manifest = dir.join("manifest.json");
    let name = format!("../{}", outside.file_name().unwrap().to_string_lossy());
    edit_json(&manifest, |m| {
        m["shapes"][0]["file"] = serde_json::json!(name)
    });
    let (path, field, got) = load_err(&dir);
    assert!(path.ends_with("manifest.json"), "{path}");
    assert_eq!(field, "shapes[0].file");
    assert!(got.contains("escaped-"), "{got}");
    // An absolute path, and a symlink inside the folder that points outside.
    edit_json(&manifest, |m| {
        m["shapes"][0]["file"] = serde_json::json!("/etc/passwd")
    });
    assert_eq!(load_err(&dir).1, "shapes[0].file");
    #[cfg(unix)]
    {
        edit_json(&manifest, |m| {
            m["shapes"][0]["file"] = serde_json::json!("shapes/00000/shape.safetensors")
        });
        std::fs::remove_file(&file).unwrap();
        std::os::unix::fs::symlink(&outside, &file).unwrap();
        assert_eq!(load_err(&dir).1, "shapes[0].file");
    }
    std::fs::remove_file(&outside).unwrap();
}

#[test]
fn hostile_views() {
    let (dir, _) = one_mug("hostile-views");
    let k = Intrinsics::new(8.0, 8.0, 2.0, 2.0, 4, 4).unwrap();
    let cam = Camera::look_at(
        k,
        DVec3::new(0.0, 0.0, 2.0),
        DVec3::ZERO,
        DVec3::Y,
        Convention::OpenCv,
    )
    .unwrap();
    let image = Tensor::zeros((4, 4, 3), DType::U8, &Device::Cpu).unwrap();
    write_shape_views(&dir, 0, &[(cam, image)]).unwrap();
    assert_eq!(load_all(&dir).shapes[0].views.len(), 1);
    let cameras = dir.join("shapes/00000/views/cameras.json");
    let original = std::fs::read(&cameras).unwrap();
    let secret = dir
        .parent()
        .unwrap()
        .join(format!("secret-{}.png", std::process::id()));
    std::fs::copy(dir.join("shapes/00000/views/000.png"), &secret).unwrap();
    let cases: Vec<(Edit, &str)> = vec![
        (
            Box::new(|v| {
                v["views"][0]["file"] = serde_json::json!(format!(
                    "../../../../{}",
                    secret.file_name().unwrap().to_string_lossy()
                ))
            }),
            "views[0].file",
        ),
        (
            Box::new(|v| v["shape_seed"] = serde_json::json!(12345)),
            "shape_seed",
        ),
        (
            Box::new(|v| v["format_version"] = serde_json::json!(2)),
            "format_version",
        ),
        (
            Box::new(|v| v["views"][0]["width"] = serde_json::json!(5)),
            "image size",
        ),
        (
            Box::new(|v| v["views"][0]["fx"] = serde_json::json!(1e300)),
            "views[0].fx",
        ),
        (
            Box::new(|v| {
                v["views"][0]["camera_to_world"][0] = serde_json::json!([2.0, 0.0, 0.0, 0.0])
            }),
            "views[0].camera_to_world",
        ),
        (
            Box::new(|v| v["views"][0]["convention"] = serde_json::json!("directx")),
            "views[0].convention",
        ),
    ];
    for (edit, want) in cases {
        std::fs::write(&cameras, &original).unwrap();
        edit_json(&cameras, |v| edit(v));
        let (path, field, _) = load_err(&dir);
        assert_eq!(field, want, "{path}");
        assert!(
            path.ends_with("cameras.json") || path.ends_with(".png"),
            "{path}"
        );
    }
    std::fs::write(&cameras, &original).unwrap();
    let few = ShapeLoadConfig {
        max_views: 0,
        ..Default::default()
    };
    assert_eq!(format_error(load_shape_collection(&dir, &few)).1, "views");
    std::fs::remove_file(&secret).unwrap();
}

#[test]
fn hostile_manifests() {
    let (dir, file) = one_mug("hostile-manifest");
    let manifest = dir.join("manifest.json");
    let original = std::fs::read(&manifest).unwrap();
    let cases: Vec<(Edit, &str)> = vec![
        (
            Box::new(|m| m["format_version"] = serde_json::json!(2)),
            "format_version",
        ),
        (
            Box::new(|m| m["format"] = serde_json::json!("something else")),
            "format",
        ),
        (
            Box::new(|m| m["categories"][0] = serde_json::json!("sofa")),
            "categories[0]",
        ),
        (
            Box::new(|m| m["shapes_per_category"] = serde_json::json!(2)),
            "shapes",
        ),
        (
            Box::new(|m| m["near_sigmas"] = serde_json::json!([0.01, "x"])),
            "near_sigmas[1]",
        ),
        (
            Box::new(|m| m["padding"] = serde_json::json!(-3)),
            "padding",
        ),
        (
            Box::new(|m| m["split_fractions"]["test"] = serde_json::json!(1.5)),
            "split_fractions.test",
        ),
        (
            Box::new(|m| m["shapes"][0]["split"] = serde_json::json!("holdout")),
            "shapes[0].split",
        ),
        (
            Box::new(|m| m["shapes"][0]["category"] = serde_json::json!("chair")),
            "shapes[0].category",
        ),
        (
            Box::new(|m| m["shapes"][0]["seed"] = serde_json::json!(-1)),
            "shapes[0].seed",
        ),
        (
            Box::new(|m| m["shapes"][0]["seed"] = serde_json::json!(7)),
            "__metadata__.seed",
        ),
        (
            Box::new(|m| m["near_points"] = serde_json::json!(51)),
            "near_points.shape",
        ),
        (
            Box::new(|m| {
                m.as_object_mut()
                    .unwrap()
                    .remove("seed")
                    .map(|_| ())
                    .unwrap()
            }),
            "seed",
        ),
    ];
    for (edit, want) in cases {
        std::fs::write(&manifest, &original).unwrap();
        edit_json(&manifest, |m| edit(m));
        let (path, field, _) = load_err(&dir);
        assert_eq!(field, want, "{path}");
        let file_named =
            if want.contains('.') && !want.starts_with("shapes") && !want.starts_with("split") {
                "shape.safetensors"
            } else {
                "manifest.json"
            };
        assert!(path.ends_with(file_named), "{want}: {path}");
    }
    // Not JSON, and deeply nested JSON.
    std::fs::write(&manifest, b"{\"format\": ").unwrap();
    assert_eq!(load_err(&dir).1, "JSON");
    std::fs::write(&manifest, "[".repeat(100_000)).unwrap();
    assert_eq!(load_err(&dir).1, "JSON");
    // A NaN point and a label 2 in the shape file.
    std::fs::write(&manifest, &original).unwrap();
    let clean = std::fs::read(&file).unwrap();
    let n = u64::from_le_bytes(clean[..8].try_into().unwrap()) as usize;
    let mut bad = clean.clone();
    bad[8 + n..8 + n + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&file, &bad).unwrap();
    assert_eq!(load_err(&dir).1, "near_points");
    let mut bad = clean.clone();
    let last = bad.len() - 1;
    bad[last] = 2;
    std::fs::write(&file, &bad).unwrap();
    assert_eq!(load_err(&dir).1, "voxels");
    // A missing manifest is an I/O error naming it.
    std::fs::remove_file(&manifest).unwrap();
    match load_shape_collection(&dir, &ShapeLoadConfig::default()) {
        Err(Error::Io { path, .. }) => assert!(path.ends_with("manifest.json"), "{path}"),
        other => panic!("{other:?}"),
    }
}

/// The timing of the default collection (5 categories × 20 shapes, 10 000 points each):
/// `cargo test --test data_shapes -- --ignored --nocapture`.
#[test]
#[ignore = "timing: run by hand"]
fn default_collection_timing() {
    let dir = scratch("timing");
    let start = std::time::Instant::now();
    write_shape_collection(&dir, &ShapeCollectionConfig::default()).unwrap();
    println!(
        "default collection (5 × 20 shapes, 10k uniform / 10k near / 10k surface points, 32³ voxels): {:.1} s",
        start.elapsed().as_secs_f64()
    );
}
