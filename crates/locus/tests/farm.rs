//! The farm over real loopback sockets: scheduler and workers in this test
//! process, against the single-machine renderer bit for bit.

use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::scene::Scene;
use locus_protocol::submit::{JobOptions, Partitioner};
use std::path::PathBuf;

fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn small_cornell() -> Scene {
    let mut s = Scene::load(&repo_root().join("scenes/cornell-box/cornell.toml")).expect("cornell");
    s.camera.width = 40;
    s.camera.height = 32;
    s.settings.spp = 3;
    s.settings.max_depth = 6;
    s.settings.seed = 7;
    // Small leaves: many regions even for 8 workers.
    s.settings.octree.max_leaf_tris = 4;
    s
}

fn single_machine(scene: &Scene) -> Vec<u32> {
    let prep = Prepared::new(scene.clone());
    let mut o = RenderOptions::from_scene(scene);
    o.threads = 2;
    render(&prep, &o, &|_, _| {}).image.to_bits()
}

#[test]
fn farm_matches_single_machine_bit_for_bit() {
    let scene = small_cornell();
    let reference = single_machine(&scene);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        for workers in [1usize, 2, 3, 4, 8] {
            let farm = locus::farm::LocalFarm::start(workers, 1).await.expect("farm");
            for partitioner in [Partitioner::RegionGrowing, Partitioner::Morton] {
                let opts = JobOptions {
                    workers: workers as u32,
                    partitioner,
                    tile_size: 8,
                    ..Default::default()
                };
                let req = locus_scheduler::client::request(&scene, opts);
                let r = farm.render(req, &|_, _| {}).await.expect("job");
                let img = locus_core::image_io::Image {
                    width: r.width,
                    height: r.height,
                    pixels: r.pixels.clone(),
                };
                let rep = &r.report;
                eprintln!(
                    "{workers} workers {partitioner:?}: forwarded/ray {:.3}, bytes/sample {:.0}, imbalance {:.2}",
                    rep.forwarded_fraction, rep.bytes_per_sample, rep.load_imbalance
                );
                assert_eq!(img.to_bits(), reference, "{workers} workers, {partitioner:?}");
                assert_eq!(rep.totals.trace.samples, (40 * 32 * 3) as u64);
                if workers > 1 {
                    assert!(rep.totals.forwarded_out > 0, "rays crossed regions");
                    let sent: u64 = rep.workers.iter().flat_map(|w| &w.stats.peers).map(|p| p.bytes_sent).sum();
                    let recv: u64 = rep.workers.iter().flat_map(|w| &w.stats.peers).map(|p| p.bytes_recv).sum();
                    assert_eq!(sent, recv, "every byte sent is received");
                }
            }
            farm.stop().await.expect("clean stop");
        }
    });
}
