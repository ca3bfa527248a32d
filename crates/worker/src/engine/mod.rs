//! The compute side of a worker in one job: a loop on its own thread that
//! owns everything pending, traces batches of work on the rayon pool, and
//! talks to peers and the scheduler through bounded channels.
//!
//! - [`kernel`] (pool side): work items traced through the core's path
//!   kernel with this worker's tracer over its [`Reach`](crate::reach::Reach).
//! - [`slots`]: camera samples of the worker's tiles and vertices that
//!   wait for answers from other workers.
//! - [`outbox`]: ray items packed per peer, flushed by size, deadline or
//!   idleness, and held back (never blocking) when a peer is full.
//! - `queue`: the work waiting to be traced, peers' packets of queries
//!   kept as the lists their links decoded.
//! - `state`: the engine's bookkeeping (samples, batches, answers,
//!   routing); `fetching`: fetch requests, served leaves, and the builder
//!   thread that merges fetched leaves into BVH parts; `polling`: random
//!   polling, which hands the queued work of a hot region to idle peers;
//!   `tiles`: tiles asked for ahead of need and finished ones sent back
//!   in bursts.
//! - `turns`: the loop. It hands batches to the pool, two per pool
//!   thread, so that none waits for the books. In a worker of fewer than
//!   [`DEDICATED_ENGINE_THREADS`] threads the engine's own thread traces
//!   too, one batch per turn, beside a pool of the others; in a larger one
//!   the pool has every thread and the engine's only keeps the books. A
//!   worker of one thread has no pool and no hand-over at all. Everything
//!   the loop waits for (peer packets, tiles, traced batches and tiles
//!   traced whole, fetched leaves built on the pool, merged BVH parts from
//!   the builder thread) arrives as an [`Event`] on one bounded channel, so
//!   it sleeps in one place and no message can be missed between two
//!   sources.
//!
//! Work arrives as ray items from peers, tiles from the scheduler and
//! answers to this worker's own queries; a camera sample is the root of a
//! path, and a tile is done when all its samples are in. A worker that
//! holds every leaf (the scene replicated, or a farm of one) traces each
//! tile's pass whole instead, as a pool task that sums its pixels the way
//! one machine does (`kernel::trace_tile`): its samples finish where they
//! start, and a slot and a queue entry per sample cost it about 5% of its
//! render. Queues are bounded
//! by construction: a worker keeps at most `max_inflight` camera samples
//! open, each sample has at most `max_depth + 1` vertices pending and two
//! queries in flight per vertex, so the ray items in the whole farm are
//! bounded, and while any message waits for a full peer no new sample
//! starts.

mod fetching;
pub mod kernel;
pub mod outbox;
mod polling;
mod queue;
pub mod slots;
mod state;
mod tiles;
mod turns;

use crate::fetch::{FetchedLeaf, Locality};
use crate::sys;
use kernel::{Batch, TileDone, Work};
use locus_core::accel_set::Part;
use locus_core::dircache::LeafCaches;
use locus_core::irradiance::IrradianceCache;
use locus_core::path::{Answer, CacheUse, Kernel, Task};
use locus_core::region::WorkerId;
use locus_core::sampler::Sampler;
use locus_protocol::control::{JobSetup, TileAssignment, WorkerToScheduler};
use locus_protocol::packet::PacketError;
use locus_protocol::rays::{HandedSample, LeafGeometry, Packet, RayItem};
use locus_protocol::report::WorkerStats;
use locus_protocol::submit::FetchPolicy;
use outbox::LinkClosed;
use slots::UnknownSlot;
use state::Engine;
use std::sync::Arc;
use turns::turns;

/// Everything a worker holds for one job that does not change while it
/// runs: what the scheduler sent, its directional caches and its fetch
/// policy.
pub struct EngineJob {
    pub setup: JobSetup,
    pub workers: usize,
    /// One directional cache per octree leaf this worker shades in.
    pub caches: Option<LeafCaches>,
    /// The irradiance cache's records, the same on every worker.
    pub irradiance: Option<IrradianceCache>,
    pub locality: Locality,
}

