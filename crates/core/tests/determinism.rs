//! Determinism: the image is a pure function of scene and seed, bit for bit,
//! whatever the thread count and tile order.

mod common;
use locus_core::render::{Prepared, RenderOptions, TileOrder, render};

#[test]
fn same_bits_for_any_threads_and_tile_order() {
    let s = common::small_cornell(40, 30, 8);
    let prep = Prepared::new(s);
    let base = RenderOptions::from_scene(&prep.scene);
    let run = |threads, order, tile| {
        let o = RenderOptions {
            threads,
            tile_order: order,
            tile_size: tile,
            ..base
        };
        render(&prep, &o, &|_, _| {})
    };
    let reference = run(1, TileOrder::Scanline, 16);
    let bits = reference.image.to_bits();
    assert!(reference.image.mean()[0] > 0.0);
    for (threads, order, tile) in [
        (2, TileOrder::Scanline, 16),
        (1, TileOrder::Shuffled(7), 16),
        (2, TileOrder::Reverse, 16),
        (2, TileOrder::Shuffled(3), 7),
    ] {
        let other = run(threads, order, tile);
        assert_eq!(
            other.image.to_bits(),
            bits,
            "threads {threads}, {order:?}, tile {tile}"
        );
        assert_eq!(
            other.stats, reference.stats,
            "counters must not depend on scheduling either"
        );
    }
    // A different seed must change the image (the test can fail).
    let o = RenderOptions {
        seed: base.seed + 1,
        ..base
    };
    assert_ne!(render(&prep, &o, &|_, _| {}).image.to_bits(), bits);
}

/// A job of fewer camera samples than triangles builds its BVH quick
/// (`BuildQuality::for_job`; a scene's `bvh` setting fixes either), a
/// different tree from the full build, and
/// renders the same image to the bit: hits are exact and ties go to the
/// smaller id whatever the tree.
#[test]
fn a_quick_bvh_renders_what_a_full_one_does() {
    use locus_core::accel::{BuildQuality, QUICK_BELOW_SAMPLES_PER_TRIANGLE};
    let mut s = common::furnace_scene(0.7, 0.3, 2, 16);
    s.camera.width = 24;
    s.camera.height = 16;
    let tris = s.tris.len() as u64;
    let samples = s.camera.samples(s.settings.spp);
    assert!(
        samples < tris * QUICK_BELOW_SAMPLES_PER_TRIANGLE,
        "{samples} {tris}"
    );
    let quick = Prepared::for_job(s.clone(), s.settings.spp);
    let full = Prepared::new(s);
    assert_eq!(quick.timings.quality, BuildQuality::Quick);
    assert_eq!(full.timings.quality, BuildQuality::Full);
    assert_ne!(
        quick.accel.bytes(),
        full.accel.bytes(),
        "the two builds made the same tree: the test would show nothing"
    );
    let o = RenderOptions::from_scene(&full.scene);
    let a = render(&quick, &o, &|_, _| {});
    let b = render(&full, &o, &|_, _| {});
    assert!(b.image.mean()[0] > 0.0);
    assert_eq!(a.image.to_bits(), b.image.to_bits());
    assert_eq!(a.stats.rays(), b.stats.rays());
    // The rule's edge: at one sample a triangle the full build pays.
    assert_eq!(BuildQuality::for_job(tris, tris), BuildQuality::Full);
    assert_eq!(BuildQuality::for_job(tris - 1, tris), BuildQuality::Quick);
    assert_eq!(BuildQuality::for_job(0, 0), BuildQuality::Full);
    // A setting other than `auto` holds whatever the job's samples.
    use locus_core::accel::BvhSetting;
    for (setting, spp, want) in [
        (BvhSetting::Auto, 1 << 20, BuildQuality::Full),
        (BvhSetting::Full, 1, BuildQuality::Full),
        (BvhSetting::Quick, 1 << 20, BuildQuality::Quick),
    ] {
        let samples = full.scene.camera.samples(spp);
        assert_eq!(
            setting.quality(samples, tris),
            want,
            "{setting:?} at {spp} spp"
        );
    }
    let mut pinned = full.scene.clone();
    pinned.settings.bvh = BvhSetting::Full;
    let spp = pinned.settings.spp;
    assert_eq!(
        Prepared::for_job(pinned, spp).timings.quality,
        BuildQuality::Full
    );
}
