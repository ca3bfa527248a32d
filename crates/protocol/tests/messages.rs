//! Every message of every family survives a postcard round trip, and
//! arbitrary bytes never panic the decoder of any family.

use glam::Vec3;
use locus_core::accel::BuildQuality;
use locus_core::dircache::CacheParams;
use locus_core::geometry::Ray;
use locus_core::integrator::{PathRay, ShadowRay};
use locus_core::octree::{Octree, OctreeParams};
use locus_core::radiosity::RadiosityParams;
use locus_core::radiosity::mesh::Patch;
use locus_core::region::{ProcessorMap, Resume};
use locus_core::sampler::SampleKey;
use locus_core::scene::{Material, RenderSettings};
use locus_protocol::control::*;
use locus_protocol::radiosity::{Balance, NodeJob, RadiosityJob, ToCoordinator, ToNode};
use locus_protocol::rays::*;
use locus_protocol::report::{FarmReport, WorkerStats};
use locus_protocol::submit::*;
use locus_protocol::testing::{camera, job_setup};
use proptest::prelude::*;

fn roundtrip<T: serde::Serialize + serde::de::DeserializeOwned + PartialEq + std::fmt::Debug>(
    m: &T,
) {
    let b = postcard::to_stdvec(m).expect("encode");
    let back: T = postcard::from_bytes(&b).expect("decode");
    assert_eq!(&back, m);
}

fn v3() -> impl Strategy<Value = Vec3> {
    (-1e6f32..1e6, -1e6f32..1e6, -1e6f32..1e6).prop_map(|(x, y, z)| Vec3::new(x, y, z))
}

fn ray() -> impl Strategy<Value = Ray> {
    (v3(), v3()).prop_map(|(o, d)| Ray::new(o, d))
}

fn path_ray() -> impl Strategy<Value = PathRay> {
    (
        ray(),
        any::<u64>(),
        any::<u32>(),
        any::<u64>(),
        0u32..64,
        0f32..1e6,
        v3(),
    )
        .prop_map(|(ray, p, s, seed, depth, prev_pdf, beta)| PathRay {
            ray,
            key: SampleKey::independent(p, s, seed),
            depth,
            prev_pdf,
            beta,
            emit_within: prev_pdf * 3.0,
        })
}

fn ray_item() -> impl Strategy<Value = RayItem> {
    let reply = (any::<u16>(), any::<u32>()).prop_map(|(worker, slot)| ReplyTo { worker, slot });
    let query = prop_oneof![
        path_ray().prop_map(Query::Path),
        path_ray().prop_map(Query::Segment),
        (ray(), 0f32..1e30).prop_map(|(ray, t_max)| Query::Shadow(ShadowRay { ray, t_max })),
    ];
    let answer = prop_oneof![
        v3().prop_map(Answer::Radiance),
        any::<bool>().prop_map(Answer::Visible),
        Just(Answer::Beyond),
    ];
    prop_oneof![
        (query, -1e6f32..1e6, 0f32..1e3, any::<bool>(), reply).prop_map(
            |(query, at, span, spans, reply)| RayItem::Trace {
                query,
                resume: if spans {
                    Resume::within(at, at + span)
                } else {
                    Resume::at(at)
                },
                reply
            }
        ),
        (any::<u32>(), answer).prop_map(|(to, answer)| RayItem::Answer { to, answer }),
    ]
}

fn tris(n: usize, seed: u64) -> Vec<[Vec3; 3]> {
    (0..n as u64)
        .map(|i| {
            let k = SampleKey::independent(i, 0, seed);
            let p = Vec3::new(k.get1d(0), k.get1d(1), k.get1d(2)) * 10.0;
            [p, p + Vec3::X, p + Vec3::Y]
        })
        .collect()
}

fn setup(n: usize, seed: u64, workers: u16) -> JobSetup {
    let base = job_setup(&tris(n, seed), workers);
    JobSetup {
        job: seed,
        spp: 4,
        max_depth: 5,
        seed,
        cache: Some(CacheParams::default()),
        fetch: FetchPolicy::Hybrid,
        plan: MemoryPlan {
            budget: seed,
            cache_nodes: 1000,
            ..base.plan
        },
        region_triangles: n as u64,
        normals: seed.is_multiple_of(2),
        layout: seed.is_multiple_of(3),
        bvh_quality: if seed.is_multiple_of(5) {
            BuildQuality::Quick
        } else {
            BuildQuality::Full
        },
        ..base
    }
}

