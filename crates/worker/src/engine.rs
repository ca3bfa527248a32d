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
//! With a fetch policy other than `forward`, a ray that reaches a leaf of
//! another worker may instead wait for that leaf's geometry
//! ([`crate::fetch`]): the first such ray sends the request, later ones
//! join its wait list, and all resume on this worker when the leaf
//! arrives. With directional caches on, a continuation ray is traced
//! exactly inside its leaf's locality sphere and answered by the leaf's
//! cache beyond it when the cache can (paper 000, section 2.4); the
//! answer of a ray the cache could not answer updates the cache when it
//! comes back, whichever worker traced it.
//!
//! Queues are bounded by construction: a worker keeps at most
//! `max_inflight` camera samples open, each sample has at most
//! `max_depth + 1` vertices pending and two queries in flight per vertex, so
//! the ray items in the whole farm are bounded. Sends to peers never block
//! this loop (a blocked loop could deadlock two workers sending to each
//! other); a packet that does not fit its peer's channel waits here, and
//! while any does, no new camera sample starts: that is the backpressure.

use crate::fetch::{FetchedLeaf, Locality, RayKind};
use glam::{DVec3, Vec3};
use locus_core::accel::Accel;
use locus_core::accel::Hit;
use locus_core::dircache::{LeafCaches, Lookup};
use locus_core::geometry::Ray;
use locus_core::integrator::{DIM_PIXEL, PathRay, shade};
use locus_core::region::{RunResult, WorkerId};
use locus_core::sampler::SampleKey;
use locus_core::stats::TraceStats;
use locus_protocol::control::{
    JobSetup, RegionGeometry, TileAssignment, TileResult, WorkerToScheduler,
};
use locus_protocol::rays::{Answer, LeafGeometry, PeerMsg, Query, RayItem, ReplyTo};
use locus_protocol::report::WorkerStats;
use locus_protocol::submit::FetchPolicy;
use std::collections::{HashMap, VecDeque};
use std::ops::ControlFlow;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Everything a worker holds for one job: what the scheduler sent, the BVH
/// built over this worker's region, its directional caches and its
/// fetched leaves.
pub struct EngineJob {
    pub setup: JobSetup,
    pub workers: usize,
    pub accel: Accel,
    pub geometry: RegionGeometry,
    /// One directional cache per octree leaf this worker shades in.
    pub caches: Option<LeafCaches>,
    pub locality: Locality,
}

impl EngineJob {
    pub fn new(setup: JobSetup, workers: usize, accel: Accel, geometry: RegionGeometry) -> Self {
        let caches = setup
            .cache
            .map(|p| LeafCaches::new(setup.map.tree.leaves.len(), p));
        let locality = Locality::new(&setup);
        Self {
            setup,
            workers,
            accel,
            geometry,
            caches,
            locality,
        }
    }

    /// Vertices and material of a hit on this worker's own geometry.
    fn own_surface(&self, h: Hit) -> Result<Surface, EngineError> {
        let Ok(k) = self.geometry.ids.binary_search(&h.tri) else {
            return Err(EngineError::ForeignTriangle(h.tri));
        };
        Ok(Surface {
            hit: h,
            verts: self.geometry.verts[k],
            material: self.geometry.material[k],
        })
    }
}

pub enum Input {
    Packet {
        from: WorkerId,
        items: Vec<RayItem>,
    },
    /// A peer asks for the geometry of leaves of ours.
    Fetch {
        from: WorkerId,
        leaves: Vec<u32>,
    },
    /// Geometry we asked for, with its frame's bytes on the wire.
    Leaf {
        from: WorkerId,
        bytes: u64,
        leaf: Box<LeafGeometry>,
    },
    Tile(TileAssignment),
    NoMoreTiles,
    End,
}

/// Where the engine's output goes.
pub struct Links {
    /// One bounded channel per peer (None for this worker itself).
    pub peers: Vec<Option<flume::Sender<PeerMsg>>>,
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
    #[error("worker {from} asked for leaf {leaf}, which this worker does not own")]
    NotMyLeaf { from: WorkerId, leaf: u32 },
    #[error("worker {from} sent geometry for leaf {leaf}: {why}")]
    BadLeaf {
        from: WorkerId,
        leaf: u32,
        why: &'static str,
    },
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
    /// The fetched leaf this work waited for, held so that eviction cannot
    /// make it wait again.
    pinned: Option<Arc<FetchedLeaf>>,
}

