//! One shot of progressive refinement, as a receiving patch computes it:
//! the irradiance from the shooter at each of its corners, the update of
//! their radiosity, adaptive subdivision where corners now differ too
//! much, and the power received.
//!
//! Visibility is asked for in batches of [`VisSample`]s, each a receiving
//! point with one bit per part of the shooter (the paper's visibility bit
//! vector): [`Visibility`] clears the bits of parts that something hides.
//! One machine answers from its whole BVH; the farm's owners each clear
//! what their region hides, and the AND of their answers is the same bits.
//! Nothing here depends on which patches are received where, so the
//! solution is the same however patches are spread over workers.

use super::formfactor::{parts, point_to_triangle};
use super::mesh::Patch;
use crate::accel::Accel;
use crate::geometry::{Ray, spawn_offset};
use crate::stats::TraceStats;
use glam::{DVec3, Vec3};

/// How far a receiving point moves from a corner towards its patch's
/// centroid, as a fraction of the distance: a corner on the line where a
/// wall meets the floor sees the wall edge-on (form factor 0), while every
/// point beside it sees the wall over half its hemisphere; the inset takes
/// the limit that interpolation needs.
pub const CORNER_INSET: f32 = 1e-3;

/// The patch side that is shooting, and its parts.
#[derive(Clone, Debug)]
pub struct Shooter {
    pub patch: u32,
    pub side: usize,
    /// Unit normal of the shooting side.
    pub normal: Vec3,
    pub tri: [Vec3; 3],
    /// Unshot radiosity being shot.
    pub delta: DVec3,
    pub parts: Vec<[Vec3; 3]>,
    /// One ray target per part: its centroid, moved off the surface to the
    /// shooting side.
    pub targets: Vec<Vec3>,
    centroid: Vec3,
    /// Distance from the centroid to the farthest corner.
    radius: f32,
    front: Vec3,
}

/// What every worker needs to know of a shot: the shooting patch side and
/// the unshot radiosity it sends. The parts follow from it.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ShotSpec {
    pub patch: u32,
    pub side: u8,
    pub tri: [Vec3; 3],
    /// Unit normal of the patch's front side.
    pub front: Vec3,
    pub delta: DVec3,
}

impl Shooter {
    pub fn new(patch: u32, side: usize, p: &Patch, delta: DVec3, part_levels: u32) -> Self {
        let spec = ShotSpec {
            patch,
            side: side as u8,
            tri: p.tri,
            front: p.normal,
            delta,
        };
        Self::from_spec(&spec, part_levels)
    }

    pub fn from_spec(spec: &ShotSpec, part_levels: u32) -> Self {
        let side = spec.side as usize;
        let normal = if side == 0 { spec.front } else { -spec.front };
        let tri = spec.tri;
        let parts = parts(&tri, part_levels);
        let off = spawn_offset(&tri);
        let targets = parts
            .iter()
            .map(|t| (t[0] + t[1] + t[2]) / 3.0 + normal * off)
            .collect();
        let centroid = (tri[0] + tri[1] + tri[2]) / 3.0;
        let radius = tri
            .iter()
            .map(|&v| (v - centroid).length())
            .fold(0.0, f32::max);
        Self {
            patch: spec.patch,
            side,
            normal,
            tri,
            delta: spec.delta,
            parts,
            targets,
            centroid,
            radius,
            front: spec.front,
        }
    }

    /// The shot as workers are told of it.
    pub fn spec(&self) -> ShotSpec {
        ShotSpec {
            patch: self.patch,
            side: self.side as u8,
            tri: self.tri,
            front: self.front,
            delta: self.delta,
        }
    }

