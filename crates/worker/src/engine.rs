//! The compute side of a worker in one job: a loop on its own thread that
//! owns every pending query and traces batches of work on the rayon pool.
//!
//! Work arrives as ray items from peers, tiles from the scheduler and answers
//! to this worker's own queries. A trace item is traced through the run of
//! owned leaves where it resumes ([`locus_core::region::ProcessorMap::trace_run`]): a hit is
//! shaded here and spawns a shadow query and a continuation query whose
//! answers come back to a pending slot; a miss is answered; a ray that
//! leaves the region is forwarded to the next owner. When both answers of a
//! vertex are in, its radiance goes back to whoever asked. Camera samples
//! are the roots: a tile is done when every one of its samples is answered.
//!
//! Queues are bounded by construction: a worker keeps at most
//! `max_inflight` camera samples open, each sample has at most
//! `max_depth + 1` vertices pending and two queries in flight per vertex, so
//! the ray items in the whole farm are bounded. Sends to peers never block
//! this loop (a blocked loop could deadlock two workers sending to each
//! other); a packet that does not fit its peer's channel waits here, and
//! while any does, no new camera sample starts: that is the backpressure.

use glam::{DVec3, Vec3};
use locus_core::accel::Accel;
use locus_core::accel::Hit;
use locus_core::geometry::Ray;
use locus_core::integrator::{DIM_PIXEL, DirectLighting, PathRay, shade};
use locus_core::region::{RunResult, WorkerId};
use locus_core::sampler::SampleKey;
use locus_core::stats::TraceStats;
use locus_protocol::control::{
    JobSetup, RegionGeometry, TileAssignment, TileResult, WorkerToScheduler,
};
use locus_protocol::rays::{Answer, Query, RayItem, ReplyTo};
use locus_protocol::report::WorkerStats;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// Everything a worker holds for one job: what the scheduler sent, and the
/// BVH built over this worker's region.
pub struct EngineJob {
    pub setup: JobSetup,
    pub workers: usize,
    pub accel: Accel,
    pub geometry: RegionGeometry,
}

pub enum Input {
    Packet { from: WorkerId, items: Vec<RayItem> },
    Tile(TileAssignment),
    NoMoreTiles,
    End,
}

/// Where the engine's output goes.
pub struct Links {
    /// One bounded channel per peer (None for this worker itself).
    pub peers: Vec<Option<flume::Sender<Vec<RayItem>>>>,
    pub control: flume::Sender<WorkerToScheduler>,
}

#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    #[error("worker {from} sent an answer for slot {slot}, which is not pending here")]
    UnknownSlot { from: WorkerId, slot: u32 },
    #[error("worker {from} sent a query that resumes in a leaf this worker does not own")]
    Misrouted { from: WorkerId },
    #[error("hit on triangle {0}, which is not in this region's geometry")]
    ForeignTriangle(u32),
    #[error("the link to {0} closed while the job was running")]
    LinkClosed(&'static str),
    #[error("the scheduler ended the job with {0} queries still pending")]
    EndedEarly(usize),
}

/// What a work item traces: a query from a peer or from this worker, or a
/// camera sample whose ray is generated on the pool, not in the serial loop.
enum Task {
    Query(Query),
    Camera { x: u32, y: u32, sample: u32 },
}

struct Work {
    task: Task,
    resume: f32,
    reply: ReplyTo,
    /// Worker it came from (itself for local work), for error messages.
    from: WorkerId,
}

enum Outcome {
    /// The query continues on another worker, resuming at the distance.
    Forward(WorkerId, Query, f32, ReplyTo),
    Answer(ReplyTo, Answer),
    /// Vertices shaded here that still wait for forwarded queries; vertex k
    /// is the continuation of vertex k - 1 (see [`eval_hit`]).
    Chain(ReplyTo, Vec<ChainVertex>),
    Error(EngineError),
}

/// A child query of a vertex shaded in this batch.
enum Child<T> {
    Done(T),
    /// Must continue on another worker, resuming at `f32`.
    Forward(WorkerId, Query, f32),
    /// The next vertex of the chain.
    Deeper,
}

struct ChainVertex {
    vertex: locus_core::integrator::ShadedVertex,
    shadow: Child<bool>,
    next: Child<Vec3>,
}

enum Wait<T> {
    Pending,
    Done(T),
}

