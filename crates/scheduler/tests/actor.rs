//! The scheduler's actor through its channels, without sockets: a worker
//! is a channel of `SchedulerToWorker`, a client one of
//! `SchedulerToClient`, and every event goes in as the connection tasks
//! would send it.

use locus_protocol::control::{SchedulerToWorker, TileAssignment, TileResult, WorkerToScheduler};
use locus_protocol::report::WorkerStats;
use locus_protocol::submit::SchedulerToClient;
use locus_scheduler::actor::{Actor, Event, MAX_FAILED_ATTEMPTS, WORKER_WAIT};
use locus_scheduler::metrics::Metrics;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::mpsc;
use tokio::time::timeout;
use tokio_util::sync::CancellationToken;

mod common;
use common::*;

/// One worker and a job for it, up to the worker having its region: the
/// worker's and the client's channels and the job's id.
async fn shipped_job(
    farm: &Farm,
) -> (
    mpsc::Receiver<SchedulerToWorker>,
    mpsc::Receiver<SchedulerToClient>,
    u64,
) {
    let mut w = farm.worker(1).await;
    let mut client = farm.submit(1).await;
    accepted(&mut client).await;
    let job = until_shipped(&mut w).await;
    (w, client, job)
}

/// Waits until the worker has its region, and returns the job id.
async fn until_shipped(w: &mut mpsc::Receiver<SchedulerToWorker>) -> u64 {
    loop {
        if let SchedulerToWorker::Geometry {
            job, last: true, ..
        } = recv(w).await
        {
            return job;
        }
    }
}

fn result(t: &TileAssignment, value: f32) -> WorkerToScheduler {
    WorkerToScheduler::TileDone(TileResult {
        job: t.job,
        tile: t.tile,
        pass: t.pass,
        sums: vec![
            locus_core::passes::Moments {
                sum: [value as f64 * t.pixel_samples(0).len() as f64; 3],
                squares: [(value as f64).powi(2) * t.pixel_samples(0).len() as f64; 3],
            };
            t.pixels() as usize
        ],
    })
}

/// The end of a one-worker job once its last tile is in: the worker is
/// told to end, reports, and the client gets the image.
async fn end_and_collect(
    farm: &Farm,
    w: &mut mpsc::Receiver<SchedulerToWorker>,
    client: &mut mpsc::Receiver<SchedulerToClient>,
    job: u64,
) -> locus_protocol::submit::JobResult {
    assert!(matches!(recv(w).await, SchedulerToWorker::EndJob { .. }));
    let stats = Box::new(WorkerStats {
        peers: vec![Default::default()],
        ..Default::default()
    });
    farm.from(1, WorkerToScheduler::Report { job, stats }).await;
    let mut collect = locus_scheduler::client::Collector::new(32, 32);
    loop {
        if let Some(r) = collect.take(Some(recv(client).await), &|_, _| {}) {
            break r.expect("the job's image");
        }
    }
}

/// A request for u32::MAX tiles is answered with the tiles there are and
/// one NoMoreTiles; a tile sent twice is counted once and its second copy
/// does not reach the film; an unknown tile is ignored; both are counted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tiles_count_once_and_requests_are_clamped() {
    let farm = start();
    let (mut w, mut client, job) = shipped_job(&farm).await;
    farm.from(1, WorkerToScheduler::Ready { job }).await;
    farm.from(
        1,
        WorkerToScheduler::NeedTiles {
            job,
            count: u32::MAX,
        },
    )
    .await;
    let mut tiles = Vec::new();
    loop {
        match recv(&mut w).await {
            SchedulerToWorker::Tile(t) => tiles.push(t),
            SchedulerToWorker::NoMoreTiles { .. } => break,
            other => panic!("unexpected {other:?}"),
        }
    }
    assert_eq!(tiles.len(), 4, "32x32 in 16x16 tiles");
    // Each tile says how many camera samples are still queued behind it
    // (one worker: the whole of them), the last none.
    for (i, t) in tiles.iter().enumerate() {
        let behind: u64 = tiles[i + 1..].iter().map(|u| u.total_samples()).sum();
        assert_eq!(t.queue_share, behind, "tile {i}");
    }
    assert!(tiles[0].queue_share > 0);
    farm.from(1, result(&tiles[0], 1.0)).await;
    farm.from(1, result(&tiles[0], 2.0)).await;
    let mut unknown = tiles[0].clone();
    unknown.tile = 99;
    farm.from(1, result(&unknown, 3.0)).await;
    assert_eq!(farm.tiles_done().await, 1);
    let text = farm.metrics.encode();
    assert!(
        text.contains("locus_tiles_ignored_total{why=\"duplicate\"} 1"),
        "{text}"
    );
    assert!(
        text.contains("locus_tiles_ignored_total{why=\"unknown\"} 1"),
        "{text}"
    );
    for t in &tiles[1..] {
        farm.from(1, result(t, 0.5)).await;
    }
    let done = end_and_collect(&farm, &mut w, &mut client, job).await;
    let t0 = tiles[0].clone();
    let first = done.pixels[(t0.y0 * 32 + t0.x0) as usize];
    assert_eq!(first, [1.0; 3], "the duplicate overwrote the film");
    farm.shutdown.cancel();
}

