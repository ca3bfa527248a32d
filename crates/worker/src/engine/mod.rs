//! The compute side of a worker in one job: a loop on its own thread that
//! owns everything pending, traces batches of work on the rayon pool, and
//! talks to peers and the scheduler through bounded channels.
//!
//! - [`kernel`] (pool side): work items traced through the core's path
//!   kernel with this worker's tracer over its [`Reach`].
//! - [`slots`]: camera samples of the worker's tiles and vertices that
//!   wait for answers from other workers.
//! - [`outbox`]: ray items packed per peer, flushed by size, deadline or
//!   idleness, and held back (never blocking) when a peer is full.
//! - this module: the loop. Everything it waits for (peer packets, tiles,
//!   traced batches, fetched leaves built on the pool, merged BVH parts from
//!   the builder thread) arrives as an [`Event`] on one bounded channel, so
//!   the loop sleeps in one place and no message can be missed between two
//!   sources.
//!
//! Work arrives as ray items from peers, tiles from the scheduler and
//! answers to this worker's own queries; a camera sample is the root of a
//! path, and a tile is done when all its samples are in. Queues are bounded
//! by construction: a worker keeps at most `max_inflight` camera samples
//! open, each sample has at most `max_depth + 1` vertices pending and two
//! queries in flight per vertex, so the ray items in the whole farm are
//! bounded, and while any message waits for a full peer no new sample
//! starts.

pub mod kernel;
pub mod outbox;
pub mod slots;