enum Slot {
    Free,
    Sample {
        tile: u32,
        index: u32,
    },
    Vertex {
        reply: ReplyTo,
        vertex: locus_core::integrator::ShadedVertex,
        shadow: Wait<bool>,
        next: Wait<Vec3>,
    },
}

struct TileState {
    a: TileAssignment,
    values: Vec<Vec3>,
    remaining: u32,
    next: u32,
}

struct Engine<'a> {
    job: &'a EngineJob,
    links: Links,
    slots: Vec<Slot>,
    free: Vec<u32>,
    tiles: Vec<Option<TileState>>,
    inflight: usize,
    no_more_tiles: bool,
    out: Vec<Vec<RayItem>>,
    out_since: Vec<Option<Instant>>,
    stalled: Vec<VecDeque<Vec<RayItem>>>,
    stats: WorkerStats,
}

/// Largest batch one pool task traces.
const BATCH: usize = 8192;
/// Smallest batch worth a pool task.
const MIN_BATCH: usize = 16;

type Traced = (Vec<Outcome>, TraceStats);

enum Event {
    Input(Input),
    Traced(Traced),
    InboxClosed,
}

/// Runs the job until the scheduler ends it; returns this worker's counters
/// (traffic bytes are added by the caller, which owns the sockets).
///
/// Batches are traced as pool tasks while this thread applies the results
/// of earlier ones: with `threads + 1` batches out, the pool never waits
/// for the bookkeeping (answers, slots, packets, tiles), which is serial.
pub fn run(
    job: &EngineJob,
    pool: &rayon::ThreadPool,
    inbox: flume::Receiver<Input>,
    links: Links,
) -> Result<WorkerStats, EngineError> {
    let n = job.workers;
    let max_out = pool.current_num_threads() + 1;
    let (done_tx, done_rx) = flume::bounded::<Traced>(max_out);
    let mut e = Engine {
        job,
        links,
        slots: Vec::new(),
        free: Vec::new(),
        tiles: Vec::new(),
        inflight: 0,
        no_more_tiles: false,
        out: (0..n).map(|_| Vec::new()).collect(),
        out_since: vec![None; n],
        stalled: (0..n).map(|_| VecDeque::new()).collect(),
        stats: WorkerStats {
            peers: vec![Default::default(); n],
            triangles: job.geometry.len() as u64,
            leaves: job
                .setup
                .map
                .owner
                .iter()
                .filter(|&&o| o == job.setup.me)
                .count() as u32,
            ..Default::default()
        },
    };
    let start = Instant::now();
    e.control(WorkerToScheduler::NeedTiles {
        job: job.setup.job,
        count: job.setup.tuning.tiles_ahead.max(1),
    })?;
    // Leaving this scope (also by an error) waits for the batches still
    // out; each finds room in `done_tx`, so none blocks.
    pool.in_place_scope(|scope| {
        let mut work: VecDeque<Work> = VecDeque::new();
        let mut idle = Duration::ZERO;
        let mut out = 0usize;
        loop {
            e.retry_stalled()?;
            if e.stalled.iter().all(VecDeque::is_empty) {
                e.originate(&mut work);
            }
            while out < max_out && !work.is_empty() {
                let share = work.len().div_ceil(max_out - out);
                let take = share.clamp(MIN_BATCH, BATCH).min(work.len());
                let batch: Vec<Work> = work.drain(..take).collect();
                let tx = done_tx.clone();
                scope.spawn(move |_| {
                    let mut st = TraceStats::default();
                    let mut scratch = Vec::new();
                    let outs = batch
                        .into_iter()
                        .map(|w| process(job, w, &mut st, &mut scratch))
                        .collect();
                    // The engine holds the receiver until the scope ends.
                    let _ = tx.send((outs, st));
                });
                out += 1;
            }
            if out == 0 {
                // Nothing is being traced: what waits in packets must go.
                e.flush_all()?;
            }
            let wait = if e.stalled.iter().any(|s| !s.is_empty()) {
                Duration::from_millis(1)
            } else if out > 0 {
                Duration::from_micros(job.setup.tuning.flush_us.max(1) as u64)
            } else {
                Duration::from_millis(100)
            };
            let t = Instant::now();
            let first = flume::Selector::new()
                .recv(&inbox, |r| r.map_or(Event::InboxClosed, Event::Input))
                .recv(&done_rx, |r| r.map_or(Event::InboxClosed, Event::Traced))
                .wait_timeout(wait)
                .ok();
            if out == 0 {
                idle += t.elapsed();
            }
            let mut events: Vec<Event> = first.into_iter().collect();
            while events.len() < 256 {
                match done_rx.try_recv() {
                    Ok(x) => events.push(Event::Traced(x)),
                    Err(_) => break,
                }
            }
            while events.len() < 512 {
                match inbox.try_recv() {
                    Ok(x) => events.push(Event::Input(x)),
                    Err(_) => break,
                }
            }
            for ev in events {
                match ev {
                    Event::InboxClosed => {
                        return Err(EngineError::LinkClosed("the worker's inbox"));
                    }
                    Event::Traced((outs, st)) => {
                        out -= 1;
                        e.stats.trace += st;
                        for o in outs {
                            e.apply(o)?;
                        }
                    }
                    Event::Input(Input::Packet { from, items }) => {
                        for it in items {
                            match it {
                                RayItem::Trace {
                                    query,
                                    resume,
                                    reply,
                                } => {
                                    e.stats.queries_in += 1;
                                    work.push_back(Work {
                                        task: Task::Query(query),
                                        resume,
                                        reply,
                                        from,
                                    });
                                }
                                RayItem::Answer { to, answer } => e.answer(from, to, answer)?,
                            }
                        }
                    }
                    Event::Input(Input::Tile(a)) => e.add_tile(a),
                    Event::Input(Input::NoMoreTiles) => e.no_more_tiles = true,
                    Event::Input(Input::End) => {
                        let pending = e.slots.len() - e.free.len();
                        if pending > 0 || !work.is_empty() || out > 0 {
                            return Err(EngineError::EndedEarly(pending + work.len()));
                        }
                        let total = start.elapsed();
                        e.stats.idle_s = idle.as_secs_f64();
                        e.stats.busy_s = (total - idle.min(total)).as_secs_f64();
                        return Ok(std::mem::take(&mut e.stats));
                    }
                }
            }
            e.flush_due()?;
        }
    })
}