    /// Form factors from the point `at` (unit normal `n`) to each part,
    /// into `out`; returns the bits of the parts with a nonzero one.
    ///
    /// The total is always the analytic form factor of the whole shooter.
    /// Near the shooter, or when it straddles the receiver's tangent
    /// plane, each part gets its own analytic form factor; farther away
    /// the total is shared among the parts in proportion to the
    /// differential kernel `cos cos / r^2` at their centroids (accurate to
    /// `(size / distance)^2` there, and four times cheaper: the analytic
    /// form was 40% of a solution's time). Either way the parts add up to
    /// the total, so a fully visible shooter gets exactly its form factor.
    pub fn part_form_factors(&self, at: Vec3, n: Vec3, out: &mut [f64]) -> u64 {
        let m = self.parts.len();
        let straddles = {
            let d = self.tri.map(|v| n.dot(v - at));
            d.iter().any(|&x| x <= 0.0) && d.iter().any(|&x| x > 0.0)
        };
        let near = (self.centroid - at).length() < 2.0 * self.radius;
        if m == 1 || near || straddles {
            let mut bits = 0;
            for (k, part) in self.parts.iter().enumerate() {
                out[k] = point_to_triangle(at, n, part);
                if out[k] > 0.0 {
                    bits |= 1 << k;
                }
            }
            return bits;
        }
        let total = point_to_triangle(at, n, &self.tri);
        if total <= 0.0 {
            return 0;
        }
        let (at, n, ns) = (at.as_dvec3(), n.as_dvec3(), self.normal.as_dvec3());
        let mut sum = 0.0;
        for (k, part) in self.parts.iter().enumerate() {
            let d = ((part[0] + part[1] + part[2]) / 3.0).as_dvec3() - at;
            let r2 = d.length_squared();
            let w = (n.dot(d).max(0.0) * (-ns.dot(d)).max(0.0)) / (r2 * r2);
            out[k] = w;
            sum += w;
        }
        if sum.is_nan() || sum <= 0.0 {
            return 0;
        }
        let mut bits = 0;
        for (k, f) in out.iter_mut().enumerate().take(m) {
            *f *= total / sum;
            if *f > 0.0 {
                bits |= 1 << k;
            }
        }
        bits
    }

    /// Whether `x` lies strictly on the shooting side.
    fn faces(&self, x: Vec3) -> bool {
        self.normal.dot(x - self.tri[0]) > 0.0
    }
}

/// A receiving point and the shooter's parts it may see.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct VisSample {
    /// The ray origin: the point moved off its surface.
    pub origin: Vec3,
    /// Bit `k` set while part `k` may be visible.
    pub bits: u64,
}

/// Clears the bits of shooter parts that geometry hides from a sample.
pub trait Visibility: Sync {
    fn resolve(&self, shooter: &Shooter, samples: &mut [VisSample], stats: &mut TraceStats);
}

/// Visibility through one BVH (one machine).
pub struct BvhVisibility<'a>(pub &'a Accel);

impl Visibility for BvhVisibility<'_> {
    fn resolve(&self, shooter: &Shooter, samples: &mut [VisSample], stats: &mut TraceStats) {
        clear_hidden(shooter, samples, stats, |ray, len, st| {
            self.0.occluded(ray, 0.0, len, st)
        });
    }
}

/// Visibility through the BVH parts of one region (a farm node's): it
/// clears what that region's triangles hide.
pub struct RegionVisibility<'a>(pub &'a crate::accel_set::AccelSet);

impl Visibility for RegionVisibility<'_> {
    fn resolve(&self, shooter: &Shooter, samples: &mut [VisSample], stats: &mut TraceStats) {
        clear_hidden(shooter, samples, stats, |ray, len, st| {
            self.0.occluded(ray, 0.0, len, st)
        });
    }
}

/// One shadow ray per set bit, from the sample to its part's target;
/// `occluded(ray, length)` clears the bit.
fn clear_hidden(
    shooter: &Shooter,
    samples: &mut [VisSample],
    stats: &mut TraceStats,
    occluded: impl Fn(&Ray, f32, &mut TraceStats) -> bool,
) {
    for s in samples {
        let mut bits = s.bits;
        while bits != 0 {
            let k = bits.trailing_zeros();
            bits &= bits - 1;
            let seg = shooter.targets[k as usize] - s.origin;
            let len = seg.length();
            if len.is_nan() || len <= 0.0 {
                continue;
            }
            stats.shadow_rays += 1;
            if occluded(&Ray::new(s.origin, seg / len), len, stats) {
                s.bits &= !(1u64 << k);
            }
        }
    }
}

