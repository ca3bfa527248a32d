//! Rays, bounds, the watertight ray/triangle test and robust ray spawning.
//!
//! The triangle test is Woop, Benthin and Wald, "Watertight Ray/Triangle
//! Intersection" (JCGT 2013): vertices are translated to the ray origin and
//! sheared so the ray runs along +z; the three 2D edge functions are then
//! computed from transformed vertices that neighbouring triangles share bit
//! for bit, so a ray through a shared edge or vertex hits at least one of the
//! triangles. Edge functions that round to exactly zero are recomputed in f64.

use glam::{DVec3, Vec3};

/// A ray with origin and unit direction. The parameter interval is passed
/// separately to every query, because the farm clips one ray to many
/// intervals (one per run of octree leaves).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
}

impl Ray {
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        Self { origin, dir }
    }
    #[inline(always)]
    pub fn at(&self, t: f32) -> Vec3 {
        self.origin + self.dir * t
    }
}

/// Axis-aligned bounds.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Bounds {
    pub min: Vec3,
    pub max: Vec3,
}

impl Bounds {
    pub const EMPTY: Bounds = Bounds {
        min: Vec3::splat(f32::INFINITY),
        max: Vec3::splat(f32::NEG_INFINITY),
    };
    pub fn new(min: Vec3, max: Vec3) -> Self {
        Self { min, max }
    }
    pub fn from_points(pts: &[Vec3]) -> Self {
        let mut b = Self::EMPTY;
        for &p in pts {
            b.grow(p);
        }
        b
    }
    /// Bounds of every vertex of `tris`.
    pub fn of_triangles(tris: &[[Vec3; 3]]) -> Self {
        let mut b = Self::EMPTY;
        for &p in tris.iter().flatten() {
            b.grow(p);
        }
        b
    }
    pub fn grow(&mut self, p: Vec3) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }
    pub fn is_empty(&self) -> bool {
        self.min.cmpgt(self.max).any()
    }
    pub fn extent(&self) -> Vec3 {
        self.max - self.min
    }
    /// Volume in f64 (zero for an empty or flat box).
    pub fn volume(&self) -> f64 {
        self.extent()
            .as_dvec3()
            .max(glam::DVec3::ZERO)
            .element_product()
    }
    pub fn center(&self) -> Vec3 {
        (self.min + self.max) * 0.5
    }
    /// Largest absolute coordinate: the magnitude that float rounding
    /// errors in this box scale with.
    pub fn max_abs(&self) -> f32 {
        self.min.abs().max(self.max.abs()).max_element()
    }
    pub fn contains(&self, p: Vec3) -> bool {
        p.cmpge(self.min).all() && p.cmple(self.max).all()
    }
    /// Parametric entry and exit of the ray, computed in f64 so the result
    /// is exact to well below the f32 spacing of the inputs. `None` when the
    /// ray misses or the overlap with [t0, t1) is empty.
    pub fn clip(&self, ray: &Ray, t0: f32, t1: f32) -> Option<(f32, f32)> {
        let mut lo = t0 as f64;
        let mut hi = t1 as f64;
        for a in 0..3 {
            let o = ray.origin[a] as f64;
            let d = ray.dir[a] as f64;
            let (bmin, bmax) = (self.min[a] as f64, self.max[a] as f64);
            if d == 0.0 {
                if o < bmin || o > bmax {
                    return None;
                }
                continue;
            }
            let (mut ta, mut tb) = ((bmin - o) / d, (bmax - o) / d);
            if ta > tb {
                std::mem::swap(&mut ta, &mut tb);
            }
            lo = lo.max(ta);
            hi = hi.min(tb);
        }
        (lo < hi).then_some((lo as f32, hi as f32))
    }
}

