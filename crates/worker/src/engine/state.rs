//! The engine's state and its serial bookkeeping: starting camera samples,
//! applying traced batches and answers, and routing queries to peers or
//! into the wait for a fetched leaf.

use super::fetching::{Builder, MERGE_AFTER};
use super::kernel::{Batch, TileDone, Work};
use super::outbox::Outbox;
use super::polling::Polling;
use super::queue::WorkQueue;
use super::slots::{Effect, Slots, UnknownSlot};
use super::{EngineError, EngineJob, Event, Input, Links, Received};
use crate::fetch::FetchedLeaf;
use crate::reach::Reach;
use locus_core::accel_set::{AccelSet, Part};
use locus_core::integrator::PathRay;
use locus_core::path::{Answer, CacheKey, Dest, Outcome, Query, Task};
use locus_core::region::{Resume, WorkerId};
use locus_protocol::control::{TileAssignment, TileResult, WorkerToScheduler};
use locus_protocol::rays::{PeerMsg, RayItem, ReplyTo};
use locus_protocol::report::WorkerStats;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Camera samples in flight per tracing thread of a worker that traces
/// everything itself: two of the largest pool batches.
pub(super) const LOCAL_INFLIGHT_PER_THREAD: usize = 2 * super::BATCH;

/// How many items ahead an answer's slot is prefetched: far enough for
/// a load from memory to land while the items between are applied.
const AHEAD: usize = 16;

/// A worker that has heard nothing for this long while work is pending
/// says what it waits for.
pub(super) const STALL_REPORT: Duration = Duration::from_secs(5);

pub(super) struct Engine<'a> {
    pub(super) job: &'a Arc<EngineJob>,
    pub(super) control: flume::Sender<WorkerToScheduler>,
    pub(super) events: flume::Sender<Event>,
    pub(super) outbox: Outbox,
    pub(super) slots: Slots,
    pub(super) work: WorkQueue,
    pub(super) no_more_tiles: bool,
    /// The scheduler's last word on the samples it still holds, an even
    /// share of them (see [`super::tiles::window`]); None before any.
    pub(super) queue_share: Option<u64>,
    /// Tiles asked for and not yet received.
    pub(super) tiles_asked: usize,
    pub(super) stats: WorkerStats,
    pub(super) effects: Vec<Effect>,
    pub(super) children: Vec<(Dest, Query, Resume, ReplyTo)>,
    /// Batches applied and emptied, for the next ones to fill
    /// ([`Batch::spare`]): at most [`Engine::spare_batches`]. Kept in their boxes,
    /// in which they travel back as events, so a reused batch allocates
    /// nothing at all.
    #[allow(clippy::vec_box)]
    pub(super) spares: Vec<Box<Batch>>,
    pub(super) traffic: Arc<crate::peers::Traffic>,
    /// Packets received from each peer.
    pub(super) received: Vec<u64>,
    // What this worker can trace.
    pub(super) reach: Arc<Reach>,
    pub(super) parts: Vec<Arc<Part>>,
    pub(super) local: Vec<bool>,
    pub(super) pending: Vec<Arc<FetchedLeaf>>,
    pub(super) reach_dirty: bool,
    /// Work waiting for a leaf's geometry, by leaf: requested, or arrived
    /// and being built on the pool.
    pub(super) waiting: HashMap<u32, Vec<Work>>,
    pub(super) building: usize,
    /// Bytes of fetched geometry held or asked for.
    pub(super) held: u64,
    pub(super) held_peak: u64,
    pub(super) fetched_ids: HashMap<u32, Arc<[u32]>>,
    pub(super) last_arrival: Instant,
    /// Crossings of pending leaves since the last merge.
    pub(super) crossings: u64,
    /// Every remote leaf was asked for at the start; they are merged at
    /// once when the last has arrived.
    pub(super) prefetching: bool,
    pub(super) builder: Builder,
    pub(super) cpu_s: f64,
    /// The clock read once per turn of the loop: packets' ages need no
    /// finer grain than that.
    pub(super) now: Instant,
    /// Threads tracing for this engine: its own and the pool's.
    pub(super) threads: usize,
    pub(super) polling: Polling,
    /// Finished tiles not yet sent, and when the first of them finished.
    pub(super) tiles_done: Vec<TileResult>,
    pub(super) tiles_done_since: Option<Instant>,
}

