//! Vertex normals from mesh files become shading normals: OBJ `vn`, PLY
//! `nx ny nz` and glTF `NORMAL`, carried through the scene file's
//! transform by its inverse transpose and normalised. A file that gives
//! normals for some faces only is shaded flat, and a normal that is not a
//! finite number is an error naming its line or element.

use glam::Vec3;
use locus_core::error::{Location, SceneError};
use locus_core::scene::Scene;
use std::path::{Path, PathBuf};

fn temp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("locus-mesh-normals-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A scene of one mesh file, scaled by `scale` along x.
fn scene_of(dir: &Path, mesh: &str, scale: f32) -> PathBuf {
    let toml = format!(
        "[camera]\nposition = [0.0, 0.0, 5.0]\nlook_at = [0.0, 0.0, 0.0]\nfov_y = 40.0\n\
         resolution = [8, 8]\n\n[[mesh]]\nfile = \"{mesh}\"\n\
         transform = {{ scale = [{scale}, 1.0, 1.0] }}\n"
    );
    let p = dir.join("scene.toml");
    std::fs::write(&p, toml).unwrap();
    p
}

/// Two triangles of a quad in the z = 0 plane, with normals tilted by
/// (1, 1, 0) away from +z at the first vertex.
const OBJ: &str = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n\
                   vn 1 1 1\nvn 0 0 1\nvn 0 0 2\n\
                   f 1//1 2//2 3//3\nf 1//1 3//3 4//2\n";

fn close(a: Vec3, b: Vec3) -> bool {
    (a - b).length() < 1e-6
}

#[test]
fn obj_normals_go_through_the_transform() {
    let d = temp("obj");
    std::fs::write(d.join("quad.obj"), OBJ).unwrap();
    let s = Scene::load(&scene_of(&d, "quad.obj", 2.0)).unwrap();
    assert_eq!(s.load_stats.shaded, 2);
    assert_eq!(s.tri_normals.len(), 2);
    // (1, 1, 1) under x scaled by 2: the inverse transpose halves x.
    let want = Vec3::new(0.5, 1.0, 1.0).normalize();
    assert!(close(s.tri_normals[0][0], want), "{:?}", s.tri_normals[0]);
    // Unnormalised normals come out of unit length.
    assert!(close(s.tri_normals[0][2], Vec3::Z));
    assert!(close(s.tri_normals[1][2], Vec3::Z));
}

#[test]
fn an_obj_with_normals_on_some_faces_only_is_flat() {
    let d = temp("partial");
    let text = OBJ.replace("f 1//1 3//3 4//2", "f 1 3 4");
    std::fs::write(d.join("quad.obj"), text).unwrap();
    let s = Scene::load(&scene_of(&d, "quad.obj", 1.0)).unwrap();
    assert_eq!(s.tris.len(), 2);
    assert!(s.tri_normals.is_empty());
    assert_eq!(s.load_stats.shaded, 0);
}

#[test]
fn bad_obj_normals_name_their_line() {
    let d = temp("badobj");
    for (bad, kind) in [
        ("vn 0 nan 1", "Syntax"),
        ("vn 0 1", "Syntax"),
        ("vn 0 1e40 1", "Syntax"),
    ] {
        let text = OBJ.replace("vn 0 0 1", bad);
        std::fs::write(d.join("quad.obj"), text).unwrap();
        let e = Scene::load(&scene_of(&d, "quad.obj", 1.0)).unwrap_err();
        assert!(e.file().ends_with("quad.obj"), "{e}");
        assert!(
            matches!(e.location(), Some(Location::Line { line: 6, .. })),
            "{bad}: {e}"
        );
        assert_eq!(variant(&e), kind, "{bad}: {e}");
    }
}

fn variant(e: &SceneError) -> &'static str {
    match e {
        SceneError::Syntax { .. } => "Syntax",
        SceneError::NonFinite { .. } => "NonFinite",
        SceneError::Invalid { .. } => "Invalid",
        _ => "other",
    }
}