/// Triangles with their global ids and materials: a worker's region, a
/// fetched leaf, or a part of a chunked BVH. The lists run in parallel;
/// `normals` (each triangle's shading normals at its vertices, all zero for
/// a flat triangle) is empty when no triangle of the set has any.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TriangleSet {
    #[serde(with = "crate::bulk")]
    pub ids: Vec<u32>,
    #[serde(with = "crate::bulk")]
    pub verts: Vec<[Vec3; 3]>,
    #[serde(with = "crate::bulk")]
    pub material: Vec<u32>,
    #[serde(with = "crate::bulk")]
    pub normals: Vec<[Vec3; 3]>,
}

/// A flat triangle's shading normals: none.
pub const FLAT: [Vec3; 3] = [Vec3::ZERO; 3];

/// Bytes a triangle takes in a [`TriangleSet`] as shipped (id, vertices,
/// material), and its shading normals besides when it has them.
pub const TRIANGLE_BYTES: u64 = 4 + 36 + 4;
pub const NORMALS_BYTES: u64 = 36;

/// Bytes a triangle of a set with (or without) shading normals takes.
pub fn triangle_bytes(normals: bool) -> u64 {
    TRIANGLE_BYTES + if normals { NORMALS_BYTES } else { 0 }
}

impl TriangleSet {
    pub fn len(&self) -> usize {
        self.ids.len()
    }
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }
    pub fn with_capacity(n: usize) -> Self {
        Self {
            ids: Vec::with_capacity(n),
            verts: Vec::with_capacity(n),
            material: Vec::with_capacity(n),
            normals: Vec::new(),
        }
    }
    /// Adds a triangle; `normals` is [`FLAT`] for one without shading
    /// normals, which costs nothing while no triangle of the set has any.
    pub fn push(&mut self, id: u32, verts: [Vec3; 3], material: u32, normals: [Vec3; 3]) {
        if normals != FLAT || !self.normals.is_empty() {
            self.normals.resize(self.ids.len(), FLAT);
            self.normals.push(normals);
        }
        self.ids.push(id);
        self.verts.push(verts);
        self.material.push(material);
    }
    /// The triangles `ids` of a scene's lists (`normals` empty when the
    /// scene has none), as [`Self::push`] one by one would leave them, in
    /// a copy per list rather than a check per triangle.
    pub fn gather(
        ids: Vec<u32>,
        verts: &[[Vec3; 3]],
        material: &[u32],
        normals: &[[Vec3; 3]],
    ) -> Self {
        let pick = |list: &[[Vec3; 3]]| ids.iter().map(|&i| list[i as usize]).collect();
        let mut set = Self {
            verts: pick(verts),
            material: ids.iter().map(|&i| material[i as usize]).collect(),
            normals: if normals.is_empty() {
                Vec::new()
            } else {
                pick(normals)
            },
            ids,
        };
        if set.normals.iter().all(|n| *n == FLAT) {
            set.normals = Vec::new();
        }
        set
    }
    /// The shading normals of triangle `i` ([`FLAT`] when it has none).
    #[inline]
    pub fn normals_of(&self, i: usize) -> [Vec3; 3] {
        self.normals.get(i).copied().unwrap_or(FLAT)
    }

    /// Two sets whose ids ascend, as one whose ids ascend; a triangle in
    /// both (a triangle of two octree leaves shipped with each) is kept
    /// once, from `self`.
    pub fn merge(self, other: TriangleSet) -> TriangleSet {
        let mut out = TriangleSet::with_capacity(self.len() + other.len());
        let (mut i, mut j) = (0, 0);
        while i < self.len() || j < other.len() {
            let take_self = j == other.len() || (i < self.len() && self.ids[i] <= other.ids[j]);
            if take_self && j < other.len() && other.ids[j] == self.ids[i] {
                j += 1;
            }
            let (from, k) = if take_self {
                (&self, &mut i)
            } else {
                (&other, &mut j)
            };
            out.push(
                from.ids[*k],
                from.verts[*k],
                from.material[*k],
                from.normals_of(*k),
            );
            *k += 1;
        }
        out
    }
    /// Whether the lists agree in length.
    pub fn is_consistent(&self) -> bool {
        self.ids.len() == self.verts.len()
            && self.ids.len() == self.material.len()
            && (self.normals.is_empty() || self.normals.len() == self.ids.len())
    }
    /// Heap bytes of the lists (at their length, as shipped).
    pub fn bytes(&self) -> usize {
        self.len() * TRIANGLE_BYTES as usize + self.normals.len() * NORMALS_BYTES as usize
    }
}

