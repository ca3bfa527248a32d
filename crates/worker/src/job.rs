//! Setting up one job on a worker: checking what the scheduler sent,
//! building the region's BVH part by part as the parts arrive, linking to
//! every peer, and starting the [`crate::engine`] on its own thread.

use crate::engine::{self, EngineError, EngineJob, Event, Links};
use crate::peers::{self, Inbox, JobLink, OnBreak, Traffic};
use crate::sys;
use anyhow::{Context, bail};
use locus_core::accel::Accel;
use locus_core::accel_set::Part;
use locus_core::irradiance::IrradianceCache;
use locus_protocol::control::{JobSetup, TriangleSet, WorkerToScheduler};
use locus_protocol::handshake::Credentials;
use locus_protocol::overture::LevelChunk;
use locus_protocol::report::WorkerStats;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

/// Capacity of the engine's event channel: enough to keep the engine fed
/// while it traces; a full channel stops the socket readers, which is TCP
/// backpressure on the senders.
const EVENTS: usize = 256;
/// Capacity of each outgoing peer channel, in packets.
const PEER_OUT: usize = 64;

/// A job whose region is arriving.
pub struct Building {
    pub setup: Box<JobSetup>,
    /// The irradiance overture's levels from the scheduler: the sender
    /// goes to the control loop when the region is in.
    pub levels: Option<(flume::Sender<LevelChunk>, flume::Receiver<LevelChunk>)>,
    pub parts: Vec<Arc<Part>>,
    pub received: u64,
    pub bvh_s: f64,
    /// Process CPU seconds when the job started (a daemon's own process).
    pub cpu0: f64,
    /// The worker's tracing pool (None for a worker of one thread): idle
    /// while the region arrives, it builds the region's BVHs.
    pub pool: Option<Arc<rayon::ThreadPool>>,
}

impl Building {
    /// Checks a job's setup before any geometry is accepted.
    pub fn new(
        setup: Box<JobSetup>,
        dedicated: bool,
        pool: Option<Arc<rayon::ThreadPool>>,
    ) -> anyhow::Result<Self> {
        check_setup(&setup)?;
        if dedicated {
            // The job's peak is measured from here.
            sys::reset_peak();
        }
        // Unbounded, but the control loop passes on at most the job's
        // `max_records` (see `Starting::pass_level`).
        let levels = setup.irradiance.as_ref().map(|_| flume::unbounded());
        Ok(Self {
            setup,
            levels,
            parts: Vec::new(),
            received: 0,
            bvh_s: 0.0,
            cpu0: if dedicated { sys::process_cpu_s() } else { 0.0 },
            pool,
        })
    }

    /// Checks one part of the region and builds its BVH off the runtime.
    pub async fn add_part(&mut self, leaves: Vec<u32>, chunk: TriangleSet) -> anyhow::Result<()> {
        let s = &self.setup;
        if !chunk.is_consistent() {
            bail!("a region part's lists differ in length");
        }
        self.received += chunk.len() as u64;
        if self.received > s.region_triangles {
            bail!(
                "the region holds more than the {} triangles announced",
                s.region_triangles
            );
        }
        if chunk
            .material
            .iter()
            .any(|&m| m as usize >= s.materials.len())
        {
            bail!("region geometry names a material the job does not define");
        }
        if chunk.verts.iter().flatten().any(|p| !p.is_finite()) {
            bail!("region geometry has a non-finite vertex");
        }
        if chunk.normals.iter().flatten().any(|n| !n.is_finite()) {
            bail!("region geometry has a non-finite shading normal");
        }
        if !chunk.ids.is_sorted_by(|a, b| a < b) {
            bail!("a region part's triangle ids are not ascending and distinct");
        }
        if !leaves.is_sorted_by(|a, b| a < b)
            || leaves
                .last()
                .is_some_and(|&l| l as usize >= s.map.owner.len())
        {
            bail!("a region part names leaves that are not ascending or not in the octree");
        }
        let (mag, t) = (s.magnitude, Instant::now());
        let pool = self.pool.clone();
        let part = tokio::task::spawn_blocking(move || {
            let p = build_region_part(chunk, leaves, mag, pool.as_deref());
            sys::trim_heap();
            p
        })
        .await?;
        self.bvh_s += t.elapsed().as_secs_f64();
        tracing::debug!(
            job = s.job,
            part = self.parts.len(),
            triangles = part.accel.len(),
            bytes = part.accel.bytes(),
            resident = sys::resident_bytes().unwrap_or(0),
            peak = sys::peak_resident_bytes().unwrap_or(0),
            "region part built"
        );
        self.parts.push(part);
        Ok(())
    }
}

