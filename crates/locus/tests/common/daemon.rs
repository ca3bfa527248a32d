//! Daemons for the tests that run a farm of processes: a `locus scheduler`
//! and `locus worker`s on loopback, sharing a token, each killed when
//! dropped.

use std::io::BufRead;
use std::process::{Child, Command, Stdio};

pub const TOKEN: &str = "recovery-test-token";

/// A daemon process, killed when dropped.
pub struct Daemon(pub Child);

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Daemon {
    pub fn spawn(args: &[&str]) -> (Self, String) {
        let mut c = Command::new(env!("CARGO_BIN_EXE_locus"))
            .args(args)
            .env("LOCUS_TOKEN", TOKEN)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::piped())
            .spawn()
            .expect("locus starts");
        let mut line = String::new();
        std::io::BufReader::new(c.stdout.take().expect("piped"))
            .read_line(&mut line)
            .expect("a daemon prints its address");
        let addr = line.trim().rsplit(' ').next().unwrap_or("").to_string();
        (Self(c), addr)
    }

    pub fn scheduler(worker_timeout_s: &str) -> (Self, String) {
        Self::spawn(&[
            "scheduler",
            "--listen",
            "127.0.0.1:0",
            "--worker-timeout",
            worker_timeout_s,
        ])
    }

    pub fn worker(scheduler: &str) -> Self {
        Self::spawn(&[
            "worker",
            "--scheduler",
            scheduler,
            "--listen",
            "127.0.0.1:0",
            "--threads",
            "1",
        ])
        .0
    }

    pub fn signal(&self, sig: &str) {
        let ok = Command::new("kill")
            .args([sig, &self.0.id().to_string()])
            .status()
            .expect("kill runs");
        assert!(ok.success(), "kill {sig}");
    }
}
