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
//! fetched from their owners and merged into its BVH parts. [`radiosity`]
//! is the radiosity job's node and its in-process farm. [`builds`] lets the
//! workers of one process (the embedded farm) build a part they all hold
//! once, on all their threads. [`sys`] reads
//! the CPU time and peak memory that reports give. Shutdown is by a
//! cancellation token every task selects on.

pub mod builds;
pub mod engine;
pub mod fetch;
pub mod job;
pub mod overture;
pub mod peers;
pub mod radiosity;
pub mod reach;
pub mod sys;

use anyhow::Context;
use engine::{Event, Input};
use job::Building;
use locus_protocol::control::{
    HEARTBEATS_MISSED, Opening, Registration, SchedulerToWorker, WorkerToScheduler,
};
use locus_protocol::handshake::Credentials;
use locus_protocol::overture::LevelChunk;
use locus_protocol::tls::Tls;
use locus_protocol::{Backoff, ConnWriter, MAX_FRAME_LEN, handshake};
use peers::{Inbox, JobLink};
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

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
    /// TLS on the links to the scheduler and the peers (None: plain TCP).
    pub tls: Option<Tls>,
    /// Tracing threads; 0 means all cores.
    pub threads: usize,
    /// Bytes the worker's process may use (0: no limit).
    pub memory_budget: u64,
    pub name: String,
    /// Whether the worker has its process to itself (a daemon): then its
    /// reports give the process's peak memory and CPU time.
    pub dedicated: bool,
    /// BVH parts shared with the other workers of this process (the
    /// embedded farm's; see [`builds`]); None for a daemon.
    pub builds: Option<Arc<builds::SharedBuilds>>,
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
        // With few threads the engine's thread traces too, and the pool
        // has the others; with more, the pool has them all.
        let pool = if threads > 1 {
            let p = rayon::ThreadPoolBuilder::new()
                .num_threads(engine::pool_threads(threads))
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

    /// Registers and serves jobs until `shutdown`. A lost scheduler link
    /// (closed, or silent for [`HEARTBEATS_MISSED`] heartbeats) drops the
    /// job in hand, and the worker registers again, retrying with backoff
    /// for as long as it takes; only a fatal error (a wrong token, another
    /// protocol version) ends it with an error.
    pub async fn run(self, shutdown: CancellationToken) -> anyhow::Result<()> {
        let creds = Arc::new(Credentials::new(&self.cfg.token, self.cfg.tls.clone()));
        let bound = self.local_addr()?;
        let (job_tx, job_rx) = watch::channel::<Option<Arc<JobLink>>>(None);
        let accept = tokio::spawn(peers::accept_loop(
            self.listener,
            creds.clone(),
            job_rx,
            shutdown.clone(),
        ));
        let ctx = Session {
            cfg: &self.cfg,
            creds: creds.clone(),
            bound,
            pool: &self.pool,
            threads: self.threads,
            links: Arc::new(job_tx),
            shutdown: &shutdown,
        };
        let mut backoff = Backoff::default();
        let result = loop {
            let conn = match connect(&self.cfg.scheduler, &creds, &shutdown, &mut backoff).await {
                Ok(Some(c)) => c,
                Ok(None) => break Ok(()),
                Err(e) => break Err(e),
            };
            match ctx.serve(conn, &mut backoff).await {
                Ok(None) => break Ok(()),
                // A farm shutting down drops the scheduler's links at the
                // moment it tells everyone to stop: a link that fails then
                // is the shutdown, not a fault to warn of and reconnect
                // after (an embedded farm printed that warning after one
                // successful render in three).
                Ok(Some(_)) if shutdown.is_cancelled() => break Ok(()),
                Ok(Some(why)) => warn!(scheduler = %self.cfg.scheduler, "{why}; registering again"),
                Err(e) => break Err(e),
            }
        };
        shutdown.cancel();
        let _ = accept.await;
        result
    }
}

