//! The pool side of the engine: batches of work items traced through the
//! core's path kernel ([`locus_core::path::Kernel`]) with this worker's
//! [`Tracer`], which traces what the worker's [`Reach`] holds and says
//! where everything else must go.

use super::EngineJob;
use crate::fetch::FetchedLeaf;
use crate::reach::{Label, Reach};
use crate::sys;
use locus_core::geometry::Ray;
use locus_core::path::{ChainVertex, Dest, Outcome, RayKind, Task, Traced, Tracer, WholeScene};
use locus_core::region::{Known, Resume, RunEnd, WorkerId, trace_local};
use locus_core::render::pixel_pass;
use locus_core::stats::TraceStats;
use locus_protocol::control::{TileAssignment, TileResult};
use locus_protocol::rays::{Packet, RayItem, ReplyTo};
use locus_protocol::report::ForwardKinds;
use std::cell::Cell;
use std::sync::Arc;

/// One item of work: what to trace, where on the ray to resume, and where
/// its answer goes.
pub struct Work {
    pub task: Task,
    pub resume: Resume,
    pub reply: ReplyTo,
    /// The worker it came from (this one for local work), for errors.
    pub from: WorkerId,
    /// The fetched leaf this work waited for, held so that it is traced
    /// here even by a batch whose snapshot predates the leaf.
    pub pinned: Option<Arc<FetchedLeaf>>,
    /// The peer that handed this query over by random polling: its leaves
    /// are fetched here, not forwarded back to it.
    pub handed_by: Option<WorkerId>,
}

/// What a traced batch hands back to the engine.
pub struct Batch {
    /// Per item: where its answer goes, how it ended here, and the peer
    /// that handed it over (whose leaves it goes on fetching).
    pub items: Vec<(ReplyTo, Outcome, Option<WorkerId>)>,
    /// The vertices `Outcome::Chain` ranges point into.
    pub chain: Vec<ChainVertex>,
    pub stats: TraceStats,
    pub fetched_leaf_traces: u64,
    pub cpu_s: f64,
    /// A query from a peer that did not start in a leaf this worker holds:
    /// the peer computed another processor vector, or the item was
    /// corrupted.
    pub misrouted: Option<WorkerId>,
    /// Queries forwarded to peers and answers to their queries, encoded
    /// here; their items are not in `items`.
    pub sends: Sends,
}

/// What tracing a tile's pass whole hands back ([`trace_tile`]): the
/// tile's sums, with no items, chains or sends, since nothing of it left
/// this worker.
pub struct TileDone {
    pub tile: TileResult,
    pub stats: TraceStats,
    pub cpu_s: f64,
}

impl Batch {
    /// An empty batch with room for `items` items: `spare` emptied where
    /// there is one (a batch applied earlier, [`Batch::spare`]), else a new
    /// one. A batch's chain outgrows its items (a path traced here leaves
    /// a vertex waiting for each ray it forwards), and each growth copies
    /// the whole chain: taking a spare keeps the room an earlier batch grew
    /// to.
    fn new(job: &EngineJob, items: usize, spare: Option<Box<Batch>>) -> Box<Self> {
        let Some(mut b) = spare else {
            return Box::new(Self {
                items: Vec::with_capacity(items),
                chain: Vec::with_capacity(items),
                stats: TraceStats::default(),
                fetched_leaf_traces: 0,
                cpu_s: 0.0,
                misrouted: None,
                sends: Sends::new(job.workers, job.setup.tuning.packet_size as usize),
            });
        };
        b.items.reserve(items);
        b.chain.reserve(items);
        b
    }

    /// This batch emptied, its vectors' room kept, once the engine has
    /// applied it: for [`trace_batch`] to fill again.
    pub fn spare(mut self: Box<Self>) -> Box<Self> {
        self.items.clear();
        self.chain.clear();
        self.stats = TraceStats::default();
        self.fetched_leaf_traces = 0;
        self.cpu_s = 0.0;
        self.misrouted = None;
        self.sends.clear();
        self
    }
}

