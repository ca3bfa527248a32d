//! The farm's daemons and clients: `scheduler`, `worker`, `submit` and
//! `status`.

use crate::cli::*;
use crate::commands::render::*;
use crate::output::*;
use crate::runtime;
use anyhow::{Context, Result};
use locus_core::image_io::Image;
use locus_protocol::handshake::Credentials;
use locus_protocol::radiosity::RadiosityJob;
use locus_protocol::submit::JobKind;
use locus_scheduler::{Scheduler, SchedulerConfig};
use locus_worker::{Worker, WorkerConfig};
use tokio_util::sync::CancellationToken;

pub(crate) fn cmd_scheduler(a: SchedulerArgs) -> Result<()> {
    let (cfg, token, tls) = a.auth.load(true)?;
    let listen = a
        .listen
        .or(cfg.scheduler.listen.clone())
        .context("no listen address: pass --listen or set [scheduler] listen in the config")?;
    let worker_timeout = match a.worker_timeout.or(cfg.scheduler.worker_timeout_s) {
        Some(t) => std::time::Duration::from_secs_f64(
            check_timeout(t).map_err(|e| anyhow::anyhow!("worker_timeout_s: {e}"))?,
        ),
        None => locus_scheduler::WORKER_TIMEOUT,
    };
    // A scheduler lives on between jobs, and each job's preparation
    // (the scene, its octree, the preview's BVHs) frees a few hundred
    // megabytes: with glibc's moving threshold much of it stayed resident
    // (84-120 MiB after jobs on the room at 160x120, 17-23 MiB with this;
    // see `docs/benchmarks/farm-history.md`, stop 56).
    locus_worker::sys::tune_allocator();
    runtime()?.block_on(async {
        let s = Scheduler::bind(SchedulerConfig {
            listen,
            token,
            tls,
            max_queued_jobs: cfg.scheduler.max_queued_jobs.unwrap_or(16),
            http: a.http.or(cfg.scheduler.http.clone()),
            worker_timeout,
            state: a.state.or(cfg.scheduler.state.clone()),
        })
        .await?;
        serve("scheduler", s.local_addr()?, |t| s.run(t)).await
    })
}

/// Prints the bound address (scripts read it from this line) and runs a
/// daemon until SIGINT or SIGTERM.
pub(crate) async fn serve<F: std::future::Future<Output = Result<()>>>(
    what: &str,
    addr: std::net::SocketAddr,
    run: impl FnOnce(CancellationToken) -> F,
) -> Result<()> {
    println!("{what} listening on {addr}");
    let shutdown = CancellationToken::new();
    locus::cancel_on_signals(shutdown.clone());
    run(shutdown).await
}

/// Where a worker listens for peer links when neither `--listen` nor its
/// config says.
const DEFAULT_WORKER_LISTEN: &str = "0.0.0.0:0";

pub(crate) fn cmd_worker(a: WorkerArgs) -> Result<()> {
    let (cfg, token, tls) = a.auth.load(true)?;
    let w = &cfg.worker;
    let scheduler = a.scheduler.or(w.scheduler.clone()).context(
        "no scheduler address: pass --scheduler or set [worker] scheduler in the config",
    )?;
    // Peers dial a wildcard listener at the address this worker reaches
    // the scheduler from (`locus_worker::advertised`), so a worker needs
    // no address of its own to join a farm.
    let listen = a
        .listen
        .or(w.listen.clone())
        .unwrap_or_else(|| DEFAULT_WORKER_LISTEN.to_string());
    let wc = WorkerConfig {
        scheduler,
        listen,
        advertise: a.advertise.or(w.advertise.clone()),
        token,
        tls,
        threads: a.threads.or(w.threads).unwrap_or(0),
        memory_budget: a.memory_budget.or(w.memory_budget).map_or(0, |b| b.0),
        name: a
            .name
            .or(w.name.clone())
            .or_else(locus_worker::sys::hostname)
            .unwrap_or_else(|| format!("worker-{}", std::process::id())),
        dedicated: true,
        builds: None,
    };
    if wc.memory_budget > 0 {
        locus_worker::sys::tune_allocator();
    }
    super::limit_threads(wc.threads);
    runtime()?.block_on(async {
        let worker = Worker::bind(wc).await?;
        serve("worker", worker.local_addr()?, |t| worker.run(t)).await
    })
}

