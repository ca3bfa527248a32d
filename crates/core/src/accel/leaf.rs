//! The triangles of a BVH's leaves in BVH primitive order, and the
//! watertight test run on a whole primitive group at once.
//!
//! A CWBVH node hands its traversal one group: the triangles of all its
//! leaf children the ray's box test kept, as a mask of up to 24 positions
//! after the node's first primitive. Where the processor has AVX2, a group
//! of three triangles or more is tested eight at a time: the lanes gather
//! their triangles' coordinates (masked, so no triangle outside the group
//! is read) and run the watertight test together, where it ran on one
//! triangle after another (in the Cornell box a query tests five
//! triangles in 1.4 nodes: the leaf tests, not the node tests, were most
//! of the tracing). Smaller groups stay with the scalar test, which leaves
//! a triangle at its first edge function of the wrong sign where the lanes
//! always run to the end. The triangles stay side by side, nine floats
//! each, as the scalar test and a hit's surface read them, so a leaf visit
//! touches the cache lines it did before. Stored by coordinate instead,
//! for plain loads in place of gathers, they cost more (callgrind on the
//! 325,000-triangle room: 19% more first-level cache misses in the
//! traversal with a run per leaf, two leaves a load, which then gained
//! nothing on the Cornell box either; a run per node was as fast as the
//! gathers on the Cornell box but spread a lone triangle over up to nine
//! lines).
//!
//! The lanes do the scalar test's products, differences and division in
//! the same order, without fused multiply-adds, and a lane whose edge
//! function is exactly zero goes to the scalar test (its f64 tie-break):
//! so every hit is the scalar test's, to the bit, and processors with and
//! without AVX2 render one image.

use crate::geometry::{SLIVER, TriHit, WatertightRay};
use glam::Vec3;

/// Lanes of one wide test.
#[cfg(target_arch = "x86_64")]
const LANES: usize = 8;

/// Groups of at most this many triangles are tested one at a time (see
/// the module's doc).
#[cfg(target_arch = "x86_64")]
const SCALAR_UP_TO: u32 = 2;

/// A primitive group: the primitives `base + i` for each bit `i` of
/// `mask`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Prims {
    pub base: u32,
    pub mask: u32,
}

/// A way of testing a primitive group: the traversal is compiled once per
/// way, beside its node test.
pub(crate) trait LeafTest {
    /// Tests the primitives of group `g` on `[t0, t1)` and calls `found`
    /// for each one hit, in no fixed order, until it returns false.
    /// Returns how many triangles were tested.
    fn each(
        tris: &[[Vec3; 3]],
        w: &WatertightRay,
        g: Prims,
        t0: f32,
        t1: f32,
        found: impl FnMut(u32, TriHit) -> bool,
    ) -> u64;

    /// Calls `hit` for every primitive of `g` hit on `[t0, t1)`; returns
    /// how many triangles were tested.
    #[inline(always)]
    fn closest(
        tris: &[[Vec3; 3]],
        w: &WatertightRay,
        g: Prims,
        t0: f32,
        t1: f32,
        mut hit: impl FnMut(u32, TriHit),
    ) -> u64 {
        Self::each(tris, w, g, t0, t1, |p, h| {
            hit(p, h);
            true
        })
    }

    /// Whether any primitive of `g` is hit on `[t0, t1)`, and how many
    /// triangles were tested to know.
    #[inline(always)]
    fn any(tris: &[[Vec3; 3]], w: &WatertightRay, g: Prims, t0: f32, t1: f32) -> (bool, u64) {
        let mut any = false;
        let tests = Self::each(tris, w, g, t0, t1, |_, _| {
            any = true;
            false
        });
        (any, tests)
    }
}

/// One triangle at a time, highest position first (obvhs's order).
pub(crate) struct Scalar;

