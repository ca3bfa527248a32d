//! Remote geometry on demand (paper 000, section 2.2, demand-driven
//! scheduling): a worker may ask a leaf's owner for its triangles and trace
//! the leaf itself instead of forwarding the ray. Which rays fetch and
//! which forward is the job's [`FetchPolicy`], decided per leaf by
//! [`Locality::wants_fetch`].
//!
//! A fetched leaf first gets a small BVH of its own and is traced only over
//! the ray's interval inside the leaf. Every triangle hit inside the leaf's
//! box is referenced by the leaf (the octree references triangles from
//! inflated leaf boxes), and ties resolve by global id in every BVH, so the
//! hit is the one the owner would find. Later the leaf is merged into the
//! worker's BVH parts ([`crate::reach`]), after which it costs nothing more
//! than the worker's own region.
//!
//! What a worker holds of fetched geometry is bounded in bytes (its memory
//! plan): a leaf that would not fit is never asked for, and rays into it
//! are forwarded. Nothing is evicted, so a leaf once held stays for the job.

use locus_core::accel::Accel;
use locus_core::geometry::{NORMALS_BYTES, TriangleSet, triangle_bytes};
use locus_core::path::RayKind;
use locus_core::region::WorkerId;
use locus_protocol::control::JobSetup;
use locus_protocol::packet::TYPICAL_FORWARD_BYTES;
use locus_protocol::submit::FetchPolicy;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering::Relaxed};

/// One remote leaf's triangles with a BVH over them.
pub struct FetchedLeaf {
    pub leaf: u32,
    pub accel: Accel,
    /// The leaf's triangle ids, ascending.
    pub ids: Vec<u32>,
    bytes: u64,
}

impl FetchedLeaf {
    /// This leaf as a merge takes it: its triangles from its own BVH.
    pub fn source(&self) -> crate::reach::LeafSource<'_> {
        crate::reach::LeafSource {
            leaf: self.leaf,
            ids: &self.ids,
            accel: &self.accel,
        }
    }

    pub fn build(leaf: u32, geometry: TriangleSet, magnitude: f32) -> Self {
        let ids = geometry.ids.clone();
        let normals = !geometry.normals.is_empty();
        let accel = Accel::from_set(geometry, magnitude);
        let bytes = (accel.bytes() + ids.len() * 4 + std::mem::size_of::<Self>()) as u64;
        debug_assert!(
            bytes <= ids.len() as u64 * held_bytes(normals) + LEAF_HELD_BYTES,
            "the held estimate must bound what a leaf holds"
        );
        Self {
            leaf,
            accel,
            ids,
            bytes,
        }
    }

    /// Bytes this leaf holds in memory.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
}

/// Bytes a forwarded query costs on the wire, query plus answer, for the
/// adaptive policy's rent-or-buy rule.
const FORWARD_COST: u64 = TYPICAL_FORWARD_BYTES;
/// At most the bytes a fetched triangle holds in memory: vertices, id,
/// material and index entry (48), a BVH node at worst (80), and its place
/// in the leaf's id list (4); its shading normals (36) besides when the
/// scene has them.
pub const TRIANGLE_HELD_BYTES: u64 = 132;

/// [`TRIANGLE_HELD_BYTES`] for a scene with or without shading normals.
pub fn held_bytes(normals: bool) -> u64 {
    TRIANGLE_HELD_BYTES + if normals { NORMALS_BYTES } else { 0 }
}
/// At most the bytes a fetched leaf holds besides its triangles.
pub const LEAF_HELD_BYTES: u64 = 512;

/// A worker's per-job state for fetching: the policy and the counts it
/// decides on.
pub struct Locality {
    pub policy: FetchPolicy,
    /// Leaves touching this worker's region (hybrid: fetch these).
    near: Vec<bool>,
    /// Forwards so far into each leaf (adaptive).
    forwards: Vec<AtomicU32>,
    /// Wire bytes of each leaf's geometry (adaptive).
    leaf_cost: Vec<u64>,
    /// Bytes a triangle takes on the wire and held, with the scene's
    /// shading normals if it has them.
    wire_bytes: u64,
    held_bytes: u64,
    /// Leaves this worker will not fetch (no room left): always forwarded.
    refused: Vec<AtomicBool>,
}

impl Locality {
    pub fn new(setup: &JobSetup) -> Self {
        let tree = &setup.map.tree;
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
            near,
            forwards: (0..n).map(|_| AtomicU32::new(0)).collect(),
            leaf_cost: (0..n)
                .map(|l| {
                    setup.leaf_tris.get(l).copied().unwrap_or(0) as u64
                        * triangle_bytes(setup.normals)
                })
                .collect(),
            wire_bytes: triangle_bytes(setup.normals),
            held_bytes: held_bytes(setup.normals),
            refused: (0..n).map(|_| AtomicBool::new(false)).collect(),
        }
    }

    /// Whether a ray of `kind` that reaches remote leaf `leaf` (not held
    /// here) should wait for its geometry rather than be forwarded.
    pub fn wants_fetch(&self, leaf: u32, kind: RayKind) -> bool {
        if !self.may_fetch(leaf) {
            return false;
        }
        let l = leaf as usize;
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

    /// Whether `leaf` may still be fetched at all (a query handed over by
    /// random polling fetches its hander's leaves whatever the policy).
    pub fn may_fetch(&self, leaf: u32) -> bool {
        self.refused
            .get(leaf as usize)
            .is_some_and(|b| !b.load(Relaxed))
    }

    /// Never fetch `leaf` again (it would not fit).
    pub fn refuse(&self, leaf: u32) {
        if let Some(b) = self.refused.get(leaf as usize) {
            b.store(true, Relaxed);
        }
    }

    /// At most the bytes `leaf` will hold here once fetched: what its
    /// request reserves, so that what a worker holds never passes its plan.
    pub fn held_estimate(&self, leaf: u32) -> u64 {
        self.leaf_cost.get(leaf as usize).copied().unwrap_or(0) / self.wire_bytes * self.held_bytes
            + LEAF_HELD_BYTES
    }
}