#[cfg(test)]
mod triangle_set_tests {
    use super::*;

    /// Gathered at once, a set is what pushing its triangles one by one
    /// leaves, with and without shading normals in the scene and in the
    /// chosen triangles.
    #[test]
    fn a_gathered_set_is_the_pushed_one() {
        let verts: Vec<[Vec3; 3]> = (0..20)
            .map(|i| [Vec3::splat(i as f32), Vec3::X * i as f32, Vec3::Y])
            .collect();
        let material: Vec<u32> = (0..20).map(|i| i % 3).collect();
        let mut normals = vec![FLAT; 20];
        normals[7] = [Vec3::Z; 3];
        for scene_normals in [Vec::new(), normals.clone()] {
            for ids in [vec![0u32, 3, 7, 19], vec![1, 2, 3], vec![], vec![7]] {
                let mut pushed = TriangleSet::default();
                for &i in &ids {
                    let n = scene_normals.get(i as usize).copied().unwrap_or(FLAT);
                    pushed.push(i, verts[i as usize], material[i as usize], n);
                }
                let gathered = TriangleSet::gather(ids.clone(), &verts, &material, &scene_normals);
                assert_eq!(gathered, pushed, "{ids:?}, normals {}", scene_normals.len());
            }
        }
    }

    #[test]
    fn normals_are_kept_from_the_first_shaded_triangle_on() {
        let t = [Vec3::ZERO, Vec3::X, Vec3::Y];
        let n = [Vec3::Z; 3];
        let mut s = TriangleSet::default();
        s.push(0, t, 0, FLAT);
        assert!(s.normals.is_empty(), "flat triangles cost nothing");
        s.push(1, t, 0, n);
        s.push(2, t, 0, FLAT);
        assert_eq!(s.normals, vec![FLAT, n, FLAT]);
        assert!(s.is_consistent());
        assert_eq!(s.normals_of(1), n);
        let mut first = TriangleSet::default();
        first.push(7, t, 0, n);
        assert_eq!(first.normals, vec![n]);
        assert_eq!(first.bytes(), 80);
    }
}

/// A ray/triangle hit: distance and the barycentric weights of v1 and v2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriHit {
    pub t: f32,
    pub b1: f32,
    pub b2: f32,
}

/// Per-ray constants of the watertight test (the shear that maps the ray
/// to +z). Computing them once per ray rather than per triangle is the
/// point of the precomputation.
#[derive(Clone, Copy, Debug)]
pub struct WatertightRay {
    pub(crate) kx: usize,
    pub(crate) ky: usize,
    pub(crate) sx: f32,
    pub(crate) sy: f32,
    pub(crate) sz: f32,
    /// The ray's origin, its components in the order `kx`, `ky`, `kz`
    /// (the shear's axes): the scalar test's six compiled axis orders
    /// share them (see [`Self::intersect_axes`]), and the eight-wide test
    /// reads them without a runtime index.
    pub(crate) origin_k: [f32; 3],
}

impl WatertightRay {
    #[inline(always)]
    pub fn new(ray: &Ray) -> Self {
        // The dominant axis kz and the two others, without branches: the
        // directions of incoherent rays make every branch here a coin
        // toss, and its mispredictions cost about a tenth of a ray.
        let a = ray.dir.abs();
        let (xy, xz, yz) = (
            (a.x > a.y) as usize,
            (a.x > a.z) as usize,
            (a.y > a.z) as usize,
        );
        let kz = 2 - 2 * (xy & xz) - ((1 - xy) & yz);
        let d = ray.dir.to_array();
        // Keep the winding of the projected triangle independent of the sign
        // of the dominant direction component: a negative one swaps kx, ky.
        const KX: [[usize; 2]; 3] = [[1, 2], [2, 0], [0, 1]];
        const KY: [[usize; 2]; 3] = [[2, 1], [0, 2], [1, 0]];
        let neg = (d[kz] < 0.0) as usize;
        let (kx, ky) = (KX[kz][neg], KY[kz][neg]);
        let dz = d[kz];
        let o = ray.origin.to_array();
        Self {
            origin_k: [o[kx], o[ky], o[kz]],
            kx,
            ky,
            sx: d[kx] / dz,
            sy: d[ky] / dz,
            sz: 1.0 / dz,
        }
    }

