//! The farm over real loopback sockets: scheduler and workers in this test
//! process, against the single-machine renderer bit for bit.

mod common;
use common::{bits, runtime, single_machine};
use locus_protocol::submit::{FetchPolicy, JobOptions, Partitioner};

fn small_cornell() -> locus_core::scene::Scene {
    common::small_cornell(40, 32, 7)
}

/// A job for `workers` workers under `fetch`, in tiles of 8 pixels (many
/// tiles a worker on these small images).
fn options(workers: usize, fetch: FetchPolicy) -> JobOptions {
    JobOptions {
        workers: workers as u32,
        tile_size: 8,
        fetch,
        ..Default::default()
    }
}

#[test]
fn farm_matches_single_machine_bit_for_bit() {
    let scene = small_cornell();
    let one = common::single_machine_output(&scene);
    let reference = one.image.to_bits();
    // The error the image reports from its samples' spread, the same to
    // the bit: the farm's film adds each pass's squares in pass order too.
    let error = one.error_estimate;
    assert!(error.is_some_and(|e| e.rel_mse > 0.0), "{error:?}");
    let rt = runtime();
    rt.block_on(async {
        for workers in [1usize, 2, 3, 4, 8] {
            let farm = locus::farm::LocalFarm::start(workers, 1).await.expect("farm");
            for partitioner in [Partitioner::RegionGrowing, Partitioner::Morton] {
                let opts = JobOptions {
                    partitioner,
                    ..options(workers, FetchPolicy::Forward)
                };
                let req = locus_scheduler::client::request(&scene, opts);
                let r = farm.render(req, &|_, _| {}).await.expect("job");
                let rep = &r.report;
                eprintln!(
                    "{workers} workers {partitioner:?}: forwarded/ray {:.3}, bytes/sample {:.0}, imbalance {:.2}",
                    rep.forwarded_fraction, rep.bytes_per_sample, rep.load_imbalance
                );
                assert_eq!(bits(&r), reference, "{workers} workers, {partitioner:?}");
                assert_eq!(rep.error_estimate, error, "{workers} workers, {partitioner:?}");
                assert_eq!(rep.totals.trace.samples, (40 * 32 * 3) as u64);
                // A worker alone holds every leaf: its tiles go whole; a
                // worker of several, under `forward`, holds only its
                // region.
                let whole = if workers == 1 { rep.totals.tiles } else { 0 };
                assert_eq!(rep.totals.whole_tiles, whole, "{workers} workers");
                // How well the preview predicted each worker's share is a
                // correlation over the workers: shown from three on.
                let r = rep.prediction.sampled_r;
                assert_eq!(r.is_some(), workers >= 3, "{workers} workers: {r:?}");
                assert!(r.is_none_or(|r| (-1.0..=1.0).contains(&r)), "{r:?}");
                // Every forward is counted by its kind, worker by worker;
                // the preview predicts them wherever a partition placed
                // the work.
                for w in &rep.workers {
                    assert_eq!(w.stats.forwards.total(), w.stats.forwarded_out);
                }
                let predicted = rep.prediction.forwards_per_path;
                assert_eq!(predicted.is_some(), workers > 1, "{predicted:?}");
                if workers > 1 {
                    assert!(rep.totals.forwarded_out > 0, "rays crossed regions");
                    assert!(predicted.is_some_and(|p| p > 0.0), "{predicted:?}");
                    let sent: u64 = rep.workers.iter().flat_map(|w| &w.stats.peers).map(|p| p.bytes_sent).sum();
                    let recv: u64 = rep.workers.iter().flat_map(|w| &w.stats.peers).map(|p| p.bytes_recv).sum();
                    assert_eq!(sent, recv, "every byte sent is received");
                }
            }
            farm.stop().await.expect("clean stop");
        }
    });
}

