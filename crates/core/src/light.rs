//! Area lights: every triangle whose material emits, chosen with probability
//! proportional to its emitted power (area times luminance of emission), then
//! sampled uniformly by area.

use crate::geometry::{tri_area_f64, tri_cross, uniform_triangle};
use crate::scene::Scene;
use glam::Vec3;

pub struct LightSet {
    /// Global triangle ids of the emitters.
    pub tris: Vec<u32>,
    /// Cumulative selection probability, ending at exactly 1.
    cdf: Vec<f64>,
    /// Selection probability divided by area, per global triangle id (0 for
    /// non-emitters): the area-measure pdf of sampling a point there.
    pdf_area: Vec<f32>,
}

pub struct LightSample {
    pub tri: u32,
    pub point: Vec3,
    /// Unit geometric normal (the emitting side).
    pub normal: Vec3,
    pub emission: Vec3,
    pub pdf_area: f32,
}

fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

impl LightSet {
    pub fn build(scene: &Scene) -> Self {
        let mut tris = Vec::new();
        let mut power = Vec::new();
        for (i, &m) in scene.tri_material.iter().enumerate() {
            let e = scene.materials[m as usize].emission;
            let l = luminance(e).max(e.max_element() * 1e-3);
            if e.max_element() > 0.0 {
                tris.push(i as u32);
                power.push(tri_area_f64(&scene.tris[i]) * l as f64);
            }
        }
        let total: f64 = power.iter().sum();
        let mut cdf = Vec::with_capacity(power.len());
        let mut acc = 0.0;
        let mut pdf_area = vec![0f32; scene.tris.len()];
        for (k, &p) in power.iter().enumerate() {
            acc += p / total;
            cdf.push(acc);
            let tri = tris[k] as usize;
            pdf_area[tri] = ((p / total) / tri_area_f64(&scene.tris[tri])) as f32;
        }
        if let Some(last) = cdf.last_mut() {
            *last = 1.0;
        }
        Self {
            tris,
            cdf,
            pdf_area,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.tris.is_empty()
    }

    /// Area-measure pdf of sampling a point on triangle `tri`.
    #[inline]
    pub fn pdf_area(&self, tri: u32) -> f32 {
        self.pdf_area[tri as usize]
    }

    pub fn sample(&self, scene: &Scene, u_select: f32, u_point: [f32; 2]) -> Option<LightSample> {
        if self.tris.is_empty() {
            return None;
        }
        let k = self
            .cdf
            .partition_point(|&c| c <= u_select as f64)
            .min(self.tris.len() - 1);
        let tri = self.tris[k];
        let v = &scene.tris[tri as usize];
        let (b1, b2) = uniform_triangle(u_point);
        let point = crate::geometry::hit_point(v, b1, b2);
        let normal = tri_cross(v).normalize();
        let emission = scene.materials[scene.tri_material[tri as usize] as usize].emission;
        Some(LightSample {
            tri,
            point,
            normal,
            emission,
            pdf_area: self.pdf_area[tri as usize],
        })
    }
}
