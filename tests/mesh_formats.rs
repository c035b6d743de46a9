//! STL and OFF meshes, point clouds, concave polygons, and the PLY defects found from
//! outside (lying counts, trailing data, amplification, truncated point clouds).
//! Real files come from Debian's assimp-testmodels when it is installed.

use neural_fields::mesh::{Mesh, MeshFormat, PointCloud};

type TestResult = Result<(), Box<dyn std::error::Error>>;

mod common;

use common::assimp_models as models;

fn cube() -> Result<Mesh, neural_fields::Error> {
    let v = (0..8)
        .map(|i| [(i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64])
        .collect();
    let f = vec![
        [0, 2, 1],
        [1, 2, 3],
        [4, 5, 6],
        [5, 7, 6],
        [0, 1, 4],
        [1, 5, 4],
        [2, 6, 3],
        [3, 6, 7],
        [0, 4, 2],
        [2, 4, 6],
        [1, 3, 5],
        [3, 7, 5],
    ];
    Mesh::new(v, f)
}

/// `bytes` with the first `from` replaced by `to` (a header edit on binary files).
fn replace(bytes: &[u8], from: &str, to: &str) -> Vec<u8> {
    let at = bytes
        .windows(from.len())
        .position(|w| w == from.as_bytes())
        .expect("the header holds the text");
    [&bytes[..at], to.as_bytes(), &bytes[at + from.len()..]].concat()
}

/// `(b − a) × (c − a)` of face `[a, b, c]` of a valid mesh: twice its area, along its
/// normal.
fn cross(m: &Mesh, f: [u32; 3]) -> [f64; 3] {
    let [a, b, c] = f.map(|i| m.vertices[i as usize]);
    let (u, v) = (
        [b[0] - a[0], b[1] - a[1], b[2] - a[2]],
        [c[0] - a[0], c[1] - a[1], c[2] - a[2]],
    );
    [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ]
}

/// The area of a mesh (sum of its triangles, `½|(b − a) × (c − a)|` each).
fn area(m: &Mesh) -> Result<f64, neural_fields::Error> {
    m.validate()?;
    Ok(m.faces
        .iter()
        .map(|&f| {
            let n = cross(m, f);
            0.5 * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt()
        })
        .sum())
}

#[test]
fn stl_and_off_round_trip_a_closed_mesh() -> TestResult {
    let c = cube()?;
    assert!(!c.faces.is_empty() && c.edge_report() == (0, 0, 0));
    for format in [MeshFormat::StlAscii, MeshFormat::StlBinary, MeshFormat::Off] {
        let bytes = c.to_bytes(format)?;
        // Either STL variant reads both encodings.
        let read_as = if format == MeshFormat::StlAscii {
            MeshFormat::StlBinary
        } else {
            format
        };
        let back = Mesh::from_bytes(&bytes, read_as)?;
        // STL welds its corners back into 8 shared vertices, so the cube stays closed.
        assert_eq!(back.vertices.len(), 8, "{format:?}");
        assert_eq!(back.faces.len(), 12, "{format:?}");
        assert!(
            !back.faces.is_empty() && back.edge_report() == (0, 0, 0),
            "{format:?}"
        );
        assert!((back.signed_volume()? - c.signed_volume()?).abs() < 1e-12);
    }
    // Binary STL's header does not start with "solid", and the file is 84 + 50·12 bytes.
    let bin = c.to_bytes(MeshFormat::StlBinary)?;
    assert_eq!(bin.len(), 84 + 50 * 12);
    assert!(!bin.starts_with(b"solid"));
    // OFF keeps colours (COFF).
    let coloured = Mesh {
        colors: Some(vec![[0.2, 0.4, 1.0]; 8]),
        ..c.clone()
    };
    let back = Mesh::from_bytes(&coloured.to_bytes(MeshFormat::Off)?, MeshFormat::Off)?;
    let col = back.colors.ok_or("colours lost")?;
    assert!((col[3][0] - 51.0 / 255.0).abs() < 1e-12);
    Ok(())
}

#[test]
fn files_save_and_load_by_extension() -> TestResult {
    let dir = std::env::temp_dir().join(format!("nf-formats-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let c = cube()?;
    for ext in ["ply", "obj", "stl", "off", "STL"] {
        let p = dir.join(format!("cube.{ext}"));
        c.save(&p)?;
        let back = Mesh::load(&p)?;
        assert_eq!(back.faces.len(), 12, "{ext}");
    }
    // A reader's error names the file it read.
    let bad = dir.join("bad.off");
    std::fs::write(&bad, "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n")?;
    let e = Mesh::load(&bad).unwrap_err().to_string();
    assert!(e.contains("bad.off") && e.contains("vertex 7 of 3"), "{e}");
    let e = Mesh::load(dir.join("cube.xyz")).unwrap_err().to_string();
    assert!(e.contains(".stl") && e.contains("xyz"), "{e}");
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}

#[test]
fn hostile_stl_and_off_files_are_errors_naming_the_problem() {
    // Binary STL whose count does not match its size: named before any allocation.
    let mut b = vec![b' '; 80];
    b.extend_from_slice(&u32::MAX.to_le_bytes());
    b.extend_from_slice(&[0; 50]);
    let e = Mesh::from_bytes(&b, MeshFormat::StlBinary)
        .unwrap_err()
        .to_string();
    assert!(e.contains("4294967295") && e.contains("134 bytes"), "{e}");
    // Too short to be either STL.
    let e = Mesh::from_bytes(b"abc", MeshFormat::StlBinary)
        .unwrap_err()
        .to_string();
    assert!(e.contains("3 bytes"), "{e}");
    // ASCII STL: a facet cut short, an unknown keyword, a bad number.
    for (text, needle) in [
        ("solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\n", "truncated"),
        ("solid x\nfacet normal 0 0 1\nouter loop\nvortex 0 0 0\n", "line 4"),
        ("solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 nan? 0\n", "line 4"),
        (
            "solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nendloop\nendfacet\nendsolid\n",
            "2 vertices",
        ),
    ] {
        let e = Mesh::from_bytes(text.as_bytes(), MeshFormat::StlAscii)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("stl:") && e.contains(needle), "{e}");
    }
    // OFF: counts beyond the file, fewer faces declared than present, a face of 0
    // vertices, binary OFF, a non-finite coordinate.
    for (text, needle) in [
        ("OFF\n1000000000 1 0\n0 0 0\n", "lying"),
        (
            "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 2 1\n",
            "fewer faces",
        ),
        ("OFF\n3 1\n0 0 0\n1 0 0\n0 1 0\n0\n", "0 vertices"),
        ("OFF BINARY\n", "binary"),
        ("OFF\n3 1 0\n0 0 0\n1 0 inf\n0 1 0\n3 0 1 2\n", "vertex 1"),
        (
            "COFF\n3 1 0\n0 0 0 255 0 0\n1 0 0 0 300 0\n0 1 0 0 0 0\n3 0 1 2\n",
            "colours",
        ),
    ] {
        let e = Mesh::from_bytes(text.as_bytes(), MeshFormat::Off)
            .unwrap_err()
            .to_string();
        assert!(e.contains(needle), "{needle}: {e}");
    }
    // ModelNet's keyword run into the counts reads.
    let m = Mesh::from_bytes(b"OFF3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", MeshFormat::Off).unwrap();
    assert_eq!(m.faces, vec![[0, 1, 2]]);
}

/// Pins a silent truncation: a PLY header declaring 2 faces where the file holds 4
/// loaded 2 faces; data after the declared rows is now an error, in ASCII and binary.
#[test]
fn ply_declaring_fewer_faces_than_it_holds_is_an_error() -> TestResult {
    let c = cube()?;
    for format in [MeshFormat::PlyAscii, MeshFormat::PlyBinary] {
        let bytes = c.to_bytes(format)?;
        let lying = replace(&bytes, "element face 12", "element face 10");
        let e = Mesh::from_bytes(&lying, format).unwrap_err().to_string();
        assert!(e.contains("trailing data"), "{format:?}: {e}");
        // Trailing whitespace after an ASCII body is fine.
        if format == MeshFormat::PlyAscii {
            let spaced = format!("{}\n\n  \n", String::from_utf8_lossy(&bytes));
            assert_eq!(Mesh::from_bytes(spaced.as_bytes(), format)?.faces.len(), 12);
        }
    }
    // An ASCII row with more values than the element has properties.
    let text = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
                property float z\nelement face 1\nproperty list uchar int vertex_indices\n\
                end_header\n0 0 0 9\n1 0 0\n0 1 0\n3 0 1 2\n";
    let e = Mesh::from_bytes(text.as_bytes(), MeshFormat::PlyAscii)
        .unwrap_err()
        .to_string();
    assert!(e.contains("line 10") && e.contains("4 values"), "{e}");
    Ok(())
}

/// Pins an amplification: a PLY of a few hundred bytes whose faces were lists of 255
/// vertices was fan-triangulated into tens of millions of faces. Every triangle now
/// consumes an index byte of the file, so a file's faces are at most its size.
#[test]
fn ply_of_255_vertex_polygons_is_bounded_by_its_size() -> TestResult {
    // A regular 255-gon (convex: fanned) as many times as a small file holds.
    let n = 255usize;
    let mut b = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\n\
         property float y\nproperty float z\nelement face 40\n\
         property list uchar uchar vertex_indices\nend_header\n"
    )
    .into_bytes();
    for i in 0..n {
        let a = i as f32 / n as f32 * std::f32::consts::TAU;
        for c in [a.cos(), a.sin(), 0.0] {
            b.extend_from_slice(&c.to_le_bytes());
        }
    }
    for _ in 0..40 {
        b.push(255);
        b.extend(0..255u8);
    }
    let m = Mesh::from_bytes(&b, MeshFormat::PlyBinary)?;
    assert_eq!(m.faces.len(), 40 * 253);
    assert!(
        m.faces.len() <= b.len(),
        "{} faces from {} bytes",
        m.faces.len(),
        b.len()
    );
    // A header that claims more such faces than the bytes hold is refused up front.
    let lying = replace(&b, "element face 40", "element face 4000000");
    let e = Mesh::from_bytes(&lying, MeshFormat::PlyBinary)
        .unwrap_err()
        .to_string();
    assert!(e.contains("element face") && e.contains("remain"), "{e}");
    Ok(())
}

/// Pins wrong geometry without an error: assimp's `OBJ/concave_polygon.obj` (one
/// 66-corner polygon) was fan-triangulated into 64 triangles covering 3.22, 29 of them
/// reversed, for a polygon of area 0.2455. Ear clipping keeps the area and the winding.
#[test]
fn concave_polygon_obj_is_triangulated_by_ear_clipping() -> TestResult {
    let Some(dir) = models() else { return Ok(()) };
    let m = Mesh::load(dir.join("OBJ/concave_polygon.obj"))?;
    assert_eq!(m.faces.len(), 64);
    let a = area(&m)?;
    assert!((a - 0.2455).abs() < 5e-4, "area {a}");
    // Every triangle's normal points the polygon's way.
    m.validate()?;
    let normals: Vec<[f64; 3]> = m.faces.iter().map(|&f| cross(&m, f)).collect();
    let reference = normals[0];
    let reversed = normals
        .iter()
        .filter(|n| n[0] * reference[0] + n[1] * reference[1] + n[2] * reference[2] < 0.0)
        .count();
    assert_eq!(reversed, 0);
    Ok(())
}

#[test]
fn self_intersecting_and_huge_concave_polygons_are_errors() {
    let bow_tie = "v 0 0 0\nv 1 1 0\nv 1 0 0\nv 0 1 0\nf 1 2 3 4\n";
    let e = Mesh::from_bytes(bow_tie.as_bytes(), MeshFormat::Obj)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("line 5") && e.contains("self-intersecting"),
        "{e}"
    );
    // A planar L (concave) loads with its area.
    let l = "v 0 0 0\nv 2 0 0\nv 2 1 0\nv 1 1 0\nv 1 2 0\nv 0 2 0\nf 1 2 3 4 5 6\n";
    let m = Mesh::from_bytes(l.as_bytes(), MeshFormat::Obj).unwrap();
    assert!((area(&m).unwrap() - 3.0).abs() < 1e-12);
}