impl EngineJob {
    /// The engine's job; `irradiance` is the cache its overture built.
    pub fn new(setup: JobSetup, irradiance: Option<IrradianceCache>) -> Self {
        let caches = setup.cache.map(|mut p| {
            p.max_nodes_total = p.max_nodes_total.min(setup.plan.cache_nodes as usize);
            LeafCaches::new(setup.map.tree.leaves.len(), p)
        });
        let locality = Locality::new(&setup);
        Self {
            workers: setup.peers.len(),
            setup,
            caches,
            irradiance,
            locality,
        }
    }

    /// The path kernel for this job.
    pub fn kernel(&self) -> Kernel<'_> {
        let s = &self.setup;
        Kernel {
            cache: self.caches.as_ref().map(|c| CacheUse {
                octree: &s.map.tree,
                caches: c,
            }),
            irradiance: self.irradiance.as_ref(),
            ..Kernel::exact(
                &s.materials,
                &s.lights,
                &s.camera,
                s.seed,
                s.sampler,
                s.max_depth,
            )
        }
    }

    /// Whether routes name remote leaves one by one: fetching asks for
    /// leaves by name, and so does a poller tracing handed queries.
    pub(crate) fn per_leaf(&self) -> bool {
        self.setup.fetch != FetchPolicy::Forward || self.setup.tuning.random_polling
    }

    /// Triangle ids of own leaf `leaf`.
    pub(crate) fn own_ids(&self, leaf: u32) -> Option<&[u32]> {
        let own = &self.setup.own_leaves;
        let i = own.binary_search_by_key(&leaf, |(l, _)| *l).ok()?;
        Some(&own[i].1)
    }
}