/// What one registration with the scheduler needs from the worker.
struct Session<'a> {
    cfg: &'a WorkerConfig,
    creds: Arc<Credentials>,
    bound: std::net::SocketAddr,
    pool: &'a Option<Arc<rayon::ThreadPool>>,
    threads: usize,
    links: Arc<watch::Sender<Option<Arc<JobLink>>>>,
    shutdown: &'a CancellationToken,
}

impl Session<'_> {
    /// Registers on `conn` and serves jobs until the link is lost (Some:
    /// why) or the worker shuts down (None).
    async fn serve(
        &self,
        mut conn: locus_protocol::Connection,
        backoff: &mut Backoff,
    ) -> anyhow::Result<Option<String>> {
        let listen = advertised(
            self.cfg.advertise.as_deref(),
            self.bound,
            conn.local_addr()?,
        );
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
            // Workers that build once for their process do without.
            layouts: self.cfg.builds.is_none(),
        }))
        .await?;
        let welcome = tokio::time::timeout(
            handshake::HANDSHAKE_TIMEOUT,
            conn.read_msg::<SchedulerToWorker>("control"),
        )
        .await;
        let (id, heartbeat_ms) = match welcome {
            Ok(Ok(Some(SchedulerToWorker::Welcome {
                worker,
                heartbeat_ms,
            }))) => (worker, heartbeat_ms.max(1)),
            Ok(Ok(other)) => return Ok(Some(format!("expected Welcome, got {other:?}"))),
            Ok(Err(e)) => return Ok(Some(format!("registration: {e}"))),
            Err(_) => return Ok(Some("no Welcome from the scheduler".into())),
        };
        backoff.reset();
        info!(worker = id, %listen, scheduler = %self.cfg.scheduler, "registered");
        let every = Duration::from_millis(heartbeat_ms as u64);
        let silent = every * HEARTBEATS_MISSED;
        let (mut reader, writer) = conn.into_split();
        let (ctl_tx, ctl_rx) = flume::bounded::<WorkerToScheduler>(256);
        let link = self.shutdown.child_token();
        let writer_task = tokio::spawn(control_writer(writer, ctl_rx, every, link.clone()));
        let mut jobs = Jobs::default();
        let end = loop {
            let msg = tokio::select! {
                _ = self.shutdown.cancelled() => break None,
                _ = link.cancelled() => break Some("the scheduler link failed".to_string()),
                r = jobs.started(), if jobs.starting.is_some() => {
                    jobs.settle(r, &ctl_tx).await;
                    continue;
                }
                m = tokio::time::timeout(silent, reader.read_msg::<SchedulerToWorker>("control")) => m,
            };
            let msg = match msg {
                Ok(Ok(Some((m, _)))) => m,
                Ok(Ok(None)) => break Some("the scheduler closed the connection".into()),
                Ok(Err(e)) => break Some(format!("scheduler link: {e}")),
                Err(_) => {
                    break Some(format!(
                        "no heartbeat from the scheduler for {:.1} s",
                        silent.as_secs_f64()
                    ));
                }
            };
            self.handle(msg, &mut jobs, &ctl_tx).await;
        };
        jobs.cancel_all();
        link.cancel();
        drop(ctl_tx);
        let _ = writer_task.await;
        Ok(end)
    }

    /// What starting a job needs, for a job cancelled by `cancel`.
    fn env(
        &self,
        ctl_tx: &flume::Sender<WorkerToScheduler>,
        cancel: CancellationToken,
    ) -> job::Env {
        job::Env {
            creds: self.creds.clone(),
            pool: self.pool.clone(),
            control: ctl_tx.clone(),
            links: self.links.clone(),
            dedicated: self.cfg.dedicated,
            threads: self.threads,
            cancel,
        }
    }

    /// The job being built has its whole region: links to the peers and
    /// starts its engine. Linking may wait on a peer that is stopped, so it
    /// runs as a task, and the link to the scheduler is served meanwhile
    /// (an abort must get through).
    fn region_in(&self, jobs: &mut Jobs, ctl_tx: &flume::Sender<WorkerToScheduler>, job: u64) {
        let Some(b) = jobs.building.take() else {
            return;
        };
        let cancel = CancellationToken::new();
        let env = self.env(ctl_tx, cancel.clone());
        let levels = b.levels.as_ref().map(|(tx, _)| tx.clone());
        let room = b
            .setup
            .irradiance
            .as_ref()
            .map_or(0, |i| i.params.max_records);
        jobs.starting = Some(Starting {
            job,
            cancel,
            levels,
            room,
            task: tokio::spawn(job::start(b, env)),
        });
    }

    /// One message from the scheduler.
    async fn handle(
        &self,
        msg: SchedulerToWorker,
        jobs: &mut Jobs,
        ctl_tx: &flume::Sender<WorkerToScheduler>,
    ) {
        match msg {
            SchedulerToWorker::Welcome { .. } => warn!("duplicate Welcome ignored"),
            SchedulerToWorker::Heartbeat => {}
            SchedulerToWorker::StartJob(s) => {
                jobs.cancel_all();
                let job = s.job;
                if !jobs.admits(job) {
                    return debug!(job, "the start of a run aborted before it came; dropped");
                }
                match Building::new(
                    s,
                    self.cfg.dedicated,
                    self.pool.clone(),
                    self.cfg.builds.clone(),
                ) {
                    Ok(b) => jobs.building = Some(b),
                    Err(e) => fail(ctl_tx, job, e).await,
                }
            }
            SchedulerToWorker::Geometry {
                job,
                leaves,
                chunk,
                last,
            } => {
                let Some(b) = jobs.building.as_mut().filter(|b| b.setup.job == job) else {
                    if jobs.admits(job) {
                        warn!(job, "geometry for a job not started here; ignored");
                    }
                    return;
                };
                // Decoded from the socket, the set is this message's alone:
                // taken, not copied.
                let chunk = std::sync::Arc::unwrap_or_clone(chunk);
                match b.add_part(leaves, chunk, last).await {
                    Ok(true) => self.region_in(jobs, ctl_tx, job),
                    Ok(false) => {}
                    Err(e) => {
                        jobs.building = None;
                        fail(ctl_tx, job, e).await;
                    }
                }
            }
            SchedulerToWorker::Layout { job, layout } => {
                let Some(b) = jobs.building.as_mut().filter(|b| b.setup.job == job) else {
                    if jobs.admits(job) {
                        warn!(job, "a BVH layout for a job not started here; ignored");
                    }
                    return;
                };
                match b.add_layout(layout).await {
                    Ok(()) => self.region_in(jobs, ctl_tx, job),
                    Err(e) => {
                        jobs.building = None;
                        fail(ctl_tx, job, e).await;
                    }
                }
            }
            SchedulerToWorker::StartNode(s) => {
                jobs.cancel_all();
                let job = s.job;
                if !jobs.admits(job) {
                    return debug!(job, "the start of a run aborted before it came; dropped");
                }
                let cancel = CancellationToken::new();
                jobs.starting = Some(Starting {
                    job,
                    cancel: cancel.clone(),
                    levels: None,
                    room: 0,
                    task: tokio::spawn(radiosity::daemon::start(s, self.env(ctl_tx, cancel))),
                });
            }
            SchedulerToWorker::Node { job, msg } => {
                jobs.forward(job, Inbound::Node(*msg), ctl_tx).await
            }
            SchedulerToWorker::Tile(t) => {
                jobs.forward(t.job, Inbound::Engine(Input::Tile(t)), ctl_tx)
                    .await
            }
            SchedulerToWorker::NoMoreTiles { job } => {
                jobs.forward(job, Inbound::Engine(Input::NoMoreTiles), ctl_tx)
                    .await
            }
            SchedulerToWorker::EndJob { job } => {
                jobs.forward(job, Inbound::Engine(Input::End), ctl_tx).await
            }
            SchedulerToWorker::Level(c) => {
                if let Err(e) = jobs.pass_level(*c) {
                    warn!("{e:#}");
                }
            }
            SchedulerToWorker::AbortJob { job, reason } => {
                if jobs.abort(job) {
                    warn!(job, %reason, "job aborted by the scheduler");
                }
            }
        }
    }
}