/// Where a query that cannot go on here goes next.
#[derive(Clone, Copy)]
enum Dest {
    /// To the owner of the next leaf.
    Peer(WorkerId),
    /// Back to this worker once the leaf's geometry has arrived.
    Leaf(u32),
}

/// A hit with the triangle it is on, from this worker's region or from a
/// fetched leaf.
struct Surface {
    hit: Hit,
    verts: [Vec3; 3],
    material: u32,
}

/// Where a traced segment leaves the ray.
enum Traced {
    Hit(Surface),
    Occluded,
    Miss,
    /// Resume at `t`, on another worker or after a fetch.
    Next(Dest, f32),
}

/// Counters a pool batch fills.
#[derive(Default)]
struct Counts {
    trace: TraceStats,
    fetched_leaf_traces: u64,
}

/// A directional cache entry to update when a continuation's radiance
/// comes back: the leaf and the ray's direction.
type CacheKey = (u32, Vec3);

enum Outcome {
    /// The query continues elsewhere, resuming at the distance.
    Forward(Dest, Query, f32, ReplyTo),
    Answer(ReplyTo, Answer),
    /// Vertices shaded here that still wait for forwarded queries; vertex k
    /// is the continuation of vertex k - 1 (see [`eval_hit`]).
    Chain(ReplyTo, Vec<ChainVertex>),
    Error(EngineError),
}

/// A child query of a vertex shaded in this batch.
enum Child<T> {
    Done(T),
    /// Must continue elsewhere, resuming at `f32`.
    Forward(Dest, Query, f32),
    /// The next vertex of the chain.
    Deeper,
}

struct ChainVertex {
    vertex: locus_core::integrator::ShadedVertex,
    shadow: Child<bool>,
    next: Child<Vec3>,
    update: Option<CacheKey>,
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
        update: Option<CacheKey>,
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
    stalled: Vec<VecDeque<PeerMsg>>,
    stats: WorkerStats,
    work: VecDeque<Work>,
    /// Work waiting for a leaf's geometry, by leaf; a leaf with an entry
    /// has its request out.
    waiting: HashMap<u32, Vec<Work>>,
}

/// Largest batch one pool task traces.
const BATCH: usize = 8192;
/// Smallest batch worth a pool task.
const MIN_BATCH: usize = 16;

type Batch = (Vec<Outcome>, Counts);

enum Event {
    Input(Input),
    Traced(Batch),
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
    let (done_tx, done_rx) = flume::bounded::<Batch>(max_out);
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
        work: VecDeque::new(),
        waiting: HashMap::new(),
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
            fetch_cache_bound: job.locality.store.bound(),
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
        let mut idle = Duration::ZERO;
        let mut out = 0usize;
        loop {
            e.retry_stalled()?;
            if e.stalled.iter().all(VecDeque::is_empty) {
                e.originate();
            }
            while out < max_out && !e.work.is_empty() {
                let share = e.work.len().div_ceil(max_out - out);
                let take = share.clamp(MIN_BATCH, BATCH).min(e.work.len());
                let batch: Vec<Work> = e.work.drain(..take).collect();
                let tx = done_tx.clone();
                scope.spawn(move |_| {
                    let mut st = Counts::default();
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
                        e.stats.trace += st.trace;
                        e.stats.fetched_leaf_traces += st.fetched_leaf_traces;
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
                                    e.work.push_back(Work {
                                        task: Task::Query(query),
                                        resume,
                                        reply,
                                        from,
                                        pinned: None,
                                    });
                                }
                                RayItem::Answer { to, answer } => e.answer(from, to, answer)?,
                            }
                        }
                    }
                    Event::Input(Input::Fetch { from, leaves }) => e.serve(from, leaves)?,
                    Event::Input(Input::Leaf { from, bytes, leaf }) => {
                        e.receive_leaf(from, bytes, *leaf)?
                    }
                    Event::Input(Input::Tile(a)) => e.add_tile(a),
                    Event::Input(Input::NoMoreTiles) => e.no_more_tiles = true,
                    Event::Input(Input::End) => {
                        let pending = e.slots.len() - e.free.len();
                        let waiting: usize = e.waiting.values().map(Vec::len).sum();
                        if pending > 0 || !e.work.is_empty() || out > 0 || waiting > 0 {
                            return Err(EngineError::EndedEarly(pending + e.work.len() + waiting));
                        }
                        let total = start.elapsed();
                        e.stats.idle_s = idle.as_secs_f64();
                        if let Some(c) = &job.caches {
                            e.stats.cache_memory = c.memory();
                        }
                        e.stats.fetch_cache_peak = job.locality.store.peak();
                        e.stats.busy_s = (total - idle.min(total)).as_secs_f64();
                        return Ok(std::mem::take(&mut e.stats));
                    }
                }
            }
            e.flush_due()?;
        }
    })
}

