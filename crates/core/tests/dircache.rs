//! The directional cache inside the renderer: where it must change nothing,
//! and where its answers are exact in expectation.

mod common;
use locus_core::dircache::CacheParams;
use locus_core::metrics::mean_and_standard_error;
use locus_core::render::{Prepared, RenderOptions, render};

/// With a locality radius that contains the whole scene, every ray that
/// can hit geometry hits it inside the sphere and is shaded exactly (with
/// MIS, as every light is inside the sphere); the rays that reach the
/// perimeter escape the scene and carry zero, so every cached answer is
/// exactly zero. The image must be bit-identical to the cache-free render.
#[test]
fn cache_with_all_geometry_inside_the_radius_changes_no_bit() {
    let mut scene = common::small_cornell(32, 32, 4);
    scene.settings.octree.max_leaf_tris = 4;
    let prep = Prepared::new(scene);
    assert!(prep.octree().leaf_count() > 4);
    let mut plain = RenderOptions::from_scene(&prep.scene);
    plain.threads = 2;
    let want = render(&prep, &plain, &|_, _| {});
    let cached = RenderOptions {
        cache: Some(CacheParams {
            radius: 1e6,
            ..CacheParams::default()
        }),
        ..plain
    };
    let got = render(&prep, &cached, &|_, _| {});
    let c = got.stats.cache;
    // The cache path ran: rays were traced locally, and the open front of
    // the box let some reach the perimeter.
    assert!(c.local > 1000, "{c:?}");
    assert!(c.global + c.lookups > 0, "{c:?}");
    assert_eq!(got.image.to_bits(), want.image.to_bits());
    // A radius that leaves lights outside the sphere changes the split of
    // direct light, so the bits differ: the test can fail.
    let small = RenderOptions {
        cache: Some(CacheParams {
            radius: 0.5,
            ..CacheParams::default()
        }),
        ..plain
    };
    assert_ne!(
        render(&prep, &small, &|_, _| {}).image.to_bits(),
        want.image.to_bits()
    );
}

/// The relative bias the directional cache may add in the furnace.
const CACHE_BIAS: f64 = 0.015;

/// Inside a white furnace the radiance arriving from every direction at
/// every point is Le / (1 - rho), and so is what a cache node averages. The
/// uncached render must agree with the analytic value within 4 standard
/// errors; the cached one within 4 standard errors plus [`CACHE_BIAS`],
/// with a good share of rays answered by the cache.
///
/// The cache is not exact in expectation. Measured here over seeds 0 to 3
/// before the Sobol sampler and the later Russian roulette, the cached
/// mean was 0.3% low on average (each seed within its 4 standard errors);
/// with them, whose lower noise and longer paths show it, 0.8 to 1.2% low.
/// It is in what the nodes average (answering with the true value instead
/// leaves no bias, as do nodes that wait for 1,000 samples), not in the
/// depth truncation (`max_depth` 200 reads as low), and cached values
/// feed other caches, which amplifies it; the directional-cache issue
/// takes it up.
#[test]
fn cache_bias_in_a_uniform_environment_is_small() {
    let (rho, le) = (0.5f32, 1.0f32);
    let mut scene = common::furnace_scene(rho, le, 160, 8);
    scene.settings.octree.max_leaf_tris = 16;
    let prep = Prepared::new(scene);
    let mut plain = RenderOptions::from_scene(&prep.scene);
    plain.threads = 2;
    let cached = RenderOptions {
        cache: Some(CacheParams {
            radius: 0.9,
            split_samples: 8,
            fine_solid_angle: 4.0 * std::f64::consts::PI / 16.0,
            trust_samples: 16,
            // Per-ray values here vary by about their mean (path length,
            // light sample): only variance well above that is direction.
            split_rel_variance: 4.0,
            answer_samples: 16,
            answer_rel_error: 0.2,
            ..CacheParams::default()
        }),
        ..plain
    };
    let expected = (le / (1.0 - rho)) as f64;
    let a = render(&prep, &plain, &|_, _| {});
    let b = render(&prep, &cached, &|_, _| {});
    let (ma, sa) = mean_and_standard_error(&a.image.pixels, 1);
    let (mb, sb) = mean_and_standard_error(&b.image.pixels, 1);
    let c = b.stats.cache;
    eprintln!(
        "furnace: uncached {ma:.5} (se {sa:.1e}), cached {mb:.5} (se {sb:.1e}), expected {expected}; cache {c:?}, hit ratio {:.3}",
        c.hit_ratio()
    );
    assert!(
        sa > 0.0 && sa < 0.01 * expected,
        "se {sa} too large to test anything"
    );
    assert!(
        c.lookups > 1000 && c.hit_ratio() > 0.2,
        "the cache barely answered: {c:?}"
    );
    assert!(
        (ma - expected).abs() < 4.0 * sa,
        "uncached {ma} vs {expected}"
    );
    assert!(
        (mb - expected).abs() < 4.0 * sb.max(1e-12) + CACHE_BIAS * expected,
        "cached {mb} vs {expected}"
    );
    let se_diff = (sa * sa + sb * sb).sqrt();
    assert!(
        (ma - mb).abs() < 4.0 * se_diff + CACHE_BIAS * expected,
        "cached {mb} vs uncached {ma}"
    );
}

