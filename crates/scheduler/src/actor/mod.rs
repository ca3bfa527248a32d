//! The scheduler's actor: it alone owns the worker registry, the queue and
//! the running job, and every connection task talks to it through one
//! bounded channel, so no state is shared between tasks.
//!
//! A job runs in attempts ([`attempt`]): each is prepared for the workers
//! it runs on, shipped, rendered tile by tile and collected, and it moves
//! through those phases in one direction only. Events may arrive in any
//! order (a worker can finish every tile of a tiny job before the last
//! worker reports ready), and none moves an attempt back. When a member
//! is lost or an attempt fails, [`recovery`] aborts the attempt, keeps the
//! finished tiles and starts a new attempt, under a new run id, on the
//! workers there are; a message of an older run is stale and ignored, so a
//! worker that comes back late cannot touch the film. [`ending`] fails or
//! finishes the job. [`clients`] attaches clients to jobs (a client whose
//! link broke takes its job up again) and keeps the last results for them.
//! With a [`Store`], jobs and their tiles are on disk as they arrive, and a
//! restarted scheduler resumes them.

mod attempt;
mod clients;
mod overture;
pub(crate) use overture::shares;
mod radiosity;

pub use clients::FINISHED_KEPT;
mod ending;
mod recovery;

pub(crate) use clients::Client;

use crate::film::{Film, PassSpread, TileSums};
use crate::job;
use crate::metrics::Metrics;
use crate::status::{EndedJob, Status};
use crate::store::{Kept, Restored, Store, Write};
use crate::tiles::TileQueue;
use locus_core::image_io::Image;
use locus_core::scene::Scene;
use locus_protocol::control::{Registration, SchedulerToWorker, WorkerToScheduler};
use locus_protocol::report::{Recovery, WorkerStats};
use locus_protocol::submit::{JobKind, JobRequest, SchedulerToClient};
use std::collections::{BTreeMap, VecDeque};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Instant;
use tokio::sync::{mpsc, oneshot};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

pub enum Event {
    Joined {
        id: u32,
        reg: Registration,
        addr: SocketAddr,
        tx: mpsc::Sender<SchedulerToWorker>,
    },
    Left {
        id: u32,
        reason: String,
    },
    FromWorker {
        id: u32,
        msg: WorkerToScheduler,
    },
    Submit {
        req: Box<JobRequest>,
        client: mpsc::Sender<SchedulerToClient>,
        /// The request encoded for the store, where the connection task
        /// did it (on a blocking thread, so neither the actor nor the
        /// runtime waits on a large scene).
        encoded: Option<Vec<u8>>,
    },
    /// A client takes up job `job` again.
    Attach {
        job: u64,
        client: mpsc::Sender<SchedulerToClient>,
    },
    /// An attempt's preparation ended; `run` names the attempt.
    Prepared {
        run: u64,
        prep: Result<Box<job::Prepared>, String>,
    },
    /// A radiosity job's coordinator returned; `run` names the job's run.
    RadiosityEnded {
        run: u64,
        outcome: Result<Box<crate::radiosity::Solved>, String>,
    },
    /// `/status`: the farm now.
    Status(oneshot::Sender<Status>),
    /// `/jobs/{id}/preview.png`: the job's film so far (the running job's
    /// finished tiles, or the last ended job's image), if it is either.
    Preview {
        job: u64,
        reply: oneshot::Sender<Option<Image>>,
    },
}

pub struct WorkerEntry {
    pub reg: Registration,
    pub addr: SocketAddr,
    pub tx: mpsc::Sender<SchedulerToWorker>,
    pub(crate) busy: bool,
    /// An `AbortJob` that found the worker's channel full, retried on
    /// every tick: dropped, it would leave the worker running a run
    /// nobody waits for until its next start.
    owed_abort: Option<SchedulerToWorker>,
}

pub(crate) struct Queued {
    /// Given at submission: the id the client attaches to.
    id: u64,
    pub(crate) req: Box<JobRequest>,
    client: Client,
    /// On tokio's clock, so that a test can let [`WORKER_WAIT`] pass.
    since: tokio::time::Instant,
    /// Tiles already rendered, some passes of them (a job restored from
    /// the store).
    tiles: Vec<(u32, TileSums)>,
    /// The open pass's spread the store kept (adaptive sampling).
    spread: Option<PassSpread>,
}

/// How long a job may wait for the workers it asks for to register (a farm
/// coming up registers its workers over a few seconds), or, after losing
/// every worker, for one to come back, before it fails, saying how many it
/// asked for and how many there are.
pub const WORKER_WAIT: std::time::Duration = std::time::Duration::from_secs(60);

