//! Remote geometry on demand (paper 000, section 2.2, demand-driven
//! scheduling): a worker may ask a leaf's owner for its triangles and trace
//! the leaf itself instead of forwarding the ray. Fetched leaves live in a
//! cache bounded in bytes ([`LeafStore`], quick_cache's CLOCK-Pro, a
//! scan-resistant approximation of least-recently-used eviction); which
//! rays fetch and which forward is the job's [`FetchPolicy`], decided per
//! leaf by [`Locality::wants_fetch`].
//!
//! A fetched leaf is traced only over the ray's interval inside that leaf.
//! Every triangle hit inside the leaf's box is referenced by the leaf (the
//! octree references triangles from inflated leaf boxes), and ties resolve
//! by global id in every BVH, so the hit is the one the owner would find.

use locus_core::accel::Accel;
use locus_core::octree::Octree;
use locus_core::region::WorkerId;
use locus_protocol::control::{JobSetup, RegionGeometry};
use locus_protocol::submit::FetchPolicy;
use quick_cache::Weighter;
use quick_cache::sync::Cache;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering::Relaxed};

/// One remote leaf's triangles with a BVH over them.
pub struct FetchedLeaf {
    pub leaf: u32,
    pub geometry: RegionGeometry,
    pub accel: Accel,
    bytes: u64,
}

impl FetchedLeaf {
    pub fn build(leaf: u32, geometry: RegionGeometry, magnitude: f32) -> Self {
        let accel = Accel::build_indexed(&geometry.ids, &geometry.verts, magnitude);
        use std::mem::size_of_val;
        let bytes = (size_of_val(geometry.ids.as_slice())
            + size_of_val(geometry.verts.as_slice())
            + size_of_val(geometry.material.as_slice())
            + accel.bytes()
            + std::mem::size_of::<Self>()) as u64;
        Self {
            leaf,
            geometry,
            accel,
            bytes,
        }
    }

    /// Bytes this leaf holds in memory: what the cache bound counts.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
}

#[derive(Clone)]
struct ByteWeighter;

impl Weighter<u32, Arc<FetchedLeaf>> for ByteWeighter {
    fn weight(&self, _leaf: &u32, v: &Arc<FetchedLeaf>) -> u64 {
        v.bytes.max(1)
    }
}

/// Fetched leaves, bounded in bytes.
pub struct LeafStore {
    cache: Cache<u32, Arc<FetchedLeaf>, ByteWeighter>,
    bound: u64,
    peak: AtomicU64,
}

/// Shards of the store: enough that tracing threads rarely meet on one
/// lock, few enough that a large leaf still fits a shard.
const SHARDS: u64 = 4;

impl LeafStore {
    /// A store of at most `bound` bytes for a job of `leaves` leaves.
    pub fn new(bound: u64, leaves: usize) -> Self {
        // Each shard holds a quarter; rounding down keeps the sum in bound.
        let per = bound / SHARDS;
        let opts = quick_cache::OptionsBuilder::new()
            .estimated_items_capacity(leaves.max(SHARDS as usize * 32))
            .weight_capacity(per * SHARDS)
            .shards(SHARDS as usize)
            .build()
            .expect("valid cache options");
        Self {
            cache: Cache::with_options(opts, ByteWeighter, Default::default(), Default::default()),
            bound,
            peak: AtomicU64::new(0),
        }
    }

    pub fn get(&self, leaf: u32) -> Option<Arc<FetchedLeaf>> {
        self.cache.get(&leaf)
    }

    /// Keeps `l`, evicting others as needed; false when the leaf alone is
    /// too large for the store (then the leaf must be forwarded).
    pub fn insert(&self, l: Arc<FetchedLeaf>) -> bool {
        let leaf = l.leaf;
        if l.bytes > self.bound / SHARDS {
            return false;
        }
        self.cache.insert(leaf, l);
        self.peak.fetch_max(self.cache.weight(), Relaxed);
        self.cache.contains_key(&leaf)
    }

    /// Bytes held now.
    pub fn weight(&self) -> u64 {
        self.cache.weight()
    }

    /// Largest weight seen after an insertion.
    pub fn peak(&self) -> u64 {
        self.peak.load(Relaxed)
    }

    pub fn bound(&self) -> u64 {
        self.bound
    }
}

/// What a ray is, for the hybrid policy: camera rays are coherent, shadow
/// and continuation rays are not.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RayKind {
    Camera,
    Secondary,
}

/// Bytes a forwarded query costs on the wire, query plus answer, for the
/// adaptive policy's rent-or-buy rule (a postcard `Trace` item of a path
/// query is about 70 bytes, an answer about 16).
const FORWARD_COST: u64 = 86;
/// Wire bytes per triangle of a shipped leaf (id, vertices, material).
const TRIANGLE_COST: u64 = 44;

/// A worker's per-job state for fetching: the store, which leaves are in
/// flight, and the counts the policies decide on.
pub struct Locality {
    pub policy: FetchPolicy,
    pub store: LeafStore,
    /// Leaves touching this worker's region (hybrid: fetch these).
    near: Vec<bool>,
    /// Forwards so far into each leaf (adaptive).
    forwards: Vec<AtomicU32>,
    /// Wire bytes of each leaf's geometry (adaptive).
    leaf_cost: Vec<u64>,
    /// Leaves the store cannot hold: always forwarded.
    too_large: Vec<AtomicBool>,
}

impl Locality {
    pub fn new(setup: &JobSetup) -> Self {
        let tree: &Octree = &setup.map.tree;
        let n = tree.leaves.len();
        let me = setup.me;
        let owner: &[WorkerId] = &setup.map.owner;
        let mut near = vec![false; n];
        if setup.fetch == FetchPolicy::Hybrid {
            for (l, nb) in tree.face_neighbours().iter().enumerate() {
                if owner[l] == me {
                    for &m in nb {
                        near[m as usize] = owner[m as usize] != me;
                    }
                }
            }
        }
        Self {
            policy: setup.fetch,
            store: LeafStore::new(setup.fetch_budget, n),
            near,
            forwards: (0..n).map(|_| AtomicU32::new(0)).collect(),
            leaf_cost: (0..n)
                .map(|l| setup.leaf_tris.get(l).copied().unwrap_or(0) as u64 * TRIANGLE_COST)
                .collect(),
            too_large: (0..n).map(|_| AtomicBool::new(false)).collect(),
        }
    }

    /// Whether a ray of `kind` that reaches remote leaf `leaf` (not in the
    /// store) should wait for its geometry rather than be forwarded.
    pub fn wants_fetch(&self, leaf: u32, kind: RayKind) -> bool {
        let l = leaf as usize;
        if self.too_large.get(l).is_none_or(|b| b.load(Relaxed)) {
            return false;
        }
        match self.policy {
            FetchPolicy::Forward => false,
            FetchPolicy::Fetch => true,
            FetchPolicy::Hybrid => kind == RayKind::Camera || self.near[l],
            FetchPolicy::Adaptive => {
                let f = self.forwards[l].fetch_add(1, Relaxed) as u64 + 1;
                f * FORWARD_COST >= self.leaf_cost[l]
            }
        }
    }

    pub fn mark_too_large(&self, leaf: u32) {
        if let Some(b) = self.too_large.get(leaf as usize) {
            b.store(true, Relaxed);
        }
    }
}
