//! The BVH's own tests: triangles found by id, a BVH against the set it
//! was built from, the two node tests alike, and builds alike on any
//! number of threads (brute-force comparisons are in `tests/brute_force`).

use super::*;
use crate::sampler::SampleKey;

/// `n` small triangles scattered in a 20-unit cube, and `long` long thin
/// ones across its diagonal (boxes mostly empty: split candidates).
pub(super) fn soup(n: u64, long: u64) -> Vec<[Vec3; 3]> {
    let mut tris = Vec::new();
    for i in 0..n + long {
        let k = SampleKey::independent(i, 0, 9);
        let c = (Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 2.0 - 1.0) * 10.0;
        let w = Vec3::new(k.get1d(3), k.get1d(4), k.get1d(5)) * 0.3;
        let d = if i < n {
            Vec3::new(0.3, 0.0, 0.1)
        } else {
            Vec3::splat(5.0)
        };
        tris.push([c - d, c + d, c + w]);
    }
    tris
}

/// `find` gives, for every id a BVH holds, a position holding that
/// triangle, and nothing for an id it does not hold: with ids in
/// ascending order (found without a sort) and in any other order, and
/// with long triangles stored once per piece of their split.
#[test]
fn find_locates_every_id_split_or_not() {
    let set = soup(400, 30);
    let ascending: Vec<u32> = (0..set.len() as u32).map(|i| 3 * i + 1).collect();
    let mut shuffled = ascending.clone();
    shuffled.reverse();
    shuffled.swap(3, 200);
    for ids in [ascending, shuffled] {
        let accel = Accel::build_indexed(&ids, &set, 20.0);
        assert!(
            accel.meta.len() > set.len(),
            "no triangle was split: the test would not cover pieces"
        );
        for (k, &id) in ids.iter().enumerate() {
            let p = accel.find(id).expect("an id the BVH holds");
            assert_eq!(accel.meta[p as usize].id, id);
            assert_eq!(accel.triangle(p).0, set[k]);
            assert_eq!(accel.find(id + 1), None);
        }
        assert_eq!(accel.find(0), None);
    }
}

/// A BVH holds exactly the set it was built from, split triangles and
/// shading normals included, and not a set that differs in one id,
/// one vertex bit, one material or one normal, or lacks a triangle.
#[test]
fn a_bvh_holds_exactly_its_own_set() {
    let verts = soup(300, 20);
    let n = verts.len();
    let set = TriangleSet {
        ids: (0..n as u32).map(|i| 2 * i + 5).collect(),
        verts,
        material: (0..n as u32).map(|i| i % 4).collect(),
        normals: (0..n).map(|i| [Vec3::Z * (i % 3) as f32; 3]).collect(),
    };
    let accel = Accel::from_set(set.clone(), 20.0);
    assert!(
        accel.boxes() > accel.len(),
        "nothing split: pieces untested"
    );
    assert!(accel.holds_exactly(&set));
    let changed: [fn(&mut TriangleSet); 5] = [
        |s| s.ids[7] += 1,
        |s| {
            let y = &mut s.verts[100][1].y;
            *y = f32::from_bits(y.to_bits() ^ 1);
        },
        |s| s.material[0] ^= 1,
        |s| s.normals[200][2].x = 1e-30,
        |s| {
            s.ids.pop();
            s.verts.pop();
            s.material.pop();
            s.normals.pop();
        },
    ];
    for (i, change) in changed.iter().enumerate() {
        let mut other = set.clone();
        change(&mut other);
        assert!(!accel.holds_exactly(&other), "change {i} not noticed");
    }
}