/// A camera inside the scene: every camera ray starts in the camera's
/// leaf, which every worker holds, so tiles go to the owners of the leaves
/// the rays enter next and several workers start samples (with the leaf
/// owned by one worker, that one started them all); the image is one
/// machine's.
#[test]
fn a_camera_inside_the_scene_lets_every_worker_start_samples() {
    let mut scene = small_cornell();
    // Low over the floor, looking at the back wall.
    scene.camera.position = glam::Vec3::new(278.0, 6.0, 120.0);
    scene.camera.look_at = glam::Vec3::new(278.0, 273.0, 559.0);
    let reference = single_machine(&scene);
    let rt = runtime();
    rt.block_on(async {
        for workers in [3usize, 4] {
            let farm = locus::farm::LocalFarm::start(workers, 1)
                .await
                .expect("farm");
            let opts = options(workers, FetchPolicy::Forward);
            let req = locus_scheduler::client::request(&scene, opts);
            let r = farm.render(req, &|_, _| {}).await.expect("job");
            assert_eq!(bits(&r), reference, "{workers} workers");
            let starting = r
                .report
                .workers
                .iter()
                .filter(|w| w.stats.tiles > 0)
                .count();
            assert!(
                starting >= 2,
                "{workers} workers: {starting} started samples"
            );
            farm.stop().await.expect("clean stop");
        }
    });
}

/// Workers of several threads: with 2, the engine's thread traces beside a
/// pool of one; with `DEDICATED_ENGINE_THREADS`, the pool has them all and
/// the engine's thread only keeps the books. Both give one machine's bits,
/// whether rays are forwarded or leaves fetched.
#[test]
fn workers_of_several_threads_keep_the_bits() {
    use locus_worker::engine::DEDICATED_ENGINE_THREADS;
    let scene = small_cornell();
    let reference = single_machine(&scene);
    let rt = runtime();
    rt.block_on(async {
        for threads in [2, DEDICATED_ENGINE_THREADS] {
            let farm = locus::farm::LocalFarm::start(2, threads)
                .await
                .expect("farm");
            for fetch in [FetchPolicy::Forward, FetchPolicy::Fetch] {
                let opts = options(2, fetch);
                let req = locus_scheduler::client::request(&scene, opts);
                let r = farm.render(req, &|_, _| {}).await.expect("job");
                assert_eq!(bits(&r), reference, "{threads} threads a worker, {fetch:?}");
                let t = &r.report.totals;
                assert_eq!(t.trace.samples, (40 * 32 * 3) as u64);
                // The scene is shipped whole under `fetch`: every tile is
                // traced whole, by the engine's thread or by its pool.
                let whole = if fetch == FetchPolicy::Fetch {
                    t.tiles
                } else {
                    0
                };
                assert!(t.tiles > 0);
                assert_eq!(
                    t.whole_tiles, whole,
                    "{threads} threads a worker, {fetch:?}"
                );
            }
            farm.stop().await.expect("clean stop");
        }
    });
}

/// Hostile and mistaken clients are refused or dropped with their reason,
/// and a job running meanwhile still completes bit for bit.
#[test]
fn bad_clients_are_dropped_while_the_job_completes() {
    use locus_protocol::{Connection, MAX_FRAME_LEN, PROTOCOL_VERSION, ProtocolError, handshake};
    use tokio::io::AsyncWriteExt;
    let scene = small_cornell();
    let reference = single_machine(&scene);
    let rt = runtime();
    rt.block_on(async {
        let farm = locus::farm::LocalFarm::start(3, 1).await.expect("farm");
        let addr = farm.scheduler.to_string();
        let req = locus_scheduler::client::request(
            &scene,
            JobOptions {
                workers: 3,
                tile_size: 4,
                fetch: FetchPolicy::Forward,
                ..Default::default()
            },
        );
        let job = farm.render(req, &|_, _| {});
        let attacks = async {
            // Wrong token: refused, and told why.
            let e = handshake::dial(&addr, &"not-the-token".into(), MAX_FRAME_LEN)
                .await
                .err()
                .expect("wrong token refused");
            assert!(
                matches!(
                    e,
                    ProtocolError::WrongToken { .. } | ProtocolError::Refused { .. }
                ),
                "{e}"
            );
            assert!(e.to_string().contains("token"), "{e}");
            // Wrong version.
            let s = tokio::net::TcpStream::connect(&addr).await.unwrap();
            let mut c = Connection::new(s, MAX_FRAME_LEN).unwrap();
            let e = handshake::client(&mut c, farm.token.as_bytes(), PROTOCOL_VERSION + 7)
                .await
                .expect_err("wrong version refused");
            assert!(e.to_string().contains("version"), "{e}");
            // Garbage, an oversized length prefix, a truncated frame.
            for bytes in [
                b"GET / HTTP/1.1\r\n\r\n".to_vec(),
                vec![0xff, 0xff, 0xff, 0xff, 1, 2, 3],
                vec![0, 0, 0, 50, 1, 2, 3],
            ] {
                let mut s = tokio::net::TcpStream::connect(&addr).await.unwrap();
                s.write_all(&bytes).await.unwrap();
                drop(s);
            }
            // A client that passes the handshake, then sends garbage.
            let mut c = handshake::dial(&addr, &farm.credentials(), MAX_FRAME_LEN)
                .await
                .unwrap();
            c.write_msg(&vec![0xffu8; 40]).await.unwrap();
            let _ = c
                .read_msg::<locus_protocol::submit::SchedulerToClient>("x")
                .await;
        };
        let (r, ()) = tokio::join!(job, attacks);
        let r = r.expect("job completes despite bad clients");
        assert_eq!(bits(&r), reference);
        farm.stop().await.expect("clean stop");
    });
}