/// Traces the ray on `[0, t_max)` from `resume` through everything this
/// worker can trace: its own run of leaves and, under a fetch policy, the
/// fetched leaves that follow. With the `forward` policy this is one walk
/// of the routing tree; otherwise the walk visits every leaf, because a
/// fetched leaf is traced over its own interval only.
#[allow(clippy::too_many_arguments)]
fn trace(
    job: &EngineJob,
    ray: &Ray,
    t_max: f32,
    resume: f32,
    any: bool,
    kind: RayKind,
    pinned: Option<&Arc<FetchedLeaf>>,
    c: &mut Counts,
) -> Result<Traced, EngineError> {
    let map = &job.setup.map;
    let me = job.setup.me;
    if job.locality.policy == FetchPolicy::Forward {
        return Ok(
            match map.trace_run(me, &job.accel, ray, t_max, resume, any, &mut c.trace) {
                RunResult::Hit(h) => Traced::Hit(job.own_surface(h)?),
                RunResult::Occluded => Traced::Occluded,
                RunResult::Miss => Traced::Miss,
                RunResult::Forward { to, t } => Traced::Next(Dest::Peer(to), t),
            },
        );
    }
    // Segments are traced in ray order, so the first hit is the closest.
    let own = |s: f32, e: f32, c: &mut Counts| -> Option<Result<Traced, EngineError>> {
        if any {
            job.accel
                .occluded(ray, s, e, &mut c.trace)
                .then_some(Ok(Traced::Occluded))
        } else {
            job.accel
                .intersect(ray, s, e, &mut c.trace)
                .map(|h| job.own_surface(h).map(Traced::Hit))
        }
    };
    let mut run: Option<(f32, f32)> = None;
    let mut found: Option<Result<Traced, EngineError>> = None;
    let _ = map.tree.walk_from(ray, 0.0, t_max, resume, |leaf, ta, tb| {
        let o = map.owner[leaf as usize];
        if o == me {
            run = Some(run.map_or((ta, tb), |(s, _)| (s, tb)));
            return ControlFlow::Continue(());
        }
        if let Some((s, e)) = run.take() {
            found = own(s, e, c);
            if found.is_some() {
                return ControlFlow::Break(());
            }
        }
        let fetched = match pinned.filter(|p| p.leaf == leaf) {
            Some(p) => Some(p.clone()),
            None => job.locality.store.get(leaf),
        };
        let Some(f) = fetched else {
            let dest = if job.locality.wants_fetch(leaf, kind) {
                Dest::Leaf(leaf)
            } else {
                Dest::Peer(o)
            };
            found = Some(Ok(Traced::Next(dest, ta)));
            return ControlFlow::Break(());
        };
        c.fetched_leaf_traces += 1;
        let r = if any {
            f.accel
                .occluded(ray, ta, tb, &mut c.trace)
                .then_some(Traced::Occluded)
        } else {
            f.accel.intersect(ray, ta, tb, &mut c.trace).map(|h| {
                let k = f
                    .geometry
                    .ids
                    .binary_search(&h.tri)
                    .expect("a leaf's BVH holds only the leaf's triangles");
                Traced::Hit(Surface {
                    hit: h,
                    verts: f.geometry.verts[k],
                    material: f.geometry.material[k],
                })
            })
        };
        match r {
            Some(r) => {
                found = Some(Ok(r));
                ControlFlow::Break(())
            }
            None => ControlFlow::Continue(()),
        }
    });
    if let Some(r) = found {
        return r;
    }
    if let Some((s, e)) = run
        && let Some(r) = own(s, e, c)
    {
        return r;
    }
    Ok(Traced::Miss)
}

/// Traces one work item through this worker's run of leaves, and keeps
/// going depth-first through everything that stays local: a path whose
/// vertices are all here is finished in this call, like the single-machine
/// integrator; only queries that leave the region become messages.
fn process(job: &EngineJob, w: Work, c: &mut Counts, chain: &mut Vec<ChainVertex>) -> Outcome {
    match process_inner(job, &w, c, chain) {
        Ok(o) => o,
        Err(e) => Outcome::Error(e),
    }
}