/// Rays along the axes, their other components +0.0 or -0.0 (negating an
/// axis gives -0.0), and rays with one component of either zero, find
/// what testing every triangle finds: closest hits and occlusion. A -0.0
/// once made the BVH miss every box.
#[test]
fn rays_with_zero_components_of_either_sign_find_what_every_triangle_gives() {
    let set = soup(8000, 40);
    let ids: Vec<u32> = (0..set.len() as u32).collect();
    let accel = Accel::build(&set, &ids, 20.0);
    let brute = |r: &Ray, t1: f32| first_hit(&set, r, 0.0, t1);
    let mut st = TraceStats::default();
    let mut hits = 0;
    for i in 0..3000u64 {
        let k = SampleKey::independent(i, 5, 9);
        let o = (Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 2.0 - 1.0) * 12.0;
        let axis = (i % 3) as usize;
        let mut d = Vec3::ZERO;
        d[axis] = if i % 2 == 0 { 1.0 } else { -1.0 };
        // Each other component +0.0, -0.0 or, for every fourth ray, a
        // value, so that one zero is left.
        for a in (0..3).filter(|&a| a != axis) {
            d[a] = match (i / 6 + a as u64) % 4 {
                0 => 0.0,
                1 | 2 => -0.0,
                _ => k.get1d(3 + a as u32) - 0.5,
            };
        }
        let d = if d.length() != 1.0 { d.normalize() } else { d };
        let r = Ray::new(o, d);
        let t1 = if i % 5 == 0 { 8.0 } else { f32::INFINITY };
        let want = brute(&r, t1);
        let got = accel.closest(&r, 0.0, t1, &mut st);
        assert_eq!(
            got.map(|h| (h.hit.t, h.hit.tri)),
            want,
            "ray {i}: {o:?} along {d:?}"
        );
        assert_eq!(
            accel.occluded(&r, 0.0, t1, &mut st),
            want.is_some(),
            "ray {i}"
        );
        hits += want.is_some() as usize;
    }
    assert!(hits > 300, "only {hits} hits: the rays test little");
}

/// A query that starts along its ray skips the nodes that end before its
/// start (`cwnode::entry_min`) and still finds every hit at or beyond it:
/// started exactly at each ray's first hit it finds that hit, started a
/// hair beyond it finds what testing every triangle finds there, and it
/// visits fewer nodes than the same queries started at the origin.
#[test]
fn queries_started_along_the_ray_find_the_hits_at_their_start() {
    let set = soup(6000, 40);
    let ids: Vec<u32> = (0..set.len() as u32).collect();
    let accel = Accel::build(&set, &ids, 20.0);
    let brute = |r: &Ray, t0: f32| first_hit(&set, r, t0, f32::INFINITY);
    // The closest-hit queries from the origin and from the first hit are
    // counted apart; the others in `rest`.
    let (mut from_origin, mut from_hit) = (TraceStats::default(), TraceStats::default());
    let mut rest = TraceStats::default();
    let mut checked = 0;
    for i in 0..1500u64 {
        let k = SampleKey::independent(i, 4, 9);
        let o = (Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 2.0 - 1.0) * 14.0;
        // Aimed at a triangle's vertex or its middle, so that most hit and
        // some graze an edge.
        let tri = set[(k.get1d(3) * set.len() as f32) as usize % set.len()];
        let aim = if i % 2 == 0 {
            tri[0]
        } else {
            (tri[0] + tri[1] + tri[2]) / 3.0
        };
        let Some(d) = (aim - o).try_normalize() else {
            continue;
        };
        let r = Ray::new(o, d);
        let Some((t_hit, _)) = brute(&r, 0.0) else {
            continue;
        };
        let _ = accel.closest(&r, 0.0, f32::INFINITY, &mut from_origin);
        let got = accel.closest(&r, t_hit, f32::INFINITY, &mut from_hit);
        assert_eq!(
            got.map(|h| (h.hit.t, h.hit.tri)),
            brute(&r, t_hit),
            "ray {i} from its hit"
        );
        assert!(
            accel.occluded(&r, t_hit, t_hit * 1.5 + 1.0, &mut rest),
            "ray {i}"
        );
        let beyond = t_hit.next_up();
        let got = accel.closest(&r, beyond, f32::INFINITY, &mut rest);
        assert_eq!(
            got.map(|h| (h.hit.t, h.hit.tri)),
            brute(&r, beyond),
            "ray {i} beyond its hit"
        );
        checked += 1;
    }
    assert!(checked > 1000, "only {checked} rays hit");
    // The same closest hits, found from the ray's origin and from the hit
    // itself: only the second can skip what lies before the hit.
    assert!(
        from_hit.bvh_nodes * 10 < from_origin.bvh_nodes * 9,
        "queries from their hit visited {} nodes, from the origin {}",
        from_hit.bvh_nodes,
        from_origin.bvh_nodes
    );
}

/// The closest of `set`'s triangles on `[t0, t1)` along `r` by the
/// watertight test, with its index: what a BVH query must find.
fn first_hit(set: &[[Vec3; 3]], r: &Ray, t0: f32, t1: f32) -> Option<(f32, u32)> {
    let w = WatertightRay::new(r);
    set.iter()
        .enumerate()
        .filter_map(|(i, v)| w.intersect(v, t0, t1).map(|h| (h.t, i as u32)))
        .min_by(|a, b| a.partial_cmp(b).unwrap())
}

