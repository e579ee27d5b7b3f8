use std::path::Path;

use deocc_geometry::{DepthMap, Intrinsics, PointCloud};
use deocc_io::cameras::{read_cameras_json, write_cameras_json, FrameCamera};
use deocc_io::images::{
    read_depth_png, read_instance_png, write_depth_png, write_instance_png, write_rgb_png,
    InstanceMap,
};
use deocc_io::mesh::read_mesh;
use deocc_io::ply::{read_ply, write_mesh};
use deocc_io::{read_point_cloud, write_point_cloud, PlyEncoding};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

/// A cloud with awkward floats (tiny, huge, negative zero, subnormal) and every attribute.
fn awkward_cloud() -> PointCloud {
    let mut state = 0x1234_5678_9abc_def0u64;
    let mut next = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let mut positions: Vec<Point3<f32>> = (0..1000)
        .map(|_| {
            let f = |b: u64| {
                f32::from_bits((b as u32 & 0x807f_ffff) | (((b >> 32) as u32 % 60 + 100) << 23))
            };
            Point3::new(f(next()), f(next()), f(next()))
        })
        .collect();
    positions.push(Point3::new(-0.0, 1e-30, f32::MIN_POSITIVE / 4.0));
    positions.push(Point3::new(f32::MAX, -f32::MAX, 0.1));
    let n = positions.len();
    PointCloud {
        colors: Some(
            (0..n)
                .map(|i| [(i % 256) as u8, (i * 7 % 256) as u8, 255])
                .collect(),
        ),
        normals: Some(
            (0..n)
                .map(|i| Vector3::new(i as f32 * 0.001, -0.5, 0.25))
                .collect(),
        ),
        instance: Some(
            (0..n)
                .map(|i| (i as u32).wrapping_mul(2_654_435_761))
                .collect(),
        ),
        generated: Some((0..n).map(|i| (i % 4) as u8).collect()),
        confidence: Some(
            (0..n)
                .map(|i| {
                    if i % 4 == 0 {
                        1.0
                    } else {
                        (i % 97) as f32 / 96.0
                    }
                })
                .collect(),
        ),
        expected_error: Some((0..n).map(|i| (i % 5) as f32 * 0.003_7).collect()),
        positions,
    }
}

fn bits(c: &PointCloud) -> Vec<u32> {
    c.positions
        .iter()
        .flat_map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
        .collect()
}

#[test]
fn ply_round_trips_bit_exactly_in_every_encoding() {
    let dir = tempfile::tempdir().unwrap();
    let cloud = awkward_cloud();
    for enc in [
        PlyEncoding::Ascii,
        PlyEncoding::BinaryLittleEndian,
        PlyEncoding::BinaryBigEndian,
    ] {
        let path = dir.path().join(format!("{enc:?}.ply"));
        write_point_cloud(&path, &cloud, enc).unwrap();
        let back = read_point_cloud(&path).unwrap();
        assert_eq!(bits(&back), bits(&cloud), "{enc:?}");
        assert_eq!(back.colors, cloud.colors);
        assert_eq!(back.instance, cloud.instance);
        assert_eq!(back.generated, cloud.generated);
        assert_eq!(back.confidence, cloud.confidence, "{enc:?}");
        assert_eq!(back.expected_error, cloud.expected_error, "{enc:?}");
        let nb: Vec<u32> = back
            .normals
            .unwrap()
            .iter()
            .flat_map(|n| n.iter().map(|v| v.to_bits()).collect::<Vec<_>>())
            .collect();
        let na: Vec<u32> = cloud
            .normals
            .as_ref()
            .unwrap()
            .iter()
            .flat_map(|n| n.iter().map(|v| v.to_bits()).collect::<Vec<_>>())
            .collect();
        assert_eq!(nb, na);
    }
}

