//! The scheduler's actor: it alone owns the worker registry, the queue and
//! the running job, and every connection task talks to it through one
//! bounded channel, so no state is shared between tasks.
//!
//! A job moves through its phases in one direction only: preparing,
//! distributing, rendering, collecting. Events may arrive in any order (a
//! worker can finish every tile of a tiny job before the last worker
//! reports ready), and none moves a job back: readiness is counted, tiles
//! are handed out as soon as a worker asks, and reports are taken once the
//! last tile is in.

use crate::distribute;
use crate::job::{self, Member};
use crate::metrics::Metrics;
use crate::report::build_report;
use crate::status::{self, EndedJob, Status};
use crate::tiles::TileQueue;
use locus_core::image_io::Image;
use locus_protocol::control::{Registration, SchedulerToWorker, TileAssignment, WorkerToScheduler};
use locus_protocol::report::WorkerStats;
use locus_protocol::submit::{JobRequest, JobResult, RESULT_CHUNK_PIXELS, SchedulerToClient};
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
    },
    Prepared {
        job: u64,
        prep: Result<Box<job::Prepared>, String>,
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
}

pub(crate) struct Queued {
    pub(crate) req: Box<JobRequest>,
    client: mpsc::Sender<SchedulerToClient>,
    /// On tokio's clock, so that a test can let [`WORKER_WAIT`] pass.
    since: tokio::time::Instant,
}

/// How long a job may wait for the workers it asks for to register (a farm
/// coming up registers its workers over a few seconds) before it fails,
/// saying how many it asked for and how many there are.
pub const WORKER_WAIT: std::time::Duration = std::time::Duration::from_secs(60);

/// The most tiles one request may ask for: a worker asks for a few, and a
/// request for billions must not keep the actor busy.
pub const MAX_TILE_REQUEST: u32 = 256;

/// How often the actor looks at what no event announces: a client that
/// went away, a job waiting too long for workers.
const TICK: std::time::Duration = std::time::Duration::from_millis(500);

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Phase {
    Preparing,
    Distributing,
    Rendering,
    Collecting,
}

pub struct Running {
    pub id: u64,
    /// The request without its triangles (the scene lives in `prep`).
    pub req: Box<JobRequest>,
    client: mpsc::Sender<SchedulerToClient>,
    /// Registry ids; the position is the job's worker id.
    pub members: Vec<u32>,
    pub(crate) phase: Phase,
    pub prep: Option<Box<job::Prepared>>,
    pub(crate) tiles: Vec<TileAssignment>,
    /// Tiles not yet handed out, by worker (made when the job is prepared).
    queue: TileQueue,
    pub(crate) done: u32,
    /// Tiles returned, by job worker.
    pub(crate) tiles_by: Vec<u32>,
    /// Which tiles are in the film: a tile is counted once, however often
    /// it arrives.
    received: Vec<bool>,
    told_no_more: Vec<bool>,
    film: Vec<[f32; 3]>,
    ready: usize,
    pub reports: Vec<Option<WorkerStats>>,
    pub started: Instant,
    pub t_prepared: Option<Instant>,
    pub t_ready: Option<Instant>,
    pub t_first_tile: Option<Instant>,
    pub t_rendered: Option<Instant>,
}

impl Running {
    /// Moves forward to `p`; never back.
    fn advance(&mut self, p: Phase) {
        self.phase = self.phase.max(p);
    }
}

pub struct Actor {
    pub workers: BTreeMap<u32, WorkerEntry>,
    pub(crate) queue: VecDeque<Queued>,
    pub(crate) job: Option<Running>,
    next_job: u64,
    max_queue: usize,
    events: mpsc::Sender<Event>,
    metrics: Arc<Metrics>,
    pub(crate) started: Instant,
    /// The last jobs that ended, newest first (at most [`status::HISTORY`]).
    pub(crate) history: VecDeque<EndedJob>,
    /// The last finished job's image, for its preview.
    last_image: Option<(u64, Arc<Image>)>,
}

impl Actor {
    pub fn new(max_queue: usize, events: mpsc::Sender<Event>, metrics: Arc<Metrics>) -> Self {
        Self {
            workers: BTreeMap::new(),
            queue: VecDeque::new(),
            job: None,
            next_job: 1,
            max_queue,
            events,
            metrics,
            started: Instant::now(),
            history: VecDeque::new(),
            last_image: None,
        }
    }

    /// Publishes the registry's and queue's counts.
    fn update_load(&self) {
        let busy = self.workers.values().filter(|w| w.busy).count();
        self.metrics.set_load(
            self.workers.len() - busy,
            busy,
            self.queue.len(),
            self.job.is_some(),
        );
    }