#[test]
fn point_cloud_ply_loads_as_a_point_cloud_and_the_mesh_reader_says_so() -> TestResult {
    // Positions, normals, colours and an extra property, no faces, in both encodings.
    let points = vec![[0.0, 0.0, 0.0], [1.0, 0.5, 0.25], [0.0, 2.0, 0.0]];
    let normals = vec![[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
    let colors = vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let cloud = PointCloud::new(points.clone(), Some(normals.clone()), Some(colors.clone()))?;
    for format in [MeshFormat::PlyAscii, MeshFormat::PlyBinary] {
        let bytes = cloud.to_bytes(format)?;
        let back = PointCloud::from_bytes(&bytes, format)?;
        assert_eq!(back, cloud);
        let e = Mesh::from_bytes(&bytes, format).unwrap_err().to_string();
        assert!(
            e.contains("point cloud (3 points") && e.contains("PointCloud::load"),
            "{e}"
        );
    }
    let text = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n\
                property float z\nproperty float psz\nproperty uchar alpha\nend_header\n\
                0 0 0 0.5 255\n1 1 1 0.5 255\n";
    let c = PointCloud::from_bytes(text.as_bytes(), MeshFormat::PlyAscii)?;
    assert_eq!(c.points(), &[[0.0; 3], [1.0; 3]]);
    assert!(c.normals().is_none() && c.colors().is_none());
    // OFF and OBJ clouds.
    let off = PointCloud::from_bytes(b"OFF\n2 0 0\n0 0 0\n1 2 3\n", MeshFormat::Off)?;
    assert_eq!(off.points().len(), 2);
    let obj = PointCloud::from_bytes(
        b"v 0 0 0\nv 1 2 3\nvn 0 0 1\nvn 0 1 0\np 1 2\n",
        MeshFormat::Obj,
    )?;
    assert_eq!(obj.normals().map(<[_]>::len), Some(2));
    // A cloud is never empty, never non-finite, and its colours lie in [0, 1].
    assert!(PointCloud::new(vec![], None, None).is_err());
    assert!(PointCloud::new(vec![[f64::NAN, 0.0, 0.0]], None, None).is_err());
    let e = PointCloud::new(points.clone(), None, Some(vec![[2.0, 0.0, 0.0]; 3])).unwrap_err();
    assert!(e.to_string().starts_with("colors"), "{e}");
    let e = PointCloud::new(points.clone(), Some(vec![[0.0; 3]; 2]), None).unwrap_err();
    assert!(e.to_string().starts_with("normals"), "{e}");
    assert_eq!(PointCloud::new(points, Some(normals), Some(colors))?, cloud);
    assert!(
        PointCloud::from_bytes(&cloud.to_bytes(MeshFormat::PlyAscii)?, MeshFormat::StlAscii)
            .is_err()
    );
    // Sampling: a subset without replacement up to N, with replacement beyond.
    let s = cloud.sample(3, 7)?;
    let mut got: Vec<[f64; 3]> = s.points().to_vec();
    got.sort_by(|a, b| a[1].total_cmp(&b[1]));
    let mut want = cloud.points().to_vec();
    want.sort_by(|a, b| a[1].total_cmp(&b[1]));
    assert_eq!(got, want);
    assert_eq!(cloud.sample(10, 7)?.points().len(), 10);
    assert_eq!(cloud.sample(10, 7)?, cloud.sample(10, 7)?);
    assert!(cloud.sample(0, 7).is_err());
    assert!(cloud.sample(usize::MAX, 7).is_err());
    Ok(())
}

#[test]
fn assimp_point_clouds_stl_and_off_models_load() -> TestResult {
    let Some(dir) = models() else { return Ok(()) };
    let points = PointCloud::load(dir.join("PLY/points.ply"))?;
    assert_eq!(points.points().len(), 4);
    assert!(points.normals().is_some() && points.colors().is_some());
    let obj = PointCloud::load(dir.join("OBJ/point_cloud.obj"))?;
    assert!(!obj.points().is_empty());
    for name in [
        "STL/Spider_ascii.stl",
        "STL/Spider_binary.stl",
        "STL/Wuson.stl",
        "STL/sphereWithHole.stl",
        "STL/3DSMaxExport.STL",
        "STL/triangle.stl",
        "STL/triangle_with_two_solids.stl",
        "OFF/Cube.off",
        "OFF/Wuson.off",
    ] {
        let m = Mesh::load(dir.join(name)).map_err(|e| format!("{name}: {e}"))?;
        assert!(area(&m)? > 0.0, "{name}");
    }
    let ascii = Mesh::load(dir.join("STL/Spider_ascii.stl"))?;
    let binary = Mesh::load(dir.join("STL/Spider_binary.stl"))?;
    assert_eq!(ascii.faces.len(), binary.faces.len());
    let cube = Mesh::load(dir.join("OFF/Cube.off"))?;
    assert_eq!(cube.faces.len(), 12);
    assert!(!cube.faces.is_empty() && cube.edge_report() == (0, 0, 0));
    assert!((cube.signed_volume()?.abs() - 1.0).abs() < 1e-12);
    let e = Mesh::load(dir.join("OFF/invalid.off"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("invalid.off") && e.contains("0 vertices"), "{e}");
    Ok(())
}

/// `pond.0.ply` is 69 bytes shorter than its header declares (70 051 rows of 31 bytes):
/// it keeps failing, and the error says how many points were complete (70 048).
#[test]
fn pond_ply_is_truncated_and_says_how_many_points_were_complete() {
    let Some(dir) = models() else { return };
    let e = PointCloud::load(dir.join("PLY/pond.0.ply"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("pond.0.ply") && e.contains("70051") && e.contains("70048 complete"),
        "{e}"
    );
}

/// A UTF-16 file of any text format is refused naming the encoding (an OBJ was read as
/// an empty mesh; PLY, OFF and STL now say the same as OBJ).
#[test]
fn utf16_text_formats_are_refused_naming_the_encoding() {
    for (text, format) in [
        ("ply\nformat ascii 1.0\nend_header\n", MeshFormat::PlyAscii),
        (
            "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
            MeshFormat::Off,
        ),
        ("solid x\nendsolid x\n", MeshFormat::StlAscii),
    ] {
        let mut b = vec![0xFF, 0xFE];
        for u in text.encode_utf16() {
            b.extend_from_slice(&u.to_le_bytes());
        }
        let e = Mesh::from_bytes(&b, format).unwrap_err().to_string();
        assert!(e.contains("UTF-16"), "{format:?}: {e}");
    }
}

/// Found by fuzzing the PLY reader: an ASCII PLY whose `float` property holds 2.2e44
/// loaded (the text was parsed as a 64-bit value) but could not be written back as the
/// PLY it came from. A value its declared type cannot hold is now an error.
#[test]
fn ascii_ply_value_beyond_its_declared_type_is_an_error() -> TestResult {
    let ply = |ty: &str, y: &str, red: &str| {
        format!(
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty {ty} x\nproperty {ty} y\n\
             property {ty} z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n\
             element face 1\nproperty list uchar int vertex_indices\nend_header\n\
             0 0 0 {red} 0 0\n1 {y} 0 0 0 0\n0 1 0 0 0 0\n3 0 1 2\n"
        )
        .into_bytes()
    };
    for (ty, y, red, bad) in [
        ("float", "2.2e44", "0", "2.2e44"),
        ("float", "1", "256", "256"),
        ("float", "1", "-1", "-1"),
        ("float", "1", "1.5", "1.5"),
    ] {
        let err = Mesh::from_bytes(&ply(ty, y, red), MeshFormat::PlyAscii)
            .expect_err(bad)
            .to_string();
        assert!(err.contains("declared type") && err.contains(bad), "{err}");
    }
    // `double` holds it; writing it as PLY (32-bit floats) refuses, OBJ keeps it.
    let mesh = Mesh::from_bytes(&ply("double", "2.2e44", "255"), MeshFormat::PlyAscii)?;
    assert_eq!(mesh.vertices[1][1], 2.2e44);
    assert!(mesh.to_bytes(MeshFormat::PlyBinary).is_err());
    let obj = Mesh::from_bytes(&mesh.to_bytes(MeshFormat::Obj)?, MeshFormat::Obj)?;
    assert_eq!(obj.vertices[1][1], 2.2e44);
    Ok(())
}

/// Found by fuzzing the STL reader: an ASCII STL may hold coordinates beyond ±3.4e38,
/// which binary STL cannot store; writing such a mesh as binary STL must refuse (naming
/// the vertex), while ASCII STL and OBJ keep it.
#[test]
fn ascii_stl_beyond_f32_refuses_binary_stl_and_keeps_text() -> TestResult {
    let stl = b"solid s\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n\
                vertex 0 0 7.7e79\nendloop\nendfacet\nendsolid s\n";
    let mesh = Mesh::from_bytes(stl, MeshFormat::StlAscii)?;
    let err = mesh
        .to_bytes(MeshFormat::StlBinary)
        .expect_err("beyond f32")
        .to_string();
    assert!(err.contains("3.4e38") && err.contains("7.7e79"), "{err}");
    for format in [MeshFormat::StlAscii, MeshFormat::Obj] {
        let back = Mesh::from_bytes(&mesh.to_bytes(format)?, format)?;
        assert_eq!(back.vertices.len(), 3);
        assert!(back.vertices.iter().any(|v| v[2] == 7.7e79));
    }
    Ok(())
}
