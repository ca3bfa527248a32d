//! The scheduler's HTTP face on a real farm: `/status` lists the workers and
//! the ended job with the traffic its workers counted, `/metrics` counts
//! what the job's report counts, the preview is the job's image, and the
//! server holds no more than its connection bound.

mod common;
use common::{bits, runtime, single_machine};
use locus::farm::{FarmSpec, LocalFarm};
use locus_protocol::submit::{FetchPolicy, JobOptions};
use locus_scheduler::http::MAX_CONNECTIONS;
use locus_scheduler::status::Status;
use std::net::SocketAddr;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// One HTTP/1.1 GET on a fresh connection: the status code and the body.
async fn get(addr: SocketAddr, path: &str) -> (u16, Vec<u8>) {
    let mut s = TcpStream::connect(addr).await.expect("connect");
    get_on(&mut s, path).await
}

async fn get_on(s: &mut TcpStream, path: &str) -> (u16, Vec<u8>) {
    let req = format!("GET {path} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n");
    s.write_all(req.as_bytes()).await.expect("write");
    let mut buf = Vec::new();
    tokio::time::timeout(Duration::from_secs(10), s.read_to_end(&mut buf))
        .await
        .expect("answered within 10 s")
        .expect("read");
    let end = buf
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a header");
    let head = String::from_utf8_lossy(&buf[..end]).to_string();
    let code = head[9..12].parse().expect("a status code");
    (code, buf[end + 4..].to_vec())
}

async fn status(addr: SocketAddr) -> Status {
    let (code, body) = get(addr, "/status").await;
    assert_eq!(code, 200);
    serde_json::from_slice(&body).expect("status JSON")
}

/// The value of the first exposition line that starts with `series `.
fn metric(text: &str, series: &str) -> u64 {
    text.lines()
        .find_map(|l| l.strip_prefix(series)?.strip_prefix(' '))
        .unwrap_or_else(|| panic!("no {series} in\n{text}"))
        .parse::<f64>()
        .expect("a number") as u64
}

#[test]
fn status_metrics_and_preview_report_the_job() {
    runtime().block_on(async {
        let spec = FarmSpec {
            http: Some("127.0.0.1:0".into()),
            ..FarmSpec::embedded(3, 1)
        };
        let farm = LocalFarm::launch(&spec).await.expect("farm");
        let http = farm.http.expect("status address");
        let page = get(http, "/").await;
        assert_eq!(page.0, 200);
        assert!(String::from_utf8_lossy(&page.1).contains("locus farm"));
        for _ in 0..100 {
            if status(http).await.workers.len() == 3 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let s = status(http).await;
        assert_eq!(s.workers.len(), 3, "{s:?}");
        assert!(s.running.is_none() && s.ended.is_empty());

        let scene = common::small_cornell(32, 24, 5);
        let opts = JobOptions {
            workers: 3,
            fetch: FetchPolicy::Forward,
            tile_size: 8,
            ..Default::default()
        };
        let r = farm
            .render(locus_scheduler::client::request(&scene, opts), &|_, _| {})
            .await
            .expect("job");
        assert_eq!(bits(&r), single_machine(&scene));

        let s = status(http).await;
        let e = &s.ended[0];
        assert_eq!((e.id, e.outcome.as_str()), (r.job, "done"));
        assert_eq!(e.workers.len(), 3);
        for (w, row) in e.traffic.iter().enumerate() {
            let sent: Vec<u64> = r.report.workers[w]
                .stats
                .peers
                .iter()
                .map(|p| p.bytes_sent)
                .collect();
            assert_eq!(*row, sent, "worker {w}'s traffic");
        }
        assert!(e.traffic.iter().flatten().sum::<u64>() > 0);
        // The error the job's report carries, as the report has it.
        let estimate = r.report.error_estimate.expect("3 samples a pixel").rel_mse;
        assert_eq!(e.rel_mse_estimate, Some(estimate));

        let (code, text) = get(http, "/metrics").await;
        assert_eq!(code, 200);
        let text = String::from_utf8(text).unwrap();
        // 12 tiles in the passes of 3 samples per pixel.
        let tiles = (32u64 / 8) * (24u64 / 8) * locus_core::passes::passes(3).len() as u64;
        assert_eq!(metric(&text, "locus_tile_passes_total"), tiles);
        assert_eq!(metric(&text, "locus_jobs_total{outcome=\"done\"}"), 1);
        let t = &r.report.totals;
        assert_eq!(
            metric(&text, "locus_rays_total{kind=\"camera\"}"),
            t.trace.camera_rays
        );
        assert_eq!(
            metric(&text, "locus_forwarded_queries_total"),
            t.forwarded_out
        );
        assert_eq!(metric(&text, "locus_workers{state=\"idle\"}"), 3);

        let (code, png) = get(http, &format!("/jobs/{}/preview.png", r.job)).await;
        assert_eq!(code, 200);
        assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
        let be = |o: usize| u32::from_be_bytes(png[o..o + 4].try_into().unwrap());
        assert_eq!((be(16), be(20)), (32, 24), "IHDR size");
        assert_eq!(get(http, "/jobs/999/preview.png").await.0, 404);
        farm.stop().await.expect("stop");
    });
}

/// With every connection slot held by an idle client, a new client waits;
/// it is answered once a slot frees.
#[test]
fn connections_beyond_the_bound_wait_for_a_slot() {
    runtime().block_on(async {
        let spec = FarmSpec {
            http: Some("127.0.0.1:0".into()),
            ..FarmSpec::embedded(1, 1)
        };
        let farm = LocalFarm::launch(&spec).await.expect("farm");
        let http = farm.http.expect("status address");
        let mut idle = Vec::new();
        for _ in 0..MAX_CONNECTIONS {
            idle.push(TcpStream::connect(http).await.expect("connect"));
        }
        // The kernel accepts into its backlog; the server reads nothing.
        let mut late = TcpStream::connect(http).await.expect("connect");
        let req = "GET /status HTTP/1.1\r\nHost: t\r\nConnection: close\r\n\r\n";
        late.write_all(req.as_bytes()).await.unwrap();
        let mut byte = [0u8; 1];
        let early = tokio::time::timeout(Duration::from_millis(500), late.read(&mut byte)).await;
        assert!(early.is_err(), "answered beyond the connection bound");
        drop(idle.pop());
        let mut rest = Vec::new();
        tokio::time::timeout(Duration::from_secs(10), late.read_to_end(&mut rest))
            .await
            .expect("answered once a slot freed")
            .unwrap();
        assert!(String::from_utf8_lossy(&rest).starts_with("HTTP/1.1 200"));
        drop(idle);
        farm.stop().await.expect("stop");
    });
}
