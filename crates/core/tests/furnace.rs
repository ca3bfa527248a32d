//! White furnace: inside a closed diffuse enclosure with albedo rho and
//! uniform emission Le on every surface, radiance is Le / (1 - rho) in every
//! direction. The path tracer (NEE + MIS + Russian roulette) must agree
//! within a bound derived from the standard error of the render.

mod common;
use locus_core::metrics::mean_and_standard_error;
use locus_core::render::{Prepared, RenderOptions, render};

fn furnace(rho: f32, le: f32, spp: u32) -> (f64, f64, f64) {
    let scene = common::furnace_scene(rho, le, spp, 6);
    let prep = Prepared::new(scene);
    let opts = RenderOptions::from_scene(&prep.scene);
    let out = render(&prep, &opts, &|_, _| {});
    assert_eq!(out.stats.invalid_samples, 0);
    let (mean, se) = mean_and_standard_error(&out.image.pixels, 1);
    (mean, se, (le / (1.0 - rho)) as f64)
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