fn process_inner(
    job: &EngineJob,
    w: &Work,
    c: &mut Counts,
    chain: &mut Vec<ChainVertex>,
) -> Result<Outcome, EngineError> {
    let query = match w.task {
        Task::Query(q) => q,
        Task::Camera { x, y, sample } => {
            let key = SampleKey::new(
                y as u64 * job.setup.camera.width as u64 + x as u64,
                sample,
                job.setup.seed,
            );
            c.trace.camera_rays += 1;
            let ray = job.setup.camera.ray(x, y, key.get2d(DIM_PIXEL));
            Query::Path(PathRay::camera(ray, key))
        }
    };
    let forward = |query: Query, dest: Dest, t: f32| {
        if t == w.resume && w.from != job.setup.me {
            // The sender computed the same processor vector; a query that
            // does not start in our leaf was corrupted or misrouted.
            return Err(EngineError::Misrouted { from: w.from });
        }
        Ok(Outcome::Forward(dest, query, t, w.reply))
    };
    let pinned = w.pinned.as_ref();
    Ok(match query {
        Query::Shadow(s) => {
            match trace(
                job,
                &s.ray,
                s.t_max,
                w.resume,
                true,
                RayKind::Secondary,
                pinned,
                c,
            )? {
                Traced::Next(dest, t) => forward(Query::Shadow(s), dest, t)?,
                Traced::Miss => Outcome::Answer(w.reply, Answer::Visible(true)),
                Traced::Occluded | Traced::Hit(_) => {
                    Outcome::Answer(w.reply, Answer::Visible(false))
                }
            }
        }
        Query::Path(q) => {
            let kind = if q.depth == 0 {
                RayKind::Camera
            } else {
                RayKind::Secondary
            };
            match trace(job, &q.ray, f32::INFINITY, w.resume, false, kind, pinned, c)? {
                Traced::Next(dest, t) => forward(Query::Path(q), dest, t)?,
                Traced::Miss | Traced::Occluded => {
                    Outcome::Answer(w.reply, Answer::Radiance(Vec3::ZERO))
                }
                Traced::Hit(h) => {
                    chain.clear();
                    match eval_hit(job, &q, &h, c, chain)? {
                        Some(l) => Outcome::Answer(w.reply, Answer::Radiance(l)),
                        None => Outcome::Chain(w.reply, std::mem::take(chain)),
                    }
                }
            }
        }
    })
}

/// Shades hit `h` of `q` and evaluates its shadow and continuation queries
/// as far as they stay here. Returns the vertex's radiance when everything
/// was local; otherwise leaves this vertex (and the pending ones below it)
/// at the end of `chain` and returns None.
fn eval_hit(
    job: &EngineJob,
    q: &PathRay,
    h: &Surface,
    c: &mut Counts,
    chain: &mut Vec<ChainVertex>,
) -> Result<Option<Vec3>, EngineError> {
    let mat = &job.setup.materials[h.material as usize];
    let s = shade(
        q,
        &h.hit,
        &h.verts,
        mat,
        &job.setup.lights,
        job.setup.max_depth,
        job.caches
            .as_ref()
            .map(|c| (&job.setup.map.tree, c.params.radius)),
    );
    let shadow = match s.shadow {
        None => Child::Done(false),
        Some(sr) => {
            c.trace.shadow_rays += 1;
            let ray = &sr.ray;
            match trace(
                job,
                ray,
                sr.t_max,
                f32::NEG_INFINITY,
                true,
                RayKind::Secondary,
                None,
                c,
            )? {
                Traced::Miss => Child::Done(true),
                Traced::Occluded | Traced::Hit(_) => Child::Done(false),
                Traced::Next(dest, t) => Child::Forward(dest, Query::Shadow(sr), t),
            }
        }
    };
    let idx = chain.len();
    chain.push(ChainVertex {
        vertex: s.vertex,
        shadow,
        next: Child::Done(Vec3::ZERO),
        update: None,
    });
    let (next, update) = match s.next {
        None => (Child::Done(Vec3::ZERO), None),
        Some(nq) => {
            c.trace.indirect_rays += 1;
            continuation(job, &nq, s.cache_leaf, c, chain)?
        }
    };
    if let (Child::Done(visible), Child::Done(l)) = (&chain[idx].shadow, &next) {
        let v = chain[idx].vertex.finish(*visible, *l);
        chain.truncate(idx);
        return Ok(Some(v));
    }
    chain[idx].next = next;
    chain[idx].update = update;
    Ok(None)
}