/// Shading normals for `n` triangles (unit length, arbitrary directions).
fn normals(n: usize, seed: u64) -> Vec<[Vec3; 3]> {
    (0..n as u64)
        .map(|i| {
            let k = SampleKey::independent(i, 1, seed);
            [0, 3, 6].map(|d| Vec3::new(k.get1d(d) - 0.5, k.get1d(d + 1) - 0.5, 1.0).normalize())
        })
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, .. ProptestConfig::default() })]

    #[test]
    fn peer_messages_roundtrip(items in proptest::collection::vec(ray_item(), 0..60), job in any::<u64>(), from in any::<u16>()) {
        let n = items.len();
        let packet = Packet::from_items(&items);
        roundtrip(&PeerMsg::Packet(packet.clone()));
        // Items come back as they went, the seed supplied by the receiver
        // (the generated keys carry arbitrary seeds; compare without them).
        let back: Vec<RayItem> = packet.items(0, locus_core::sampler::Sampler::Independent).collect::<Result<_, _>>().unwrap();
        let unseeded = |i: &RayItem| match *i {
            RayItem::Trace { query: Query::Path(mut q), resume, reply } => {
                q.key.seed = 0;
                RayItem::Trace { query: Query::Path(q), resume, reply }
            }
            RayItem::Trace { query: Query::Segment(mut q), resume, reply } => {
                q.key.seed = 0;
                RayItem::Trace { query: Query::Segment(q), resume, reply }
            }
            other => other,
        };
        prop_assert_eq!(back, items.iter().map(unseeded).collect::<Vec<_>>());
        roundtrip(&PeerMsg::Hello { job, from });
        roundtrip(&PeerMsg::Fetch(vec![job as u32, from as u32]));
        roundtrip(&PeerMsg::Poll);
        roundtrip(&PeerMsg::NoWork { idle: vec![from, from / 2] });
        let samples = (0..n as u32)
            .map(|i| HandedSample { x: i, y: job as u32, sample: from as u32, slot: i * 7 })
            .collect();
        roundtrip(&PeerMsg::Handed { queries: packet.clone(), samples });
        let verts: Vec<[Vec3; 3]> = tris(n, job);
        roundtrip(&PeerMsg::Leaf(Box::new(LeafGeometry {
            leaf: from as u32,
            geometry: TriangleSet {
                ids: (0..verts.len() as u32).collect(),
                material: vec![0; verts.len()],
                normals: if job.is_multiple_of(2) { normals(verts.len(), job) } else { Vec::new() },
                verts,
            },
        })));
    }

    #[test]
    fn control_messages_roundtrip(n in 1usize..40, seed in any::<u64>(), workers in 1u16..6, count in any::<u32>(), reason in ".{0,40}") {
        let s = setup(n, seed, workers);
        let t = tris(n, seed);
        let chunk = TriangleSet { ids: (0..n as u32).collect(), verts: t, material: vec![0; n], normals: normals(n, seed) };
        let tile = TileAssignment { job: seed, tile: count, pass: workers as u32 % 8, samples: PassSamples::Even([count / 2, count]), x0: 0, y0: 0, x1: 4, y1: 3, queue_share: u64::from(count) * 3 };
        let layout = locus_core::accel::Layout::build(&chunk, 10.0, locus_core::accel::BuildQuality::Full);
        for m in [
            SchedulerToWorker::Welcome { worker: count, heartbeat_ms: count / 3 },
            SchedulerToWorker::StartJob(Box::new(s)),
            SchedulerToWorker::Geometry { job: seed, leaves: vec![1, 2, count], chunk: std::sync::Arc::new(chunk), last: count % 2 == 0 },
            SchedulerToWorker::Layout { job: seed, layout: Some(std::sync::Arc::new(layout)) },
            SchedulerToWorker::Layout { job: seed, layout: None },
            SchedulerToWorker::Tile(tile),
            SchedulerToWorker::NoMoreTiles { job: seed },
            SchedulerToWorker::EndJob { job: seed },
            SchedulerToWorker::AbortJob { job: seed, reason: reason.clone() },
            SchedulerToWorker::Heartbeat,
        ] {
            roundtrip(&m);
        }
        let stats = WorkerStats { busy_s: n as f64, tiles: count, peers: vec![Default::default(); workers as usize], ..Default::default() };
        for m in [
            WorkerToScheduler::Ready { job: seed },
            WorkerToScheduler::NeedTiles { job: seed, count },
            WorkerToScheduler::TileDone(TileResult { job: seed, tile: count, pass: workers as u32, sums: vec![locus_core::passes::Moments { sum: [n as f64, 0.5, -1e300], squares: [1e300, 0.25, n as f64] }; 12] }),
            WorkerToScheduler::Report { job: seed, stats: Box::new(stats) },
            WorkerToScheduler::Failed { job: seed, reason: reason.clone() },
            WorkerToScheduler::Heartbeat,
        ] {
            roundtrip(&m);
        }
        roundtrip(&Opening::Register(Registration { listen: reason.clone(), cores: count, memory_budget: seed, resident: seed / 3, name: reason.clone(), layouts: count % 2 == 0 }));
    }

    #[test]
    fn submit_messages_roundtrip(n in 0usize..40, seed in any::<u64>(), workers in any::<u32>(), reason in ".{0,40}") {
        let t = tris(n, seed);
        let req = JobRequest {
            name: reason.clone(),
            camera: camera(),
            settings: RenderSettings { seed, ..Default::default() },
            materials: vec![Material { name: reason.clone(), albedo: Vec3::splat(0.3), emission: Vec3::ZERO }],
            tri_material: vec![0; n],
            tri_normals: normals(n, seed),
            tris: t,
            options: JobOptions { workers, partitioner: Partitioner::Morton, cost_model: CostModel::Analytic, ..Default::default() },
            load_s: 0.25,
            kind: if seed % 2 == 0 {
                JobKind::Render
            } else {
                JobKind::Radiosity(Box::new(RadiosityJob { params: RadiosityParams { mesh: workers, ..Default::default() }, ring: workers / 7, balance: Balance::ALL[n % 4], spp: workers / 3 }))
            },
        };
        let req_again = req.clone();
        roundtrip(&Opening::Submit(Box::new(req)));
        roundtrip(&Opening::Attach { job: seed });
        roundtrip(&Opening::SubmitInParts { request: Box::new(JobRequest { tris: Vec::new(), tri_material: Vec::new(), tri_normals: Vec::new(), ..req_again.clone() }), triangles: seed, normals: true });
        roundtrip(&locus_protocol::submit::TrianglePart { tris: req_again.tris.clone(), material: req_again.tri_material.clone(), normals: req_again.tri_normals.clone() });
        let report = FarmReport { scene: reason.clone(), seed, load_imbalance: n as f64, ..Default::default() };
        for m in [
            SchedulerToClient::Accepted { job: seed, workers },
            SchedulerToClient::Progress { job: seed, samples_done: seed / 2, samples: seed, pass: workers / 3, passes: workers },
            SchedulerToClient::Done(Box::new(JobResult { job: seed, width: 2, height: 1, pixels: vec![[1.0, 2.0, 3.0]; 2], report, sample_counts: None, radiosity: None })),
            SchedulerToClient::Counts { job: seed, offset: seed, counts: vec![workers; workers as usize % 5] },
            SchedulerToClient::Mesh { job: seed, offset: seed / 5, tris: vec![[(Vec3::X, Vec3::splat(n as f32)); 3]; n % 7] },
            SchedulerToClient::Failed { job: seed, reason: reason.clone() },
            SchedulerToClient::Pixels { job: seed, offset: seed, pixels: vec![[f32::MIN_POSITIVE, -1e30, f32::INFINITY]; workers as usize % 5] },
            SchedulerToClient::Queued { job: seed, ahead: workers },
        ] {
            roundtrip(&m);
        }
    }

    #[test]
    fn radiosity_messages_roundtrip(n in 0usize..20, seed in any::<u64>(), initial in 0u32..3) {
        let t = tris(n.max(1), seed);
        let patch = Patch::new(t[0], Vec3::splat(0.5), Vec3::ONE, initial, initial + 2);
        let setup = NodeJob {
            job: seed,
            me: (n % 3) as u32,
            peers: vec!["127.0.0.1:1".into(); 3],
            ring: 3,
            map: ProcessorMap::new(&Octree::build(&t, OctreeParams::default()), vec![0; Octree::build(&t, OctreeParams::default()).leaves.len()]),
            region: TriangleSet { ids: (0..t.len() as u32).collect(), material: vec![0; t.len()], verts: t.clone(), normals: Vec::new() },
            magnitude: 4.0,
            patches: vec![(n as u32, patch.clone())],
            part_levels: 2,
            dynamic: seed % 2 == 0,
            seed,
            stall_ms: 1000,
        };
        roundtrip(&SchedulerToWorker::StartNode(Box::new(setup)));
        roundtrip(&SchedulerToWorker::Node { job: seed, msg: Box::new(ToNode::Finish) });
        let end = ToCoordinator::End { node: n as u32, patches: vec![(3, patch)], snapshots: vec![vec![(3, [0.5, 1.0])]], last: true };
        roundtrip(&WorkerToScheduler::Node { job: seed, msg: Box::new(end) });
        roundtrip(&PeerMsg::Node(Box::new(ToNode::Idle { iteration: seed, from: 2, idle: vec![1, 2] })));
    }

    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
        let _ = postcard::from_bytes::<PeerMsg>(&bytes);
        let _ = postcard::from_bytes::<Opening>(&bytes);
        let _ = postcard::from_bytes::<SchedulerToWorker>(&bytes);
        let _ = postcard::from_bytes::<WorkerToScheduler>(&bytes);
        let _ = postcard::from_bytes::<SchedulerToClient>(&bytes);
        // The same bytes as a packet's contents: decoded item by item, an
        // error at worst.
        let wire = postcard::to_stdvec(&bytes).unwrap();
        let p: Packet = postcard::from_bytes(&wire).unwrap();
        prop_assert!(p.items(1, locus_core::sampler::Sampler::Independent).count() <= bytes.len());
    }
}