/// A client that goes away cancels its running job: the workers are told
/// to abort, and the next job starts.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_leaves_cancels_its_job() {
    let farm = start();
    let (mut w, client, job) = shipped_job(&farm).await;
    drop(client);
    match recv(&mut w).await {
        SchedulerToWorker::AbortJob { job: j, reason } => {
            assert_eq!(j, job);
            assert!(reason.contains("client"), "{reason}");
        }
        other => panic!("unexpected {other:?}"),
    }
    let mut next = farm.submit(1).await;
    accepted(&mut next).await;
    farm.shutdown.cancel();
}

/// A job that asks for more workers than register fails once
/// `WORKER_WAIT` has passed, saying how many it asked for and how many
/// there are.
#[tokio::test(start_paused = true)]
async fn a_job_waits_for_workers_within_a_deadline() {
    let farm = start();
    let _w = farm.worker(1).await;
    let mut client = farm.submit(3).await;
    let t = tokio::time::Instant::now();
    assert!(matches!(
        client.recv().await,
        Some(SchedulerToClient::Queued { ahead: 0, .. })
    ));
    let reason = match timeout(WORKER_WAIT * 2, client.recv()).await.unwrap() {
        Some(SchedulerToClient::Failed { reason, .. }) => reason,
        other => panic!("expected a failure, got {other:?}"),
    };
    assert!(t.elapsed() >= WORKER_WAIT, "{:?}", t.elapsed());
    assert!(reason.contains("asks for 3 workers but 1"), "{reason}");
    farm.shutdown.cancel();
}

/// Waits for the next StartJob and the end of its region, skipping
/// anything else; returns the run id and how many workers it has.
async fn next_start(w: &mut mpsc::Receiver<SchedulerToWorker>) -> (u64, usize) {
    let (run, peers) = loop {
        if let SchedulerToWorker::StartJob(s) = recv(w).await {
            break (s.job, s.peers.len());
        }
    };
    assert_eq!(until_shipped(w).await, run);
    (run, peers)
}

/// Workers 1 and 2 and a job for both, up to both having their region:
/// the workers' and the client's channels and the run id.
async fn shipped_pair(
    farm: &Farm,
) -> (
    mpsc::Receiver<SchedulerToWorker>,
    mpsc::Receiver<SchedulerToWorker>,
    mpsc::Receiver<SchedulerToClient>,
    u64,
) {
    let mut w1 = farm.worker(1).await;
    let mut w2 = farm.worker(2).await;
    let mut client = farm.submit(2).await;
    accepted(&mut client).await;
    let (run, n) = next_start(&mut w1).await;
    assert_eq!(n, 2);
    assert_eq!(next_start(&mut w2).await.0, run);
    (w1, w2, client, run)
}

/// Asks for `count` tiles as member `id` of run `run` and returns them.
async fn ask(
    farm: &Farm,
    w: &mut mpsc::Receiver<SchedulerToWorker>,
    id: u32,
    run: u64,
    count: u32,
) -> Vec<TileAssignment> {
    farm.from(id, WorkerToScheduler::NeedTiles { job: run, count })
        .await;
    let mut tiles = Vec::new();
    while tiles.len() < count as usize {
        match recv(w).await {
            SchedulerToWorker::Tile(t) => {
                assert_eq!(t.job, run, "a tile handed out under another run");
                tiles.push(t);
            }
            SchedulerToWorker::NoMoreTiles { .. } => break,
            other => panic!("unexpected {other:?}"),
        }
    }
    tiles
}

