//! Area lights: every triangle whose material emits, chosen with probability
//! proportional to its emitted power (area times luminance of emission), then
//! sampled uniformly by area.
//!
//! A `LightSet` carries the emitters' own vertices and emission, so a farm
//! worker can sample every light of the scene (next-event estimation needs
//! them all) while holding only its region's geometry.

use crate::geometry::{tri_area_f64, tri_cross, uniform_triangle};
use crate::scene::Scene;
use glam::Vec3;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LightSet {
    /// Global triangle ids of the emitters, ascending.
    pub tris: Vec<u32>,
    verts: Vec<[Vec3; 3]>,
    emission: Vec<Vec3>,
    /// Cumulative selection probability, ending at exactly 1.
    cdf: Vec<f64>,
    /// Selection probability divided by area: the area-measure pdf of
    /// sampling a point on that emitter.
    pdf_area: Vec<f32>,
}

pub struct LightSample {
    pub tri: u32,
    pub point: Vec3,
    /// Unit geometric normal (the emitting side).
    pub normal: Vec3,
    pub emission: Vec3,
    pub pdf_area: f32,
    /// The emitter's vertices, for the spawn offset of the shadow ray's end.
    pub verts: [Vec3; 3],
}

fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

impl LightSet {
    pub fn build(scene: &Scene) -> Self {
        let mut s = Self::default();
        let mut power = Vec::new();
        for (i, &m) in scene.tri_material.iter().enumerate() {
            let e = scene.materials[m as usize].emission;
            let l = luminance(e).max(e.max_element() * 1e-3);
            if e.max_element() > 0.0 {
                s.tris.push(i as u32);
                s.verts.push(scene.tris[i]);
                s.emission.push(e);
                power.push(tri_area_f64(&scene.tris[i]) * l as f64);
            }
        }
        let total: f64 = power.iter().sum();
        let mut acc = 0.0;
        for (k, &p) in power.iter().enumerate() {
            acc += p / total;
            s.cdf.push(acc);
            s.pdf_area
                .push(((p / total) / tri_area_f64(&s.verts[k])) as f32);
        }
        if let Some(last) = s.cdf.last_mut() {
            *last = 1.0;
        }
        s
    }

    pub fn is_empty(&self) -> bool {
        self.tris.is_empty()
    }

    /// Area-measure pdf of sampling a point on global triangle `tri` (0 for
    /// a triangle that does not emit).
    #[inline]
    pub fn pdf_area(&self, tri: u32) -> f32 {
        match self.tris.binary_search(&tri) {
            Ok(k) => self.pdf_area[k],
            Err(_) => 0.0,
        }
    }

    pub fn sample(&self, u_select: f32, u_point: [f32; 2]) -> Option<LightSample> {
        if self.tris.is_empty() {
            return None;
        }
        let k = self
            .cdf
            .partition_point(|&c| c <= u_select as f64)
            .min(self.tris.len() - 1);
        let v = self.verts[k];
        let (b1, b2) = uniform_triangle(u_point);
        Some(LightSample {
            tri: self.tris[k],
            point: crate::geometry::hit_point(&v, b1, b2),
            normal: tri_cross(&v).normalize(),
            emission: self.emission[k],
            pdf_area: self.pdf_area[k],
            verts: v,
        })
    }
}