/// A continuation ray. Without caches it is traced like any query. With
/// them it is traced exactly inside the locality sphere of the leaf it
/// starts in (`leaf`, from [`shade`]); a ray that hits nothing there is answered by the leaf's
/// cache when the cache can, and otherwise traced on (returning the key
/// under which its radiance must update the cache if that radiance is not
/// known yet). A ray that leaves this worker's reach inside the sphere
/// goes on uncached.
fn continuation(
    job: &EngineJob,
    nq: &PathRay,
    leaf: Option<u32>,
    c: &mut Counts,
    chain: &mut Vec<ChainVertex>,
) -> Result<(Child<Vec3>, Option<CacheKey>), EngineError> {
    let follow = |t: Traced, c: &mut Counts, chain: &mut Vec<ChainVertex>| {
        Ok::<_, EngineError>(match t {
            Traced::Miss | Traced::Occluded => Child::Done(Vec3::ZERO),
            Traced::Next(dest, t) => Child::Forward(dest, Query::Path(*nq), t),
            Traced::Hit(h) => match eval_hit(job, nq, &h, c, chain)? {
                Some(l) => Child::Done(l),
                None => Child::Deeper,
            },
        })
    };
    let inf = f32::INFINITY;
    // `shade` found the leaf and used the perimeter `emit_within` for this
    // ray's emission and its vertex's next-event weights.
    let tp = nq.emit_within;
    let (Some(caches), Some(leaf)) = (&job.caches, leaf) else {
        let t = trace(
            job,
            &nq.ray,
            inf,
            f32::NEG_INFINITY,
            false,
            RayKind::Secondary,
            None,
            c,
        )?;
        return Ok((follow(t, c, chain)?, None));
    };
    let inside = trace(
        job,
        &nq.ray,
        tp,
        f32::NEG_INFINITY,
        false,
        RayKind::Secondary,
        None,
        c,
    )?;
    if !matches!(inside, Traced::Miss) {
        c.trace.cache.local += 1;
        return Ok((follow(inside, c, chain)?, None));
    }
    if let Lookup::Answer(v) = caches.lookup(leaf, nq.ray.dir) {
        c.trace.cache.lookups += 1;
        return Ok((Child::Done(v), None));
    }
    c.trace.cache.global += 1;
    let beyond = trace(job, &nq.ray, inf, tp, false, RayKind::Secondary, None, c)?;
    match follow(beyond, c, chain)? {
        Child::Done(v) => {
            caches.update(leaf, nq.ray.dir, v);
            Ok((Child::Done(v), None))
        }
        pending => Ok((pending, Some((leaf, nq.ray.dir)))),
    }
}

