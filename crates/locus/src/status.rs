//! `locus status`: the farm's state, read from the scheduler's `/status`
//! (see `locus_scheduler::http`) and printed as a table, or as the JSON
//! itself.

use anyhow::{Context, Result};
use locus_scheduler::status::Status;
use std::fmt::Write as _;
use std::time::Duration;

/// The largest `/status` answer read: a farm of thousands of workers fits
/// many times over, and a wrong address cannot make the client read forever.
const MAX_STATUS_BYTES: u64 = 16 << 20;

/// Fetches `/status` from the scheduler's HTTP address (`host:port` or a
/// URL).
pub fn fetch(http: &str) -> Result<(String, Status)> {
    let base = if http.contains("://") {
        http.trim_end_matches('/').to_string()
    } else {
        format!("http://{http}")
    };
    let url = format!("{base}/status");
    let agent: ureq::Agent = ureq::Agent::config_builder()
        .timeout_global(Some(Duration::from_secs(10)))
        .build()
        .into();
    let body = agent
        .get(&url)
        .call()
        .with_context(|| format!("GET {url}"))?
        .into_body()
        .with_config()
        .limit(MAX_STATUS_BYTES)
        .read_to_string()
        .with_context(|| format!("reading {url}"))?;
    let status =
        serde_json::from_str(&body).with_context(|| format!("{url}: not a locus status"))?;
    Ok((body, status))
}

fn bytes(b: u64) -> String {
    match b {
        0 => "none".into(),
        b if b >= 1 << 30 => format!("{:.1} GiB", b as f64 / (1u64 << 30) as f64),
        b => format!("{:.0} MiB", b as f64 / (1u64 << 20) as f64),
    }
}

/// The state as a few lines of text.
pub fn format(s: &Status) -> String {
    let mut o = String::new();
    let busy = s.workers.iter().filter(|w| w.state == "busy").count();
    let _ = writeln!(
        o,
        "locus {} scheduler, up {:.0} s: {} workers ({busy} busy), {} jobs queued",
        s.version,
        s.uptime_s,
        s.workers.len(),
        s.queued.len()
    );
    let _ = writeln!(
        o,
        "{:>4}  {:<16} {:<24} {:>5} {:>9}  state",
        "id", "name", "peer address", "cores", "budget"
    );
    for w in &s.workers {
        let _ = writeln!(
            o,
            "{:>4}  {:<16} {:<24} {:>5} {:>9}  {}",
            w.id,
            w.name,
            w.listen,
            w.cores,
            bytes(w.memory_budget),
            w.state
        );
    }
    match &s.running {
        Some(j) => {
            let eta = j
                .eta_s
                .map_or(String::new(), |e| format!(", about {e:.0} s left"));
            let target = j
                .target_rel_mse
                .map_or(String::new(), |t| format!(" to relMSE {t:.2e}"));
            let _ = writeln!(
                o,
                "job {}: {} {}x{} {} spp{target} ({}), {}: pass {} of {}, {:.1}% of samples after {:.1} s{eta}",
                j.id,
                j.scene,
                j.width,
                j.height,
                j.spp,
                j.policy,
                j.phase,
                (j.pass + 1).min(j.passes),
                j.passes,
                100.0 * j.samples_done as f64 / j.samples.max(1) as f64,
                j.elapsed_s
            );
        }
        None => o.push_str("no job running\n"),
    }
    for q in &s.queued {
        let _ = writeln!(
            o,
            "queued: {} {}x{} {} spp",
            q.scene, q.width, q.height, q.spp
        );
    }
    for e in s.ended.iter().take(5) {
        let why = e
            .reason
            .as_deref()
            .map_or(String::new(), |r| format!(": {r}"));
        let target = e
            .target_rel_mse
            .map_or(String::new(), |t| format!(" to relMSE {t:.2e}"));
        let _ = writeln!(
            o,
            "ended: job {} {} {} spp{target} {} after {:.1} s{why}",
            e.id, e.scene, e.spp, e.outcome, e.seconds
        );
    }
    o
}
