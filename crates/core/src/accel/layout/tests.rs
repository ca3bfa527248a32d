//! A shipped layout gives the BVH the set's own build gives, and one a
//! peer corrupted is refused, or else walked without harm.

use super::*;
use crate::accel::Accel;
use crate::accel::tests::soup;
use crate::geometry::{Ray, TriangleSet};
use crate::sampler::SampleKey;
use crate::stats::TraceStats;

/// 500 triangles (some long, so some are split) with ascending ids,
/// materials and shading normals.
fn set() -> TriangleSet {
    let verts = soup(480, 20);
    let n = verts.len();
    TriangleSet {
        ids: (0..n as u32).map(|i| 2 * i + 5).collect(),
        verts,
        material: (0..n as u32).map(|i| i % 3).collect(),
        normals: (0..n)
            .map(|i| [Vec3::new(0.0, 0.0, 1.0 + i as f32 * 1e-3).normalize(); 3])
            .collect(),
    }
}

/// Ray `i` of the comparisons: from a point in the soup's cube towards
/// another, over the whole ray or a piece of it.
fn ray(i: u64) -> (Ray, f32, f32) {
    let k = SampleKey::independent(i, 2, 13);
    let p = |d: u32| (Vec3::new(k.get1d(d), k.get1d(d + 1), k.get1d(d + 2)) * 2.0 - 1.0) * 12.0;
    let (o, q) = (p(0), p(3));
    let dir = (q - o).try_normalize().unwrap_or(Vec3::X);
    let t1 = if i.is_multiple_of(3) {
        (q - o).length()
    } else {
        f32::INFINITY
    };
    (Ray::new(o, dir), 0.0, t1)
}

/// Every answer of `a` and `b` over 3,000 rays, closest hits with their
/// triangles and occlusion, and how many rays hit.
fn same_answers(a: &Accel, b: &Accel) -> usize {
    let mut hits = 0;
    for i in 0..3000 {
        let (r, t0, t1) = ray(i);
        let (mut sa, mut sb) = (TraceStats::default(), TraceStats::default());
        let (ha, hb) = (
            a.closest(&r, t0, t1, &mut sa),
            b.closest(&r, t0, t1, &mut sb),
        );
        assert_eq!(ha.map(|h| h.hit), hb.map(|h| h.hit), "ray {i}");
        if let (Some(ha), Some(hb)) = (ha, hb) {
            assert_eq!(a.surface(&ha), b.surface(&hb), "ray {i}");
            hits += 1;
        }
        assert_eq!(
            a.occluded(&r, t0, t1, &mut sa),
            b.occluded(&r, t0, t1, &mut sb)
        );
    }
    hits
}

/// A layout that went through postcard, taken for its own set: the same
/// BVH as the set's own build, node for node, and the same answers.
#[test]
fn a_shipped_layout_is_the_sets_own_bvh() {
    let set = set();
    let layout = Layout::build(&set, 20.0, BuildQuality::Full);
    assert!(layout.order.len() > set.len(), "no triangle was split");
    let bytes = postcard::to_allocvec(&layout).unwrap();
    let shipped: Layout = postcard::from_bytes(&bytes).unwrap();
    assert_eq!(shipped, layout);
    let own = Accel::from_set(set.clone(), 20.0);
    let taken = Accel::from_layout(set.clone(), &shipped).expect("its own set's layout");
    assert_eq!(taken.bvh.nodes, own.bvh.nodes);
    assert!(taken.holds_exactly(&set));
    let hits = same_answers(&own, &taken);
    assert!(
        hits > 100,
        "only {hits} rays hit: the comparison says little"
    );
    // An empty set's layout is empty, and taken.
    let none = TriangleSet::default();
    let empty = Layout::build(&none, 1.0, BuildQuality::Full);
    assert!(Accel::from_layout(none, &empty).unwrap().is_empty());
}

/// A layout built in place over a scene's vertices and a subset's ids
/// (what the scheduler does) is the one built over the gathered subset,
/// and the subset's BVH takes it.
#[test]
fn a_layout_built_in_place_is_the_gathered_sets() {
    let whole = set();
    let pick: Vec<usize> = (0..whole.len()).filter(|i| i % 3 != 1).collect();
    let subset = TriangleSet {
        ids: pick.iter().map(|&i| whole.ids[i]).collect(),
        verts: pick.iter().map(|&i| whole.verts[i]).collect(),
        material: pick.iter().map(|&i| whole.material[i]).collect(),
        normals: pick.iter().map(|&i| whole.normals[i]).collect(),
    };
    for s in [&whole, &subset] {
        let gathered = Layout::build(s, 20.0, BuildQuality::Full);
        let in_place = Layout::build_over(&s.verts, &s.ids, 20.0, BuildQuality::Full);
        assert_eq!(in_place, gathered);
        assert!(Accel::from_layout(s.clone(), &in_place).is_ok());
    }
    // Over the whole scene's vertices with the subset's ids it is a layout
    // of other triangles (the count and ids differ from the vertices').
    let wrong = Layout::build_over(&whole.verts, &whole.ids, 20.0, BuildQuality::Full);
    assert!(Accel::from_layout(subset, &wrong).is_err());
}