/// The scheduler to submit to: the flag, or the config's.
fn scheduler_of(flag: Option<String>, cfg: &locus::config::Config) -> Result<String> {
    flag.or(cfg.worker.scheduler.clone())
        .context("no scheduler address: pass --scheduler or set [worker] scheduler in the config")
}

pub(crate) fn cmd_submit(a: SubmitArgs) -> Result<()> {
    let (cfg, token, tls) = a.auth.load(false)?;
    let creds = Credentials::new(&token, tls);
    let scheduler = scheduler_of(a.scheduler.clone(), &cfg)?;
    let scene = load_for_farm(
        &a.scene,
        Overrides {
            spp: a.spp,
            max_depth: a.max_depth,
            seed: a.seed,
            sampler: a.sampler,
            target_rel_mse: a.target_rel_mse,
            adaptive_sampling: a.adaptive_sampling,
            bvh: a.bvh,
        },
    )?;
    let reference = a.reference.as_deref().map(Image::read_exr).transpose()?;
    let mut req = locus_scheduler::client::request(&scene, a.farm.job_options(a.workers));
    if a.kind == JobKindArg::Radiosity {
        let params = a.radiosity.params();
        params.check()?;
        req.kind = JobKind::Radiosity(Box::new(RadiosityJob {
            params,
            ring: a.radiosity.ring.unwrap_or(0),
            balance: a.radiosity.balance.balance(),
            spp: a.spp.unwrap_or(16),
        }));
    }
    if a.detach {
        let job = runtime()?.block_on(locus_scheduler::client::submit_detached(
            &scheduler, creds, req,
        ))?;
        println!("job {job}");
        eprintln!(
            "job {job} runs detached; fetch its image with: locus attach --scheduler {scheduler} {job} -o {}",
            a.output.display()
        );
        return Ok(());
    }
    let (pb, progress) = tile_progress(0);
    let result = runtime()?.block_on(async {
        let shutdown = CancellationToken::new();
        locus::cancel_on_signals(shutdown.clone());
        tokio::select! {
            r = locus_scheduler::client::submit(&scheduler, creds, req, &progress) => r,
            _ = shutdown.cancelled() => Err(anyhow::anyhow!("interrupted")),
        }
    })?;
    if let Some(pb) = pb {
        pb.finish_and_clear();
    }
    write_result(&a.scene, &a.output, a.exposure, &result, reference.as_ref())
}

/// Writes a job's result: a render's image and report, or a radiosity
/// job's image, mesh, convergence plot and report.
fn write_result(
    scene: &std::path::Path,
    output: &std::path::Path,
    exposure: f32,
    r: &locus_protocol::submit::JobResult,
    reference: Option<&Image>,
) -> Result<()> {
    match &r.radiosity {
        Some(rad) => crate::commands::radiosity::write_farm_solution(
            scene, output, exposure, r, rad, reference,
        ),
        None => write_farm_result(scene, output, exposure, r, reference),
    }
}

pub(crate) fn cmd_attach(a: AttachArgs) -> Result<()> {
    let (cfg, token, tls) = a.auth.load(false)?;
    let creds = Credentials::new(&token, tls);
    let scheduler = scheduler_of(a.scheduler.clone(), &cfg)?;
    let (pb, progress) = tile_progress(0);
    let result = runtime()?.block_on(async {
        let shutdown = CancellationToken::new();
        locus::cancel_on_signals(shutdown.clone());
        tokio::select! {
            r = locus_scheduler::client::attach_to(&scheduler, creds, a.job, &progress) => r,
            _ = shutdown.cancelled() => Err(anyhow::anyhow!("interrupted")),
        }
    })?;
    if let Some(pb) = pb {
        pb.finish_and_clear();
    }
    let scene = std::path::PathBuf::from(&result.report.scene);
    write_result(&scene, &a.output, a.exposure, &result, None)
}

pub(crate) fn cmd_status(http: &str, json: bool) -> Result<()> {
    let (body, status) = locus::status::fetch(http)?;
    if json {
        println!("{body}");
    } else {
        print!("{}", locus::status::format(&status));
    }
    Ok(())
}