#[test]
fn ply_mesh_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let verts = PointCloud::from_positions(vec![
        Point3::origin(),
        Point3::new(1.0, 0.0, 0.0),
        Point3::new(0.0, 1.0, 0.0),
        Point3::new(1.0, 1.0, 0.0),
    ]);
    let tris = vec![[0, 1, 2], [1, 3, 2]];
    for enc in [PlyEncoding::Ascii, PlyEncoding::BinaryLittleEndian] {
        let path = dir.path().join("m.ply");
        write_mesh(&path, &verts, &tris, enc).unwrap();
        let m = read_ply(&path).unwrap();
        assert_eq!(m.triangles, tris);
        assert_eq!(m.vertices.positions, verts.positions);
    }
}

fn err_text(r: Result<impl std::fmt::Debug, deocc_io::IoError>) -> String {
    r.expect_err("expected an error").to_string()
}

#[test]
fn ply_errors_name_the_file_and_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("good.ply");
    write_point_cloud(&good, &awkward_cloud(), PlyEncoding::BinaryLittleEndian).unwrap();
    let bytes = std::fs::read(&good).unwrap();

    let truncated = dir.path().join("truncated.ply");
    std::fs::write(&truncated, &bytes[..bytes.len() - 7]).unwrap();
    let e = err_text(read_point_cloud(&truncated));
    assert!(
        e.contains("truncated.ply") && e.contains("truncated"),
        "{e}"
    );

    let cases: [(&str, &[u8], &str); 8] = [
        ("notply.ply", b"hello\n", "does not start with 'ply'"),
        ("noformat.ply", b"ply\nelement vertex 1\nproperty float x\nend_header\n", "no 'format'"),
        ("badtype.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quux x\nend_header\n", "unknown type"),
        ("noxyz.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n", "lacks x, y or z"),
        ("nan.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 nan 2\n", "non-finite"),
        ("conf.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nproperty float confidence\nend_header\n0 0 0 1\n1 2 3 1.5\n", "vertex 1 has confidence 1.5"),
        ("err.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nproperty float expected_error\nend_header\n0 0 0 0\n1 2 3 -0.01\n", "vertex 1 has expected_error -0.01"),
        ("empty.ply", b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n", "no points"),
    ];
    for (name, content, expect) in cases {
        let p = dir.path().join(name);
        std::fs::write(&p, content).unwrap();
        let e = err_text(read_point_cloud(&p));
        assert!(e.contains(name) && e.contains(expect), "{name}: {e}");
    }
    let badface = dir.path().join("badface.ply");
    std::fs::write(&badface, b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n3 0 1 2\n").unwrap();
    assert!(err_text(read_ply(&badface)).contains("only 1"));
    let missing = dir.path().join("missing.ply");
    assert!(err_text(read_point_cloud(&missing)).contains("missing.ply"));
}

#[test]
fn writing_a_non_finite_cloud_fails_and_leaves_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bad.ply");
    let cloud = PointCloud::from_positions(vec![Point3::new(f32::NAN, 0.0, 0.0)]);
    assert!(write_point_cloud(&p, &cloud, PlyEncoding::Ascii).is_err());
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    // An unwritable place: error naming it, nothing created.
    let nowhere = dir.path().join("no/such/dir/x.ply");
    let e = err_text(write_point_cloud(
        &nowhere,
        &awkward_cloud(),
        PlyEncoding::Ascii,
    ));
    assert!(e.contains("x.ply"), "{e}");
}

#[test]
fn depth_png_round_trips_in_millimetres() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("d.png");
    let data: Vec<f32> = (0..64 * 48)
        .map(|i| {
            if i % 5 == 0 {
                0.0
            } else {
                0.5 + i as f32 * 0.001
            }
        })
        .collect();
    let depth = DepthMap::new(64, 48, data.clone()).unwrap();
    write_depth_png(&p, &depth).unwrap();
    let back = read_depth_png(&p).unwrap();
    assert_eq!((back.width(), back.height()), (64, 48));
    for (a, b) in back.data().iter().zip(&data) {
        assert!((a - b).abs() <= 0.0005 + 1e-6, "{a} vs {b}");
    }
}