    /// Intersects the triangle (v0, v1, v2); a hit is reported only for
    /// `t0 <= t < t1`. Both faces are hit (no culling).
    #[inline(always)]
    pub fn intersect(&self, v: &[Vec3; 3], t0: f32, t1: f32) -> Option<TriHit> {
        // The axes as constants: indexing a vector by a runtime axis is a
        // three-way branch per component (about a tenth of all the
        // instructions a path spends), where this is one well-predicted
        // branch per triangle. The arithmetic is the same, bit for bit.
        match (self.kx, self.ky) {
            (1, 2) => self.intersect_axes::<1, 2, 0>(v, t0, t1),
            (2, 1) => self.intersect_axes::<2, 1, 0>(v, t0, t1),
            (2, 0) => self.intersect_axes::<2, 0, 1>(v, t0, t1),
            (0, 2) => self.intersect_axes::<0, 2, 1>(v, t0, t1),
            (0, 1) => self.intersect_axes::<0, 1, 2>(v, t0, t1),
            _ => self.intersect_axes::<1, 0, 2>(v, t0, t1),
        }
    }

    #[inline(always)]
    fn intersect_axes<const KX: usize, const KY: usize, const KZ: usize>(
        &self,
        v: &[Vec3; 3],
        t0: f32,
        t1: f32,
    ) -> Option<TriHit> {
        // Each vertex less the origin in the sheared frame's axis order:
        // the same differences as `(v - origin)[k]`, with the origin's
        // components picked once a ray (`origin_k`), so that the six
        // compiled orders do not each keep their own copy of them.
        let [ox, oy, oz] = self.origin_k;
        let rel = |p: &Vec3| [p[KX] - ox, p[KY] - oy, p[KZ] - oz];
        let (a, b, c) = (rel(&v[0]), rel(&v[1]), rel(&v[2]));
        let ax = a[0] - self.sx * a[2];
        let ay = a[1] - self.sy * a[2];
        let bx = b[0] - self.sx * b[2];
        let by = b[1] - self.sy * b[2];
        let cx = c[0] - self.sx * c[2];
        let cy = c[1] - self.sy * c[2];
        let mut u = cx * by - cy * bx;
        let mut vv = ax * cy - ay * cx;
        let mut w = bx * ay - by * ax;
        if u == 0.0 || vv == 0.0 || w == 0.0 {
            // The f32 products cancelled exactly: decide the sign in f64,
            // where the products of f32 values are exact.
            let (ax, ay, bx, by, cx, cy) = (
                ax as f64, ay as f64, bx as f64, by as f64, cx as f64, cy as f64,
            );
            u = (cx * by - cy * bx) as f32;
            vv = (ax * cy - ay * cx) as f32;
            w = (bx * ay - by * ax) as f32;
        }
        if (u < 0.0 || vv < 0.0 || w < 0.0) && (u > 0.0 || vv > 0.0 || w > 0.0) {
            return None;
        }
        let det = u + vv + w;
        if det == 0.0 {
            return None;
        }
        let az = self.sz * a[2];
        let bz = self.sz * b[2];
        let cz = self.sz * c[2];
        let tt = u * az + vv * bz + w * cz;
        let inv = 1.0 / det;
        let t = tt * inv;
        let e = (cx * by).abs()
            + (cy * bx).abs()
            + (ax * cy).abs()
            + (ay * cx).abs()
            + (bx * ay).abs()
            + (by * ax).abs();
        if e <= SLIVER * det.abs() {
            if !(t >= t0 && t < t1) {
                return None;
            }
            return Some(TriHit {
                t,
                b1: vv * inv,
                b2: w * inv,
            });
        }
        let dt = t_error_bound(e, [az, bz, cz], det, t);
        if !(t + dt >= t0 && t - dt < t1) {
            return None;
        }
        let h = refined_hit(&[ax, ay, bx, by, cx, cy], [az, bz, cz]);
        (h.t >= t0 && h.t < t1).then_some(h)
    }
}

