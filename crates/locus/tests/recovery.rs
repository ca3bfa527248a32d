//! Worker loss on real processes: a scheduler and three `locus worker`
//! daemons on loopback, and jobs that lose a worker to `kill -9` at random
//! moments, or to SIGSTOP. Every job must finish with the single-machine
//! image's bits; the killed worker is started again and rejoins, and the
//! stopped one, resumed, is fenced out of the job it was stopped in and
//! takes part in the next.
#![cfg(unix)]

mod common;
use common::daemon::{Daemon, TOKEN};

use locus_core::sampler::mix64;
use locus_protocol::submit::{JobOptions, JobResult};
use std::process::Command;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, mpsc};
use std::time::{Duration, Instant};

/// Submits `scene` for `workers` workers from a thread of its own, so that
/// the test can act while the job runs; the result arrives on the channel.
fn submit(
    addr: &str,
    scene: &locus_core::scene::Scene,
    workers: u32,
) -> mpsc::Receiver<anyhow::Result<JobResult>> {
    submit_watched(addr, scene, workers, Arc::new(AtomicU64::new(0)))
}

/// As [`submit`], counting the tiles done in `done` as progress arrives.
fn submit_watched(
    addr: &str,
    scene: &locus_core::scene::Scene,
    workers: u32,
    done: Arc<AtomicU64>,
) -> mpsc::Receiver<anyhow::Result<JobResult>> {
    let opts = JobOptions {
        workers,
        tile_size: 16,
        ..Default::default()
    };
    submit_options(addr, scene, opts, done)
}

/// As [`submit_watched`], with the job's options.
fn submit_options(
    addr: &str,
    scene: &locus_core::scene::Scene,
    opts: JobOptions,
    done: Arc<AtomicU64>,
) -> mpsc::Receiver<anyhow::Result<JobResult>> {
    let req = locus_scheduler::client::request(scene, opts);
    let (tx, rx) = mpsc::channel();
    let addr = addr.to_string();
    std::thread::spawn(move || {
        let rt = common::runtime();
        let progress = move |d: u64, _: u64| done.store(d, Relaxed);
        let r = rt.block_on(locus_scheduler::client::submit(
            &addr, TOKEN, req, &progress,
        ));
        let _ = tx.send(r);
    });
    rx
}

fn wait(rx: &mpsc::Receiver<anyhow::Result<JobResult>>) -> JobResult {
    rx.recv_timeout(Duration::from_secs(180))
        .expect("the job ends within 180 s")
        .expect("the job completes")
}

fn scene() -> locus_core::scene::Scene {
    scene_of(160, 120)
}

fn scene_of(width: u32, height: u32) -> locus_core::scene::Scene {
    let mut s = common::small_cornell(width, height, 11);
    s.settings.spp = 16;
    s
}

