//! Area lights: every triangle whose material emits, chosen with probability
//! proportional to its emitted power (area times luminance of emission), then
//! sampled uniformly by area.
//!
//! One 2D sample does both: its first coordinate picks the emitter and,
//! rescaled to the emitter's share of the unit interval, places the point
//! with the second. So the points of a low-discrepancy pattern stay
//! stratified over all emitters together (the two triangles of a quad
//! light are one light to the pattern), where a separate selection
//! dimension dealt them out at random between the triangles.
//!
//! A `LightSet` carries the emitters' own vertices and emission, so a farm
//! worker can sample every light of the scene (next-event estimation needs
//! them all) while holding only its region's geometry.

use crate::geometry::{spawn_offset, tri_area_f64, tri_cross, uniform_triangle};
use crate::scene::Scene;
use glam::Vec3;
use serde::{Deserialize, Serialize};

/// The emitters as they travel: what each is. The rest of a [`LightSet`]
/// (selection, pdfs, normals, offsets) is derived from them on arrival by
/// the same code as where it was built, so it is the same to the bit and a
/// peer cannot send a set whose parts disagree.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(from = "Emitters", into = "Emitters")]
pub struct LightSet {
    /// Global triangle ids of the emitters, ascending.
    pub tris: Vec<u32>,
    /// What a sample reads of the emitter it chose, in one place, in the
    /// order of `tris`.
    emitters: Vec<Emitter>,
}

/// One emitter as sampling reads it: its parts that do not depend on the
/// sample are computed once, here, rather than for every sample.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Emitter {
    verts: [Vec3; 3],
    emission: Vec3,
    /// Unit geometric normal (the emitting side).
    normal: Vec3,
    /// Selection probability divided by area: the area-measure pdf of
    /// sampling a point on this emitter.
    pdf_area: f32,
    /// The spawn offset of a shadow ray's end on it.
    offset: f32,
    /// The cumulative selection probability up to and with it (ending at
    /// exactly 1): its share of the unit interval ends here and starts at
    /// the emitter before's.
    hi: f64,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
struct Emitters {
    tris: Vec<u32>,
    verts: Vec<[Vec3; 3]>,
    emission: Vec<Vec3>,
}

impl From<Emitters> for LightSet {
    fn from(e: Emitters) -> Self {
        Self::from_emitters(
            e.tris
                .into_iter()
                .zip(e.verts)
                .zip(e.emission)
                .map(|((id, v), e)| (id, v, e)),
        )
    }
}

impl From<LightSet> for Emitters {
    fn from(s: LightSet) -> Self {
        Self {
            tris: s.tris,
            verts: s.emitters.iter().map(|e| e.verts).collect(),
            emission: s.emitters.iter().map(|e| e.emission).collect(),
        }
    }
}

pub struct LightSample {
    pub tri: u32,
    pub point: Vec3,
    /// Unit geometric normal (the emitting side).
    pub normal: Vec3,
    pub emission: Vec3,
    pub pdf_area: f32,
    /// The emitter's spawn offset ([`spawn_offset`] of its vertices), for
    /// the shadow ray's end.
    pub offset: f32,
}

/// The largest f32 below 1.
const ONE_BELOW: f32 = 1.0 - f32::EPSILON / 2.0;

fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

impl LightSet {
    pub fn build(scene: &Scene) -> Self {
        Self::from_emitters(scene.tri_material.iter().enumerate().filter_map(|(i, &m)| {
            let e = scene.materials[m as usize].emission;
            (e.max_element() > 0.0).then_some((i as u32, scene.tris[i], e))
        }))
    }