#[test]
fn depth_png_rejects_8_bit_and_corrupt_files() {
    let dir = tempfile::tempdir().unwrap();
    let rgb = dir.path().join("rgb.png");
    write_rgb_png(&rgb, &image::RgbImage::new(4, 4)).unwrap();
    let e = err_text(read_depth_png(&rgb));
    assert!(e.contains("rgb.png") && e.contains("16-bit"), "{e}");
    let corrupt = dir.path().join("corrupt.png");
    std::fs::write(&corrupt, b"\x89PNG\r\n\x1a\nnot really").unwrap();
    assert!(err_text(read_depth_png(&corrupt)).contains("corrupt.png"));
}

#[test]
fn instance_png_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("i.png");
    let map = InstanceMap {
        width: 8,
        height: 4,
        ids: (0..32).map(|i| i * 1000).collect(),
    };
    write_instance_png(&p, &map).unwrap();
    assert_eq!(read_instance_png(&p).unwrap(), map);
}

#[test]
fn cameras_json_round_trips_and_validates() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("cameras.json");
    let pose = Isometry3::from_parts(
        Translation3::new(1.0, 2.0, 3.0),
        UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3),
    );
    let frames = vec![
        FrameCamera {
            name: "a".into(),
            intrinsics: Intrinsics::new(500.0, 510.0, 320.0, 240.0, 640, 480).unwrap(),
            world_from_camera: Some(pose),
            lens: Default::default(),
        },
        FrameCamera {
            name: "b".into(),
            intrinsics: Intrinsics::new(500.0, 510.0, 320.0, 240.0, 640, 480).unwrap(),
            world_from_camera: None,
            lens: Default::default(),
        },
    ];
    write_cameras_json(&p, &frames).unwrap();
    let back = read_cameras_json(&p).unwrap();
    assert_eq!(back.len(), 2);
    assert_eq!(back[0].intrinsics, frames[0].intrinsics);
    let d = back[0].world_from_camera.unwrap().inverse() * pose;
    assert!(d.translation.vector.norm() < 1e-6 && d.rotation.angle() < 1e-6);
    assert!(back[1].world_from_camera.is_none());

    let bad_focal = dir.path().join("bad_focal.json");
    std::fs::write(&bad_focal, r#"{"frames":[{"name":"x","intrinsics":{"fx":0,"fy":1,"cx":0,"cy":0,"width":4,"height":4}}]}"#).unwrap();
    let e = err_text(read_cameras_json(&bad_focal));
    assert!(e.contains("bad_focal.json") && e.contains("focal"), "{e}");
    let bad_pose = dir.path().join("bad_pose.json");
    std::fs::write(&bad_pose, r#"{"frames":[{"name":"x","intrinsics":{"fx":1,"fy":1,"cx":0,"cy":0,"width":4,"height":4},"world_from_camera":[[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#).unwrap();
    assert!(err_text(read_cameras_json(&bad_pose)).contains("orthonormal"));
}

#[test]
fn obj_and_stl_meshes_load() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("quad.obj");
    std::fs::write(
        &obj,
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1/1 2/2 3/3 4/4\n",
    )
    .unwrap();
    let m = read_mesh(&obj).unwrap();
    assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    let stl = dir.path().join("tri.stl");
    std::fs::write(&stl, "solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid\n").unwrap();
    assert_eq!(read_mesh(&stl).unwrap().triangles.len(), 1);
    // Binary STL: 80-byte header, count, one triangle.
    let mut b = vec![0u8; 80];
    b.extend_from_slice(&1u32.to_le_bytes());
    for v in [0f32, 0., 1., 0., 0., 0., 1., 0., 0., 0., 1., 0.] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    b.extend_from_slice(&[0, 0]);
    let bstl = dir.path().join("bin.stl");
    std::fs::write(&bstl, &b).unwrap();
    let m = read_mesh(&bstl).unwrap();
    assert_eq!(m.vertices.positions[1], Point3::new(1.0, 0.0, 0.0));
    let bad = dir.path().join("bad.obj");
    std::fs::write(&bad, "v 0 0 0\nf 1 2 3\n").unwrap();
    assert!(err_text(read_mesh(&bad)).contains("out of range"));
    assert!(err_text(read_mesh(Path::new("x.fbx"))).contains("unknown mesh format"));
}

