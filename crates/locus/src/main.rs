//! `locus`: the command line of the locus render farm.
//!
//! Subcommands: `render` (single machine, or the embedded farm with
//! `--workers N`), `radiosity` (progressive refinement radiosity), the daemons `scheduler` and `worker`, `submit` (a job to a
//! running farm), `diff` (error metrics between two EXRs), `gen` (writes
//! generated scenes) and `bench` (tracing throughput; `bench farm` for the
//! farm). Logs go to stderr through `tracing`, filtered by `RUST_LOG`.
//!
//! [`cli`] holds the clap definitions, [`commands`] one module per family
//! of subcommands, and [`output`] the writer of images and reports that one
//! machine and the farm share.

mod cli;
mod commands;
mod output;

use anyhow::Result;
use clap::Parser;
use cli::{Cli, Cmd};
use commands::{bench::*, daemons::*, render::*, tools::*};

/// Refuses to run on a processor without the instruction-set extensions
/// this binary was built to use (`.cargo/config.toml` builds for
/// x86-64-v2), with a message rather than an illegal instruction later.
#[cfg(target_arch = "x86_64")]
#[inline(never)]
fn check_cpu() {
    use std::arch::is_x86_feature_detected as has;
    let missing: Vec<&str> = [
        ("popcnt", cfg!(target_feature = "popcnt") && !has!("popcnt")),
        ("sse4.2", cfg!(target_feature = "sse4.2") && !has!("sse4.2")),
        ("sse4.1", cfg!(target_feature = "sse4.1") && !has!("sse4.1")),
        ("ssse3", cfg!(target_feature = "ssse3") && !has!("ssse3")),
        (
            "cmpxchg16b",
            cfg!(target_feature = "cmpxchg16b") && !has!("cmpxchg16b"),
        ),
        ("avx", cfg!(target_feature = "avx") && !has!("avx")),
        ("avx2", cfg!(target_feature = "avx2") && !has!("avx2")),
        ("fma", cfg!(target_feature = "fma") && !has!("fma")),
        ("bmi2", cfg!(target_feature = "bmi2") && !has!("bmi2")),
    ]
    .into_iter()
    .filter_map(|(name, lacking)| lacking.then_some(name))
    .collect();
    if !missing.is_empty() {
        eprintln!(
            "error: this locus was built for processors with {} and this one lacks them; \
             build it with RUSTFLAGS=\"-C target-cpu=x86-64\" for any x86-64 processor",
            missing.join(", ")
        );
        std::process::exit(2);
    }
}

#[cfg(not(target_arch = "x86_64"))]
fn check_cpu() {}

fn main() {
    check_cpu();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let r = match cli.cmd {
        Cmd::Render(a) => cmd_render(a),
        Cmd::Radiosity(a) => commands::radiosity::cmd_radiosity(a),
        Cmd::Diff {
            image,
            reference,
            exact,
        } => cmd_diff(&image, &reference, exact),
        Cmd::Gen { what } => cmd_gen(what),
        Cmd::Bench(a) => cmd_bench(a),
        Cmd::Scheduler(a) => cmd_scheduler(a),
        Cmd::Worker(a) => cmd_worker(a),
        Cmd::Submit(a) => cmd_submit(a),
        Cmd::Attach(a) => cmd_attach(a),
        Cmd::Status { http, json } => cmd_status(&http, json),
        Cmd::BenchFarm(a) => cmd_bench_farm(a),
        Cmd::TlsInit { out_dir, force } => cmd_tls_init(&out_dir, force),
    };
    if let Err(e) = r {
        let msg = error_chain(&e);
        tracing::error!("{msg}");
        eprintln!("error: {msg}");
        std::process::exit(1);
    }
}

/// An error and its causes, each cause once: our error types already name
/// their source in their own message, and a cause repeated after it reads
/// like a second failure.
fn error_chain(e: &anyhow::Error) -> String {
    let mut msg = String::new();
    for cause in e.chain() {
        let s = cause.to_string();
        if !msg.contains(&s) {
            if !msg.is_empty() {
                msg.push_str(": ");
            }
            msg.push_str(&s);
        }
    }
    msg
}

pub(crate) fn runtime() -> Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?)
}