impl<'a> Engine<'a> {
    /// The engine of `job` over its region's `parts`.
    pub(super) fn new(
        job: &'a Arc<EngineJob>,
        parts: Vec<Arc<Part>>,
        events_tx: &flume::Sender<Event>,
        links: Links,
        threads: usize,
    ) -> Self {
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
        let own = AccelSet::from_parts(parts.clone());
        let region_bytes = own.bytes() as u64;
        let reach = Arc::new(Reach::new(
            &s.map.tree,
            &s.map.owner,
            &s.leaf_tris,
            &local,
            own,
            Vec::new(),
            job.per_leaf(),
        ));
        let flush = Duration::from_micros(s.tuning.flush_us.max(1) as u64);
        Engine {
            job,
            control: links.control,
            events: events_tx.clone(),
            outbox: Outbox::new(links.peers, s.tuning.packet_size.max(1) as usize, flush),
            slots: Slots::new(s.me, s.job, [s.camera.width, s.camera.height, s.spp]),
            work: WorkQueue::default(),
            no_more_tiles: false,
            queue_share: None,
            tiles_asked: 0,
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
            spares: Vec::new(),
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
            threads: threads.max(1),
            polling: Polling::new(s.tuning.random_polling, job.workers, s.me, s.seed),
            tiles_done: Vec::new(),
            tiles_done_since: None,
        }
    }

    pub(super) fn control(&self, m: WorkerToScheduler) -> Result<(), EngineError> {
        self.control
            .send(m)
            .map_err(|_| EngineError::LinkClosed("the scheduler"))
    }

    /// Starts camera samples until `max_inflight` are open; a worker that
    /// traces everything itself (one worker, or the scene replicated)
    /// needs only enough to keep its threads busy, since its samples
    /// finish where they start: more would hold tiles that an idle peer
    /// could render at the end of the job (unless idle peers poll for
    /// them).
    pub(super) fn originate(&mut self) {
        let mut cap = self.job.setup.tuning.max_inflight.max(1) as usize;
        if self.reach.all_local && !self.polling.on {
            cap = cap.min(LOCAL_INFLIGHT_PER_THREAD * self.threads);
        }
        let cap = super::tiles::window(cap, self.queue_share, self.threads);
        let me = self.job.setup.me;
        let whole = self.whole_tiles();
        while self.slots.samples_open() < cap {
            // Tiles go whole where they can ([`Engine::take_whole`]); one
            // started sample by sample before (the reach grew to every
            // leaf meanwhile) finishes that way.
            if whole && !self.slots.front_started() {
                break;
            }
            let Some(n) = self.slots.start_sample() else {
                break;
            };
            self.work.push_back(Work {
                task: Task::Camera {
                    x: n.x,
                    y: n.y,
                    sample: n.sample,
                },
                resume: Resume::START,
                reply: n.reply,
                from: me,
                pinned: None,
                handed_by: None,
            });
        }
    }

    /// Whether tiles are traced whole, a pool task each ([`trace_tile`]):
    /// where this worker holds every leaf, so that its samples finish
    /// where they start, and no peer polls for them.
    ///
    /// [`trace_tile`]: super::kernel::trace_tile
    pub(super) fn whole_tiles(&self) -> bool {
        self.reach.all_local && !self.polling.on
    }

    /// The next held tile to trace whole, if tiles go whole and it has not
    /// started sample by sample.
    pub(super) fn take_whole(&mut self) -> Option<TileAssignment> {
        if self.whole_tiles() {
            self.slots.take_whole()
        } else {
            None
        }
    }

    /// Whether [`Self::take_whole`] would hand out a tile.
    pub(super) fn whole_ready(&self) -> bool {
        self.whole_tiles() && self.slots.whole_ready()
    }

