//! BVH parts built once for every worker of one process.
//!
//! The embedded farm (`locus render --workers N`) runs its workers in one
//! process. When a job replicates the scene, each of them is shipped the
//! same triangles and built the same BVH, on its own threads: N builds,
//! each on a share of the cores, and N copies in memory. The country
//! kitchen's (1.44 million triangles) took 1.8-2.0 s on each of two
//! one-thread workers where one machine builds it in 1.06 s on both
//! threads, and the process peaked at 1.3 GB against one machine's 0.73.
//!
//! [`SharedBuilds`] is handed to every worker of such a process. The first
//! worker to ask for a part builds it, on a pool of all the process's
//! threads; a worker asking for the same part meanwhile or later (while
//! some worker still holds it) waits for that build and takes it, once it
//! has checked that the BVH holds exactly its own triangles
//! ([`Accel::holds_exactly`](locus_core::accel::Accel::holds_exactly)).
//! A part that differs is built apart, as before. Worker daemons, one to a
//! process, have none.

use crate::job::build_region_part;
use locus_core::accel::BuildQuality;
use locus_core::accel_set::Part;
use locus_core::geometry::TriangleSet;
use std::collections::HashMap;
use std::hash::{DefaultHasher, Hash, Hasher};
use std::sync::{Arc, Mutex, OnceLock, PoisonError, Weak};

/// Parts built in this process, by what they were built from.
pub struct SharedBuilds {
    /// Every thread of the process's workers (None: one in all).
    pool: Option<Arc<rayon::ThreadPool>>,
    parts: Mutex<HashMap<Key, Entry>>,
}

impl std::fmt::Debug for SharedBuilds {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SharedBuilds")
            .field(
                "threads",
                &self.pool.as_ref().map_or(1, |p| p.current_num_threads()),
            )
            .finish_non_exhaustive()
    }
}

/// What tells parts apart before their triangles are compared.
#[derive(Clone, PartialEq, Eq, Hash)]
struct Key {
    magnitude: u32,
    quality: BuildQuality,
    leaves: Vec<u32>,
    triangles: usize,
    /// A hash of the triangle ids.
    ids: u64,
}

enum Entry {
    /// Being built: whoever else asks waits on the cell.
    Building(Arc<OnceLock<Arc<Part>>>),
    /// Built and held by some worker still.
    Built(Weak<Part>),
}

/// Where a worker's part came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Origin {
    /// Built by this worker.
    Built,
    /// Built by another worker of the process, for the same triangles.
    Shared,
    /// Laid out by the scheduler, once for every worker of the job
    /// (`locus_core::accel::Layout`).
    Shipped,
}

impl SharedBuilds {
    /// Builds for workers that have `threads` tracing threads in all.
    pub fn new(threads: usize) -> anyhow::Result<Self> {
        let pool = if threads > 1 {
            Some(Arc::new(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .thread_name(|i| format!("locus-build-{i}"))
                    .build()?,
            ))
        } else {
            None
        };
        Ok(Self {
            pool,
            parts: Mutex::new(HashMap::new()),
        })
    }

    /// The part over `chunk` for `leaves`: one built before for exactly
    /// these triangles, while a worker holds it, or else built now. Blocks
    /// while another worker builds the same part; call it off the async
    /// runtime.
    pub fn part(
        &self,
        chunk: TriangleSet,
        leaves: Vec<u32>,
        magnitude: f32,
        quality: BuildQuality,
    ) -> (Arc<Part>, Origin) {
        let key = Key::of(&chunk, &leaves, magnitude, quality);
        let found = {
            let mut parts = self.parts.lock().unwrap_or_else(PoisonError::into_inner);
            parts.retain(|_, e| match e {
                Entry::Built(w) => w.strong_count() > 0,
                Entry::Building(_) => true,
            });
            match parts.get(&key) {
                Some(Entry::Built(w)) => match w.upgrade() {
                    Some(p) => Found::Held(p),
                    None => Found::Cell(start(&mut parts, key.clone())),
                },
                Some(Entry::Building(c)) => Found::Cell(c.clone()),
                None => Found::Cell(start(&mut parts, key.clone())),
            }
        };
        let mut own = Some((chunk, leaves));
        let part = match found {
            Found::Held(p) => p,
            Found::Cell(cell) => {
                // The builder runs this closure; a waiter runs it only if
                // the builder failed, and then builds its own.
                let p = cell
                    .get_or_init(|| {
                        let (chunk, leaves) = own.take().expect("taken once");
                        build_region_part(chunk, leaves, magnitude, quality, self.pool.as_deref())
                    })
                    .clone();
                if own.is_none() {
                    self.finished(&key, &cell, &p);
                }
                p
            }
        };
        match own {
            None => (part, Origin::Built),
            Some((chunk, _)) if part.accel.holds_exactly(&chunk) => (part, Origin::Shared),
            Some((chunk, leaves)) => {
                tracing::warn!(
                    triangles = chunk.len(),
                    "a BVH part built in this process for the same leaves holds other triangles; building this one apart"
                );
                let p = build_region_part(chunk, leaves, magnitude, quality, self.pool.as_deref());
                (p, Origin::Built)
            }
        }
    }