/// One run trace. With a single owner the routing tree is one leaf, so the
/// walk costs a root clip and nothing more.
#[inline]
fn trace(
    job: &EngineJob,
    ray: &Ray,
    t_max: f32,
    resume: f32,
    any: bool,
    st: &mut TraceStats,
) -> RunResult {
    job.setup
        .map
        .trace_run(job.setup.me, &job.accel, ray, t_max, resume, any, st)
}

/// Traces one work item through this worker's run of leaves, and keeps
/// going depth-first through everything that stays local: a path whose
/// vertices are all here is finished in this call, like the single-machine
/// integrator; only queries that leave the region become messages.
fn process(job: &EngineJob, w: Work, st: &mut TraceStats, chain: &mut Vec<ChainVertex>) -> Outcome {
    let query = match w.task {
        Task::Query(q) => q,
        Task::Camera { x, y, sample } => {
            let key = SampleKey::new(
                y as u64 * job.setup.camera.width as u64 + x as u64,
                sample,
                job.setup.seed,
            );
            st.camera_rays += 1;
            let ray = job.setup.camera.ray(x, y, key.get2d(DIM_PIXEL));
            Query::Path(PathRay::camera(ray, key))
        }
    };
    let forward = |query: Query, to: WorkerId, t: f32| {
        if t == w.resume && w.from != job.setup.me {
            // The sender computed the same processor vector; a query that
            // does not start in our leaf was corrupted or misrouted.
            return Outcome::Error(EngineError::Misrouted { from: w.from });
        }
        Outcome::Forward(to, query, t, w.reply)
    };
    match query {
        Query::Shadow(s) => match trace(job, &s.ray, s.t_max, w.resume, true, st) {
            RunResult::Forward { to, t } => forward(Query::Shadow(s), to, t),
            RunResult::Miss => Outcome::Answer(w.reply, Answer::Visible(true)),
            RunResult::Occluded | RunResult::Hit(_) => {
                Outcome::Answer(w.reply, Answer::Visible(false))
            }
        },
        Query::Path(q) => match trace(job, &q.ray, f32::INFINITY, w.resume, false, st) {
            RunResult::Forward { to, t } => forward(Query::Path(q), to, t),
            RunResult::Miss | RunResult::Occluded => {
                Outcome::Answer(w.reply, Answer::Radiance(Vec3::ZERO))
            }
            RunResult::Hit(h) => {
                chain.clear();
                match eval_hit(job, &q, &h, st, chain) {
                    Err(e) => Outcome::Error(e),
                    Ok(Some(l)) => Outcome::Answer(w.reply, Answer::Radiance(l)),
                    Ok(None) => Outcome::Chain(w.reply, std::mem::take(chain)),
                }
            }
        },
    }
}

