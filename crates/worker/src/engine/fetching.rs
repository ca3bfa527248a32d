//! Fetching and merging: a worker's requests for remote leaves, the
//! leaves it serves, and the builder thread that merges fetched leaves into
//! its BVH parts so that they cost no more than its own region.

use super::state::Engine;
use super::{EngineError, EngineJob, Event};
use crate::fetch::FetchedLeaf;
use crate::reach::{LeafSource, Reach, cut_run, merge, merge_target};
use crate::sys;
use locus_core::accel_set::{AccelSet, MAX_PARTS, Part};
use locus_core::region::WorkerId;
use locus_protocol::control::TriangleSet;
use locus_protocol::rays::{LeafGeometry, PeerMsg};
use locus_protocol::submit::FetchPolicy;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Rent or buy for merging: a ray crossing a leaf that waits to be merged
/// costs about this many triangle builds more than crossing merged geometry
/// (its own BVH, an extra step of the route walk); merging rebuilds the
/// parts the leaves join. Pending leaves are merged once their crossings
/// since the last merge have cost as much as that rebuild, which keeps the
/// total at most twice the best choice made in hindsight.
pub(super) const CROSSING_IN_BUILDS: u64 = 1;
/// Leaves waiting longer than this are merged whatever their crossings, so
/// that a job's end does not leave fetched leaves on the slow path.
pub(super) const MERGE_AFTER: Duration = Duration::from_millis(500);
/// Leaves per request when a worker asks for many at once.
const PREFETCH_CHUNK: usize = 64;

/// New parts from the builder, and the leaves now in them.
pub struct Merged {
    pub(super) parts: Vec<Arc<Part>>,
    pub(super) leaves: Vec<u32>,
    pub(super) built: usize,
    pub(super) secs: f64,
    pub(super) cpu_s: f64,
}

/// The builder thread: merges pending leaves into BVH parts off the
/// engine's thread, one merge at a time.
pub(super) struct Builder {
    pub(super) tx: Option<flume::Sender<MergeRequest>>,
    pub(super) busy: bool,
}

pub(super) struct MergeRequest {
    parts: Vec<Arc<Part>>,
    new: Vec<Arc<FetchedLeaf>>,
    fetched_ids: HashMap<u32, Arc<[u32]>>,
}

