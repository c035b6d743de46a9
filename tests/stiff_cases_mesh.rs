//! Stiff cases of the mesh types: point clouds and meshes at extreme scales, through
//! every file format.

#![cfg(feature = "occupancy")]

mod common;

use candle_core::{DType, Device, Tensor};

use common::stiff::{Expect, Suite, DTYPES};

#[test]
fn point_clouds_stay_finite() {
    let mut s = Suite::default();
    sweep_point_clouds(&mut s);
    s.finish("point clouds", POINT_CLOUDS);
}

#[test]
fn meshes_stay_finite() {
    let mut s = Suite::default();
    sweep_meshes(&mut s);
    s.finish("meshes", MESHES);
}

#[test]
fn every_public_mesh_function_is_swept_or_exempt() {
    common::stiff::check_coverage(
        "stiff_cases_mesh",
        &[POINT_CLOUDS, MESHES],
        EXEMPT,
        &[],
        &[],
    );
}

/// Items swept by `sweep_point_clouds`.
const POINT_CLOUDS: &[&str] = &[
    "occupancy::Mesh::from_bytes",
    "occupancy::PointCloud::from_bytes",
    "occupancy::PointCloud::load",
    "occupancy::PointCloud::new",
    "occupancy::PointCloud::normals_tensor",
    "occupancy::PointCloud::sample",
    "occupancy::PointCloud::save",
    "occupancy::PointCloud::to_bytes",
    "occupancy::PointCloud::to_tensor",
    "occupancy::PointCloud::with_colors",
    "occupancy::PointCloud::with_normals",
];

/// Items swept by `sweep_meshes`.
const MESHES: &[&str] = &[
    "occupancy::Mesh::from_bytes",
    "occupancy::Mesh::load",
    "occupancy::Mesh::new",
    "occupancy::Mesh::normalize_unit_cube",
    "occupancy::Mesh::sample_surface",
    "occupancy::Mesh::save",
    "occupancy::Mesh::to_bytes",
    "occupancy::Mesh::validate",
    "occupancy::Mesh::with_colors",
    "occupancy::points_tensor",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    ("occupancy::PointCloud::points", "getter"),
    ("occupancy::PointCloud::normals", "getter"),
    ("occupancy::PointCloud::colors", "getter"),
    ("occupancy::PointCloud::len", "getter"),
    ("occupancy::PointCloud::is_empty", "getter"),
    (
        "occupancy::MeshFormat::from_path",
        "an extension; no float input",
    ),
    (
        "occupancy::Polygons::iter",
        "crate-private reader, swept via Mesh::from_bytes and PointCloud::from_bytes",
    ),
    (
        "occupancy::Polygons::len",
        "crate-private reader, swept via Mesh::from_bytes and PointCloud::from_bytes",
    ),
    (
        "occupancy::Polygons::push",
        "crate-private reader, swept via Mesh::from_bytes and PointCloud::from_bytes",
    ),
    (
        "occupancy::Soup::locate",
        "crate-private reader, swept via Mesh::from_bytes",
    ),
    (
        "occupancy::ObjContent::",
        "crate-private reader, swept via Mesh::from_bytes",
    ),
    (
        "occupancy::Mesh::bounds",
        "swept through normalize_unit_cube",
    ),
    ("occupancy::Mesh::edge_report", "integer topology"),
    ("occupancy::Mesh::face_areas", "swept through Mesh::new"),
    ("occupancy::Mesh::face_normals", "swept through Mesh::new"),
    (
        "occupancy::Mesh::is_watertight_and_oriented",
        "integer topology",
    ),
    ("occupancy::Mesh::signed_volume", "swept through Mesh::new"),
    ("occupancy::Mesh::vertex_normals", "swept through Mesh::new"),
];