/// A PLY header that declares far more rows than the file can hold is refused before anything is
/// allocated (2^44 vertices in a 300-byte file, and u64::MAX).
#[test]
fn lying_ply_headers_are_refused_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    for count in ["17592186044416", "18446744073709551615", "9999999999999"] {
        for format in ["binary_little_endian", "ascii"] {
            let path = dir.path().join("lie.ply");
            let mut bytes = format!(
                "ply\nformat {format} 1.0\nelement vertex {count}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
            )
            .into_bytes();
            bytes.extend_from_slice(&[0u8; 120]);
            std::fs::write(&path, &bytes).unwrap();
            let e = deocc_io::ply::read_ply(&path).unwrap_err().to_string();
            assert!(
                e.contains("lie.ply") && e.contains("declares"),
                "{count} {format}: {e}"
            );
        }
    }
}

/// The CRC-32 of PNG chunks.
fn crc32(data: &[u8]) -> u32 {
    let mut crc = 0xffff_ffffu32;
    for &b in data {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xedb8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// A PNG whose header claims a size other than the camera's (or a decompression bomb: 15,000 x
/// 15,000 pixels in a few hundred bytes) is refused from its header, before decoding.
#[test]
fn png_sizes_are_checked_before_decoding() {
    use deocc_io::images::{read_depth_png_expecting, read_rgb_png, write_rgb_png};
    let dir = tempfile::tempdir().unwrap();
    let small = dir.path().join("small.png");
    write_rgb_png(&small, &image::RgbImage::new(4, 3)).unwrap();
    let mut png = std::fs::read(&small).unwrap();
    // IHDR is the first chunk: length (4), type (4), width (4), height (4), ..., CRC after 13 bytes.
    png[16..20].copy_from_slice(&15_000u32.to_be_bytes());
    png[20..24].copy_from_slice(&15_000u32.to_be_bytes());
    let crc = crc32(&png[12..29]);
    png[29..33].copy_from_slice(&crc.to_be_bytes());
    let bomb = dir.path().join("bomb.png");
    std::fs::write(&bomb, &png).unwrap();
    let e = read_depth_png_expecting(&bomb, Some((640, 480)))
        .unwrap_err()
        .to_string();
    assert!(e.contains("bomb.png") && e.contains("15000x15000"), "{e}");
    let e = read_rgb_png(&bomb).unwrap_err().to_string();
    assert!(e.contains("bomb.png") && e.contains("larger than"), "{e}");
}

/// Cameras whose numbers are implausible (a unit mistake) or not representable are refused,
/// naming cameras.json.
#[test]
fn implausible_cameras_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cameras.json");
    let frame = |k: &str, t: &str| {
        format!(
            r#"{{"frames":[{{"name":"a","intrinsics":{k},"world_from_camera":[[1,0,0,{t}],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}}]}}"#
        )
    };
    let ok_k = r#"{"fx":500,"fy":500,"cx":320,"cy":240,"width":640,"height":480}"#;
    for (k, t, expect) in [
        (
            r#"{"fx":1e-30,"fy":500,"cx":320,"cy":240,"width":640,"height":480}"#,
            "0",
            "fx",
        ),
        (
            r#"{"fx":500,"fy":500,"cx":1e30,"cy":240,"width":640,"height":480}"#,
            "0",
            "principal point",
        ),
        (ok_k, "1e39", "translation"),
        (
            r#"{"fx":500,"fy":500,"cx":320,"cy":240,"width":99999,"height":480}"#,
            "0",
            "image size",
        ),
    ] {
        std::fs::write(&path, frame(k, t)).unwrap();
        let e = deocc_io::cameras::read_cameras_json(&path)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("cameras.json") && e.contains(expect),
            "{k} {t}: {e}"
        );
    }
    std::fs::write(&path, frame(ok_k, "0.5")).unwrap();
    assert!(deocc_io::cameras::read_cameras_json(&path).is_ok());
}

