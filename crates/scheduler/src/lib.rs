//! locus-scheduler: the scheduler daemon of the locus farm, and the client
//! that submits jobs to it.
//!
//! Connections are accepted here and authenticated by the handshake; the
//! first message says whether the peer is a worker ([`Opening::Register`])
//! or a client ([`Opening::Submit`]). Every connection task talks to one
//! actor task through a bounded channel; the actor owns the worker registry
//! and the running job, so no state is shared between tasks. A job goes
//! through [`job::prepare`] (octree, [`cost`] prediction, [`partition`]) on
//! a blocking thread, then distribution (processor map plus each region's
//! geometry, once per job), then demand-driven tiles, then the workers'
//! reports, which become the [`FarmReport`]. [`client`] is the submitting
//! side used by `locus submit` and the embedded farm.

pub mod client;
pub mod cost;
pub mod job;
pub mod partition;

use anyhow::Context;
use locus_protocol::control::{
    JobSetup, Opening, Registration, SchedulerToWorker, TileAssignment, WorkerToScheduler,
};
use locus_protocol::report::{FarmReport, Phases, Prediction, WorkerStats, WorkerSummary};
use locus_protocol::submit::{JobRequest, JobResult, SchedulerToClient};
use locus_protocol::{Connection, MAX_FRAME_LEN, handshake};
use std::collections::{BTreeMap, VecDeque};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::net::TcpListener;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{info, instrument, warn};

#[derive(Clone, Debug)]
pub struct SchedulerConfig {
    pub listen: String,
    pub token: String,
    /// Jobs that may wait behind the running one.
    pub max_queued_jobs: usize,
}

pub struct Scheduler {
    cfg: SchedulerConfig,
    listener: TcpListener,
}

/// Triangles per geometry frame: about 20 MB, well under the frame limit.
const GEOMETRY_CHUNK: usize = 400_000;

enum Event {
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
        prep: Box<job::Prepared>,
    },
}

impl Scheduler {
    pub async fn bind(cfg: SchedulerConfig) -> anyhow::Result<Self> {
        let listener = TcpListener::bind(&cfg.listen)
            .await
            .with_context(|| format!("scheduler: cannot listen on {}", cfg.listen))?;
        Ok(Self { cfg, listener })
    }

    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    pub async fn run(self, shutdown: CancellationToken) -> anyhow::Result<()> {
        info!(addr = %self.local_addr()?, "scheduler listening");
        let (ev_tx, ev_rx) = mpsc::channel::<Event>(1024);
        let actor = tokio::spawn(
            Actor {
                workers: BTreeMap::new(),
                queue: VecDeque::new(),
                job: None,
                next_job: 1,
                max_queue: self.cfg.max_queued_jobs,
                events: ev_tx.clone(),
            }
            .run(ev_rx, shutdown.clone()),
        );
        let token = Arc::new(self.cfg.token.into_bytes());
        let mut next_id = 0u32;
        loop {
            let (stream, addr) = tokio::select! {
                _ = shutdown.cancelled() => break,
                r = self.listener.accept() => match r {
                    Ok(x) => x,
                    Err(e) => {
                        warn!("accept: {e}");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                        continue;
                    }
                },
            };
            next_id += 1;
            let (token, ev, sd) = (token.clone(), ev_tx.clone(), shutdown.clone());
            let id = next_id;
            tokio::spawn(async move {
                if let Err(e) = serve(stream, id, &token, ev, sd).await {
                    warn!(%addr, "connection dropped: {e:#}");
                }
            });
        }
        drop(ev_tx);
        let _ = actor.await;
        Ok(())
    }
}