/// Worker `id` asks for tiles and renders each as it comes (every pixel
/// `value`) until `n` are in: a worker is handed at most its share of the
/// tiles left at a time, and the rest as tiles come in.
async fn render_tiles(
    farm: &Farm,
    w: &mut mpsc::Receiver<SchedulerToWorker>,
    id: u32,
    run: u64,
    n: usize,
    value: f32,
) {
    farm.from(
        id,
        WorkerToScheduler::NeedTiles {
            job: run,
            count: 64,
        },
    )
    .await;
    render_handed(farm, w, id, run, 0, n, value).await
}

/// Worker `id`, with `done` tiles rendered already, renders each tile it
/// is handed as it comes (every pixel `value`) until `n` are in.
async fn render_handed(
    farm: &Farm,
    w: &mut mpsc::Receiver<SchedulerToWorker>,
    id: u32,
    run: u64,
    mut done: usize,
    n: usize,
    value: f32,
) {
    while done < n {
        match recv(w).await {
            SchedulerToWorker::Tile(t) => {
                assert_eq!(t.job, run, "a tile handed out under another run");
                farm.from(id, result(&t, value)).await;
                done += 1;
            }
            other => panic!("unexpected {other:?}"),
        }
    }
}

async fn report(farm: &Farm, id: u32, run: u64, workers: usize) {
    let stats = Box::new(WorkerStats {
        peers: vec![Default::default(); workers],
        ..Default::default()
    });
    farm.from(id, WorkerToScheduler::Report { job: run, stats })
        .await;
}

async fn image(
    client: &mut mpsc::Receiver<SchedulerToClient>,
) -> locus_protocol::submit::JobResult {
    let mut collect = locus_scheduler::client::Collector::new(32, 32);
    loop {
        if let Some(r) = collect.take(Some(recv(client).await), &|_, _| {}) {
            return r.expect("the job's image");
        }
    }
}

/// A member lost mid-job: the attempt is aborted, the job restarts on the
/// survivor under a new run id, renders only the tiles not yet in, keeps
/// the finished tile's pixels, ignores the old run's late results, and
/// reports what it survived.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lost_worker_s_tiles_are_rendered_again_by_the_survivors() {
    let farm = start();
    let (mut w1, mut w2, mut client, r1) = shipped_pair(&farm).await;
    farm.from(1, WorkerToScheduler::Ready { job: r1 }).await;
    farm.from(2, WorkerToScheduler::Ready { job: r1 }).await;
    let first = ask(&farm, &mut w1, 1, r1, 1).await;
    let held = ask(&farm, &mut w2, 2, r1, 1).await;
    // Four tile passes of one size: each tile's share is what is queued
    // behind it over the two members.
    let size = first[0].total_samples();
    assert_eq!(first[0].queue_share, (3 * size).div_ceil(2));
    assert_eq!(held[0].queue_share, size);
    farm.from(1, result(&first[0], 1.0)).await;
    farm.events
        .send(Event::Left {
            id: 2,
            reason: "no heartbeat for 5.0 s".into(),
        })
        .await
        .unwrap();
    match recv(&mut w1).await {
        SchedulerToWorker::AbortJob { job, .. } => assert_eq!(job, r1),
        other => panic!("expected the attempt aborted, got {other:?}"),
    }
    let (r2, n) = next_start(&mut w1).await;
    assert_ne!(r2, r1, "a new attempt needs a new run id");
    assert_eq!(n, 1, "the survivor alone");
    // The survivor's report of the aborted run goes to the recovery.
    let stats = Box::new(WorkerStats {
        trace: locus_core::stats::TraceStats {
            samples: 7,
            ..Default::default()
        },
        ..Default::default()
    });
    farm.from(1, WorkerToScheduler::Report { job: r1, stats })
        .await;
    // The lost worker's tile, arriving late under the old run, is fenced.
    farm.from(1, result(&held[0], 9.0)).await;
    assert_eq!(farm.tiles_done().await, 1);
    assert!(
        farm.metrics
            .encode()
            .contains("locus_stale_messages_total 1"),
        "{}",
        farm.metrics.encode()
    );
    farm.from(1, WorkerToScheduler::Ready { job: r2 }).await;
    let rest = ask(&farm, &mut w1, 1, r2, 64).await;
    assert_eq!(rest.len(), 3, "only the tiles not yet in");
    assert!(rest.iter().all(|t| t.tile != first[0].tile));
    for t in &rest {
        farm.from(1, result(t, 0.5)).await;
    }
    assert!(matches!(
        recv(&mut w1).await,
        SchedulerToWorker::EndJob { job } if job == r2
    ));
    report(&farm, 1, r2, 1).await;
    let done = image(&mut client).await;
    let t0 = first[0].clone();
    assert_eq!(done.pixels[(t0.y0 * 32 + t0.x0) as usize], [1.0; 3]);
    let h = held[0].clone();
    assert_eq!(done.pixels[(h.y0 * 32 + h.x0) as usize], [0.5; 3]);
    let rec = &done.report.recovery;
    assert_eq!(rec.attempts, 2);
    assert_eq!(rec.tile_passes_kept, 1);
    assert_eq!((rec.aborted.samples, rec.aborted_reports), (7, 1));
    assert_eq!(
        done.report.totals.trace.samples, 0,
        "the last attempt's own"
    );
    assert_eq!(rec.lost.len(), 1);
    assert!(rec.lost[0].0.contains("w2") && rec.lost[0].1.contains("heartbeat"));
    farm.shutdown.cancel();
}

