//! locus-fuzz: what each fuzz target does with its input. A target takes
//! arbitrary bytes and must come back, with a value or an error, without
//! panicking, hanging or exhausting memory. The AFL++ harness (`fuzz/`,
//! built with `cargo afl`, outside the workspace) calls these; so does the
//! corpus replay test here (`tests/corpus.rs`), which runs every committed
//! corpus input and every crash found once (`fuzz/corpus/TARGET/`,
//! `fuzz/regressions/TARGET/`) in the ordinary test suite.
//!
//! The scene loaders read files (a scene names its meshes, an OBJ its
//! MTL), so their targets write the input to a file of the right name in
//! a per-process directory (on /dev/shm where there is one) and load it.
//! A loader that reports a panic it caught inside a parsing crate counts
//! as a crash here: it is an input the loader's own checks let through.

use locus_protocol::control::{Opening, SchedulerToWorker, WorkerToScheduler};
use locus_protocol::handshake::Handshake;
use locus_protocol::rays::PeerMsg;
use locus_protocol::submit::{SchedulerToClient, TrianglePart};
use std::path::PathBuf;

/// A target: takes any bytes, panics only on a bug.
pub type Target = fn(&[u8]);

/// The targets, by name: the name is the corpus directory's.
pub const TARGETS: &[(&str, Target)] = &[
    ("scene_toml", scene_toml),
    ("obj", obj),
    ("mtl", mtl),
    ("ply", ply),
    ("gltf", gltf),
    ("glb", glb),
    ("frames", frames),
];

/// The target named `name`.
pub fn target(name: &str) -> Option<Target> {
    TARGETS.iter().find(|(n, _)| *n == name).map(|(_, f)| *f)
}

fn scratch() -> PathBuf {
    let base = if std::path::Path::new("/dev/shm").is_dir() {
        PathBuf::from("/dev/shm")
    } else {
        std::env::temp_dir()
    };
    let d = base.join(format!("locus-fuzz-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&d);
    d
}

/// Writes `data` to `name` in the scratch directory; its path.
fn file(name: &str, data: &[u8]) -> PathBuf {
    let p = scratch().join(name);
    std::fs::write(&p, data).expect("the scratch directory is writable");
    p
}

/// A scene file: its TOML, with the meshes it names resolved beside it
/// (none exist, so a mesh reference is a named error).
pub fn scene_toml(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let p = scratch().join("scene.toml");
    let _ = locus_core::scene::Scene::from_toml(&p, text);
}

fn mesh(name: &str, data: &[u8]) {
    let p = file(name, data);
    if let Err(e) = locus_core::mesh_io::load(&p) {
        // The loaders catch a panic inside a parsing crate and say so: for
        // the fuzzer that is still a crash, an input our checks let by.
        let e = e.to_string();
        assert!(!e.contains("crashed on this file"), "{e}");
    }
}

/// An OBJ file (its `mtllib`, if any, is missing or the last MTL input).
pub fn obj(data: &[u8]) {
    mesh("mesh.obj", data);
}

/// An MTL file, through an OBJ that uses it for one triangle.
pub fn mtl(data: &[u8]) {
    file("lib.mtl", data);
    let obj = b"mtllib lib.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl a\nf 1 2 3\n";
    mesh("uses-mtl.obj", obj);
}

/// A PLY file, ASCII or binary.
pub fn ply(data: &[u8]) {
    mesh("mesh.ply", data);
}

/// A glTF JSON document (buffers as data URIs, or missing files).
pub fn gltf(data: &[u8]) {
    mesh("mesh.gltf", data);
}

/// A binary glTF (GLB) file.
pub fn glb(data: &[u8]) {
    mesh("mesh.glb", data);
}

/// One frame's payload, as every message family decodes it: the
/// handshake, a connection's opening, request parts, the control link
/// both ways, the client link, and the peer link (whose packets are then
/// decoded item by item).
pub fn frames(data: &[u8]) {
    let _ = postcard::from_bytes::<Handshake>(data);
    let _ = postcard::from_bytes::<Opening>(data);
    let _ = postcard::from_bytes::<TrianglePart>(data);
    let _ = postcard::from_bytes::<WorkerToScheduler>(data);
    let _ = postcard::from_bytes::<SchedulerToWorker>(data);
    let _ = postcard::from_bytes::<SchedulerToClient>(data);
    if let Ok(PeerMsg::Packet(p)) = postcard::from_bytes::<PeerMsg>(data) {
        for item in p.items(7, locus_core::sampler::Sampler::Independent) {
            if item.is_err() {
                break;
            }
        }
    }
}
