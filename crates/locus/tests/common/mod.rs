//! What the farm tests share: a small Cornell box, a runtime like the
//! CLI's, the single-machine image to compare with, and a farm result's
//! bits.
#![allow(dead_code)]

pub mod daemon;

use locus_core::image_io::Image;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::scene::Scene;
use locus_protocol::submit::JobResult;
use std::path::PathBuf;

/// The Cornell box at `width` x `height`, 3 spp, depth 6, with small
/// leaves so that even 8 workers get several regions' worth.
pub fn small_cornell(width: u32, height: u32, seed: u64) -> Scene {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut s = Scene::load(&root.join("scenes/cornell-box/cornell.toml")).expect("cornell");
    s.camera.width = width;
    s.camera.height = height;
    s.settings.spp = 3;
    s.settings.max_depth = 6;
    s.settings.seed = seed;
    s.settings.octree.max_leaf_tris = 4;
    s
}

/// Sends the farm's warnings (a worker's stall report, a scheduler's
/// retries) to the test's captured output, so that a test that fails shows
/// what the farm said; `RUST_LOG` widens it.
pub fn log_to_test_output() {
    let filter =
        tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into());
    // A second call in the same binary finds the subscriber set.
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_test_writer()
        .try_init();
}

/// A 2-thread runtime like the CLI's, for the farm's tasks.
pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}

/// The single-machine image's bits (no caches).
pub fn single_machine(scene: &Scene) -> Vec<u32> {
    single_machine_output(scene).image.to_bits()
}

/// One machine's render of `scene` on 2 threads: its image and the error
/// it reports.
pub fn single_machine_output(scene: &Scene) -> locus_core::render::RenderOutput {
    let prep = Prepared::new(scene.clone());
    let mut o = RenderOptions::from_scene(scene);
    o.threads = 2;
    render(&prep, &o, &|_, _| {})
}

/// A farm result's image bits.
pub fn bits(r: &JobResult) -> Vec<u32> {
    Image {
        width: r.width,
        height: r.height,
        pixels: r.pixels.clone(),
    }
    .to_bits()
}
