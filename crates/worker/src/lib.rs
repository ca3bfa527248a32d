//! locus-worker: the worker daemon of the locus farm.
//!
//! A worker registers with the scheduler (this file), receives a job's
//! processor map and its region's geometry one BVH part at a time
//! ([`job`]: each part is built as it arrives, so no build needs more
//! memory than the job's memory plan allows), links to every peer
//! ([`peers`]) and runs the job's [`engine`] on a dedicated thread with a
//! rayon pool for tracing, while tokio tasks move frames: one reader per
//! incoming peer link, one writer per outgoing one, and the scheduler link.
//! Rays never pass through the scheduler. What a worker can trace is its
//! [`reach`]: its own region plus, under a fetch policy ([`fetch`]), leaves
//! fetched from their owners and merged into its BVH parts. [`sys`] reads
//! the CPU time and peak memory that reports give. Shutdown is by a
//! cancellation token every task selects on.

pub mod engine;
pub mod fetch;
pub mod job;
pub mod peers;
pub mod reach;
pub mod sys;

use anyhow::{Context, bail};
use engine::{Event, Input};
use job::Building;
use locus_protocol::control::{Opening, Registration, SchedulerToWorker, WorkerToScheduler};
use locus_protocol::{ConnWriter, MAX_FRAME_LEN, handshake};
use peers::JobLink;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

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
    /// Bytes the worker's process may use (0: no limit).
    pub memory_budget: u64,
    pub name: String,
    /// Whether the worker has its process to itself (a daemon): then its
    /// reports give the process's peak memory and CPU time.
    pub dedicated: bool,
}

/// A worker with its peer listener bound.
pub struct Worker {
    cfg: WorkerConfig,
    listener: TcpListener,
    /// The tracing threads besides the engine's own (None for a worker of
    /// one thread).
    pool: Option<Arc<rayon::ThreadPool>>,
    /// Tracing threads in all, the engine's included.
    threads: usize,
}

impl Worker {
    pub async fn bind(cfg: WorkerConfig) -> anyhow::Result<Self> {
        let listener = TcpListener::bind(&cfg.listen)
            .await
            .with_context(|| format!("worker: cannot listen on {}", cfg.listen))?;
        let threads = match cfg.threads {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
            t => t,
        };
        // The engine's thread traces too: the pool has the others.
        let pool = if threads > 1 {
            let p = rayon::ThreadPoolBuilder::new()
                .num_threads(threads - 1)
                .thread_name(|i| format!("locus-trace-{i}"))
                .build()
                .context("worker: cannot start the tracing pool")?;
            Some(Arc::new(p))
        } else {
            None
        };
        Ok(Self {
            cfg,
            listener,
            pool,
            threads,
        })
    }

    pub fn local_addr(&self) -> std::io::Result<std::net::SocketAddr> {
        self.listener.local_addr()
    }

    /// Registers and serves jobs until `shutdown` or until the scheduler
    /// goes away.
    pub async fn run(self, shutdown: CancellationToken) -> anyhow::Result<()> {
        let token = self.cfg.token.as_bytes().to_vec();
        let bound = self.local_addr()?;
        let (job_tx, job_rx) = watch::channel::<Option<Arc<JobLink>>>(None);
        let accept = tokio::spawn(peers::accept_loop(
            self.listener,
            token.clone(),
            job_rx,
            shutdown.clone(),
        ));

        let mut conn = connect_with_retry(&self.cfg.scheduler, &token, &shutdown).await?;
        let listen = advertised(self.cfg.advertise.as_deref(), bound, conn.local_addr()?);
        conn.write_msg(&Opening::Register(Registration {
            listen: listen.clone(),
            cores: self.threads as u32,
            memory_budget: self.cfg.memory_budget,
            resident: if self.cfg.dedicated {
                sys::resident_bytes().unwrap_or(0)
            } else {
                0
            },
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

        let mut building: Option<Building> = None;
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
                    let job = s.job;
                    building = None;
                    match Building::new(s, self.cfg.dedicated) {
                        Ok(b) => building = Some(b),
                        Err(e) => fail(&ctl_tx, job, e).await,
                    }
                }
                SchedulerToWorker::Geometry {
                    job,
                    leaves,
                    chunk,
                    last,
                } => {
                    let Some(b) = building.as_mut().filter(|b| b.setup.job == job) else {
                        warn!(job, "geometry for a job not started here; ignored");
                        continue;
                    };
                    if let Err(e) = b.add_part(leaves, chunk).await {
                        building = None;
                        fail(&ctl_tx, job, e).await;
                        continue;
                    }
                    if last {
                        let b = building.take().expect("checked above");
                        let env = job::Env {
                            token: &token,
                            pool: &self.pool,
                            control: &ctl_tx,
                            links: &job_tx,
                            dedicated: self.cfg.dedicated,
                        };
                        match job::start(b, env).await {
                            Ok(link) => current = Some(link),
                            Err(e) => fail(&ctl_tx, job, e).await,
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
                    building.take_if(|b| b.setup.job == job);
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

async fn fail(ctl: &flume::Sender<WorkerToScheduler>, job: u64, e: anyhow::Error) {
    warn!(job, "job setup failed: {e:#}");
    let _ = ctl
        .send_async(WorkerToScheduler::Failed {
            job,
            reason: format!("{e:#}"),
        })
        .await;
}

async fn forward(current: &Option<Arc<JobLink>>, job: u64, input: Input) {
    match current {
        Some(j) if j.job == job => {
            if j.inbox.send_async(Event::Input(input)).await.is_err() {
                warn!(job, "the job's engine has stopped; message dropped");
            }
        }
        _ => warn!(job, "message for a job not running here; ignored"),
    }
}

/// The address peers are told to dial: `--advertise` when given; else the
/// bound address, unless it is a wildcard (`0.0.0.0`, `::`, as in a
/// container), which no peer can dial: then the address this worker
/// reaches the scheduler from (its address on the network the farm
/// shares), with the bound port.
fn advertised(
    advertise: Option<&str>,
    bound: std::net::SocketAddr,
    toward_scheduler: std::net::SocketAddr,
) -> String {
    match advertise {
        Some(a) => a.to_string(),
        None if bound.ip().is_unspecified() => {
            std::net::SocketAddr::new(toward_scheduler.ip(), bound.port()).to_string()
        }
        None => bound.to_string(),
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

#[cfg(test)]
mod tests {
    use super::advertised;

    #[test]
    fn a_wildcard_listener_advertises_its_address_toward_the_scheduler() {
        let toward = "172.18.0.5:40112".parse().unwrap();
        let any4 = "0.0.0.0:7001".parse().unwrap();
        let any6 = "[::]:7001".parse().unwrap();
        let lo = "127.0.0.1:7001".parse().unwrap();
        assert_eq!(advertised(None, any4, toward), "172.18.0.5:7001");
        assert_eq!(advertised(None, any6, toward), "172.18.0.5:7001");
        assert_eq!(advertised(None, lo, toward), "127.0.0.1:7001");
        assert_eq!(
            advertised(Some("worker-3.locus:7001"), any4, toward),
            "worker-3.locus:7001"
        );
    }
}
