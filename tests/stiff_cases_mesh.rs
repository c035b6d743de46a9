//! Stiff cases of the mesh types: point clouds and meshes at extreme scales, through
//! every file format.

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
    "mesh::Mesh::from_bytes",
    "mesh::PointCloud::from_bytes",
    "mesh::PointCloud::load",
    "mesh::PointCloud::new",
    "mesh::PointCloud::sample",
    "mesh::PointCloud::save",
    "mesh::PointCloud::to_bytes",
    "mesh::points_to_tensor",
];

/// Items swept by `sweep_meshes`.
const MESHES: &[&str] = &[
    "mesh::Mesh::from_bytes",
    "mesh::Mesh::load",
    "mesh::Mesh::new",
    "mesh::Mesh::normalize_unit_cube",
    "mesh::Mesh::sample_surface",
    "mesh::Mesh::save",
    "mesh::Mesh::to_bytes",
    "mesh::Mesh::validate",
    "mesh::points_from_tensor",
    "mesh::points_to_tensor",
];

/// Public items without floating-point input (or only reached through a swept item),
/// with the reason. Matching is by prefix.
const EXEMPT: &[(&str, &str)] = &[
    ("mesh::PointCloud::points", "getter"),
    ("mesh::PointCloud::normals", "getter"),
    ("mesh::PointCloud::colors", "getter"),
    ("mesh::Mesh::bounds", "swept through normalize_unit_cube"),
    ("mesh::Mesh::edge_report", "integer topology"),
    ("mesh::Mesh::signed_volume", "swept through Mesh::new"),
    ("mesh::Mesh::vertex_normals", "swept through Mesh::new"),
];