/// The most tiles one request may ask for: a worker asks for a few, and a
/// request for billions must not keep the actor busy.
pub const MAX_TILE_REQUEST: u32 = 256;

/// Attempts in a row that may fail without a worker being lost before the
/// job fails: a failure that repeats on the same workers is the job's.
pub const MAX_FAILED_ATTEMPTS: u32 = 3;

/// How often the actor looks at what no event announces: a client that
/// went away, a job waiting too long for workers.
const TICK: std::time::Duration = std::time::Duration::from_millis(500);

/// An attempt's phase; `Waiting` is a job between attempts, with no
/// worker to run on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Phase {
    Waiting,
    Preparing,
    Distributing,
    Rendering,
    Collecting,
}

impl Phase {
    pub fn name(self) -> &'static str {
        match self {
            Phase::Waiting => "waiting for workers",
            Phase::Preparing => "preparing",
            Phase::Distributing => "distributing",
            Phase::Rendering => "rendering",
            Phase::Collecting => "collecting",
        }
    }
}

/// The job the farm is rendering: what outlives its attempts (the scene,
/// the film and which tiles it holds, the client).
pub struct Running {
    /// The id the client knows.
    pub id: u64,
    /// The request without its triangles (the scene holds them).
    pub req: Box<JobRequest>,
    pub(crate) scene: Arc<Scene>,
    client: Client,
    /// The image's tiles and every pass of them in so far: a tile's pass
    /// is counted once, however often it arrives, and kept across
    /// attempts.
    pub(crate) film: Film,
    pub started: Instant,
    pub recovery: Recovery,
    /// The run ids of its aborted attempts, whose workers' late reports
    /// are added to `recovery.aborted`.
    past_runs: Vec<u64>,
    /// Attempts in a row that failed with no worker lost.
    failures: u32,
    /// The irradiance cache's levels so far, kept across attempts.
    pub overture: Option<crate::overture::Overture>,
    pub attempt: Attempt,
}

impl Running {
    /// The job's progress, for its client.
    pub(crate) fn progress(&self) -> SchedulerToClient {
        let (samples_done, samples) = self.film.samples();
        SchedulerToClient::Progress {
            job: self.id,
            samples_done,
            samples,
            pass: self.film.pass(),
            passes: self.film.passes().len() as u32,
        }
    }
}

/// One attempt at the job's unfinished tiles on a set of workers.
pub struct Attempt {
    /// The id workers know this attempt by: fresh for every attempt.
    pub run: u64,
    /// Registry ids; the position is the attempt's worker id.
    pub members: Vec<u32>,
    pub(crate) phase: Phase,
    pub prep: Option<Box<job::Prepared>>,
    /// Tile passes not yet handed out, by worker (made when prepared).
    queue: TileQueue,
    /// Tile passes returned in this attempt, by worker.
    pub(crate) tiles_by: Vec<u32>,
    /// The film's tile passes and pixel samples when the attempt started.
    pub(crate) before: (u64, u64),
    told_no_more: Vec<bool>,
    /// Tiles each member asked for while the next pass was closed (a noise
    /// target's barrier, [`Film::open_passes`]): handed out when it opens.
    owed: Vec<u32>,
    /// Members that said `Ready`: their region has arrived and their job
    /// runs, so a message for it reaches its engine. One that is not ready
    /// yet may still be receiving its region (shipped by a task of its
    /// own), and would drop a message for a job it does not know.
    ready: Vec<bool>,
    /// Members whose `EndJob` is in their control channel. It is owed to
    /// every ready member once the last tile is in; a full channel is
    /// retried on the next tick.
    ended: Vec<bool>,
    /// The overture level the members are measuring, if they are.
    round: Option<crate::overture::Round>,
    pub reports: Vec<Option<WorkerStats>>,
    /// On tokio's clock: when a waiting job gives up.
    waiting_since: tokio::time::Instant,
    pub started: Instant,
    pub t_prepared: Option<Instant>,
    pub t_ready: Option<Instant>,
    pub t_first_tile: Option<Instant>,
    pub t_rendered: Option<Instant>,
}

impl Attempt {
    /// An attempt that has not started: no members, waiting for workers.
    fn waiting(before: (u64, u64)) -> Self {
        Self {
            run: 0,
            members: Vec::new(),
            phase: Phase::Waiting,
            prep: None,
            queue: TileQueue::new([], &[], 0, Default::default()),
            tiles_by: Vec::new(),
            before,
            told_no_more: Vec::new(),
            owed: Vec::new(),
            ready: Vec::new(),
            ended: Vec::new(),
            round: None,
            reports: Vec::new(),
            waiting_since: tokio::time::Instant::now(),
            started: Instant::now(),
            t_prepared: None,
            t_ready: None,
            t_first_tile: None,
            t_rendered: None,
        }
    }

