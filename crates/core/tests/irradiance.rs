//! Ward's irradiance cache in the renderer: interpolation against the
//! irradiance traced at the same points, what gradients buy, and an image
//! that does not depend on the number of threads.

mod common;
use glam::Vec3;
use locus_core::integrator::Frame;
use locus_core::irradiance::overture::{build, traced};
use locus_core::irradiance::{IrradianceCache, IrradianceParams};
use locus_core::path::WholeScene;
use locus_core::render::{Prepared, RenderOptions, render};
use locus_core::sampler::SampleKey;
use locus_core::stats::TraceStats;

fn prepared(size: u32, max_depth: u32) -> Prepared {
    let mut scene = common::small_cornell(size, size, 4);
    scene.settings.max_depth = max_depth;
    Prepared::new(scene)
}

/// Frames of first hits at jittered points in the image, with the traced
/// irradiance there (many rays: its own error is small against the
/// interpolation's).
fn references(prep: &Prepared, n: u32) -> Vec<(Frame, Vec3)> {
    let kernel = prep.kernel(prep.scene.settings.max_depth, None);
    let tracer = WholeScene(&prep.accel);
    let cam = &prep.scene.camera;
    let mut st = TraceStats::default();
    let mut out = Vec::new();
    for i in 0..n {
        let k = SampleKey::independent(i as u64, 0, 99);
        let (x, y) = (
            (k.get1d(0) * cam.width as f32) as u32,
            (k.get1d(1) * cam.height as f32) as u32,
        );
        let ray = cam.ray(x, y, k.get2d(2));
        let Some(h) = prep.accel.closest(&ray, 0.0, f32::INFINITY, &mut st) else {
            continue;
        };
        let s = prep.accel.surface(&h);
        if prep.scene.materials[s.material as usize]
            .albedo
            .max_element()
            <= 0.0
        {
            continue;
        }
        let f = Frame::at(ray.dir, &s.verts, &s.hit, s.shading);
        let e = traced(&kernel, &tracer, &f, 1_000_000 + i as u64, 65_536, &mut st).e;
        out.push((f, e));
    }
    out
}

fn cache(prep: &Prepared, params: IrradianceParams) -> IrradianceCache {
    let kernel = prep.kernel(prep.scene.settings.max_depth, None);
    let tracer = WholeScene(&prep.accel);
    let bounds = locus_core::geometry::Bounds::of_triangles(&prep.scene.tris);
    build(&kernel, &tracer, params, &bounds).0
}

/// Mean relative error of the interpolated irradiance at the covered
/// reference points (luminance-like channel sum), and the share covered.
fn error(c: &IrradianceCache, refs: &[(Frame, Vec3)]) -> (f64, f64) {
    let (mut sum, mut covered) = (0.0f64, 0usize);
    for (f, e) in refs {
        if let Some(got) = c.interpolate(f.p, f.ns) {
            covered += 1;
            let want = e.element_sum() as f64;
            sum += ((got.element_sum() as f64) - want).abs() / want.max(1e-3);
        }
    }
    (
        sum / covered.max(1) as f64,
        covered as f64 / refs.len() as f64,
    )
}

/// As Ward's accuracy `a` shrinks, records are placed closer and the
/// interpolated irradiance approaches the irradiance traced at the point;
/// with gradients it is closer still at the same `a`.
#[test]
fn interpolation_approaches_the_traced_irradiance_as_the_bound_shrinks() {
    // Pixels small enough that the records' validity follows Ward's bound
    // rather than the screen-space clamp.
    // One bounce after the record (its rays see the direct light at their
    // hits): the records' own noise stays below the interpolation's error.
    let prep = prepared(128, 2);
    let refs = references(&prep, 120);
    assert!(refs.len() > 80, "{} reference points", refs.len());
    let at = |accuracy: f32, gradients: bool| {
        let p = IrradianceParams {
            accuracy,
            divisions: 4096,
            resolution: 256.0,
            gradients,
            spacing: 8,
            ..Default::default()
        };
        let c = cache(&prep, p);
        let (e, cov) = error(&c, &refs);
        eprintln!(
            "a {accuracy} gradients {gradients}: {} records, error {e:.4}, covered {cov:.3}",
            c.len()
        );
        (e, cov, c.len())
    };
    let coarse = at(0.6, true);
    let mid = at(0.3, true);
    let fine = at(0.15, true);
    let flat = at(0.3, false);
    assert!(
        coarse.2 < mid.2 && mid.2 < fine.2,
        "records {coarse:?} {mid:?} {fine:?}"
    );
    assert!(
        fine.0 < mid.0 && mid.0 < coarse.0,
        "errors {coarse:?} {mid:?} {fine:?}"
    );
    assert!(fine.0 < 0.05, "at a = 0.15 the mean error is {:.3}", fine.0);
    assert!(mid.0 < flat.0, "gradients {mid:?} against none {flat:?}");
    for (_, cov, _) in [coarse, mid, fine] {
        assert!(cov > 0.9, "only {cov} of the points covered");
    }
}

