//! Ray queries through an obvhs CWBVH over a set of triangles.
//!
//! The BVH is built over padded triangle boxes (see [`Accel::build`]), a
//! large triangle cut into several tighter boxes first (obvhs's spatial
//! pre-splits, after Embree's); the triangles are stored in BVH order with
//! their global ids and materials, once per box (on huge pages where the
//! kernel gives them: `pages`), and the global id stays the identity of a
//! triangle everywhere in locus.
//! Closest hits at equal distance resolve to the smaller global id, so the
//! answer does not depend on BVH layout, and therefore not on which worker
//! traced the ray. [`crate::accel_set::AccelSet`] traces several such BVHs
//! as one, which is how a worker bounds the memory a build needs.
//!
//! obvhs builds the binary tree (PLOC, then reinsertion); `convert`
//! collapses it into the eight-wide BVH as obvhs would, node for node, in
//! less time. `cwnode` and `leaf` are the traversal's node and triangle
//! tests, `walk` the traversal, `build` the build's steps and how much
//! each [`BuildQuality`] spends on them, `split` the pre-splits,
//! `pages` the huge-page arrays and `merge` the joining of BVHs built in
//! parts into one ([`Accel::join`]).

use crate::geometry::{Bounds, FLAT, Ray, TriHit, TriangleSet, WatertightRay};
use crate::octree::Octree;
use crate::stats::TraceStats;
use glam::{UVec2, Vec3, Vec3A};
use obvhs::cwbvh::CwBvh;
use std::ops::ControlFlow;

mod build;
mod convert;
mod cwnode;
pub(crate) use cwnode::wide_available;
mod layout;
mod leaf;
mod merge;
mod pages;
mod split;
mod walk;

use leaf::{LeafTest, Prims};

pub use build::{
    BUILD_BYTES_PER_TRIANGLE, BuildQuality, BvhSetting, QUICK_BELOW_SAMPLES_PER_TRIANGLE,
};
pub use layout::{Layout, ids_hash};

/// A closest hit: global triangle id plus distance and barycentrics.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub tri: u32,
    pub t: f32,
    pub b1: f32,
    pub b2: f32,
}

/// A hit and the position of its triangle in the BVH that found it, so the
/// triangle's vertices and material are read without a lookup.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AccelHit {
    pub hit: Hit,
    pub prim: u32,
}

/// A hit with the triangle it lies on: what shading needs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Surface {
    pub hit: Hit,
    pub verts: [Vec3; 3],
    pub material: u32,
    /// The shading normal interpolated at the hit (unit length), or zero
    /// for a flat triangle.
    pub shading: Vec3,
}

/// The closer of two hits; at equal distance the smaller global id, which
/// makes the answer independent of which BVH found which.
#[inline(always)]
pub fn closer(a: Option<AccelHit>, b: Option<AccelHit>) -> Option<AccelHit> {
    match (a, b) {
        (Some(x), Some(y)) => {
            if y.hit.t < x.hit.t || (y.hit.t == x.hit.t && y.hit.tri < x.hit.tri) {
                Some(y)
            } else {
                Some(x)
            }
        }
        (x, None) => x,
        (None, y) => y,
    }
}

#[derive(Clone)]
pub struct Accel {
    bvh: CwBvh,
    /// Triangle vertices in BVH primitive order, so leaf visits read
    /// contiguous memory.
    verts: Vec<[Vec3; 3]>,
    /// Global triangle id and material of each BVH primitive, side by
    /// side: a traversal reads the id of every triangle it hits, and the
    /// hit's surface then finds the material in the same cache line. Kept
    /// apart, the material was a miss of its own on every hit (`perf`: half
    /// the samples of a farm worker's tracer outside the BVH and the route,
    /// 341 to 170 on the room under `forward`).
    meta: Vec<PrimMeta>,
    /// Shading normals of each BVH primitive; empty when none has any.
    normals: Vec<[Vec3; 3]>,
    /// One primitive position per triangle, ordered by global id, for
    /// serving triangles by id (a split triangle's copies are identical).
    by_id: Vec<u32>,
    /// Bounds of the padded triangle boxes.
    bounds: Bounds,
}