/// A job naming a material that does not exist is refused with its reason;
/// the farm stays up for the next job.
#[test]
fn invalid_job_is_refused_and_the_farm_stays_up() {
    let scene = small_cornell();
    let rt = runtime();
    rt.block_on(async {
        let farm = locus::farm::LocalFarm::start(2, 1).await.expect("farm");
        let mut bad = locus_scheduler::client::request(&scene, JobOptions::default());
        bad.tri_material[3] = 999;
        let e = farm.render(bad, &|_, _| {}).await.expect_err("refused");
        assert!(e.to_string().contains("material 999"), "{e}");
        let good = locus_scheduler::client::request(&scene, JobOptions::default());
        let r = farm.render(good, &|_, _| {}).await.expect("next job runs");
        assert_eq!(r.report.workers.len(), 2);
        farm.stop().await.expect("clean stop");
    });
}

/// An image of more pixels than one result message carries arrives whole,
/// in order and bit for bit.
#[test]
fn an_image_larger_than_a_result_chunk_arrives_whole() {
    use locus_protocol::submit::RESULT_CHUNK_PIXELS;
    let mut scene = common::small_cornell(1100, 1000, 3);
    scene.settings.spp = 1;
    const { assert!(1100 * 1000 > RESULT_CHUNK_PIXELS) };
    let want = single_machine(&scene);
    runtime().block_on(async {
        let farm = locus::farm::LocalFarm::start(2, 1).await.expect("farm");
        let opts = JobOptions {
            workers: 2,
            tile_size: 64,
            ..Default::default()
        };
        let req = locus_scheduler::client::request(&scene, opts);
        let r = farm.render(req, &|_, _| {}).await.expect("job");
        assert_eq!(r.pixels.len(), 1100 * 1000);
        assert!(bits(&r) == want, "the assembled image differs");
        farm.stop().await.expect("stop");
    });
}

/// A request sent in parts (here of 7 triangles, so the Cornell box's 32
/// take 5) renders the same bits as one machine; a part longer than
/// announced, with lists of different lengths, or with shading normals the
/// request did not announce, is refused with its reason, and the farm goes
/// on.
#[test]
fn a_request_in_parts_matches_and_bad_parts_are_refused() {
    use locus_protocol::control::Opening;
    use locus_protocol::submit::{SchedulerToClient, TrianglePart};
    use locus_protocol::{MAX_FRAME_LEN, handshake};
    let scene = small_cornell();
    let reference = single_machine(&scene);
    let rt = runtime();
    rt.block_on(async {
        let farm = locus::farm::LocalFarm::start(2, 1).await.expect("farm");
        let addr = farm.scheduler.to_string();
        let req = locus_scheduler::client::request(&scene, JobOptions::default());
        assert!(req.tris.len() > 4 * 7, "several parts");
        let r = locus_scheduler::client::submit_in_parts_of(&addr, &farm.token, req, &|_, _| {}, 7)
            .await
            .expect("a request in parts renders");
        assert_eq!(bits(&r), reference);
        let bad_parts = [
            TrianglePart {
                tris: vec![scene.tris[0]; 11],
                material: vec![0; 11],
                normals: Vec::new(),
            },
            TrianglePart {
                tris: vec![scene.tris[0]; 3],
                material: vec![0; 2],
                normals: Vec::new(),
            },
            TrianglePart {
                tris: vec![scene.tris[0]; 3],
                material: vec![0; 3],
                normals: vec![[glam::Vec3::Z; 3]; 3],
            },
        ];
        for part in bad_parts {
            let mut c = handshake::dial(&addr, &farm.credentials(), MAX_FRAME_LEN)
                .await
                .unwrap();
            let mut req = locus_scheduler::client::request(&scene, JobOptions::default());
            req.tris.clear();
            req.tri_material.clear();
            c.write_msg(&Opening::SubmitInParts {
                request: Box::new(req),
                triangles: 10,
                normals: false,
            })
            .await
            .unwrap();
            c.write_msg(&part).await.unwrap();
            match c.read_msg::<SchedulerToClient>("submit").await.unwrap() {
                Some(SchedulerToClient::Failed { reason, .. }) => {
                    assert!(reason.contains("request part"), "{reason}")
                }
                other => panic!("expected a refusal, got {other:?}"),
            }
        }
        let again = locus_scheduler::client::request(&scene, JobOptions::default());
        let r = locus_scheduler::client::submit(&addr, &farm.token, again, &|_, _| {})
            .await
            .expect("the farm goes on");
        assert_eq!(bits(&r), reference);
        farm.stop().await.expect("clean stop");
    });
}

