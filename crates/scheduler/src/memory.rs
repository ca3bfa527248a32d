//! Memory plans: how much of the scene a worker can hold under its budget,
//! and how it must build and fetch to stay within it.
//!
//! A worker's budget covers its whole process. What a job adds to the
//! process's resident memory at registration is, per triangle of the
//! region, the BVH parts it is built into (vertices, ids, materials, the id
//! index and the nodes) and its place in the own-leaf lists; while a part is
//! built, its shipped triangles and the build's scratch besides; then the
//! fetched leaves and the directional caches; and the bounded queues of ray
//! traffic. The constants below are measured (see the README's memory
//! section); the farm's tests and `locus bench-farm` check the resulting
//! peak resident memory of worker processes against their budgets.

use locus_core::accel::BUILD_BYTES_PER_TRIANGLE;
use locus_core::geometry::{NORMALS_BYTES, triangle_bytes};
use locus_protocol::control::MemoryPlan;

/// Bytes a region triangle holds once built: about 60 in its BVH part and
/// up to 8 in id lists (a triangle is referenced by 1.1 to 1.5 leaves).
pub const REGION_BYTES_PER_TRIANGLE: u64 = 72;

/// What one triangle of a job costs a worker: held in its BVH part, and
/// shipped until the part is built. Shading normals add 36 bytes to both.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TriangleBytes {
    pub region: u64,
    pub shipped: u64,
}

impl TriangleBytes {
    pub fn of(normals: bool) -> Self {
        let n = if normals { NORMALS_BYTES } else { 0 };
        Self {
            region: REGION_BYTES_PER_TRIANGLE + n,
            shipped: triangle_bytes(normals),
        }
    }
}
/// Room for the ray traffic's bounded queues, the tile buffers and the
/// allocator's slack.
pub const QUEUE_BYTES: u64 = 24 << 20;
/// Camera samples in flight that [`QUEUE_BYTES`] holds with room to spare:
/// a sample in flight holds its pending vertices' slots and queries, a few
/// hundred bytes.
pub const INFLIGHT_IN_QUEUE_ROOM: u32 = 24 << 10;
/// Camera samples a worker keeps in flight, of the `n` its tiles call for:
/// with a budget, what [`QUEUE_BYTES`] holds. Under random polling a
/// worker also holds the work peers hand it, up to as much again (it polls
/// only while fewer slots than its own share wait for answers), so its own
/// share is half: with its whole queue room for its own samples, a
/// polling worker of a 160 MiB budget peaked at 161 MiB.
pub fn inflight_cap(n: u32, budget: u64, polling: bool) -> u32 {
    match (budget, polling) {
        (0, _) => n,
        (_, false) => n.min(INFLIGHT_IN_QUEUE_ROOM),
        (_, true) => n.min(INFLIGHT_IN_QUEUE_ROOM / 2),
    }
}
/// Bytes a directional cache node may take (the node, and the growth of
/// its leaf's node list).
pub const CACHE_NODE_BYTES: u64 = 112;
/// The smallest part worth a BVH of its own.
pub const PART_FLOOR: u64 = 16 << 10;
/// The largest part: one geometry frame must stay well under the frame
/// limit (64 MiB), so a part ships in at most 48 MiB.
pub const PART_CEILING: u64 = 1 << 20;
const PART_FRAME_BYTES: u64 = 48 << 20;

/// The largest part for triangles of `tb`.
pub fn part_ceiling(tb: TriangleBytes) -> u64 {
    PART_CEILING.min(PART_FRAME_BYTES / tb.shipped)
}

/// What a worker may spend on a job: its budget less what its process held
/// at registration and the queues; None when it has no budget.
pub fn usable(budget: u64, resident: u64) -> Option<u64> {
    (budget > 0).then(|| budget.saturating_sub(resident).saturating_sub(QUEUE_BYTES))
}

/// Triangles per BVH part: a fifth of what is usable may go to one build's
/// scratch and shipment.
pub fn part_triangles(usable: Option<u64>, tb: TriangleBytes) -> u64 {
    let ceiling = part_ceiling(tb);
    match usable {
        None => ceiling,
        Some(u) => (u / 5 / (BUILD_BYTES_PER_TRIANGLE as u64 + tb.shipped))
            .clamp(PART_FLOOR.min(ceiling), ceiling),
    }
}