fn check_setup(s: &JobSetup) -> anyhow::Result<()> {
    let n = s.peers.len();
    if s.map.owner.iter().any(|&o| o as usize >= n) || s.me as usize >= n {
        bail!("processor map names a worker outside the job");
    }
    if !s.own_leaves.is_sorted_by(|a, b| a.0 < b.0)
        || s.own_leaves
            .iter()
            .any(|(l, _)| s.map.owner.get(*l as usize) != Some(&s.me))
    {
        bail!("the list of own leaves is not ascending or names a leaf of another worker");
    }
    if s.leaf_tris.len() != s.map.owner.len() {
        bail!("one triangle count per leaf expected");
    }
    if let Some(c) = &s.cache {
        c.check()
            .map_err(|e| anyhow::anyhow!("cache parameters: {e}"))?;
    }
    if let Some(irr) = &s.irradiance {
        irr.check(n)
            .map_err(|e| anyhow::anyhow!("irradiance cache: {e}"))?;
    }
    Ok(())
}

/// One part of the region's BVH, built on the worker's own threads: in its
/// tracing pool, or on this thread alone for a worker of one thread (the
/// BVH builds in parallel wherever a rayon pool has threads).
pub fn build_region_part(
    chunk: TriangleSet,
    leaves: Vec<u32>,
    magnitude: f32,
    pool: Option<&rayon::ThreadPool>,
) -> Arc<Part> {
    let build = move || region_part_now(chunk, leaves, magnitude);
    match pool {
        Some(p) => p.install(build),
        None => {
            let _alone = sys::this_thread_alone();
            build()
        }
    }
}

/// The build itself, out of line so that profiles can set a region's
/// builds apart from rendering on whichever thread they ran
/// (`bench/forward_cost.py`).
#[inline(never)]
fn region_part_now(chunk: TriangleSet, leaves: Vec<u32>, magnitude: f32) -> Arc<Part> {
    Arc::new(Part::new(Accel::from_set(chunk, magnitude), leaves))
}

/// What starting a job needs from the daemon.
pub struct Env {
    pub creds: Arc<Credentials>,
    pub pool: Option<Arc<rayon::ThreadPool>>,
    pub control: flume::Sender<WorkerToScheduler>,
    pub links: Arc<watch::Sender<Option<Arc<JobLink>>>>,
    pub dedicated: bool,
    /// Tracing threads in all, the engine's included.
    pub threads: usize,
    /// The job's cancellation: aborting it while the peers are being
    /// dialed (one may be stopped and never answer) ends the start.
    pub cancel: CancellationToken,
}

/// Links to every peer and starts the engine on the built region.
pub async fn start(b: Building, env: Env) -> anyhow::Result<Arc<JobLink>> {
    let Building {
        setup,
        levels,
        parts,
        bvh_s,
        cpu0,
        received,
        pool: _,
    } = b;
    if received != setup.region_triangles {
        bail!(
            "the region ended after {received} of the {} triangles announced",
            setup.region_triangles
        );
    }
    let n = setup.peers.len();
    let me = setup.me;
    let job = setup.job;
    info!(
        job,
        me,
        parts = parts.len(),
        triangles = received,
        bvh_s,
        "region built"
    );
    let cancel = env.cancel.clone();
    let traffic = Arc::new(Traffic::new(n));
    let (events_tx, events_rx) = flume::bounded::<Event>(EVENTS);
    let link = Arc::new(JobLink {
        job,
        inbox: Inbox::Engine {
            tx: events_tx.clone(),
            seed: setup.seed,
            sampler: setup.sampler,
            workers: n,
        },
        traffic: traffic.clone(),
        cancel: cancel.clone(),
    });
    // Publish before dialing: peers dial us at the same time.
    env.links.send_replace(Some(link.clone()));

    let (outs, writers) =
        link_peers(&setup.peers, job, me, &env, &traffic, OnBreak::CancelJob).await?;

    let (setup, irradiance) = match (setup.irradiance.is_some(), levels) {
        (true, Some((_, rx))) => {
            let (setup, cache) = irradiance(setup, parts.clone(), rx, &env).await?;
            (setup, Some(cache))
        }
        _ => (setup, None),
    };
    let ej = Arc::new(EngineJob::new(*setup, irradiance));
    let links = Links {
        peers: outs,
        control: env.control.clone(),
        traffic: traffic.clone(),
        cancel: cancel.clone(),
    };
    let (pool, ctl, dedicated) = (env.pool.clone(), env.control.clone(), env.dedicated);
    let setup_cpu = if dedicated {
        sys::process_cpu_s() - cpu0
    } else {
        0.0
    };
    tokio::spawn(async move {
        let res = tokio::task::spawn_blocking(move || {
            engine::run(ej, parts, pool.as_deref(), (events_tx, events_rx), links)
        })
        .await;
        // The engine dropped its senders; a writer's byte count is final
        // once its last write returned.
        for h in writers {
            let _ = tokio::time::timeout(Duration::from_secs(10), h).await;
        }
        let msg = match res {
            Ok(Ok(mut stats)) => {
                stats.bvh_build_s = bvh_s;
                if dedicated {
                    stats.cpu_s = sys::process_cpu_s() - cpu0;
                    stats.setup_cpu_s = setup_cpu;
                    stats.peak_rss = sys::peak_resident_bytes().unwrap_or(0);
                }
                add_traffic(&mut stats, &traffic);
                WorkerToScheduler::Report {
                    job,
                    stats: Box::new(stats),
                }
            }
            // Aborted by the scheduler (or the worker shutting down):
            // what was done goes in a report of the aborted run, which
            // the scheduler adds to the job's recovery.
            Ok(Err(EngineError::Cancelled(mut stats))) => {
                add_traffic(&mut stats, &traffic);
                WorkerToScheduler::Report { job, stats }
            }
            Ok(Err(e)) => {
                warn!(job, "job failed: {e}");
                WorkerToScheduler::Failed {
                    job,
                    reason: e.to_string(),
                }
            }
            Err(e) => WorkerToScheduler::Failed {
                job,
                reason: format!("engine crashed: {e}"),
            },
        };
        let _ = ctl.send_async(msg).await;
        cancel.cancel();
    });
    env.control
        .send_async(WorkerToScheduler::Ready { job })
        .await
        .context("scheduler link closed")?;
    Ok(link)
}

