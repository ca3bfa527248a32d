//! Unidirectional path tracing with next-event estimation on area lights,
//! multiple importance sampling (power heuristic), Russian roulette and a
//! maximum depth, following pbrt-v4's `PathIntegrator`.
//!
//! Sampling dimensions are keyed by path vertex: vertex `d` (1 for the first
//! surface hit) uses dimensions `vertex_dim(d) ..+6`. Where a vertex is
//! shaded therefore never changes which random numbers it sees.

use crate::accel::Accel;
use crate::geometry::{Ray, cosine_hemisphere, hit_point, offset_point, spawn_offset, tri_cross};
use crate::light::LightSet;
use crate::sampler::SampleKey;
use crate::scene::Scene;
use crate::stats::TraceStats;
use glam::Vec3;
use std::f32::consts::PI;

/// Dimensions 0 and 1 jitter the camera ray inside the pixel.
pub const DIM_PIXEL: u32 = 0;
/// Dimensions used per path vertex: light selection (1), light point (2),
/// BSDF direction (2), Russian roulette (1).
pub const DIMS_PER_VERTEX: u32 = 6;

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

/// What the integrator needs to know about the scene.
pub struct Integrator<'a> {
    pub scene: &'a Scene,
    pub accel: &'a Accel,
    pub lights: &'a LightSet,
    pub max_depth: u32,
}

impl Integrator<'_> {
    /// Radiance arriving at the camera along `ray` for sample `key`.
    pub fn radiance(&self, camera_ray: Ray, key: SampleKey, stats: &mut TraceStats) -> Vec3 {
        let scene = self.scene;
        let mut l = Vec3::ZERO;
        let mut beta = Vec3::ONE;
        let mut ray = camera_ray;
        // BSDF pdf (solid angle) of the direction that produced `ray`, for MIS
        // when it hits an emitter; None for the camera ray.
        let mut prev_pdf: Option<f32> = None;
        let mut vertex = 0u32;
        stats.camera_rays += 1;
        while let Some(h) = self.accel.intersect(&ray, 0.0, f32::INFINITY, stats) {
            let v = &scene.tris[h.tri as usize];
            let mat = &scene.materials[scene.tri_material[h.tri as usize] as usize];
            let ng = tri_cross(v).normalize();
            let wo = -ray.dir;
            let cos_o = ng.dot(wo);
            if mat.is_emissive() && cos_o > 0.0 {
                let w = match prev_pdf {
                    None => 1.0,
                    Some(pdf_b) => {
                        let pdf_l = self.lights.pdf_area(h.tri) * h.t * h.t / cos_o;
                        power_heuristic(pdf_b, pdf_l)
                    }
                };
                l += beta * mat.emission * w;
            }
            if vertex == self.max_depth {
                break;
            }
            vertex += 1;
            if mat.albedo.max_element() <= 0.0 {
                break;
            }
            let p = hit_point(v, h.b1, h.b2);
            let n = if cos_o >= 0.0 { ng } else { -ng };
            let off = spawn_offset(v);
            let origin = offset_point(p, ng, n, off);
            let base = vertex_dim(vertex);
            let f = mat.albedo / PI;

            // Next-event estimation.
            if let Some(ls) = self
                .lights
                .sample(scene, key.get1d(base), key.get2d(base + 1))
            {
                let target = ls.point + ls.normal * spawn_offset(&scene.tris[ls.tri as usize]);
                let to = ls.point - p;
                let dist2 = to.length_squared();
                let wi = to / dist2.sqrt();
                let cos_s = n.dot(wi);
                let cos_l = -ls.normal.dot(wi);
                if cos_s > 0.0 && cos_l > 0.0 && ls.pdf_area > 0.0 && dist2 > 0.0 {
                    let seg = target - origin;
                    let len = seg.length();
                    if len > 0.0 {
                        stats.shadow_rays += 1;
                        let sray = Ray::new(origin, seg / len);
                        if !self.accel.occluded(&sray, 0.0, len, stats) {
                            let pdf_l = ls.pdf_area * dist2 / cos_l;
                            let pdf_b = cos_s / PI;
                            let w = power_heuristic(pdf_l, pdf_b);
                            l += beta * f * ls.emission * (cos_s * w / pdf_l);
                        }
                    }
                }
            }

            // Continue the path by cosine sampling: f cos / pdf = albedo.
            let wi = cosine_hemisphere(n, key.get2d(base + 3));
            let pdf_b = n.dot(wi) / PI;
            if pdf_b.is_nan() || pdf_b <= 0.0 {
                break;
            }
            beta *= mat.albedo;
            if vertex >= 3 {
                let q = (1.0 - beta.max_element()).max(0.0);
                if key.get1d(base + 5) < q {
                    break;
                }
                beta /= 1.0 - q;
            }
            prev_pdf = Some(pdf_b);
            stats.indirect_rays += 1;
            ray = Ray::new(origin, wi);
        }
        l
    }
}