/// Shading normals travel with their triangles: in the request (whole and
/// in parts), in each worker's region, and in fetched leaves. A Cornell box
/// whose triangles carry normals tilted a little from their faces renders
/// on the farm bit for bit as on one machine, under every fetch policy,
/// and differs from the box without them (so they were not dropped).
#[test]
fn shading_normals_travel_with_their_triangles() {
    use glam::Vec3;
    let flat = small_cornell();
    let mut scene = flat.clone();
    scene.tri_normals = scene
        .tris
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let n = locus_core::geometry::tri_cross(t).normalize();
            let tilt = |k: usize| {
                let a = Vec3::new(1.0 + k as f32, (i % 5) as f32, 2.0 - k as f32).normalize();
                (n + a.cross(n) * 0.2).normalize()
            };
            [tilt(0), tilt(1), tilt(2)]
        })
        .collect();
    let reference = single_machine(&scene);
    assert_ne!(
        reference,
        single_machine(&flat),
        "the normals change the image"
    );
    let rt = runtime();
    rt.block_on(async {
        let farm = locus::farm::LocalFarm::start(3, 1).await.expect("farm");
        for fetch in [
            FetchPolicy::Forward,
            FetchPolicy::Fetch,
            FetchPolicy::Hybrid,
            FetchPolicy::Adaptive,
        ] {
            let opts = JobOptions {
                // Too small to hold the scene: leaves are fetched one by
                // one, normals and all.
                fetch_budget: 4 << 10,
                ..options(3, fetch)
            };
            let req = locus_scheduler::client::request(&scene, opts);
            let r = farm.render(req, &|_, _| {}).await.expect("job");
            assert_eq!(bits(&r), reference, "{fetch:?}");
            if fetch == FetchPolicy::Fetch {
                assert!(r.report.totals.fetched_leaves > 0, "leaves were fetched");
            }
        }
        let addr = farm.scheduler.to_string();
        let req = locus_scheduler::client::request(&scene, JobOptions::default());
        let r = locus_scheduler::client::submit_in_parts_of(&addr, &farm.token, req, &|_, _| {}, 7)
            .await
            .expect("a request with normals in parts renders");
        assert_eq!(bits(&r), reference, "in parts");
        farm.stop().await.expect("clean stop");
    });
}

/// Random polling for hot regions: idle workers poll, loaded ones hand
/// queued queries and camera samples over, the pollers fetch the handers'
/// leaves to trace them, and the image keeps one machine's bits. Every
/// handed item arrives. Whether a poll finds a queue long enough to share
/// depends on timing, so the job runs until one has (at most 4 times); a
/// farm that never hands anything over fails.
#[test]
fn random_polling_hands_work_over_and_keeps_the_bits() {
    let mut scene = common::small_cornell(96, 64, 11);
    scene.settings.spp = 8;
    let reference = single_machine(&scene);
    let rt = runtime();
    rt.block_on(async {
        let farm = locus::farm::LocalFarm::start(2, 1).await.expect("farm");
        let mut handed = 0;
        for run in 0..4 {
            let mut opts = JobOptions {
                workers: 2,
                // Two tiles a worker: thousands of samples queued at once.
                tile_size: 32,
                fetch: FetchPolicy::Forward,
                ..Default::default()
            };
            opts.tuning.random_polling = true;
            let req = locus_scheduler::client::request(&scene, opts);
            let r = farm.render(req, &|_, _| {}).await.expect("job");
            assert_eq!(bits(&r), reference, "run {run}");
            let t = &r.report.totals;
            eprintln!(
                "run {run}: polls {}, answered {}, handed {}, fetched leaves {}",
                t.polls, t.polls_answered, t.handed_out, t.fetched_leaves
            );
            assert_eq!(t.handed_out, t.handed_in, "every handed item arrives");
            assert!(t.polls_answered <= t.polls);
            handed += t.handed_out;
            if handed > 0 {
                assert!(t.fetched_leaves > 0, "pollers fetch the handers' leaves");
                break;
            }
        }
        assert!(handed > 0, "no poll found work to share in 4 runs");
        farm.stop().await.expect("clean stop");
    });
}