/// Point clouds at three scales through their constructors, sampling, tensors and files,
/// and the mesh formats' round trips.
fn sweep_point_clouds(s: &mut Suite) {
    use neural_fields::occupancy::{Mesh, MeshFormat, PointCloud};
    let d = Device::Cpu;
    let flat = |v: &[[f64; 3]]| Tensor::from_vec(v.concat(), v.len() * 3, &d);
    for scale in [1e-300, 1e-6, 1.0, 1e6, 1e300] {
        let label = format!("scale {scale:e}");
        let pts = vec![[0.0, 0.0, 0.0], [scale, 0.0, 0.0], [0.0, scale, -scale]];
        let normals = vec![[0.0, 0.0, scale]; 3];
        s.case(
            "occupancy::PointCloud::new",
            &label,
            Expect::Finite,
            &[],
            || Ok(vec![flat(PointCloud::new(pts.clone())?.points())?]),
        );
        s.case(
            "occupancy::PointCloud::with_normals",
            &label,
            Expect::Finite,
            &[],
            || {
                let c = PointCloud::new(pts.clone())?.with_normals(normals.clone())?;
                Ok(vec![flat(c.normals().unwrap_or(&[]))?])
            },
        );
        s.case(
            "occupancy::PointCloud::with_colors",
            &label,
            Expect::Finite,
            &[],
            || {
                let c = PointCloud::new(pts.clone())?.with_colors(vec![[0.0, 0.5, 1.0]; 3])?;
                Ok(vec![flat(c.colors().unwrap_or(&[]))?])
            },
        );
        let cloud = PointCloud::new(pts.clone())
            .unwrap()
            .with_normals(normals.clone())
            .unwrap();
        s.case(
            "occupancy::PointCloud::sample",
            &label,
            Expect::Finite,
            &[],
            || Ok(vec![flat(cloud.sample(7, 1)?.points())?]),
        );
        for dtype in DTYPES {
            // f32 overflows beyond 3.4e38: an infinite tensor would be a silent result.
            let expect = if dtype == DType::F32 && scale > 1e38 {
                Expect::FiniteOrErr
            } else {
                Expect::Finite
            };
            s.case(
                "occupancy::PointCloud::to_tensor",
                format!("{label}, {dtype:?}"),
                expect,
                &[],
                || Ok(vec![cloud.to_tensor(&d, dtype)?]),
            );
            s.case(
                "occupancy::PointCloud::normals_tensor",
                format!("{label}, {dtype:?}"),
                expect,
                &[],
                || Ok(vec![cloud.normals_tensor(&d, dtype)?]),
            );
        }
        for format in [MeshFormat::PlyAscii, MeshFormat::PlyBinary] {
            s.case(
                "occupancy::PointCloud::to_bytes",
                format!("{label}, {format:?}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    let bytes = cloud.to_bytes(format)?;
                    Ok(vec![flat(
                        PointCloud::from_bytes(&bytes, format)?.points(),
                    )?])
                },
            );
            s.case(
                "occupancy::PointCloud::from_bytes",
                format!("{label}, {format:?}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    Ok(vec![flat(
                        PointCloud::from_bytes(&cloud.to_bytes(format)?, format)?.points(),
                    )?])
                },
            );
        }
        let path = std::env::temp_dir().join(format!("nf-stiff-cloud-{}.ply", std::process::id()));
        s.case(
            "occupancy::PointCloud::save",
            &label,
            Expect::FiniteOrErr,
            &[],
            || {
                cloud.save(&path)?;
                Ok(vec![flat(PointCloud::load(&path)?.points())?])
            },
        );
        s.case(
            "occupancy::PointCloud::load",
            &label,
            Expect::FiniteOrErr,
            &[],
            || {
                let c = PointCloud::load(&path)?;
                let _ = std::fs::remove_file(&path);
                Ok(vec![flat(c.points())?])
            },
        );
        // The mesh formats: a tetrahedron at this scale through STL and OFF.
        let tet = Mesh::new(
            vec![
                [0.0; 3],
                [scale, 0.0, 0.0],
                [0.0, scale, 0.0],
                [0.0, 0.0, scale],
            ],
            vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        )
        .unwrap();
        for format in [MeshFormat::StlAscii, MeshFormat::StlBinary, MeshFormat::Off] {
            s.case(
                "occupancy::Mesh::from_bytes",
                format!("{label}, {format:?}"),
                Expect::FiniteOrErr,
                &[],
                || {
                    Ok(vec![flat(
                        &Mesh::from_bytes(&tet.to_bytes(format)?, format)?.vertices,
                    )?])
                },
            );
        }
    }
}

