//! The farm over real loopback sockets: scheduler and workers in this test
//! process, against the single-machine renderer bit for bit.

mod common;
use common::{bits, runtime, single_machine};
use locus_protocol::submit::{FetchPolicy, JobOptions, Partitioner};

fn small_cornell() -> locus_core::scene::Scene {
    common::small_cornell(40, 32, 7)
}

#[test]
fn farm_matches_single_machine_bit_for_bit() {
    let scene = small_cornell();
    let reference = single_machine(&scene);
    let rt = runtime();
    rt.block_on(async {
        for workers in [1usize, 2, 3, 4, 8] {
            let farm = locus::farm::LocalFarm::start(workers, 1).await.expect("farm");
            for partitioner in [Partitioner::RegionGrowing, Partitioner::Morton] {
                let opts = JobOptions {
                    workers: workers as u32,
                    partitioner,
                    tile_size: 8,
                    fetch: FetchPolicy::Forward,
                    ..Default::default()
                };
                let req = locus_scheduler::client::request(&scene, opts);
                let r = farm.render(req, &|_, _| {}).await.expect("job");
                let rep = &r.report;
                eprintln!(
                    "{workers} workers {partitioner:?}: forwarded/ray {:.3}, bytes/sample {:.0}, imbalance {:.2}",
                    rep.forwarded_fraction, rep.bytes_per_sample, rep.load_imbalance
                );
                assert_eq!(bits(&r), reference, "{workers} workers, {partitioner:?}");
                assert_eq!(rep.totals.trace.samples, (40 * 32 * 3) as u64);
                if workers > 1 {
                    assert!(rep.totals.forwarded_out > 0, "rays crossed regions");
                    let sent: u64 = rep.workers.iter().flat_map(|w| &w.stats.peers).map(|p| p.bytes_sent).sum();
                    let recv: u64 = rep.workers.iter().flat_map(|w| &w.stats.peers).map(|p| p.bytes_recv).sum();
                    assert_eq!(sent, recv, "every byte sent is received");
                }
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
            let e = handshake::dial(&addr, b"not-the-token", MAX_FRAME_LEN)
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
            let mut c = handshake::dial(&addr, farm.token.as_bytes(), MAX_FRAME_LEN)
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