impl Builder {
    pub(super) fn spawn(job: Arc<EngineJob>, events: flume::Sender<Event>) -> Self {
        let (tx, rx) = flume::bounded::<MergeRequest>(1);
        let spawned = std::thread::Builder::new()
            .name("locus-build".into())
            .spawn(move || {
                // Merges build on this thread alone: BVH builds run in
                // parallel where a rayon pool has threads (obvhs's
                // `parallel` feature), but here the tracing threads are
                // busy, the merge's memory plan is for one build, and
                // its CPU seconds are this thread's. A pool of this one
                // thread keeps the build here.
                let _alone = sys::this_thread_alone();
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

/// Rebuilds every part a merge may build ([`Part::mergeable`]) into parts
/// of at most `max_part` triangles; the others are kept.
fn merge_all(
    parts: &[Arc<Part>],
    ids: &dyn Fn(u32) -> Option<Arc<[u32]>>,
    max_part: usize,
    magnitude: f32,
) -> (Vec<Arc<Part>>, usize) {
    let (mut out, rebuilt): (Vec<Arc<Part>>, Vec<Arc<Part>>) =
        parts.iter().cloned().partition(|p| !p.mergeable);
    let mut built = 0;
    for chunk in rebuilt.chunks(2) {
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

impl<'a> Engine<'a> {
    /// Under `fetch`, when the plan holds every remote leaf that has
    /// triangles, asks for all of them now, owner by owner: every one of
    /// them will be needed (light bounces everywhere), and one merge of
    /// all of them costs less than the merges and the slow traversals of
    /// leaves arriving one by one.
    pub(super) fn prefetch(&mut self) -> Result<(), EngineError> {
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
    pub(super) fn serve(&mut self, from: WorkerId, leaves: Vec<u32>) -> Result<(), EngineError> {
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
                let found = part.and_then(|p| {
                    let prim = p.accel.find(id)?;
                    let (v, m) = p.accel.triangle(prim);
                    Some((v, m, p.accel.shading(prim)))
                });
                let Some((v, m, n)) = found else {
                    return Err(EngineError::NotMyLeaf { from, leaf });
                };
                g.push(id, v, m, n);
            }
            self.stats.leaves_served += 1;
            let msg = PeerMsg::Leaf(Box::new(LeafGeometry { leaf, geometry: g }));
            self.outbox.send(from, msg)?;
        }
        Ok(())
    }

    /// Checks geometry we asked for and builds its BVH on the pool.
    pub(super) fn receive_leaf<'s>(
        &mut self,
        from: WorkerId,
        bytes: u64,
        lg: LeafGeometry,
        scope: Option<&rayon::Scope<'s>>,
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
        if !g.normals.is_empty() && !job.setup.normals {
            return Err(bad(
                "it carries shading normals, which the job's scene has none of",
            ));
        }
        if g.normals.iter().flatten().any(|n| !n.is_finite()) {
            return Err(bad("it has a non-finite shading normal"));
        }
        if !self.waiting.contains_key(&leaf) {
            return Err(bad("it was not asked for"));
        }
        self.stats.fetched_leaves += 1;
        self.stats.fetched_bytes += bytes;
        self.building += 1;
        let (mag, tx) = (job.setup.magnitude, self.events.clone());
        let build = move || {
            let cpu0 = sys::thread_cpu_s();
            let f = FetchedLeaf::build(leaf, lg.geometry, mag);
            (Arc::new(f), sys::thread_cpu_s() - cpu0)
        };
        match scope {
            Some(scope) => scope.spawn(move |_| {
                let (f, cpu) = build();
                let _ = tx.send(Event::LeafBuilt(f, cpu));
            }),
            // No pool: this thread builds it (a leaf is small).
            None => {
                let (f, cpu) = build();
                self.leaf_built(f, cpu);
            }
        }
        Ok(())
    }

    /// A fetched leaf is ready: the work that waited for it resumes here.
    pub(super) fn leaf_built(&mut self, f: Arc<FetchedLeaf>, cpu: f64) {
        self.building -= 1;
        self.cpu_s += cpu;
        let est = self.job.locality.held_estimate(f.leaf);
        self.held = self.held - est.min(self.held) + f.bytes();
        self.held_peak = self.held_peak.max(self.held);
        for mut w in self.waiting.remove(&f.leaf).unwrap_or_default() {
            w.pinned = Some(f.clone());
            self.work.push_front(w);
        }
        self.pending.push(f);
        self.reach_dirty = true;
        self.last_arrival = Instant::now();
    }

    /// Hands the pending leaves to the builder when they are worth a
    /// merge (see [`CROSSING_IN_BUILDS`]).
    pub(super) fn maybe_merge(&mut self) {
        if self.builder.busy || self.pending.is_empty() {
            return;
        }
        let Some(tx) = &self.builder.tx else { return };
        // What the merge would build: the pending leaves and every part one
        // of them joins (see `reach::merge`). Under a memory budget a merge
        // builds at most about one part, the build the plan reserves room
        // for (the old parts stay alive until the new ones replace them):
        // the leaves that would build more wait for the next merge.
        let budgeted = self.job.setup.plan.budget > 0;
        let most = self.job.setup.plan.part_triangles.max(1) as u64;
        let mut joined = vec![false; self.parts.len()];
        let mut build: u64 = 0;
        let mut chosen = vec![false; self.pending.len()];
        let mut take = 0;
        for (i, f) in self.pending.iter().enumerate() {
            // The part it joins, counted once; a leaf without one builds
            // itself alone.
            let k = merge_target(&self.parts, f.leaf).filter(|&k| !joined[k]);
            let more = f.ids.len() as u64 + k.map_or(0, |k| self.parts[k].accel.len() as u64);
            if budgeted && take > 0 && build + more > most {
                continue;
            }
            build += more;
            if let Some(k) = k {
                joined[k] = true;
            }
            chosen[i] = true;
            take += 1;
        }
        let paid = self.crossings * CROSSING_IN_BUILDS;
        let prefetched = self.prefetching && self.waiting.is_empty() && self.building == 0;
        if !prefetched && paid < build && self.last_arrival.elapsed() < MERGE_AFTER {
            return;
        }
        if prefetched {
            self.prefetching = false;
        }
        let new: Vec<Arc<FetchedLeaf>> = self
            .pending
            .iter()
            .zip(&chosen)
            .filter(|(_, c)| **c)
            .map(|(f, _)| f.clone())
            .collect();
        for p in &new {
            self.fetched_ids.insert(p.leaf, Arc::from(p.ids.as_slice()));
        }
        let r = MergeRequest {
            parts: self.parts.clone(),
            new,
            fetched_ids: self.fetched_ids.clone(),
        };
        if tx.try_send(r).is_ok() {
            self.builder.busy = true;
            self.crossings = 0;
        }
    }

    /// New parts from the builder: the leaves it merged are local now.
    pub(super) fn merged(&mut self, m: Merged) {
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
    pub(super) fn republish(&mut self) {
        let s = &self.job.setup;
        self.reach = Arc::new(Reach::new(
            &s.map.tree,
            &s.map.owner,
            &s.leaf_tris,
            &self.local,
            AccelSet::from_parts(self.parts.clone()),
            self.pending.clone(),
            self.job.per_leaf(),
        ));
        self.reach_dirty = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    /// The distinct threads that ran a parallel loop, and whether the
    /// calling thread was one of them.
    fn threads_of_a_loop() -> (usize, bool) {
        let ids: std::collections::HashSet<std::thread::ThreadId> = (0..10_000u32)
            .into_par_iter()
            .map(|i| {
                // Enough work per item for idle threads to steal some.
                std::hint::black_box((0..2_000u32).fold(i, |a, b| a ^ b.wrapping_mul(a)));
                std::thread::current().id()
            })
            .collect();
        (ids.len(), ids.contains(&std::thread::current().id()))
    }

    /// Parallel work started on a thread that made `this_thread_alone`
    /// runs on that thread only: what keeps a merge's build, and its CPU
    /// seconds, on the builder thread. Asked again on the same thread (a
    /// tokio blocking thread building a second region part), it makes no
    /// second pool and the work still stays. In a pool of three, the same
    /// loop spreads.
    #[test]
    fn work_stays_on_the_thread_alone() {
        let alone = std::thread::spawn(|| {
            let first = sys::this_thread_alone();
            assert!(first.is_some(), "a fresh thread gets its pool");
            let a = threads_of_a_loop();
            drop(first);
            let again = sys::this_thread_alone();
            assert!(again.is_none(), "the thread is still in its pool");
            (a, threads_of_a_loop())
        })
        .join()
        .expect("thread");
        assert_eq!(alone, ((1, true), (1, true)));
        let three = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .expect("pool");
        let (spread, _) = three.install(threads_of_a_loop);
        assert!(spread > 1, "a pool of three ran it on {spread} thread(s)");
    }
}