#[instrument(skip_all, fields(conn = id, peer = %stream.peer_addr().map(|a| a.to_string()).unwrap_or_default()))]
async fn serve(
    stream: tokio::net::TcpStream,
    id: u32,
    token: &[u8],
    ev: mpsc::Sender<Event>,
    shutdown: CancellationToken,
) -> anyhow::Result<()> {
    let mut conn = Connection::new(stream, MAX_FRAME_LEN)?;
    handshake::server(&mut conn, token).await?;
    let addr = conn.peer();
    let opening = tokio::select! {
        _ = shutdown.cancelled() => return Ok(()),
        m = conn.read_msg::<Opening>("opening") => m?,
    };
    match opening {
        None => Ok(()),
        Some(Opening::Register(reg)) => {
            conn.write_msg(&SchedulerToWorker::Welcome { worker: id })
                .await?;
            let (mut r, mut w) = conn.into_split();
            let (tx, mut rx) = mpsc::channel::<SchedulerToWorker>(256);
            info!(worker = id, listen = %reg.listen, cores = reg.cores, "worker registered");
            ev.send(Event::Joined { id, reg, addr, tx }).await?;
            let writer = tokio::spawn(async move {
                while let Some(m) = rx.recv().await {
                    w.write_msg(&m).await?;
                }
                Ok::<(), locus_protocol::ProtocolError>(())
            });
            let reason = loop {
                let m = tokio::select! {
                    _ = shutdown.cancelled() => break "scheduler shutting down".to_string(),
                    m = r.read_msg::<WorkerToScheduler>("control") => m,
                };
                match m {
                    Ok(Some((msg, _))) => {
                        if ev.send(Event::FromWorker { id, msg }).await.is_err() {
                            break "scheduler shutting down".into();
                        }
                    }
                    Ok(None) => break "closed the connection".into(),
                    Err(e) => break e.to_string(),
                }
            };
            writer.abort();
            let _ = ev.send(Event::Left { id, reason }).await;
            Ok(())
        }
        Some(Opening::Submit(req)) => {
            let (tx, mut rx) = mpsc::channel::<SchedulerToClient>(64);
            ev.send(Event::Submit { req, client: tx }).await?;
            loop {
                let m = tokio::select! {
                    _ = shutdown.cancelled() => return Ok(()),
                    m = rx.recv() => m,
                };
                let Some(m) = m else { return Ok(()) };
                let last = matches!(
                    m,
                    SchedulerToClient::Done(_) | SchedulerToClient::Failed { .. }
                );
                conn.write_msg(&m).await?;
                if last {
                    return Ok(());
                }
            }
        }
    }
}

struct WorkerEntry {
    reg: Registration,
    addr: SocketAddr,
    tx: mpsc::Sender<SchedulerToWorker>,
    busy: bool,
}

struct Queued {
    req: Box<JobRequest>,
    client: mpsc::Sender<SchedulerToClient>,
}

#[derive(PartialEq)]
enum Phase {
    Preparing,
    Distributing,
    Rendering,
    Collecting,
}

struct Running {
    id: u64,
    req: Box<JobRequest>,
    client: mpsc::Sender<SchedulerToClient>,
    /// Registry ids; the position is the job's worker id.
    members: Vec<u32>,
    phase: Phase,
    prep: Option<Box<job::Prepared>>,
    tiles: Vec<TileAssignment>,
    next_tile: usize,
    done: u32,
    told_no_more: Vec<bool>,
    film: Vec<[f32; 3]>,
    ready: usize,
    reports: Vec<Option<WorkerStats>>,
    started: Instant,
    t_prepared: Instant,
    t_ready: Instant,
    t_rendered: Instant,
}

struct Actor {
    workers: BTreeMap<u32, WorkerEntry>,
    queue: VecDeque<Queued>,
    job: Option<Running>,
    next_job: u64,
    max_queue: usize,
    events: mpsc::Sender<Event>,
}

