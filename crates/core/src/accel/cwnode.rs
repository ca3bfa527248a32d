//! The CWBVH node test: obvhs's `CwBvhNode::intersect_ray_simd` with the
//! same arithmetic (so a query from its ray's origin visits the same
//! children, to the bit; one that starts along its ray also skips those
//! that end before its start, see [`NodeRay`]), made cheaper where a
//! profile showed it:
//!
//! - the quantised child bounds are widened with SSE4.1's `pmovzxbd` and
//!   one conversion, four children at once, where obvhs converts each byte
//!   alone (obvhs found the wide form slower in builds without SSE4.1,
//!   where it is a call; locus builds for x86-64-v2, see the README);
//! - which of a child's two planes is near is decided once per ray, as a
//!   byte offset into the node, not per node;
//! - the hit children are turned into the traversal mask in the SIMD
//!   lanes, without a branch per child (incoherent rays make each one a
//!   coin toss).
//!
//! Elsewhere (no SSE4.1) it is obvhs's own test.
//!
//! On a processor with AVX2 (found at run time: the build targets
//! x86-64-v2, which lacks it) the same test runs on all eight children at
//! once ([`Wide`]), and the traversal around it is compiled for AVX2 too
//! (see `Accel::closest`). Its lanes do the same products, sums and
//! comparisons, without fused multiply-adds, so the masks, and every hit,
//! are the same on either kind of processor, and a farm that mixes them
//! renders one machine's image.

use glam::Vec3A;
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::ray::Ray;

/// obvhs's lower bound on a child's entry distance (`node::EPSILON`, not
/// exported): the same value keeps the same children for a query from its
/// origin.
const ENTRY_MIN: f32 = 0.0001;

/// What a ray's node tests share: per axis, the byte offsets in a node of
/// the near and far quantised planes (which depend only on the direction's
/// signs), and the least entry distance a child may have and be visited.
#[derive(Clone, Copy)]
pub(crate) struct NodeRay {
    near: [usize; 3],
    far: [usize; 3],
    /// obvhs's [`ENTRY_MIN`], or the query's own start where that is
    /// later. A query that starts along its ray (a forwarded query's run
    /// in a region, or a resumed one) then skips the children that end
    /// before it, which can hold no hit it takes. Safe by the boxes'
    /// padding: a triangle's box reaches beyond every point of it by 2^-18
    /// of the scene's magnitude, far more than the slab test's rounding,
    /// and `tmin` is the start moved back by the ray's shift (`bvh_ray`).
    entry_min: f32,
}

impl NodeRay {
    #[inline(always)]
    pub(crate) fn new(r: &Ray) -> Self {
        use std::mem::offset_of;
        let lo = [
            offset_of!(CwBvhNode, child_min_x),
            offset_of!(CwBvhNode, child_min_y),
            offset_of!(CwBvhNode, child_min_z),
        ];
        let hi = [
            offset_of!(CwBvhNode, child_max_x),
            offset_of!(CwBvhNode, child_max_y),
            offset_of!(CwBvhNode, child_max_z),
        ];
        let d = r.direction.to_array();
        let pick = |a: usize, near: bool| {
            // A negative direction enters a box through its upper plane.
            if (d[a] < 0.0) == near { hi[a] } else { lo[a] }
        };
        Self {
            near: [pick(0, true), pick(1, true), pick(2, true)],
            far: [pick(0, false), pick(1, false), pick(2, false)],
            entry_min: r.tmin.max(ENTRY_MIN),
        }
    }
}

/// A form of the node test: the traversal is compiled once per form.
pub(crate) trait NodeTest {
    /// The traversal's hit mask for `node` (children in the ray's octant
    /// order, as obvhs's test returns it).
    fn intersect(node: &CwBvhNode, r: &Ray, nr: &NodeRay, oct_inv4: u32) -> u32;
}

/// Four children at a time (SSE4.1), or obvhs's own test.
pub(crate) struct Narrow;

impl NodeTest for Narrow {
    #[inline(always)]
    fn intersect(node: &CwBvhNode, r: &Ray, nr: &NodeRay, oct_inv4: u32) -> u32 {
        intersect(node, r, nr, oct_inv4)
    }
}

