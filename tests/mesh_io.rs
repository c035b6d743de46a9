//! Mesh IO and validation: PLY (ASCII, binary) and OBJ round trips, real files from
//! Debian's assimp-testmodels, errors that name the problem and where it is. The round
//! trips of a marching-cubes sphere need the `occupancy` feature; the rest runs without.

use neural_fields::mesh::{Mesh, MeshFormat};

mod common;

use common::assimp_models as models;

#[cfg(feature = "occupancy")]
fn sphere_mesh() -> Mesh {
    use neural_fields::field::Inside;
    use neural_fields::occupancy::{marching_cubes, Grid};
    let g = Grid::from_fn([17; 3], [-0.5; 3], [0.5; 3], |p| {
        (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 0.4
    })
    .unwrap();
    marching_cubes(&g, 0.0, Inside::Negative).unwrap()
}

#[cfg(feature = "occupancy")]
fn close(a: &Mesh, b: &Mesh, tol: f64) {
    assert_eq!(a.faces, b.faces);
    assert_eq!(a.vertices.len(), b.vertices.len());
    for (p, q) in a.vertices.iter().zip(&b.vertices) {
        for c in 0..3 {
            assert!((p[c] - q[c]).abs() <= tol, "{p:?} {q:?}");
        }
    }
}

#[cfg(feature = "occupancy")]
#[test]
fn ply_and_obj_round_trip_with_and_without_normals() {
    let mut m = sphere_mesh();
    for with_normals in [false, true] {
        if with_normals {
            m.normals = Some(m.vertex_normals().unwrap());
        }
        for fmt in [MeshFormat::PlyAscii, MeshFormat::PlyBinary] {
            let bytes = m.to_bytes(fmt).unwrap();
            let back = Mesh::from_bytes(&bytes, fmt).unwrap();
            close(&m, &back, 1e-7); // written as f32
            assert_eq!(back.normals.is_some(), with_normals);
        }
        let back =
            Mesh::from_bytes(&m.to_bytes(MeshFormat::Obj).unwrap(), MeshFormat::Obj).unwrap();
        close(&m, &back, 0.0); // OBJ keeps f64 exactly (shortest round-trip printing)
        assert_eq!(back.normals.is_some(), with_normals);
    }
    // Through files, by extension.
    let dir = std::env::temp_dir().join(format!("nf_mesh_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for name in ["a.ply", "a.obj", "A.PLY"] {
        let p = dir.join(name);
        m.save(&p).unwrap();
        close(&m, &Mesh::load(&p).unwrap(), 1e-7);
    }
    assert!(m
        .save(dir.join("a.xyz"))
        .unwrap_err()
        .to_string()
        .contains("extension"));
    let e = Mesh::load(dir.join("missing.ply")).unwrap_err().to_string();
    assert!(e.contains("missing.ply"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn ply_reads_big_endian_extra_properties_other_elements_and_quads() {
    // Binary big-endian, a double x, an extra uchar property, a quad with ushort indices
    // and uint count, plus an unknown element after the faces.
    let mut b = b"ply\nformat binary_big_endian 1.0\nelement vertex 4\nproperty double x\nproperty float y\nproperty float z\nproperty uchar red\nelement face 1\nproperty uint nothing\nproperty list uint ushort vertex_index\nelement edge 1\nproperty int a\nend_header\n".to_vec();
    for (i, v) in [
        [0.0f64, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
    ]
    .iter()
    .enumerate()
    {
        b.extend_from_slice(&v[0].to_be_bytes());
        b.extend_from_slice(&(v[1] as f32).to_be_bytes());
        b.extend_from_slice(&(v[2] as f32).to_be_bytes());
        b.push(i as u8);
    }
    b.extend_from_slice(&7u32.to_be_bytes());
    b.extend_from_slice(&4u32.to_be_bytes());
    for k in 0..4u16 {
        b.extend_from_slice(&k.to_be_bytes());
    }
    b.extend_from_slice(&9i32.to_be_bytes());
    let m = Mesh::from_bytes(&b, MeshFormat::PlyBinary).unwrap();
    assert_eq!(m.faces, vec![[0, 1, 2], [0, 2, 3]]);
    assert_eq!(m.vertices[2], [1.0, 1.0, 0.0]);
    // Truncated by one byte: the error says so and where.
    let e = Mesh::from_bytes(&b[..b.len() - 1], MeshFormat::PlyBinary)
        .unwrap_err()
        .to_string();
    assert!(e.contains("truncated") && e.contains("byte"), "{e}");
}

#[test]
fn bad_files_and_bad_meshes_name_the_problem() {
    let good = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
    assert_eq!(
        Mesh::from_bytes(good.as_bytes(), MeshFormat::PlyAscii)
            .unwrap()
            .faces
            .len(),
        1
    );
    let cases: Vec<(String, &str)> = vec![
        (good.replace("3 0 1 2\n", ""), "truncated"), // missing face row: too few bytes left
        (good.replace("1 0 0\n", "1 0\n"), "line 11"), // short vertex row
        (good.replace("1 0 0\n", "1 zero 0\n"), "line 11"), // not a number
        (
            good.replace("3 0 1 2", "3 0 1 5"),
            "face 0 = [0, 1, 5] indexes vertex 5 of 3",
        ),
        (good.replace("0 1 0\n", "0 nan 0\n"), "vertex 2"),
        (good.replace("3 0 1 2", "2 0 1"), "face 0: 2 vertices"),
        (good.replace("end_header\n", ""), "header"),
        (
            good.replace("format ascii", "format weird"),
            "header line 2",
        ),
        (good.replace("ply\n", "plx\n"), "line 1"),
        (
            good.replace("element face 1", "element face 0"),
            "trailing data",
        ),
    ];
    for (text, needle) in cases {
        let e = Mesh::from_bytes(text.as_bytes(), MeshFormat::PlyAscii)
            .unwrap_err()
            .to_string();
        assert!(e.contains(needle), "{needle:?} not in {e:?}");
    }
    let obj_cases = [
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n",
            "indexes vertex 3 of 3",
        ),
        ("v 0 0 0\nv 1 0\n", "line 2"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", "line 4"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "index 0"),
        ("v 0 0 0\n", "a point cloud (1 point, no faces)"),
        ("", "empty mesh"),
    ];
    for (text, needle) in obj_cases {
        let e = Mesh::from_bytes(text.as_bytes(), MeshFormat::Obj)
            .unwrap_err()
            .to_string();
        assert!(e.contains(needle), "{needle:?} not in {e:?}");
    }
    // Relative indices and the a/b/c forms; convex quads are fan-triangulated.
    let m = Mesh::from_bytes(
        b"v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf -4/1 -3/1 -2/1 -1/1\n",
        MeshFormat::Obj,
    )
    .unwrap();
    assert_eq!(m.faces, vec![[0, 1, 2], [0, 2, 3]]);
    assert!(Mesh::new(vec![], vec![]).is_err());
    let e = Mesh::new(vec![[0.0; 3]], vec![[0, 0, 0]]).map(|mut m| m.normalize_unit_cube());
    assert!(e.unwrap().is_err());
}

#[test]
fn surface_samples_are_area_weighted_and_on_the_surface() {
    // Two triangles of areas 1/2 and 2: the second gets ~80% of the samples.
    let m = Mesh::new(
        vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 5.0],
            [2.0, 0.0, 5.0],
            [0.0, 2.0, 5.0],
        ],
        vec![[0, 1, 2], [3, 4, 5]],
    )
    .unwrap();
    let (p, n) = m.sample_surface(20_000, 1).unwrap();
    let high = p.iter().filter(|q| q[2] > 2.5).count() as f64 / p.len() as f64;
    assert!((high - 0.8).abs() < 0.01, "{high}");
    assert!(p
        .iter()
        .all(|q| q[0] >= 0.0 && q[1] >= 0.0 && q[0] + q[1] <= 2.0 + 1e-12));
    assert!(n.iter().all(|v| *v == [0.0, 0.0, 1.0]));
    // Uniform within a triangle: the mean is the centroid.
    let lows: Vec<_> = p.iter().filter(|q| q[2] < 2.5).collect();
    let mx = lows.iter().map(|q| q[0]).sum::<f64>() / lows.len() as f64;
    assert!((mx - 1.0 / 3.0).abs() < 0.01, "{mx}");
    assert_eq!(
        m.sample_surface(10, 4).unwrap(),
        m.sample_surface(10, 4).unwrap()
    );
}

#[test]
fn assimp_test_models_load() {
    let Some(dir) = models() else { return };
    let mut wuson = Mesh::load(dir.join("PLY/Wuson.ply")).unwrap();
    assert_eq!(wuson.vertices.len(), 11184);
    assert!(wuson.faces.len() >= 3732);
    assert!(wuson.normals.is_some());
    wuson.normalize_unit_cube().unwrap();
    let (lo, hi) = wuson.bounds();
    let ext = (0..3).map(|c| hi[c] - lo[c]).fold(0.0, f64::max);
    assert!((ext - 1.0).abs() < 1e-12);
    assert!((0..3).all(|c| (lo[c] + hi[c]).abs() < 1e-12));
    let cube = Mesh::load(dir.join("PLY/cube.ply")).unwrap();
    assert_eq!((cube.vertices.len(), cube.faces.len()), (8, 12));
    assert!(!cube.faces.is_empty() && cube.edge_report() == (0, 0, 0));
    assert!((cube.signed_volume().unwrap().abs() - 1.0).abs() < 1e-12);
    let bin = Mesh::load(dir.join("PLY/cube_binary.ply")).unwrap();
    assert_eq!(bin.faces.len(), 12);
    let bx = Mesh::load(dir.join("OBJ/box.obj")).unwrap();
    assert_eq!((bx.vertices.len(), bx.faces.len()), (8, 12));
    assert!(!bx.faces.is_empty() && bx.edge_report() == (0, 0, 0));
    assert!((bx.signed_volume().unwrap().abs() - 1.0).abs() < 1e-12);
    let spider = Mesh::load(dir.join("OBJ/spider.obj")).unwrap();
    assert!(spider.faces.len() > 100);
    // What we write, we read back (and so do other tools that read standard PLY).
    let back = Mesh::from_bytes(
        &wuson.to_bytes(MeshFormat::PlyBinary).unwrap(),
        MeshFormat::PlyBinary,
    )
    .unwrap();
    assert_eq!(back.faces, wuson.faces);
}

/// Binary PLY whose header declares `extra` before a one-triangle mesh (`vertex` and
/// `face` elements, little-endian).
fn ply_with_element_before_the_mesh(extra: &str) -> Vec<u8> {
    let mut b = format!(
        "ply\nformat binary_little_endian 1.0\n{extra}element vertex 3\nproperty float x\n\
         property float y\nproperty float z\nelement face 1\n\
         property list uchar int vertex_indices\nend_header\n"
    )
    .into_bytes();
    for v in [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]] {
        for c in v {
            b.extend_from_slice(&c.to_le_bytes());
        }
    }
    b.push(3);
    for k in 0..3i32 {
        b.extend_from_slice(&k.to_le_bytes());
    }
    b
}

/// Runs `f` on another thread and fails the test if it takes more than 20 s (a reader
/// whose work follows a number in the header instead of the file's size).
fn within_20_s<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(std::time::Duration::from_secs(20))
        .expect("the reader did not return within 20 s")
}

/// Pins a hang: a binary PLY whose header declares an element with no properties and a
/// count of 2⁶⁴ − 1 before the vertex element kept the reader looping (each row reads
/// zero bytes). Such an element holds no data and is skipped; the mesh after it loads.
#[test]
fn ply_element_without_properties_and_a_huge_count_does_not_hang() {
    let b = ply_with_element_before_the_mesh("element junk 18446744073709551615\n");
    let m = within_20_s(move || Mesh::from_bytes(&b, MeshFormat::PlyBinary)).unwrap();
    assert_eq!(m.faces, vec![[0, 1, 2]]);
}

/// Pins the same class of defect with properties: a header may not make the reader loop
/// over more rows than the rest of the file can hold; the error names the element, its
/// count and the bytes that remain, before any row is read.
#[test]
fn ply_element_count_beyond_the_file_size_is_an_error_naming_it() {
    let b = ply_with_element_before_the_mesh(
        "element junk 18446744073709551615\nproperty uchar flag\n",
    );
    let e = within_20_s(move || Mesh::from_bytes(&b, MeshFormat::PlyBinary))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("element junk") && e.contains("18446744073709551615") && e.contains("remain"),
        "{e}"
    );
    // ASCII: one row per line, so a count above the bytes left is refused too.
    let text = "ply\nformat ascii 1.0\nelement vertex 1000000\nproperty float x\n\
                property float y\nproperty float z\nend_header\n0 0 0\n";
    let e = within_20_s(move || Mesh::from_bytes(text.as_bytes(), MeshFormat::PlyAscii))
        .unwrap_err()
        .to_string();
    assert!(e.contains("element vertex") && e.contains("1000000"), "{e}");
}

/// Pins a misleading error: a UTF-16 OBJ was read lossily as UTF-8 and reported as an
/// "empty mesh"; the error now names the encoding.
#[test]
fn utf16_obj_is_refused_naming_the_encoding() {
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";
    for bom in [[0xFFu8, 0xFE], [0xFE, 0xFF]] {
        let mut b = bom.to_vec();
        for u in text.encode_utf16() {
            let pair = if bom[0] == 0xFF {
                u.to_le_bytes()
            } else {
                u.to_be_bytes()
            };
            b.extend_from_slice(&pair);
        }
        let e = Mesh::from_bytes(&b, MeshFormat::Obj)
            .unwrap_err()
            .to_string();
        assert!(e.contains("UTF-16"), "{e}");
        // Without its byte-order mark too.
        let e = Mesh::from_bytes(&b[2..], MeshFormat::Obj)
            .unwrap_err()
            .to_string();
        assert!(e.contains("UTF-16"), "{e}");
    }
    assert_eq!(
        Mesh::from_bytes(text.as_bytes(), MeshFormat::Obj)
            .unwrap()
            .faces
            .len(),
        1
    );
}

type TestResult = Result<(), Box<dyn std::error::Error>>;

/// The header of PLY bytes, up to and including `end_header`.
#[cfg(feature = "occupancy")]
fn ply_header(bytes: &[u8]) -> Result<String, Box<dyn std::error::Error>> {
    let end = bytes
        .windows(b"end_header\n".len())
        .position(|w| w == b"end_header\n")
        .ok_or("no end_header")?;
    Ok(String::from_utf8(
        bytes[..end + b"end_header\n".len()].to_vec(),
    )?)
}

/// The sphere with a colour per vertex from its position, and the extremes 0 and 1 on
/// the first vertices.
#[cfg(feature = "occupancy")]
fn coloured_sphere() -> Result<Mesh, neural_fields::Error> {
    let m = sphere_mesh();
    let mut colors: Vec<[f64; 3]> = m
        .vertices
        .iter()
        .map(|p| [p[0] + 0.5, p[1] + 0.5, p[2] + 0.5])
        .collect();
    colors[0] = [0.0, 1.0, 0.5];
    colors[1] = [1.0, 1.0, 1.0];
    colors[2] = [0.0, 0.0, 0.0];
    colors[3] = [0.5 / 255.0, 254.5 / 255.0, 1.0 / 3.0];
    let mut m = m;
    m.colors = Some(colors);
    m.validate()?;
    Ok(m)
}

/// `back` is `m` written through PLY: vertices (and normals) exact to f32 (the ASCII
/// text is the shortest decimal that reads back as the same f32), the same faces,
/// colours within half a step of 1/255.
#[cfg(feature = "occupancy")]
fn same_through_ply(m: &Mesh, back: &Mesh) -> TestResult {
    let f32s = |p: &[f64; 3]| p.map(|c| c as f32);
    assert_eq!(back.faces, m.faces);
    assert_eq!(back.vertices.len(), m.vertices.len());
    for (p, q) in m.vertices.iter().zip(&back.vertices) {
        assert_eq!(f32s(p), f32s(q));
    }
    assert_eq!(back.normals.is_some(), m.normals.is_some());
    if let (Some(a), Some(b)) = (&m.normals, &back.normals) {
        for (p, q) in a.iter().zip(b) {
            assert_eq!(f32s(p), f32s(q));
        }
    }
    let (a, b) = (
        m.colors.as_ref().ok_or("input without colours")?,
        back.colors.as_ref().ok_or("colours lost")?,
    );
    assert_eq!(a.len(), b.len());
    for (p, q) in a.iter().zip(b) {
        for c in 0..3 {
            assert!((p[c] - q[c]).abs() <= 0.5 / 255.0 + 1e-12, "{p:?} {q:?}");
            assert_eq!(
                (q[c] * 255.0).round() / 255.0,
                q[c],
                "not a multiple of 1/255"
            );
        }
    }
    Ok(())
}

#[cfg(feature = "occupancy")]
#[test]
fn coloured_mesh_round_trips_through_ascii_and_binary_ply_and_files() -> TestResult {
    let mut m = coloured_sphere()?;
    let dir = std::env::temp_dir().join(format!("nf_mesh_colors_{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    for with_normals in [false, true] {
        if with_normals {
            m.normals = Some(m.vertex_normals()?);
        }
        for fmt in [MeshFormat::PlyAscii, MeshFormat::PlyBinary] {
            let bytes = m.to_bytes(fmt)?;
            let header = ply_header(&bytes)?;
            let after = if with_normals { "nz" } else { "z" };
            assert!(
                header.contains(&format!(
                    "property float {after}\nproperty uchar red\nproperty uchar green\n\
                     property uchar blue\nelement face"
                )),
                "{header}"
            );
            same_through_ply(&m, &Mesh::from_bytes(&bytes, fmt)?)?;
        }
        let p = dir.join(format!("colored_{with_normals}.ply"));
        m.save(&p)?;
        same_through_ply(&m, &Mesh::load(&p)?)?;
        // OBJ has no standard for colours: they are dropped, the rest is kept.
        let obj = Mesh::from_bytes(&m.to_bytes(MeshFormat::Obj)?, MeshFormat::Obj)?;
        assert_eq!((obj.faces == m.faces, obj.colors), (true, None));
    }
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}

#[cfg(feature = "occupancy")]
#[test]
fn mesh_without_colours_writes_no_colour_properties() -> TestResult {
    let mut m = sphere_mesh();
    for with_normals in [false, true] {
        if with_normals {
            m.normals = Some(m.vertex_normals()?);
        }
        for fmt in [MeshFormat::PlyAscii, MeshFormat::PlyBinary] {
            let bytes = m.to_bytes(fmt)?;
            let header = ply_header(&bytes)?;
            for word in ["red", "green", "blue", "uchar red"] {
                assert!(!header.contains(word), "{word:?} in {header}");
            }
            assert_eq!(Mesh::from_bytes(&bytes, fmt)?.colors, None);
        }
    }
    Ok(())
}

/// A one-triangle ASCII PLY with the vertex properties `x y z` then `props`, each vertex
/// row `x y z` then the row of `values`.
fn ascii_ply_with(props: &str, values: [&str; 3]) -> String {
    let mut s = format!(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
         property float z\n{props}element face 1\nproperty list uchar int vertex_indices\n\
         end_header\n"
    );
    for (p, v) in ["0 0 0", "1 0 0", "0 1 0"].iter().zip(values) {
        s.push_str(&format!("{p} {v}\n"));
    }
    s.push_str("3 0 1 2\n");
    s
}

#[test]
fn ascii_ply_uchar_colours_load_divided_by_255_and_alpha_is_ignored() -> TestResult {
    let props = "property uchar red\nproperty uchar green\nproperty uchar blue\n\
                 property uchar alpha\n";
    let text = ascii_ply_with(props, ["255 0 0 128", "0 128 255 7", "10 20 30 255"]);
    let m = Mesh::from_bytes(text.as_bytes(), MeshFormat::PlyAscii)?;
    let expected: Vec<[f64; 3]> = [[255.0, 0.0, 0.0], [0.0, 128.0, 255.0], [10.0, 20.0, 30.0]]
        .iter()
        .map(|c| c.map(|x| x / 255.0))
        .collect();
    assert_eq!(m.colors, Some(expected));
    assert_eq!(m.faces, vec![[0, 1, 2]]);
    // Alpha before the colours is skipped too.
    let props = "property uchar alpha\nproperty uchar red\nproperty uchar green\n\
                 property uchar blue\n";
    let text = ascii_ply_with(props, ["9 255 255 255", "9 0 0 0", "9 51 51 51"]);
    let m = Mesh::from_bytes(text.as_bytes(), MeshFormat::PlyAscii)?;
    assert_eq!(m.colors, Some(vec![[1.0; 3], [0.0; 3], [51.0 / 255.0; 3]]));
    // Only some of red, green and blue: no colours, the mesh still loads.
    let text = ascii_ply_with(
        "property uchar red\nproperty uchar green\n",
        ["1 2", "3 4", "5 6"],
    );
    let m = Mesh::from_bytes(text.as_bytes(), MeshFormat::PlyAscii)?;
    assert_eq!((m.colors, m.faces.len()), (None, 1));
    // Other integer types are divided by their largest value.
    let text = ascii_ply_with(
        "property ushort red\nproperty ushort green\nproperty ushort blue\n",
        ["65535 0 0", "0 65535 0", "0 0 65535"],
    );
    let m = Mesh::from_bytes(text.as_bytes(), MeshFormat::PlyAscii)?;
    assert_eq!(
        m.colors,
        Some(vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    );
    Ok(())
}

#[test]
fn ascii_ply_float_colours_load_as_they_are() -> TestResult {
    let props = "property float red\nproperty float green\nproperty float blue\n";
    let text = ascii_ply_with(props, ["0.25 0.5 1", "0 0.75 0.125", "1 1 0"]);
    let m = Mesh::from_bytes(text.as_bytes(), MeshFormat::PlyAscii)?;
    assert_eq!(
        m.colors,
        Some(vec![[0.25, 0.5, 1.0], [0.0, 0.75, 0.125], [1.0, 1.0, 0.0]])
    );
    // Out of [0, 1]: an error naming colors, the vertex and its line.
    for bad in ["0 0.75 1.5", "0 -0.25 0.5", "0 nan 0.5"] {
        let text = ascii_ply_with(props, ["0.25 0.5 1", bad, "1 1 0"]);
        let e = match Mesh::from_bytes(text.as_bytes(), MeshFormat::PlyAscii) {
            Ok(m) => return Err(format!("{bad:?} loaded as {:?}", m.colors).into()),
            Err(e) => e.to_string(),
        };
        assert!(
            e.contains("colors") && e.contains("vertex 1") && e.contains("line 14"),
            "{e}"
        );
    }
    Ok(())
}

#[test]
fn bad_colours_are_rejected_naming_colors() -> TestResult {
    let tri = Mesh::new(
        vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        vec![[0, 1, 2]],
    )?;
    let good = [[0.0, 0.5, 1.0]; 3];
    let coloured = Mesh {
        colors: Some(good.to_vec()),
        ..tri.clone()
    };
    coloured.validate()?;
    assert_eq!(coloured.colors, Some(good.to_vec()));
    let cases: Vec<(Vec<[f64; 3]>, &str)> = vec![
        (vec![[0.0, f64::NAN, 0.0]; 3], "NaN"),
        (vec![[0.0, 0.5, -0.1]; 3], "-0.1"),
        (vec![[1.5, 0.5, 0.0]; 3], "1.5"),
        (vec![[0.0, f64::INFINITY, 0.0]; 3], "inf"),
        (vec![[0.5; 3]; 2], "2 colors for 3 vertices"),
        (vec![[0.5; 3]; 4], "4 colors for 3 vertices"),
    ];
    for (colors, needle) in cases {
        let literal = Mesh {
            colors: Some(colors),
            ..tri.clone()
        };
        let e = match literal.validate() {
            Ok(()) => return Err(format!("{needle:?}: accepted").into()),
            Err(e) => e.to_string(),
        };
        assert!(
            e.contains("colors") && e.contains(needle),
            "{needle:?} in {e}"
        );
        // Writers validate first.
        assert!(literal.to_bytes(MeshFormat::PlyBinary).is_err());
    }
    Ok(())
}

#[test]
fn binary_ply_double_colours_load_and_out_of_range_names_the_byte() -> TestResult {
    let header = "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n\
                  property float y\nproperty float z\nproperty double red\n\
                  property double green\nproperty double blue\nelement face 1\n\
                  property list uchar int vertex_indices\nend_header\n";
    let file = |colors: [[f64; 3]; 3]| {
        let mut b = header.as_bytes().to_vec();
        for (v, c) in [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
            .iter()
            .zip(colors)
        {
            v.iter().for_each(|x| b.extend_from_slice(&x.to_le_bytes()));
            c.iter().for_each(|x| b.extend_from_slice(&x.to_le_bytes()));
        }
        b.push(3);
        (0..3i32).for_each(|k| b.extend_from_slice(&k.to_le_bytes()));
        b
    };
    let good = [[0.1, 0.2, 0.3], [1.0, 0.0, 0.5], [0.0, 1.0, 1.0 / 3.0]];
    let m = Mesh::from_bytes(&file(good), MeshFormat::PlyBinary)?;
    assert_eq!(m.colors, Some(good.to_vec()));
    let bad = [good[0], [1.0, 1.0 + 1e-9, 0.5], good[2]];
    let e = match Mesh::from_bytes(&file(bad), MeshFormat::PlyBinary) {
        Ok(m) => return Err(format!("loaded as {:?}", m.colors).into()),
        Err(e) => e.to_string(),
    };
    // Vertex 1 starts one 36-byte row after the header.
    let at = format!("byte {}", header.len() + 36);
    assert!(
        e.contains("colors") && e.contains("vertex 1") && e.contains(&at),
        "{e}"
    );
    Ok(())
}