use crate::fetch::{FetchedLeaf, Locality};
use crate::reach::{LeafSource, Reach, cut_run, merge};
use crate::sys;
use kernel::{Batch, Work, trace_batch};
use locus_core::accel_set::{AccelSet, MAX_PARTS, Part};
use locus_core::dircache::LeafCaches;
use locus_core::path::{Answer, CacheUse, Dest, Kernel, Outcome, Query, Task};
use locus_core::region::WorkerId;
use locus_protocol::control::{JobSetup, TileAssignment, TriangleSet, WorkerToScheduler};
use locus_protocol::rays::{LeafGeometry, PeerMsg, RayItem, ReplyTo};
use locus_protocol::report::WorkerStats;
use locus_protocol::submit::FetchPolicy;
use outbox::{LinkClosed, Outbox};
use slots::{Effect, Slots, UnknownSlot};
use std::collections::{HashMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Everything a worker holds for one job that does not change while it
/// runs: what the scheduler sent, its directional caches and its fetch
/// policy.
pub struct EngineJob {
    pub setup: JobSetup,
    pub workers: usize,
    /// One directional cache per octree leaf this worker shades in.
    pub caches: Option<LeafCaches>,
    pub locality: Locality,
}

impl EngineJob {
    pub fn new(setup: JobSetup) -> Self {
        let caches = setup.cache.map(|mut p| {
            p.max_nodes_total = p.max_nodes_total.min(setup.plan.cache_nodes as usize);
            LeafCaches::new(setup.map.tree.leaves.len(), p)
        });
        let locality = Locality::new(&setup);
        Self {
            workers: setup.peers.len(),
            setup,
            caches,
            locality,
        }
    }

    /// The path kernel for this job.
    pub fn kernel(&self) -> Kernel<'_> {
        let s = &self.setup;
        Kernel {
            materials: &s.materials,
            lights: &s.lights,
            camera: &s.camera,
            seed: s.seed,
            max_depth: s.max_depth,
            cache: self.caches.as_ref().map(|c| CacheUse {
                octree: &s.map.tree,
                caches: c,
            }),
        }
    }

    /// Triangle ids of own leaf `leaf`.
    fn own_ids(&self, leaf: u32) -> Option<&[u32]> {
        let own = &self.setup.own_leaves;
        let i = own.binary_search_by_key(&leaf, |(l, _)| *l).ok()?;
        Some(&own[i].1)
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

/// What the engine loop waits for.
pub enum Event {
    Input(Input),
    Traced(Batch),
    /// A fetched leaf's BVH, built on the pool.
    LeafBuilt(Arc<FetchedLeaf>, f64),
    /// New BVH parts with pending leaves merged, from the builder thread.
    Merged(Merged),
}

pub struct Merged {
    parts: Vec<Arc<Part>>,
    leaves: Vec<u32>,
    built: usize,
    secs: f64,
    cpu_s: f64,
}

/// Where the engine's output goes.
pub struct Links {
    /// One bounded channel per peer (None for this worker itself).
    pub peers: Vec<Option<flume::Sender<PeerMsg>>>,
    pub control: flume::Sender<WorkerToScheduler>,
    /// What the sockets counted, for reports of a stalled job.
    pub traffic: Arc<crate::peers::Traffic>,
    /// Cancelled when the job is aborted or the worker shuts down: the
    /// engine stops at its next turn.
    pub cancel: tokio_util::sync::CancellationToken,
}

#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    #[error(transparent)]
    UnknownSlot(#[from] UnknownSlot),
    #[error("worker {from} sent a query that resumes in a leaf this worker does not hold")]
    Misrouted { from: WorkerId },
    #[error(transparent)]
    Peer(#[from] LinkClosed),
    #[error("the link to {0} closed while the job was running")]
    LinkClosed(&'static str),
    #[error("the scheduler ended the job with {0} queries still pending")]
    EndedEarly(usize),
    #[error("the job was cancelled")]
    Cancelled,
    #[error("worker {from} asked for leaf {leaf}, which this worker does not own")]
    NotMyLeaf { from: WorkerId, leaf: u32 },
    #[error("worker {from} sent geometry for leaf {leaf}: {why}")]
    BadLeaf {
        from: WorkerId,
        leaf: u32,
        why: &'static str,
    },
}

/// Largest batch one pool task traces.
const BATCH: usize = 4096;
/// Smallest batch worth a pool task.
const MIN_BATCH: usize = 16;
/// Events handled per wake-up before the loop looks at its queues again.
const EVENTS_PER_TURN: usize = 512;
/// Rent or buy for merging: a ray crossing a leaf that waits to be merged
/// costs about this many triangle builds more than crossing merged geometry
/// (its own BVH, an extra step of the route walk); merging rebuilds the
/// parts the leaves join. Pending leaves are merged once their crossings
/// since the last merge have cost as much as that rebuild, which keeps the
/// total at most twice the best choice made in hindsight.
const CROSSING_IN_BUILDS: u64 = 1;
/// Leaves waiting longer than this are merged whatever their crossings, so
/// that a job's end does not leave fetched leaves on the slow path.
const MERGE_AFTER: Duration = Duration::from_millis(500);
/// A worker that has heard nothing for this long while work is pending
/// says what it waits for.
const STALL_REPORT: Duration = Duration::from_secs(5);
/// Leaves per request when a worker asks for many at once.
const PREFETCH_CHUNK: usize = 64;

/// The builder thread: merges pending leaves into BVH parts off the
/// engine's thread, one merge at a time.
struct Builder {
    tx: Option<flume::Sender<MergeRequest>>,
    busy: bool,
}

struct MergeRequest {
    parts: Vec<Arc<Part>>,
    new: Vec<Arc<FetchedLeaf>>,
    fetched_ids: HashMap<u32, Arc<[u32]>>,
}

impl Builder {
    fn spawn(job: Arc<EngineJob>, events: flume::Sender<Event>) -> Self {
        let (tx, rx) = flume::bounded::<MergeRequest>(1);
        let spawned = std::thread::Builder::new()
            .name("locus-build".into())
            .spawn(move || {
                while let Ok(r) = rx.recv() {
                    let t = Instant::now();
                    let cpu0 = sys::thread_cpu_s();
                    let ids = |l: u32| -> Option<Arc<[u32]>> {
                        r.fetched_ids
                            .get(&l)
                            .cloned()
                            .or_else(|| job.own_ids(l).map(Arc::from))
                    };
                    let mag = job.setup.magnitude;
                    let mut max_part = job.setup.plan.part_triangles.max(1) as usize;
                    let (mut parts, mut built) = merge(&r.parts, &r.new, &ids, max_part, mag);
                    // A part size far below what is held would make more
                    // parts than a query keeps track of: grow it.
                    while parts.len() > MAX_PARTS {
                        max_part *= 2;
                        let (p, n) = merge_all(&parts, &ids, max_part, mag);
                        built += n;
                        parts = p;
                    }
                    let m = Merged {
                        parts,
                        leaves: r.new.iter().map(|f| f.leaf).collect(),
                        built,
                        secs: t.elapsed().as_secs_f64(),
                        cpu_s: sys::thread_cpu_s() - cpu0,
                    };
                    if events.send(Event::Merged(m)).is_err() {
                        break;
                    }
                }
            });
        Self {
            tx: spawned.ok().map(|_| tx),
            busy: false,
        }
    }
}

/// Rebuilds every part into parts of at most `max_part` triangles.
fn merge_all(
    parts: &[Arc<Part>],
    ids: &dyn Fn(u32) -> Option<Arc<[u32]>>,
    max_part: usize,
    magnitude: f32,
) -> (Vec<Arc<Part>>, usize) {
    let mut out = Vec::new();
    let mut built = 0;
    for chunk in parts.chunks(2) {
        // Pairs of neighbouring parts rebuilt as one halve the count.
        let leaves: Vec<(u32, Arc<[u32]>, &Part)> = chunk
            .iter()
            .flat_map(|p| {
                p.leaves
                    .iter()
                    .filter_map(move |&l| Some((l, ids(l)?, p.as_ref())))
            })
            .collect();
        let run: Vec<LeafSource> = leaves
            .iter()
            .map(|(l, i, p)| LeafSource {
                leaf: *l,
                ids: i,
                accel: &p.accel,
            })
            .collect();
        let (mut p, n) = cut_run(&run, max_part, magnitude);
        built += n;
        out.append(&mut p);
    }
    (out, built)
}

struct Engine<'a> {
    job: &'a Arc<EngineJob>,
    control: flume::Sender<WorkerToScheduler>,
    events: flume::Sender<Event>,
    outbox: Outbox,
    slots: Slots,
    work: VecDeque<Work>,
    no_more_tiles: bool,
    stats: WorkerStats,
    effects: Vec<Effect>,
    children: Vec<(Dest, Query, f32, ReplyTo)>,
    traffic: Arc<crate::peers::Traffic>,
    /// Packets received from each peer.
    received: Vec<u64>,
    // What this worker can trace.
    reach: Arc<Reach>,
    parts: Vec<Arc<Part>>,
    local: Vec<bool>,
    pending: Vec<Arc<FetchedLeaf>>,
    reach_dirty: bool,
    /// Work waiting for a leaf's geometry, by leaf: requested, or arrived
    /// and being built on the pool.
    waiting: HashMap<u32, Vec<Work>>,
    building: usize,
    /// Bytes of fetched geometry held or asked for.
    held: u64,
    held_peak: u64,
    fetched_ids: HashMap<u32, Arc<[u32]>>,
    last_arrival: Instant,
    /// Crossings of pending leaves since the last merge.
    crossings: u64,
    /// Every remote leaf was asked for at the start; they are merged at
    /// once when the last has arrived.
    prefetching: bool,
    builder: Builder,
    cpu_s: f64,
    /// The clock read once per turn of the loop: packets' ages need no
    /// finer grain than that.
    now: Instant,
}

/// Runs the job until the scheduler ends it; returns this worker's counters
/// (traffic bytes are added by the caller, which owns the sockets).
///
/// Batches are traced as pool tasks while this thread applies the results
/// of earlier ones: with `threads + 1` batches out, the pool never waits
/// for the bookkeeping, which is serial.
pub fn run(
    job: Arc<EngineJob>,
    parts: Vec<Arc<Part>>,
    pool: &rayon::ThreadPool,
    events: (flume::Sender<Event>, flume::Receiver<Event>),
    links: Links,
) -> Result<WorkerStats, EngineError> {
    let cpu0 = sys::thread_cpu_s();
    let (events_tx, inbox) = events;
    let s = &job.setup;
    let n_leaves = s.map.owner.len();
    let mut local = vec![false; n_leaves];
    // What the parts hold is local: the worker's own leaves, and every
    // leaf when the scheduler replicated the scene.
    for l in s
        .own_leaves
        .iter()
        .map(|(l, _)| *l)
        .chain(parts.iter().flat_map(|p| p.leaves.iter().copied()))
    {
        if let Some(x) = local.get_mut(l as usize) {
            *x = true;
        }
    }
    let per_leaf = s.fetch != FetchPolicy::Forward;
    let own = AccelSet::from_parts(parts.clone());
    let region_bytes = own.bytes() as u64;
    let reach = Arc::new(Reach::new(
        &s.map.tree,
        &s.map.owner,
        &local,
        own,
        Vec::new(),
        per_leaf,
    ));
    let flush = Duration::from_micros(s.tuning.flush_us.max(1) as u64);
    let mut e = Engine {
        job: &job,
        control: links.control,
        events: events_tx.clone(),
        outbox: Outbox::new(links.peers, s.tuning.packet_size.max(1) as usize, flush),
        slots: Slots::new(s.me, s.job, s.spp),
        work: VecDeque::new(),
        no_more_tiles: false,
        stats: WorkerStats {
            peers: vec![Default::default(); job.workers],
            triangles: s.region_triangles,
            leaves: s.own_leaves.len() as u32,
            fetch_cache_bound: s.plan.fetch_bytes,
            memory_budget: s.plan.budget,
            region_bytes,
            ..Default::default()
        },
        effects: Vec::new(),
        children: Vec::new(),
        traffic: links.traffic.clone(),
        received: vec![0; job.workers],
        reach,
        parts,
        local,
        pending: Vec::new(),
        reach_dirty: false,
        waiting: HashMap::new(),
        building: 0,
        held: 0,
        held_peak: 0,
        fetched_ids: HashMap::new(),
        last_arrival: Instant::now(),
        crossings: 0,
        prefetching: false,
        builder: Builder::spawn(job.clone(), events_tx.clone()),
        cpu_s: 0.0,
        now: Instant::now(),
    };
    drop(events_tx);
    let cancel = links.cancel.clone();
    let max_out = pool.current_num_threads() + 1;
    e.prefetch()?;
    e.control(WorkerToScheduler::NeedTiles {
        job: s.job,
        count: s.tuning.tiles_ahead.max(1),
    })?;
    let start = Instant::now();
    let result = pool.in_place_scope(move |scope| {
        // The receiver lives (and dies) in here: leaving the scope by an
        // error drops it first, so no pool task can block on a send while
        // the scope waits for it.
        let inbox = inbox;
        let mut idle = Duration::ZERO;
        let mut out = 0usize;
        let mut last_event = Instant::now();
        let mut warned = false;
        loop {
            if cancel.is_cancelled() {
                return Err(EngineError::Cancelled);
            }
            e.outbox.retry_stalled()?;
            if !e.outbox.is_stalled() {
                e.originate();
            }
            e.maybe_merge();
            if e.reach_dirty {
                e.republish();
            }
            while out < max_out && !e.work.is_empty() {
                let share = e.work.len().div_ceil(max_out - out);
                let take = share.clamp(MIN_BATCH, BATCH).min(e.work.len());
                let batch: Vec<Work> = e.work.drain(..take).collect();
                let (job, reach, tx) = (e.job.clone(), e.reach.clone(), e.events.clone());
                scope.spawn(move |_| {
                    let b = trace_batch(&job, &reach, batch);
                    // A closed inbox means the job is over.
                    let _ = tx.send(Event::Traced(b));
                });
                out += 1;
            }
            if out == 0 {
                // Nothing is being traced: what waits in packets must go.
                e.outbox.flush_all()?;
            }
            let now = Instant::now();
            let wait = if e.outbox.is_stalled() {
                Duration::from_millis(1)
            } else {
                let mut w = Duration::from_millis(100);
                if let Some(d) = e.outbox.next_deadline() {
                    w = w.min(d.saturating_duration_since(now));
                }
                if !e.pending.is_empty() && !e.builder.busy {
                    w = w.min((e.last_arrival + MERGE_AFTER).saturating_duration_since(now));
                }
                w
            };
            let t = Instant::now();
            let first = inbox.recv_timeout(wait);
            if out == 0 {
                idle += t.elapsed();
            }
            e.now = Instant::now();
            let mut next = match first {
                Ok(ev) => Some(ev),
                Err(flume::RecvTimeoutError::Timeout) => None,
                Err(flume::RecvTimeoutError::Disconnected) => {
                    return Err(EngineError::LinkClosed("the worker's inbox"));
                }
            };
            if next.is_some() {
                last_event = e.now;
                warned = false;
            } else if !warned && e.now.duration_since(last_event) > STALL_REPORT {
                warned = true;
                e.report_stall(out);
            }
            let mut handled = 0;
            while let Some(ev) = next.take() {
                handled += 1;
                match ev {
                    Event::Traced(b) => {
                        out -= 1;
                        e.apply(b)?;
                    }
                    Event::LeafBuilt(f, cpu) => e.leaf_built(f, cpu),
                    Event::Merged(m) => e.merged(m),
                    Event::Input(Input::End) => {
                        let waiting: usize = e.waiting.values().map(Vec::len).sum();
                        let left = e.slots.pending() + e.work.len() + waiting + out;
                        if left > 0 || e.building > 0 {
                            return Err(EngineError::EndedEarly(left));
                        }
                        return Ok(e.finish(start.elapsed(), idle));
                    }
                    Event::Input(i) => e.input(i, scope)?,
                }
                if handled < EVENTS_PER_TURN {
                    next = inbox.try_recv().ok();
                }
            }
            e.outbox.flush_due(e.now)?;
        }
    });
    result.map(|mut st| {
        st.cpu_s += sys::thread_cpu_s() - cpu0;
        st
    })
}

impl<'a> Engine<'a> {
    fn control(&self, m: WorkerToScheduler) -> Result<(), EngineError> {
        self.control
            .send(m)
            .map_err(|_| EngineError::LinkClosed("the scheduler"))
    }

    /// Starts camera samples until `max_inflight` are open.
    fn originate(&mut self) {
        let cap = self.job.setup.tuning.max_inflight.max(1) as usize;
        let me = self.job.setup.me;
        while self.slots.samples_open() < cap {
            let Some(n) = self.slots.start_sample() else {
                break;
            };
            self.work.push_back(Work {
                task: Task::Camera {
                    x: n.x,
                    y: n.y,
                    sample: n.sample,
                },
                resume: f32::NEG_INFINITY,
                reply: n.reply,
                from: me,
                pinned: None,
            });
        }
    }

    fn input<'s>(&mut self, i: Input, scope: &rayon::Scope<'s>) -> Result<(), EngineError>
    where
        'a: 's,
    {
        match i {
            Input::Packet { from, items } => {
                if let Some(r) = self.received.get_mut(from as usize) {
                    *r += 1;
                }
                for it in items {
                    match it {
                        RayItem::Trace {
                            query,
                            resume,
                            reply,
                        } => {
                            self.stats.queries_in += 1;
                            self.work.push_back(Work {
                                task: Task::Query(query),
                                resume,
                                reply,
                                from,
                                pinned: None,
                            });
                        }
                        RayItem::Answer { to, answer } => {
                            self.slots.answer(
                                from,
                                to,
                                answer,
                                &mut self.effects,
                                &mut self.stats.trace,
                            )?;
                            self.effects()?;
                        }
                    }
                }
            }
            Input::Fetch { from, leaves } => self.serve(from, leaves)?,
            Input::Leaf { from, bytes, leaf } => self.receive_leaf(from, bytes, *leaf, scope)?,
            Input::Tile(a) => self.slots.add_tile(a),
            Input::NoMoreTiles => self.no_more_tiles = true,
            Input::End => unreachable!("handled by the loop"),
        }
        Ok(())
    }

    /// Applies a traced batch.
    fn apply(&mut self, b: Batch) -> Result<(), EngineError> {
        if let Some(from) = b.misrouted {
            return Err(EngineError::Misrouted { from });
        }
        self.stats.trace += b.stats;
        self.stats.fetched_leaf_traces += b.fetched_leaf_traces;
        self.crossings += b.fetched_leaf_traces;
        self.cpu_s += b.cpu_s;
        let me = self.job.setup.me;
        for (reply, o) in b.items {
            match o {
                Outcome::Answer(a) => {
                    if reply.worker == me {
                        self.slots.answer(
                            me,
                            reply.slot,
                            a,
                            &mut self.effects,
                            &mut self.stats.trace,
                        )?;
                        self.effects()?;
                    } else {
                        self.reply(reply, a)?;
                    }
                }
                Outcome::Forward {
                    dest,
                    query,
                    resume,
                } => self.route(dest, query, resume, reply)?,
                Outcome::Chain { start, end } => {
                    let mut children = std::mem::take(&mut self.children);
                    self.slots.open_chain(
                        reply,
                        &b.chain[start as usize..end as usize],
                        &mut children,
                    );
                    for (dest, query, resume, r) in children.drain(..) {
                        self.route(dest, query, resume, r)?;
                    }
                    self.children = children;
                }
            }
        }
        Ok(())
    }

    fn reply(&mut self, to: ReplyTo, answer: Answer) -> Result<(), EngineError> {
        self.stats.answers_out += 1;
        let item = RayItem::Answer {
            to: to.slot,
            answer,
        };
        Ok(self.outbox.push(to.worker, item, self.now)?)
    }

    /// Carries out what answers set off.
    fn effects(&mut self) -> Result<(), EngineError> {
        let mut fx = std::mem::take(&mut self.effects);
        for f in fx.drain(..) {
            match f {
                Effect::Reply(to, a) => self.reply(to, a)?,
                Effect::CacheUpdate((leaf, dir), v) => {
                    if let Some(c) = &self.job.caches {
                        c.update(leaf, dir, v);
                    }
                }
                Effect::TileDone(r) => {
                    self.stats.tiles += 1;
                    self.control(WorkerToScheduler::TileDone(r))?;
                    if !self.no_more_tiles {
                        self.control(WorkerToScheduler::NeedTiles {
                            job: self.job.setup.job,
                            count: 1,
                        })?;
                    }
                }
            }
        }
        self.effects = fx;
        Ok(())
    }

    /// Sends a query on: to a peer, or into the wait for a leaf.
    fn route(
        &mut self,
        dest: Dest,
        query: Query,
        resume: f32,
        reply: ReplyTo,
    ) -> Result<(), EngineError> {
        let job = self.job;
        let leaf = match dest {
            Dest::Peer(to) => {
                self.stats.forwarded_out += 1;
                let item = RayItem::Trace {
                    query,
                    resume,
                    reply,
                };
                return Ok(self.outbox.push(to, item, self.now)?);
            }
            Dest::Leaf(leaf) => leaf,
        };
        let w = Work {
            task: Task::Query(query),
            resume,
            reply,
            from: job.setup.me,
            pinned: None,
        };
        let l = leaf as usize;
        if self.local.get(l) == Some(&true) || self.pending.iter().any(|p| p.leaf == leaf) {
            // It arrived while this query was being traced.
            self.work.push_back(w);
            return Ok(());
        }
        self.stats.fetch_waits += 1;
        if let Some(list) = self.waiting.get_mut(&leaf) {
            list.push(w);
            return Ok(());
        }
        let need = job.locality.held_estimate(leaf);
        let Some(&owner) = job.setup.map.owner.get(l) else {
            return Err(EngineError::BadLeaf {
                from: job.setup.me,
                leaf,
                why: "a ray asked for a leaf outside the octree",
            });
        };
        if self.held + need > job.setup.plan.fetch_bytes {
            // No room: this leaf is forwarded from now on.
            job.locality.refuse(leaf);
            self.stats.fetch_waits -= 1;
            return self.route(Dest::Peer(owner), query, resume, reply);
        }
        self.held += need;
        self.held_peak = self.held_peak.max(self.held);
        self.stats.fetch_requests += 1;
        self.waiting.insert(leaf, vec![w]);
        tracing::debug!(
            job = job.setup.job,
            me = job.setup.me,
            leaf,
            owner,
            "fetch sent"
        );
        Ok(self.outbox.send(owner, PeerMsg::Fetch(vec![leaf]))?)
    }

    /// Under `fetch`, when the plan holds every remote leaf that has
    /// triangles, asks for all of them now, owner by owner: every one of
    /// them will be needed (light bounces everywhere), and one merge of
    /// all of them costs less than the merges and the slow traversals of
    /// leaves arriving one by one.
    fn prefetch(&mut self) -> Result<(), EngineError> {
        let job = self.job;
        let s = &job.setup;
        if s.fetch != FetchPolicy::Fetch {
            return Ok(());
        }
        let remote: Vec<u32> = (0..s.map.owner.len() as u32)
            .filter(|&l| !self.local[l as usize] && s.leaf_tris[l as usize] > 0)
            .collect();
        let need: u64 = remote.iter().map(|&l| job.locality.held_estimate(l)).sum();
        if remote.is_empty() || need > s.plan.fetch_bytes {
            return Ok(());
        }
        let mut by_owner: Vec<Vec<u32>> = vec![Vec::new(); job.workers];
        for &l in &remote {
            by_owner[s.map.owner[l as usize] as usize].push(l);
            self.waiting.insert(l, Vec::new());
        }
        self.held += need;
        self.held_peak = self.held_peak.max(self.held);
        self.stats.fetch_requests += remote.len() as u64;
        self.prefetching = true;
        for (owner, leaves) in by_owner.into_iter().enumerate() {
            for chunk in leaves.chunks(PREFETCH_CHUNK) {
                self.outbox
                    .send(owner as WorkerId, PeerMsg::Fetch(chunk.to_vec()))?;
            }
        }
        Ok(())
    }

    /// Ships the geometry of our leaves that a peer asked for.
    fn serve(&mut self, from: WorkerId, leaves: Vec<u32>) -> Result<(), EngineError> {
        let job = self.job;
        tracing::debug!(
            job = job.setup.job,
            me = job.setup.me,
            from,
            ?leaves,
            "fetch received"
        );
        for leaf in leaves {
            let Some(ids) = job.own_ids(leaf) else {
                return Err(EngineError::NotMyLeaf { from, leaf });
            };
            let part = self
                .parts
                .iter()
                .find(|p| p.leaves.binary_search(&leaf).is_ok());
            let mut g = TriangleSet::with_capacity(ids.len());
            for &id in ids {
                let found = part.and_then(|p| Some(p.accel.triangle(p.accel.find(id)?)));
                let Some((v, m)) = found else {
                    return Err(EngineError::NotMyLeaf { from, leaf });
                };
                g.push(id, v, m);
            }
            self.stats.leaves_served += 1;
            let msg = PeerMsg::Leaf(Box::new(LeafGeometry { leaf, geometry: g }));
            self.outbox.send(from, msg)?;
        }
        Ok(())
    }

    /// Checks geometry we asked for and builds its BVH on the pool.
    fn receive_leaf<'s>(
        &mut self,
        from: WorkerId,
        bytes: u64,
        lg: LeafGeometry,
        scope: &rayon::Scope<'s>,
    ) -> Result<(), EngineError>
    where
        'a: 's,
    {
        let job = self.job;
        let leaf = lg.leaf;
        tracing::debug!(
            job = job.setup.job,
            me = job.setup.me,
            from,
            leaf,
            "leaf received"
        );
        let bad = |why| EngineError::BadLeaf { from, leaf, why };
        if job.setup.map.owner.get(leaf as usize) != Some(&from) {
            return Err(bad("the sender does not own it"));
        }
        let g = &lg.geometry;
        if !g.is_consistent() {
            return Err(bad("its lists differ in length"));
        }
        if !g.ids.is_sorted_by(|a, b| a < b) {
            return Err(bad("its triangle ids are not ascending"));
        }
        if g.len() as u64 != job.setup.leaf_tris.get(leaf as usize).copied().unwrap_or(0) as u64 {
            return Err(bad("it holds another number of triangles than the leaf"));
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
        if !self.waiting.contains_key(&leaf) {
            return Err(bad("it was not asked for"));
        }
        self.stats.fetched_leaves += 1;
        self.stats.fetched_bytes += bytes;
        self.building += 1;
        let (mag, tx) = (job.setup.magnitude, self.events.clone());
        scope.spawn(move |_| {
            let cpu0 = sys::thread_cpu_s();
            let f = FetchedLeaf::build(leaf, lg.geometry, mag);
            let _ = tx.send(Event::LeafBuilt(Arc::new(f), sys::thread_cpu_s() - cpu0));
        });
        Ok(())
    }

    /// A fetched leaf is ready: the work that waited for it resumes here.
    fn leaf_built(&mut self, f: Arc<FetchedLeaf>, cpu: f64) {
        self.building -= 1;
        self.cpu_s += cpu;
        let est = self.job.locality.held_estimate(f.leaf);
        self.held = self.held - est.min(self.held) + f.bytes();
        self.held_peak = self.held_peak.max(self.held);
        for mut w in self.waiting.remove(&f.leaf).unwrap_or_default() {
            w.pinned = Some(f.clone());
            self.work.push_back(w);
        }
        self.pending.push(f);
        self.reach_dirty = true;
        self.last_arrival = Instant::now();
    }

    /// Hands the pending leaves to the builder when they are worth a
    /// merge (see [`CROSSING_IN_BUILDS`]).
    fn maybe_merge(&mut self) {
        if self.builder.busy || self.pending.is_empty() {
            return;
        }
        let Some(tx) = &self.builder.tx else { return };
        // What the merge would build: the pending leaves and every part one
        // of them joins (see `reach::merge`).
        let mut joined = vec![false; self.parts.len()];
        let mut build: u64 = 0;
        for f in &self.pending {
            build += f.ids.len() as u64;
            let k = self
                .parts
                .iter()
                .rposition(|p| p.leaves.first().is_some_and(|&l| l <= f.leaf))
                .unwrap_or(0);
            if let Some(j) = joined.get_mut(k) {
                *j = true;
            }
        }
        build += self
            .parts
            .iter()
            .zip(&joined)
            .filter(|(_, j)| **j)
            .map(|(p, _)| p.accel.len() as u64)
            .sum::<u64>();
        let paid = self.crossings * CROSSING_IN_BUILDS;
        let prefetched = self.prefetching && self.waiting.is_empty() && self.building == 0;
        if !prefetched && paid < build && self.last_arrival.elapsed() < MERGE_AFTER {
            return;
        }
        if prefetched {
            self.prefetching = false;
        }
        for p in &self.pending {
            self.fetched_ids.insert(p.leaf, Arc::from(p.ids.as_slice()));
        }
        let r = MergeRequest {
            parts: self.parts.clone(),
            new: self.pending.clone(),
            fetched_ids: self.fetched_ids.clone(),
        };
        if tx.try_send(r).is_ok() {
            self.builder.busy = true;
            self.crossings = 0;
        }
    }

    /// New parts from the builder: the leaves it merged are local now.
    fn merged(&mut self, m: Merged) {
        self.builder.busy = false;
        self.cpu_s += m.cpu_s;
        self.parts = m.parts;
        for &l in &m.leaves {
            self.local[l as usize] = true;
        }
        self.pending.retain(|p| !m.leaves.contains(&p.leaf));
        self.stats.rebuilds += 1;
        self.stats.rebuild_s += m.secs;
        let _ = m.built;
        self.reach_dirty = true;
    }

    /// Makes the snapshot that the next batches trace.
    fn republish(&mut self) {
        let s = &self.job.setup;
        self.reach = Arc::new(Reach::new(
            &s.map.tree,
            &s.map.owner,
            &self.local,
            AccelSet::from_parts(self.parts.clone()),
            self.pending.clone(),
            s.fetch != FetchPolicy::Forward,
        ));
        self.reach_dirty = false;
    }

    fn report_stall(&self, out: usize) {
        let waiting: Vec<(u32, usize)> = self.waiting.iter().map(|(l, w)| (*l, w.len())).collect();
        tracing::warn!(
            job = self.job.setup.job,
            me = self.job.setup.me,
            pending_slots = self.slots.pending(),
            samples_open = self.slots.samples_open(),
            has_tiles = self.slots.has_tiles(),
            work = self.work.len(),
            batches_out = out,
            ?waiting,
            building = self.building,
            pending_leaves = self.pending.len(),
            merging = self.builder.busy,
            outbox_empty = self.outbox.is_empty(),
            packets_sent = ?self.outbox.sent,
            packets_received = ?self.received,
            socket = ?self.traffic.snapshot().iter().map(|t| (t.msgs_sent, t.msgs_recv)).collect::<Vec<_>>(),
            "no event for {} s with work pending",
            STALL_REPORT.as_secs()
        );
    }

    fn finish(&mut self, total: Duration, idle: Duration) -> WorkerStats {
        let mut st = std::mem::take(&mut self.stats);
        st.idle_s = idle.as_secs_f64();
        st.busy_s = (total - idle.min(total)).as_secs_f64();
        if let Some(c) = &self.job.caches {
            st.cache_memory = c.memory();
        }
        st.backpressure_stalls = self.outbox.stalls;
        st.fetch_cache_peak = self.held_peak;
        st.fetched_held_peak = self.held_peak;
        st.parts = self.parts.len() as u32;
        st.cpu_s = self.cpu_s;
        st
    }
}
