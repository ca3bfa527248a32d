//! Memory-bounded workers, on real processes: a generated room that one
//! machine renders with more resident memory than any worker's budget
//! renders on four worker processes, each within its budget as the process
//! itself measures it, under `forward` and `adaptive`, bit-identical to one
//! machine.

mod common;

use locus::farm::{FarmSpec, LocalFarm};
use locus_core::generate::{RoomParams, write_room};
use locus_core::scene::Scene;
use locus_protocol::submit::{FetchPolicy, JobOptions};
use std::path::PathBuf;

/// Each worker process's budget: below what one machine needs for the
/// room (asserted), above what a region of a quarter of it needs.
const BUDGET: u64 = 64 << 20;

#[test]
fn four_budgeted_workers_render_what_one_machine_needs_more_for() {
    let exe = PathBuf::from(env!("CARGO_BIN_EXE_locus"));
    let dir = std::env::temp_dir().join(format!("locus-memory-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let params = RoomParams {
        resolution: [48, 36],
        spp: 2,
        ..RoomParams::default()
    };
    let (path, tris) = write_room(&dir, "room", &params).unwrap();
    assert!(tris > 300_000, "{tris} triangles");

    // One machine's peak, on a process of its own.
    let one_peak = locus::bench::farm::single_peak(&exe, &path, 2, Default::default()).unwrap();
    if cfg!(target_os = "linux") {
        assert!(
            one_peak > BUDGET,
            "one machine peaks at {one_peak} bytes, within a worker's budget {BUDGET}: the test shows nothing"
        );
    }

    let scene = Scene::load(&path).unwrap();
    let want = common::single_machine(&scene);
    let rt = common::runtime();
    for fetch in [FetchPolicy::Forward, FetchPolicy::Adaptive] {
        let spec = FarmSpec {
            workers: 4,
            threads_per_worker: 1,
            memory_budget: BUDGET,
            processes: Some(exe.clone()),
            ..FarmSpec::embedded(4, 1)
        };
        let opts = JobOptions {
            workers: 4,
            fetch,
            ..JobOptions::default()
        };
        let req = locus_scheduler::client::request(&scene, opts);
        let r = rt
            .block_on(async {
                let farm = LocalFarm::launch(&spec).await?;
                let r = farm.render(req, &|_, _| {}).await;
                farm.stop().await?;
                r
            })
            .unwrap_or_else(|e| panic!("{fetch:?}: {e:#}"));
        assert!(common::bits(&r) == want, "{fetch:?}: image differs");
        assert!(!r.report.replicated, "{fetch:?}: the room fits no worker");
        for (i, w) in r.report.workers.iter().enumerate() {
            let peak = w.stats.peak_rss;
            if cfg!(target_os = "linux") {
                assert!(peak > 0, "{fetch:?}: worker {i}'s peak was not measured");
            }
            assert!(
                peak <= BUDGET,
                "{fetch:?}: worker {i} peaked at {peak} bytes, over its budget {BUDGET}"
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
