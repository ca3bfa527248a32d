//! Self-intersection: a large, finely tessellated plane lit by a small
//! rectangular light at grazing incidence. With direct lighting only, every
//! pixel's expected radiance is albedo / pi times the closed-form irradiance
//! from a uniform polygon (Lambert's formula). Surface acne shows as pixels
//! far below it.

mod common;
use glam::Vec3;
use locus_core::generate::MeshBuilder;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::scene::{Material, RenderSettings};

/// Irradiance at `p` (normal `n`) from a polygon of radiance `le`, fully
/// visible and above the horizon: E = le/2 * sum_i theta_i * (n . gamma_i).
fn polygon_irradiance(p: Vec3, n: Vec3, poly: &[Vec3], le: f64) -> f64 {
    let mut s = 0.0f64;
    for i in 0..poly.len() {
        let a = (poly[i] - p).as_dvec3().normalize();
        let b = (poly[(i + 1) % poly.len()] - p).as_dvec3().normalize();
        let theta = a.dot(b).clamp(-1.0, 1.0).acos();
        let g = a.cross(b).normalize();
        s += theta * n.as_dvec3().dot(g);
    }
    (le / 2.0 * s).abs()
}

fn grazing(offset: Vec3) -> (f64, f64, usize, usize) {
    let mut mb = MeshBuilder::default();
    let half = 40.0;
    // Plane y = 0 (offset), normal +y, 80 x 80 grid: many shared edges.
    mb.grid(
        offset + Vec3::new(-half, 0.0, -half),
        Vec3::Z * 2.0 * half,
        Vec3::X * 2.0 * half,
        80,
        0,
    );
    // Light: 2 x 0.5 rectangle standing 0.3 above the plane, 25 units away
    // in -x, facing +x, so it reaches the viewed patch at 80-89 degrees.
    let (c, ea, eb) = (
        offset + Vec3::new(-25.0, 0.3, -1.0),
        Vec3::Y * 0.5,
        Vec3::Z * 2.0,
    );
    let quad = [c, c + ea, c + ea + eb, c + eb];
    // Winding so the normal (ea x eb) points +x.
    assert!(ea.cross(eb).x > 0.0);
    mb.grid(c, ea, eb, 1, 1);
    let le = 50.0f32;
    let mats = vec![
        Material {
            name: "plane".into(),
            albedo: Vec3::splat(0.5),
            emission: Vec3::ZERO,
        },
        Material {
            name: "light".into(),
            albedo: Vec3::ZERO,
            emission: Vec3::splat(le),
        },
    ];
    // Look straight down on the patch [-4, 4]^2 around the origin.
    let mut cam = common::camera(offset + Vec3::new(0.0, 20.0, 0.0), offset, 22.6, 32, 32);
    cam.up = Vec3::Z;
    let settings = RenderSettings {
        spp: 64,
        max_depth: 1,
        seed: 5,
        ..Default::default()
    };
    let scene = common::scene_from(&mb, mats, cam.clone(), settings);
    let prep = Prepared::new(scene);
    let out = render(&prep, &RenderOptions::from_scene(&prep.scene), &|_, _| {});
    // Expected value per pixel at the pixel centre's ground point.
    let mut ratio_sum = 0.0;
    let mut ratios = Vec::new();
    let mut dark = 0;
    for y in 0..cam.height {
        for x in 0..cam.width {
            let r = cam.ray(x, y, [0.5, 0.5]);
            let t = (offset.y - r.origin.y) / r.dir.y;
            let p = r.at(t);
            let e = polygon_irradiance(p, Vec3::Y, &quad, le as f64);
            let expected = 0.5 / std::f64::consts::PI * e;
            let got = out.image.pixels[(y * cam.width + x) as usize][0] as f64;
            let q = got / expected;
            if q < 0.5 {
                dark += 1;
            }
            ratio_sum += q;
            ratios.push(q);
        }
    }
    let n = ratios.len() as f64;
    let mean = ratio_sum / n;
    let var = ratios.iter().map(|q| (q - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, (var / n).sqrt(), dark, ratios.len())
}

#[test]
fn grazing_light_shows_no_acne() {
    for offset in [Vec3::ZERO, Vec3::new(3.0e4, 1.0e4, -2.0e4)] {
        let (mean, se, dark, n) = grazing(offset);
        eprintln!(
            "offset {offset}: mean rendered/closed-form {mean:.5} (se {se:.2e}), {dark} of {n} pixels below half"
        );
        assert_eq!(
            dark, 0,
            "{dark} pixels lost more than half their light: shadow rays hit their own surface"
        );
        // Pixel-footprint averaging of a smoothly varying irradiance differs
        // from its centre value by well under 1%; the rest is noise.
        assert!(
            (mean - 1.0).abs() < 4.0 * se + 0.01,
            "mean ratio {mean}, se {se}"
        );
    }
}