/// What one patch received in one shot: power (W) per side, and the work.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Receipt {
    pub received: [DVec3; 2],
    pub new_elements: u64,
}

/// Subdivision settings of a shot.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Refine {
    /// Split when corners' radiosity (mean of channels) differs by more
    /// than this fraction of their mean...
    pub threshold: f32,
    /// ...or of this floor, whichever is larger, so that dark corners with
    /// large relative but invisible differences are left alone.
    pub floor: f32,
    /// Elements the whole solution may still create in this shot.
    pub budget: u64,
}

fn level(c: Vec3) -> f32 {
    (c.x + c.y + c.z) / 3.0
}

/// Per-side irradiance this shot brings to each vertex of a patch.
type Incoming = Vec<[Vec3; 2]>;

/// Receives one shot into patch `p` (whose index is `index`), asking `vis`
/// for each round's visibility in one batch.
pub fn receive(
    p: &mut Patch,
    index: u32,
    shooter: &Shooter,
    vis: &dyn Visibility,
    refine: Refine,
    stats: &mut TraceStats,
) -> Receipt {
    let mut r = Reception::start(p, index, shooter);
    while !r.is_done() {
        vis.resolve(shooter, r.samples_mut(), stats);
        r.advance(p, shooter, refine);
    }
    r.receipt
}

/// Receiving points waiting for visibility, and what each one is for.
#[derive(Default)]
struct Pending {
    samples: Vec<VisSample>,
    /// `m` form factors per sample, one per shooter part.
    ffs: Vec<f64>,
    /// The vertex and side each sample lights.
    owners: Vec<(u32, usize)>,
}

/// One patch receiving one shot, as a sequence of rounds: each round's
/// receiving points wait for visibility (which a farm answers through its
/// regions while the patch waits), then [`Reception::advance`] lights
/// them, splits what now differs too much and makes the next round's
/// points at the new corners. [`receive`] runs the rounds on one machine;
/// the farm runs every patch's round together; the arithmetic is the same.
pub struct Reception {
    index: u32,
    sides: [bool; 2],
    inc: Incoming,
    pending: Pending,
    /// Vertices whose irradiance the pending round brings: every vertex
    /// in the first round, the new corners after.
    lit: Option<Vec<u32>>,
    /// Elements to check for splitting after the pending round: None for
    /// the first round (all leaves).
    check: Option<Vec<u32>>,
    /// Elements this patch may still create in this shot.
    budget: Option<u64>,
    done: bool,
    pub receipt: Receipt,
}

impl Reception {
    /// The first round's receiving points (none if the patch is the
    /// shooter or faces none of it: then it is done at once).
    pub fn start(p: &Patch, index: u32, shooter: &Shooter) -> Self {
        let sides = facing_sides(p, shooter);
        let mut r = Self {
            index,
            sides,
            inc: Vec::new(),
            pending: Pending::default(),
            lit: None,
            check: None,
            budget: None,
            done: index == shooter.patch || sides == [false, false],
            receipt: Receipt::default(),
        };
        if !r.done {
            r.inc = vec![[Vec3::ZERO; 2]; p.vertices.len()];
            let all: Vec<u32> = (0..p.vertices.len() as u32).collect();
            r.pending = sample_points(p, shooter, sides, &all);
        }
        r
    }

    pub fn index(&self) -> u32 {
        self.index
    }

    pub fn is_done(&self) -> bool {
        self.done
    }

    /// This round's receiving points, for visibility to clear hidden
    /// parts in.
    pub fn samples_mut(&mut self) -> &mut [VisSample] {
        &mut self.pending.samples
    }

