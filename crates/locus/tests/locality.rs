//! Data locality in the farm: fetching remote geometry must not change a
//! bit, and the directional caches on workers must change nothing where
//! they cannot be used and stay unbiased where their answers are exact in
//! expectation.

mod common;
use common::{bits, runtime, single_machine};
use locus_core::dircache::CacheParams;
use locus_core::metrics::mean_and_standard_error;
use locus_core::scene::Scene;
use locus_protocol::submit::{FetchPolicy, JobOptions};

fn small_cornell() -> Scene {
    common::small_cornell(32, 24, 5)
}

/// Every policy, with a budget that holds the whole scene and one so small
/// that leaves are evicted all the time, gives the single machine's image
/// bit for bit: a fetched leaf finds exactly the hits its owner would.
#[test]
fn fetch_policies_keep_the_farm_bit_identical() {
    let scene = small_cornell();
    let want = single_machine(&scene);
    runtime().block_on(async {
        // With the embedded farm's one build for all its workers, and
        // without it, as worker daemons build.
        for (workers, shared_builds) in [(2usize, true), (4, true), (3, false)] {
            let spec = locus::farm::FarmSpec {
                shared_builds,
                ..locus::farm::FarmSpec::embedded(workers, 1)
            };
            let farm = locus::farm::LocalFarm::launch(&spec).await.expect("farm");
            for fetch in [FetchPolicy::Fetch, FetchPolicy::Hybrid, FetchPolicy::Adaptive] {
                for budget in [64u64 << 20, 8 << 10] {
                    let opts = JobOptions {
                        workers: workers as u32,
                        tile_size: 8,
                        fetch,
                        fetch_budget: budget,
                        ..Default::default()
                    };
                    let req = locus_scheduler::client::request(&scene, opts);
                    let r = farm.render(req, &|_, _| {}).await.expect("job");
                    let t = &r.report.totals;
                    eprintln!(
                        "{workers} workers, {fetch:?}, budget {budget}: fetched {} leaves ({} bytes), {} forwards, peak {} of {}",
                        t.fetched_leaves,
                        t.fetched_bytes,
                        t.forwarded_out,
                        t.fetch_cache_peak,
                        t.fetch_cache_bound
                    );
                    assert_eq!(bits(&r), want, "{workers} workers, {fetch:?}, budget {budget}");
                    // Room for everything: `fetch` ships the scene whole to
                    // every worker, and so does `adaptive` here (a few dozen
                    // triangles against thousands of rays); nothing is
                    // fetched later and no ray forwarded.
                    let whole = budget > 1 << 20 && fetch != FetchPolicy::Hybrid;
                    assert_eq!(r.report.replicated, whole, "{fetch:?}");
                    if whole {
                        assert_eq!(t.fetched_leaves, 0);
                        assert_eq!(t.forwarded_out, 0);
                        for w in &r.report.workers {
                            assert!(w.stats.triangles >= scene.tris.len() as u64);
                        }
                        // The embedded farm's workers share one build of
                        // the scene: all but the first take it (each may,
                        // if the job before left it held a moment longer).
                        // Workers that build alone take the scheduler's
                        // layout instead, every one of them.
                        let (shared, laid) = (t.shared_parts as usize, t.shipped_layouts as usize);
                        if shared_builds {
                            assert!(
                                (workers - 1..=workers).contains(&shared) && laid == 0,
                                "{fetch:?}: {shared} of {workers} workers took a shared build, {laid} a layout"
                            );
                        } else {
                            assert_eq!((shared, laid), (0, workers), "{fetch:?}: shared, layouts");
                        }
                    } else {
                        assert!(t.fetched_leaves > 0, "{fetch:?} fetched nothing");
                    }
                    assert_eq!(t.fetched_leaves, t.fetch_requests);
                    assert_eq!(t.fetched_leaves, t.leaves_served);
                    assert!(t.fetch_cache_peak <= budget);
                    if !whole && fetch != FetchPolicy::Fetch {
                        // Far, incoherent rays forward; rent-or-buy leaf by
                        // leaf forwards before it buys.
                        assert!(t.forwarded_out > 0, "{fetch:?} never forwarded");
                    }
                }
            }
            farm.stop().await.expect("clean stop");
        }
    });
}