/// Two pairs at 2x2 with every field filled (distinct values, so a swapped field shows).
fn two_pairs() -> deocc_io::pairs::PairSet {
    let (n, px) = (2, 4);
    deocc_io::pairs::PairSet {
        resolution: 2,
        crop_rgb: (0..n * px * 3).map(|i| i as u8).collect(),
        visible_mask: vec![1, 0, 1, 0, 0, 1, 1, 0],
        visible_depth: (0..n * px).map(|i| i as f32 * 0.1).collect(),
        scene_depth: (0..n * px).map(|i| -(i as f32) * 0.05).collect(),
        whole_rgb: (0..n * px * 3).map(|i| 200 - i as u8).collect(),
        amodal_mask: vec![1, 1, 1, 0, 0, 1, 1, 1],
        whole_depth: (0..n * px).map(|i| i as f32 * 0.2).collect(),
        whole_back_depth: (0..n * px).map(|i| i as f32 * 0.3).collect(),
        group: vec![7, 9],
        category: vec![3, 6],
        held_out: vec![0, 1],
        occlusion: vec![0.25, 0.5],
        crop_width_m: vec![0.31, 1.52],
        elsewhere_rgb: Vec::new(),
        elsewhere_depth: Vec::new(),
    }
}

/// Pairs keep each crop's metric width; a shard written before it was stored (no
/// `crop_width_m` tensor) still loads, its widths unknown (NaN), everything else the same.
#[test]
fn pairs_round_trip_with_crop_width_and_older_shards_load_without_it() {
    use deocc_io::pairs::{load_pairs, save_pairs};
    use safetensors::tensor::TensorView;
    let dir = tempfile::tempdir().unwrap();
    let set = two_pairs();
    let path = dir.path().join("pairs.safetensors");
    save_pairs(&path, &set).unwrap();
    assert_eq!(load_pairs(&path).unwrap(), set);

    // The same shard without the tensor.
    let bytes = std::fs::read(&path).unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let views: Vec<(String, TensorView)> = st
        .tensors()
        .into_iter()
        .filter(|(name, _)| name != "crop_width_m")
        .collect();
    assert_eq!(views.len(), st.len() - 1);
    let old = dir.path().join("old.safetensors");
    std::fs::write(&old, safetensors::serialize(views, None).unwrap()).unwrap();
    let mut loaded = load_pairs(&old).unwrap();
    assert_eq!(loaded.crop_width_m.len(), 2);
    assert!(loaded.crop_width_m.iter().all(|w| w.is_nan()));
    // Everything else as written.
    loaded.crop_width_m = set.crop_width_m.clone();
    assert_eq!(loaded, set);

    // Truncating and extending keep the widths with their pairs.
    let mut both = set.clone();
    both.extend(&set);
    both.truncate(3);
    assert_eq!(both.crop_width_m, vec![0.31, 1.52, 0.31]);
    assert_eq!(both.len(), 3);
}