/// Twenty jobs, each losing one of three workers to `kill -9` at a moment
/// drawn from a fixed seed over the job's length: every one completes with
/// the single-machine bits, and the killed worker, started again, rejoins
/// for the next job.
#[test]
fn jobs_survive_a_worker_killed_at_random_moments() {
    let scene = scene();
    let reference = common::single_machine(&scene);
    let (_sched, addr) = Daemon::scheduler("2");
    let mut workers: Vec<Daemon> = (0..3).map(|_| Daemon::worker(&addr)).collect();
    // Undisturbed jobs set the time scale of the kills (the first one
    // also pays for the workers' start).
    let mut span = Duration::MAX;
    for _ in 0..2 {
        let t = Instant::now();
        let warm = wait(&submit(&addr, &scene, 3));
        span = span.min(t.elapsed());
        assert_eq!(common::bits(&warm), reference);
        assert_eq!(warm.report.recovery.attempts, 1);
    }
    // LOCUS_SOAK_RUNS=500 makes this the soak (tests/soak-recovery.sh).
    let runs: u64 = std::env::var("LOCUS_SOAK_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20);
    let mut recovered = 0;
    for k in 0..runs {
        let h = mix64(0x6b11 ^ k);
        let delay = span.mul_f64((h % 1000) as f64 / 1250.0);
        let victim = (h >> 32) as usize % workers.len();
        let rx = submit(&addr, &scene, 3);
        std::thread::sleep(delay);
        let killed = Instant::now();
        workers[victim].signal("-KILL");
        let r = wait(&rx);
        let rec = &r.report.recovery;
        eprintln!(
            "run {k}: kill after {:.0} ms, job done {:.0} ms later, {} attempts, lost {:?}, {} tile passes kept, \
             {} samples in {} reports of aborted attempts",
            delay.as_secs_f64() * 1e3,
            killed.elapsed().as_secs_f64() * 1e3,
            rec.attempts,
            rec.lost,
            rec.tile_passes_kept,
            rec.aborted.samples,
            rec.aborted_reports
        );
        if rec.attempts > 1 {
            // Both survivors report what they did in the aborted attempt
            // (unless the loss came as they finished).
            assert!(rec.aborted_reports <= 2, "run {k}: {rec:?}");
        }
        assert_eq!(common::bits(&r), reference, "run {k}: the image differs");
        if !rec.lost.is_empty() {
            recovered += 1;
        }
        workers[victim] = Daemon::worker(&addr);
    }
    eprintln!("{recovered} of {runs} jobs lost a worker while running and completed bit-identical");
    assert!(
        recovered >= runs / 2,
        "only {recovered} of {runs} kills landed during a job: the test is not testing recovery"
    );
}

/// A worker killed while the workers measure the irradiance cache's
/// overture between them (`fetch`: each holds the whole scene): the
/// attempt is aborted, the levels already merged are kept, and the
/// workers left measure the rest; the image is one machine's with the
/// cache on, bit for bit, with the same records.
#[test]
fn a_worker_killed_mid_overture_leaves_the_records_one_machine_makes() {
    use locus_core::irradiance::IrradianceParams;
    use locus_core::render::{Prepared, RenderOptions, render};
    use locus_protocol::submit::FetchPolicy;
    let mut scene = common::small_cornell(96, 72, 5);
    scene.settings.spp = 2;
    let params = IrradianceParams {
        divisions: 2048,
        spacing: 8,
        ..Default::default()
    };
    let mut o = RenderOptions::from_scene(&scene);
    o.threads = 2;
    o.irradiance = Some(params);
    let one = render(&Prepared::new(scene.clone()), &o, &|_, _| {});
    let reference = one.image.to_bits();
    let records = one.irradiance.expect("overture").records;
    let opts = JobOptions {
        workers: 3,
        tile_size: 16,
        fetch: FetchPolicy::Fetch,
        irradiance: Some(params),
        ..Default::default()
    };
    let (_sched, addr) = Daemon::scheduler("2");
    let mut workers: Vec<Daemon> = (0..3).map(|_| Daemon::worker(&addr)).collect();
    let done = || Arc::new(AtomicU64::new(0));
    let t = Instant::now();
    let warm = wait(&submit_options(&addr, &scene, opts.clone(), done()));
    let whole = t.elapsed();
    let ir = warm.report.irradiance.expect("irradiance report");
    assert!(ir.by_workers && ir.records == records, "{ir:?}");
    assert_eq!(common::bits(&warm), reference);
    // The overture is most of the job: a kill at 60% of its measuring
    // lands in it. Other tests share the cores, so a job may run faster
    // than the one timed: a kill that lands after the job is tried again,
    // sooner.
    let mut into = whole.saturating_sub(Duration::from_secs_f64(ir.seconds)) / 2
        + Duration::from_secs_f64(ir.seconds * 0.6);
    let mut landed = false;
    for tries in 0..6 {
        let rx = submit_options(&addr, &scene, opts.clone(), done());
        std::thread::sleep(into);
        workers[1].signal("-KILL");
        let r = wait(&rx);
        let rec = &r.report.recovery;
        let ir2 = r.report.irradiance.expect("irradiance report");
        eprintln!(
            "try {tries}: overture {:.2} s of a {:.2} s job; killed at {:.2} s: {} attempts, rays {} against {} undisturbed",
            ir.seconds,
            whole.as_secs_f64(),
            into.as_secs_f64(),
            rec.attempts,
            ir2.rays,
            ir.rays
        );
        assert_eq!(ir2.records, records, "{ir2:?}");
        assert_eq!(common::bits(&r), reference, "the image differs");
        workers[1] = Daemon::worker(&addr);
        if rec.attempts >= 2 {
            landed = true;
            break;
        }
        into /= 2;
    }
    assert!(landed, "no kill landed during a job in 6 tries");
    workers.truncate(0);
}

/// A worker stopped mid-job (SIGSTOP: its sockets stay open, it just stops
/// answering) is lost once its heartbeats are missed; the job completes on
/// the others with the single-machine bits. Resumed, it finds itself
/// dropped, registers again, and renders its share of the next job.
#[test]
fn a_stopped_worker_is_fenced_out_and_rejoins_when_resumed() {
    let scene = scene();
    let reference = common::single_machine(&scene);
    let (_sched, addr) = Daemon::scheduler("1.5");
    let workers: Vec<Daemon> = (0..3).map(|_| Daemon::worker(&addr)).collect();
    let t = Instant::now();
    assert_eq!(common::bits(&wait(&submit(&addr, &scene, 3))), reference);
    let span = t.elapsed();
    let rx = submit(&addr, &scene, 3);
    std::thread::sleep(span / 3);
    workers[1].signal("-STOP");
    let stopped = Instant::now();
    let r = wait(&rx);
    eprintln!(
        "stopped worker: job done {:.2} s after the stop, {} attempts, lost {:?}",
        stopped.elapsed().as_secs_f64(),
        r.report.recovery.attempts,
        r.report.recovery.lost
    );
    assert_eq!(common::bits(&r), reference, "the image differs");
    assert_eq!(r.report.recovery.lost.len(), 1, "{:?}", r.report.recovery);
    assert!(
        r.report.recovery.lost[0].1.contains("heartbeat"),
        "{:?}",
        r.report.recovery.lost
    );
    assert!(
        r.report.workers.len() == 2,
        "the job went on with the others"
    );
    workers[1].signal("-CONT");
    // The next job asks for all three: it starts once the resumed worker
    // has registered again, and each of them renders tiles.
    let next = wait(&submit(&addr, &scene, 3));
    assert_eq!(common::bits(&next), reference);
    assert_eq!(next.report.workers.len(), 3);
    assert!(
        next.report.workers.iter().all(|w| w.stats.tiles > 0),
        "every worker rendered tiles: {:?}",
        next.report
            .workers
            .iter()
            .map(|w| w.stats.tiles)
            .collect::<Vec<_>>()
    );
}

/// A scheduler with a state directory: how to start it on an address.
struct Stateful {
    dir: std::path::PathBuf,
}

impl Stateful {
    fn new(tag: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("locus-state-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        Self { dir }
    }

    fn spawn(&self, listen: &str) -> (Daemon, String) {
        let state = self.dir.to_str().expect("a UTF-8 temp dir");
        Daemon::spawn(&[
            "scheduler",
            "--listen",
            listen,
            "--worker-timeout",
            "2",
            "--state",
            state,
        ])
    }
}

impl Drop for Stateful {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// Runs `scene` on two workers and a scheduler with a state directory,
/// kills the scheduler (`kill -9`) once `kill_at` pixel samples are in and
/// the store has had time for three commits since the first tile (it
/// commits at most every `COMMIT_EVERY`, and loses what came since its
/// last commit), starts it again on the same address and state, and
/// waits for the job: its result and the restarted scheduler.
fn killed_mid_job(
    state: &Stateful,
    scene: &locus_core::scene::Scene,
    kill_at: u64,
) -> (JobResult, Daemon) {
    let (sched, addr) = state.spawn("127.0.0.1:0");
    let _workers: Vec<Daemon> = (0..2).map(|_| Daemon::worker(&addr)).collect();
    let done = Arc::new(AtomicU64::new(0));
    let rx = submit_watched(&addr, scene, 2, done.clone());
    let t = Instant::now();
    let mut first = None;
    loop {
        let d = done.load(Relaxed);
        if d > 0 && first.is_none() {
            first = Some(Instant::now());
        }
        let settled =
            first.is_some_and(|f| f.elapsed() >= 3 * locus_scheduler::store::COMMIT_EVERY);
        if d >= kill_at && settled {
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(120),
            "the job never got going"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
    sched.signal("-KILL");
    drop(sched);
    let killed = Instant::now();
    // The same address again (a restarted daemon behind the same name).
    let mut again = None;
    for _ in 0..50 {
        let (d, a) = state.spawn(&addr);
        if a == addr {
            again = Some(d);
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let sched = again.expect("the scheduler restarts on its address");
    let r = wait(&rx);
    eprintln!(
        "scheduler restarted: job done {:.2} s after the kill, {} tile passes kept from the store, {} attempts",
        killed.elapsed().as_secs_f64(),
        r.report.recovery.tile_passes_kept,
        r.report.recovery.attempts
    );
    (r, sched)
}

/// The scheduler killed (`kill -9`) a quarter of the way into a job and
/// started again on the same address and state directory: the workers
/// register again, the client attaches again, and the job resumes with
/// the tiles the store held, ending with the single-machine bits.
#[test]
fn a_scheduler_restarted_on_its_state_resumes_the_job() {
    // Long enough that a kill after the store's first commits of tiles
    // (at most `COMMIT_EVERY` apart) still lands mid-job.
    let scene = scene_of(320, 240);
    let reference = common::single_machine(&scene);
    let state = Stateful::new("even");
    // 300 tiles of 16x16 in 5 passes of 1, 1, 2, 4 and 8 samples: killed
    // once a quarter of the samples are in (the first three passes, 900
    // tile passes).
    let (r, sched) = killed_mid_job(&state, &scene, 320 * 240 * 16 / 4);
    assert_eq!(
        common::bits(&r),
        reference,
        "the resumed job's image differs"
    );
    // What the store had committed: not what came after its last commit,
    // so not all of the 900 or more tile passes in.
    let kept = r.report.recovery.tile_passes_kept;
    assert!(
        (1..1500).contains(&kept),
        "the store kept {kept} tile passes of the 900 or more done before the kill"
    );
    // Killed once more after the job finished: the result is in the store,
    // and a client attaching to the restarted scheduler gets it.
    sched.signal("-KILL");
    drop(sched);
    let (_third, addr) = state.spawn("127.0.0.1:0");
    let rt = common::runtime();
    let again = rt
        .block_on(locus_scheduler::client::attach_to(
            &addr,
            TOKEN,
            r.job,
            &|_, _| {},
        ))
        .expect("the finished job's result outlives a restart");
    assert_eq!(common::bits(&again), reference, "the stored result differs");
}

/// Adaptive sampling through a scheduler killed in its spread pass, some
/// tiles' share of it in the store and others not: the restarted film
/// hands out the spread it kept, and the job ends with one machine's bits
/// and counts.
#[test]
fn a_scheduler_restarted_in_a_spread_pass_keeps_one_machines_bits() {
    let mut scene = scene_of(320, 240);
    scene.settings.spp = 32;
    scene.settings.adaptive_sampling = true;
    let one = common::single_machine_output(&scene);
    let counts = one.sample_counts.as_deref().expect("counted");
    let state = Stateful::new("adaptive");
    // 32 spp: a pilot of 8 (passes of 1, 1, 2 and 4 samples, 1,200 tile
    // passes), then spread passes of 8 and 16 samples' worth, a quarter
    // and a half of the job: killed 65% of the way in, which the store,
    // a commit or two behind, holds in a spread pass.
    let (r, _sched) = killed_mid_job(&state, &scene, 320 * 240 * 32 * 13 / 20);
    let (got, want) = (common::bits(&r), one.image.to_bits());
    let differ = got.iter().zip(&want).filter(|(a, b)| a != b).count();
    assert_eq!(
        (got.len(), differ),
        (want.len(), 0),
        "pixel channels differing from one machine's"
    );
    assert_eq!(
        r.report.sample_counts,
        locus_core::report::SampleCounts::of(counts)
    );
    let kept = r.report.recovery.tile_passes_kept;
    assert!(
        (1201..1800).contains(&kept),
        "the store kept {kept} tile passes: not in a spread pass"
    );
}

/// Runs `c`, which must succeed; its output.
fn succeeds(c: &mut Command) -> std::process::Output {
    let o = c.output().expect("locus runs");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    o
}

/// `locus submit --detach` returns with the job's id while the job runs;
/// the job is not cancelled by its client leaving, and `locus attach`
/// fetches its image, bit-identical to `locus render` on one machine.
#[test]
fn a_detached_job_runs_on_and_attach_fetches_it() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let out = root.join("target/test-detach");
    let _ = std::fs::remove_dir_all(&out);
    std::fs::create_dir_all(&out).unwrap();
    let scene = root.join("scenes/cornell-box/cornell.toml");
    let (_sched, addr) = Daemon::scheduler("5");
    let _worker = Daemon::worker(&addr);
    let locus = || {
        let mut c = Command::new(env!("CARGO_BIN_EXE_locus"));
        c.env("LOCUS_TOKEN", TOKEN).env("RUST_LOG", "warn");
        c
    };
    let sub = succeeds(
        locus()
            .args(["submit", "--detach", "--spp", "12", "--scheduler", &addr])
            .arg(&scene),
    );
    let said = String::from_utf8_lossy(&sub.stdout);
    let job = said
        .trim()
        .strip_prefix("job ")
        .unwrap_or_else(|| panic!("`job N` on stdout, got {said:?}"));
    succeeds(
        locus()
            .args(["attach", "--scheduler", &addr, job, "-o"])
            .arg(out.join("attached.exr")),
    );
    succeeds(
        locus()
            .args(["render", "--spp", "12", "--threads", "2"])
            .arg(&scene)
            .arg("-o")
            .arg(out.join("single.exr")),
    );
    let diff = locus()
        .args(["diff", "--exact"])
        .arg(out.join("attached.exr"))
        .arg(out.join("single.exr"))
        .output()
        .unwrap();
    assert!(
        diff.status.success(),
        "{}{}",
        String::from_utf8_lossy(&diff.stdout),
        String::from_utf8_lossy(&diff.stderr)
    );
    // A job that is not there says so.
    let none = locus()
        .args(["attach", "--scheduler", &addr, "999", "-o"])
        .arg(out.join("none.exr"))
        .output()
        .unwrap();
    assert!(!none.status.success());
    assert!(
        String::from_utf8_lossy(&none.stderr).contains("no job 999"),
        "{}",
        String::from_utf8_lossy(&none.stderr)
    );
}

/// A radiosity job that loses one of its three node workers to `kill -9`
/// mid-solve starts again on the two left and ends with the one machine's
/// solution, bit for bit, naming the worker it lost.
#[test]
fn a_radiosity_job_survives_a_killed_node() {
    use locus_core::radiosity::output::mesh_triangles;
    use locus_core::radiosity::shoot::BvhVisibility;
    use locus_core::radiosity::{RadiosityParams, Solver, solve};
    use locus_protocol::radiosity::{Balance, RadiosityJob};
    use locus_protocol::submit::JobKind;
    let mut scene = common::small_cornell(32, 24, 3);
    scene.settings.spp = 1;
    let params = RadiosityParams {
        mesh: 4,
        stop: 1e-2,
        ..Default::default()
    };
    let mut solver = Solver::new(&scene, params).unwrap();
    let prep = locus_core::render::Prepared::new(scene.clone());
    solve(&mut solver, &BvhVisibility(&prep.accel), &mut |_| {});
    let bits = |m: &[[(glam::Vec3, glam::Vec3); 3]]| -> Vec<u32> {
        m.iter()
            .flatten()
            .flat_map(|(p, l)| p.to_array().into_iter().chain(l.to_array()))
            .map(f32::to_bits)
            .collect()
    };
    let want = bits(&mesh_triangles(&solver));
    let (_sched, addr) = Daemon::scheduler("2");
    let mut workers: Vec<Daemon> = (0..3).map(|_| Daemon::worker(&addr)).collect();
    let run = |addr: &str| {
        let mut req = locus_scheduler::client::request(
            &scene,
            JobOptions {
                workers: 3,
                ..Default::default()
            },
        );
        req.kind = JobKind::Radiosity(Box::new(RadiosityJob {
            params,
            ring: 0,
            balance: Balance::Both,
            spp: 1,
        }));
        let (tx, rx) = mpsc::channel();
        let addr = addr.to_string();
        std::thread::spawn(move || {
            let rt = common::runtime();
            let r = rt.block_on(locus_scheduler::client::submit(
                &addr,
                TOKEN,
                req,
                &|_, _| {},
            ));
            let _ = tx.send(r);
        });
        rx
    };
    let t = Instant::now();
    let calm = wait(&run(&addr));
    let span = t.elapsed();
    let rad = calm.radiosity.as_ref().expect("radiosity");
    assert_eq!(bits(&rad.mesh), want);
    assert_eq!(rad.attempts, 1);
    let rx = run(&addr);
    std::thread::sleep(span / 2);
    workers[1].signal("-KILL");
    let r = wait(&rx);
    let rad = r.radiosity.as_ref().expect("radiosity");
    eprintln!(
        "undisturbed {:.2} s; after the kill: {} attempts, lost {:?}, {} nodes",
        span.as_secs_f64(),
        rad.attempts,
        rad.lost,
        rad.nodes
    );
    assert_eq!(bits(&rad.mesh), want, "the solution after a lost node");
    assert_eq!(rad.attempts, 2, "the kill landed mid-solve: {:?}", rad.lost);
    assert_eq!(rad.lost.len(), 1);
    assert_eq!(rad.nodes, 2);
    workers.remove(1);
}