/// A triangle whose edge functions' products add up to more than this
/// times their sum is a sliver as the ray sees it: its f32 distance can be
/// off by more than the BVH's box padding, and [`refined_hit`] gives it.
/// Below it, [`t_error_bound`] keeps the f32 distance within about 2^-18
/// of the hit's depth, well inside the padding, as it always was.
pub const SLIVER: f32 = 4.0;

/// Twice the unit roundoff of the f32 test's steps, with room for the
/// bound's own rounding.
const T_BOUND_EPS: f32 = 1.0 / (1u32 << 21) as f32;

/// How far the f32 distance `t` of the watertight test can lie from the
/// exact distance through the same sheared triangle: `e` the sum of the
/// magnitudes of the edge functions' six products, `z` the scaled depths,
/// `det` the sum of the edge functions. Each edge function is off by at
/// most two units of roundoff times its two products, and the three share
/// one sign here, so `det` is their magnitudes' sum. For a long thin
/// sliver `det` is tiny against `e`, and `t` can be off by far more than
/// the BVH's box padding: on the country kitchen a sliver 0.5 mm wide and
/// 4.3 m long came out 2.8e-4 nearer than it is, in front of the triangle
/// the ray really meets first, and only a BVH whose boxes let the ray
/// reach the sliver found it, so one machine and a farm worker gave
/// different answers. Infinite where the rounding could swamp `det`.
#[inline(always)]
fn t_error_bound(e: f32, z: [f32; 3], det: f32, t: f32) -> f32 {
    let zm = z[0].abs().max(z[1].abs()).max(z[2].abs());
    let room = det.abs() - T_BOUND_EPS * e;
    if room <= 0.0 {
        return f32::INFINITY;
    }
    T_BOUND_EPS * (e / room + 3.0) * (zm + t.abs())
}

/// The hit of the watertight test recomputed in f64 from its sheared
/// coordinates: their products are exact there, so the edge functions,
/// the distance and the barycentrics come out to about 1e-13 even for a
/// sliver, and a hit's distance no longer depends on how it was rounded.
/// This is what makes a closest hit a pure function of the ray and the
/// triangles: a hit point is then within rounding of the triangle, so
/// inside its padded box, and no BVH can cull it while another finds it.
#[inline(never)]
fn refined_hit(sheared: &[f32; 6], z: [f32; 3]) -> TriHit {
    let [ax, ay, bx, by, cx, cy] = sheared.map(f64::from);
    let [az, bz, cz] = z.map(f64::from);
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    let det = u + v + w;
    let t = (u * az + v * bz + w * cz) / det;
    TriHit {
        t: t as f32,
        b1: (v / det) as f32,
        b2: (w / det) as f32,
    }
}

/// Unnormalised geometric normal (cross product of the edges); its length is
/// twice the area.
#[inline(always)]
pub fn tri_cross(v: &[Vec3; 3]) -> Vec3 {
    (v[1] - v[0]).cross(v[2] - v[0])
}

/// Area computed in f64 so that slivers are measured, not rounded to zero
/// or inflated by cancellation.
pub fn tri_area_f64(v: &[Vec3; 3]) -> f64 {
    let a = v[0].as_dvec3();
    let e1 = v[1].as_dvec3() - a;
    let e2 = v[2].as_dvec3() - a;
    0.5 * e1.cross(e2).length()
}

/// Relative size of the spawn offset: 2^-18 of the coordinate magnitude is
/// about 32 f32 ulps, well above the error of a barycentric hit point and far
/// below any feature of a scene expressed in that magnitude.
pub const SPAWN_OFFSET_REL: f32 = 1.0 / (1u32 << 18) as f32;