    /// Moves forward to `p`; never back.
    fn advance(&mut self, p: Phase) {
        self.phase = self.phase.max(p);
    }
}

pub struct Actor {
    pub workers: BTreeMap<u32, WorkerEntry>,
    pub(crate) queue: VecDeque<Queued>,
    pub(crate) job: Option<Running>,
    /// The running radiosity job (never beside a running render job).
    pub(crate) radiosity: Option<radiosity::RadiosityRunning>,
    next_job: u64,
    /// Run ids, one per attempt of any job: never reused, so a message of
    /// an aborted attempt can never be taken for the current one's.
    next_run: u64,
    max_queue: usize,
    events: mpsc::Sender<Event>,
    metrics: Arc<Metrics>,
    pub(crate) started: Instant,
    /// The last jobs that ended, newest first (at most [`crate::status::HISTORY`]).
    pub(crate) history: VecDeque<EndedJob>,
    /// The last finished jobs' images and reports, newest first, for their
    /// previews and for clients that attach late.
    finished: VecDeque<clients::Finished>,
    store: Option<Store>,
}

impl Actor {
    pub fn new(max_queue: usize, events: mpsc::Sender<Event>, metrics: Arc<Metrics>) -> Self {
        Self {
            workers: BTreeMap::new(),
            queue: VecDeque::new(),
            job: None,
            radiosity: None,
            next_job: 1,
            next_run: 1,
            max_queue,
            events,
            metrics,
            started: Instant::now(),
            history: VecDeque::new(),
            finished: VecDeque::new(),
            store: None,
        }
    }

    /// Keeps jobs and tiles in `store` from now on, and queues the jobs it
    /// held (with their tiles) ahead of any new one; ids continue from
    /// `next_job`.
    pub fn with_store(
        mut self,
        store: Store,
        next_job: u64,
        jobs: Vec<Restored>,
        kept: Vec<Kept>,
    ) -> Self {
        for k in kept {
            self.next_job = self.next_job.max(k.id + 1);
            self.finished.push_front(clients::Finished {
                id: k.id,
                image: Arc::new(k.image),
                report: Arc::new(k.report),
                counts: k.counts.map(Arc::new),
            });
        }
        self.finished.truncate(FINISHED_KEPT);
        self.next_job = self.next_job.max(next_job);
        for r in jobs {
            self.next_job = self.next_job.max(r.id + 1);
            self.queue.push_back(Queued {
                id: r.id,
                req: r.req,
                client: Client::none(),
                since: tokio::time::Instant::now(),
                tiles: r.tiles,
                spread: r.spread,
            });
        }
        self.store = Some(store);
        self
    }

    /// Publishes the registry's and queue's counts.
    fn update_load(&self) {
        let busy = self.workers.values().filter(|w| w.busy).count();
        self.metrics.set_load(
            self.workers.len() - busy,
            busy,
            self.queue.len(),
            self.busy(),
        );
    }

    /// Whether a job (of either kind) is running.
    fn busy(&self) -> bool {
        self.job.is_some() || self.radiosity.is_some()
    }

    fn preview(&self, id: u64) -> Option<Image> {
        if let Some(j) = self.job.as_ref().filter(|j| j.id == id) {
            return Some(j.film.image());
        }
        let f = self.finished.iter().find(|f| f.id == id)?;
        Some((*f.image).clone())
    }