/// A failure that repeats with every worker still there is the job's: it
/// fails after `MAX_FAILED_ATTEMPTS` attempts, with the worker's reason.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn attempts_that_keep_failing_fail_the_job() {
    let farm = start();
    let mut w = farm.worker(1).await;
    let mut client = farm.submit(1).await;
    accepted(&mut client).await;
    let mut runs = Vec::new();
    for _ in 0..MAX_FAILED_ATTEMPTS {
        let (run, _) = next_start(&mut w).await;
        runs.push(run);
        let reason = "region exceeds the memory budget".to_string();
        farm.from(1, WorkerToScheduler::Failed { job: run, reason })
            .await;
    }
    runs.dedup();
    assert_eq!(runs.len(), MAX_FAILED_ATTEMPTS as usize, "{runs:?}");
    let reason = loop {
        match recv(&mut client).await {
            SchedulerToClient::Failed { reason, .. } => break reason,
            SchedulerToClient::Progress { .. } => {}
            other => panic!("unexpected {other:?}"),
        }
    };
    assert!(reason.contains("memory budget"), "{reason}");
    assert!(reason.contains("without a worker lost"), "{reason}");
    farm.shutdown.cancel();
}

/// A member lost after the last tile is in: the image is complete, and the
/// job ends without that worker's report.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_lost_after_the_last_tile_leaves_the_image_whole() {
    let farm = start();
    let (mut w1, _w2, mut client, run) = shipped_pair(&farm).await;
    for id in [1, 2] {
        farm.from(id, WorkerToScheduler::Ready { job: run }).await;
    }
    // Asking far ahead, it gets its share of the 4 tiles (the other
    // worker's half stays), and the rest as it renders them.
    farm.from(
        1,
        WorkerToScheduler::NeedTiles {
            job: run,
            count: 64,
        },
    )
    .await;
    // The status answer comes after the request was handled.
    farm.tiles_done().await;
    let mut first = Vec::new();
    while let Ok(m) = w1.try_recv() {
        match m {
            SchedulerToWorker::Tile(t) => first.push(t),
            other => panic!("unexpected {other:?}"),
        }
    }
    assert_eq!(first.len(), 2, "a share of two workers");
    for t in &first {
        farm.from(1, result(t, 0.25)).await;
    }
    render_handed(&farm, &mut w1, 1, run, first.len(), 4, 0.25).await;
    report(&farm, 1, run, 2).await;
    farm.events
        .send(Event::Left {
            id: 2,
            reason: "closed the connection".into(),
        })
        .await
        .unwrap();
    let done = image(&mut client).await;
    assert!(done.pixels.iter().all(|p| *p == [0.25; 3]));
    assert_eq!(done.report.recovery.attempts, 1);
    assert_eq!(done.report.recovery.lost.len(), 1);
    farm.shutdown.cancel();
}