/// Offset for a point on triangle `v`: proportional to the largest vertex
/// coordinate, so the same relative safety holds at 1e-3 and at 1e5.
#[inline(always)]
pub fn spawn_offset(v: &[Vec3; 3]) -> f32 {
    let m = v[0].abs().max(v[1].abs()).max(v[2].abs()).max_element();
    m * SPAWN_OFFSET_REL + f32::MIN_POSITIVE
}

/// Moves `p` off its surface along the geometric normal `n` (unit), to the
/// side that `towards` points into.
#[inline(always)]
pub fn offset_point(p: Vec3, n: Vec3, towards: Vec3, offset: f32) -> Vec3 {
    if n.dot(towards) >= 0.0 {
        p + n * offset
    } else {
        p - n * offset
    }
}

/// Barycentric interpolation of the hit point: more accurate than
/// `o + t d` because its error scales with the triangle's coordinates,
/// not with the distance travelled.
#[inline(always)]
pub fn hit_point(v: &[Vec3; 3], b1: f32, b2: f32) -> Vec3 {
    let b0 = 1.0 - b1 - b2;
    v[0] * b0 + v[1] * b1 + v[2] * b2
}

/// An orthonormal basis around unit `n` (Duff et al. 2017, branchless).
#[inline(always)]
pub fn basis(n: Vec3) -> (Vec3, Vec3) {
    let s = 1.0f32.copysign(n.z);
    let a = -1.0 / (s + n.z);
    let b = n.x * n.y * a;
    (
        Vec3::new(1.0 + s * n.x * n.x * a, s * b, -s * n.x),
        Vec3::new(b, s + n.y * n.y * a, -n.y),
    )
}

/// `(sin 2πu, cos 2πu)` for `u` in [0, 1], within 1e-7 of the exact
/// values, in plain f32 arithmetic: the same bits on every processor.
/// The C library's `sincosf` picks its code by the processor (glibc has
/// one variant for processors with fused multiply-add and one without),
/// so its last bit could differ between two machines of one farm; it also
/// cost a vertex about fifty instructions more than this.
///
/// `4u` splits exactly into a quadrant `q` and a remainder in [-1/2, 1/2],
/// whose angle (at most π/4) takes short Taylor series (the first term
/// left out is below 2e-8 of the result there); the quadrant then swaps
/// and negates them.
#[inline(always)]
pub fn sin_cos_turns(u: f32) -> (f32, f32) {
    let v = 4.0 * u;
    let q = v.round();
    let x = (v - q) * std::f32::consts::FRAC_PI_2;
    let x2 = x * x;
    let s = x
        * (1.0
            + x2 * (-1.0 / 6.0
                + x2 * (1.0 / 120.0 + x2 * (-1.0 / 5040.0 + x2 * (1.0 / 362_880.0)))));
    let c = 1.0 + x2 * (-0.5 + x2 * (1.0 / 24.0 + x2 * (-1.0 / 720.0 + x2 * (1.0 / 40_320.0))));
    match (q as i32) & 3 {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    }
}

/// Cosine-weighted direction around unit `n`; pdf is cos(theta) / pi.
#[inline(always)]
pub fn cosine_hemisphere(n: Vec3, u: [f32; 2]) -> Vec3 {
    let r = u[0].sqrt();
    let (s, c) = sin_cos_turns(u[1]);
    let z = (1.0 - u[0]).max(0.0).sqrt();
    let (t, b) = basis(n);
    (t * (r * c) + b * (r * s) + n * z).normalize()
}

/// Uniform point on a triangle as barycentrics (b1, b2) (the square-root
/// warp of Osada et al.).
#[inline(always)]
pub fn uniform_triangle(u: [f32; 2]) -> (f32, f32) {
    let su = u[0].sqrt();
    (u[1] * su, 1.0 - su)
}