/// A BVH primitive's global triangle id and material, kept together (see
/// `Accel::meta`).
#[derive(Clone, Copy, Debug)]
struct PrimMeta {
    id: u32,
    material: u32,
}

/// How far (in t) the ray handed to obvhs starts behind the real origin.
/// obvhs culls every child box whose exit distance is below its fixed
/// `EPSILON` (1e-4, whatever the ray's tmin), so a box that a ray leaves
/// within 1e-4 of its origin (a thin padded box around a triangle the
/// origin lies on) was dropped or kept depending on how large its BVH node
/// happened to be: a worker's BVH and the global one disagreed on hits at
/// t = 0. Starting the BVH ray 2.5 x 1e-4 earlier puts every box that
/// reaches the origin beyond that cull; triangle tests still use the real
/// ray, so no answer changes except those the cull got wrong.
const BVH_T_SHIFT: f32 = 2.5e-4;

/// obvhs stores 1/d clamped at 1/f32::EPSILON, which shrinks slab
/// intervals of near-parallel rays; a much larger clamp keeps the slabs
/// conservative without creating inf * 0. The origin moves back by
/// [`BVH_T_SHIFT`] along the ray; its rounding moves the ray by about an
/// ulp of the scene's magnitude, far inside the boxes' padding.
///
/// The clamp's sign follows `x < 0.0`, as the node test's near planes
/// ([`cwnode::NodeRay`]) and the ray's octant do. Taken from the sign bit
/// (obvhs's `safe_inverse` and `copysign` both do), a direction component
/// of -0.0, which negating an axis gives (`-Vec3::Z`), had a negative
/// inverse but positive near planes: every box's entry came out beyond
/// its exit, and such a ray hit nothing at all.
#[inline(always)]
fn bvh_ray(ray: &Ray, tmin: f32, tmax: f32) -> obvhs::ray::Ray {
    let inv = |x: f32| {
        if x.abs() < 1e-30 {
            if x < 0.0 { -1e30 } else { 1e30 }
        } else {
            1.0 / x
        }
    };
    obvhs::ray::Ray {
        origin: Vec3A::from(ray.origin - ray.dir * BVH_T_SHIFT),
        direction: Vec3A::from(ray.dir),
        inv_direction: Vec3A::new(inv(ray.dir.x), inv(ray.dir.y), inv(ray.dir.z)),
        // Shifted as the origin is, then taken back by as much again: the
        // node test skips children that end before `tmin`, with this as a
        // margin beyond the boxes' padding.
        tmin: tmin.max(0.0),
        tmax: tmax + BVH_T_SHIFT,
    }
}

impl Accel {
    /// Builds over the triangles `ids` of `all` (material 0 for every one).
    /// Each triangle's box is padded by 2^-18 of `magnitude` (the largest
    /// coordinate the rays and the scene reach), because obvhs's slab test
    /// rounds in f32 and could otherwise reject a box that a ray grazes at
    /// a vertex or an edge.
    pub fn build(all: &[[Vec3; 3]], ids: &[u32], magnitude: f32) -> Self {
        let verts: Vec<[Vec3; 3]> = ids.iter().map(|&i| all[i as usize]).collect();
        Self::build_indexed(ids, &verts, magnitude)
    }

    /// Builds over triangles given as parallel lists of global ids and
    /// vertices (material 0 for every one).
    pub fn build_indexed(ids: &[u32], verts: &[[Vec3; 3]], magnitude: f32) -> Self {
        assert_eq!(ids.len(), verts.len(), "one vertex triple per id");
        Self::from_set(
            TriangleSet {
                ids: ids.to_vec(),
                verts: verts.to_vec(),
                material: vec![0; ids.len()],
                normals: Vec::new(),
            },
            magnitude,
        )
    }