    /// Keeps a built part for later askers while some worker holds it.
    fn finished(&self, key: &Key, cell: &Arc<OnceLock<Arc<Part>>>, part: &Arc<Part>) {
        let mut parts = self.parts.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(e) = parts.get_mut(key)
            && matches!(e, Entry::Building(c) if Arc::ptr_eq(c, cell))
        {
            *e = Entry::Built(Arc::downgrade(part));
        }
    }

    /// Parts this process keeps track of (built or being built).
    #[cfg(test)]
    fn tracked(&self) -> usize {
        self.parts
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .len()
    }
}

/// What a worker asking for a part finds.
enum Found {
    Held(Arc<Part>),
    Cell(Arc<OnceLock<Arc<Part>>>),
}

/// Marks `key` as being built; returns the cell its builder fills.
fn start(parts: &mut HashMap<Key, Entry>, key: Key) -> Arc<OnceLock<Arc<Part>>> {
    let cell = Arc::new(OnceLock::new());
    parts.insert(key, Entry::Building(cell.clone()));
    cell
}

impl Key {
    fn of(chunk: &TriangleSet, leaves: &[u32], magnitude: f32, quality: BuildQuality) -> Self {
        let mut h = DefaultHasher::new();
        chunk.ids.hash(&mut h);
        Self {
            magnitude: magnitude.to_bits(),
            quality,
            leaves: leaves.to_vec(),
            triangles: chunk.len(),
            ids: h.finish(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use locus_core::geometry::FLAT;

    fn set(n: u32, lift: f32) -> TriangleSet {
        let mut s = TriangleSet::with_capacity(n as usize);
        for i in 0..n {
            let v = Vec3::new(i as f32, lift, 0.0);
            s.push(i, [v, v + Vec3::X, v + Vec3::Y], i % 2, FLAT);
        }
        s
    }

    /// Workers asking at once for the same part get one build between
    /// them; a part asked for after every holder dropped it is built again.
    #[test]
    fn the_same_part_is_built_once_while_held() {
        let builds = SharedBuilds::new(2).unwrap();
        let got: Vec<(Arc<Part>, Origin)> = std::thread::scope(|s| {
            let hs: Vec<_> = (0..4)
                .map(|_| {
                    s.spawn(|| builds.part(set(2000, 0.0), vec![1, 2], 10.0, BuildQuality::Full))
                })
                .collect();
            hs.into_iter().map(|h| h.join().unwrap()).collect()
        });
        let built = got.iter().filter(|(_, o)| *o == Origin::Built).count();
        assert_eq!(built, 1, "one of four builds, the others share it");
        assert!(got.iter().all(|(p, _)| Arc::ptr_eq(p, &got[0].0)));
        assert!(got[0].0.accel.holds_exactly(&set(2000, 0.0)));
        drop(got);
        let (again, o) = builds.part(set(2000, 0.0), vec![1, 2], 10.0, BuildQuality::Full);
        assert_eq!(o, Origin::Built, "nobody held the part: built again");
        drop(again);
        // A part of other leaves: the one nobody holds is forgotten.
        let (_other, _) = builds.part(set(2000, 0.0), vec![3], 10.0, BuildQuality::Full);
        assert_eq!(builds.tracked(), 1, "dropped parts are forgotten");
    }

    /// Different leaves, ids or padding make different parts, and a set
    /// with the key of a held part but other vertices is built apart.
    #[test]
    fn other_triangles_are_built_apart() {
        let builds = SharedBuilds::new(1).unwrap();
        let (a, o) = builds.part(set(50, 0.0), vec![3], 10.0, BuildQuality::Full);
        assert_eq!(o, Origin::Built);
        for (chunk, leaves, mag) in [
            (set(50, 0.0), vec![4], 10.0),
            (set(49, 0.0), vec![3], 10.0),
            (set(50, 0.0), vec![3], 11.0),
            (set(50, 0.5), vec![3], 10.0),
        ] {
            let (p, o) = builds.part(chunk.clone(), leaves, mag, BuildQuality::Full);
            assert_eq!(o, Origin::Built);
            assert!(!Arc::ptr_eq(&p, &a));
            assert!(p.accel.holds_exactly(&chunk));
        }
        let (p, o) = builds.part(set(50, 0.0), vec![3], 10.0, BuildQuality::Full);
        assert_eq!((Arc::ptr_eq(&p, &a), o), (true, Origin::Shared));
    }
}