/// Each way a layout can name what is not there is refused, with the
/// reason.
#[test]
fn a_layout_naming_what_is_not_there_is_refused() {
    let set = set();
    let good = Layout::build(&set, 20.0, BuildQuality::Full);
    assert!(good.check(&set).is_ok());
    let refused = |change: &dyn Fn(&mut Layout), why: &str| {
        let mut l = good.clone();
        change(&mut l);
        let e = l.check(&set).expect_err(why);
        assert!(e.contains(why), "{why}: said {e}");
    };
    let mut other = set.clone();
    other.ids[7] += 1;
    assert!(good.check(&other).unwrap_err().contains("other triangles"));
    refused(&|l| l.triangles += 1, "other triangles");
    refused(&|l| l.order[3] = set.len() as u32, "names triangle");
    refused(&|l| l.order[3] = l.order[4], "leaves triangles out");
    refused(&|l| l.order.extend(vec![0; 2 * set.len()]), "boxes for");
    refused(&|l| l.bounds.max.x = f32::NAN, "bounds");
    refused(&|l| l.nodes.clear(), "boxes without nodes");
    let inner = good.nodes.iter().position(|n| n.imask != 0).unwrap();
    refused(
        &|l| l.nodes[inner].child_base_idx = l.nodes.len() as u32,
        "children outside",
    );
    refused(
        &|l| l.nodes[inner].child_base_idx = inner as u32,
        "children outside",
    );
    // An inner child entry whose slot the mask lacks.
    let slot = (0..8)
        .find(|&k| good.nodes[inner].child_meta[k] & 0x18 == 0x18)
        .unwrap();
    refused(
        &|l| l.nodes[inner].imask &= !(1 << (l.nodes[inner].child_meta[slot] & 7)),
        "mask lacks",
    );
    refused(&|l| l.nodes[inner].child_meta[slot] |= 0x40, "mask lacks");
    // A leaf entry whose boxes run into the inner bits, or past the order.
    let leafy = good
        .nodes
        .iter()
        .position(|n| n.child_meta.iter().any(|&m| m != 0 && m & 0x18 != 0x18))
        .unwrap();
    let k = (0..8)
        .find(|&k| {
            let m = good.nodes[leafy].child_meta[k];
            m != 0 && m & 0x18 != 0x18
        })
        .unwrap();
    refused(
        &|l| l.nodes[leafy].child_meta[k] = 0b1111_0110,
        "does not have",
    );
    refused(
        &|l| l.nodes[leafy].primitive_base_idx = l.order.len() as u32,
        "does not have",
    );
    refused(
        &|l| l.nodes[leafy].primitive_base_idx = u32::MAX,
        "does not have",
    );
}

/// A chain of nodes deeper than the traversal's stack is refused, and so
/// are two nodes sharing a child; a chain as deep as the stack is taken.
#[test]
fn a_tree_deeper_than_the_stack_is_refused() {
    let n = 40;
    let set = TriangleSet {
        ids: (0..n as u32).collect(),
        verts: soup(n, 0),
        material: vec![0; n as usize],
        normals: Vec::new(),
    };
    let mut l = Layout::build(&set, 20.0, BuildQuality::Quick);
    let chain = |depth: usize| {
        (0..depth)
            .map(|i| {
                let mut node = CwBvhNode::default();
                if i + 1 < depth {
                    // One inner child, in slot 0, the next node.
                    node.imask = 1;
                    node.child_base_idx = i as u32 + 1;
                    node.child_meta[0] = 0b0011_1000;
                } else {
                    // The leaf: one box, the first.
                    node.child_meta[0] = 0b0010_0000;
                }
                node
            })
            .collect::<Vec<_>>()
    };
    // Two nodes (1 and 2, the root's children) claiming node 3.
    let mut two = chain(4);
    two[0].imask = 0b11;
    two[0].child_meta[1] = 0b0011_1001;
    two[1].child_base_idx = 3;
    assert!(l.clone().check(&set).is_ok());
    l.nodes = two;
    assert!(l.check(&set).unwrap_err().contains("two parents"));
    l.nodes = chain(MAX_DEPTH as usize + 1);
    assert!(l.check(&set).is_ok(), "{:?}", l.check(&set));
    l.nodes = chain(MAX_DEPTH as usize + 2);
    assert!(l.check(&set).unwrap_err().contains("deeper"));
}

/// Layouts with random bytes of their nodes changed (4,000 of them):
/// each is refused, or else every query over it ends without a panic.
#[test]
fn corrupted_layouts_are_refused_or_walked_safely() {
    let set = set();
    let good = Layout::build(&set, 20.0, BuildQuality::Full);
    let (mut taken, mut refused) = (0, 0);
    for seed in 0..4000u64 {
        let k = SampleKey::independent(seed, 0, 17);
        let mut wire = Wire::from(good.clone());
        for c in 0..1 + seed % 4 {
            let u = |d: u32| k.get1d(d + 3 * c as u32);
            let node = (u(0) * wire.nodes.len() as f32) as usize % wire.nodes.len();
            let word = (u(1) * NODE_WORDS as f32) as usize % NODE_WORDS;
            let bit = (u(2) * 32.0) as u32 % 32;
            // Flip a bit, or set a whole byte of the word at random.
            if seed.is_multiple_of(2) {
                wire.nodes[node][word] ^= 1 << bit;
            } else {
                let shift = 8 * (bit / 8);
                let byte = (u(2) * 65536.0) as u32 & 0xff;
                wire.nodes[node][word] =
                    (wire.nodes[node][word] & !(0xff << shift)) | byte << shift;
            }
        }
        let l = Layout::from(wire);
        match Accel::from_layout(set.clone(), &l) {
            Err(_) => refused += 1,
            Ok(accel) => {
                taken += 1;
                for i in 0..40 {
                    let (r, t0, t1) = ray(seed * 40 + i);
                    let mut st = TraceStats::default();
                    if let Some(h) = accel.closest(&r, t0, t1, &mut st) {
                        let _ = accel.surface(&h);
                    }
                    let _ = accel.occluded(&r, t0, t1, &mut st);
                }
            }
        }
    }
    // Most single changes land in box bounds, which are taken (they only
    // move answers); some land in indices and masks, which are refused.
    assert!(
        taken > 1000 && refused > 200,
        "taken {taken}, refused {refused}"
    );
}
