//! Fetched geometry against its owner: a leaf shipped to another worker
//! and traced there over the ray's interval in that leaf finds exactly the
//! hits of a BVH over the whole scene.

use glam::Vec3;
use locus_core::geometry::Ray;
use locus_core::octree::{Octree, OctreeParams};
use locus_core::stats::TraceStats;
use locus_protocol::control::TriangleSet;
use locus_worker::fetch::FetchedLeaf;
use std::ops::ControlFlow;
use std::sync::Arc;

/// A small generated conference room: walls, table and chairs, full of
/// shared edges and axis-aligned faces, with small leaves.
fn room() -> (locus_core::render::Prepared, Octree) {
    use locus_core::generate::{RoomParams, conference_room, room_materials};
    let p = RoomParams {
        chairs_per_side: 2,
        detail: 3,
        leg_segments: 6,
        ..RoomParams::default()
    };
    let scene = locus_core::scene::Scene::from_triangles(
        "<room>".into(),
        locus_core::scene::Camera {
            position: Vec3::new(6.0, 1.5, 7.0),
            look_at: Vec3::new(6.0, 1.0, 0.0),
            up: Vec3::Y,
            fov_y: 60.0,
            width: 8,
            height: 8,
        },
        Default::default(),
        room_materials(),
        conference_room(&p).tagged_triangles(),
    );
    let tree = Octree::build(
        &scene.tris,
        OctreeParams {
            max_leaf_tris: 24,
            max_depth: 7,
        },
    );
    (locus_core::render::Prepared::new(scene), tree)
}

/// Incoherent rays through the room; every 5th runs along an axis inside
/// one of the root's splitting planes, where leaves share faces.
fn rays(prep: &locus_core::render::Prepared, tree: &Octree, n: usize) -> Vec<Ray> {
    let centre = tree.bounds.center();
    locus_core::generate::incoherent_rays(prep, n, 9)
        .into_iter()
        .enumerate()
        .map(|(i, r)| {
            if i % 5 != 0 {
                return r;
            }
            let a = i / 5 % 3;
            let mut d = Vec3::ZERO;
            d[a] = if i % 2 == 0 { 1.0 } else { -1.0 };
            let mut o = r.origin;
            o[(a + 1) % 3] = centre[(a + 1) % 3];
            Ray::new(o, d)
        })
        .collect()
}

fn fetched_leaves(tris: &[[Vec3; 3]], tree: &Octree, magnitude: f32) -> Vec<Arc<FetchedLeaf>> {
    tree.leaves
        .iter()
        .enumerate()
        .map(|(i, l)| {
            let g = TriangleSet {
                ids: l.tris.clone(),
                verts: l.tris.iter().map(|&t| tris[t as usize]).collect(),
                material: vec![0; l.tris.len()],
                normals: Vec::new(),
            };
            Arc::new(FetchedLeaf::build(i as u32, g, magnitude))
        })
        .collect()
}

#[test]
fn fetched_leaves_give_the_same_hits_as_the_whole_scene() {
    let (prep, tree) = room();
    assert!(tree.leaves.len() > 50);
    let global = &prep.accel;
    let leaves = fetched_leaves(&prep.scene.tris, &tree, prep.scene.magnitude());
    let mut st = TraceStats::default();
    let (mut hits, mut leaf_visits) = (0, 0);
    for (i, ray) in rays(&prep, &tree, 4000).iter().enumerate() {
        let want = global.intersect(ray, 0.0, f32::INFINITY, &mut st);
        let mut got = None;
        let _ = tree.walk(ray, 0.0, f32::INFINITY, |leaf, ta, tb| {
            leaf_visits += 1;
            got = leaves[leaf as usize].accel.intersect(ray, ta, tb, &mut st);
            if got.is_some() {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        });
        let key = |h: Option<locus_core::accel::Hit>| h.map(|h| (h.tri, h.t.to_bits()));
        assert_eq!(key(got), key(want), "ray {i}: {ray:?}");
        hits += want.is_some() as u32;
    }
    // The rays tested something: most hit, and they crossed many leaves.
    assert!(hits > 1500, "{hits} hits");
    assert!(leaf_visits > 4000 * 3, "{leaf_visits} leaf visits");
}