/// A scheduler message for a running job: to a render job's engine or a
/// radiosity job's node.
enum Inbound {
    Engine(Input),
    Node(locus_protocol::radiosity::ToNode),
}

/// The job a worker is receiving, starting (linking to its peers) or
/// running: at most one at a time.
#[derive(Default)]
struct Jobs {
    building: Option<Building>,
    starting: Option<Starting>,
    current: Option<Arc<JobLink>>,
    /// The last run the scheduler aborted before this worker had it. The
    /// scheduler ships a run's setup and region from a task of its own, so
    /// its `AbortJob` can overtake the `StartJob`; that start is then
    /// dropped, not run as a job nobody waits for. Run ids are never
    /// reused.
    aborted_early: Option<u64>,
}

struct Starting {
    job: u64,
    cancel: CancellationToken,
    /// The irradiance overture's levels, to the starting job.
    levels: Option<flume::Sender<LevelChunk>>,
    /// Records the overture may still be sent.
    room: usize,
    task: tokio::task::JoinHandle<anyhow::Result<Arc<JobLink>>>,
}

type Started = Result<anyhow::Result<Arc<JobLink>>, tokio::task::JoinError>;

impl Jobs {
    /// The job in hand, whatever its stage.
    fn job(&self) -> Option<u64> {
        (self.building.as_ref().map(|b| b.setup.job))
            .or(self.starting.as_ref().map(|s| s.job))
            .or(self.current.as_ref().map(|c| c.job))
    }

