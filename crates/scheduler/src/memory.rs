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
use locus_protocol::control::MemoryPlan;

/// Bytes a region triangle holds once built: about 60 in its BVH part and
/// up to 8 in id lists (a triangle is referenced by 1.1 to 1.5 leaves).
pub const REGION_BYTES_PER_TRIANGLE: u64 = 72;
/// Bytes a shipped triangle occupies until its part is built.
pub const SHIPPED_BYTES_PER_TRIANGLE: u64 = 44;
/// Room for the ray traffic's bounded queues, the tile buffers and the
/// allocator's slack.
pub const QUEUE_BYTES: u64 = 24 << 20;
/// Camera samples in flight that [`QUEUE_BYTES`] holds with room to spare:
/// a sample in flight holds its pending vertices' slots and queries, a few
/// hundred bytes.
pub const INFLIGHT_IN_QUEUE_ROOM: u32 = 24 << 10;
/// Bytes a directional cache node may take (the node, and the growth of
/// its leaf's node list).
pub const CACHE_NODE_BYTES: u64 = 112;
/// The smallest part worth a BVH of its own.
pub const PART_FLOOR: u64 = 16 << 10;
/// The largest part: one geometry frame must stay well under the frame
/// limit.
pub const PART_CEILING: u64 = 1 << 20;

/// What a worker may spend on a job: its budget less what its process held
/// at registration and the queues; None when it has no budget.
pub fn usable(budget: u64, resident: u64) -> Option<u64> {
    (budget > 0).then(|| budget.saturating_sub(resident).saturating_sub(QUEUE_BYTES))
}

/// Triangles per BVH part: a fifth of what is usable may go to one build's
/// scratch and shipment.
pub fn part_triangles(usable: Option<u64>) -> u64 {
    match usable {
        None => PART_CEILING,
        Some(u) => (u / 5 / (BUILD_BYTES_PER_TRIANGLE as u64 + SHIPPED_BYTES_PER_TRIANGLE))
            .clamp(PART_FLOOR, PART_CEILING),
    }
}

/// Bytes a build of one part needs besides what is already built: its
/// shipment and scratch, and the part itself while the previous one is
/// still held during a merge.
fn build_reserve(part: u64) -> u64 {
    part * (BUILD_BYTES_PER_TRIANGLE as u64
        + SHIPPED_BYTES_PER_TRIANGLE
        + REGION_BYTES_PER_TRIANGLE)
}

/// Triangle references a worker's region may hold (what the partitioner
/// keeps to); None when unbounded. Directional caches, when on, take up to
/// a quarter of what is usable first.
pub fn region_cap(usable: Option<u64>, caches: bool) -> Option<u64> {
    let u = usable?;
    let part = part_triangles(Some(u));
    let rest = u
        .saturating_sub(build_reserve(part))
        .saturating_sub(if caches { u / 4 } else { 0 });
    Some(rest / REGION_BYTES_PER_TRIANGLE)
}

/// The plan a worker follows for a region of `refs` triangle references:
/// fetched geometry takes what is left, at most `fetch_cap` bytes.
pub fn plan(
    budget: u64,
    usable: Option<u64>,
    refs: u64,
    caches: Option<u64>,
    fetch_cap: u64,
) -> MemoryPlan {
    let part = part_triangles(usable);
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
        .saturating_sub(build_reserve(part))
        .saturating_sub(cache_bytes)
        .saturating_sub(refs * REGION_BYTES_PER_TRIANGLE);
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
    fn plans_fit_their_budget() {
        let budget = 160 << 20;
        let u = usable(budget, 20 << 20);
        let cap = region_cap(u, false).unwrap();
        let p = plan(budget, u, cap, None, u64::MAX);
        let part = p.part_triangles as u64;
        assert!((PART_FLOOR..=PART_CEILING).contains(&part));
        // Region, one build, fetched leaves: within what is usable.
        let spent = cap * REGION_BYTES_PER_TRIANGLE + build_reserve(part) + p.fetch_bytes;
        assert!(spent <= u.unwrap(), "{spent} > {u:?}");
        // A region under the cap leaves room to fetch.
        let half = plan(budget, u, cap / 2, None, u64::MAX);
        assert!(half.fetch_bytes >= cap / 2 * REGION_BYTES_PER_TRIANGLE - 1);
        // Caches take their quarter first.
        assert!(region_cap(u, true).unwrap() < cap);
        // No budget: no cap, the user's fetch cap, large parts.
        assert_eq!(region_cap(None, true), None);
        assert_eq!(plan(0, None, 5, None, 77).fetch_bytes, 77);
        // A budget below the process's resident memory leaves nothing.
        assert_eq!(usable(10, 20), Some(0));
        assert_eq!(region_cap(Some(0), false), Some(0));
    }
}