impl Actor {
    async fn run(mut self, mut rx: mpsc::Receiver<Event>, shutdown: CancellationToken) {
        loop {
            let ev = tokio::select! {
                _ = shutdown.cancelled() => break,
                e = rx.recv() => match e { Some(e) => e, None => break },
            };
            match ev {
                Event::Joined { id, reg, addr, tx } => {
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
                        if self.job.as_ref().is_some_and(|j| j.members.contains(&id)) {
                            self.fail(format!(
                                "worker {id} ({}) left during the job: {reason}",
                                w.reg.listen
                            ));
                        }
                    }
                }
                Event::Submit { req, client } => {
                    if self.queue.len() >= self.max_queue {
                        let _ = client.try_send(SchedulerToClient::Failed {
                            job: 0,
                            reason: format!(
                                "the scheduler's queue is full ({} jobs waiting)",
                                self.queue.len()
                            ),
                        });
                    } else if let Err(reason) = job::validate(&req) {
                        let _ = client.try_send(SchedulerToClient::Failed {
                            job: 0,
                            reason: format!("invalid job {}: {reason}", req.name),
                        });
                    } else {
                        self.queue.push_back(Queued { req, client });
                        self.try_start();
                    }
                }
                Event::Prepared { job, prep } => self.on_prepared(job, prep),
                Event::FromWorker { id, msg } => self.on_worker(id, msg),
            }
        }
        if self.job.is_some() {
            self.fail("the scheduler is shutting down".into());
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
        for m in &members {
            self.workers.get_mut(m).expect("idle").busy = true;
        }
        let id = self.next_job;
        self.next_job += 1;
        info!(job = id, scene = %q.req.name, workers = want, "job starting");
        let _ = q.client.try_send(SchedulerToClient::Accepted {
            job: id,
            workers: want as u32,
        });
        let cam = &q.req.camera;
        let ts = q.req.options.tile_size;
        let tiles = locus_core::render::tiles(
            cam.width,
            cam.height,
            ts,
            locus_core::render::TileOrder::Scanline,
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
        let now = Instant::now();
        self.job = Some(Running {
            id,
            film: vec![[0.0; 3]; (cam.width * cam.height) as usize],
            req: q.req.clone(),
            client: q.client,
            reports: vec![None; want],
            told_no_more: vec![false; want],
            members,
            phase: Phase::Preparing,
            prep: None,
            tiles,
            next_tile: 0,
            done: 0,
            ready: 0,
            started: now,
            t_prepared: now,
            t_ready: now,
            t_rendered: now,
        });
        let events = self.events.clone();
        tokio::spawn(async move {
            let prep = tokio::task::spawn_blocking(move || job::prepare(&q.req, want)).await;
            match prep {
                Ok(p) => {
                    let _ = events
                        .send(Event::Prepared {
                            job: id,
                            prep: Box::new(p),
                        })
                        .await;
                }
                Err(e) => warn!(job = id, "preparation crashed: {e}"),
            }
        });
    }

    fn on_prepared(&mut self, id: u64, mut prep: Box<job::Prepared>) {
        let Some(j) = self.job.as_mut().filter(|j| j.id == id) else {
            return;
        };
        j.t_prepared = Instant::now();
        j.phase = Phase::Distributing;
        info!(
            job = id,
            leaves = prep.leaves,
            seconds = prep.seconds,
            "partitioned"
        );
        let peers: Vec<String> = j
            .members
            .iter()
            .map(|m| self.workers[m].reg.listen.clone())
            .collect();
        let mut own_leaves = std::mem::take(&mut prep.own_leaves);
        for (w, m) in j.members.iter().enumerate() {
            let setup = JobSetup {
                job: id,
                me: w as u16,
                peers: peers.clone(),
                camera: prep.scene.camera.clone(),
                spp: prep.scene.settings.spp,
                max_depth: prep.scene.settings.max_depth,
                seed: prep.scene.settings.seed,
                materials: prep.scene.materials.clone(),
                lights: prep.lights.clone(),
                map: prep.map.clone(),
                magnitude: prep.scene.magnitude(),
                tuning: j.req.options.tuning,
                cache: j.req.options.cache,
                fetch: j.req.options.fetch,
                fetch_budget: j.req.options.fetch_budget,
                own_leaves: std::mem::take(&mut own_leaves[w]),
                leaf_tris: prep.leaf_tris.clone(),
            };
            let region = prep.regions[w].clone();
            let tx = self.workers[m].tx.clone();
            // A task per worker, so a slow link does not hold the actor.
            tokio::spawn(async move {
                tx.send(SchedulerToWorker::StartJob(Box::new(setup)))
                    .await?;
                let n = region.len();
                let mut start = 0;
                loop {
                    let end = (start + GEOMETRY_CHUNK).min(n);
                    let chunk = locus_protocol::control::RegionGeometry {
                        ids: region.ids[start..end].to_vec(),
                        verts: region.verts[start..end].to_vec(),
                        material: region.material[start..end].to_vec(),
                    };
                    tx.send(SchedulerToWorker::Geometry {
                        job: id,
                        chunk,
                        last: end == n,
                    })
                    .await?;
                    if end == n {
                        break;
                    }
                    start = end;
                }
                Ok::<_, mpsc::error::SendError<SchedulerToWorker>>(())
            });
        }
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
        let job_of = |m: &WorkerToScheduler| match m {
            WorkerToScheduler::Ready { job }
            | WorkerToScheduler::NeedTiles { job, .. }
            | WorkerToScheduler::Report { job, .. }
            | WorkerToScheduler::Failed { job, .. } => *job,
            WorkerToScheduler::TileDone(t) => t.job,
        };
        if job_of(&msg) != j.id {
            warn!(worker = id, "message for another job ignored");
            return;
        }
        match msg {
            WorkerToScheduler::Ready { .. } => {
                j.ready += 1;
                if j.ready == j.members.len() {
                    j.phase = Phase::Rendering;
                    j.t_ready = Instant::now();
                    info!(job = j.id, "all workers ready; rendering");
                }
            }
            WorkerToScheduler::NeedTiles { count, .. } => {
                let tx = &self.workers[&id].tx;
                for _ in 0..count {
                    if j.next_tile < j.tiles.len() {
                        let t = j.tiles[j.next_tile];
                        j.next_tile += 1;
                        if tx.try_send(SchedulerToWorker::Tile(t)).is_err() {
                            // The worker asked for it, so its queue has room
                            // unless the worker is gone.
                            j.next_tile -= 1;
                            break;
                        }
                    } else if !j.told_no_more[w] {
                        j.told_no_more[w] = true;
                        let _ = tx.try_send(SchedulerToWorker::NoMoreTiles { job: j.id });
                    }
                }
            }
            WorkerToScheduler::TileDone(r) => {
                let Some(t) = j.tiles.get(r.tile as usize).copied() else {
                    warn!(
                        worker = id,
                        tile = r.tile,
                        "result for an unknown tile ignored"
                    );
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
                let width = j.req.camera.width;
                let mut k = 0;
                for y in t.y0..t.y1 {
                    for x in t.x0..t.x1 {
                        j.film[(y * width + x) as usize] = r.pixels[k];
                        k += 1;
                    }
                }
                j.done += 1;
                let _ = j.client.try_send(SchedulerToClient::Progress {
                    job: j.id,
                    tiles_done: j.done,
                    tiles: j.tiles.len() as u32,
                });
                if j.done as usize == j.tiles.len() {
                    j.phase = Phase::Collecting;
                    j.t_rendered = Instant::now();
                    for m in &j.members {
                        let _ = self.workers[m]
                            .tx
                            .try_send(SchedulerToWorker::EndJob { job: j.id });
                    }
                }
            }
            WorkerToScheduler::Report { stats, .. } => {
                if j.phase != Phase::Collecting {
                    warn!(worker = id, "report before the end of the job ignored");
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

    fn release(&mut self) -> Option<Running> {
        let j = self.job.take()?;
        for m in &j.members {
            if let Some(w) = self.workers.get_mut(m) {
                w.busy = false;
            }
        }
        Some(j)
    }

    fn fail(&mut self, reason: String) {
        let Some(j) = self.release() else { return };
        warn!(job = j.id, %reason, "job failed");
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
        let Some(j) = self.release() else { return };
        let report = build_report(&j, &self.workers);
        info!(
            job = j.id,
            render_s = report.phases.render_s,
            imbalance = report.load_imbalance,
            forwarded = report.forwarded_fraction,
            "job done"
        );
        let result = JobResult {
            job: j.id,
            width: j.req.camera.width,
            height: j.req.camera.height,
            pixels: j.film,
            report,
        };
        let client = j.client;
        // The result can be large; a dedicated task waits for room.
        tokio::spawn(async move {
            let _ = client.send(SchedulerToClient::Done(Box::new(result))).await;
        });
        self.try_start();
    }
}

fn build_report(j: &Running, workers: &BTreeMap<u32, WorkerEntry>) -> FarmReport {
    let prep = j.prep.as_ref().expect("prepared before reporting");
    let stats: Vec<WorkerStats> = j
        .reports
        .iter()
        .map(|r| r.clone().unwrap_or_default())
        .collect();
    let work: Vec<f64> = stats
        .iter()
        .map(|s| (s.trace.bvh_nodes + s.trace.tri_tests) as f64)
        .collect();
    let total_work: f64 = work.iter().sum();
    let measured: Vec<f64> = work
        .iter()
        .map(|w| {
            if total_work > 0.0 {
                w / total_work
            } else {
                0.0
            }
        })
        .collect();
    let mut totals = WorkerStats::default();
    let mut bytes = 0u64;
    for s in &stats {
        totals += s;
        bytes += s.peers.iter().map(|p| p.bytes_sent).sum::<u64>();
    }
    let busy: Vec<f64> = stats.iter().map(|s| s.busy_s).collect();
    let mean_busy = busy.iter().sum::<f64>() / busy.len().max(1) as f64;
    let max_busy = busy.iter().cloned().fold(0.0, f64::max);
    let render_s = (j.t_rendered - j.t_ready).as_secs_f64();
    let samples = totals.trace.samples;
    FarmReport {
        scene: j.req.name.clone(),
        width: j.req.camera.width,
        height: j.req.camera.height,
        spp: j.req.settings.spp,
        max_depth: j.req.settings.max_depth,
        seed: j.req.settings.seed,
        partitioner: format!("{:?}", j.req.options.partitioner),
        cost_model: format!("{:?}", j.req.options.cost_model),
        leaves: prep.leaves,
        triangles: prep.scene.tris.len() as u64,
        phases: Phases {
            partition_s: (j.t_prepared - j.started).as_secs_f64(),
            distribution_s: (j.t_ready - j.t_prepared).as_secs_f64(),
            render_s,
            total_s: j.started.elapsed().as_secs_f64(),
        },
        prediction: Prediction {
            analytic_r: cost::correlation(&prep.analytic_share, &measured),
            sampled_r: cost::correlation(&prep.sampled_share, &measured),
            preview_rays: prep.preview_rays,
        },
        workers: stats
            .iter()
            .enumerate()
            .map(|(w, s)| WorkerSummary {
                id: w as u16,
                addr: workers
                    .get(&j.members[w])
                    .map(|e| e.reg.listen.clone())
                    .unwrap_or_default(),
                predicted_cost_share: match j.req.options.cost_model {
                    locus_protocol::submit::CostModel::Analytic => prep.analytic_share[w],
                    locus_protocol::submit::CostModel::Sampled => prep.sampled_share[w],
                },
                measured_cost_share: measured[w],
                stats: s.clone(),
            })
            .collect(),
        load_imbalance: if mean_busy > 0.0 {
            max_busy / mean_busy
        } else {
            1.0
        },
        forwarded_fraction: totals.forwarded_out as f64 / totals.trace.rays().max(1) as f64,
        bytes_per_sample: bytes as f64 / samples.max(1) as f64,
        samples_per_s: samples as f64 / render_s.max(1e-9),
        totals,
    }
}