    pub(super) fn input<'s>(
        &mut self,
        i: Input,
        scope: Option<&rayon::Scope<'s>>,
    ) -> Result<(), EngineError>
    where
        'a: 's,
    {
        match i {
            Input::Packet { from, items } => {
                if let Some(r) = self.received.get_mut(from as usize) {
                    *r += 1;
                }
                let Received { queries, answers } = items?;
                self.stats.queries_in += queries.len() as u64;
                // Peers' queries go first (see `queue`).
                self.work.push_list(queries);
                // Each answer's slot is fetched from memory a few answers
                // ahead (answers arrive for slots at random), and what it
                // will write next half as far ahead.
                for i in 0..answers.len() {
                    if let Some(&(to, _)) = answers.get(i + AHEAD) {
                        self.slots.prefetch(to);
                    }
                    if let Some(&(to, _)) = answers.get(i + AHEAD / 2) {
                        self.slots.prefetch_next(to);
                    }
                    let (to, answer) = answers[i];
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
            Input::Fetch { from, leaves } => self.serve(from, leaves)?,
            Input::Poll { from } => self.polled(from)?,
            Input::Handed {
                from,
                queries,
                samples,
            } => self.handed(from, queries, samples)?,
            Input::NoWork { from, idle } => self.no_work(from, idle)?,
            Input::Leaf { from, bytes, leaf } => self.receive_leaf(from, bytes, *leaf, scope)?,
            Input::Tile(a) => {
                self.tiles_asked = self.tiles_asked.saturating_sub(1);
                self.queue_share = Some(a.queue_share);
                if let Some(empty) = self.slots.add_tile(a).map_err(EngineError::BadTile)? {
                    self.tile_done(empty)?;
                }
            }
            Input::NoMoreTiles => {
                self.no_more_tiles = true;
                self.queue_share = Some(0);
            }
            Input::End => unreachable!("handled by the loop"),
        }
        Ok(())
    }

    /// Takes in a tile's pass traced whole.
    pub(super) fn apply_tile(&mut self, t: TileDone) -> Result<(), EngineError> {
        self.stats.trace += t.stats;
        self.cpu_s += t.cpu_s;
        self.stats.whole_tiles += 1;
        self.slots.whole_done();
        self.tile_done(t.tile)
    }

    /// Applies a traced batch.
    pub(super) fn apply(&mut self, b: Box<Batch>) -> Result<(), EngineError> {
        self.apply_items(&b)?;
        if self.spares.len() < self.spare_batches() {
            self.spares.push(b.spare());
        }
        Ok(())
    }

    /// How many emptied batches to keep: as many as the pool has out at
    /// once (two a thread, and one), so that reuse never holds more than
    /// the batches in flight held. Each keeps the room its largest fill
    /// grew to: a few megabytes at [`super::BATCH`] items (248 bytes a
    /// chain vertex, 112 an item).
    fn spare_batches(&self) -> usize {
        2 * self.threads + 1
    }

    fn apply_items(&mut self, b: &Batch) -> Result<(), EngineError> {
        if let Some(from) = b.misrouted {
            return Err(EngineError::Misrouted { from });
        }
        self.stats.trace += b.stats;
        self.stats.fetched_leaf_traces += b.fetched_leaf_traces;
        self.crossings += b.fetched_leaf_traces;
        self.cpu_s += b.cpu_s;
        self.stats.forwarded_out += b.sends.forwards.total();
        self.stats.forwards += b.sends.forwards;
        self.stats.answers_out += b.sends.answers;
        for (to, packet, n) in &b.sends.full {
            self.outbox.push_encoded(*to, packet, *n, self.now)?;
        }
        for (to, (packet, n)) in b.sends.open.iter().enumerate() {
            if *n > 0 {
                self.outbox
                    .push_encoded(to as WorkerId, packet, *n, self.now)?;
            }
        }
        let me = self.job.setup.me;
        // As for a packet's answers: slots a few items ahead.
        let mine = |i: usize| match b.items.get(i) {
            Some((r, Outcome::Answer(_), _)) if r.worker == me => Some(r.slot),
            _ => None,
        };
        for i in 0..b.items.len() {
            if let Some(slot) = mine(i + AHEAD) {
                self.slots.prefetch(slot);
            }
            if let Some(slot) = mine(i + AHEAD / 2) {
                self.slots.prefetch_next(slot);
            }
            let (reply, o, handed_by) = b.items[i];
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
                } => self.route(dest, query, resume, reply, handed_by)?,
                Outcome::Chain { start, end } => {
                    let mut children = std::mem::take(&mut self.children);
                    self.slots.open_chain(
                        reply,
                        &b.chain[start as usize..end as usize],
                        &mut children,
                    );
                    for (dest, query, resume, r) in children.drain(..) {
                        self.route(dest, query, resume, r, None)?;
                    }
                    self.children = children;
                }
            }
        }
        Ok(())
    }

    pub(super) fn reply(&mut self, to: ReplyTo, answer: Answer) -> Result<(), EngineError> {
        self.stats.answers_out += 1;
        let item = RayItem::Answer {
            to: to.slot,
            answer,
        };
        Ok(self.outbox.push(to.worker, item, self.now)?)
    }

    /// Carries out what answers set off.
    pub(super) fn effects(&mut self) -> Result<(), EngineError> {
        // A cache's answer to a segment finishes its vertex, which may set
        // off more: until none is left.
        while !self.effects.is_empty() {
            let mut fx = std::mem::take(&mut self.effects);
            for f in fx.drain(..) {
                match f {
                    Effect::Reply(to, a) => self.reply(to, a)?,
                    Effect::CacheUpdate((leaf, dir), v) => {
                        if let Some(c) = &self.job.caches {
                            c.update(leaf, dir, v);
                        }
                    }
                    Effect::TileDone(r) => self.tile_done(r)?,
                    Effect::Beyond { slot, key, ray } => self.beyond(slot, key, ray)?,
                }
            }
            if self.effects.is_empty() {
                self.effects = fx;
            }
        }
        Ok(())
    }

    /// A vertex's segment query got beyond its perimeter: its leaf's cache
    /// answers, or the rest of the ray is traced from the perimeter here
    /// (forwarded on as needed) and its radiance updates the cache, exactly
    /// as [`locus_core::path::Kernel`] does when the whole sphere is local.
    fn beyond(&mut self, slot: u32, key: CacheKey, ray: PathRay) -> Result<(), EngineError> {
        let me = self.job.setup.me;
        let Some(c) = &self.job.caches else {
            return Err(UnknownSlot { from: me, slot }.into());
        };
        let st = &mut self.stats.trace;
        if let Some(v) = c.at_perimeter(key.0, key.1, &mut st.cache) {
            let answer = Answer::Radiance(v);
            return Ok(self.slots.answer(me, slot, answer, &mut self.effects, st)?);
        }
        self.slots.expect_update(slot, key);
        self.work.push_front(Work {
            task: Task::Query(Query::Path(ray)),
            resume: Resume::at(ray.emit_within),
            reply: ReplyTo { worker: me, slot },
            from: me,
            pinned: None,
            handed_by: None,
        });
        Ok(())
    }

    /// Sends a query on: to a peer, or into the wait for a leaf (with the
    /// peer that handed it over, whose leaves it goes on fetching).
    pub(super) fn route(
        &mut self,
        dest: Dest,
        query: Query,
        resume: Resume,
        reply: ReplyTo,
        handed_by: Option<WorkerId>,
    ) -> Result<(), EngineError> {
        let job = self.job;
        let leaf = match dest {
            Dest::Peer(to) => {
                self.stats.forwarded_out += 1;
                self.stats.forwards.count(&query);
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
            handed_by,
        };
        let l = leaf as usize;
        if self.local.get(l) == Some(&true) || self.pending.iter().any(|p| p.leaf == leaf) {
            // It arrived while this query was being traced.
            self.work.push_front(w);
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
            return self.route(Dest::Peer(owner), query, resume, reply, None);
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

    /// How long the loop may sleep when it has nothing to trace: until
    /// the oldest packet is due, a stalled peer may have room, or pending
    /// leaves are due for a merge.
    pub(super) fn wait_bound(&self, now: Instant) -> Duration {
        if self.outbox.is_stalled() {
            return Duration::from_millis(1);
        }
        let mut w = Duration::from_millis(100);
        if let Some(d) = self.outbox.next_deadline() {
            w = w.min(d.saturating_duration_since(now));
        }
        if !self.pending.is_empty() && !self.builder.busy {
            w = w.min((self.last_arrival + MERGE_AFTER).saturating_duration_since(now));
        }
        if let Some(p) = self.polling.wake(now) {
            w = w.min(p);
        }
        if let Some(t) = self.tiles_done_since {
            w = w.min((t + super::tiles::TILES_DONE_HOLD).saturating_duration_since(now));
        }
        w
    }

    pub(super) fn report_stall(&self, out: usize) {
        let waiting: Vec<(u32, usize)> = self.waiting.iter().map(|(l, w)| (*l, w.len())).collect();
        tracing::warn!(
            job = self.job.setup.job,
            me = self.job.setup.me,
            pending_slots = self.slots.pending(),
            samples_open = self.slots.samples_open(),
            has_tiles = self.slots.has_tiles(),
            no_more_tiles = self.no_more_tiles,
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
            "no event for {} s (a stall only if something is pending or no_more_tiles is false: else this worker is done and waits for the job's end)",
            STALL_REPORT.as_secs()
        );
    }

    pub(super) fn finish(
        &mut self,
        total: Duration,
        idle: Duration,
        waited: Duration,
    ) -> WorkerStats {
        let mut st = std::mem::take(&mut self.stats);
        st.idle_s = idle.as_secs_f64();
        st.engine_wait_s = waited.as_secs_f64();
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