#[test]
fn tile_problems_are_named() {
    let t = TileAssignment {
        job: 1,
        tile: 7,
        pass: 0,
        samples: PassSamples::Even([0, 4]),
        x0: 0,
        y0: 0,
        x1: 4,
        y1: 3,
        queue_share: 0,
    };
    assert_eq!(t.problem(4, 3, 4), None);
    assert_eq!(t.total_samples(), 48);
    let bad = [
        TileAssignment { x1: 5, ..t.clone() },
        TileAssignment { y0: 3, ..t.clone() },
        TileAssignment { x0: 9, ..t.clone() },
        TileAssignment {
            samples: PassSamples::Even([4, 4]),
            ..t.clone()
        },
        TileAssignment {
            samples: PassSamples::Even([3, 5]),
            ..t.clone()
        },
    ];
    for b in bad {
        let p = b.problem(4, 3, 4).expect("refused");
        assert!(p.contains("tile 7"), "{p}");
        let _ = (b.pixels(), b.total_samples());
    }
    // A spread pass: each pixel its own range, up to MAX_SHARE times spp.
    let cap = 4 * locus_core::spread::MAX_SHARE;
    let spread = |first: Vec<u32>, count: Vec<u32>| TileAssignment {
        samples: PassSamples::Spread { first, count },
        ..t.clone()
    };
    let mut count = vec![0u32; 12];
    count[5] = cap - 4;
    count[11] = 3;
    let ok = spread(vec![4; 12], count.clone());
    assert_eq!(ok.problem(4, 3, 4), None);
    assert_eq!(ok.total_samples(), u64::from(cap - 1));
    assert_eq!(ok.pixel_samples(5), 4..cap);
    assert_eq!(ok.pixel_samples(0), 4..4);
    assert_eq!(ok.pixel_samples(99), 0..0);
    count[5] += 1;
    let p = spread(vec![4; 12], count)
        .problem(4, 3, 4)
        .expect("past the cap");
    assert!(p.contains("tile 7") && p.contains("pixel 5"), "{p}");
    let p = spread(vec![4; 11], vec![1; 12])
        .problem(4, 3, 4)
        .expect("short");
    assert!(
        p.contains("tile 7") && p.contains("11 first samples"),
        "{p}"
    );
    // A tile whose result would not fit one message, in an image it fits.
    let wide = TileAssignment {
        samples: PassSamples::Even([0, 1]),
        x1: 1400,
        y1: 1000,
        ..t
    };
    assert_eq!(
        TileAssignment {
            y1: 998,
            ..wide.clone()
        }
        .problem(1400, 1000, 1),
        None
    );
    let p = wide.problem(1400, 1000, 1).expect("refused");
    assert!(p.contains("tile 7") && p.contains("1400000 pixels"), "{p}");
}