/// A locality radius that holds the whole scene leaves the cache nothing
/// but escaped rays (zero radiance) to answer: on any number of workers
/// and under any policy the image is the single machine's cache-free
/// image, bit for bit.
#[test]
fn farm_cache_with_all_geometry_inside_the_radius_changes_no_bit() {
    let scene = small_cornell();
    let want = single_machine(&scene);
    runtime().block_on(async {
        let farm = locus::farm::LocalFarm::start(3, 1).await.expect("farm");
        for workers in [1usize, 3] {
            for fetch in [FetchPolicy::Forward, FetchPolicy::Fetch] {
                let opts = JobOptions {
                    workers: workers as u32,
                    tile_size: 8,
                    fetch,
                    cache: Some(CacheParams {
                        radius: 1e6,
                        ..CacheParams::default()
                    }),
                    ..Default::default()
                };
                let req = locus_scheduler::client::request(&scene, opts);
                let r = farm.render(req, &|_, _| {}).await.expect("job");
                let c = r.report.totals.trace.cache;
                assert!(c.local > 1000, "{c:?}");
                assert!(c.global + c.lookups > 0, "{c:?}");
                assert_eq!(bits(&r), want, "{workers} workers, {fetch:?}");
            }
        }
        farm.stop().await.expect("clean stop");
    });
}

/// The white furnace on four workers with small regions, so that cache
/// misses are traced across workers and their answers update the caches
/// when they come back: the mean stays within 4 standard errors (pixels are
/// independent estimates of it) plus a 2% bias budget of the analytic
/// value. The directional cache is not exact in expectation (see the core's
/// `cache_bias_in_a_uniform_environment_is_small`): measured here 1.3% low
/// with the Sobol sampler and Russian roulette from the fifth vertex,
/// more than on one machine, where answers update the caches sooner.
#[test]
fn farm_cache_bias_in_a_uniform_environment_is_small() {
    let (rho, le) = (0.5f32, 1.0f32);
    let mut scene = locus_core::generate::furnace(rho, le, 160, 8);
    scene.settings.octree.max_leaf_tris = 16;
    let expected = (le / (1.0 - rho)) as f64;
    runtime().block_on(async {
        let farm = locus::farm::LocalFarm::start(4, 1).await.expect("farm");
        let opts = JobOptions {
            workers: 4,
            tile_size: 8,
            fetch: FetchPolicy::Forward,
            // A miss updates its cache only when its answer is back: keep
            // the samples in flight a small part of this small image, as
            // they are of a real one.
            tuning: locus_protocol::control::Tuning {
                max_inflight: 128,
                ..Default::default()
            },
            cache: Some(CacheParams {
                radius: 0.9,
                split_samples: 8,
                fine_solid_angle: 4.0 * std::f64::consts::PI / 16.0,
                trust_samples: 16,
                split_rel_variance: 4.0,
                answer_samples: 16,
                answer_rel_error: 0.2,
                ..CacheParams::default()
            }),
            ..Default::default()
        };
        let req = locus_scheduler::client::request(&scene, opts);
        let r = farm.render(req, &|_, _| {}).await.expect("job");
        let t = &r.report.totals;
        let c = t.trace.cache;
        let (m, se) = mean_and_standard_error(&r.pixels, 1);
        eprintln!(
            "farm furnace: {m:.5} (se {se:.1e}) vs {expected}; cache {c:?}, hit ratio {:.3}, forwards {}, cache {} nodes",
            c.hit_ratio(),
            t.forwarded_out,
            t.cache_memory.nodes
        );
        assert!(se > 0.0 && se < 0.01 * expected, "se {se}");
        assert!(t.forwarded_out > 1000, "misses must cross workers");
        assert!(c.lookups > 1000 && c.hit_ratio() > 0.1, "{c:?}");
        // Rays that leave a small region inside the locality sphere go on
        // as segment queries, and each ends as exactly one of local,
        // global or lookup, wherever that is known.
        assert!(c.segments > 1000, "{c:?}");
        assert_eq!(
            c.local + c.global + c.lookups,
            t.trace.indirect_rays,
            "{c:?}"
        );
        assert!(t.cache_memory.nodes > 0);
        assert!(
            (m - expected).abs() < 4.0 * se + 0.02 * expected,
            "{m} vs {expected}"
        );
        farm.stop().await.expect("clean stop");
    });
}
