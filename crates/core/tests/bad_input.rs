//! Bad input: every malformed file in `tests/corpus` yields its own error,
//! naming the offending file and the line or element, and nothing panics.
//! Truncations of valid files at many points must not panic either.

mod common;
use locus_core::error::{Location, SceneError};
use locus_core::scene::Scene;
use std::path::{Path, PathBuf};

fn corpus() -> PathBuf {
    common::repo_root().join("tests/corpus")
}

fn load(name: &str) -> Result<Scene, SceneError> {
    Scene::load(&corpus().join(name))
}

fn line(n: usize) -> Location {
    Location::Line {
        line: n,
        column: None,
    }
}

fn file_name(e: &SceneError) -> String {
    e.file().file_name().unwrap().to_string_lossy().into_owned()
}

/// (scene, file named by the error, variant name, location check)
type Case = (
    &'static str,
    &'static str,
    &'static str,
    fn(&Location) -> bool,
);

#[test]
fn each_corpus_file_gets_its_error() {
    let cases: Vec<Case> = vec![
        ("toml_syntax.toml", "toml_syntax.toml", "Syntax", |l| {
            matches!(l, Location::Line { line: 8, .. })
        }),
        (
            "toml_unknown_key.toml",
            "toml_unknown_key.toml",
            "Syntax",
            |l| matches!(l, Location::Line { line: 8, .. }),
        ),
        (
            "toml_nan_camera.toml",
            "toml_nan_camera.toml",
            "NonFinite",
            |l| matches!(l, Location::Line { line: 1, .. }),
        ),
        (
            "toml_bad_resolution.toml",
            "toml_bad_resolution.toml",
            "Invalid",
            |l| matches!(l, Location::Line { line: 1, .. }),
        ),
        (
            "toml_endless_spp.toml",
            "toml_endless_spp.toml",
            "Invalid",
            |l| matches!(l, Location::Line { line: 7, .. }),
        ),
        (
            "toml_negative_target.toml",
            "toml_negative_target.toml",
            "Invalid",
            |l| matches!(l, Location::Line { line: 9, .. }),
        ),
        (
            "toml_unknown_bvh.toml",
            "toml_unknown_bvh.toml",
            "Syntax",
            |l| matches!(l, Location::Line { line: 9, .. }),
        ),
        (
            "toml_deep_paths.toml",
            "toml_deep_paths.toml",
            "Invalid",
            |l| matches!(l, Location::Line { line: 7, .. }),
        ),
        (
            "toml_missing_mesh.toml",
            "toml_missing_mesh.toml",
            "MissingFile",
            |l| matches!(l, Location::Line { line: 7, .. }),
        ),
        (
            "toml_unknown_material.toml",
            "toml_unknown_material.toml",
            "Invalid",
            |l| matches!(l, Location::Line { line: 7, .. }),
        ),
        (
            "toml_inf_light.toml",
            "toml_inf_light.toml",
            "NonFinite",
            |l| matches!(l, Location::Line { line: 7, .. }),
        ),
        ("obj_syntax.toml", "obj_syntax.obj", "Syntax", |l| {
            *l == line(3)
        }),
        ("obj_nan.toml", "obj_nan.obj", "NonFinite", |l| {
            *l == line(3)
        }),
        ("obj_inf.toml", "obj_inf.obj", "NonFinite", |l| {
            *l == line(2)
        }),
        ("obj_index.toml", "obj_index.obj", "IndexOutOfRange", |l| {
            *l == line(5)
        }),
        (
            "obj_missing_mtl.toml",
            "obj_missing_mtl.obj",
            "MissingFile",
            |l| *l == line(1),
        ),
        ("obj_bad_mtl.toml", "obj_bad_mtl.mtl", "Syntax", |l| {
            *l == line(2)
        }),
        ("obj_binary.toml", "obj_binary.obj", "Syntax", |l| {
            matches!(l, Location::Element(_))
        }),
        ("ply_syntax.toml", "ply_syntax.ply", "Syntax", |l| {
            matches!(l, Location::Line { .. })
        }),
        ("ply_index.toml", "ply_index.ply", "IndexOutOfRange", |l| {
            *l == Location::Element("face 0".into())
        }),
        ("ply_nan.toml", "ply_nan.ply", "NonFinite", |l| {
            *l == Location::Element("vertex 1".into())
        }),
        (
            "gltf_index.toml",
            "gltf_index.gltf",
            "IndexOutOfRange",
            |l| matches!(l, Location::Element(e) if e.contains("meshes[0].primitives[0]")),
        ),
        (
            "gltf_missing_bin.toml",
            "gltf_missing_bin.gltf",
            "MissingFile",
            |l| matches!(l, Location::Element(e) if e == "buffers[0].uri"),
        ),
        ("gltf_syntax.toml", "gltf_syntax.gltf", "Syntax", |_| true),
    ];
    let mut failures = Vec::new();
    for (scene, file, variant, loc_ok) in cases {
        let err = match load(scene) {
            Ok(_) => {
                failures.push(format!("{scene}: loaded without error"));
                continue;
            }
            Err(e) => e,
        };
        let msg = err.to_string();
        let (v, loc) = match &err {
            SceneError::Io { .. } => ("Io", None),
            SceneError::Syntax { location, .. } => ("Syntax", Some(location)),
            SceneError::MissingFile { location, .. } => ("MissingFile", Some(location)),
            SceneError::NonFinite { location, .. } => ("NonFinite", Some(location)),
            SceneError::IndexOutOfRange { location, .. } => ("IndexOutOfRange", Some(location)),
            SceneError::Invalid { location, .. } => ("Invalid", Some(location)),
        };
        eprintln!("{scene}: {msg}");
        if v != variant
            || file_name(&err) != file
            || !loc.is_some_and(loc_ok)
            || !msg.contains(file)
        {
            failures.push(format!(
                "{scene}: expected {variant} in {file}, got {v} in {} at {loc:?}: {msg}",
                file_name(&err)
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn degenerate_triangles_are_dropped_and_counted() {
    let s = load("obj_degenerate.toml").unwrap();
    assert_eq!(s.load_stats.triangles_read, 3);
    assert_eq!(s.load_stats.degenerate_dropped, 2);
    assert_eq!(s.tris.len(), 1);
}

#[test]
fn obj_ply_and_gltf_load_with_materials_and_transforms() {
    let s = load("good_all_formats.toml").unwrap();
    assert_eq!(s.tris.len(), 3);
    assert_eq!(s.load_stats.meshes, 3);
    // The PLY triangle takes the override material, scaled by 2, rotated 90
    // degrees about y and moved to z = 1: (1, 0, 0) -> (0, 0, -2) + (0, 0, 1).
    let ply = s.tris[1];
    assert!(
        (ply[1] - glam::Vec3::new(0.0, 0.0, -1.0)).length() < 1e-5,
        "{ply:?}"
    );
    assert_eq!(s.materials[s.tri_material[1] as usize].name, "m");
    // glTF base colour becomes the albedo.
    let g = &s.materials[s.tri_material[2] as usize];
    assert_eq!(g.albedo, glam::Vec3::splat(0.5));
}

/// Loads `text` written to `name` in a scratch folder with the corpus's
/// helper files, returning whether it panicked.
fn survives(dir: &Path, name: &str, bytes: &[u8], scene: &str) -> bool {
    std::fs::write(dir.join(name), bytes).unwrap();
    std::fs::write(dir.join("s.toml"), scene).unwrap();
    std::panic::catch_unwind(|| {
        let _ = Scene::load(&dir.join("s.toml"));
    })
    .is_ok()
}

#[test]
fn truncated_files_never_panic() {
    let dir = std::env::temp_dir().join(format!("locus-trunc-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cb = common::repo_root().join("scenes/cornell-box");
    std::fs::copy(cb.join("cornell.mtl"), dir.join("cornell.mtl")).unwrap();
    let scene_text = std::fs::read_to_string(cb.join("cornell.toml")).unwrap();
    let obj = std::fs::read(cb.join("cornell.obj")).unwrap();
    let ply = std::fs::read(corpus().join("ply_good.ply")).unwrap();
    let gltf = std::fs::read(corpus().join("gltf_good.gltf")).unwrap();
    let mut cuts = 0;
    for n in (0..obj.len()).step_by(37) {
        assert!(
            survives(&dir, "cornell.obj", &obj[..n], &scene_text),
            "obj cut at {n}"
        );
        cuts += 1;
    }
    for n in (0..scene_text.len()).step_by(7) {
        std::fs::write(dir.join("cornell.obj"), &obj).unwrap();
        assert!(
            std::panic::catch_unwind(
                || Scene::from_toml(&dir.join("t.toml"), &scene_text[..n]).is_ok()
            )
            .is_ok(),
            "toml cut at {n}"
        );
        cuts += 1;
    }
    let ply_scene = "[camera]\nposition = [0.0, 0.0, 5.0]\nlook_at = [0.0, 0.0, 0.0]\nfov_y = 45.0\nresolution = [8, 8]\n[[mesh]]\nfile = \"m.ply\"\n";
    for n in 0..ply.len() {
        assert!(
            survives(&dir, "m.ply", &ply[..n], ply_scene),
            "ply cut at {n}"
        );
        cuts += 1;
    }
    let gltf_scene = ply_scene.replace("m.ply", "m.gltf");
    for n in (0..gltf.len()).step_by(11) {
        assert!(
            survives(&dir, "m.gltf", &gltf[..n], &gltf_scene),
            "gltf cut at {n}"
        );
        cuts += 1;
    }
    std::fs::remove_dir_all(&dir).ok();
    assert!(cuts > 300);
}

/// Hostile glTF files, made from a good one by changing one thing each:
/// every one is refused with an error naming the file and the element,
/// never a panic, a hang or gigabytes (a node cycle once looped for ever,
/// a node with many parents multiplied its meshes, a short byteStride and
/// float indices crashed inside the gltf crate).
#[test]
fn hostile_gltf_is_refused_by_element() {
    let dir = std::env::temp_dir().join(format!("locus-hostile-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let good: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(corpus().join("gltf_good.gltf")).unwrap())
            .unwrap();
    type Edit = fn(&mut serde_json::Value);
    let cases: Vec<(&str, Edit, &str)> = vec![
        (
            "short stride",
            |g| g["bufferViews"][0]["byteStride"] = 4.into(),
            "byteStride 4",
        ),
        (
            "float indices",
            |g| g["accessors"][1]["componentType"] = 5126.into(),
            "indices",
        ),
        (
            "vec2 positions",
            |g| g["accessors"][0]["type"] = "VEC2".into(),
            "POSITION",
        ),
        (
            "missing accessor",
            |g| g["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = 7.into(),
            "attributes.POSITION",
        ),
        (
            "empty accessor",
            |g| g["accessors"][0]["count"] = 0.into(),
            "no elements",
        ),
        (
            "a child past the nodes",
            |g| g["nodes"][0]["children"] = serde_json::json!([5]),
            "nodes[0].children",
        ),
        (
            "count past the view",
            |g| g["accessors"][0]["count"] = 4000000.into(),
            "reaches past",
        ),
        (
            "view past the buffer",
            |g| g["bufferViews"][1]["byteLength"] = 4000.into(),
            "ends past",
        ),
        (
            "no buffer view",
            |g| {
                g["accessors"][0]
                    .as_object_mut()
                    .unwrap()
                    .remove("bufferView");
            },
            "bufferView",
        ),
        (
            "node cycle",
            |g| {
                g["nodes"] = serde_json::json!([{"mesh": 0, "children": [1]}, {"children": [0]}]);
            },
            "nodes[",
        ),
        (
            "node with two parents",
            |g| {
                g["nodes"] = serde_json::json!([{"children": [1, 2]}, {"children": [3]}, {"children": [3]}, {"mesh": 0}]);
            },
            "nodes[3]",
        ),
        (
            "negative albedo",
            |g| g["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"][0] = (-0.5).into(),
            "materials[0]",
        ),
        (
            "huge emission",
            |g| g["materials"][0]["emissiveFactor"][1] = 1e39.into(),
            "materials[0]",
        ),
    ];
    let scene = "[camera]\nposition = [0.0, 0.0, 5.0]\nlook_at = [0.0, 0.0, 0.0]\nfov_y = 45.0\nresolution = [8, 8]\n\n[[mesh]]\nfile = \"h.gltf\"\n";
    std::fs::write(dir.join("s.toml"), scene).unwrap();
    for (what, edit, says) in cases {
        let mut g = good.clone();
        edit(&mut g);
        std::fs::write(dir.join("h.gltf"), serde_json::to_string(&g).unwrap()).unwrap();
        let r = std::panic::catch_unwind(|| Scene::load(&dir.join("s.toml")));
        let e = match r {
            Ok(Ok(_)) => panic!("{what}: loaded"),
            Ok(Err(e)) => e,
            Err(_) => panic!("{what}: panicked"),
        };
        assert_eq!(file_name(&e), "h.gltf", "{what}: {e}");
        let text = format!("{e}");
        assert!(text.contains(says), "{what}: {text}");
    }
    // The good file still loads.
    std::fs::write(dir.join("h.gltf"), serde_json::to_string(&good).unwrap()).unwrap();
    assert_eq!(Scene::load(&dir.join("s.toml")).unwrap().tris.len(), 1);
    let _ = std::fs::remove_dir_all(&dir);
}

/// MTL colours follow the scene file's rule: a negative Kd is refused at
/// its line.
#[test]
fn mtl_colours_outside_the_scene_rules_are_refused() {
    let dir = std::env::temp_dir().join(format!("locus-mtl-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(
        dir.join("m.mtl"),
        "newmtl a\nKd 0.5 0.5 0.5\nnewmtl b\nKd -0.2 0.5 0.5\n",
    )
    .unwrap();
    std::fs::write(
        dir.join("m.obj"),
        "mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl b\nf 1 2 3\n",
    )
    .unwrap();
    let scene = "[camera]\nposition = [0.0, 0.0, 5.0]\nlook_at = [0.0, 0.0, 0.0]\nfov_y = 45.0\nresolution = [8, 8]\n\n[[mesh]]\nfile = \"m.obj\"\n";
    std::fs::write(dir.join("s.toml"), scene).unwrap();
    let e = Scene::load(&dir.join("s.toml")).unwrap_err();
    assert_eq!(file_name(&e), "m.mtl");
    assert!(
        matches!(
            &e,
            SceneError::Invalid {
                location: Location::Line { line: 4, .. },
                ..
            }
        ),
        "{e:?}"
    );
    assert!(format!("{e}").contains("albedo"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A PLY header may declare any number of elements: one that declares
/// more than the file can hold is refused before the parser makes them
/// (a fuzzed header of 85 bytes once took 21 GB and ran on), naming the
/// element; one that the file holds loads.
#[test]
fn ply_counts_beyond_the_file_are_refused() {
    let dir = std::env::temp_dir().join(format!("locus-ply-count-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let scene = "[camera]\nposition = [0.0, 0.0, 5.0]\nlook_at = [0.0, 0.0, 0.0]\nfov_y = 45.0\nresolution = [8, 8]\n[[mesh]]\nfile = \"m.ply\"\n";
    std::fs::write(dir.join("s.toml"), scene).unwrap();
    let header = |format: &str, n: &str| {
        format!(
            "ply\nformat {format} 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\n\
             element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        )
    };
    for format in ["binary_little_endian", "ascii"] {
        // An element with no properties takes no bytes to the parser.
        let mut bytes =
            format!("ply\nformat {format} 1.0\nelement vertex 5555555555555555\nend_header\n")
                .into_bytes();
        bytes.extend_from_slice(&[b'\n'; 64]);
        std::fs::write(dir.join("m.ply"), &bytes).unwrap();
        let t = std::time::Instant::now();
        let e = Scene::load(&dir.join("s.toml")).unwrap_err().to_string();
        assert!(
            e.contains("element vertex") && e.contains("can hold"),
            "{format}: {e}"
        );
        assert!(
            t.elapsed().as_secs() < 5,
            "{format}: refused only after {:?}",
            t.elapsed()
        );
    }
    let mut good = header("binary_little_endian", "3").into_bytes();
    for v in [[0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]] {
        for c in v {
            good.extend_from_slice(&c.to_le_bytes());
        }
    }
    good.push(3);
    for i in [0i32, 1, 2] {
        good.extend_from_slice(&i.to_le_bytes());
    }
    std::fs::write(dir.join("m.ply"), &good).unwrap();
    assert_eq!(Scene::load(&dir.join("s.toml")).unwrap().tris.len(), 1);
    let _ = std::fs::remove_dir_all(&dir);
}