/// The job's irradiance cache, from its overture on a blocking thread; the
/// setup goes there and comes back, as it holds the job's geometry.
async fn irradiance(
    setup: Box<JobSetup>,
    parts: Vec<Arc<Part>>,
    levels: flume::Receiver<LevelChunk>,
    env: &Env,
) -> anyhow::Result<(Box<JobSetup>, IrradianceCache)> {
    let (control, cancel, threads) = (env.control.clone(), env.cancel.clone(), env.threads);
    let (setup, built) = tokio::task::spawn_blocking(move || {
        let irr = setup.irradiance.as_ref().expect("checked by the caller");
        let links = crate::overture::Links {
            control: &control,
            levels: &levels,
            cancel: &cancel,
        };
        let built = crate::overture::build(&setup, irr, parts, threads, links);
        (setup, built)
    })
    .await
    .context("the irradiance overture crashed")?;
    let (cache, stats) = built?;
    info!(
        records = stats.records,
        rays = stats.trace.rays(),
        seconds = stats.seconds,
        "irradiance cache built"
    );
    Ok((setup, cache))
}

/// Outgoing peer channels (none for this worker itself) and the tasks
/// writing them.
pub type PeerLinks = (
    Vec<Option<flume::Sender<crate::peers::Outgoing>>>,
    Vec<tokio::task::JoinHandle<()>>,
);

/// Dials every peer of a job (whose links go up as their jobs start: each
/// side publishes its job before dialing), giving up when the job is
/// aborted.
pub async fn link_peers(
    peers: &[String],
    job: u64,
    me: u16,
    env: &Env,
    traffic: &Arc<Traffic>,
    on_break: OnBreak,
) -> anyhow::Result<PeerLinks> {
    let mut outs = Vec::with_capacity(peers.len());
    let mut writers = Vec::with_capacity(peers.len());
    for (w, addr) in peers.iter().enumerate() {
        if w == me as usize {
            outs.push(None);
            continue;
        }
        let (tx, rx) = flume::bounded(PEER_OUT);
        let dial = peers::dial(
            addr,
            &env.creds,
            job,
            me,
            w as u16,
            rx,
            traffic.clone(),
            env.cancel.clone(),
            on_break,
        );
        let h = tokio::select! {
            _ = env.cancel.cancelled() => bail!("the job was aborted while linking to its peers"),
            h = dial => h.with_context(|| format!("linking to peer {w} at {addr}"))?,
        };
        writers.push(h);
        outs.push(Some(tx));
    }
    Ok((outs, writers))
}

fn add_traffic(stats: &mut WorkerStats, t: &Traffic) {
    for (p, c) in stats.peers.iter_mut().zip(t.snapshot()) {
        *p = c;
    }
}