/// A member still receiving its region when another has rendered every
/// tile is told to end the job only once it says it is ready: before, its
/// region is shipped by a task of its own and may come after the
/// `EndJob`, which it would drop for a job it does not have yet, then
/// start the job and wait for the end for ever (the tiny-job hang).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_member_not_yet_ready_is_told_to_end_once_it_is() {
    let farm = start();
    let (mut w1, mut w2, mut client, run) = shipped_pair(&farm).await;
    farm.from(1, WorkerToScheduler::Ready { job: run }).await;
    render_tiles(&farm, &mut w1, 1, run, 4, 0.25).await;
    // Told that no tile is left (it asked for more), then to end.
    loop {
        match recv(&mut w1).await {
            SchedulerToWorker::NoMoreTiles { .. } => {}
            SchedulerToWorker::EndJob { job } if job == run => break,
            other => panic!("unexpected {other:?}"),
        }
    }
    // The status answer comes after every event sent before it.
    assert_eq!(farm.tiles_done().await, 4);
    match w2.try_recv() {
        Err(mpsc::error::TryRecvError::Empty) => {}
        other => panic!("worker 2 was sent {other:?} before it was ready"),
    }
    farm.from(2, WorkerToScheduler::Ready { job: run }).await;
    assert!(matches!(
        recv(&mut w2).await,
        SchedulerToWorker::EndJob { job } if job == run
    ));
    // A second Ready is not a second EndJob.
    farm.from(2, WorkerToScheduler::Ready { job: run }).await;
    report(&farm, 1, run, 2).await;
    report(&farm, 2, run, 2).await;
    let done = image(&mut client).await;
    assert!(done.pixels.iter().all(|p| *p == [0.25; 3]));
    assert!(matches!(
        w2.try_recv(),
        Err(mpsc::error::TryRecvError::Empty)
    ));
    farm.shutdown.cancel();
}

/// A worker that asks for more tiles than its control channel holds gets
/// the rest when it asks again: a tile that found the channel full is
/// kept for the next request, not lost (the film would never be whole,
/// and the job never end).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tile_that_finds_the_channel_full_is_handed_out_later() {
    let farm = start();
    let mut w = farm.worker_with_room(1, 2).await;
    let mut client = farm.submit(1).await;
    accepted(&mut client).await;
    let run = until_shipped(&mut w).await;
    farm.from(1, WorkerToScheduler::Ready { job: run }).await;
    let mut got = std::collections::BTreeSet::new();
    let mut no_more = false;
    for _ in 0..4 {
        farm.from(1, WorkerToScheduler::NeedTiles { job: run, count: 4 })
            .await;
        // The status answer comes after the request was handled.
        farm.tiles_done().await;
        while let Ok(m) = w.try_recv() {
            match m {
                SchedulerToWorker::Tile(t) => assert!(got.insert(t.tile), "tile {} twice", t.tile),
                SchedulerToWorker::NoMoreTiles { .. } => no_more = true,
                other => panic!("unexpected {other:?}"),
            }
        }
    }
    assert_eq!(
        got.len(),
        4,
        "32x32 in 16x16 tiles, each handed out once: {got:?}"
    );
    assert!(no_more, "told there are no more once they are all out");
    farm.shutdown.cancel();
}

/// An abort that finds the worker's control channel full is sent again
/// once there is room, not dropped: the worker would otherwise run the
/// aborted run until its next start.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_abort_that_finds_the_channel_full_comes_later() {
    let farm = start();
    let mut w = farm.worker_with_room(1, 2).await;
    let client = farm.submit(1).await;
    let run = until_shipped(&mut w).await;
    farm.from(1, WorkerToScheduler::Ready { job: run }).await;
    // Two tiles fill the channel.
    farm.from(1, WorkerToScheduler::NeedTiles { job: run, count: 2 })
        .await;
    farm.tiles_done().await;
    drop(client);
    // The client's departure is seen on the next tick.
    tokio::time::sleep(Duration::from_millis(1200)).await;
    for _ in 0..2 {
        assert!(matches!(recv(&mut w).await, SchedulerToWorker::Tile(_)));
    }
    match recv(&mut w).await {
        SchedulerToWorker::AbortJob { job, reason } => {
            assert_eq!(job, run);
            assert!(reason.contains("client"), "{reason}");
        }
        other => panic!("expected the abort, got {other:?}"),
    }
    farm.shutdown.cancel();
}

/// The next `n` messages to the worker, each a tile (a `NoMoreTiles` is a
/// failure here: the job still has passes to come).
async fn tiles_sent(w: &mut mpsc::Receiver<SchedulerToWorker>, n: usize) -> Vec<TileAssignment> {
    let mut tiles = Vec::new();
    while tiles.len() < n {
        match recv(w).await {
            SchedulerToWorker::Tile(t) => tiles.push(t),
            other => panic!("unexpected {other:?}"),
        }
    }
    tiles
}

