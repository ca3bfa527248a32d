//! locus-worker: the worker daemon of the locus farm.
//!
//! A worker registers with the scheduler (`lib.rs`, this file), receives a
//! job's processor map and the geometry of its own octree leaves, builds a
//! BVH over that region, links to every peer ([`peers`]) and then runs the
//! job's [`engine`] on a dedicated thread with a rayon pool for tracing,
//! while tokio tasks move frames: one reader per incoming peer link, one
//! writer per outgoing one, and the scheduler link. Rays never pass through
//! the scheduler. Under a fetch policy the engine may ask a peer for a
//! leaf's triangles instead of forwarding a ray there ([`fetch`]: the
//! byte-bounded store and the policies). Shutdown is by a cancellation
//! token every task selects on.

pub mod engine;
pub mod fetch;
pub mod peers;

use anyhow::{Context, bail};
use engine::{EngineJob, Input, Links};
use locus_core::accel::Accel;
use locus_protocol::control::{
    Opening, RegionGeometry, Registration, SchedulerToWorker, WorkerToScheduler,
};
use locus_protocol::report::WorkerStats;
use locus_protocol::{ConnWriter, MAX_FRAME_LEN, handshake};
use peers::{JobLink, Traffic};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tracing::{info, instrument, warn};

#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// host:port of the scheduler.
    pub scheduler: String,
    /// Address the peer listener binds (port 0 picks one).
    pub listen: String,
    /// Address peers should dial, when it differs from the bound one (NAT,
    /// containers); defaults to the bound address.
    pub advertise: Option<String>,
    pub token: String,
    /// Tracing threads; 0 means all cores.
    pub threads: usize,
    pub memory_budget: u64,
    pub name: String,
}

/// A worker with its peer listener bound.
pub struct Worker {
    cfg: WorkerConfig,
    listener: TcpListener,
    pool: Arc<rayon::ThreadPool>,
}

/// Capacity of the engine's inbox, in packets: enough to keep the engine fed
/// while it traces a batch; a full inbox stops the socket readers, which is
/// TCP backpressure on the senders.
const INBOX: usize = 256;
/// Capacity of each outgoing peer channel, in packets.
const PEER_OUT: usize = 64;

impl Worker {
    pub async fn bind(cfg: WorkerConfig) -> anyhow::Result<Self> {
        let listener = TcpListener::bind(&cfg.listen)
            .await
            .with_context(|| format!("worker: cannot listen on {}", cfg.listen))?;
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(cfg.threads)
            .thread_name(|i| format!("locus-trace-{i}"))
            .build()
            .context("worker: cannot start the tracing pool")?;
        Ok(Self {
            cfg,
            listener,
            pool: Arc::new(pool),
        })
    }

    pub fn local_addr(&self) -> std::io::Result<std::net::SocketAddr> {
        self.listener.local_addr()
    }