/// All eight children at once (AVX2). Only for code compiled with AVX2
/// enabled, which runs only where [`wide_available`] said so.
#[cfg(target_arch = "x86_64")]
pub(crate) struct Wide;

#[cfg(target_arch = "x86_64")]
impl NodeTest for Wide {
    #[inline(always)]
    fn intersect(node: &CwBvhNode, r: &Ray, nr: &NodeRay, oct_inv4: u32) -> u32 {
        // SAFETY: `Wide` is only used by traversals that run where AVX2 was
        // detected (`wide_available`); reads as in `intersect`.
        unsafe { intersect_avx2(node, r, nr, oct_inv4) }
    }
}

/// Whether this processor runs the [`Wide`] test: AVX2 is present and
/// `LOCUS_NODE_TEST=narrow` does not ask for the four-wide one (for
/// measuring one against the other on one machine).
#[inline(always)]
pub(crate) fn wide_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        use std::sync::LazyLock;
        static WIDE: LazyLock<bool> = LazyLock::new(|| {
            std::arch::is_x86_feature_detected!("avx2")
                && std::env::var("LOCUS_NODE_TEST").as_deref() != Ok("narrow")
        });
        *WIDE
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// The traversal's hit mask for `node` (children in the ray's octant
/// order, as obvhs's test returns it).
#[inline(always)]
pub(crate) fn intersect(node: &CwBvhNode, r: &Ray, nr: &NodeRay, oct_inv4: u32) -> u32 {
    #[cfg(all(target_arch = "x86_64", target_feature = "sse4.1"))]
    {
        // SAFETY: the target has SSE4.1 (checked at compile time), and every
        // read is four bytes inside `node` at a field offset plus 0 or 4.
        unsafe { intersect_sse41(node, r, nr, oct_inv4) }
    }
    #[cfg(not(all(target_arch = "x86_64", target_feature = "sse4.1")))]
    {
        let _ = nr;
        node.intersect_ray(r, oct_inv4)
    }
}

#[cfg(all(target_arch = "x86_64", target_feature = "sse4.1"))]
#[inline(always)]
unsafe fn intersect_sse41(node: &CwBvhNode, r: &Ray, nr: &NodeRay, oct_inv4: u32) -> u32 {
    use std::arch::x86_64::*;
    let inv = node.compute_extent() * r.inv_direction;
    let org = (Vec3A::from(node.p) - r.origin) * r.inv_direction;
    let base = (node as *const CwBvhNode).cast::<u8>();
    // SAFETY (for the block): see `intersect`.
    unsafe {
        let q = |off: usize| {
            let four = base.add(off).cast::<i32>().read_unaligned();
            _mm_cvtepi32_ps(_mm_cvtepu8_epi32(_mm_cvtsi32_si128(four)))
        };
        let (ix, iy, iz) = (_mm_set1_ps(inv.x), _mm_set1_ps(inv.y), _mm_set1_ps(inv.z));
        let (ox, oy, oz) = (_mm_set1_ps(org.x), _mm_set1_ps(org.y), _mm_set1_ps(org.z));
        let (entry_min, exit_max) = (_mm_set1_ps(nr.entry_min), _mm_set1_ps(r.tmax));
        // Each child's contribution to the mask is `bits << at` (its
        // leaf-or-inner bits at its octant-ordered position), kept where the
        // box is hit: computed in the lanes, `1 << at` as the float 2^at
        // truncated (2^31 truncates to 0x8000_0000, which is `1 << 31`).
        let (child_bits, bit_index) = node.get_child_and_index_bits(oct_inv4);
        let (bits8, at8) = (
            _mm_cvtsi64_si128(child_bits as i64),
            _mm_cvtsi64_si128(bit_index as i64),
        );
        let mut mask = _mm_setzero_si128();
        for half in 0..2 {
            let o = half * 4;
            // The same products and sums, in the same order, as obvhs's.
            let t = |off: usize, i: __m128, g: __m128| _mm_add_ps(_mm_mul_ps(q(off + o), i), g);
            let tmin_x = t(nr.near[0], ix, ox);
            let tmax_x = t(nr.far[0], ix, ox);
            let tmin_y = t(nr.near[1], iy, oy);
            let tmax_y = t(nr.far[1], iy, oy);
            let tmin_z = t(nr.near[2], iz, oz);
            let tmax_z = t(nr.far[2], iz, oz);
            let tmin = _mm_max_ps(tmin_x, _mm_max_ps(tmin_y, tmin_z));
            let tmax = _mm_min_ps(tmax_x, _mm_min_ps(tmax_y, tmax_z));
            let tmin = _mm_max_ps(tmin, entry_min);
            let tmax = _mm_min_ps(tmax, exit_max);
            let hit = _mm_castps_si128(_mm_cmple_ps(tmin, tmax));
            let (bits, at) = if half == 0 {
                (_mm_cvtepu8_epi32(bits8), _mm_cvtepu8_epi32(at8))
            } else {
                (
                    _mm_cvtepu8_epi32(_mm_srli_si128::<4>(bits8)),
                    _mm_cvtepu8_epi32(_mm_srli_si128::<4>(at8)),
                )
            };
            let exponent = _mm_slli_epi32::<23>(_mm_add_epi32(at, _mm_set1_epi32(127)));
            let pow2 = _mm_cvttps_epi32(_mm_castsi128_ps(exponent));
            mask = _mm_or_si128(mask, _mm_and_si128(hit, _mm_mullo_epi32(bits, pow2)));
        }
        let mask = _mm_or_si128(mask, _mm_shuffle_epi32::<0b01_00_11_10>(mask));
        let mask = _mm_or_si128(mask, _mm_shuffle_epi32::<0b10_11_00_01>(mask));
        _mm_cvtsi128_si32(mask) as u32
    }
}