/// Nothing reaches the worker for a moment: what was not sent in 300 ms
/// after the actor took every event before it is not coming.
async fn nothing_sent(w: &mut mpsc::Receiver<SchedulerToWorker>, why: &str) {
    if let Ok(m) = timeout(Duration::from_millis(300), w.recv()).await {
        panic!("{why}, but the worker was sent {m:?}");
    }
}

/// A job with a noise target: a worker asking for every tile gets the
/// first pass's alone, without being told there are no more; the next
/// pass's come, owed, once the first is in; and a film that meets the
/// target (samples of one value: no spread) ends the job after the second
/// pass of four, with the samples of two passes in the image.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_noise_target_holds_each_pass_until_the_one_before_is_in() {
    let farm = start();
    let mut w = farm.worker(1).await;
    let mut client = farm.submit_request(request(1, 8, Some(1e-3))).await;
    accepted(&mut client).await;
    let job = until_shipped(&mut w).await;
    farm.from(1, WorkerToScheduler::Ready { job }).await;
    farm.from(1, WorkerToScheduler::NeedTiles { job, count: 64 })
        .await;
    let first = tiles_sent(&mut w, 4).await;
    assert!(first.iter().all(|t| t.pass == 0));
    nothing_sent(&mut w, "the first pass's four tiles, no more").await;
    for t in &first[..3] {
        farm.from(1, result(t, 0.5)).await;
    }
    nothing_sent(&mut w, "pass 1 waits for pass 0").await;
    farm.from(1, result(&first[3], 0.5)).await;
    // The owed request, served when pass 1 opened.
    let second = tiles_sent(&mut w, 4).await;
    assert!(second.iter().all(|t| t.pass == 1));
    for t in &second {
        farm.from(1, result(t, 0.5)).await;
    }
    let done = end_and_collect(&farm, &mut w, &mut client, job).await;
    assert_eq!(done.report.spp, 8);
    assert_eq!(
        done.report.spp_rendered, 2,
        "passes of 8 samples end at 1, 2, 4, 8"
    );
    let e = done.report.error_estimate.expect("two samples a pixel");
    assert_eq!(e.rel_mse, 0.0);
    assert!(done.pixels.iter().all(|p| *p == [0.5; 3]));
    farm.shutdown.cancel();
}

/// A scheduler that stopped after the store kept a job's last tile but
/// before it kept the job's end finds the job whole when it starts again:
/// the job ends once its workers are ready, with no tile to render (it
/// waited for a tile that would never come).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_restored_whole_ends_without_a_tile() {
    use locus_scheduler::film::TileSums;
    use locus_scheduler::store::{Store, Write};
    let dir = std::env::temp_dir().join(format!("locus-whole-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    {
        let (s, ..) = Store::open(&dir).unwrap();
        let request = postcard::to_allocvec(&request(1, 1, None)).unwrap();
        s.write(Write::Job { id: 5, request });
        for tile in 0..4 {
            let one = locus_core::passes::Moments {
                sum: [0.25; 3],
                squares: [0.0625; 3],
            };
            let sums = TileSums {
                passes: 1,
                sums: vec![one; 256],
                counts: vec![1; 256],
            };
            s.write(Write::Tile { job: 5, tile, sums });
        }
        s.synced().await.expect("committed");
    }
    // Opened again once the first handle's writer thread lets the file go.
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    let (store, next, jobs, kept) = loop {
        match Store::open(&dir) {
            Ok(x) => break x,
            Err(e) if std::time::Instant::now() < deadline => {
                let _ = e;
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            Err(e) => panic!("{e:#}"),
        }
    };
    assert_eq!(jobs.len(), 1);
    assert_eq!(jobs[0].tiles.len(), 4);
    let (tx, rx) = mpsc::channel(64);
    let metrics = Arc::new(Metrics::new());
    let shutdown = CancellationToken::new();
    let actor = Actor::new(4, tx.clone(), metrics.clone()).with_store(store, next, jobs, kept);
    tokio::spawn(actor.run(rx, shutdown.clone()));
    let farm = Farm {
        events: tx,
        metrics,
        shutdown,
    };
    let mut w = farm.worker(1).await;
    let job = until_shipped(&mut w).await;
    farm.from(1, WorkerToScheduler::Ready { job }).await;
    assert!(matches!(
        recv(&mut w).await,
        SchedulerToWorker::EndJob { .. }
    ));
    farm.shutdown.cancel();
    let _ = std::fs::remove_dir_all(&dir);
}
