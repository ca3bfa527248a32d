//! Adaptive sampling ([`locus_core::spread`]) on one machine: it renders
//! exactly the samples an even render does, reproduces itself on any
//! thread count and tile order, and leaves less error than the even render
//! of as many samples, by more than the seeds' spread.

mod common;
use locus_core::metrics::compare;
use locus_core::render::{Prepared, RenderOptions, RenderOutput, TileOrder, render};
use locus_core::spread::{MAX_SHARE, pilot_end};

fn run(
    prep: &Prepared,
    spp: u32,
    seed: u64,
    adaptive: bool,
    threads: usize,
    order: TileOrder,
) -> RenderOutput {
    let mut o = RenderOptions::from_scene(&prep.scene);
    o.spp = spp;
    o.seed = seed;
    o.adaptive = adaptive;
    o.threads = threads;
    o.tile_order = order;
    render(prep, &o, &|_, _| {})
}

#[test]
fn an_adaptive_render_spends_the_even_renders_samples_and_reproduces_itself() {
    let spp = 32;
    let prep = Prepared::new(common::small_cornell(40, 30, spp));
    let pixels = 40 * 30;
    let a = run(&prep, spp, 3, true, 2, TileOrder::Scanline);
    let counts = a.sample_counts.clone().expect("an adaptive render counts");
    assert_eq!(counts.len(), pixels);
    let total: u64 = counts.iter().map(|&c| c as u64).sum();
    assert_eq!(
        total,
        spp as u64 * pixels as u64,
        "the even render's samples"
    );
    assert_eq!(a.stats.samples, total, "every counted sample traced once");
    assert!(
        counts
            .iter()
            .all(|&c| c >= pilot_end(spp) && c <= MAX_SHARE * spp)
    );
    assert!(
        counts.iter().any(|&c| c != spp),
        "the Cornell box's noise is not even: some pixel gets more than another"
    );
    for (threads, order) in [(1, TileOrder::Reverse), (2, TileOrder::Shuffled(7))] {
        let b = run(&prep, spp, 3, true, threads, order);
        assert_eq!(
            b.sample_counts.as_ref(),
            Some(&counts),
            "{threads} threads, {order:?}"
        );
        assert_eq!(
            b.image.to_bits(),
            a.image.to_bits(),
            "{threads} threads, {order:?}"
        );
        assert_eq!(b.error_estimate, a.error_estimate);
    }
    // Off, the render is the even one, counted as such.
    let even = run(&prep, spp, 3, false, 2, TileOrder::Scanline);
    assert_eq!((even.sample_counts, even.stats.samples), (None, total));
}

/// The relMSE against a reference of eight seeds' renders with and without
/// adaptive sampling, at the same samples: the per-seed difference has a
/// mean above four of its standard errors. The reference's own noise adds
/// (nearly) the same to both, so it does not favour either.
#[test]
fn adaptive_sampling_leaves_less_error_at_equal_samples() {
    let prep = Prepared::new(common::small_cornell(48, 48, 32));
    let reference = run(&prep, 2048, 1_000, false, 2, TileOrder::Scanline).image;
    let rel = |seed, adaptive| {
        let o = run(&prep, 32, seed, adaptive, 2, TileOrder::Scanline);
        compare(&o.image, &reference).unwrap().rel_mse
    };
    let pairs: Vec<(f64, f64)> = (1..=8).map(|s| (rel(s, false), rel(s, true))).collect();
    let d: Vec<f64> = pairs.iter().map(|(e, a)| e - a).collect();
    let n = d.len() as f64;
    let even = pairs.iter().map(|p| p.0).sum::<f64>() / n;
    let mean = d.iter().sum::<f64>() / n;
    let se = (d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0) / n).sqrt();
    eprintln!(
        "relMSE taken off by adaptive sampling: {mean:.3e} of {even:.3e} (standard error {se:.2e})"
    );
    assert!(
        mean > 4.0 * se,
        "adaptive sampling took {mean:.3e} off the relMSE (standard error {se:.2e}): {d:?}"
    );
}