    /// Aborts run `job`: whatever stage it is in here, or, when it is not
    /// here yet, its start when it comes (see `aborted_early`). True when
    /// there was something to cancel.
    fn abort(&mut self, job: u64) -> bool {
        if self.job() == Some(job) {
            self.cancel_all();
            return true;
        }
        self.aborted_early = Some(job);
        false
    }

    /// Whether a start (or region) of run `job` is to be taken: not when
    /// the run was aborted before it came.
    fn admits(&self, job: u64) -> bool {
        self.aborted_early != Some(job)
    }

    fn cancel_all(&mut self) {
        self.building = None;
        if let Some(s) = self.starting.take() {
            s.cancel.cancel();
        }
        if let Some(j) = self.current.take() {
            j.cancel.cancel();
        }
    }

    /// Passes an overture level's chunk to the starting job, within its
    /// `max_records`. Past them the job's levels stop, which fails its
    /// overture and so tells the scheduler; a chunk for no starting job is
    /// dropped.
    fn pass_level(&mut self, c: LevelChunk) -> anyhow::Result<()> {
        let job = c.job;
        let Some(s) = self.starting.as_mut().filter(|s| s.job == job) else {
            anyhow::bail!("overture level for job {job}, which is not starting here; dropped");
        };
        let Some(tx) = s.levels.as_ref().filter(|_| c.records.len() <= s.room) else {
            s.levels = None;
            anyhow::bail!("job {job}: more irradiance records than the job allows");
        };
        s.room -= c.records.len();
        // The overture has ended (failed) if its receiver is gone.
        let _ = tx.send(c);
        Ok(())
    }

    /// Waits for the starting job's task (only while there is one).
    async fn started(&mut self) -> Started {
        let s = self.starting.as_mut().expect("polled only while starting");
        (&mut s.task).await
    }

    /// Takes the starting job's outcome: it runs, or its failure goes to
    /// the scheduler.
    async fn settle(&mut self, r: Started, ctl: &flume::Sender<WorkerToScheduler>) {
        let s = self.starting.take().expect("settled only while starting");
        match r {
            Ok(Ok(link)) => self.current = Some(link),
            // Aborted: the scheduler knows.
            _ if s.cancel.is_cancelled() => {}
            Ok(Err(e)) => fail(ctl, s.job, e).await,
            Err(e) => fail(ctl, s.job, anyhow::anyhow!("job start crashed: {e}")).await,
        }
    }