    /// The emitters `(global triangle id, vertices, emission)`, ids
    /// ascending.
    pub fn from_emitters(emitters: impl IntoIterator<Item = (u32, [Vec3; 3], Vec3)>) -> Self {
        let mut s = Self::default();
        let mut power = Vec::new();
        for (id, verts, emission) in emitters {
            let l = luminance(emission).max(emission.max_element() * 1e-3);
            s.tris.push(id);
            s.emitters.push(Emitter {
                verts,
                emission,
                normal: tri_cross(&verts).normalize(),
                pdf_area: 0.0,
                offset: spawn_offset(&verts),
                hi: 0.0,
            });
            power.push(tri_area_f64(&verts) * l as f64);
        }
        let total: f64 = power.iter().sum();
        let mut acc = 0.0;
        for (e, &p) in s.emitters.iter_mut().zip(&power) {
            acc += p / total;
            e.hi = acc;
            e.pdf_area = ((p / total) / tri_area_f64(&e.verts)) as f32;
        }
        if let Some(last) = s.emitters.last_mut() {
            last.hi = 1.0;
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
            Ok(k) => self.emitters[k].pdf_area,
            Err(_) => 0.0,
        }
    }

    /// A point on an emitter from the 2D sample `u` (32-bit fractions, as
    /// [`crate::sampler::SampleKey::get2d_bits`] gives them).
    pub fn sample(&self, u: [u32; 2]) -> Option<LightSample> {
        let last = self.emitters.len().checked_sub(1)?;
        let x = u[0] as f64 * (1.0 / 4_294_967_296.0);
        let k = self.emitters.partition_point(|e| e.hi <= x).min(last);
        let e = &self.emitters[k];
        let lo = if k == 0 { 0.0 } else { self.emitters[k - 1].hi };
        // Where `x` lies within the emitter's share, as a fresh uniform
        // value (32 bits of `x` keep at least 24 for a share above 2^-8).
        let rescaled = if e.hi > lo {
            (((x - lo) / (e.hi - lo)) as f32).clamp(0.0, ONE_BELOW)
        } else {
            0.5
        };
        let (b1, b2) = uniform_triangle([rescaled, (u[1] >> 8) as f32 * (1.0 / 16_777_216.0)]);
        Some(LightSample {
            tri: self.tris[k],
            point: crate::geometry::hit_point(&e.verts, b1, b2),
            normal: e.normal,
            emission: e.emission,
            pdf_area: e.pdf_area,
            offset: e.offset,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampler::{SampleKey, Sampler};

    /// A 2 x 1 quad light of two triangles, and a small bright triangle
    /// beside it with three times its power (area 1/8, emission 48).
    fn lights() -> LightSet {
        let (a, b, c, d) = (
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(2.0, 0.0, 0.0),
            Vec3::new(2.0, 1.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        );
        let small = [
            Vec3::new(3.0, 0.0, 0.0),
            Vec3::new(3.5, 0.0, 0.0),
            Vec3::new(3.0, 0.5, 0.0),
        ];
        LightSet::from_emitters([
            (0, [a, b, c], Vec3::ONE),
            (1, [a, c, d], Vec3::ONE),
            (7, small, Vec3::splat(48.0)),
        ])
    }

    /// The exact mean of `f` over the lights, weighted by power: the
    /// quad's (x, y) mean is (1, 0.5), the small triangle's its centroid.
    fn exact_mean_x() -> f64 {
        0.25 * 1.0 + 0.75 * (3.0 + 0.5 / 3.0)
    }

    /// Every sample lands on its emitter with that emitter's area pdf, and
    /// the emitters are chosen in proportion to power: the mean x of the
    /// points converges to the power-weighted mean. With Sobol the choice
    /// and the point are one stratified pattern, so its error at 1024
    /// points is far below independent sampling's standard error (a
    /// separate choice dimension dealt the pattern's points out between
    /// the emitters at random and was no better than that error).
    #[test]
    fn one_pattern_chooses_the_emitter_and_places_the_point() {
        let set = lights();
        let n = 1024u32;
        let pixels = 64u64;
        let (mut se_sobol, mut se_indep, mut var_indep) = (0.0f64, 0.0f64, 0.0f64);
        for sampler in [Sampler::Sobol, Sampler::Independent] {
            for pixel in 0..pixels {
                let (mut sum, mut sum2) = (0.0f64, 0.0f64);
                let mut counts = [0u32; 3];
                for i in 0..n {
                    let key = SampleKey::new(pixel, i, 5, sampler);
                    let s = set.sample(key.get2d_bits(7)).unwrap();
                    let k = set.tris.binary_search(&s.tri).unwrap();
                    counts[k] += 1;
                    assert_eq!(s.pdf_area, set.pdf_area(s.tri));
                    let x = s.point.x as f64;
                    sum += x;
                    sum2 += x * x;
                }
                let mean = sum / n as f64;
                let err2 = (mean - exact_mean_x()).powi(2);
                match sampler {
                    Sampler::Sobol => {
                        // Power 1 : 1 : 6 over 1024 stratified points.
                        assert_eq!(counts, [128, 128, 768], "pixel {pixel}");
                        se_sobol += err2;
                    }
                    Sampler::Independent => {
                        se_indep += err2;
                        var_indep += (sum2 / n as f64 - mean * mean) / n as f64;
                    }
                }
            }
        }
        let (rms_sobol, rms_indep, sigma) = (
            (se_sobol / pixels as f64).sqrt(),
            (se_indep / pixels as f64).sqrt(),
            (var_indep / pixels as f64).sqrt(),
        );
        // Independent sampling is unbiased: its RMS error over 64 pixels
        // is its standard error to within a few tenths.
        assert!(
            (rms_indep / sigma - 1.0).abs() < 0.3,
            "independent: rms {rms_indep}, standard error {sigma}"
        );
        assert!(
            rms_sobol < 0.05 * sigma,
            "sobol: rms {rms_sobol} against the standard error {sigma}"
        );
        // The choice from a dimension of its own, as before: its error
        // (measured: 0.22 of the standard error, against 0.004 above) stays
        // above a tenth of it, so the bound above tells the two apart.
        let mut se_apart = 0.0f64;
        for pixel in 0..pixels {
            let mut sum = 0.0f64;
            for i in 0..n {
                let key = SampleKey::new(pixel, i, 5, Sampler::Sobol);
                let u = key.get1d(6) as f64;
                let k = set.emitters.partition_point(|e| e.hi <= u);
                let (b1, b2) = uniform_triangle(key.get2d(7));
                sum += crate::geometry::hit_point(&set.emitters[k].verts, b1, b2).x as f64;
            }
            se_apart += (sum / n as f64 - exact_mean_x()).powi(2);
        }
        let rms_apart = (se_apart / pixels as f64).sqrt();
        assert!(
            rms_apart > 0.1 * sigma,
            "a separate choice: rms {rms_apart}, standard error {sigma}"
        );
    }

    /// A set travels as its emitters alone and is rebuilt on arrival: the
    /// same set to the bit, pdfs, normals and offsets included.
    #[test]
    fn the_wire_carries_the_emitters_and_the_rest_is_rebuilt() {
        let set = lights();
        let bytes = postcard::to_allocvec(&set).unwrap();
        let back: LightSet = postcard::from_bytes(&bytes).unwrap();
        assert_eq!(back, set);
        for tri in [0, 1, 7, 3] {
            assert_eq!(back.pdf_area(tri).to_bits(), set.pdf_area(tri).to_bits());
        }
        // Parts of unequal length from a peer give a set of the emitters
        // they agree on, not one that indexes past its arrays.
        let ragged = Emitters {
            tris: vec![0, 1, 7],
            verts: set.emitters.iter().map(|e| e.verts).take(2).collect(),
            emission: vec![Vec3::ONE; 3],
        };
        let back: LightSet =
            postcard::from_bytes(&postcard::to_allocvec(&ragged).unwrap()).unwrap();
        assert_eq!(back.tris, [0, 1]);
        assert!(back.sample([u32::MAX, u32::MAX]).is_some());
        assert_eq!(back.pdf_area(7), 0.0);
    }
}