    /// Registers and serves jobs until `shutdown` or until the scheduler
    /// goes away.
    pub async fn run(self, shutdown: CancellationToken) -> anyhow::Result<()> {
        let token = self.cfg.token.as_bytes().to_vec();
        let listen = match &self.cfg.advertise {
            Some(a) => a.clone(),
            None => self.local_addr()?.to_string(),
        };
        let (job_tx, job_rx) = watch::channel::<Option<Arc<JobLink>>>(None);
        let accept = tokio::spawn(peers::accept_loop(
            self.listener,
            token.clone(),
            job_rx,
            shutdown.clone(),
        ));

        let mut conn = connect_with_retry(&self.cfg.scheduler, &token, &shutdown).await?;
        conn.write_msg(&Opening::Register(Registration {
            listen: listen.clone(),
            cores: self.pool.current_num_threads() as u32,
            memory_budget: self.cfg.memory_budget,
            name: self.cfg.name.clone(),
        }))
        .await?;
        let id = match conn.read_msg::<SchedulerToWorker>("control").await? {
            Some(SchedulerToWorker::Welcome { worker }) => worker,
            other => bail!("scheduler {}: expected Welcome, got {other:?}", conn.peer()),
        };
        info!(worker = id, %listen, scheduler = %self.cfg.scheduler, "registered");
        let sched = conn.peer();
        let (mut reader, writer) = conn.into_split();
        let (ctl_tx, ctl_rx) = flume::bounded::<WorkerToScheduler>(256);
        let writer_task = tokio::spawn(control_writer(writer, ctl_rx, shutdown.clone()));

        let mut setup: Option<Box<locus_protocol::control::JobSetup>> = None;
        let mut geometry = RegionGeometry::default();
        let mut current: Option<Arc<JobLink>> = None;
        let result = loop {
            let msg = tokio::select! {
                _ = shutdown.cancelled() => break Ok(()),
                m = reader.read_msg::<SchedulerToWorker>("control") => m,
            };
            let msg = match msg {
                Ok(Some((m, _))) => m,
                Ok(None) => {
                    info!(%sched, "scheduler closed the connection");
                    break Ok(());
                }
                Err(e) => break Err(anyhow::Error::from(e).context("scheduler link")),
            };
            match msg {
                SchedulerToWorker::Welcome { .. } => warn!(%sched, "duplicate Welcome ignored"),
                SchedulerToWorker::StartJob(s) => {
                    if let Some(j) = current.take() {
                        j.cancel.cancel();
                    }
                    geometry = RegionGeometry::default();
                    setup = Some(s);
                }
                SchedulerToWorker::Geometry { job, chunk, last } => {
                    if setup.as_ref().is_none_or(|s| s.job != job) {
                        warn!(job, "geometry for a job not started here; ignored");
                        continue;
                    }
                    geometry.ids.extend(chunk.ids);
                    geometry.verts.extend(chunk.verts);
                    geometry.material.extend(chunk.material);
                    if last {
                        let s = setup.take().expect("checked above");
                        let g = std::mem::take(&mut geometry);
                        match start_job(*s, g, &token, &self.pool, &ctl_tx, &job_tx).await {
                            Ok(link) => current = Some(link),
                            Err(e) => {
                                warn!("job setup failed: {e:#}");
                                let _ = ctl_tx
                                    .send_async(WorkerToScheduler::Failed {
                                        job,
                                        reason: format!("{e:#}"),
                                    })
                                    .await;
                            }
                        }
                    }
                }
                SchedulerToWorker::Tile(t) => forward(&current, t.job, Input::Tile(t)).await,
                SchedulerToWorker::NoMoreTiles { job } => {
                    forward(&current, job, Input::NoMoreTiles).await
                }
                SchedulerToWorker::EndJob { job } => forward(&current, job, Input::End).await,
                SchedulerToWorker::AbortJob { job, reason } => {
                    if let Some(j) = current.take_if(|j| j.job == job) {
                        warn!(job, %reason, "job aborted by the scheduler");
                        j.cancel.cancel();
                    }
                }
            }
        };
        if let Some(j) = current.take() {
            j.cancel.cancel();
        }
        shutdown.cancel();
        let _ = accept.await;
        drop(ctl_tx);
        let _ = writer_task.await;
        result
    }
}

async fn forward(current: &Option<Arc<JobLink>>, job: u64, input: Input) {
    match current {
        Some(j) if j.job == job => {
            if j.inbox.send_async(input).await.is_err() {
                warn!(job, "the job's engine has stopped; message dropped");
            }
        }
        _ => warn!(job, "message for a job not running here; ignored"),
    }
}

async fn connect_with_retry(
    addr: &str,
    token: &[u8],
    shutdown: &CancellationToken,
) -> anyhow::Result<locus_protocol::Connection> {
    // Daemons may start before the scheduler; a refused handshake (token,
    // version) is final.
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        match handshake::dial(addr, token, MAX_FRAME_LEN).await {
            Ok(c) => return Ok(c),
            Err(e @ locus_protocol::ProtocolError::Connect { .. }) if Instant::now() < deadline => {
                warn!("{e}; retrying");
                tokio::select! {
                    _ = shutdown.cancelled() => bail!("shut down before reaching the scheduler"),
                    _ = tokio::time::sleep(Duration::from_millis(500)) => {}
                }
            }
            Err(e) => return Err(anyhow::Error::from(e).context("worker: scheduler handshake")),
        }
    }
}

async fn control_writer(
    mut w: ConnWriter,
    rx: flume::Receiver<WorkerToScheduler>,
    shutdown: CancellationToken,
) {
    loop {
        let m = tokio::select! {
            _ = shutdown.cancelled() => break,
            m = rx.recv_async() => match m { Ok(m) => m, Err(_) => break },
        };
        if let Err(e) = w.write_msg(&m).await {
            warn!("scheduler link: {e}");
            shutdown.cancel();
            break;
        }
    }
}