/// Ray items for peers, encoded on the pool thread that traced them, so
/// that the engine's thread, which is serial, only appends bytes to its
/// outbox: in a worker of 8 tracing threads, encoding and routing them
/// took 19-20% of that thread's instructions.
#[derive(Default)]
pub struct Sends {
    /// Per peer: the items encoded since its last full packet, and how
    /// many.
    pub open: Vec<(Packet, usize)>,
    /// Packets of `limit` items, in the order they filled.
    pub full: Vec<(WorkerId, Packet, usize)>,
    /// Queries forwarded (by kind), and answers sent.
    pub forwards: ForwardKinds,
    pub answers: u64,
    limit: usize,
}

impl Sends {
    /// For a job of `workers`, whose packets hold `limit` items.
    pub fn new(workers: usize, limit: usize) -> Self {
        Self {
            open: (0..workers).map(|_| (Packet::default(), 0)).collect(),
            limit: limit.max(1),
            ..Self::default()
        }
    }

    /// Empty, its open packets' room kept (full packets were handed on).
    fn clear(&mut self) {
        for (p, n) in &mut self.open {
            p.clear();
            *n = 0;
        }
        self.full.clear();
        self.forwards = ForwardKinds::default();
        self.answers = 0;
    }

    fn push(&mut self, to: WorkerId, item: &RayItem) {
        let (p, n) = &mut self.open[to as usize];
        p.push(item);
        *n += 1;
        if *n >= self.limit {
            self.full.push((to, std::mem::take(p), std::mem::take(n)));
        }
    }
}

/// This worker's tracer for one work item.
struct ItemTracer<'a> {
    job: &'a EngineJob,
    reach: &'a Reach,
    pinned: Option<&'a Arc<FetchedLeaf>>,
    handed_by: Option<WorkerId>,
    fetched_traces: Cell<u64>,
}

impl ItemTracer<'_> {
    /// Traces fetched leaf `f` over `[ta, tb)`.
    fn trace_leaf(
        &self,
        f: &FetchedLeaf,
        ray: &Ray,
        ta: f32,
        tb: f32,
        any: bool,
        st: &mut TraceStats,
    ) -> Option<Traced> {
        self.fetched_traces.set(self.fetched_traces.get() + 1);
        if any {
            f.accel
                .occluded(ray, ta, tb, st)
                .then_some(Traced::Occluded)
        } else {
            f.accel
                .closest(ray, ta, tb, st)
                .map(|h| Traced::Hit(f.accel.surface(&h)))
        }
    }
}

impl Tracer for ItemTracer<'_> {
    fn trace(
        &self,
        ray: &Ray,
        t_max: f32,
        resume: Resume,
        any: bool,
        kind: RayKind,
        st: &mut TraceStats,
    ) -> Traced {
        let reach = self.reach;
        if reach.all_local {
            let t0 = resume.at.max(0.0);
            return if any {
                if reach.accel.occluded(ray, t0, t_max, st) {
                    Traced::Occluded
                } else {
                    Traced::Miss
                }
            } else {
                match reach.accel.closest(ray, t0, t_max, st) {
                    Some(h) => Traced::Hit(reach.accel.surface(&h)),
                    None => Traced::Miss,
                }
            };
        }
        let mut known = Known::Unknown;
        let mut resume = resume;
        loop {
            let end = trace_local(
                &reach.route,
                |l| l == Label::Local,
                &reach.accel,
                ray,
                t_max,
                resume,
                any,
                &mut known,
                st,
            );
            let (label, ta, tb) = match end {
                RunEnd::Hit(h) => return Traced::Hit(reach.accel.surface(&h)),
                RunEnd::Occluded => return Traced::Occluded,
                RunEnd::Miss => return Traced::Miss,
                RunEnd::Foreign { label, ta, tb } => (label, ta, tb),
            };
            match label {
                Label::Pending(i) => {
                    let f = &reach.pending[i as usize];
                    if let Some(t) = self.trace_leaf(f, ray, ta, tb, any, st) {
                        return t;
                    }
                    resume = Resume::at(tb);
                }
                Label::Remote { owner, leaf } => {
                    if let Some(p) = self.pinned.filter(|p| p.leaf == leaf) {
                        if let Some(t) = self.trace_leaf(p, ray, ta, tb, any, st) {
                            return t;
                        }
                        resume = Resume::at(tb);
                    } else if leaf != u32::MAX
                        && if self.handed_by == Some(owner) {
                            self.job.locality.may_fetch(leaf)
                        } else {
                            self.job.locality.wants_fetch(leaf, kind)
                        }
                    {
                        // Traced here once the leaf has come: nothing of it
                        // is in the BVH parts meanwhile.
                        return Traced::Next(Dest::Leaf(leaf), Resume::at(ta));
                    } else {
                        // The owner holds the whole route node.
                        return Traced::Next(Dest::Peer(owner), Resume::within(ta, tb));
                    }
                }
                Label::Local => unreachable!("trace_local stops only at foreign leaves"),
            }
        }
    }
}