fn child_query<T>(c: Child<T>) -> Option<(Dest, Query, f32)> {
    match c {
        Child::Forward(dest, q, t) => Some((dest, q, t)),
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
    fn originate(&mut self) {
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
                self.work.push_back(Work {
                    task: Task::Camera {
                        x: a.x0 + p % w,
                        y: a.y0 + p / w,
                        sample: index % job.setup.spp,
                    },
                    resume: f32::NEG_INFINITY,
                    reply: ReplyTo { worker: me, slot },
                    from: me,
                    pinned: None,
                });
            }
        }
    }

    /// Sends a query on: to a peer, or into the wait for a leaf.
    fn route(
        &mut self,
        dest: Dest,
        query: Query,
        resume: f32,
        reply: ReplyTo,
    ) -> Result<(), EngineError> {
        match dest {
            Dest::Peer(to) => {
                self.stats.forwarded_out += 1;
                self.push_out(
                    to,
                    RayItem::Trace {
                        query,
                        resume,
                        reply,
                    },
                )
            }
            Dest::Leaf(leaf) => {
                self.stats.fetch_waits += 1;
                let mut w = Work {
                    task: Task::Query(query),
                    resume,
                    reply,
                    from: self.job.setup.me,
                    pinned: None,
                };
                if let Some(f) = self.job.locality.store.get(leaf) {
                    // It arrived while this query was being traced.
                    w.pinned = Some(f);
                    self.work.push_back(w);
                    return Ok(());
                }
                let list = self.waiting.entry(leaf).or_default();
                list.push(w);
                if list.len() == 1 {
                    self.stats.fetch_requests += 1;
                    let owner = self.job.setup.map.owner[leaf as usize];
                    self.send_msg(owner as usize, PeerMsg::Fetch(vec![leaf]))?;
                }
                Ok(())
            }
        }
    }

    /// Ships the geometry of our leaves that a peer asked for.
    fn serve(&mut self, from: WorkerId, leaves: Vec<u32>) -> Result<(), EngineError> {
        let job = self.job;
        for leaf in leaves {
            let Ok(i) = job
                .setup
                .own_leaves
                .binary_search_by_key(&leaf, |(l, _)| *l)
            else {
                return Err(EngineError::NotMyLeaf { from, leaf });
            };
            let g = &job.geometry;
            let mut geometry = RegionGeometry::default();
            for &id in &job.setup.own_leaves[i].1 {
                let Ok(k) = g.ids.binary_search(&id) else {
                    return Err(EngineError::ForeignTriangle(id));
                };
                geometry.ids.push(id);
                geometry.verts.push(g.verts[k]);
                geometry.material.push(g.material[k]);
            }
            self.stats.leaves_served += 1;
            let msg = PeerMsg::Leaf(Box::new(LeafGeometry { leaf, geometry }));
            self.send_msg(from as usize, msg)?;
        }
        Ok(())
    }

    /// Keeps a fetched leaf and resumes the work that waited for it.
    fn receive_leaf(
        &mut self,
        from: WorkerId,
        bytes: u64,
        lg: LeafGeometry,
    ) -> Result<(), EngineError> {
        let job = self.job;
        let leaf = lg.leaf;
        let bad = |why| EngineError::BadLeaf { from, leaf, why };
        if job.setup.map.owner.get(leaf as usize) != Some(&from) {
            return Err(bad("the sender does not own it"));
        }
        let g = &lg.geometry;
        if g.ids.len() != g.verts.len() || g.ids.len() != g.material.len() {
            return Err(bad("its lists differ in length"));
        }
        if !g.ids.is_sorted_by(|a, b| a < b) {
            return Err(bad("its triangle ids are not ascending"));
        }
        if g.material
            .iter()
            .any(|&m| m as usize >= job.setup.materials.len())
        {
            return Err(bad("it names a material the job does not define"));
        }
        if g.verts.iter().flatten().any(|p| !p.is_finite()) {
            return Err(bad("it has a non-finite vertex"));
        }
        let Some(list) = self.waiting.remove(&leaf) else {
            return Err(bad("it was not asked for"));
        };
        self.stats.fetched_leaves += 1;
        self.stats.fetched_bytes += bytes;
        let f = Arc::new(FetchedLeaf::build(leaf, lg.geometry, job.setup.magnitude));
        if !job.locality.store.insert(f.clone()) {
            job.locality.mark_too_large(leaf);
        }
        for mut w in list {
            w.pinned = Some(f.clone());
            self.work.push_back(w);
        }
        Ok(())
    }

    fn apply(&mut self, o: Outcome) -> Result<(), EngineError> {
        let me = self.job.setup.me;
        match o {
            Outcome::Error(e) => return Err(e),
            Outcome::Forward(dest, query, resume, reply) => {
                self.route(dest, query, resume, reply)?;
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
                        update: cv.update,
                    });
                    let mine = ReplyTo { worker: me, slot };
                    for c in [child_query(cv.shadow), child_query(cv.next)]
                        .into_iter()
                        .flatten()
                    {
                        let (dest, query, resume) = c;
                        self.route(dest, query, resume, mine)?;
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
                    update,
                } => {
                    match (a, &*shadow, &*next) {
                        (Answer::Visible(v), Wait::Pending, _) => *shadow = Wait::Done(v),
                        (Answer::Radiance(l), _, Wait::Pending) => {
                            *next = Wait::Done(l);
                            if let (Some((leaf, dir)), Some(c)) = (*update, &self.job.caches) {
                                c.update(leaf, dir, l);
                            }
                        }
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
        self.send_msg(p, PeerMsg::Packet(items))
    }

    /// Sends behind whatever already waits for peer `p`, keeping order.
    fn send_msg(&mut self, p: usize, msg: PeerMsg) -> Result<(), EngineError> {
        if !self.stalled[p].is_empty() {
            self.stalled[p].push_back(msg);
            return Ok(());
        }
        let Some(tx) = &self.links.peers.get(p).and_then(Option::as_ref) else {
            return Err(EngineError::LinkClosed("a peer"));
        };
        match tx.try_send(msg) {
            Ok(()) => Ok(()),
            Err(flume::TrySendError::Full(msg)) => {
                self.stats.backpressure_stalls += 1;
                self.stalled[p].push_back(msg);
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