/// Records are placed against the coarser levels only, so the image is
/// the same on any number of threads; the cache answers nearly every first
/// vertex, and the rest are path traced.
#[test]
fn the_cached_image_is_the_same_on_any_number_of_threads() {
    let prep = prepared(32, 8);
    let mut opts = RenderOptions::from_scene(&prep.scene);
    opts.irradiance = Some(IrradianceParams {
        divisions: 128,
        ..Default::default()
    });
    opts.threads = 1;
    let one = render(&prep, &opts, &|_, _| {});
    opts.threads = 2;
    let two = render(&prep, &opts, &|_, _| {});
    assert_eq!(one.image.to_bits(), two.image.to_bits());
    let o = one.irradiance.expect("overture stats");
    assert!(o.records > 20, "{o:?}");
    let u = one.stats.irradiance;
    assert!(u.interpolated > 10 * u.traced && u.traced > 0, "{u:?}");
    // The cache changed the image: the test can fail.
    opts.irradiance = None;
    let plain = render(&prep, &opts, &|_, _| {});
    assert_ne!(plain.image.to_bits(), one.image.to_bits());
    assert_eq!(plain.stats.irradiance.interpolated, 0);
}

/// Members sharing the overture level by level (shares 1, 2 and 1, on
/// their own threads, exchanging through a barrier as a farm's scheduler
/// relays) hold exactly the records one machine makes, in the same order;
/// so does a member that resumes after two levels others measured.
#[test]
fn members_sharing_the_overture_hold_the_records_one_machine_makes() {
    use locus_core::irradiance::overture::{Measured, Share, for_scene, run};
    use std::collections::HashMap;
    use std::sync::{Barrier, Mutex};
    let prep = prepared(24, 4);
    let params = IrradianceParams {
        divisions: 64,
        spacing: 8,
        ..Default::default()
    };
    let alone = cache(&prep, params);
    let lights = locus_core::light::LightSet::build(&prep.scene);
    let bounds = locus_core::geometry::Bounds::of_triangles(&prep.scene.tris);
    let shares = [1u32, 2, 1];
    let barrier = Barrier::new(shares.len());
    let levels: Mutex<HashMap<u32, Vec<(u32, Measured)>>> = Mutex::default();
    let members: Vec<IrradianceCache> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..shares.len())
            .map(|me| {
                let (prep, barrier, levels, bounds) = (&prep, &barrier, &levels, &bounds);
                s.spawn(move || {
                    let kernel = prep.kernel(prep.scene.settings.max_depth, None);
                    let tracer = WholeScene(&prep.accel);
                    let share = Share {
                        me,
                        shares: &shares,
                        resume: 0,
                    };
                    let exchange = |level: u32, mine: Vec<(u32, Measured)>, _: &TraceStats| {
                        levels
                            .lock()
                            .unwrap()
                            .entry(level)
                            .or_default()
                            .extend(mine);
                        barrier.wait();
                        let mut all = levels.lock().unwrap()[&level].clone();
                        all.sort_by_key(|(i, _)| *i);
                        assert!(all.iter().enumerate().all(|(k, (i, _))| k as u32 == *i));
                        Ok::<_, ()>(all.into_iter().map(|(_, m)| m).collect())
                    };
                    run(&kernel, &tracer, params, bounds, share, exchange)
                        .unwrap()
                        .0
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    assert!(alone.len() > 30, "{} records", alone.len());
    for (me, c) in members.iter().enumerate() {
        assert_eq!(c.records(), alone.records(), "member {me}");
    }
    // Every member measured some of them.
    let got = levels.into_inner().unwrap();
    let by_member = |w: usize| {
        got.values()
            .flatten()
            .filter(|(i, _)| locus_core::irradiance::overture::measurer(*i, &shares) == w)
            .count()
    };
    assert!((0..3).all(|w| by_member(w) > 0));
    // The scheduler's overture, whole and resumed after two levels.
    let (whole, _, known) = for_scene(&prep.scene, &lights, params, &[]);
    assert_eq!(whole.records(), alone.records());
    let (resumed, stats, again) = for_scene(&prep.scene, &lights, params, &known[..2]);
    assert_eq!(resumed.records(), alone.records());
    assert_eq!(again, known);
    assert!(stats.points > 0 && stats.levels as usize == known.len());
}

/// The overture measures without the directional caches, as the farm's
/// measurers do: switching them on changes the render, not the records.
#[test]
fn the_directional_cache_leaves_the_records_alone() {
    let prep = prepared(32, 8);
    let mut opts = RenderOptions::from_scene(&prep.scene);
    opts.irradiance = Some(IrradianceParams {
        divisions: 64,
        ..Default::default()
    });
    opts.threads = 2;
    let plain = render(&prep, &opts, &|_, _| {});
    opts.cache = Some(locus_core::dircache::CacheParams {
        radius: 0.5,
        ..Default::default()
    });
    let both = render(&prep, &opts, &|_, _| {});
    // Rays reached the directional caches' perimeters in the render.
    let c = both.stats.cache;
    assert!(c.global + c.lookups > 0, "{c:?}");
    let (a, b) = (plain.irradiance.unwrap(), both.irradiance.unwrap());
    assert_eq!(a.records, b.records);
    assert_eq!(
        (a.trace.rays(), a.trace.bvh_nodes),
        (b.trace.rays(), b.trace.bvh_nodes)
    );
}