/// Other views' observations travel with their pairs: saved and loaded, truncated, and a set
/// without them extended by one with them (and the reverse) gives its own pairs none.
#[test]
fn pairs_keep_other_views_observations_and_sets_without_them_mix_in() {
    use deocc_io::pairs::{load_pairs, save_pairs};
    let dir = tempfile::tempdir().unwrap();
    let plain = two_pairs();
    let mut seen = two_pairs();
    seen.elsewhere_rgb = (0..2 * 4 * 3).map(|i| 100 + i as u8).collect();
    seen.elsewhere_depth = vec![0.1, f32::INFINITY, -0.2, 0.3, f32::INFINITY, 0.0, 0.5, -0.5];
    assert!(seen.has_elsewhere() && !plain.has_elsewhere());
    let path = dir.path().join("seen.safetensors");
    save_pairs(&path, &seen).unwrap();
    assert_eq!(load_pairs(&path).unwrap(), seen);
    save_pairs(&path, &plain).unwrap();
    assert!(!load_pairs(&path).unwrap().has_elsewhere());

    let mut mixed = plain.clone();
    mixed.extend(&seen);
    assert_eq!(mixed.len(), 4);
    assert!(mixed.elsewhere_depth[..8].iter().all(|d| d.is_infinite()));
    assert_eq!(mixed.elsewhere_depth[8..], seen.elsewhere_depth[..]);
    assert_eq!(mixed.elsewhere_rgb[24..], seen.elsewhere_rgb[..]);
    let mut other_way = seen.clone();
    other_way.extend(&plain);
    assert_eq!(other_way.elsewhere_depth[..8], seen.elsewhere_depth[..]);
    assert!(other_way.elsewhere_depth[8..]
        .iter()
        .all(|d| d.is_infinite()));
    other_way.truncate(1);
    assert_eq!(
        other_way.elsewhere_depth,
        seen.elsewhere_depth[..4].to_vec()
    );
    assert_eq!(other_way.elsewhere_rgb, seen.elsewhere_rgb[..12].to_vec());
    save_pairs(&path, &mixed).unwrap();
    assert_eq!(load_pairs(&path).unwrap(), mixed);
}

