//! Unidirectional path tracing with next-event estimation on area lights,
//! multiple importance sampling (power heuristic), Russian roulette and a
//! maximum depth, following pbrt-v4's `PathIntegrator`, written as a
//! recursion over path vertices so that the farm can evaluate each vertex on
//! a different worker and still get the same bits.
//!
//! The unit of work is a [`PathRay`]: "the radiance arriving at this ray's
//! origin along it". Its answer, `L(ray)`, is computed where the ray hits:
//! [`shade`] returns the vertex's emitted term, its next-event contribution
//! (valid only if the shadow segment is unoccluded) and the continuation ray
//! with its scale, and [`ShadedVertex::finish`] combines them as
//! `(emitted + nee) + scale * L(next)`. The single-machine renderer and the
//! farm both evaluate exactly this expression, in this order, through the
//! one state machine of [`crate::path`].
//!
//! Sampling dimensions are keyed by path vertex: vertex `d` (1 for the first
//! surface hit) uses dimensions `vertex_dim(d) ..+5`. Where a vertex is
//! shaded therefore never changes which random numbers it sees.

use crate::accel::Hit;
use crate::dircache::{locality_sphere, perimeter};
use crate::geometry::{Ray, cosine_hemisphere, hit_point, offset_point, spawn_offset, tri_cross};
use crate::irradiance::IrradianceCache;
use crate::light::LightSet;
use crate::octree::Octree;
use crate::sampler::SampleKey;
use crate::scene::Material;
use glam::Vec3;
use serde::{Deserialize, Serialize};
use std::f32::consts::PI;

/// Dimensions 0 and 1 jitter the camera ray inside the pixel.
pub const DIM_PIXEL: u32 = 0;
/// Dimensions used per path vertex: the light's choice and point (2, one
/// pattern: see [`LightSet::sample`]), BSDF direction (2), Russian
/// roulette (1).
pub const DIMS_PER_VERTEX: u32 = 5;

/// Russian roulette starts at the fifth surface vertex (Mitsuba 3's
/// `rr_depth`): ending paths earlier, at the third, threw away most of the
/// light that bounces around a white room (1.27 times the variance a
/// sample leaves in the Cornell box; see `docs/benchmarks/quality.md`,
/// its roulette table), while the short paths it saves are cheap.
pub const RR_START_VERTEX: u32 = 5;
/// The continuation probability is the throughput's largest channel
/// (survivors carry throughput 1), capped so that bright paths still end.
pub const RR_MAX_CONTINUE: f32 = 0.95;

#[inline(always)]
pub fn vertex_dim(vertex: u32) -> u32 {
    2 + (vertex - 1) * DIMS_PER_VERTEX
}

#[inline(always)]
fn power_heuristic(a: f32, b: f32) -> f32 {
    let (a2, b2) = (a * a, b * b);
    if a2.is_infinite() {
        1.0
    } else {
        a2 / (a2 + b2)
    }
}

/// A ray whose answer is the radiance arriving at its origin along it:
/// emission at its hit point (MIS-weighted against the next-event estimate
/// that the previous vertex already made, which is why `prev_pdf` travels
/// with it) plus everything scattered there. This is what a forwarded path
/// query carries between workers, bit for bit.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PathRay {
    pub ray: Ray,
    pub key: SampleKey,
    /// Path vertices before this ray's hit (0 for a camera ray).
    pub depth: u32,
    /// Solid-angle BSDF pdf of `ray.dir` at its origin; 0 for a camera ray,
    /// whose hit on an emitter takes the full emission.
    pub prev_pdf: f32,
    /// Path throughput up to the origin, used only by Russian roulette.
    pub beta: Vec3,
    /// Emission at the first hit counts (MIS-weighted) only when the hit
    /// is nearer than this: the locality perimeter of the origin's leaf
    /// when directional caches are on (see [`shade`]), infinity otherwise.
    pub emit_within: f32,
}

impl PathRay {
    pub fn camera(ray: Ray, key: SampleKey) -> Self {
        Self {
            ray,
            key,
            depth: 0,
            prev_pdf: 0.0,
            beta: Vec3::ONE,
            emit_within: f32::INFINITY,
        }
    }
}

/// A shadow segment: unoccluded when nothing lies in `[0, t_max)`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShadowRay {
    pub ray: Ray,
    pub t_max: f32,
}

/// The local part of one path vertex, waiting for its shadow answer and the
/// radiance of its continuation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShadedVertex {
    pub emitted: Vec3,
    /// Next-event contribution if the shadow segment is unoccluded.
    pub nee: Vec3,
    pub scale: Vec3,
}