    pub async fn run(mut self, mut rx: mpsc::Receiver<Event>, shutdown: CancellationToken) {
        let mut tick = tokio::time::interval(TICK);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            let ev = tokio::select! {
                _ = shutdown.cancelled() => break,
                _ = tick.tick() => {
                    self.watch();
                    continue;
                }
                e = rx.recv() => match e { Some(e) => e, None => break },
            };
            match ev {
                Event::Joined { id, reg, addr, tx } => {
                    self.metrics.worker_joined(&reg.listen);
                    self.workers.insert(
                        id,
                        WorkerEntry {
                            reg,
                            addr,
                            tx,
                            busy: false,
                            owed_abort: None,
                        },
                    );
                    self.restart();
                    self.try_start();
                }
                Event::Left { id, reason } => self.left(id, reason),
                Event::Submit {
                    req,
                    client,
                    encoded,
                } => self.submit(req, client, encoded),
                Event::Attach { job, client } => self.attach(job, client),
                Event::Prepared { run, prep } => self.on_prepared(run, prep),
                Event::RadiosityEnded { run, outcome } => self.radiosity_ended(run, outcome),
                Event::FromWorker { id, msg } => self.on_worker(id, msg),
                Event::Status(reply) => {
                    let _ = reply.send(self.status());
                }
                Event::Preview { job, reply } => {
                    let _ = reply.send(self.preview(job));
                }
            }
            self.update_load();
        }
        if self.store.is_some() {
            // The store keeps the job for the next start: its workers
            // drop it, and its client attaches again then.
            self.abort_members("the scheduler is shutting down");
        } else if self.job.is_some() {
            self.fail("the scheduler is shutting down".into());
        }
        self.fail_radiosity("the scheduler is shutting down".into());
    }

    /// A worker's connection ended: it leaves the registry, and the
    /// running job recovers if it was one of the attempt's members.
    fn left(&mut self, id: u32, reason: String) {
        let Some(w) = self.workers.remove(&id) else {
            return;
        };
        info!(worker = id, addr = %w.addr, %reason, "worker left");
        self.metrics.worker_left(&w.reg.listen);
        if self.radiosity_member(id) {
            self.metrics.worker_lost();
            self.radiosity_lost(w.reg.listen, reason);
            return;
        }
        if let Some(m) = self.member(id) {
            self.metrics.worker_lost();
            let lost = recovery::Setback::Lost {
                w: m,
                addr: w.reg.listen,
            };
            self.recover(lost, reason);
        }
    }

    /// What no event announces: a running job whose client went away is
    /// cancelled, queued ones are dropped, a job that has waited
    /// [`WORKER_WAIT`] for more workers than are registered fails, and so
    /// does a job that lost every worker and has waited as long for one.
    fn watch(&mut self) {
        if self
            .job
            .as_ref()
            .is_some_and(|j| j.client.left() && !j.req.options.detached)
        {
            self.fail("the client disconnected".into());
        }
        if self
            .radiosity
            .as_ref()
            .is_some_and(|r| r.client_left() && !r.req.options.detached)
        {
            self.fail_radiosity("the client disconnected".into());
        }
        self.restart();
        self.send_ends();
        self.retry_aborts();
        let (keep, gone): (VecDeque<Queued>, VecDeque<Queued>) = std::mem::take(&mut self.queue)
            .into_iter()
            .partition(|q| !q.client.left() || q.req.options.detached);
        self.queue = keep;
        if !gone.is_empty() {
            info!(
                dropped = gone.len(),
                "queued jobs whose clients disconnected dropped"
            );
            for q in gone {
                self.forget(q.id);
            }
        }
        if !self.busy()
            && let Some(q) = self.queue.front()
            && q.since.elapsed() >= WORKER_WAIT
        {
            let want = (q.req.options.workers as usize).max(1);
            let have = self.workers.len();
            let q = self.queue.pop_front().expect("peeked");
            let reason = format!(
                "the job asks for {want} workers but {have} registered within {} s: \
                 start more workers, or submit with --workers {have}",
                WORKER_WAIT.as_secs()
            );
            warn!(scene = %q.req.name, "{reason}");
            self.metrics.job_failed();
            self.forget(q.id);
            q.client
                .send(SchedulerToClient::Failed { job: q.id, reason });
            self.try_start();
        }
        self.update_load();
    }

    fn submit(
        &mut self,
        req: Box<JobRequest>,
        client: mpsc::Sender<SchedulerToClient>,
        encoded: Option<Vec<u8>>,
    ) {
        let refuse = |reason: String| {
            let _ = client.try_send(SchedulerToClient::Failed { job: 0, reason });
        };
        if self.queue.len() >= self.max_queue {
            refuse(format!(
                "the scheduler's queue is full ({} jobs waiting)",
                self.queue.len()
            ));
        } else if let Err(reason) = job::validate(&req) {
            refuse(format!("invalid job {}: {reason}", req.name));
        } else {
            let id = self.next_job;
            self.next_job += 1;
            let _ = client.try_send(SchedulerToClient::Queued {
                job: id,
                ahead: self.queue.len() as u32 + self.busy() as u32,
            });
            if let Some(s) = &self.store {
                match encoded.map_or_else(|| postcard::to_allocvec(&*req), Ok) {
                    Ok(request) => {
                        s.write(Write::Job { id, request });
                    }
                    Err(e) => warn!(job = id, "job not stored: {e}"),
                }
            }
            self.queue.push_back(Queued {
                id,
                req,
                client: Client::some(client),
                since: tokio::time::Instant::now(),
                tiles: Vec::new(),
                spread: None,
            });
            self.try_start();
        }
    }

    /// Idle workers, in registry order.
    fn idle(&self) -> Vec<u32> {
        self.workers
            .iter()
            .filter(|(_, w)| !w.busy)
            .map(|(&i, _)| i)
            .collect()
    }

    /// Starts the next queued job once the workers it asks for are idle.
    fn try_start(&mut self) {
        if self.busy() {
            return;
        }
        let Some(q) = self.queue.front() else { return };
        let idle = self.idle();
        let want = match q.req.options.workers {
            0 => idle.len().max(1),
            n => n as usize,
        };
        if idle.len() < want {
            info!(want, have = idle.len(), "job waiting for workers");
            return;
        }
        let q = self.queue.pop_front().expect("peeked");
        let id = q.id;
        info!(job = id, scene = %q.req.name, workers = want, "job starting");
        q.client.send(SchedulerToClient::Accepted {
            job: id,
            workers: want as u32,
        });
        if let JobKind::Radiosity(rj) = &q.req.kind {
            let rj = (**rj).clone();
            self.start_radiosity(q, rj, idle[..want].to_vec());
            return;
        }
        let cam = q.req.camera.clone();
        // Tiles in a shuffled order: at any moment the tiles in flight are
        // spread over the image, so every region sees its share of the work
        // all along, not only when the tiles that look at it come up (in
        // scanline order a worker whose region the top of the image sees
        // little of waited half the job for the others).
        let tiles = locus_core::render::tiles(
            cam.width,
            cam.height,
            q.req.options.tile_size,
            locus_core::render::TileOrder::Shuffled(q.req.settings.seed ^ 0x711e),
        );
        let mut req = q.req;
        let scene = job::scene_of(&mut req);
        let mut film = Film::new(cam.width, cam.height, req.settings.spp, tiles)
            .with_target(req.settings.target_rel_mse)
            .with_adaptive(req.settings.adaptive_sampling);
        for (k, kept) in q.tiles {
            // A stored tile that does not fit the job is rendered again.
            if !film.restore(k, kept) {
                warn!(
                    job = id,
                    tile = k,
                    "a stored tile does not fit the job; rendered again"
                );
            }
        }
        if let Some(s) = q.spread
            && !film.restore_spread(s)
        {
            warn!(
                job = id,
                "a stored spread does not fit the job; spread again"
            );
        }
        film.resume();
        let before = film.done();
        let req_irradiance = req.options.irradiance;
        self.job = Some(Running {
            id,
            film,
            req,
            scene,
            client: q.client,
            started: Instant::now(),
            recovery: Recovery {
                attempts: 0,
                ..Default::default()
            },
            failures: 0,
            past_runs: Vec::new(),
            overture: req_irradiance.map(crate::overture::Overture::new),
            attempt: Attempt::waiting(before),
        });
        self.start_attempt(idle[..want].to_vec());
    }

    /// The running attempt's worker id of registry worker `id`.
    fn member(&self, id: u32) -> Option<usize> {
        self.job
            .as_ref()?
            .attempt
            .members
            .iter()
            .position(|&m| m == id)
    }

    /// Marks the attempt's members idle (they are told to drop it
    /// separately).
    fn release_members(&mut self) {
        let Some(j) = self.job.as_ref() else { return };
        for m in &j.attempt.members {
            if let Some(w) = self.workers.get_mut(m) {
                w.busy = false;
            }
        }
    }

    /// Tells the attempt's members still registered to drop it.
    fn abort_members(&mut self, reason: &str) {
        let Some(j) = self.job.as_ref() else { return };
        for m in &j.attempt.members {
            if let Some(w) = self.workers.get_mut(m) {
                let msg = SchedulerToWorker::AbortJob {
                    job: j.attempt.run,
                    reason: reason.to_string(),
                };
                w.owed_abort = owed(w.tx.try_send(msg));
            }
        }
    }

    /// Sends again the aborts that found a channel full (see
    /// `WorkerEntry::owed_abort`). One that comes after the worker's next
    /// start names a run the worker no longer has, which it ignores.
    fn retry_aborts(&mut self) {
        for w in self.workers.values_mut() {
            if let Some(msg) = w.owed_abort.take() {
                w.owed_abort = owed(w.tx.try_send(msg));
            }
        }
    }
}

/// What a send left to send again: the message, when the channel was full
/// (a closed channel's worker is leaving the registry).
fn owed(
    sent: Result<(), mpsc::error::TrySendError<SchedulerToWorker>>,
) -> Option<SchedulerToWorker> {
    match sent {
        Err(mpsc::error::TrySendError::Full(m)) => Some(m),
        _ => None,
    }
}