    /// Lights the round's vertices with its resolved samples, splits, and
    /// makes the next round's points; done when nothing was split.
    pub fn advance(&mut self, p: &mut Patch, shooter: &Shooter, refine: Refine) {
        debug_assert!(!self.done, "advance after the last round");
        let pending = std::mem::take(&mut self.pending);
        gather(&pending, shooter, &mut self.inc);
        let albedo = p.albedo;
        match self.lit.take() {
            None => {
                for (v, e) in p.vertices.iter_mut().zip(&self.inc) {
                    reflect(v, albedo, e);
                }
            }
            Some(created) => {
                for &v in &created {
                    reflect(&mut p.vertices[v as usize], albedo, &self.inc[v as usize]);
                }
            }
        }
        let check = self.check.take().unwrap_or_else(|| p.leaves());
        let budget = self.budget.get_or_insert(refine.budget);
        let mut split_now = Vec::new();
        for &e in &check {
            if (p.elements[e as usize].level as u32) < p.levels
                && *budget >= 3
                && too_different(p, e, refine)
            {
                split_now.push(e);
                *budget -= 3;
            }
        }
        let mut created = Vec::new();
        let mut children = Vec::new();
        for e in split_now {
            // New corners start from zero here; `seed_midpoints` gives
            // them the radiosity their edge had before this shot.
            let (first, new) = p.split(e, [Vec3::ZERO; 2]);
            created.extend(new);
            children.extend(first..first + 4);
        }
        self.receipt.new_elements += 3 * (children.len() as u64 / 4);
        if created.is_empty() && children.is_empty() {
            self.finish(p);
            return;
        }
        seed_midpoints(p, &created, &mut self.inc);
        self.pending = sample_points(p, shooter, self.sides, &created);
        self.lit = Some(created);
        self.check = Some(children);
    }

    /// The power received over the patch's leaves.
    fn finish(&mut self, p: &Patch) {
        for e in p.leaves() {
            let c = p.elements[e as usize].corners;
            let area = p.element_area(e);
            for (s, received) in self.receipt.received.iter_mut().enumerate() {
                let sum: DVec3 = c.iter().map(|&v| self.inc[v as usize][s].as_dvec3()).sum();
                *received += sum / 3.0 * area;
            }
        }
        self.done = true;
    }
}

/// Adds what a corner reflects of this shot's irradiance `e`, per side.
fn reflect(v: &mut super::mesh::Vertex, albedo: Vec3, e: &[Vec3; 2]) {
    for (b, e) in v.b.iter_mut().zip(e) {
        *b += albedo * *e;
    }
}

/// Which sides of `p` can receive from the shooter at all: the side must
/// face some of the shooter, and some of `p` must lie on the shooting side.
fn facing_sides(p: &Patch, shooter: &Shooter) -> [bool; 2] {
    if !p.tri.iter().any(|&v| shooter.faces(v)) {
        return [false, false];
    }
    let above = |n: Vec3| shooter.tri.iter().any(|&q| n.dot(q - p.tri[0]) > 0.0);
    [above(p.normal), above(-p.normal)]
}

fn too_different(p: &Patch, e: u32, refine: Refine) -> bool {
    let c = p.elements[e as usize].corners;
    (0..2).any(|s| {
        let l = c.map(|v| level(p.vertices[v as usize].b[s]));
        let (lo, hi) = (l[0].min(l[1]).min(l[2]), l[0].max(l[1]).max(l[2]));
        let mean = (l[0] + l[1] + l[2]) / 3.0;
        hi - lo > refine.threshold * mean.max(refine.floor)
    })
}

/// New midpoints take the radiosity their edge had before this shot,
/// interpolated between the edge's ends (already updated by this shot, so
/// this shot's reflected part is taken off first).
fn seed_midpoints(p: &mut Patch, created: &[u32], inc: &mut Incoming) {
    inc.resize(p.vertices.len(), [Vec3::ZERO; 2]);
    for &v in created {
        let l = p.vertices[v as usize].lattice;
        let (a, b) = edge_ends(p, l);
        let before = |x: u32, s: usize| p.vertices[x as usize].b[s] - p.albedo * inc[x as usize][s];
        let b_new = [0, 1].map(|s| (before(a, s) + before(b, s)) * 0.5);
        p.vertices[v as usize].b = b_new;
    }
}