    /// Builds over a triangle set, which it keeps (in BVH order).
    pub fn from_set(set: TriangleSet, magnitude: f32) -> Self {
        Self::from_set_with(set, magnitude, BuildQuality::Full)
    }

    /// [`Self::from_set`] at the quality asked for.
    pub fn from_set_with(set: TriangleSet, magnitude: f32, quality: BuildQuality) -> Self {
        let layout = Layout::build(&set, magnitude, quality);
        Self::assemble(set, &layout)
    }

    /// The BVH over `set` whose shape another built ([`Layout::build`] of
    /// the same triangles), once [`Layout::check`] has shown it safe to
    /// walk: the same BVH the set's own build gives, for the cost of
    /// gathering the triangles into its order.
    pub fn from_layout(set: TriangleSet, layout: &Layout) -> Result<Self, String> {
        layout.check(&set)?;
        Ok(Self::assemble(set, layout))
    }

    /// The triangles of `set` stored in the order of the layout's boxes,
    /// with its nodes (copied: a layout shipped once may serve several
    /// workers of a process).
    fn assemble(set: TriangleSet, layout: &Layout) -> Self {
        let Layout {
            nodes,
            order,
            bounds,
            splits,
            ..
        } = layout;
        // The primitive index list is not needed: the triangles are
        // stored in the boxes' order (a split one at each of its boxes).
        let bvh = CwBvh {
            nodes: pages::collect(nodes.len(), nodes.iter().copied()),
            primitive_indices: Vec::new(),
            total_aabb: obvhs::aabb::Aabb::new(bounds.min.into(), bounds.max.into()),
            exact_node_aabbs: None,
            uses_spatial_splits: *splits,
        };
        let verts = pages::collect(order.len(), order.iter().map(|&p| set.verts[p as usize]));
        let meta: Vec<PrimMeta> = pages::collect(
            order.len(),
            order.iter().map(|&p| PrimMeta {
                id: set.ids[p as usize],
                material: set.material[p as usize],
            }),
        );
        let normals = if set.normals.is_empty() {
            Vec::new()
        } else {
            pages::collect(order.len(), order.iter().map(|&p| set.normals[p as usize]))
        };
        let by_id = if set.ids.is_sorted_by(|a, b| a < b) {
            // Ids in the set's order: a position's place among the ids is
            // its triangle's index in the set, so no sort is needed (it
            // took 10 ms of the room's build). A split triangle's first
            // box stands for it.
            let mut by_id = vec![u32::MAX; set.ids.len()];
            for (p, &t) in order.iter().enumerate() {
                let first = &mut by_id[t as usize];
                if *first == u32::MAX {
                    *first = p as u32;
                }
            }
            by_id.retain(|&p| p != u32::MAX);
            by_id
        } else {
            let mut by_id: Vec<u32> = (0..meta.len() as u32).collect();
            by_id.sort_unstable_by_key(|&p| meta[p as usize].id);
            by_id.dedup_by_key(|p| meta[*p as usize].id);
            by_id
        };
        drop(set);
        Self {
            bvh,
            verts,
            meta,
            normals,
            by_id,
            bounds: *bounds,
        }
    }

    /// Number of triangles the BVH holds (each once, however many boxes it
    /// was split into).
    pub fn len(&self) -> usize {
        self.by_id.len()
    }

    /// Number of boxes (BVH primitives): a triangle split into several
    /// counts once for each. At most a twentieth more than [`Self::len`].
    pub fn boxes(&self) -> usize {
        self.meta.len()
    }

    pub fn is_empty(&self) -> bool {
        self.meta.is_empty()
    }

    /// Bounds of every triangle box (padded); empty for an empty BVH.
    pub fn bounds(&self) -> Bounds {
        self.bounds
    }

    /// Heap bytes held: BVH nodes, vertices, ids, materials and the id
    /// index.
    pub fn bytes(&self) -> usize {
        use std::mem::size_of_val;
        size_of_val(self.bvh.nodes.as_slice())
            + size_of_val(self.verts.as_slice())
            + size_of_val(self.meta.as_slice())
            + size_of_val(self.normals.as_slice())
            + size_of_val(self.by_id.as_slice())
    }

