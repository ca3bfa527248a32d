//! TLS on every link: a farm of worker processes started with the TLS
//! flags renders bit-identical to one machine, with a client over TLS;
//! a client without TLS, or trusting another authority, is refused
//! promptly, and the second with a fatal error (no retrying).

mod common;
use common::{bits, runtime, single_machine};
use locus::farm::{FarmSpec, LocalFarm};
use locus_protocol::handshake::{self, Credentials};
use locus_protocol::submit::{FetchPolicy, JobOptions};
use locus_protocol::tls::{Tls, TlsFiles};
use locus_protocol::{MAX_FRAME_LEN, ProtocolError};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// A certificate and key for the farm (`locus tls-init` writes the same),
/// in `dir`.
fn farm_files(dir: &Path) -> TlsFiles {
    std::fs::create_dir_all(dir).unwrap();
    let (cert, key) = locus_protocol::tls::generate().unwrap();
    let (c, k) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&c, cert).unwrap();
    std::fs::write(&k, key).unwrap();
    TlsFiles {
        cert: Some(c),
        key: Some(k),
        ..Default::default()
    }
}

fn temp(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("locus-tls-{name}-{}", std::process::id()))
}

#[test]
fn a_tls_farm_renders_bit_identical_and_refuses_plain_clients() {
    let dir = temp("farm");
    let files = farm_files(&dir);
    let scene = common::small_cornell(40, 32, 3);
    let reference = single_machine(&scene);
    let rt = runtime();
    rt.block_on(async {
        // Worker processes get the TLS flags; the scheduler is in here.
        let spec = FarmSpec {
            processes: Some(PathBuf::from(env!("CARGO_BIN_EXE_locus"))),
            tls: Some(files.clone()),
            ..FarmSpec::embedded(2, 1)
        };
        let farm = LocalFarm::launch(&spec).await.expect("farm");
        let addr = farm.scheduler.to_string();
        let opts = JobOptions {
            workers: 2,
            fetch: FetchPolicy::Forward,
            tile_size: 8,
            ..Default::default()
        };
        let req = locus_scheduler::client::request(&scene, opts.clone());
        let r = locus_scheduler::client::submit(&addr, farm.credentials(), req, &|_, _| {})
            .await
            .expect("a job over TLS");
        assert_eq!(bits(&r), reference);
        assert!(
            r.report.totals.forwarded_out > 0,
            "rays crossed between the workers, over TLS"
        );

        // A client that does not speak TLS gets nowhere, at once.
        let req = locus_scheduler::client::request(&scene, opts.clone());
        let plain = tokio::time::timeout(
            Duration::from_secs(20),
            locus_scheduler::client::submit(&addr, &farm.token, req, &|_, _| {}),
        )
        .await
        .expect("a plain client is answered within 20 s");
        assert!(plain.is_err(), "a plain client was served");

        // A client trusting another authority refuses the scheduler, and
        // knows retrying cannot help.
        let other = farm_files(&temp("other"));
        let wrong = Credentials::new(
            &farm.token,
            Tls::load(
                &TlsFiles {
                    ca: other.cert.clone(),
                    ..Default::default()
                },
                false,
            )
            .unwrap(),
        );
        let e = handshake::dial(&addr, &wrong, MAX_FRAME_LEN)
            .await
            .err()
            .expect("a certificate of another authority is refused");
        assert!(e.is_refusal(), "{e}");
        assert!(matches!(e, ProtocolError::Tls { .. }), "{e}");
        assert!(e.to_string().contains("certificate"), "{e}");
        farm.stop().await.expect("stop");
    });
    let _ = std::fs::remove_dir_all(&dir);
    let _ = std::fs::remove_dir_all(temp("other"));
}

#[test]
fn tls_settings_that_cannot_work_are_named() {
    let dir = temp("bad");
    let files = farm_files(&dir);
    // A node that accepts needs its key.
    let no_key = TlsFiles {
        key: None,
        ..files.clone()
    };
    let e = Tls::load(&no_key, true).unwrap_err().to_string();
    assert!(e.contains("key is not given"), "{e}");
    // A client needs only the authority.
    let client = TlsFiles {
        ca: files.cert.clone(),
        ..Default::default()
    };
    assert!(Tls::load(&client, false).unwrap().is_some());
    // Files that are not PEM, or missing, name the file.
    let junk = dir.join("junk.pem");
    std::fs::write(&junk, "not a certificate").unwrap();
    for (f, what) in [
        (
            TlsFiles {
                cert: Some(junk.clone()),
                ..files.clone()
            },
            "junk.pem",
        ),
        (
            TlsFiles {
                key: Some(junk.clone()),
                ..files.clone()
            },
            "junk.pem",
        ),
        (
            TlsFiles {
                ca: Some(dir.join("missing.pem")),
                ..files.clone()
            },
            "missing.pem",
        ),
    ] {
        let e = Tls::load(&f, true).unwrap_err().to_string();
        assert!(e.contains(what), "{e}");
    }
    // No settings: plain TCP.
    assert!(Tls::load(&TlsFiles::default(), true).unwrap().is_none());
    let _ = std::fs::remove_dir_all(&dir);
}