/// The ends of the edge whose midpoint is lattice point `l`: the points
/// of the next coarser lattice on either side of it, along the one of the
/// three lattice directions where both lie on that lattice.
fn edge_ends(p: &Patch, l: [u32; 2]) -> (u32, u32) {
    // The midpoint's lowest set bit gives the step at which it was made.
    let step = 1u32 << (l[0] | l[1] | 1u32 << p.levels).trailing_zeros();
    // Only the true edge's ends lie on the coarser lattice (multiples of
    // twice the step): along another direction the points at the same
    // distance are midpoints of this level, perhaps not yet seeded.
    let find = |x: [i64; 2]| -> Option<u32> {
        if x[0] < 0 || x[1] < 0 || (x[0] | x[1]) % (2 * step as i64) != 0 {
            return None;
        }
        p.vertex_id([x[0] as u32, x[1] as u32])
    };
    let (i, j, s) = (l[0] as i64, l[1] as i64, step as i64);
    for (di, dj) in [(1, 0), (0, 1), (1, -1)] {
        if let (Some(a), Some(b)) = (
            find([i - di * s, j - dj * s]),
            find([i + di * s, j + dj * s]),
        ) {
            return (a, b);
        }
    }
    unreachable!("a midpoint at {l:?} without its edge's ends")
}

/// The receiving points of vertices `which`, with their form factors,
/// for the parts each may see.
fn sample_points(p: &Patch, shooter: &Shooter, sides: [bool; 2], which: &[u32]) -> Pending {
    let centroid = (p.tri[0] + p.tri[1] + p.tri[2]) / 3.0;
    let off = spawn_offset(&p.tri);
    let m = shooter.parts.len();
    let mut out = Pending::default();
    for &v in which {
        let pos = p.vertices[v as usize].pos;
        let at = pos + (centroid - pos) * CORNER_INSET;
        if !shooter.faces(at) {
            continue;
        }
        for (s, _) in sides.iter().enumerate().filter(|(_, on)| **on) {
            let n = if s == 0 { p.normal } else { -p.normal };
            let at_ff = out.ffs.len();
            out.ffs.resize(at_ff + m, 0.0);
            let bits = shooter.part_form_factors(at, n, &mut out.ffs[at_ff..]);
            if bits != 0 {
                out.samples.push(VisSample {
                    origin: at + n * off,
                    bits,
                });
                out.owners.push((v, s));
            } else {
                out.ffs.truncate(at_ff);
            }
        }
    }
    out
}

/// The irradiance each resolved sample brings: the shooter's unshot
/// radiosity times the form factors of its visible parts.
fn gather(pending: &Pending, shooter: &Shooter, inc: &mut Incoming) {
    let m = shooter.parts.len();
    let rows = pending.samples.iter().zip(pending.ffs.chunks_exact(m));
    for ((sample, ff), &(v, s)) in rows.zip(&pending.owners) {
        let mut f = 0.0;
        let mut bits = sample.bits;
        while bits != 0 {
            let k = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            f += ff[k];
        }
        inc[v as usize][s] = (shooter.delta * f).as_vec3();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edge_ends_are_the_vertices_either_side() {
        let tri = [Vec3::ZERO, Vec3::X, Vec3::Y];
        let mut p = Patch::new(tri, Vec3::splat(0.5), Vec3::ZERO, 1, 4);
        for e in 1..5 {
            let (_, created) = p.split(e, [Vec3::ZERO; 2]);
            for v in created {
                let l = p.vertices[v as usize].lattice;
                let (a, b) = edge_ends(&p, l);
                let (la, lb) = (
                    p.vertices[a as usize].lattice,
                    p.vertices[b as usize].lattice,
                );
                assert_eq!([(la[0] + lb[0]) / 2, (la[1] + lb[1]) / 2], l);
            }
        }
    }
}