    /// Whether this BVH was built over exactly `set`: the same triangle
    /// ids, vertices, materials and shading normals, bit for bit. A worker
    /// that is handed a BVH another built (the embedded farm's workers
    /// share one, see `locus_worker::builds`) checks it with this rather
    /// than trusting that equal keys mean equal triangles. False for a set
    /// whose ids do not ascend (no shipped region's).
    pub fn holds_exactly(&self, set: &TriangleSet) -> bool {
        let same = |a: &[Vec3; 3], b: &[Vec3; 3]| {
            a.iter()
                .zip(b)
                .all(|(a, b)| a.to_array().map(f32::to_bits) == b.to_array().map(f32::to_bits))
        };
        // `by_id` lists one position per triangle by ascending id, so the
        // set's k-th triangle is at `by_id[k]`.
        set.is_consistent()
            && set.ids.is_sorted_by(|a, b| a < b)
            && set.len() == self.by_id.len()
            && self.by_id.iter().enumerate().all(|(k, &p)| {
                let (p, m) = (p as usize, self.meta[p as usize]);
                m.id == set.ids[k]
                    && m.material == set.material[k]
                    && same(&self.verts[p], &set.verts[k])
                    && same(&self.shading(p as u32), &set.normals_of(k))
            })
    }

    /// The triangle at BVH position `prim`: vertices and material.
    #[inline(always)]
    pub fn triangle(&self, prim: u32) -> ([Vec3; 3], u32) {
        (self.verts[prim as usize], self.meta[prim as usize].material)
    }

    /// The shading normals of the triangle at BVH position `prim`
    /// ([`FLAT`] when it has none).
    #[inline(always)]
    pub fn shading(&self, prim: u32) -> [Vec3; 3] {
        self.normals.get(prim as usize).copied().unwrap_or(FLAT)
    }

    /// Whether any triangle here has shading normals.
    pub fn has_normals(&self) -> bool {
        !self.normals.is_empty()
    }

    /// The hit with its triangle.
    #[inline(always)]
    pub fn surface(&self, h: &AccelHit) -> Surface {
        let (verts, material) = self.triangle(h.prim);
        let shading = match self.normals.get(h.prim as usize) {
            Some(n) => crate::integrator::interpolate_normal(n, h.hit.b1, h.hit.b2),
            None => Vec3::ZERO,
        };
        Surface {
            hit: h.hit,
            verts,
            material,
            shading,
        }
    }

    /// Position of global id `id`, if this BVH holds it.
    pub fn find(&self, id: u32) -> Option<u32> {
        self.by_id
            .binary_search_by_key(&id, |&p| self.meta[p as usize].id)
            .ok()
            .map(|k| self.by_id[k])
    }

    /// Closest hit with `t0 <= t < t1`; ties in t go to the smaller global id.
    #[inline]
    pub fn closest(&self, ray: &Ray, t0: f32, t1: f32, stats: &mut TraceStats) -> Option<AccelHit> {
        if self.meta.is_empty() {
            return None;
        }
        #[cfg(target_arch = "x86_64")]
        if cwnode::wide_available() {
            // SAFETY: this processor has AVX2 (`wide_available`).
            return unsafe { self.closest_avx2(ray, t0, t1, stats) };
        }
        self.closest_narrow(ray, t0, t1, stats)
    }

    /// [`Self::closest`]'s traversal without AVX2. Kept out of line so that
    /// the dispatch above stays a few instructions a query: with it inlined
    /// there, every query through the AVX2 traversal paid for saving and
    /// restoring the registers and the stack frame the narrow one needs.
    #[inline(never)]
    fn closest_narrow(
        &self,
        ray: &Ray,
        t0: f32,
        t1: f32,
        stats: &mut TraceStats,
    ) -> Option<AccelHit> {
        self.closest_with::<cwnode::Narrow, leaf::Scalar>(ray, t0, t1, stats)
    }