/// With Ward's irradiance cache every worker interpolates the same records,
/// so the farm still gives one machine's bits: measured on the scheduler
/// when the workers hold regions (`forward`), and by the workers between
/// them, level by level, when each holds the whole scene (`fetch`). The
/// report counts the records, who measured them, the bytes both ways and
/// every first vertex the cache answered.
#[test]
fn the_irradiance_cache_keeps_the_bits_on_the_farm() {
    use locus_core::irradiance::IrradianceParams;
    use locus_core::render::{Prepared, RenderOptions, render};
    let scene = small_cornell();
    let params = IrradianceParams {
        divisions: 64,
        spacing: 4,
        ..Default::default()
    };
    let prep = Prepared::new(scene.clone());
    let mut o = RenderOptions::from_scene(&scene);
    o.threads = 2;
    o.irradiance = Some(params);
    let one = render(&prep, &o, &|_, _| {});
    let records = one.irradiance.expect("overture").records;
    assert!(records > 10, "{records} records");
    // The cache changes the image: the comparison can fail.
    assert_ne!(one.image.to_bits(), single_machine(&scene));
    let rt = runtime();
    rt.block_on(async {
        let workers = 3;
        let farm = locus::farm::LocalFarm::start(workers, 1)
            .await
            .expect("farm");
        for fetch in [FetchPolicy::Forward, FetchPolicy::Fetch] {
            let opts = JobOptions {
                irradiance: Some(params),
                ..options(workers, fetch)
            };
            let req = locus_scheduler::client::request(&scene, opts);
            let r = farm.render(req, &|_, _| {}).await.expect("job");
            assert_eq!(bits(&r), one.image.to_bits(), "{fetch:?}");
            let rep = &r.report;
            let ir = rep.irradiance.expect("irradiance report");
            assert_eq!(ir.records, records);
            let per_record = locus_core::irradiance::overture::Measured::WIRE_BYTES;
            assert!(
                ir.bytes_sent >= workers as u64 * records * per_record,
                "{ir:?}"
            );
            let by_workers = fetch == FetchPolicy::Fetch;
            assert_eq!(ir.by_workers, by_workers, "{fetch:?}");
            // What the workers measured came up once.
            assert_eq!(
                ir.bytes_gathered >= records * per_record,
                by_workers,
                "{ir:?}"
            );
            assert!(ir.rays > records * params.divisions as u64 / 2, "{ir:?}");
            assert_eq!(
                rep.totals.trace.irradiance, one.stats.irradiance,
                "{fetch:?}"
            );
        }
        farm.stop().await.expect("clean stop");
    });
}