/// Brute-force reference: f64 barycentric test used only by tests.
pub fn intersect_f64(ray: &Ray, v: &[Vec3; 3]) -> Option<f64> {
    let o: DVec3 = ray.origin.as_dvec3();
    let d: DVec3 = ray.dir.as_dvec3();
    let p0 = v[0].as_dvec3();
    let e1 = v[1].as_dvec3() - p0;
    let e2 = v[2].as_dvec3() - p0;
    let pv = d.cross(e2);
    let det = e1.dot(pv);
    if det.abs() < 1e-300 {
        return None;
    }
    let inv = 1.0 / det;
    let tv = o - p0;
    let u = tv.dot(pv) * inv;
    let qv = tv.cross(e1);
    let w = d.dot(qv) * inv;
    if u < 0.0 || w < 0.0 || u + w > 1.0 {
        return None;
    }
    Some(e2.dot(qv) * inv)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Merging keeps the ids ascending, each triangle once with its own
    /// vertices, material and normals, whichever set holds it.
    #[test]
    fn merged_sets_ascend_with_each_triangle_once() {
        let set = |ids: &[u32], normals: bool| {
            let mut s = TriangleSet::with_capacity(ids.len());
            for &id in ids {
                let v = Vec3::splat(id as f32);
                let n = if normals { [Vec3::Z; 3] } else { FLAT };
                s.push(id, [v, v + Vec3::X, v + Vec3::Y], id % 3, n);
            }
            s
        };
        let m = set(&[1, 4, 5, 9], false).merge(set(&[0, 4, 7, 9, 12], true));
        assert_eq!(m.ids, vec![0, 1, 4, 5, 7, 9, 12]);
        assert!(m.is_consistent());
        for (k, &id) in m.ids.iter().enumerate() {
            assert_eq!(m.verts[k][0], Vec3::splat(id as f32));
            assert_eq!(m.material[k], id % 3);
        }
        // Normals where the set that kept the triangle had them.
        assert_eq!(m.normals_of(0), [Vec3::Z; 3]);
        assert_eq!(m.normals_of(1), FLAT);
        assert_eq!(m.normals_of(2), FLAT);
        assert_eq!(m.normals_of(4), [Vec3::Z; 3]);
        assert_eq!(set(&[], false).merge(set(&[2], false)).ids, vec![2]);
    }

    #[test]
    fn hits_and_misses_simple_triangle() {
        let tri = [Vec3::ZERO, Vec3::X, Vec3::Y];
        let ray = Ray::new(Vec3::new(0.25, 0.25, 1.0), -Vec3::Z);
        let h = WatertightRay::new(&ray)
            .intersect(&tri, 0.0, f32::INFINITY)
            .unwrap();
        assert!((h.t - 1.0).abs() < 1e-6);
        assert!((h.b1 - 0.25).abs() < 1e-6 && (h.b2 - 0.25).abs() < 1e-6);
        let miss = Ray::new(Vec3::new(0.75, 0.75, 1.0), -Vec3::Z);
        assert!(
            WatertightRay::new(&miss)
                .intersect(&tri, 0.0, f32::INFINITY)
                .is_none()
        );
        // Interval is half-open: a hit at exactly t1 is not reported.
        assert!(WatertightRay::new(&ray).intersect(&tri, 0.0, 1.0).is_none());
        assert!(WatertightRay::new(&ray).intersect(&tri, 1.0, 2.0).is_some());
    }

    #[test]
    fn shared_edge_hits_one_of_two() {
        // Two triangles sharing the diagonal of a unit square; rays aimed at
        // points exactly on the diagonal must hit at least one of them.
        let a = [Vec3::ZERO, Vec3::X, Vec3::ONE.with_z(0.0)];
        let b = [Vec3::ZERO, Vec3::ONE.with_z(0.0), Vec3::Y];
        // The end points are outer corners of the square, where a ray may
        // legitimately pass outside; every interior point must be hit.
        for i in 1..1000 {
            let s = i as f32 / 1000.0;
            let target = Vec3::new(s, s, 0.0);
            let origin = Vec3::new(0.3, -0.7, 2.1);
            let ray = Ray::new(origin, (target - origin).normalize());
            let w = WatertightRay::new(&ray);
            let hit = w.intersect(&a, 0.0, f32::INFINITY).is_some()
                || w.intersect(&b, 0.0, f32::INFINITY).is_some();
            assert!(hit, "ray through diagonal point {s} escaped");
        }
    }

    /// Against f64's sine and cosine over a fine grid of the unit interval
    /// (every quadrant's ends included) and the exact values at the
    /// quarter turns.
    #[test]
    fn sin_cos_turns_is_within_a_few_ulps() {
        let n = 1 << 20;
        let mut worst = 0.0f64;
        for i in 0..=n {
            let u = i as f32 / n as f32;
            let (s, c) = sin_cos_turns(u);
            let a = std::f64::consts::TAU * u as f64;
            worst = worst
                .max((s as f64 - a.sin()).abs())
                .max((c as f64 - a.cos()).abs());
        }
        assert!(worst < 1e-7, "worst error {worst:e}");
        assert_eq!(sin_cos_turns(0.0), (0.0, 1.0));
        assert_eq!(sin_cos_turns(0.25), (1.0, -0.0));
        assert_eq!(sin_cos_turns(0.5), (-0.0, -1.0));
        assert_eq!(sin_cos_turns(0.75), (-1.0, 0.0));
        assert_eq!(sin_cos_turns(1.0), (0.0, 1.0));
    }

    #[test]
    fn cosine_hemisphere_is_unit_and_upper() {
        let n = Vec3::new(0.3, -0.5, 0.8).normalize();
        for i in 0..1000 {
            let u = [
                (i as f32 + 0.5) / 1000.0,
                ((i * 7919) % 1000) as f32 / 1000.0,
            ];
            let w = cosine_hemisphere(n, u);
            assert!((w.length() - 1.0).abs() < 1e-5);
            assert!(w.dot(n) >= -1e-6);
        }
    }

    /// The branchless axis choice is the branching one it replaced: the
    /// dominant axis (ties to the later axis, NaN to z), the next two in
    /// cyclic order, swapped when the dominant component is negative.
    #[test]
    fn watertight_axes_match_their_definition() {
        let reference = |d: Vec3| {
            let a = d.abs();
            let kz = if a.x > a.y {
                if a.x > a.z { 0 } else { 2 }
            } else if a.y > a.z {
                1
            } else {
                2
            };
            let (kx, ky) = ((kz + 1) % 3, (kz + 2) % 3);
            if d[kz] < 0.0 { (ky, kx) } else { (kx, ky) }
        };
        // Every combination of these components: signs, ties, zeros.
        let values = [-2.0f32, -1.0, -0.5, -0.0, 0.0, 0.5, 1.0, 2.0, f32::NAN];
        let mut checked = 0;
        for &x in &values {
            for &y in &values {
                for &z in &values {
                    let d = Vec3::new(x, y, z);
                    let w = WatertightRay::new(&Ray::new(Vec3::ZERO, d));
                    assert_eq!((w.kx, w.ky), reference(d), "direction {d:?}");
                    checked += 1;
                }
            }
        }
        assert_eq!(checked, values.len().pow(3));
    }

    #[test]
    fn box_clip_matches_slabs() {
        let b = Bounds::new(Vec3::ZERO, Vec3::ONE);
        let r = Ray::new(Vec3::new(-1.0, 0.5, 0.5), Vec3::X);
        assert_eq!(b.clip(&r, 0.0, f32::INFINITY), Some((1.0, 2.0)));
        let along_face = Ray::new(Vec3::new(-1.0, 1.0, 0.5), Vec3::X);
        assert_eq!(b.clip(&along_face, 0.0, f32::INFINITY), Some((1.0, 2.0)));
        let outside = Ray::new(Vec3::new(-1.0, 1.5, 0.5), Vec3::X);
        assert!(b.clip(&outside, 0.0, f32::INFINITY).is_none());
    }
}