/// Point clouds at three scales through their constructors, sampling, tensors and files,
/// and the mesh formats' round trips.
fn sweep_point_clouds(s: &mut Suite) {
    use neural_fields::mesh::{points_to_tensor, Mesh, MeshFormat, PointCloud};
    let d = Device::Cpu;
    let flat = |v: &[[f64; 3]]| Tensor::from_vec(v.concat(), v.len() * 3, &d);
    for scale in [1e-300, 1e-6, 1.0, 1e6, 1e300] {
        let label = format!("scale {scale:e}");
        let pts = vec![[0.0, 0.0, 0.0], [scale, 0.0, 0.0], [0.0, scale, -scale]];
        let normals = vec![[0.0, 0.0, scale]; 3];
        s.case("mesh::PointCloud::new", &label, Expect::Finite, &[], || {
            Ok(vec![flat(
                PointCloud::new(pts.clone(), None, None)?.points(),
            )?])
        });
        s.case(
            "mesh::PointCloud::new",
            format!("{label}, normals"),
            Expect::Finite,
            &[],
            || {
                let c = PointCloud::new(pts.clone(), Some(normals.clone()), None)?;
                Ok(vec![flat(c.normals().unwrap_or(&[]))?])
            },
        );
        s.case(
            "mesh::PointCloud::new",
            format!("{label}, colours"),
            Expect::Finite,
            &[],
            || {
                let c = PointCloud::new(pts.clone(), None, Some(vec![[0.0, 0.5, 1.0]; 3]))?;
                Ok(vec![flat(c.colors().unwrap_or(&[]))?])
            },
        );
        let cloud = PointCloud::new(pts.clone(), Some(normals.clone()), None).unwrap();
        s.case(
            "mesh::PointCloud::sample",
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
                "mesh::points_to_tensor",
                format!("{label}, cloud points, {dtype:?}"),
                expect,
                &[],
                || Ok(vec![points_to_tensor(cloud.points(), &d, dtype)?]),
            );
            s.case(
                "mesh::points_to_tensor",
                format!("{label}, cloud normals, {dtype:?}"),
                expect,
                &[],
                || {
                    Ok(vec![points_to_tensor(
                        cloud.normals().unwrap_or(&[]),
                        &d,
                        dtype,
                    )?])
                },
            );
        }
        for format in [MeshFormat::PlyAscii, MeshFormat::PlyBinary] {
            s.case(
                "mesh::PointCloud::to_bytes",
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
                "mesh::PointCloud::from_bytes",
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
            "mesh::PointCloud::save",
            &label,
            Expect::FiniteOrErr,
            &[],
            || {
                cloud.save(&path)?;
                Ok(vec![flat(PointCloud::load(&path)?.points())?])
            },
        );
        s.case(
            "mesh::PointCloud::load",
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
                "mesh::Mesh::from_bytes",
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
    use neural_fields::mesh::{points_from_tensor, points_to_tensor, Mesh, MeshFormat};
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
        s.case("mesh::Mesh::new", &label, Expect::Finite, &[], || {
            let m = tet(scale)?;
            m.validate()?;
            Ok(vec![
                flat(m.vertex_normals()?)?,
                vt(m.sample_surface(64, 1)?.0.concat())?,
                Tensor::new(&[m.signed_volume()?], &d)?,
            ])
        });
        s.case("mesh::Mesh::validate", &label, Expect::Finite, &[], || {
            mesh.validate()?;
            Ok(vec![])
        });
        for c in [0.0, 1e-300, 1.0, -1e-300, 1.0 + 1e-12, 1e300, f64::NAN] {
            s.case(
                "mesh::Mesh::validate",
                format!("{label}, colour {c:e}"),
                if (0.0..=1.0).contains(&c) {
                    Expect::Finite
                } else {
                    Expect::FiniteOrErr
                },
                &[],
                || {
                    let coloured = Mesh {
                        colors: Some(vec![[c; 3]; mesh.vertices.len()]),
                        ..mesh.clone()
                    };
                    coloured.validate()?;
                    let flat: Vec<f64> = coloured.colors.unwrap_or_default().concat();
                    Ok(vec![Tensor::from_vec(flat.clone(), flat.len(), &d)?])
                },
            );
        }
        s.case(
            "mesh::Mesh::normalize_unit_cube",
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
            "mesh::Mesh::sample_surface",
            &label,
            Expect::Finite,
            &[],
            || {
                let smp = mesh.sample_surface(64, 1)?;
                Ok(vec![flat(smp.0)?, flat(smp.1)?])
            },
        );
        s.case(
            "mesh::points_to_tensor",
            format!("{label}, vertices"),
            Expect::Finite,
            &[],
            || Ok(vec![points_to_tensor(&mesh.vertices, &d, DType::F32)?]),
        );
        s.case(
            "mesh::points_to_tensor",
            &label,
            Expect::Finite,
            &[],
            || Ok(vec![points_to_tensor(&q, &d, DType::F32)?]),
        );
        s.case(
            "mesh::Mesh::to_bytes",
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
            "mesh::Mesh::from_bytes",
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
            "mesh::Mesh::to_bytes",
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
            "mesh::Mesh::from_bytes",
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
        s.case("mesh::Mesh::save", &label, Expect::Finite, &[], || {
            let path =
                std::env::temp_dir().join(format!("nf_stiff_{}_{scale:e}.ply", std::process::id()));
            mesh.save(&path)?;
            let m = Mesh::load(&path)?;
            let _ = std::fs::remove_file(&path);
            Ok(vec![flat(m.vertices)?])
        });
        s.case("mesh::Mesh::load", &label, Expect::FiniteOrErr, &[], || {
            Ok(vec![flat(Mesh::load("/nonexistent/mesh.ply")?.vertices)?])
        });
    }
    // Host points to tensors and back, from 1e-30 to 1e30 in one point.
    for dtype in DTYPES {
        let tag = format!("{dtype:?}");
        s.case(
            "mesh::points_to_tensor",
            format!("{tag}, 1e-30…1e30"),
            Expect::Finite,
            &[],
            || Ok(vec![points_to_tensor(&[[1e-30, 1e30, 0.0]], &d, dtype)?]),
        );
        s.case(
            "mesh::points_from_tensor",
            &tag,
            Expect::Finite,
            &[],
            || {
                Ok(vec![flat(points_from_tensor(
                    &Tensor::new(&[[1e-30f64, 1e30, 0.0]], &d)?.to_dtype(dtype)?,
                )?)?])
            },
        );
    }
}