/// Traces a batch of work through `reach`, into `spare` where the engine
/// had one ([`Batch::spare`]).
pub fn trace_batch(
    job: &EngineJob,
    reach: &Reach,
    work: impl ExactSizeIterator<Item = Work>,
    spare: Option<Box<Batch>>,
) -> Box<Batch> {
    let cpu0 = sys::thread_cpu_s();
    let kernel = job.kernel();
    let me = job.setup.me;
    let mut b = Batch::new(job, work.len(), spare);
    for w in work {
        let tracer = ItemTracer {
            job,
            reach,
            pinned: w.pinned.as_ref(),
            handed_by: w.handed_by,
            fetched_traces: Cell::new(0),
        };
        let o = kernel.process(&tracer, w.task, w.resume, &mut b.chain, &mut b.stats);
        b.fetched_leaf_traces += tracer.fetched_traces.get();
        if let Outcome::Forward { resume, .. } = o
            && resume.at == w.resume.at
            && w.from != me
            && w.handed_by.is_none()
        {
            // The sender computed the same processor vector; a query that
            // does not start in a leaf of ours was corrupted or misrouted.
            // (A handed query starts in its hander's leaves.)
            b.misrouted = Some(w.from);
        }
        match o {
            Outcome::Forward {
                dest: Dest::Peer(to),
                query,
                resume,
            } if to != me => {
                b.sends.forwards.count(&query);
                let reply = w.reply;
                b.sends.push(
                    to,
                    &RayItem::Trace {
                        query,
                        resume,
                        reply,
                    },
                );
            }
            // The reader checked that `reply` names a worker of the job.
            Outcome::Answer(answer) if w.reply.worker != me => {
                b.sends.answers += 1;
                let to = w.reply.slot;
                b.sends
                    .push(w.reply.worker, &RayItem::Answer { to, answer });
            }
            o => b.items.push((w.reply, o, w.handed_by)),
        }
    }
    b.cpu_s = sys::thread_cpu_s() - cpu0;
    b
}

/// Traces the pass of tile `a` whole, on a worker whose reach holds every
/// leaf: each pixel's samples through the core's [`pixel_pass`] with one
/// machine's tracer over this worker's BVH parts, so the sums are one
/// machine's by construction. No sample takes a slot or goes through the
/// engine's books, which cost a replicated worker about 1,000
/// instructions a camera sample (5% of the room's render, counted by
/// `forward_cost.py --fetch fetch`).
pub fn trace_tile(job: &EngineJob, reach: &Reach, a: TileAssignment) -> TileDone {
    debug_assert!(
        reach.all_local,
        "a tile is traced whole only where every leaf is local"
    );
    let cpu0 = sys::thread_cpu_s();
    let mut stats = TraceStats::default();
    // A BVH of one part is traced as one machine traces its BVH: the set's
    // tracer, called for every ray, stays out of line (570.6 M against
    // 559.5 M instructions, 2.0% of the room's render at 96x72, 4 spp:
    // `forward_cost.py --fetch fetch`).
    let sums = match reach.accel.parts() {
        [p] => tile_sums(job, &WholeScene(&p.accel), &a, &mut stats),
        _ => tile_sums(job, &WholeScene(&reach.accel), &a, &mut stats),
    };
    TileDone {
        tile: TileResult {
            job: job.setup.job,
            tile: a.tile,
            pass: a.pass,
            sums,
        },
        stats,
        cpu_s: sys::thread_cpu_s() - cpu0,
    }
}