/// The traversal compiled for AVX2 around the eight-wide node test and
/// the eight-lane triangle test gives every query the four-wide and
/// scalar one's answer, to the bit, visiting the same nodes and, for
/// closest hits, testing the same triangles: so processors with and
/// without AVX2 render the same image. (An occlusion query's lanes test
/// a whole load of triangles before they stop, so its count differs.
/// The brute-force tests check whichever of the two this processor
/// runs.)
#[test]
fn both_node_tests_trace_alike() {
    #[cfg(target_arch = "x86_64")]
    {
        if !std::arch::is_x86_feature_detected!("avx2") {
            eprintln!("both_node_tests_trace_alike: no AVX2 here; nothing to compare");
            return;
        }
        let set = soup(3000, 40);
        let ids: Vec<u32> = (0..set.len() as u32).collect();
        let accel = Accel::build(&set, &ids, 20.0);
        let (mut narrow, mut wide) = (TraceStats::default(), TraceStats::default());
        let (mut narrow_any, mut wide_any) = (TraceStats::default(), TraceStats::default());
        let mut hits = 0;
        for i in 0..4000u64 {
            let k = SampleKey::independent(i, 3, 9);
            let o = (Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 2.0 - 1.0) * 12.0;
            let mut d = Vec3::new(k.get1d(3), k.get1d(4), k.get1d(5)) * 2.0 - 1.0;
            if i % 3 != 0 {
                // Most rays aim at a triangle, so that many hit.
                d = set[(k.get1d(8) * set.len() as f32) as usize % set.len()][0] - o;
            }
            if i % 9 == 0 {
                d.y = 0.0;
            }
            let ray = Ray::new(o, d.normalize());
            let (t0, t1) = if i % 2 == 0 {
                (0.0, f32::INFINITY)
            } else {
                (k.get1d(6) * 4.0, 4.0 + k.get1d(7) * 20.0)
            };
            let a = accel.closest_with::<cwnode::Narrow, leaf::Scalar>(&ray, t0, t1, &mut narrow);
            // SAFETY: AVX2 is present (checked above).
            let b = unsafe { accel.closest_avx2(&ray, t0, t1, &mut wide) };
            let bits = |h: Option<AccelHit>| {
                h.map(|h| {
                    let hit = h.hit;
                    (
                        h.prim,
                        hit.tri,
                        hit.t.to_bits(),
                        hit.b1.to_bits(),
                        hit.b2.to_bits(),
                    )
                })
            };
            assert_eq!(bits(a), bits(b), "ray {i}");
            hits += usize::from(a.is_some());
            let a =
                accel.occluded_with::<cwnode::Narrow, leaf::Scalar>(&ray, t0, t1, &mut narrow_any);
            // SAFETY: as above.
            let b = unsafe { accel.occluded_avx2(&ray, t0, t1, &mut wide_any) };
            assert_eq!(a, b, "ray {i}, occlusion");
        }
        assert_eq!(
            (narrow.bvh_nodes, narrow.tri_tests),
            (wide.bvh_nodes, wide.tri_tests)
        );
        assert_eq!(narrow_any.bvh_nodes, wide_any.bvh_nodes);
        assert!(wide_any.tri_tests >= narrow_any.tri_tests);
        assert!(hits > 1000 && hits < 3900, "{hits} of 4000 rays hit");
    }
}

/// obvhs builds in parallel on the rayon pool it runs in (its
/// `parallel` feature), chunking work by the pool's size; the BVH must
/// not depend on it, so that a preview's per-leaf node counts and a
/// worker's traversal are the same on any machine. One pool's BVH
/// against another's, node for node and primitive for primitive.
#[test]
fn builds_alike_on_any_number_of_threads() {
    let set = soup(20_000, 200);
    let ids: Vec<u32> = (0..set.len() as u32).collect();
    let build = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        pool.install(|| Accel::build(&set, &ids, 20.0))
    };
    let one = build(1);
    let ids_of = |a: &Accel| a.meta.iter().map(|m| m.id).collect::<Vec<u32>>();
    for threads in [2, 3, 8] {
        let other = build(threads);
        assert!(one.bvh.nodes.len() > 1000, "{} nodes", one.bvh.nodes.len());
        assert!(
            one.bvh.nodes == other.bvh.nodes,
            "{threads} threads: the nodes differ"
        );
        assert_eq!(ids_of(&one), ids_of(&other), "{threads} threads");
    }
}