impl LeafTest for Scalar {
    #[inline(always)]
    fn each(
        tris: &[[Vec3; 3]],
        w: &WatertightRay,
        g: Prims,
        t0: f32,
        t1: f32,
        mut found: impl FnMut(u32, TriHit) -> bool,
    ) -> u64 {
        let Prims { base, mut mask } = g;
        let mut tests = 0;
        while mask != 0 {
            let i = 31 - mask.leading_zeros();
            mask &= !(1 << i);
            tests += 1;
            let p = base + i;
            if let Some(h) = w.intersect(&tris[p as usize], t0, t1)
                && !found(p, h)
            {
                break;
            }
        }
        tests
    }
}

/// Eight triangles at a time (AVX2). Only for code compiled with AVX2
/// enabled, which runs only where the processor has it (see
/// `cwnode::wide_available`).
#[cfg(target_arch = "x86_64")]
pub(crate) struct Wide;

#[cfg(target_arch = "x86_64")]
impl Wide {
    /// The group eight positions at a time: the test of each load, its
    /// first primitive and its lanes, until `each` returns false.
    /// Returns how many triangles were tested.
    #[inline(always)]
    fn loads(
        tris: &[[Vec3; 3]],
        w: &WatertightRay,
        g: Prims,
        t0: f32,
        t1: f32,
        mut each: impl FnMut(&Lanes, u32, u32) -> bool,
    ) -> u64 {
        let mut rest = g.mask;
        let mut tests = 0;
        while rest != 0 {
            let lo = rest.trailing_zeros();
            let lanes = (rest >> lo) & 0xff;
            rest &= !(0xff << lo);
            tests += lanes.count_ones() as u64;
            let first = g.base + lo;
            // SAFETY: AVX2 is present (see `Wide`), and the lanes are
            // primitives of this BVH.
            let r = unsafe { test8(tris, w, first, lanes, t0, t1) };
            if !each(&r, first, lanes) {
                break;
            }
        }
        tests
    }
}

#[cfg(target_arch = "x86_64")]
impl LeafTest for Wide {
    #[inline(always)]
    fn each(
        tris: &[[Vec3; 3]],
        w: &WatertightRay,
        g: Prims,
        t0: f32,
        t1: f32,
        mut found: impl FnMut(u32, TriHit) -> bool,
    ) -> u64 {
        if g.mask.count_ones() <= SCALAR_UP_TO {
            return Scalar::each(tris, w, g, t0, t1, found);
        }
        Self::loads(tris, w, g, t0, t1, |r, first, lanes| {
            let mut hits = r.hit & lanes;
            while hits != 0 {
                let k = hits.trailing_zeros();
                hits &= hits - 1;
                let (k8, p) = (k as usize, first + k);
                let h = TriHit {
                    t: r.t[k8],
                    b1: r.b1[k8],
                    b2: r.b2[k8],
                };
                if !found(p, h) {
                    return false;
                }
            }
            let mut left = r.scalar & lanes;
            while left != 0 {
                let k = left.trailing_zeros();
                left &= left - 1;
                let p = first + k;
                if let Some(h) = w.intersect(&tris[p as usize], t0, t1)
                    && !found(p, h)
                {
                    return false;
                }
            }
            true
        })
    }
}

/// What eight lanes found: the lanes hit, their distances and
/// barycentrics, and the lanes left to the scalar test: those whose edge
/// functions cancelled exactly (it decides their signs in f64) and the
/// slivers the ray's line crosses (it refines their distances in f64; see
/// `geometry::refined_hit`).
#[cfg(target_arch = "x86_64")]
struct Lanes {
    hit: u32,
    scalar: u32,
    t: [f32; LANES],
    b1: [f32; LANES],
    b2: [f32; LANES],
}