pub enum Input {
    /// A peer's packet, decoded by the reader of its link
    /// ([`Received::decode`]), or what was wrong with it.
    Packet {
        from: WorkerId,
        items: Result<Received, EngineError>,
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
    /// Random polling: a peer with nothing to trace asks for work.
    Poll {
        from: WorkerId,
    },
    /// Work a polled peer handed over.
    Handed {
        from: WorkerId,
        queries: Packet,
        samples: Vec<HandedSample>,
    },
    /// A polled peer had none to spare; these workers are idle too.
    NoWork {
        from: WorkerId,
        idle: Vec<WorkerId>,
    },
    Tile(TileAssignment),
    NoMoreTiles,
    End,
}

/// A packet's items as the reader of its link sorted them: queries to trace
/// here, as the work the engine queues and hands to its pool as it is
/// (`queue`), and answers for this worker's slots. Decoding there keeps
/// it off the engine's thread, which is serial: in a worker of 8 tracing
/// threads on the room, decoding took 17-28% of that thread's
/// instructions, and the engine fed its pool more slowly than the pool
/// traced.
#[derive(Default)]
pub struct Received {
    pub queries: Vec<Work>,
    pub answers: Vec<(u32, Answer)>,
}

impl Received {
    /// Decodes `packet` from worker `from` of a job of `workers`; path
    /// queries get the job's `seed` and `sampler`. A malformed item, or a
    /// query whose answer would go to a worker outside the job, is an
    /// error naming the sender.
    pub fn decode(
        from: WorkerId,
        packet: &Packet,
        seed: u64,
        sampler: Sampler,
        workers: usize,
    ) -> Result<Self, EngineError> {
        // Room for the items a packet of this many bytes typically holds
        // (a path query takes 59-68 bytes, a radiance answer 15-16), so
        // that decoding seldom copies what it has decoded: growing the
        // lists by doubling was about a seventh of the decoder's
        // instructions (3.3 M of 23.2 M on the room, `forward_cost.py`).
        let n = packet.len();
        let mut r = Received {
            queries: Vec::with_capacity(n / 56),
            answers: Vec::with_capacity(n / 32),
        };
        for it in packet.items(seed, sampler) {
            match it.map_err(|why| EngineError::BadPacket { from, why })? {
                RayItem::Trace { reply, .. } if reply.worker as usize >= workers => {
                    let worker = reply.worker;
                    return Err(EngineError::BadReply { from, worker });
                }
                RayItem::Trace {
                    query,
                    resume,
                    reply,
                } => r.queries.push(Work {
                    task: Task::Query(query),
                    resume,
                    reply,
                    from,
                    pinned: None,
                    handed_by: None,
                }),
                RayItem::Answer { to, answer } => r.answers.push((to, answer)),
            }
        }
        Ok(r)
    }
}

/// What the engine loop waits for.
pub enum Event {
    Input(Input),
    /// Boxed: a batch's lists are most of its size, and a batch comes
    /// back once per thousands of items.
    Traced(Box<Batch>),
    /// A tile's pass traced whole on the pool.
    Tile(TileDone),
    /// A fetched leaf's BVH, built on the pool.
    LeafBuilt(Arc<FetchedLeaf>, f64),
    /// New BVH parts with pending leaves merged, from the builder thread.
    Merged(fetching::Merged),
}

/// Where the engine's output goes.
pub struct Links {
    /// One bounded channel per peer (None for this worker itself).
    pub peers: Vec<Option<flume::Sender<crate::peers::Outgoing>>>,
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
    #[error("the scheduler sent a tile this worker cannot render: {0}")]
    BadTile(String),
    #[error("worker {from} sent a query that resumes in a leaf this worker does not hold")]
    Misrouted { from: WorkerId },
    #[error(transparent)]
    Peer(#[from] LinkClosed),
    #[error("the link to {0} closed while the job was running")]
    LinkClosed(&'static str),
    #[error("the scheduler ended the job with {0} queries still pending")]
    EndedEarly(usize),
    /// With what the engine had counted when it stopped, which the worker
    /// reports for the aborted attempt.
    #[error("the job was cancelled")]
    Cancelled(Box<WorkerStats>),
    #[error("worker {from} sent a malformed packet: {why}")]
    BadPacket { from: WorkerId, why: PacketError },
    #[error(
        "worker {from} sent a query to be answered to worker {worker}, which is not in the job"
    )]
    BadReply { from: WorkerId, worker: WorkerId },
    #[error("worker {from} handed over {what}")]
    BadHanded { from: WorkerId, what: String },
    #[error("worker {from} named worker {worker} idle, which is not in the job")]
    BadIdle { from: WorkerId, worker: WorkerId },
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
/// Largest batch the engine's own thread traces in one turn: a few
/// milliseconds, so that answers and packets keep moving.
const INLINE_BATCH: usize = 2048;
/// Smallest batch worth a pool task.
const MIN_BATCH: usize = 16;
/// Events handled per turn before the loop looks at its queues again.
const EVENTS_PER_TURN: usize = 512;
/// A worker of at least this many threads gives its pool all of them, and
/// its engine's thread only keeps the books (about 1% of a tracing
/// thread's time per thread it feeds when its rays stay local; under
/// `forward` on 16 cores, 73-89% of its time at 2 x 8 and 4 x 4 threads,
/// which `WorkerStats::engine_wait_s` shows). A thread that traced a batch of its
/// own each turn answered the pool late: on 16 cores, a worker of 16
/// threads traced at 0.8 of one machine with it.
pub const DEDICATED_ENGINE_THREADS: usize = 4;

/// The threads of a worker's tracing pool, when it has `threads` in all.
pub fn pool_threads(threads: usize) -> usize {
    if threads >= DEDICATED_ENGINE_THREADS {
        threads
    } else {
        threads.saturating_sub(1)
    }
}

/// Runs the job until the scheduler ends it; returns this worker's counters
/// (traffic bytes are added by the caller, which owns the sockets).
///
/// With a pool (a worker of more than one thread), batches go to the
/// pool's threads, two per thread and one more, so that none waits for the
/// bookkeeping, which is serial; the engine's thread traces a batch per
/// turn itself only beside a small pool ([`DEDICATED_ENGINE_THREADS`]).
pub fn run(
    job: Arc<EngineJob>,
    parts: Vec<Arc<Part>>,
    pool: Option<&rayon::ThreadPool>,
    events: (flume::Sender<Event>, flume::Receiver<Event>),
    links: Links,
) -> Result<WorkerStats, EngineError> {
    let cpu0 = sys::thread_cpu_s();
    sys::name_thread(&format!("locus-engine-{}", job.setup.me));
    let (events_tx, inbox) = events;
    let cancel = links.cancel.clone();
    let pool_n = pool.map_or(0, |p| p.current_num_threads());
    // [`pool_threads`] gives a pool of fewer than this only to workers
    // whose engine's thread traces beside it.
    let engine_traces = pool_n < DEDICATED_ENGINE_THREADS;
    let threads = pool_n + usize::from(engine_traces);
    let mut e = Engine::new(&job, parts, &events_tx, links, threads);
    drop(events_tx);
    tracing::debug!(me = job.setup.me, "engine started");
    e.prefetch()?;
    e.top_up_tiles()?;
    let result = match pool {
        // The receiver is moved into the scope and dropped when its body
        // ends (also by an error), before the scope waits for its tasks:
        // no pool task can then block on a send.
        Some(p) => {
            let threads = p.current_num_threads();
            p.in_place_scope(move |s| turns(e, inbox, &cancel, Some(s), threads, engine_traces))
        }
        None => turns(e, inbox, &cancel, None, 0, true),
    };
    result.map(|mut st| {
        st.cpu_s += sys::thread_cpu_s() - cpu0;
        st
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use locus_core::path::Query;
    use locus_core::region::Resume;
    use locus_protocol::rays::ReplyTo;

    #[test]
    fn the_engine_thread_traces_only_beside_a_small_pool() {
        assert_eq!(pool_threads(1), 0);
        assert_eq!(pool_threads(2), 1);
        assert_eq!(
            pool_threads(DEDICATED_ENGINE_THREADS - 1),
            DEDICATED_ENGINE_THREADS - 2
        );
        assert_eq!(
            pool_threads(DEDICATED_ENGINE_THREADS),
            DEDICATED_ENGINE_THREADS
        );
        assert_eq!(pool_threads(16), 16);
    }

    fn shadow(worker: WorkerId, slot: u32) -> RayItem {
        let ray = locus_core::geometry::Ray::new(glam::Vec3::ZERO, glam::Vec3::X);
        RayItem::Trace {
            query: Query::Shadow(locus_core::integrator::ShadowRay { ray, t_max: 1.0 }),
            resume: Resume::START,
            reply: ReplyTo { worker, slot },
        }
    }

    fn answer(to: u32) -> RayItem {
        RayItem::Answer {
            to,
            answer: Answer::Visible(to.is_multiple_of(2)),
        }
    }

    #[test]
    fn a_received_packet_is_sorted_in_order_and_checked_against_the_job() {
        let p = Packet::from_items(&[shadow(0, 4), answer(7), shadow(2, 5), answer(8)]);
        let r = Received::decode(1, &p, 3, Sampler::Independent, 3).unwrap();
        let replies: Vec<_> = r
            .queries
            .iter()
            .map(|w| (w.reply.worker, w.reply.slot, w.from))
            .collect();
        assert_eq!(replies, [(0, 4, 1), (2, 5, 1)]);
        let answers: Vec<_> = r.answers.iter().map(|(to, a)| (*to, *a)).collect();
        assert_eq!(
            answers,
            [(7, Answer::Visible(false)), (8, Answer::Visible(true))]
        );
        // Worker 3 is not in a job of 3: its answer would have nowhere to go.
        let e = Received::decode(1, &p, 3, Sampler::Independent, 2);
        assert!(
            matches!(e, Err(EngineError::BadReply { from: 1, worker: 2 })),
            "{:?}",
            e.err()
        );
        // The shadow query's last byte cut off.
        let whole = Packet::from_items(&[answer(7), shadow(0, 1)]);
        let short = Packet::from_bytes(whole.as_bytes()[..whole.len() - 1].to_vec());
        let e = Received::decode(1, &short, 3, Sampler::Independent, 3);
        assert!(
            matches!(e, Err(EngineError::BadPacket { from: 1, .. })),
            "{:?}",
            e.err()
        );
    }
}
