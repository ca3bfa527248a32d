//! Scale: the Cornell box translated by 1e5 and, separately, scaled by 1e-3
//! (camera included) must render like the original. Renders use identical
//! sample keys, so differences come only from rounding; the tolerance is a
//! fraction of the noise between two independent renders (different seeds)
//! of the original, and the image means must agree within 4 standard
//! errors of the difference.

mod common;
use glam::{Mat4, Vec3};
use locus_core::image_io::Image;
use locus_core::metrics::compare;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::scene::Scene;

fn render_scene(mut s: Scene, seed: u64) -> Image {
    s.camera.width = 48;
    s.camera.height = 48;
    s.settings.spp = 16;
    s.settings.seed = seed;
    let prep = Prepared::new(s);
    render(&prep, &RenderOptions::from_scene(&prep.scene), &|_, _| {}).image
}

fn lum(img: &Image) -> Vec<f64> {
    img.pixels
        .iter()
        .map(|p| (p[0] + p[1] + p[2]) as f64 / 3.0)
        .collect()
}

#[test]
fn translated_and_scaled_cornell_box_render_the_same() {
    let base = common::cornell();
    let original = render_scene(base.clone(), 1);
    let noise = compare(&render_scene(base.clone(), 2), &original)
        .unwrap()
        .rmse;
    for (name, m, bound) in [
        (
            "translate 1e5",
            Mat4::from_translation(Vec3::splat(1.0e5)),
            0.1,
        ),
        ("scale 1e-3", Mat4::from_scale(Vec3::splat(1.0e-3)), 0.1),
    ] {
        let img = render_scene(base.transformed(m), 1);
        let e = compare(&img, &original).unwrap();
        let (a, b) = (lum(&img), lum(&original));
        let d: Vec<f64> = a.iter().zip(&b).map(|(x, y)| x - y).collect();
        let n = d.len() as f64;
        let md = d.iter().sum::<f64>() / n;
        let sd = (d.iter().map(|x| (x - md).powi(2)).sum::<f64>() / (n - 1.0)).sqrt() / n.sqrt();
        eprintln!(
            "{name}: RMSE {:.4e} vs seed-to-seed noise {noise:.4e} (ratio {:.3}); mean diff {md:.3e} ({:.2} se)",
            e.rmse,
            e.rmse / noise,
            md.abs() / sd.max(1e-30)
        );
        assert!(
            e.rmse < bound * noise,
            "{name}: RMSE {} exceeds {bound} x noise {noise}",
            e.rmse
        );
        assert!(
            md.abs() <= 4.0 * sd + 1e-9,
            "{name}: mean shifted by {md} ({sd} se)"
        );
    }
}