/// Shades hit `h` of `q` and evaluates its shadow and continuation queries
/// as far as they stay here. Returns the vertex's radiance when everything
/// was local; otherwise leaves this vertex (and the pending ones below it)
/// at the end of `chain` and returns None.
fn eval_hit(
    job: &EngineJob,
    q: &PathRay,
    h: &Hit,
    st: &mut TraceStats,
    chain: &mut Vec<ChainVertex>,
) -> Result<Option<Vec3>, EngineError> {
    let Ok(k) = job.geometry.ids.binary_search(&h.tri) else {
        return Err(EngineError::ForeignTriangle(h.tri));
    };
    let mat = &job.setup.materials[job.geometry.material[k] as usize];
    let s = shade(
        q,
        h,
        &job.geometry.verts[k],
        mat,
        &job.setup.lights,
        job.setup.max_depth,
        DirectLighting::Mis,
    );
    let shadow = match s.shadow {
        None => Child::Done(false),
        Some(sr) => {
            st.shadow_rays += 1;
            match trace(job, &sr.ray, sr.t_max, f32::NEG_INFINITY, true, st) {
                RunResult::Miss => Child::Done(true),
                RunResult::Occluded | RunResult::Hit(_) => Child::Done(false),
                RunResult::Forward { to, t } => Child::Forward(to, Query::Shadow(sr), t),
            }
        }
    };
    let idx = chain.len();
    chain.push(ChainVertex {
        vertex: s.vertex,
        shadow,
        next: Child::Done(Vec3::ZERO),
    });
    let next = match s.next {
        None => Child::Done(Vec3::ZERO),
        Some(nq) => {
            st.indirect_rays += 1;
            match trace(job, &nq.ray, f32::INFINITY, f32::NEG_INFINITY, false, st) {
                RunResult::Miss | RunResult::Occluded => Child::Done(Vec3::ZERO),
                RunResult::Forward { to, t } => Child::Forward(to, Query::Path(nq), t),
                RunResult::Hit(h2) => match eval_hit(job, &nq, &h2, st, chain)? {
                    Some(l) => Child::Done(l),
                    None => Child::Deeper,
                },
            }
        }
    };
    if let (Child::Done(visible), Child::Done(l)) = (&chain[idx].shadow, &next) {
        let v = chain[idx].vertex.finish(*visible, *l);
        chain.truncate(idx);
        return Ok(Some(v));
    }
    chain[idx].next = next;
    Ok(None)
}

fn child_query<T>(c: Child<T>) -> Option<(WorkerId, Query, f32)> {
    match c {
        Child::Forward(to, q, t) => Some((to, q, t)),
        _ => None,
    }
}