/// The watertight test (`WatertightRay::intersect_axes`) on the
/// primitives `first + k` for the bits `k` of `lanes` (eight at most),
/// operation for operation. Other lanes read nothing and are not hits.
///
/// # Safety
/// AVX2 must be present, and every primitive of `lanes` inside `tris`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn test8(
    tris: &[[Vec3; 3]],
    w: &WatertightRay,
    first: u32,
    lanes: u32,
    t0: f32,
    t1: f32,
) -> Lanes {
    use std::arch::x86_64::*;
    let (kx, ky) = (w.kx, w.ky);
    let kz = 3 - kx - ky;
    // The origin in the shear's axis order, picked once a ray
    // (`WatertightRay::origin_k`): picked here by the runtime axes, it
    // cost more at every wide test (callgrind, the room's 500,000
    // incoherent rays: 579.6 M instructions against 571.4 M).
    let [o_x, o_y, o_z] = w.origin_k;
    debug_assert!(
        lanes < 256
            && (lanes == 0 || first as usize + (32 - lanes.leading_zeros()) as usize <= tris.len())
    );
    // SAFETY (for the block): AVX2 is enabled here, and the gathers read
    // only the lanes of `lanes`, each nine floats of a triangle in `tris`.
    unsafe {
        let d = tris.as_ptr().cast::<f32>().add(9 * first as usize);
        let which = _mm256_set1_epi32(lanes as i32);
        let bit = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
        let on = _mm256_castsi256_ps(_mm256_cmpeq_epi32(_mm256_and_si256(which, bit), bit));
        let index = _mm256_setr_epi32(0, 9, 18, 27, 36, 45, 54, 63);
        // Macros, not closures: a closure's body is not compiled for AVX2
        // and was called, not inlined (`perf`: a symbol of its own).
        macro_rules! load {
            ($k:expr) => {
                _mm256_mask_i32gather_ps::<4>(_mm256_setzero_ps(), d.add($k), index, on)
            };
        }
        let (ox, oy, oz) = (
            _mm256_set1_ps(o_x),
            _mm256_set1_ps(o_y),
            _mm256_set1_ps(o_z),
        );
        let (sx, sy, sz) = (
            _mm256_set1_ps(w.sx),
            _mm256_set1_ps(w.sy),
            _mm256_set1_ps(w.sz),
        );
        // Vertex v relative to the origin, sheared: (x, y) and the
        // unsheared z.
        macro_rules! vertex {
            ($v:expr) => {{
                let ax = _mm256_sub_ps(load!(3 * $v + kx), ox);
                let ay = _mm256_sub_ps(load!(3 * $v + ky), oy);
                let az = _mm256_sub_ps(load!(3 * $v + kz), oz);
                (
                    _mm256_sub_ps(ax, _mm256_mul_ps(sx, az)),
                    _mm256_sub_ps(ay, _mm256_mul_ps(sy, az)),
                    az,
                )
            }};
        }
        let (ax, ay, a_z) = vertex!(0);
        let (bx, by, b_z) = vertex!(1);
        let (cx, cy, c_z) = vertex!(2);
        macro_rules! edge {
            ($p:expr, $q:expr, $r:expr, $s:expr) => {
                _mm256_sub_ps(_mm256_mul_ps($p, $q), _mm256_mul_ps($r, $s))
            };
        }
        let u = edge!(cx, by, cy, bx);
        let v = edge!(ax, cy, ay, cx);
        let ww = edge!(bx, ay, by, ax);
        let zero = _mm256_setzero_ps();
        let is_zero = _mm256_or_ps(
            _mm256_cmp_ps::<_CMP_EQ_OQ>(u, zero),
            _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_EQ_OQ>(v, zero),
                _mm256_cmp_ps::<_CMP_EQ_OQ>(ww, zero),
            ),
        );
        let any_neg = _mm256_or_ps(
            _mm256_cmp_ps::<_CMP_LT_OQ>(u, zero),
            _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_LT_OQ>(v, zero),
                _mm256_cmp_ps::<_CMP_LT_OQ>(ww, zero),
            ),
        );
        let any_pos = _mm256_or_ps(
            _mm256_cmp_ps::<_CMP_GT_OQ>(u, zero),
            _mm256_or_ps(
                _mm256_cmp_ps::<_CMP_GT_OQ>(v, zero),
                _mm256_cmp_ps::<_CMP_GT_OQ>(ww, zero),
            ),
        );
        let det = _mm256_add_ps(_mm256_add_ps(u, v), ww);
        let (az, bz, cz) = (
            _mm256_mul_ps(sz, a_z),
            _mm256_mul_ps(sz, b_z),
            _mm256_mul_ps(sz, c_z),
        );
        let tt = _mm256_add_ps(
            _mm256_add_ps(_mm256_mul_ps(u, az), _mm256_mul_ps(v, bz)),
            _mm256_mul_ps(ww, cz),
        );
        let inv = _mm256_div_ps(_mm256_set1_ps(1.0), det);
        let t = _mm256_mul_ps(tt, inv);
        // Slivers as `WatertightRay::intersect_axes` finds them, operation
        // for operation: their distances are the scalar test's to refine.
        let sign = _mm256_set1_ps(-0.0);
        macro_rules! mag {
            ($p:expr, $q:expr) => {
                _mm256_andnot_ps(sign, _mm256_mul_ps($p, $q))
            };
        }
        let e = _mm256_add_ps(
            _mm256_add_ps(
                _mm256_add_ps(
                    _mm256_add_ps(_mm256_add_ps(mag!(cx, by), mag!(cy, bx)), mag!(ax, cy)),
                    mag!(ay, cx),
                ),
                mag!(bx, ay),
            ),
            mag!(by, ax),
        );
        let plain = _mm256_cmp_ps::<_CMP_LE_OQ>(
            e,
            _mm256_mul_ps(_mm256_set1_ps(SLIVER), _mm256_andnot_ps(sign, det)),
        );
        let agree = _mm256_andnot_ps(
            _mm256_or_ps(is_zero, _mm256_and_ps(any_neg, any_pos)),
            _mm256_cmp_ps::<_CMP_NEQ_OQ>(det, zero),
        );
        let ok = _mm256_and_ps(
            _mm256_and_ps(agree, plain),
            _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GE_OQ>(t, _mm256_set1_ps(t0)),
                _mm256_cmp_ps::<_CMP_LT_OQ>(t, _mm256_set1_ps(t1)),
            ),
        );
        let mut g = Lanes {
            hit: _mm256_movemask_ps(ok) as u32,
            scalar: _mm256_movemask_ps(_mm256_or_ps(is_zero, _mm256_andnot_ps(plain, agree)))
                as u32,
            t: [0.0; LANES],
            b1: [0.0; LANES],
            b2: [0.0; LANES],
        };
        if g.hit != 0 {
            _mm256_storeu_ps(g.t.as_mut_ptr(), t);
            _mm256_storeu_ps(g.b1.as_mut_ptr(), _mm256_mul_ps(v, inv));
            _mm256_storeu_ps(g.b2.as_mut_ptr(), _mm256_mul_ps(ww, inv));
        }
        g
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Ray;
    use crate::sampler::SampleKey;

    /// Triangles that make every branch of the test: ordinary ones, ones
    /// seen edge-on, ones sharing edges and vertices with their neighbours
    /// (rays through a shared edge or vertex cancel an edge function
    /// exactly), degenerate ones and ones behind the ray.
    fn awkward(n: u64) -> Vec<[Vec3; 3]> {
        (0..n)
            .map(|i| {
                let k = SampleKey::independent(i, 0, 21);
                let r = |d: u32| (k.get1d(d) * 8.0).floor() - 4.0;
                let a = Vec3::new(r(0), r(1), r(2));
                let b = Vec3::new(r(3), r(4), r(5));
                let c = match i % 6 {
                    0 => a,
                    1 => a + (b - a) * 0.5,
                    // A sliver, whose distance the scalar test refines.
                    2 => a + (b - a) * 0.5 + Vec3::new(1e-3, 2e-3, -1e-3),
                    _ => Vec3::new(r(6), r(7), r(8)),
                };
                [a, b, c]
            })
            .collect()
    }

    /// Every group mask over a set of awkward triangles, against rays
    /// through their vertices and edges and at random: the wide test
    /// reports exactly the scalar test's hits, to the bit, and the same
    /// answer to "any hit".
    #[test]
    fn eight_lanes_hit_what_one_does() {
        #[cfg(target_arch = "x86_64")]
        {
            if !std::arch::is_x86_feature_detected!("avx2") {
                eprintln!("eight_lanes_hit_what_one_does: no AVX2 here; nothing to compare");
                return;
            }
            let verts = awkward(120);
            // Leaves of one to three triangles, one after the other, as a
            // CWBVH lays them out.
            let mut runs = Vec::new();
            let mut base = 0u32;
            for n in [3, 1, 2, 3, 2, 3, 3].into_iter().cycle() {
                if base + n > verts.len() as u32 {
                    break;
                }
                runs.push((base, n));
                base += n;
            }
            let tris = &verts[..];
            let (mut hits, mut exact, mut slivers) = (0u64, 0u64, 0u64);
            for i in 0..3000u64 {
                let k = SampleKey::independent(i, 1, 21);
                let o = Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 12.0 - 6.0;
                let o = if i % 4 == 0 { o.round() } else { o };
                // A node's group: up to eight leaves from a random one.
                let first = (i % runs.len() as u64) as usize;
                let leaves = &runs[first..(first + 1 + (i % 8) as usize).min(runs.len())];
                let base = leaves[0].0;
                let n = leaves.iter().map(|r| r.1).sum::<u32>();
                let near = &verts[(base + (i as u32 % n)) as usize];
                let target = match i % 3 {
                    0 => near[(i / 3 % 3) as usize],
                    1 => (near[0] + near[1]) * 0.5,
                    _ => Vec3::new(k.get1d(3), k.get1d(4), k.get1d(5)) * 8.0 - 4.0,
                };
                let Some(d) = (target - o).try_normalize() else {
                    continue;
                };
                let w = WatertightRay::new(&Ray::new(o, d));
                let (t0, t1) = if i % 2 == 0 {
                    (0.0, f32::INFINITY)
                } else {
                    (0.5, 6.0)
                };
                let all = (1u32 << n) - 1;
                let mask = (k.get1d(6) * (1u32 << 24) as f32) as u32 & all;
                let mask = if i % 7 == 0 { all } else { mask };
                let g = Prims { base, mask };
                let mut scalar = Vec::new();
                let n1 = Scalar::closest(tris, &w, g, t0, t1, |p, h| scalar.push((p, h)));
                let mut wide = Vec::new();
                // SAFETY: AVX2 is present (checked above).
                let n8 = Wide::closest(tris, &w, g, t0, t1, |p, h| wide.push((p, h)));
                let bits = |v: &mut Vec<(u32, TriHit)>| {
                    v.sort_by_key(|x| x.0);
                    v.iter()
                        .map(|(p, h)| (*p, h.t.to_bits(), h.b1.to_bits(), h.b2.to_bits()))
                        .collect::<Vec<_>>()
                };
                assert_eq!(bits(&mut scalar), bits(&mut wide), "ray {i}, mask {mask:x}");
                assert_eq!(n1, n8);
                let (a, _) = Scalar::any(tris, &w, g, t0, t1);
                let (b, _) = Wide::any(tris, &w, g, t0, t1);
                assert_eq!(a, b, "ray {i}, any");
                assert_eq!(a, !scalar.is_empty());
                hits += scalar.len() as u64;
                // The lanes the scalar test decided (edge functions that
                // cancelled exactly, and slivers): count them, so that the
                // test is seen to reach its f64 branches.
                Wide::loads(tris, &w, g, t0, t1, |r, first, lanes| {
                    let left = r.scalar & lanes;
                    exact += left.count_ones() as u64;
                    slivers += (0..8)
                        .filter(|k| left >> k & 1 == 1 && (first + k) % 6 == 2)
                        .count() as u64;
                    true
                });
            }
            assert!(hits > 500, "{hits} hits");
            assert!(exact > 50, "{exact} lanes decided by the scalar test");
            assert!(
                slivers > 20,
                "{slivers} sliver lanes decided by the scalar test"
            );
        }
    }
}