/// The farm's segment query (a continuation ray inside its locality sphere
/// only) on one machine's tracer: a ray that hits before its perimeter
/// gets the radiance the same ray gets as a path query, bit for bit, and
/// counts as local; one whose perimeter comes first gets `Beyond` and no
/// radiance at all.
#[test]
fn a_segment_query_answers_its_hit_inside_the_sphere_or_beyond() {
    use locus_core::geometry::Ray;
    use locus_core::integrator::PathRay;
    use locus_core::path::{Answer, Outcome, Query, Task, WholeScene};
    use locus_core::region::Resume;
    use locus_core::sampler::SampleKey;
    use locus_core::stats::TraceStats;
    let prep = Prepared::new(common::cornell());
    let kernel = prep.kernel(6, None);
    let tracer = WholeScene(&prep.accel);
    let mut chain = Vec::new();
    let mut hits = 0;
    for i in 0..64u32 {
        let cam = &prep.scene.camera;
        let (x, y) = (i % 8 * cam.width / 8, i / 8 * cam.height / 8);
        let ray: Ray = cam.ray(x, y, [0.5, 0.5]);
        let key = SampleKey::independent(i as u64, 3, 7);
        let far = PathRay {
            emit_within: 1e6,
            ..PathRay::camera(ray, key)
        };
        let run = |q: Query, st: &mut TraceStats, chain: &mut Vec<_>| {
            kernel.process(&tracer, Task::Query(q), Resume::START, chain, st)
        };
        let (mut a, mut b) = (TraceStats::default(), TraceStats::default());
        let seg = run(Query::Segment(far), &mut a, &mut chain);
        let path = run(Query::Path(far), &mut b, &mut chain);
        match (seg, path) {
            (Outcome::Answer(Answer::Radiance(s)), Outcome::Answer(Answer::Radiance(p))) => {
                assert_eq!(
                    s.to_array().map(f32::to_bits),
                    p.to_array().map(f32::to_bits)
                );
                assert_eq!(a.cache.local, 1);
                hits += 1;
            }
            (Outcome::Answer(Answer::Beyond), Outcome::Answer(Answer::Radiance(p))) => {
                assert_eq!(p, glam::Vec3::ZERO, "only an escaped ray gets beyond");
            }
            other => panic!("{other:?}"),
        }
        let near = PathRay {
            emit_within: 1e-4,
            ..far
        };
        let mut st = TraceStats::default();
        let out = run(Query::Segment(near), &mut st, &mut chain);
        assert!(matches!(out, Outcome::Answer(Answer::Beyond)), "{out:?}");
        assert_eq!(st.cache.local, 0);
    }
    assert!(hits > 32, "{hits} of 64 rays hit the box");
}
