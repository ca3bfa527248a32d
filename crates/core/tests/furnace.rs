//! White furnace: inside a closed diffuse enclosure with albedo rho and
//! uniform emission Le on every surface, radiance is Le / (1 - rho) in every
//! direction. The path tracer (NEE + MIS + Russian roulette) must agree
//! within a bound derived from the standard error of the render.

mod common;
use glam::Vec3;
use locus_core::generate::MeshBuilder;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::scene::{Material, RenderSettings};

fn furnace(rho: f32, le: f32, spp: u32) -> (f64, f64, f64) {
    // A cube seen from inside: faces wound to point inward, because emission
    // is one-sided. Finely tessellated so NEE samples many triangles.
    let mut mb = MeshBuilder::default();
    let (lo, s) = (Vec3::splat(-1.0), 2.0);
    let (x, y, z) = (Vec3::X * s, Vec3::Y * s, Vec3::Z * s);
    let n = 6;
    mb.grid(lo, y, z, n, 0); // x = -1, normal +x
    mb.grid(lo + x, z, y, n, 0); // x = +1, normal -x
    mb.grid(lo, z, x, n, 0); // y = -1, normal +y
    mb.grid(lo + y, x, z, n, 0); // y = +1, normal -y
    mb.grid(lo, x, y, n, 0); // z = -1, normal +z
    mb.grid(lo + z, y, x, n, 0); // z = +1, normal -z
    let mats = vec![Material {
        name: "furnace".into(),
        albedo: Vec3::splat(rho),
        emission: Vec3::splat(le),
    }];
    let cam = common::camera(
        Vec3::new(0.1, -0.2, 0.05),
        Vec3::new(1.0, 0.3, 0.7),
        90.0,
        24,
        24,
    );
    let settings = RenderSettings {
        spp,
        max_depth: 200,
        seed: 11,
        ..Default::default()
    };
    let scene = common::scene_from(&mb, mats, cam, settings);
    // Every face must point inward for the emission to be seen.
    for t in &scene.tris {
        let c = (t[0] + t[1] + t[2]) / 3.0;
        assert!(
            locus_core::geometry::tri_cross(t).dot(-c) > 0.0,
            "face points outward"
        );
    }
    let prep = Prepared::new(scene);
    let opts = RenderOptions::from_scene(&prep.scene);
    let out = render(&prep, &opts, &|_, _| {});
    assert_eq!(out.stats.invalid_samples, 0);
    // Pixels are independent estimates (disjoint sample keys), so the
    // standard error of the image mean follows from their spread.
    let vals: Vec<f64> = out.image.pixels.iter().map(|p| p[1] as f64).collect();
    let n = vals.len() as f64;
    let mean = vals.iter().sum::<f64>() / n;
    let var = vals.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, (var / n).sqrt(), (le / (1.0 - rho)) as f64)
}

#[test]
fn white_furnace_matches_le_over_one_minus_rho() {
    for (rho, le) in [(0.5f32, 1.0f32), (0.8, 0.25)] {
        let (mean, se, expected) = furnace(rho, le, 64);
        // Truncation at depth 200 removes rho^201 / (1 - rho) * Le: below 1e-19.
        let tol = 4.0 * se;
        eprintln!(
            "furnace rho={rho} Le={le}: mean {mean:.6} expected {expected:.6} se {se:.2e} (|err| = {:.2} se)",
            (mean - expected).abs() / se
        );
        assert!(
            se > 0.0 && se < 0.02 * expected,
            "standard error {se} too large to test anything"
        );
        assert!(
            (mean - expected).abs() < tol,
            "furnace mean {mean} vs {expected}, tolerance {tol} (4 standard errors)"
        );
    }
}
