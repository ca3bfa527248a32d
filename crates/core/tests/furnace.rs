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

/// The tolerances above come from the spread of pixels, which is honest
/// for the Sobol sampler only if pixels are independent estimates (each
/// pixel's patterns scrambled by its own hash). Checked from independent
/// seeds: over 16 seeds, the spread of the image mean must agree with the
/// standard error the pixels give. With 15 degrees of freedom the ratio of
/// the two lies in [0.554, 1.479] with 99% probability for independent
/// pixels; pixels that shared their sample patterns would put it far above.
#[test]
fn pixel_standard_errors_hold_for_the_sobol_sampler() {
    use locus_core::sampler::Sampler;
    let mut scene = common::furnace_scene(0.8, 0.25, 16, 6);
    scene.settings.sampler = Sampler::Sobol;
    let prep = Prepared::new(scene);
    let (mut means, mut ses) = (Vec::new(), Vec::new());
    for seed in 0..16u64 {
        let mut opts = RenderOptions::from_scene(&prep.scene);
        opts.seed = 1000 + seed;
        let out = render(&prep, &opts, &|_, _| {});
        let (m, se) = mean_and_standard_error(&out.image.pixels, 1);
        means.push(m);
        ses.push(se);
    }
    let n = means.len() as f64;
    let mean = means.iter().sum::<f64>() / n;
    let spread = (means.iter().map(|m| (m - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    let se = (ses.iter().map(|s| s * s).sum::<f64>() / n).sqrt();
    let ratio = spread / se;
    eprintln!(
        "Sobol furnace: seed spread {spread:.3e}, pixel standard error {se:.3e}, ratio {ratio:.3}"
    );
    assert!(
        (0.554..1.479).contains(&ratio),
        "the spread over seeds ({spread:.3e}) and the pixels' standard error ({se:.3e}) disagree: ratio {ratio:.3}"
    );
}