impl Engine<'_> {
    fn control(&self, m: WorkerToScheduler) -> Result<(), EngineError> {
        self.links
            .control
            .send(m)
            .map_err(|_| EngineError::LinkClosed("the scheduler"))
    }

    fn alloc(&mut self, s: Slot) -> u32 {
        match self.free.pop() {
            Some(i) => {
                self.slots[i as usize] = s;
                i
            }
            None => {
                self.slots.push(s);
                (self.slots.len() - 1) as u32
            }
        }
    }

    fn add_tile(&mut self, a: TileAssignment) {
        let n = a.pixels() * self.job.setup.spp;
        let st = TileState {
            a,
            values: vec![Vec3::ZERO; n as usize],
            remaining: n,
            next: 0,
        };
        match self.tiles.iter().position(Option::is_none) {
            Some(i) => self.tiles[i] = Some(st),
            None => self.tiles.push(Some(st)),
        }
    }

    /// Starts camera samples until `max_inflight` are open.
    fn originate(&mut self, work: &mut VecDeque<Work>) {
        let cap = self.job.setup.tuning.max_inflight.max(1) as usize;
        let job = self.job;
        let me = job.setup.me;
        for ti in 0..self.tiles.len() {
            loop {
                if self.inflight >= cap {
                    return;
                }
                let Some(t) = self.tiles[ti].as_mut() else {
                    break;
                };
                if t.next as usize >= t.values.len() {
                    break;
                }
                let index = t.next;
                t.next += 1;
                let a = t.a;
                let p = index / job.setup.spp;
                let w = a.x1 - a.x0;
                let slot = self.alloc(Slot::Sample {
                    tile: ti as u32,
                    index,
                });
                self.inflight += 1;
                work.push_back(Work {
                    task: Task::Camera {
                        x: a.x0 + p % w,
                        y: a.y0 + p / w,
                        sample: index % job.setup.spp,
                    },
                    resume: f32::NEG_INFINITY,
                    reply: ReplyTo { worker: me, slot },
                    from: me,
                });
            }
        }
    }

    fn apply(&mut self, o: Outcome) -> Result<(), EngineError> {
        let me = self.job.setup.me;
        match o {
            Outcome::Error(e) => return Err(e),
            Outcome::Forward(to, query, resume, reply) => {
                self.stats.forwarded_out += 1;
                self.push_out(
                    to,
                    RayItem::Trace {
                        query,
                        resume,
                        reply,
                    },
                )?;
            }
            Outcome::Answer(reply, a) => self.deliver(reply, a)?,
            Outcome::Chain(reply, chain) => {
                let mut parent = reply;
                for cv in chain {
                    let slot = self.alloc(Slot::Vertex {
                        reply: parent,
                        vertex: cv.vertex,
                        shadow: match cv.shadow {
                            Child::Done(b) => Wait::Done(b),
                            _ => Wait::Pending,
                        },
                        next: match cv.next {
                            Child::Done(l) => Wait::Done(l),
                            _ => Wait::Pending,
                        },
                    });
                    let mine = ReplyTo { worker: me, slot };
                    for c in [child_query(cv.shadow), child_query(cv.next)]
                        .into_iter()
                        .flatten()
                    {
                        let (to, query, resume) = c;
                        self.stats.forwarded_out += 1;
                        self.push_out(
                            to,
                            RayItem::Trace {
                                query,
                                resume,
                                reply: mine,
                            },
                        )?;
                    }
                    parent = mine;
                }
            }
        }
        Ok(())
    }

    fn deliver(&mut self, reply: ReplyTo, a: Answer) -> Result<(), EngineError> {
        if reply.worker == self.job.setup.me {
            self.answer(reply.worker, reply.slot, a)
        } else {
            self.stats.answers_out += 1;
            self.push_out(
                reply.worker,
                RayItem::Answer {
                    to: reply.slot,
                    answer: a,
                },
            )
        }
    }

    /// Applies an answer to a pending slot; completed vertices answer their
    /// own asker in turn (iteratively: a chain can be max_depth long).
    fn answer(&mut self, from: WorkerId, slot: u32, a: Answer) -> Result<(), EngineError> {
        // A completed vertex answers exactly one asker, so the cascade is a
        // chain: no stack needed.
        let mut todo = Some((from, slot, a));
        while let Some((from, slot, a)) = todo.take() {
            let bad = EngineError::UnknownSlot { from, slot };
            let Some(s) = self.slots.get_mut(slot as usize) else {
                return Err(bad);
            };
            match s {
                Slot::Free => return Err(bad),
                Slot::Sample { tile, index } => {
                    let Answer::Radiance(l) = a else {
                        return Err(bad);
                    };
                    let (tile, index) = (*tile, *index);
                    *s = Slot::Free;
                    self.free.push(slot);
                    self.inflight -= 1;
                    let Some(t) = self.tiles[tile as usize].as_mut() else {
                        return Err(bad);
                    };
                    t.values[index as usize] = l;
                    t.remaining -= 1;
                    if t.remaining == 0 {
                        self.finish_tile(tile)?;
                    }
                }
                Slot::Vertex {
                    reply,
                    vertex,
                    shadow,
                    next,
                } => {
                    match (a, &*shadow, &*next) {
                        (Answer::Visible(v), Wait::Pending, _) => *shadow = Wait::Done(v),
                        (Answer::Radiance(l), _, Wait::Pending) => *next = Wait::Done(l),
                        _ => return Err(bad),
                    }
                    let (Wait::Done(visible), Wait::Done(nl)) = (&*shadow, &*next) else {
                        continue;
                    };
                    let (visible, nl) = (*visible, *nl);
                    let l = vertex.finish(visible, nl);
                    let reply = *reply;
                    *s = Slot::Free;
                    self.free.push(slot);
                    if reply.worker == self.job.setup.me {
                        todo = Some((reply.worker, reply.slot, Answer::Radiance(l)));
                    } else {
                        self.deliver(reply, Answer::Radiance(l))?;
                    }
                }
            }
        }
        Ok(())
    }

    /// Sums each pixel's samples in index order, exactly as the
    /// single-machine renderer does.
    fn finish_tile(&mut self, tile: u32) -> Result<(), EngineError> {
        let Some(t) = self.tiles[tile as usize].take() else {
            return Ok(());
        };
        let spp = self.job.setup.spp as usize;
        let pixels = t
            .values
            .chunks(spp)
            .map(|samples| {
                let mut sum = DVec3::ZERO;
                for l in samples {
                    self.stats.trace.samples += 1;
                    if l.is_finite() {
                        sum += l.as_dvec3();
                    } else {
                        self.stats.trace.invalid_samples += 1;
                    }
                }
                let m = sum / spp as f64;
                [m.x as f32, m.y as f32, m.z as f32]
            })
            .collect();
        self.stats.tiles += 1;
        self.control(WorkerToScheduler::TileDone(TileResult {
            job: self.job.setup.job,
            tile: t.a.tile,
            pixels,
        }))?;
        if !self.no_more_tiles {
            self.control(WorkerToScheduler::NeedTiles {
                job: self.job.setup.job,
                count: 1,
            })?;
        }
        Ok(())
    }

    fn push_out(&mut self, peer: WorkerId, item: RayItem) -> Result<(), EngineError> {
        let p = peer as usize;
        if self.out[p].is_empty() {
            self.out_since[p] = Some(Instant::now());
        }
        self.out[p].push(item);
        if self.out[p].len() >= self.job.setup.tuning.packet_size.max(1) as usize {
            self.send(p)?;
        }
        Ok(())
    }

    fn send(&mut self, p: usize) -> Result<(), EngineError> {
        let items = std::mem::take(&mut self.out[p]);
        self.out_since[p] = None;
        if items.is_empty() {
            return Ok(());
        }
        if !self.stalled[p].is_empty() {
            self.stalled[p].push_back(items);
            return Ok(());
        }
        let Some(tx) = &self.links.peers[p] else {
            return Err(EngineError::LinkClosed("a peer"));
        };
        match tx.try_send(items) {
            Ok(()) => Ok(()),
            Err(flume::TrySendError::Full(items)) => {
                self.stats.backpressure_stalls += 1;
                self.stalled[p].push_back(items);
                Ok(())
            }
            Err(flume::TrySendError::Disconnected(_)) => Err(EngineError::LinkClosed("a peer")),
        }
    }

    fn retry_stalled(&mut self) -> Result<(), EngineError> {
        for p in 0..self.stalled.len() {
            while let Some(items) = self.stalled[p].pop_front() {
                let Some(tx) = &self.links.peers[p] else {
                    return Err(EngineError::LinkClosed("a peer"));
                };
                match tx.try_send(items) {
                    Ok(()) => {}
                    Err(flume::TrySendError::Full(items)) => {
                        self.stalled[p].push_front(items);
                        break;
                    }
                    Err(flume::TrySendError::Disconnected(_)) => {
                        return Err(EngineError::LinkClosed("a peer"));
                    }
                }
            }
        }
        Ok(())
    }

    fn flush_due(&mut self) -> Result<(), EngineError> {
        let deadline = Duration::from_micros(self.job.setup.tuning.flush_us as u64);
        for p in 0..self.out.len() {
            if self.out_since[p].is_some_and(|t| t.elapsed() >= deadline) {
                self.send(p)?;
            }
        }
        Ok(())
    }

    fn flush_all(&mut self) -> Result<(), EngineError> {
        for p in 0..self.out.len() {
            self.send(p)?;
        }
        Ok(())
    }
}