/// The pass sums of tile `a`'s pixels, in rows.
fn tile_sums<T: Tracer>(
    job: &EngineJob,
    tracer: &T,
    a: &TileAssignment,
    st: &mut TraceStats,
) -> Vec<locus_core::passes::Moments> {
    let kernel = job.kernel();
    let mut chain = Vec::new();
    (0..a.pixels())
        .map(|p| {
            pixel_pass(
                &kernel,
                tracer,
                a.pixel(p),
                a.pixel_samples(p),
                &mut chain,
                st,
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use locus_core::path::Answer;

    fn answers(p: &Packet) -> Vec<u32> {
        p.items(0, locus_core::sampler::Sampler::Independent)
            .map(|i| match i {
                Ok(RayItem::Answer { to, .. }) => to,
                other => panic!("{other:?}"),
            })
            .collect()
    }

    #[test]
    fn sends_fill_packets_per_peer_in_order() {
        let mut s = Sends::new(3, 2);
        for (to, k) in [
            (1, 10),
            (2, 20),
            (1, 11),
            (1, 12),
            (2, 21),
            (1, 13),
            (1, 14),
        ] {
            let answer = Answer::Visible(true);
            s.push(to, &RayItem::Answer { to: k, answer });
        }
        let full: Vec<_> = s
            .full
            .iter()
            .map(|(to, p, n)| (*to, answers(p), *n))
            .collect();
        assert_eq!(
            full,
            [
                (1, vec![10, 11], 2),
                (2, vec![20, 21], 2),
                (1, vec![12, 13], 2)
            ]
        );
        let open: Vec<_> = s.open.iter().map(|(p, n)| (answers(p), *n)).collect();
        assert_eq!(open, [(vec![], 0), (vec![14], 1), (vec![], 0)]);
    }

    /// A batch handed back for reuse holds nothing of what it carried (no
    /// item, vertex, packet or count would reach the next batch's engine
    /// twice) and keeps the room its vectors grew to.
    #[test]
    fn a_spare_batch_is_empty_and_keeps_its_room() {
        let answer = Answer::Visible(true);
        let reply = ReplyTo { worker: 0, slot: 7 };
        let vertex = ChainVertex {
            vertex: locus_core::integrator::ShadedVertex {
                emitted: glam::Vec3::ZERO,
                nee: glam::Vec3::ZERO,
                scale: glam::Vec3::ONE,
            },
            shadow: locus_core::path::Child::Done(true),
            next: locus_core::path::Child::Deeper,
            update: None,
        };
        let mut sends = Sends::new(2, 2);
        for k in 0..3 {
            sends.push(1, &RayItem::Answer { to: k, answer });
        }
        sends.answers = 3;
        sends.forwards.shadow = 2;
        let b = Box::new(Batch {
            items: vec![(reply, Outcome::Answer(answer), None); 100],
            chain: vec![vertex; 300],
            stats: TraceStats {
                camera_rays: 5,
                ..Default::default()
            },
            fetched_leaf_traces: 4,
            cpu_s: 1.5,
            misrouted: Some(1),
            sends,
        });
        let s = b.spare();
        assert!(s.items.is_empty() && s.items.capacity() >= 100);
        assert!(s.chain.is_empty() && s.chain.capacity() >= 300);
        assert_eq!(s.stats, TraceStats::default());
        assert_eq!(
            (s.fetched_leaf_traces, s.cpu_s, s.misrouted),
            (0, 0.0, None)
        );
        assert!(s.sends.full.is_empty());
        assert!(s.sends.open.iter().all(|(p, n)| p.is_empty() && *n == 0));
        assert_eq!(s.sends.open.len(), 2);
        assert_eq!((s.sends.answers, s.sends.forwards.total()), (0, 0));
        // It fills its packets as a new one does.
        let mut s = s;
        for k in 10..13 {
            s.sends.push(1, &RayItem::Answer { to: k, answer });
        }
        assert_eq!(answers(&s.sends.full[0].1), [10, 11]);
        assert_eq!(answers(&s.sends.open[1].0), [12]);
    }
}