    /// Hands a scheduler message to the job's engine or node. The engine asks for
    /// tiles as soon as it runs, a moment before its start has settled
    /// here: a message for the starting job waits for the start.
    async fn forward(&mut self, job: u64, msg: Inbound, ctl: &flume::Sender<WorkerToScheduler>) {
        let sent = match (self.running(job, ctl).await.map(|j| &j.inbox), msg) {
            (Some(Inbox::Engine { tx, .. }), Inbound::Engine(input)) => {
                tx.send_async(Event::Input(input)).await.is_ok()
            }
            (Some(Inbox::Node(tx)), Inbound::Node(m)) => tx.send_async(m).await.is_ok(),
            (Some(_), _) => {
                return warn!(job, "a message for the other kind of job; ignored");
            }
            (None, _) => return warn!(job, "message for a job not running here; ignored"),
        };
        if !sent {
            warn!(job, "the job has stopped; message dropped");
        }
    }

    /// Job `job` once it runs here (waiting for its start), if it does.
    async fn running(
        &mut self,
        job: u64,
        ctl: &flume::Sender<WorkerToScheduler>,
    ) -> Option<&Arc<JobLink>> {
        if self.starting.as_ref().is_some_and(|s| s.job == job) {
            let r = self.started().await;
            self.settle(r, ctl).await;
        }
        self.current.as_ref().filter(|j| j.job == job)
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

/// Reaches the scheduler and completes the handshake, retrying with
/// `backoff` while it cannot be reached (daemons may start before it, and
/// it may restart); None when shut down first. A refused handshake (a
/// wrong token, another protocol version) is fatal: retrying cannot help.
async fn connect(
    addr: &str,
    creds: &Credentials,
    shutdown: &CancellationToken,
    backoff: &mut Backoff,
) -> anyhow::Result<Option<locus_protocol::Connection>> {
    loop {
        let e = tokio::select! {
            _ = shutdown.cancelled() => return Ok(None),
            r = handshake::dial(addr, creds, MAX_FRAME_LEN) => match r {
                Ok(c) => return Ok(Some(c)),
                Err(e) => e,
            },
        };
        if e.is_refusal() {
            return Err(anyhow::Error::from(e).context("worker: scheduler handshake"));
        }
        let wait = backoff.next_delay();
        warn!("{e}; retrying in {:.1} s", wait.as_secs_f64());
        tokio::select! {
            _ = shutdown.cancelled() => return Ok(None),
            _ = tokio::time::sleep(wait) => {}
        }
    }
}

/// The most messages written to the scheduler with one flush.
const BURST: usize = 64;

/// Writes the worker's messages to the scheduler, and a heartbeat whenever
/// the link has been quiet for `every`; a failed write ends the session
/// (`link`).
async fn control_writer(
    mut w: ConnWriter,
    rx: flume::Receiver<WorkerToScheduler>,
    every: Duration,
    link: CancellationToken,
) {
    loop {
        let m = tokio::select! {
            _ = link.cancelled() => break,
            m = tokio::time::timeout(every, rx.recv_async()) => match m {
                Ok(Ok(m)) => m,
                Ok(Err(_)) => break,
                Err(_) => WorkerToScheduler::Heartbeat,
            },
        };
        // What the engine sent meanwhile goes in the same write.
        let written = tokio::select! {
            _ = link.cancelled() => break,
            r = w.write_burst(&m, || rx.try_recv().ok(), BURST) => r,
        };
        if let Err(e) = written {
            warn!("scheduler link: {e}");
            link.cancel();
            break;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{Jobs, advertised};

    /// The scheduler ships a run from a task of its own, so its abort can
    /// come first: the run's start is then refused, and only that run's.
    #[test]
    fn a_run_aborted_before_it_came_is_not_started() {
        let mut jobs = Jobs::default();
        assert!(jobs.admits(7));
        assert!(!jobs.abort(7), "nothing here to cancel");
        assert!(!jobs.admits(7));
        assert!(jobs.admits(8), "the next run starts");
    }

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