    /// [`Self::closest`]'s traversal compiled for AVX2, around the
    /// eight-wide node test.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn closest_avx2(
        &self,
        ray: &Ray,
        t0: f32,
        t1: f32,
        stats: &mut TraceStats,
    ) -> Option<AccelHit> {
        self.closest_with::<cwnode::Wide, leaf::Wide>(ray, t0, t1, stats)
    }

    #[inline(always)]
    fn closest_with<N: cwnode::NodeTest, L: LeafTest>(
        &self,
        ray: &Ray,
        t0: f32,
        t1: f32,
        stats: &mut TraceStats,
    ) -> Option<AccelHit> {
        let w = WatertightRay::new(ray);
        let mut r = bvh_ray(ray, t0, t1);
        let nr = cwnode::NodeRay::new(&r);
        let mut best: Option<AccelHit> = None;
        let mut room = walk::slots();
        let mut state = walk::Walk::new(self.bvh.nodes.len(), r.direction, &mut room);
        let mut node;
        let mut nodes = 0u64;
        let mut tests = 0u64;
        obvhs::traverse!(
            self.bvh,
            node,
            state,
            {
                nodes += 1;
                N::intersect(node, &r, &nr, state.oct_inv4)
            },
            {
                // The whole group at once (see `group`): the macro then
                // finds it empty.
                let g = group(&mut state);
                tests += L::closest(&self.verts, &w, g, t0, t1, |p, h| {
                    let TriHit { t, b1, b2 } = h;
                    let id = self.meta[p as usize].id;
                    // A split triangle's boxes are primitives of their own
                    // with identical copies: between two of them the
                    // smaller position wins, whatever order a group's
                    // triangles were tested in (hits are never NaN).
                    let better = match best {
                        None => true,
                        Some(b) => (t, id, p) < (b.hit.t, b.hit.tri, b.prim),
                    };
                    if better {
                        best = Some(AccelHit {
                            hit: Hit { tri: id, t, b1, b2 },
                            prim: p,
                        });
                    }
                });
                // Equal-t primitives in other nodes are still visited:
                // obvhs keeps nodes with entry <= tmax.
                if let Some(b) = best {
                    r.tmax = b.hit.t + BVH_T_SHIFT;
                }
            }
        );
        stats.bvh_nodes += nodes;
        stats.tri_tests += tests;
        stats.bvh_queries += 1;
        best
    }

    /// Closest hit with `t0 <= t < t1` (see [`Self::closest`]).
    #[inline]
    pub fn intersect(&self, ray: &Ray, t0: f32, t1: f32, stats: &mut TraceStats) -> Option<Hit> {
        self.closest(ray, t0, t1, stats).map(|h| h.hit)
    }

    /// Whether anything blocks `[t0, t1)`.
    #[inline]
    pub fn occluded(&self, ray: &Ray, t0: f32, t1: f32, stats: &mut TraceStats) -> bool {
        if self.meta.is_empty() {
            return false;
        }
        #[cfg(target_arch = "x86_64")]
        if cwnode::wide_available() {
            // SAFETY: this processor has AVX2 (`wide_available`).
            return unsafe { self.occluded_avx2(ray, t0, t1, stats) };
        }
        self.occluded_narrow(ray, t0, t1, stats)
    }

    /// [`Self::occluded`]'s traversal without AVX2, out of line (see
    /// [`Self::closest_narrow`]).
    #[inline(never)]
    fn occluded_narrow(&self, ray: &Ray, t0: f32, t1: f32, stats: &mut TraceStats) -> bool {
        self.occluded_with::<cwnode::Narrow, leaf::Scalar>(ray, t0, t1, stats)
    }

    /// [`Self::occluded`]'s traversal compiled for AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn occluded_avx2(&self, ray: &Ray, t0: f32, t1: f32, stats: &mut TraceStats) -> bool {
        self.occluded_with::<cwnode::Wide, leaf::Wide>(ray, t0, t1, stats)
    }

    #[inline(always)]
    fn occluded_with<N: cwnode::NodeTest, L: LeafTest>(
        &self,
        ray: &Ray,
        t0: f32,
        t1: f32,
        stats: &mut TraceStats,
    ) -> bool {
        let w = WatertightRay::new(ray);
        let r = bvh_ray(ray, t0, t1);
        let nr = cwnode::NodeRay::new(&r);
        let mut room = walk::slots();
        let mut state = walk::Walk::new(self.bvh.nodes.len(), r.direction, &mut room);
        let mut node;
        let mut nodes = 0u64;
        let mut tests = 0u64;
        let mut hit = false;
        'outer: {
            obvhs::traverse!(
                self.bvh,
                node,
                state,
                {
                    nodes += 1;
                    N::intersect(node, &r, &nr, state.oct_inv4)
                },
                {
                    let g = group(&mut state);
                    let (any, n) = L::any(&self.verts, &w, g, t0, t1);
                    tests += n;
                    if any {
                        hit = true;
                        break 'outer;
                    }
                }
            );
        }
        stats.bvh_nodes += nodes;
        stats.tri_tests += tests;
        stats.bvh_queries += 1;
        hit
    }

    /// Closest hit restricted to the leaves for which `selected(leaf)` is
    /// true: the octree is walked along the ray and each maximal run of
    /// selected leaves is traced with the ray clipped to the run's interval.
    /// (A test oracle: workers trace through [`crate::region::trace_local`].)
    pub fn intersect_in_leaves(
        &self,
        octree: &Octree,
        selected: &dyn Fn(u32) -> bool,
        ray: &Ray,
        t0: f32,
        t1: f32,
        stats: &mut TraceStats,
    ) -> Option<Hit> {
        let mut run: Option<(f32, f32)> = None;
        let mut found = None;
        let flow = octree.walk(ray, t0, t1, |leaf, a, b| {
            if selected(leaf) {
                run = Some(match run {
                    Some((s, _)) => (s, b),
                    None => (a, b),
                });
                return ControlFlow::Continue(());
            }
            if let Some((s, e)) = run.take()
                && let Some(h) = self.intersect(ray, s, e, stats)
            {
                found = Some(h);
                return ControlFlow::Break(());
            }
            ControlFlow::Continue(())
        });
        if flow.is_continue()
            && let Some((s, e)) = run
        {
            found = self.intersect(ray, s, e, stats);
        }
        found
    }

    /// Raw obvhs traversal with obvhs's own triangle test, for measuring
    /// this module's overhead against the library (see `locus bench`).
    pub fn raw_obvhs_closest(&self, tris: &[obvhs::triangle::Triangle], ray: &Ray) -> f32 {
        let r = obvhs::ray::Ray::new_inf(ray.origin.into(), ray.dir.into());
        let mut hit = obvhs::ray::RayHit::none();
        self.bvh
            .ray_traverse(r, &mut hit, |r, id| tris[id].intersect(r));
        hit.t
    }

    /// The triangles in BVH primitive order as obvhs triangles, for
    /// [`Self::raw_obvhs_closest`].
    pub fn obvhs_triangles(&self) -> Vec<obvhs::triangle::Triangle> {
        self.verts
            .iter()
            .map(|v| obvhs::triangle::Triangle {
                v0: v[0].into(),
                v1: v[1].into(),
                v2: v[2].into(),
            })
            .collect()
    }
}

/// The primitive group obvhs's traversal is in, whole. The macro hands
/// the group over one primitive at a time, highest position first, and
/// has taken that one out of the mask; this takes the rest too, so the
/// macro finds the group empty and goes on to the next node.
#[inline(always)]
fn group(state: &mut walk::Walk<'_>) -> Prims {
    let base = state.primitive_group.x;
    let mask = state.primitive_group.y | (1 << (state.primitive_id - base));
    state.primitive_group.y = 0;
    Prims { base, mask }
}

// obvhs's traverse! macro names UVec2 unqualified.
#[allow(dead_code)]
type _UseUVec2 = UVec2;

#[cfg(test)]
mod tests;