/// Builds the region's BVH, links to every peer and starts the engine.
#[instrument(skip_all, fields(job = setup.job, me = setup.me))]
async fn start_job(
    setup: locus_protocol::control::JobSetup,
    geometry: RegionGeometry,
    token: &[u8],
    pool: &Arc<rayon::ThreadPool>,
    ctl: &flume::Sender<WorkerToScheduler>,
    job_tx: &watch::Sender<Option<Arc<JobLink>>>,
) -> anyhow::Result<Arc<JobLink>> {
    let n = setup.peers.len();
    let me = setup.me;
    if geometry.ids.len() != geometry.verts.len() || geometry.ids.len() != geometry.material.len() {
        bail!("region geometry lists differ in length");
    }
    if geometry
        .material
        .iter()
        .any(|&m| m as usize >= setup.materials.len())
    {
        bail!("region geometry names a material the job does not define");
    }
    if setup.map.owner.iter().any(|&o| o as usize >= n) || me as usize >= n {
        bail!("processor map names a worker outside the job");
    }
    if !setup.own_leaves.is_sorted_by(|a, b| a.0 < b.0)
        || setup
            .own_leaves
            .iter()
            .any(|(l, _)| setup.map.owner.get(*l as usize) != Some(&me))
    {
        bail!("the list of own leaves is not ascending or names a leaf of another worker");
    }
    if setup.leaf_tris.len() != setup.map.owner.len() {
        bail!("one triangle count per leaf expected");
    }
    if let Some(c) = &setup.cache {
        c.check()
            .map_err(|e| anyhow::anyhow!("cache parameters: {e}"))?;
    }
    let t = Instant::now();
    let (accel, geometry) = tokio::task::spawn_blocking({
        let mag = setup.magnitude;
        move || {
            (
                Accel::build_indexed(&geometry.ids, &geometry.verts, mag),
                geometry,
            )
        }
    })
    .await?;
    let bvh_s = t.elapsed().as_secs_f64();
    info!(triangles = geometry.len(), bvh_s, "region BVH built");

    let cancel = CancellationToken::new();
    let traffic = Arc::new(Traffic::new(n));
    let (inbox_tx, inbox_rx) = flume::bounded::<Input>(INBOX);
    let link = Arc::new(JobLink {
        job: setup.job,
        inbox: inbox_tx,
        traffic: traffic.clone(),
        cancel: cancel.clone(),
    });
    // Publish before dialing: peers dial us at the same time.
    job_tx.send_replace(Some(link.clone()));

    let mut outs = Vec::with_capacity(n);
    let mut writers = Vec::with_capacity(n);
    for (w, addr) in setup.peers.iter().enumerate() {
        if w == me as usize {
            outs.push(None);
            continue;
        }
        let (tx, rx) = flume::bounded(PEER_OUT);
        let h = peers::dial(
            addr,
            token,
            setup.job,
            me,
            w as u16,
            rx,
            traffic.clone(),
            cancel.clone(),
        )
        .await
        .with_context(|| format!("linking to peer {w} at {addr}"))?;
        writers.push(h);
        outs.push(Some(tx));
    }

    let job = setup.job;
    let ej = EngineJob::new(setup, n, accel, geometry);
    let links = Links {
        peers: outs,
        control: ctl.clone(),
    };
    let pool = pool.clone();
    let ctl2 = ctl.clone();
    let cancel2 = cancel.clone();
    tokio::spawn(async move {
        let res =
            tokio::task::spawn_blocking(move || engine::run(&ej, &pool, inbox_rx, links)).await;
        // The engine dropped its senders; a writer's byte count is final
        // once its last write returned.
        for h in writers {
            let _ = tokio::time::timeout(Duration::from_secs(10), h).await;
        }
        let msg = match res {
            Ok(Ok(mut stats)) => {
                stats.bvh_build_s = bvh_s;
                add_traffic(&mut stats, &traffic);
                WorkerToScheduler::Report {
                    job,
                    stats: Box::new(stats),
                }
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
        let _ = ctl2.send_async(msg).await;
        cancel2.cancel();
    });
    ctl.send_async(WorkerToScheduler::Ready { job })
        .await
        .context("scheduler link closed")?;
    Ok(link)
}

fn add_traffic(stats: &mut WorkerStats, t: &Traffic) {
    for (p, c) in stats.peers.iter_mut().zip(t.snapshot()) {
        *p = c;
    }
}
