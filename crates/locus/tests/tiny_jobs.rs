//! Tiny jobs finish. Three mechanisms once made tiny jobs hang for ever,
//! silently:
//! - a job of a few pixels can be rendered in full by the first worker that
//!   is ready before the last one says so; the scheduler then moved the job
//!   back from collecting to rendering and ignored every report;
//! - a peer packet that arrived in the same segment as the link's `Hello`
//!   sat in the reader's buffer after the connection was split, because the
//!   new reader looked at the socket before its buffer; a worker that sent
//!   its only packet and waited for the answer waited for ever;
//! - the scheduler ships each worker's region from a task of its own, so a
//!   worker still receiving it when another had rendered every tile got
//!   the `EndJob` first, dropped it for a job it did not have yet, then
//!   started the job and waited for its end (twice in 1,500 jobs of 11x1
//!   pixels on 3 workers under `fetch`, on a loaded machine); the end now
//!   goes to a worker only once it is ready.
//!
//! 500 jobs of random sizes (1x1 to 16x16), worker counts (1 to 8), fetch
//! policies, partitioners and tile sizes, with random polling on in every
//! third and adaptive sampling in every fifth, each under a timeout, must all finish with the single machine's
//! bits on the embedded farm, and 60 more on a farm of daemon processes.

mod common;
use common::{bits, runtime, single_machine};
use locus_core::sampler::SampleKey;
use locus_core::scene::Scene;
use locus_protocol::submit::{FetchPolicy, JobOptions, Partitioner};
use std::time::Duration;

/// The job `i` of a run seeded `seed`: a small Cornell box of random size
/// at 1 spp (every fifth at 16 with adaptive sampling) and its options (at most `max_workers` workers, a random fetch
/// policy, partitioner and tile size, random polling in every third), and
/// a line that names it.
fn tiny_job(i: u64, seed: u64, max_workers: usize) -> (Scene, JobOptions, String) {
    let k = SampleKey::independent(i, 0, seed);
    let w = 1 + (k.get1d(0) * 16.0) as u32;
    let h = 1 + (k.get1d(1) * 16.0) as u32;
    let workers = 1 + (k.get1d(2) * max_workers as f32) as usize;
    let fetch = FetchPolicy::ALL[(k.get1d(3) * 4.0) as usize % 4];
    let partitioner = if i.is_multiple_of(2) {
        Partitioner::RegionGrowing
    } else {
        Partitioner::Morton
    };
    let mut scene = common::small_cornell(w, h, i);
    scene.settings.spp = 1;
    // Every fifth spreads its samples: 16 spp, a pilot of 8 and one spread
    // pass, in which a tile of one dark pixel may get no sample at all.
    let adaptive = i % 5 == 4;
    if adaptive {
        scene.settings.spp = 16;
        scene.settings.adaptive_sampling = true;
    }
    let mut opts = JobOptions {
        workers: workers as u32,
        partitioner,
        fetch,
        tile_size: 1 + (k.get1d(4) * 8.0) as u32,
        ..Default::default()
    };
    let polling = i.is_multiple_of(3);
    opts.tuning.random_polling = polling;
    let what = format!(
        "job {i} (seed {seed}): {w}x{h}, {workers} workers, {fetch:?}, {partitioner:?}, random polling {polling}, adaptive sampling {adaptive}"
    );
    (scene, opts, what)
}

/// The draws' seed; another one (`LOCUS_TINY_SEED`) explores other jobs
/// when hunting a rare hang.
fn seed() -> u64 {
    std::env::var("LOCUS_TINY_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(77)
}

/// The same on a farm of processes: a `locus scheduler` and four `locus
/// worker --threads 1` daemons, 60 jobs submitted over the network, each
/// under a timeout.
#[cfg(unix)]
#[test]
fn tiny_jobs_on_daemons_all_finish_bit_for_bit() {
    use common::daemon::{Daemon, TOKEN};
    common::log_to_test_output();
    let seed = seed();
    let (_scheduler, addr) = Daemon::scheduler("5");
    let _workers: Vec<Daemon> = (0..4).map(|_| Daemon::worker(&addr)).collect();
    runtime().block_on(async {
        for i in 0..60u64 {
            let (scene, opts, what) = tiny_job(i, seed, 4);
            let want = single_machine(&scene);
            let req = locus_scheduler::client::request(&scene, opts);
            let job = locus_scheduler::client::submit(&addr, TOKEN, req, &|_, _| {});
            let r = match tokio::time::timeout(Duration::from_secs(30), job).await {
                Ok(r) => r.unwrap_or_else(|e| panic!("{what} failed: {e:#}")),
                Err(_) => panic!("{what} did not finish in 30 s"),
            };
            assert_eq!(bits(&r), want, "{what}");
        }
    });
}

#[test]
fn five_hundred_tiny_jobs_all_finish_bit_for_bit() {
    common::log_to_test_output();
    let seed = seed();
    runtime().block_on(async {
        let farm = locus::farm::LocalFarm::start(8, 1).await.expect("farm");
        let mut workers_seen = [false; 9];
        for i in 0..500u64 {
            let (scene, opts, what) = tiny_job(i, seed, 8);
            workers_seen[opts.workers as usize] = true;
            let want = single_machine(&scene);
            let req = locus_scheduler::client::request(&scene, opts);
            let r =
                match tokio::time::timeout(Duration::from_secs(30), farm.render(req, &|_, _| {}))
                    .await
                {
                    Ok(r) => r.unwrap_or_else(|e| panic!("{what} failed: {e:#}")),
                    Err(_) => {
                        // Stop the farm so the failure is reported, not hung.
                        farm.shutdown_token().cancel();
                        panic!("{what} did not finish in 30 s");
                    }
                };
            assert_eq!(bits(&r), want, "{what}");
        }
        assert!(
            workers_seen[1..].iter().all(|&s| s),
            "every worker count ran"
        );
        farm.stop().await.expect("clean stop");
    });
}