#[test]
fn ply_normals_are_read_and_checked() {
    let d = temp("ply");
    let ply = |n1: &str| {
        format!(
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
             property float z\nproperty float nx\nproperty float ny\nproperty float nz\n\
             element face 1\nproperty list uchar int vertex_indices\nend_header\n\
             0 0 0 0 0 1\n1 0 0 {n1}\n0 1 0 0 0 3\n3 0 1 2\n"
        )
    };
    std::fs::write(d.join("tri.ply"), ply("0 1 1")).unwrap();
    let s = Scene::load(&scene_of(&d, "tri.ply", 1.0)).unwrap();
    assert_eq!(s.tri_normals.len(), 1);
    assert!(close(
        s.tri_normals[0][1],
        Vec3::new(0.0, 1.0, 1.0).normalize()
    ));
    assert!(close(s.tri_normals[0][2], Vec3::Z));
    // ASCII: not a number the parser reads, at its line.
    std::fs::write(d.join("tri.ply"), ply("0 inf 1")).unwrap();
    let e = Scene::load(&scene_of(&d, "tri.ply", 1.0)).unwrap_err();
    assert!(
        matches!(e.location(), Some(Location::Line { line: 14, .. })),
        "{e}"
    );
    // Binary: an infinite normal, at its vertex.
    let mut bin = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n\
        property float x\nproperty float y\nproperty float z\n\
        property float nx\nproperty float ny\nproperty float nz\n\
        element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        .to_vec();
    let verts = [
        [0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        [1.0, 0.0, 0.0, 0.0, f32::INFINITY, 1.0],
        [0.0, 1.0, 0.0, 0.0, 0.0, 1.0f32],
    ];
    for x in verts.iter().flatten() {
        bin.extend_from_slice(&x.to_le_bytes());
    }
    bin.push(3);
    for i in 0..3i32 {
        bin.extend_from_slice(&i.to_le_bytes());
    }
    std::fs::write(d.join("tri.ply"), bin).unwrap();
    let e = Scene::load(&scene_of(&d, "tri.ply", 1.0)).unwrap_err();
    assert!(
        matches!(e.location(), Some(Location::Element(el)) if el == "vertex 1"),
        "{e}"
    );
}

/// A glTF triangle with normals, under a node scaled by 2 along x.
fn gltf(dir: &Path, normal1: [f32; 3]) {
    let pos: [[f32; 3]; 3] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
    let nrm: [[f32; 3]; 3] = [[0.0, 0.0, 1.0], normal1, [1.0, 1.0, 1.0]];
    let bytes: Vec<u8> = pos
        .iter()
        .chain(&nrm)
        .flatten()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    std::fs::write(dir.join("tri.bin"), &bytes).unwrap();
    let json = r#"{
      "asset": {"version": "2.0"},
      "buffers": [{"uri": "tri.bin", "byteLength": 72}],
      "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36},
                      {"buffer": 0, "byteOffset": 36, "byteLength": 36}],
      "accessors": [
        {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
         "min": [0, 0, 0], "max": [1, 1, 0]},
        {"bufferView": 1, "componentType": 5126, "count": 3, "type": "VEC3"}],
      "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1}}]}],
      "nodes": [{"mesh": 0, "scale": [2, 1, 1]}],
      "scenes": [{"nodes": [0]}],
      "scene": 0
    }"#;
    std::fs::write(dir.join("tri.gltf"), json).unwrap();
}

#[test]
fn gltf_normals_go_through_the_node_matrix() {
    let d = temp("gltf");
    gltf(&d, [0.0, 1.0, 0.0]);
    let s = Scene::load(&scene_of(&d, "tri.gltf", 1.0)).unwrap();
    assert_eq!(s.tri_normals.len(), 1);
    assert!(close(s.tri_normals[0][0], Vec3::Z));
    let want = Vec3::new(0.5, 1.0, 1.0).normalize();
    assert!(close(s.tri_normals[0][2], want), "{:?}", s.tri_normals[0]);
    gltf(&d, [0.0, f32::NAN, 0.0]);
    let e = Scene::load(&scene_of(&d, "tri.gltf", 1.0)).unwrap_err();
    assert!(
        matches!(e.location(), Some(Location::Element(el)) if el.contains("NORMAL[1]")),
        "{e}"
    );
}