#[test]
fn half_turn_camera_poses_are_read_as_written() {
    // nalgebra's iterative `Rotation3::from_matrix` returns the identity for a half-turn: a
    // camera looking back read as one looking forward, its points 1 m and more off, exit 0.
    let rows = [
        [-1.0, 0.0, 0.0, 0.3],
        [0.0, 1.0, 0.0, -0.1],
        [0.0, 0.0, -1.0, 1.2],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let pose = deocc_io::cameras::pose_from_rows(&rows).unwrap();
    let back = deocc_io::cameras::pose_to_rows(&pose);
    for r in 0..4 {
        for c in 0..4 {
            assert!(
                (rows[r][c] - back[r][c]).abs() < 1e-6,
                "entry ({r}, {c}): {} became {}",
                rows[r][c],
                back[r][c]
            );
        }
    }
    // Every half-turn about the axes and their diagonals, through cameras.json.
    let axes = [
        Vector3::x(),
        Vector3::y(),
        Vector3::z(),
        Vector3::new(1.0, 1.0, 0.0),
        Vector3::new(0.0, 1.0, -1.0),
        Vector3::new(1.0, 1.0, 1.0),
    ];
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cameras.json");
    let frames: Vec<FrameCamera> = axes
        .iter()
        .enumerate()
        .map(|(k, a)| FrameCamera {
            name: format!("{k}"),
            intrinsics: Intrinsics::new(500.0, 500.0, 320.0, 240.0, 640, 480).unwrap(),
            world_from_camera: Some(Isometry3::from_parts(
                Translation3::new(0.1, 0.2, 0.3),
                UnitQuaternion::from_axis_angle(
                    &nalgebra::Unit::new_normalize(*a),
                    std::f32::consts::PI,
                ),
            )),
            lens: Default::default(),
        })
        .collect();
    write_cameras_json(&path, &frames).unwrap();
    let read = read_cameras_json(&path).unwrap();
    for (w, r) in frames.iter().zip(&read) {
        let (w, r) = (w.world_from_camera.unwrap(), r.world_from_camera.unwrap());
        let p = Point3::new(0.3, -0.5, 1.0);
        assert!(
            (w * p - r * p).norm() < 1e-5,
            "frame {}: a point moved {} m",
            w.translation.vector,
            (w * p - r * p).norm()
        );
    }
}

/// A header line has a length cap: a 2 GB file of zeros (or a link to /dev/zero) held all of it
/// in one `read_line` (4.3 GB, 16 GB). Endless zeros, endless newlines and a long body line are
/// refused at once, naming the file.
#[test]
fn endless_ply_input_is_refused_without_holding_it() {
    use std::io::{BufReader, Read};
    let name = Path::new("zeros.ply");
    let zeros = BufReader::new(std::io::repeat(0));
    let e = deocc_io::ply::read_ply_from(name, zeros)
        .unwrap_err()
        .to_string();
    assert!(e.contains("zeros.ply") && e.contains("longer than"), "{e}");
    let header = std::io::Cursor::new(b"ply\n".to_vec()).chain(std::io::repeat(b'\n'));
    let e = deocc_io::ply::read_ply_from(name, BufReader::new(header))
        .unwrap_err()
        .to_string();
    assert!(e.contains("end_header"), "{e}");
    let body = std::io::Cursor::new(
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
            .to_vec(),
    )
    .chain(std::io::repeat(b'1'));
    let e = deocc_io::ply::read_ply_from(name, BufReader::new(body))
        .unwrap_err()
        .to_string();
    assert!(e.contains("longer than"), "{e}");
    #[cfg(unix)]
    {
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("ground_truth.ply");
        std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
        let e = err_text(read_ply(&link));
        assert!(e.contains("ground_truth.ply"), "{e}");
    }
}

/// Options documents must be JSON objects: serde reads a struct from an array field by field, so
/// `[]` was "all defaults" and `[4]` set the first field, without a word.
#[test]
fn options_documents_must_be_objects() {
    #[derive(serde::Deserialize, Debug, Default)]
    #[serde(default, deny_unknown_fields)]
    struct Settings {
        first: u32,
        second: f32,
    }
    let ok: Settings = deocc_io::cameras::options_from_json(r#"{"second": 2.5}"#).unwrap();
    assert_eq!((ok.first, ok.second), (0, 2.5));
    for text in ["[]", "[4]", "[4, 1.0]", "null", "7", "\"x\""] {
        let e = deocc_io::cameras::options_from_json::<Settings>(text).unwrap_err();
        assert!(e.contains("expected a JSON object"), "{text}: {e}");
    }
    let e = deocc_io::cameras::options_from_json::<Settings>(r#"{"thrid": 1}"#).unwrap_err();
    assert!(e.contains("thrid"), "{e}");
}

/// A scene folder with one frame: depth given as `write_depth` writes it, `cameras.json` given
/// as `frame` (a JSON object without the name).
fn one_frame_scene(dir: &Path, frame: serde_json::Value, write_depth: impl FnOnce(&Path)) {
    let mut frame = frame;
    frame["name"] = "f".into();
    std::fs::create_dir_all(dir.join("rgb")).unwrap();
    std::fs::create_dir_all(dir.join("depth")).unwrap();
    let (w, h) = (
        frame["intrinsics"]["width"].as_u64().unwrap() as u32,
        frame["intrinsics"]["height"].as_u64().unwrap() as u32,
    );
    deocc_io::images::write_rgb_png(&dir.join("rgb/f.png"), &image::RgbImage::new(w, h)).unwrap();
    write_depth(&dir.join("depth"));
    std::fs::write(
        dir.join("cameras.json"),
        serde_json::json!({ "frames": [frame] }).to_string(),
    )
    .unwrap();
}

#[test]
fn depth_units_are_read_as_stated() {
    let tmp = tempfile::tempdir().unwrap();
    let intr =
        serde_json::json!({"fx": 50.0, "fy": 50.0, "cx": 2.0, "cy": 1.5, "width": 4, "height": 3});
    // 1.234 m everywhere, as an SR300 counts it (1/8 mm), as TUM does (1/5000 m) and as float32.
    let truth = 1.234f32;
    let write_u16 = |p: &Path, units: u16| {
        let img =
            image::ImageBuffer::<image::Luma<u16>, _>::from_raw(4, 3, vec![units; 12]).unwrap();
        img.save(p.join("f.png")).unwrap();
    };
    for (scale, units, tol) in [
        (0.000125, 9872u16, 1e-6),
        (0.0002, 6170, 1e-6),
        (0.001, 1234, 1e-6),
    ] {
        let dir = tmp.path().join(format!("s{units}"));
        one_frame_scene(
            &dir,
            serde_json::json!({"intrinsics": intr, "depth_scale": scale}),
            |p| write_u16(p, units),
        );
        let scene = deocc_io::scene::read_scene(&dir).unwrap();
        let got = scene.frames[0].depth.get(1, 1);
        assert!((got - truth).abs() < tol, "scale {scale}: {got}");
    }
    let dir = tmp.path().join("npy");
    one_frame_scene(&dir, serde_json::json!({"intrinsics": intr}), |p| {
        std::fs::write(
            p.join("f.npy"),
            deocc_io::npy::depth_npy_bytes(4, 3, &[truth; 12]),
        )
        .unwrap()
    });
    let scene = deocc_io::scene::read_scene(&dir).unwrap();
    assert_eq!(scene.frames[0].depth.get(3, 2), truth);
    // A scale outside its range is refused, naming the field.
    let dir = tmp.path().join("bad");
    one_frame_scene(
        &dir,
        serde_json::json!({"intrinsics": intr, "depth_scale": 1000.0}),
        |p| write_u16(p, 1),
    );
    let e = deocc_io::scene::read_scene(&dir).unwrap_err().to_string();
    assert!(
        e.contains("depth_scale") && e.contains("cameras.json"),
        "{e}"
    );
}

#[test]
fn a_separate_depth_camera_is_registered_to_colour() {
    // A wall 1.5 m away seen by a 6x4 depth camera 2 cm to the colour camera's left: every
    // registered colour pixel is the wall, at the colour camera's own depth of it.
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("s");
    let frame = serde_json::json!({
        "intrinsics": {"fx": 20.0, "fy": 20.0, "cx": 4.0, "cy": 3.0, "width": 8, "height": 6},
        "depth_camera": {
            "intrinsics": {"fx": 12.0, "fy": 12.0, "cx": 3.0, "cy": 2.0, "width": 6, "height": 4},
            "color_from_depth": [[1,0,0,-0.02],[0,1,0,0],[0,0,1,0],[0,0,0,1]]
        }
    });
    one_frame_scene(&dir, frame, |p| {
        let img =
            image::ImageBuffer::<image::Luma<u16>, _>::from_raw(6, 4, vec![1500u16; 24]).unwrap();
        img.save(p.join("f.png")).unwrap();
    });
    let scene = deocc_io::scene::read_scene(&dir).unwrap();
    let d = &scene.frames[0].depth;
    assert_eq!((d.width(), d.height()), (8, 6));
    assert!(
        d.valid_count() >= 40,
        "{} of 48 colour pixels have depth",
        d.valid_count()
    );
    for &z in d.data() {
        assert!(z == 0.0 || (z - 1.5).abs() < 1e-5, "{z}");
    }
    // The depth image must have the depth camera's size.
    let dir = tmp.path().join("wrong-size");
    let frame = serde_json::json!({
        "intrinsics": {"fx": 20.0, "fy": 20.0, "cx": 4.0, "cy": 3.0, "width": 8, "height": 6},
        "depth_camera": {
            "intrinsics": {"fx": 12.0, "fy": 12.0, "cx": 3.0, "cy": 2.0, "width": 6, "height": 4},
            "color_from_depth": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]
        }
    });
    one_frame_scene(&dir, frame, |p| {
        let img =
            image::ImageBuffer::<image::Luma<u16>, _>::from_raw(8, 6, vec![1500u16; 48]).unwrap();
        img.save(p.join("f.png")).unwrap();
    });
    let e = deocc_io::scene::read_scene(&dir).unwrap_err().to_string();
    assert!(e.contains("6x4"), "{e}");
}