/// A noise target on the farm: the scheduler hands out a pass only once
/// the one before is in, judges the film at each pass end as one machine
/// judges its image, and stops at the same pass with the same image, to the
/// bit, under every policy.
#[test]
fn a_noise_target_stops_the_farm_where_it_stops_one_machine() {
    let mut scene = common::small_cornell(40, 32, 5);
    // Between the estimates after 4 and 8 samples (the passes of 16
    // samples end at 1, 2, 4, 8 and 16): met after 8.
    let estimate = |spp| {
        let mut s = scene.clone();
        s.settings.spp = spp;
        let o = common::single_machine_output(&s);
        o.error_estimate.expect("two samples or more").rel_mse
    };
    let (at_4, at_8) = (estimate(4), estimate(8));
    assert!(at_8 < at_4);
    scene.settings.spp = 16;
    scene.settings.target_rel_mse = Some((at_4 * at_8).sqrt());
    let one = common::single_machine_output(&scene);
    assert_eq!(one.spp, 8, "stopped after the fourth pass");
    let reference = one.image.to_bits();
    let rt = runtime();
    rt.block_on(async {
        for (workers, fetch) in [
            (2usize, FetchPolicy::Forward),
            (3, FetchPolicy::Forward),
            (3, FetchPolicy::Adaptive),
        ] {
            let farm = locus::farm::LocalFarm::start(workers, 1)
                .await
                .expect("farm");
            let opts = options(workers, fetch);
            let req = locus_scheduler::client::request(&scene, opts);
            let r = farm.render(req, &|_, _| {}).await.expect("job");
            let rep = &r.report;
            let what = format!("{workers} workers, {fetch:?}");
            assert_eq!(bits(&r), reference, "{what}");
            assert_eq!(rep.spp_rendered, one.spp, "{what}");
            assert_eq!(rep.spp, 16, "{what}");
            assert_eq!(rep.error_estimate, one.error_estimate, "{what}");
            assert_eq!(rep.target_rel_mse, scene.settings.target_rel_mse);
            // Only the passes kept were rendered.
            assert_eq!(
                rep.totals.trace.samples,
                (40 * 32 * one.spp) as u64,
                "{what}"
            );
            farm.stop().await.expect("clean stop");
        }
    });
}

/// Adaptive sampling on the farm: the scheduler's film spreads each pass
/// after the pilot by the same sums one machine spreads it by, so the
/// farm renders the same counts and the same image to the bit, under every
/// policy, tracing exactly the even render's samples.
#[test]
fn adaptive_sampling_on_the_farm_keeps_one_machines_bits() {
    let mut scene = common::small_cornell(40, 32, 9);
    // Passes of 32 samples end at 1, 2, 4, 8, 16 and 32: a pilot of 8,
    // then two spread passes.
    scene.settings.spp = 32;
    scene.settings.adaptive_sampling = true;
    let one = common::single_machine_output(&scene);
    let counts = one.sample_counts.clone().expect("counted");
    let spread = locus_core::report::SampleCounts::of(&counts);
    assert!(
        spread.is_some_and(|c| c.min < c.max && c.max > 32),
        "spread unevenly: {spread:?}"
    );
    let reference = one.image.to_bits();
    let rt = runtime();
    rt.block_on(async {
        for (workers, fetch) in [
            (2usize, FetchPolicy::Forward),
            (3, FetchPolicy::Adaptive),
            (2, FetchPolicy::Fetch),
        ] {
            let farm = locus::farm::LocalFarm::start(workers, 1)
                .await
                .expect("farm");
            let req = locus_scheduler::client::request(&scene, options(workers, fetch));
            let r = farm.render(req, &|_, _| {}).await.expect("job");
            let rep = &r.report;
            let what = format!("{workers} workers, {fetch:?}");
            assert_eq!(bits(&r), reference, "{what}");
            assert_eq!(rep.sample_counts, spread, "{what}");
            assert_eq!(rep.spp_rendered, 32, "{what}");
            assert_eq!(rep.error_estimate, one.error_estimate, "{what}");
            assert_eq!(rep.totals.trace.samples, 40 * 32 * 32, "{what}");
            farm.stop().await.expect("clean stop");
        }
    });

    // With a noise target too: the film judges after each pass, the
    // spread ones included, and stops where one machine stops.
    let full = one.error_estimate.expect("estimated").rel_mse;
    scene.settings.target_rel_mse = Some(full * 2.5);
    let one = common::single_machine_output(&scene);
    assert_eq!(one.spp, 16, "met after the first spread pass");
    rt.block_on(async {
        let farm = locus::farm::LocalFarm::start(2, 1).await.expect("farm");
        let req = locus_scheduler::client::request(&scene, options(2, FetchPolicy::Forward));
        let r = farm.render(req, &|_, _| {}).await.expect("job");
        assert_eq!(bits(&r), one.image.to_bits());
        assert_eq!(r.report.spp_rendered, 16);
        let counts = one.sample_counts.as_deref().expect("counted");
        let spread = locus_core::report::SampleCounts::of(counts);
        assert_eq!(r.report.sample_counts, spread);
        assert_eq!(r.report.totals.trace.samples, 40 * 32 * 16);
        farm.stop().await.expect("clean stop");
    });
}