/// Meshes at three scales (tiny, unit, huge): construction, validation, colours, the unit
/// cube, surface samples, PLY/OBJ/STL/OFF round trips, and loading a missing file.
fn sweep_meshes(s: &mut Suite) {
    use neural_fields::occupancy::{points_tensor, Mesh, MeshFormat};
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
        s.case("occupancy::Mesh::new", &label, Expect::Finite, &[], || {
            let m = tet(scale)?;
            m.validate()?;
            Ok(vec![
                flat(m.vertex_normals()?)?,
                flat(m.face_normals()?)?,
                vt(m.face_areas()?)?,
                Tensor::new(
                    &[m.face_areas()?.iter().sum::<f64>(), m.signed_volume()?],
                    &d,
                )?,
            ])
        });
        s.case(
            "occupancy::Mesh::validate",
            &label,
            Expect::Finite,
            &[],
            || {
                mesh.validate()?;
                Ok(vec![])
            },
        );
        for c in [0.0, 1e-300, 1.0, -1e-300, 1.0 + 1e-12, 1e300, f64::NAN] {
            s.case(
                "occupancy::Mesh::with_colors",
                format!("{label}, colour {c:e}"),
                if (0.0..=1.0).contains(&c) {
                    Expect::Finite
                } else {
                    Expect::FiniteOrErr
                },
                &[],
                || {
                    let coloured = mesh
                        .clone()
                        .with_colors(vec![[c; 3]; mesh.vertices.len()])?;
                    let flat: Vec<f64> = coloured.colors.unwrap_or_default().concat();
                    Ok(vec![Tensor::from_vec(flat.clone(), flat.len(), &d)?])
                },
            );
        }
        s.case(
            "occupancy::Mesh::normalize_unit_cube",
            &label,
            Expect::Finite,
            &[],
            || {
                let mut m = mesh.clone();
                let (c, k) = m.normalize_unit_cube()?;
                Ok(vec![
                    flat(m.vertices.clone())?,
                    Tensor::new(&[c[0], c[1], c[2], k], &d)?,
                ])
            },
        );
        s.case(
            "occupancy::Mesh::sample_surface",
            &label,
            Expect::Finite,
            &[],
            || {
                let smp = mesh.sample_surface(64, 1)?;
                Ok(vec![flat(smp.0)?, flat(smp.1)?])
            },
        );
        s.case(
            "occupancy::points_tensor",
            format!("{label}, vertices"),
            Expect::Finite,
            &[],
            || Ok(vec![points_tensor(&mesh.vertices, &d, DType::F32)?]),
        );
        s.case(
            "occupancy::points_tensor",
            &label,
            Expect::Finite,
            &[],
            || Ok(vec![points_tensor(&q, &d, DType::F32)?]),
        );
        s.case(
            "occupancy::Mesh::to_bytes",
            format!("{label}, PLY"),
            Expect::Finite,
            &[],
            || {
                let a = mesh.to_bytes(MeshFormat::PlyAscii)?;
                let b = mesh.to_bytes(MeshFormat::PlyBinary)?;
                let a = Mesh::from_bytes(&a, MeshFormat::PlyBinary)?;
                let b = Mesh::from_bytes(&b, MeshFormat::PlyBinary)?;
                Ok(vec![flat(a.vertices)?, flat(b.vertices)?])
            },
        );
        s.case(
            "occupancy::Mesh::from_bytes",
            format!("{label}, ASCII PLY"),
            Expect::Finite,
            &[],
            || {
                let bytes = mesh.to_bytes(MeshFormat::PlyAscii)?;
                Ok(vec![flat(
                    Mesh::from_bytes(&bytes, MeshFormat::PlyBinary)?.vertices,
                )?])
            },
        );
        s.case(
            "occupancy::Mesh::to_bytes",
            format!("{label}, OBJ"),
            Expect::Finite,
            &[],
            || {
                let obj = String::from_utf8(mesh.to_bytes(MeshFormat::Obj)?).unwrap();
                Ok(vec![flat(
                    Mesh::from_bytes(obj.as_bytes(), MeshFormat::Obj)?.vertices,
                )?])
            },
        );
        s.case(
            "occupancy::Mesh::from_bytes",
            format!("{label}, OBJ"),
            Expect::Finite,
            &[],
            || {
                let obj = String::from_utf8(mesh.to_bytes(MeshFormat::Obj)?).unwrap();
                Ok(vec![flat(
                    Mesh::from_bytes(obj.as_bytes(), MeshFormat::Obj)?.vertices,
                )?])
            },
        );
        s.case("occupancy::Mesh::save", &label, Expect::Finite, &[], || {
            let path =
                std::env::temp_dir().join(format!("nf_stiff_{}_{scale:e}.ply", std::process::id()));
            mesh.save(&path)?;
            let m = Mesh::load(&path)?;
            let _ = std::fs::remove_file(&path);
            Ok(vec![flat(m.vertices)?])
        });
        s.case(
            "occupancy::Mesh::load",
            &label,
            Expect::FiniteOrErr,
            &[],
            || Ok(vec![flat(Mesh::load("/nonexistent/mesh.ply")?.vertices)?]),
        );
    }
}