/// `intersect_sse41` on all eight children at once: the same per-lane
/// arithmetic in 256-bit registers, and each child's `bits << at` by a
/// variable shift.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn intersect_avx2(node: &CwBvhNode, r: &Ray, nr: &NodeRay, oct_inv4: u32) -> u32 {
    use std::arch::x86_64::*;
    let inv = node.compute_extent() * r.inv_direction;
    let org = (Vec3A::from(node.p) - r.origin) * r.inv_direction;
    let base = (node as *const CwBvhNode).cast::<u8>();
    // SAFETY (for the block): AVX2 is enabled here, and every read is
    // eight bytes inside `node` at the offset of a field of eight bytes.
    unsafe {
        let q = |off: usize| {
            let eight = base.add(off).cast::<i64>().read_unaligned();
            _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_cvtsi64_si128(eight)))
        };
        let (ix, iy, iz) = (
            _mm256_set1_ps(inv.x),
            _mm256_set1_ps(inv.y),
            _mm256_set1_ps(inv.z),
        );
        let (ox, oy, oz) = (
            _mm256_set1_ps(org.x),
            _mm256_set1_ps(org.y),
            _mm256_set1_ps(org.z),
        );
        let t = |off: usize, i: __m256, g: __m256| _mm256_add_ps(_mm256_mul_ps(q(off), i), g);
        let tmin_x = t(nr.near[0], ix, ox);
        let tmax_x = t(nr.far[0], ix, ox);
        let tmin_y = t(nr.near[1], iy, oy);
        let tmax_y = t(nr.far[1], iy, oy);
        let tmin_z = t(nr.near[2], iz, oz);
        let tmax_z = t(nr.far[2], iz, oz);
        let tmin = _mm256_max_ps(tmin_x, _mm256_max_ps(tmin_y, tmin_z));
        let tmax = _mm256_min_ps(tmax_x, _mm256_min_ps(tmax_y, tmax_z));
        let tmin = _mm256_max_ps(tmin, _mm256_set1_ps(nr.entry_min));
        let tmax = _mm256_min_ps(tmax, _mm256_set1_ps(r.tmax));
        // `cmpleps`'s predicate: false when either side is NaN.
        let hit = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LE_OS>(tmin, tmax));
        // obvhs's `get_child_and_index_bits`, a byte per lane: an inner
        // child (meta bits 3 and 4 both set) is ordered by the ray's
        // octant, a leaf by its triangle offset.
        let meta = base
            .add(std::mem::offset_of!(CwBvhNode, child_meta))
            .cast::<i64>()
            .read_unaligned();
        let meta = _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(meta));
        let both = _mm256_and_si256(meta, _mm256_slli_epi32::<1>(meta));
        let sixteen = _mm256_set1_epi32(0x10);
        let inner = _mm256_cmpeq_epi32(_mm256_and_si256(both, sixteen), sixteen);
        let oct = _mm256_set1_epi32((oct_inv4 & 0xff) as i32);
        let at = _mm256_and_si256(
            _mm256_xor_si256(meta, _mm256_and_si256(oct, inner)),
            _mm256_set1_epi32(0x1f),
        );
        let bits = _mm256_and_si256(_mm256_srli_epi32::<5>(meta), _mm256_set1_epi32(7));
        let m = _mm256_and_si256(hit, _mm256_sllv_epi32(bits, at));
        let m = _mm_or_si128(_mm256_castsi256_si128(m), _mm256_extracti128_si256::<1>(m));
        let m = _mm_or_si128(m, _mm_shuffle_epi32::<0b01_00_11_10>(m));
        let m = _mm_or_si128(m, _mm_shuffle_epi32::<0b10_11_00_01>(m));
        _mm_cvtsi128_si32(m) as u32
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::SampleKey;
    use obvhs::aabb::Aabb;
    use obvhs::cwbvh::builder::build_cwbvh;

    /// Every node of a BVH over random boxes, against every kind of ray
    /// (directions with zero and negative components, clipped and open
    /// intervals): the mask is obvhs's, bit for bit.
    #[test]
    fn node_masks_match_obvhs() {
        let boxes: Vec<Aabb> = (0..2000u64)
            .map(|i| {
                let k = SampleKey::independent(i, 0, 11);
                let c = glam::Vec3A::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 20.0 - 10.0;
                let h = glam::Vec3A::new(k.get1d(3), k.get1d(4), k.get1d(5)) * 0.8 + 0.01;
                Aabb::new(c - h, c + h)
            })
            .collect();
        let bvh = build_cwbvh(
            &boxes,
            obvhs::BvhBuildParams::medium_build(),
            &mut Default::default(),
        );
        let mut checked = 0u64;
        let mut nonzero = 0u64;
        let mut wide_checked = 0u64;
        for i in 0..400u64 {
            let k = SampleKey::independent(i, 1, 11);
            let o = glam::Vec3A::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 24.0 - 12.0;
            let mut d = glam::Vec3A::new(k.get1d(3), k.get1d(4), k.get1d(5)) * 2.0 - 1.0;
            // Axis-parallel rays too: zero components give infinite inverses.
            if i % 7 == 0 {
                d.x = 0.0;
            }
            if i % 11 == 0 {
                d.y = 0.0;
            }
            let mut r = Ray::new_inf(o, d.normalize());
            if i % 2 == 1 {
                r.tmax = k.get1d(6) * 15.0;
            }
            let nr = NodeRay::new(&r);
            let oct_inv4 = bvh.new_traversal(r.direction).oct_inv4;
            for node in &bvh.nodes {
                let ours = intersect(node, &r, &nr, oct_inv4);
                assert_eq!(ours, node.intersect_ray(&r, oct_inv4), "ray {i}");
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: AVX2 is present.
                    let wide = unsafe { intersect_avx2(node, &r, &nr, oct_inv4) };
                    assert_eq!(wide, ours, "ray {i}, eight-wide");
                    wide_checked += 1;
                }
                checked += 1;
                nonzero += u64::from(ours != 0);
            }
        }
        assert!(
            checked > 10_000 && nonzero > 1_000,
            "{checked} tests, {nonzero} hit"
        );
        if wide_checked == 0 {
            // Said, not skipped quietly: this processor cannot run it.
            eprintln!("node_masks_match_obvhs: no AVX2 here; the eight-wide test was not run");
        }
    }
}