impl ShadedVertex {
    /// `L = (emitted + nee·[visible]) + scale · L(next)`; `next` is zero when
    /// the path ended here or its continuation escaped.
    #[inline(always)]
    pub fn finish(&self, visible: bool, next: Vec3) -> Vec3 {
        let nee = if visible { self.nee } else { Vec3::ZERO };
        (self.emitted + nee) + self.scale * next
    }
}

/// What shading a hit produces.
pub struct Shaded {
    pub vertex: ShadedVertex,
    pub shadow: Option<ShadowRay>,
    pub next: Option<PathRay>,
    /// With `locality`: the leaf whose sphere split this vertex's light,
    /// whose cache answers `next` beyond `next.emit_within`.
    pub cache_leaf: Option<u32>,
    /// With an irradiance cache, at the first vertex: whether its records
    /// answered (true) or the vertex was path traced (false).
    pub ambient: Option<bool>,
}

/// Where a path vertex sits and which way it faces.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Frame {
    pub p: Vec3,
    /// The geometric normal as the triangle's winding gives it.
    pub ng: Vec3,
    /// The geometric normal on the side the ray arrived from.
    pub n: Vec3,
    /// The shading normal on that side ([`shading_normal`]).
    pub ns: Vec3,
    /// `p` moved off the surface to that side: where new rays leave.
    pub origin: Vec3,
    /// Whether the triangle has shading normals.
    pub shaded: bool,
}

impl Frame {
    /// The frame of hit `h` on triangle `tri` by a ray along `dir`.
    #[inline(always)]
    pub fn at(dir: Vec3, tri: &[Vec3; 3], h: &Hit, shading: Vec3) -> Self {
        Self::with_normal(dir, tri, h, shading, tri_cross(tri).normalize())
    }

    /// [`Frame::at`] with the triangle's unit normal `ng` already known.
    #[inline(always)]
    fn with_normal(dir: Vec3, tri: &[Vec3; 3], h: &Hit, shading: Vec3, ng: Vec3) -> Self {
        let p = hit_point(tri, h.b1, h.b2);
        let n = if ng.dot(-dir) >= 0.0 { ng } else { -ng };
        let ns = shading_normal(shading, n);
        Self {
            p,
            ng,
            n,
            ns,
            origin: offset_point(p, ng, n, spawn_offset(tri)),
            shaded: shading != Vec3::ZERO,
        }
    }
}

/// A triangle's shading normals interpolated at barycentrics `(b1, b2)`
/// and normalised (pbrt's and Mitsuba's smooth shading); zero for a flat
/// triangle ([`crate::geometry::FLAT`]) or one whose normals cancel there.
#[inline]
pub fn interpolate_normal(normals: &[Vec3; 3], b1: f32, b2: f32) -> Vec3 {
    if *normals == crate::geometry::FLAT {
        return Vec3::ZERO;
    }
    let b0 = 1.0 - b1 - b2;
    (normals[0] * b0 + normals[1] * b1 + normals[2] * b2).normalize_or_zero()
}

/// The normal a hit is shaded with: `shading` (from
/// [`interpolate_normal`]) turned to the side of `n`, the geometric normal
/// facing the incoming ray; `n` itself, bit for bit, when `shading` is
/// zero.
#[inline(always)]
pub fn shading_normal(shading: Vec3, n: Vec3) -> Vec3 {
    if shading == Vec3::ZERO {
        n
    } else if shading.dot(n) < 0.0 {
        -shading
    } else {
        shading
    }
}