    fn preview(&self, id: u64) -> Option<Image> {
        if let Some(j) = self.job.as_ref().filter(|j| j.id == id) {
            return Some(Image {
                width: j.req.camera.width,
                height: j.req.camera.height,
                pixels: j.film.clone(),
            });
        }
        let (last, img) = self.last_image.as_ref()?;
        (*last == id).then(|| (**img).clone())
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
                        },
                    );
                    self.try_start();
                }
                Event::Left { id, reason } => {
                    if let Some(w) = self.workers.remove(&id) {
                        info!(worker = id, addr = %w.addr, %reason, "worker left");
                        self.metrics.worker_left(&w.reg.listen);
                        if self.job.as_ref().is_some_and(|j| j.members.contains(&id)) {
                            self.fail(format!(
                                "worker {id} ({}) left during the job: {reason}",
                                w.reg.listen
                            ));
                        }
                    }
                }
                Event::Submit { req, client } => self.submit(req, client),
                Event::Prepared { job, prep } => self.on_prepared(job, prep),
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
        if self.job.is_some() {
            self.fail("the scheduler is shutting down".into());
        }
    }

    /// What no event announces: a running job whose client went away is
    /// cancelled, queued ones are dropped, and a job that has waited
    /// [`WORKER_WAIT`] for more workers than are registered fails.
    fn watch(&mut self) {
        if self.job.as_ref().is_some_and(|j| j.client.is_closed()) {
            self.fail("the client disconnected".into());
        }
        let before = self.queue.len();
        self.queue.retain(|q| !q.client.is_closed());
        if self.queue.len() < before {
            info!(
                dropped = before - self.queue.len(),
                "queued jobs whose clients disconnected dropped"
            );
        }
        if self.job.is_none()
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
            let _ = q
                .client
                .try_send(SchedulerToClient::Failed { job: 0, reason });
            self.try_start();
        }
        self.update_load();
    }

    fn submit(&mut self, req: Box<JobRequest>, client: mpsc::Sender<SchedulerToClient>) {
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
            self.queue.push_back(Queued {
                req,
                client,
                since: tokio::time::Instant::now(),
            });
            self.try_start();
        }
    }

    fn try_start(&mut self) {
        if self.job.is_some() {
            return;
        }
        let Some(q) = self.queue.front() else { return };
        let idle: Vec<u32> = self
            .workers
            .iter()
            .filter(|(_, w)| !w.busy)
            .map(|(&i, _)| i)
            .collect();
        let want = match q.req.options.workers {
            0 => idle.len().max(1),
            n => n as usize,
        };
        if idle.len() < want {
            info!(want, have = idle.len(), "job waiting for workers");
            return;
        }
        let q = self.queue.pop_front().expect("peeked");
        let members: Vec<u32> = idle[..want].to_vec();
        let info: Vec<Member> = members
            .iter()
            .map(|m| {
                let w = self.workers.get_mut(m).expect("idle");
                w.busy = true;
                Member {
                    cores: w.reg.cores,
                    budget: w.reg.memory_budget,
                    resident: w.reg.resident,
                }
            })
            .collect();
        let id = self.next_job;
        self.next_job += 1;
        info!(job = id, scene = %q.req.name, workers = want, "job starting");
        let _ = q.client.try_send(SchedulerToClient::Accepted {
            job: id,
            workers: want as u32,
        });
        let cam = q.req.camera.clone();
        // Tiles in a shuffled order: at any moment the tiles in flight are
        // spread over the image, so every region sees its share of the work
        // all along, not only when the tiles that look at it come up (in
        // scanline order a worker whose region the top of the image sees
        // little of waited half the job for the others).
        let tiles: Vec<TileAssignment> = locus_core::render::tiles(
            cam.width,
            cam.height,
            q.req.options.tile_size,
            locus_core::render::TileOrder::Shuffled(q.req.settings.seed ^ 0x711e),
        )
        .into_iter()
        .enumerate()
        .map(|(i, t)| TileAssignment {
            job: id,
            tile: i as u32,
            x0: t.x0,
            y0: t.y0,
            x1: t.x1,
            y1: t.y1,
        })
        .collect();
        // The triangles go to preparation; the job keeps the rest.
        let mut full = q.req;
        let tris = std::mem::take(&mut full.tris);
        let mats = std::mem::take(&mut full.tri_material);
        let meta = full.clone();
        full.tris = tris;
        full.tri_material = mats;
        self.job = Some(Running {
            id,
            film: vec![[0.0; 3]; (cam.width * cam.height) as usize],
            req: meta,
            client: q.client,
            reports: vec![None; want],
            told_no_more: vec![false; want],
            tiles_by: vec![0; want],
            received: vec![false; tiles.len()],
            members,
            phase: Phase::Preparing,
            prep: None,
            tiles,
            queue: TileQueue::new([], &[], 0),
            done: 0,
            ready: 0,
            started: Instant::now(),
            t_prepared: None,
            t_ready: None,
            t_first_tile: None,
            t_rendered: None,
        });
        let events = self.events.clone();
        let rects = self
            .job
            .as_ref()
            .map(|j| j.tiles.clone())
            .unwrap_or_default();
        tokio::spawn(async move {
            let prep =
                tokio::task::spawn_blocking(move || job::prepare(*full, &info, &rects)).await;
            let prep = match prep {
                Ok(Ok(p)) => Ok(Box::new(p)),
                Ok(Err(e)) => Err(e),
                Err(e) => Err(format!("preparation crashed: {e}")),
            };
            let _ = events.send(Event::Prepared { job: id, prep }).await;
        });
    }

    fn on_prepared(&mut self, id: u64, prep: Result<Box<job::Prepared>, String>) {
        let Some(j) = self.job.as_mut().filter(|j| j.id == id) else {
            return;
        };
        let mut prep = match prep {
            Ok(p) => p,
            Err(e) => {
                self.fail(format!("job {id} could not be prepared: {e}"));
                return;
            }
        };
        j.t_prepared = Some(Instant::now());
        j.advance(Phase::Distributing);
        j.queue = TileQueue::new(
            0..j.tiles.len() as u32,
            &prep.tile_affinity,
            j.members.len(),
        );
        info!(
            job = id,
            leaves = prep.leaves,
            seconds = prep.timings.total_s,
            "partitioned"
        );
        let txs: Vec<_> = j
            .members
            .iter()
            .map(|m| {
                let w = &self.workers[m];
                (w.reg.listen.clone(), w.tx.clone())
            })
            .collect();
        distribute::ship(id, &j.req, &mut prep, txs);
        j.prep = Some(prep);
    }

    fn member(&self, id: u32) -> Option<usize> {
        self.job.as_ref()?.members.iter().position(|&m| m == id)
    }

    fn on_worker(&mut self, id: u32, msg: WorkerToScheduler) {
        let Some(w) = self.member(id) else {
            warn!(
                worker = id,
                "message from a worker outside the running job ignored"
            );
            return;
        };
        let j = self.job.as_mut().expect("member of a job");
        let job_of = match &msg {
            WorkerToScheduler::Ready { job }
            | WorkerToScheduler::NeedTiles { job, .. }
            | WorkerToScheduler::Report { job, .. }
            | WorkerToScheduler::Failed { job, .. } => *job,
            WorkerToScheduler::TileDone(t) => t.job,
        };
        if job_of != j.id {
            warn!(worker = id, "message for another job ignored");
            return;
        }
        match msg {
            WorkerToScheduler::Ready { .. } => {
                j.ready += 1;
                if j.ready == j.members.len() {
                    j.t_ready = Some(Instant::now());
                    j.advance(Phase::Rendering);
                    info!(job = j.id, "all workers ready");
                }
            }
            WorkerToScheduler::NeedTiles { count, .. } => {
                let tx = &self.workers[&id].tx;
                for _ in 0..count.min(MAX_TILE_REQUEST) {
                    if let Some(k) = j.queue.next_for(w) {
                        let t = j.tiles[k as usize];
                        if tx.try_send(SchedulerToWorker::Tile(t)).is_err() {
                            // The worker asked for it, so its queue has
                            // room unless it is gone, which ends the job.
                            break;
                        }
                        j.t_first_tile.get_or_insert_with(Instant::now);
                    } else {
                        if !j.told_no_more[w] {
                            j.told_no_more[w] = true;
                            let _ = tx.try_send(SchedulerToWorker::NoMoreTiles { job: j.id });
                        }
                        break;
                    }
                }
            }
            WorkerToScheduler::TileDone(r) => self.on_tile(id, w, r),
            WorkerToScheduler::Report { stats, .. } => {
                if j.phase != Phase::Collecting {
                    self.fail(format!("worker {w} reported before the last tile was in"));
                    return;
                }
                j.reports[w] = Some(*stats);
                if j.reports.iter().all(Option::is_some) {
                    self.finish();
                }
            }
            WorkerToScheduler::Failed { reason, .. } => {
                let addr = self.workers[&id].reg.listen.clone();
                self.fail(format!("worker {w} ({addr}): {reason}"));
            }
        }
    }

    fn on_tile(&mut self, id: u32, w: usize, r: locus_protocol::control::TileResult) {
        let j = self.job.as_mut().expect("member of a job");
        let ignore = |why: &str| {
            warn!(worker = id, tile = r.tile, why, "tile result ignored");
            self.metrics.tile_ignored(why);
        };
        let Some(t) = j.tiles.get(r.tile as usize).copied() else {
            ignore("unknown");
            return;
        };
        if r.pixels.len() != t.pixels() as usize {
            let reason = format!(
                "worker {id} sent tile {} with {} pixels, expected {}",
                r.tile,
                r.pixels.len(),
                t.pixels()
            );
            self.fail(reason);
            return;
        }
        if std::mem::replace(&mut j.received[r.tile as usize], true) {
            ignore("duplicate");
            return;
        }
        let width = j.req.camera.width;
        let mut k = 0;
        for y in t.y0..t.y1 {
            for x in t.x0..t.x1 {
                j.film[(y * width + x) as usize] = r.pixels[k];
                k += 1;
            }
        }
        j.done += 1;
        j.tiles_by[w] += 1;
        self.metrics.tile();
        let _ = j.client.try_send(SchedulerToClient::Progress {
            job: j.id,
            tiles_done: j.done,
            tiles: j.tiles.len() as u32,
        });
        if j.done as usize == j.tiles.len() {
            j.advance(Phase::Collecting);
            j.t_rendered = Some(Instant::now());
            for m in &j.members {
                let _ = self.workers[m]
                    .tx
                    .try_send(SchedulerToWorker::EndJob { job: j.id });
            }
        }
    }

    fn release(&mut self) -> Option<Running> {
        let j = self.job.take()?;
        for m in &j.members {
            if let Some(w) = self.workers.get_mut(m) {
                w.busy = false;
            }
        }
        Some(j)
    }

    /// The job's workers' peer addresses, in job order.
    fn member_names(&self, j: &Running) -> Vec<String> {
        j.members
            .iter()
            .map(|m| {
                self.workers
                    .get(m)
                    .map_or_else(|| format!("worker {m}"), |w| w.reg.listen.clone())
            })
            .collect()
    }

    fn ended(&self, j: &Running, outcome: &str) -> EndedJob {
        EndedJob {
            id: j.id,
            scene: j.req.name.clone(),
            width: j.req.camera.width,
            height: j.req.camera.height,
            spp: j.req.settings.spp,
            outcome: outcome.to_string(),
            reason: None,
            seconds: j.started.elapsed().as_secs_f64(),
            workers: self.member_names(j),
            traffic: Vec::new(),
            forwarded_fraction: None,
            load_imbalance: None,
        }
    }

    fn fail(&mut self, reason: String) {
        let Some(j) = self.release() else { return };
        warn!(job = j.id, %reason, "job failed");
        self.metrics.job_failed();
        let ended = EndedJob {
            reason: Some(reason.clone()),
            ..self.ended(&j, "failed")
        };
        status::push_history(&mut self.history, ended);
        for m in &j.members {
            if let Some(w) = self.workers.get(m) {
                let _ = w.tx.try_send(SchedulerToWorker::AbortJob {
                    job: j.id,
                    reason: reason.clone(),
                });
            }
        }
        let _ = j
            .client
            .try_send(SchedulerToClient::Failed { job: j.id, reason });
        self.try_start();
    }

    fn finish(&mut self) {
        let Some(mut j) = self.release() else { return };
        let report = build_report(&j, &self.workers);
        let ended = EndedJob {
            traffic: report
                .workers
                .iter()
                .map(|w| w.stats.peers.iter().map(|p| p.bytes_sent).collect())
                .collect(),
            forwarded_fraction: Some(report.forwarded_fraction),
            load_imbalance: Some(report.load_imbalance),
            ..self.ended(&j, "done")
        };
        self.metrics
            .job_done(&report, ended.seconds, &ended.workers);
        status::push_history(&mut self.history, ended);
        info!(
            job = j.id,
            render_s = report.phases.render_s,
            imbalance = report.load_imbalance,
            forwarded = report.forwarded_fraction,
            "job done"
        );
        // One image serves the client and the preview (the last finished
        // job's, however many jobs): the client's copy is sent from it in
        // runs, never copied whole.
        let image = Arc::new(Image {
            width: j.req.camera.width,
            height: j.req.camera.height,
            pixels: std::mem::take(&mut j.film),
        });
        self.last_image = Some((j.id, image.clone()));
        let result = JobResult {
            job: j.id,
            width: image.width,
            height: image.height,
            pixels: Vec::new(),
            report,
        };
        let client = j.client;
        // The result can be large: a dedicated task sends it in chunks,
        // waiting for room, then `Done` without pixels.
        tokio::spawn(async move {
            for (k, run) in image.pixels.chunks(RESULT_CHUNK_PIXELS).enumerate() {
                let chunk = SchedulerToClient::Pixels {
                    job: result.job,
                    offset: (k * RESULT_CHUNK_PIXELS) as u64,
                    pixels: run.to_vec(),
                };
                if client.send(chunk).await.is_err() {
                    return;
                }
            }
            drop(image);
            let _ = client.send(SchedulerToClient::Done(Box::new(result))).await;
        });
        self.try_start();
    }
}