/// Bytes a build of one part needs besides what is already built: its
/// shipment and scratch, and the part itself while the previous one is
/// still held during a merge.
fn build_reserve(part: u64, tb: TriangleBytes) -> u64 {
    part * (BUILD_BYTES_PER_TRIANGLE as u64 + tb.shipped + tb.region)
}

/// Triangle references a worker's region may hold (what the partitioner
/// keeps to); None when unbounded. Directional caches, when on, take up to
/// a quarter of what is usable first.
pub fn region_cap(usable: Option<u64>, caches: bool, tb: TriangleBytes) -> Option<u64> {
    let u = usable?;
    let part = part_triangles(Some(u), tb);
    let rest = u
        .saturating_sub(build_reserve(part, tb))
        .saturating_sub(if caches { u / 4 } else { 0 });
    Some(rest / tb.region)
}

/// The plan a worker follows for a region of `refs` triangle references:
/// fetched geometry takes what is left, at most `fetch_cap` bytes.
pub fn plan(
    budget: u64,
    usable: Option<u64>,
    refs: u64,
    caches: Option<u64>,
    fetch_cap: u64,
    tb: TriangleBytes,
) -> MemoryPlan {
    let part = part_triangles(usable, tb);
    let Some(u) = usable else {
        return MemoryPlan {
            budget: 0,
            part_triangles: part as u32,
            fetch_bytes: fetch_cap,
            cache_nodes: caches.unwrap_or(0),
        };
    };
    let cache_bytes = if caches.is_some() { u / 4 } else { 0 };
    let left = u
        .saturating_sub(build_reserve(part, tb))
        .saturating_sub(cache_bytes)
        .saturating_sub(refs * tb.region);
    MemoryPlan {
        budget,
        part_triangles: part as u32,
        fetch_bytes: left.min(fetch_cap),
        cache_nodes: caches.map_or(0, |n| n.min(cache_bytes / CACHE_NODE_BYTES)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn polling_halves_a_budgeted_workers_own_samples_in_flight() {
        const Q: u32 = INFLIGHT_IN_QUEUE_ROOM;
        assert_eq!(inflight_cap(100_000, 0, true), 100_000);
        assert_eq!(inflight_cap(100_000, 1 << 30, false), Q);
        assert_eq!(inflight_cap(100_000, 1 << 30, true), Q / 2);
        assert_eq!(inflight_cap(1_000, 1 << 30, true), 1_000);
    }

    #[test]
    fn plans_fit_their_budget() {
        for normals in [false, true] {
            let tb = TriangleBytes::of(normals);
            let budget = 160 << 20;
            let u = usable(budget, 20 << 20);
            let cap = region_cap(u, false, tb).unwrap();
            let p = plan(budget, u, cap, None, u64::MAX, tb);
            let part = p.part_triangles as u64;
            assert!((PART_FLOOR..=part_ceiling(tb)).contains(&part));
            // Region, one build, fetched leaves: within what is usable.
            let spent = cap * tb.region + build_reserve(part, tb) + p.fetch_bytes;
            assert!(spent <= u.unwrap(), "{spent} > {u:?}");
            // A region under the cap leaves room to fetch.
            let half = plan(budget, u, cap / 2, None, u64::MAX, tb);
            assert!(half.fetch_bytes >= cap / 2 * tb.region - 1);
            // Caches take their quarter first.
            assert!(region_cap(u, true, tb).unwrap() < cap);
            // No budget: no cap, the user's fetch cap, large parts that
            // ship within a frame.
            assert_eq!(region_cap(None, true, tb), None);
            assert_eq!(plan(0, None, 5, None, 77, tb).fetch_bytes, 77);
            let big = plan(0, None, 5, None, 77, tb).part_triangles as u64;
            assert!(big * tb.shipped <= locus_protocol::MAX_FRAME_LEN as u64 * 3 / 4);
            // A budget below the process's resident memory leaves nothing.
            assert_eq!(usable(10, 20), Some(0));
            assert_eq!(region_cap(Some(0), false, tb), Some(0));
        }
        // Normals make every triangle dearer: fewer fit.
        let u = usable(160 << 20, 20 << 20);
        assert!(
            region_cap(u, false, TriangleBytes::of(true))
                < region_cap(u, false, TriangleBytes::of(false))
        );
    }
}