/// Shades the hit `h` of `q` on triangle `tri` with material `mat`.
///
/// With a shading normal (`shading`, interpolated at the hit; zero for a
/// flat triangle) the reflection is computed about it: next-event
/// estimation weighs a light by its cosine to it, and continuations are
/// sampled about it. The geometric normal still decides which side a
/// surface emits on, where rays leave from, and whether a direction is
/// reflected at all: a light behind the triangle itself gets no next-event
/// estimate, and a continuation sampled below it ends the path (it would
/// pass through the surface). A flat triangle is shaded exactly as before.
///
/// With directional caches on, `locality` is the octree and the locality
/// radius: light is then split at the perimeter of the locality sphere of
/// the leaf holding the new vertex. A light point inside the sphere is
/// reached both by next-event estimation and by the continuation ray
/// (traced exactly there), and the two are combined by MIS as without
/// caches; a light point beyond it is counted by next-event estimation
/// alone (weight one), because a continuation ray that reaches the
/// perimeter carries the radiance beyond it *without* the emission of the
/// surface it hits first (`emit_within`). That quantity does not depend on
/// where in the leaf the ray started, which is what lets the leaf's cache
/// answer it (see [`crate::dircache`]).
///
/// With an irradiance cache (`ambient`), a first vertex (`q.depth == 0`)
/// that its records cover takes its diffuse interreflection from them and
/// sends no continuation; its next-event estimate then has weight one, as
/// the records hold no emission (see [`crate::irradiance`]).
#[allow(clippy::too_many_arguments)]
pub fn shade(
    q: &PathRay,
    h: &Hit,
    tri: &[Vec3; 3],
    shading: Vec3,
    mat: &Material,
    lights: &LightSet,
    max_depth: u32,
    locality: Option<(&Octree, f32)>,
    ambient: Option<&IrradianceCache>,
) -> Shaded {
    let mut out = Shaded {
        vertex: ShadedVertex {
            emitted: Vec3::ZERO,
            nee: Vec3::ZERO,
            scale: Vec3::ZERO,
        },
        shadow: None,
        next: None,
        cache_leaf: None,
        ambient: None,
    };
    let ng = tri_cross(tri).normalize();
    let wo = -q.ray.dir;
    let cos_o = ng.dot(wo);
    if mat.is_emissive() && cos_o > 0.0 {
        let w = if q.depth == 0 {
            1.0
        } else if h.t < q.emit_within {
            let pdf_l = lights.pdf_area(h.tri) * h.t * h.t / cos_o;
            power_heuristic(q.prev_pdf, pdf_l)
        } else {
            0.0
        };
        out.vertex.emitted = mat.emission * w;
    }
    if q.depth == max_depth || mat.albedo.max_element() <= 0.0 {
        return out;
    }
    let vertex = q.depth + 1;
    let key = q.key;
    let draws = key.draws();
    let Frame {
        p,
        ng: _,
        n,
        ns,
        origin,
        shaded,
    } = Frame::with_normal(q.ray.dir, tri, h, shading, ng);
    let base = vertex_dim(vertex);
    let f = mat.albedo / PI;
    // Ward's irradiance cache answers the first vertex's diffuse
    // interreflection where its records cover the point: the vertex then
    // sends no continuation, and its next-event estimate takes all of the
    // direct light (the records hold the light arriving from surfaces,
    // without their emission).
    let cached = match ambient {
        Some(cache) if q.depth == 0 => {
            let e = cache.interpolate(p, ns);
            out.ambient = Some(e.is_some());
            e
        }
        _ => None,
    };
    if let Some(e) = cached {
        out.vertex.emitted += f * e;
    }
    out.cache_leaf = locality.and_then(|(octree, _)| octree.leaf_at(origin));
    let sphere = locality
        .zip(out.cache_leaf)
        .map(|((octree, radius), leaf)| {
            locality_sphere(&octree.leaves[leaf as usize].bounds, radius)
        });

    // Next-event estimation.
    if let Some(ls) = lights.sample(draws.get2d_bits(base)) {
        let target = ls.point + ls.normal * ls.offset;
        let to = ls.point - p;
        let dist2 = to.length_squared();
        let wi = to / dist2.sqrt();
        let cos_s = ns.dot(wi);
        let cos_l = -ls.normal.dot(wi);
        let in_front = !shaded || n.dot(wi) > 0.0;
        if cos_s > 0.0 && cos_l > 0.0 && ls.pdf_area > 0.0 && dist2 > 0.0 && in_front {
            let seg = target - origin;
            let len = seg.length();
            if len > 0.0 {
                let pdf_l = ls.pdf_area * dist2 / cos_l;
                let pdf_b = cos_s / PI;
                let ray = Ray::new(origin, seg / len);
                let w = match sphere {
                    _ if cached.is_some() => 1.0,
                    Some(s) if len >= perimeter(s, &ray) => 1.0,
                    _ => power_heuristic(pdf_l, pdf_b),
                };
                out.vertex.nee = f * ls.emission * (cos_s * w / pdf_l);
                out.shadow = Some(ShadowRay { ray, t_max: len });
            }
        }
    }

    if cached.is_some() {
        return out;
    }
    // Continue by cosine sampling: f cos / pdf = albedo.
    let wi = cosine_hemisphere(ns, draws.get2d(base + 2));
    let pdf_b = ns.dot(wi) / PI;
    if pdf_b.is_nan() || pdf_b <= 0.0 || (shaded && n.dot(wi) <= 0.0) {
        return out;
    }
    let mut scale = mat.albedo;
    let mut beta = q.beta * mat.albedo;
    if vertex >= RR_START_VERTEX {
        let p = beta.max_element().min(RR_MAX_CONTINUE);
        if draws.get1d(base + 4) >= p {
            return out;
        }
        scale /= p;
        beta /= p;
    }
    out.vertex.scale = scale;
    let ray = Ray::new(origin, wi);
    out.next = Some(PathRay {
        ray,
        key,
        depth: vertex,
        prev_pdf: pdf_b,
        beta,
        emit_within: sphere.map_or(f32::INFINITY, |s| perimeter(s, &ray)),
    });
    out
}
