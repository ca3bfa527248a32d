//! The scheduler's Prometheus metrics (`/metrics`), kept by the actor as
//! events happen and encoded by `prometheus-client`. Everything is counted:
//! tiles as they arrive, workers as they join and leave, and rays, forwards,
//! bytes, fetches and cache hits from the workers' reports when a job ends
//! (a worker counts them where the work happened).
//!
//! Series labelled by worker are bounded: a worker's are removed once more
//! than [`DEPARTED_KEPT`] workers have left since it did, so a farm whose
//! workers come and go for months does not grow its metrics without end.

use locus_protocol::report::FarmReport;
use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;
use std::collections::VecDeque;
use std::sync::Mutex;

/// Departed workers whose series stay (at 0 for `locus_worker_up`).
pub const DEPARTED_KEPT: usize = 64;

type Labels = Vec<(String, String)>;

pub struct Metrics {
    registry: Registry,
    worker_up: Family<Labels, Gauge>,
    /// `locus_workers{state="idle"}` and `{state="busy"}`, set after
    /// every event: kept at hand rather than looked up by label.
    idle: Gauge,
    busy: Gauge,
    queued: Gauge,
    running: Gauge,
    jobs: Family<Labels, Counter>,
    job_seconds: Histogram,
    tiles: Counter,
    tiles_ignored: Family<Labels, Counter>,
    workers_lost: Counter,
    attempts_restarted: Counter,
    stale_messages: Counter,
    samples: Counter,
    rays: Family<Labels, Counter>,
    forwarded: Counter,
    bytes_sent: Family<Labels, Counter>,
    fetched_leaves: Counter,
    fetched_bytes: Counter,
    cache: Family<Labels, Counter>,
    departed: Mutex<VecDeque<String>>,
}

fn labels(pairs: &[(&str, &str)]) -> Labels {
    pairs
        .iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    pub fn new() -> Self {
        let mut r = Registry::with_prefix("locus");
        // Gauges are shared handles: these two are the family's own series.
        let workers = Family::<Labels, Gauge>::default();
        let m = Metrics {
            worker_up: Family::default(),
            idle: workers.get_or_create_owned(&labels(&[("state", "idle")])),
            busy: workers.get_or_create_owned(&labels(&[("state", "busy")])),
            queued: Gauge::default(),
            running: Gauge::default(),
            jobs: Family::default(),
            job_seconds: Histogram::new(exponential_buckets(0.25, 2.0, 16)),
            tiles: Counter::default(),
            tiles_ignored: Family::default(),
            workers_lost: Counter::default(),
            attempts_restarted: Counter::default(),
            stale_messages: Counter::default(),
            samples: Counter::default(),
            rays: Family::default(),
            forwarded: Counter::default(),
            bytes_sent: Family::default(),
            fetched_leaves: Counter::default(),
            fetched_bytes: Counter::default(),
            cache: Family::default(),
            departed: Mutex::new(VecDeque::new()),
            registry: Registry::default(),
        };
        r.register(
            "worker_up",
            "1 while a worker is registered, 0 once it has left",
            m.worker_up.clone(),
        );
        r.register(
            "workers",
            "Registered workers by state (idle, busy)",
            workers,
        );
        r.register("jobs_queued", "Jobs waiting", m.queued.clone());
        r.register("jobs_running", "Jobs running (0 or 1)", m.running.clone());
        r.register(
            "jobs",
            "Jobs ended, by outcome (done, failed)",
            m.jobs.clone(),
        );
        r.register(
            "job_duration_seconds",
            "Wall time of finished jobs, from start to image",
            m.job_seconds.clone(),
        );
        r.register(
            "tile_passes",
            "Tile passes (a tile in one progressive pass) received from workers",
            m.tiles.clone(),
        );
        r.register(
            "tiles_ignored",
            "Tile results ignored, by why (duplicate, unknown)",
            m.tiles_ignored.clone(),
        );
        r.register(
            "workers_lost",
            "Workers lost during a job (connection closed, heartbeats missed)",
            m.workers_lost.clone(),
        );
        r.register(
            "job_attempts_restarted",
            "Attempts of a job started again after a loss or a failure",
            m.attempts_restarted.clone(),
        );
        r.register(
            "stale_messages",
            "Worker messages of an aborted attempt or a finished job, ignored",
            m.stale_messages.clone(),
        );
        r.register("samples", "Camera samples rendered", m.samples.clone());
        r.register(
            "rays",
            "Rays traced, by kind (camera, shadow, indirect)",
            m.rays.clone(),
        );
        r.register(
            "forwarded_queries",
            "Ray queries forwarded from one worker to another",
            m.forwarded.clone(),
        );
        r.register(
            "peer_bytes_sent",
            "Bytes a worker sent to its peers (rays, answers, leaves)",
            m.bytes_sent.clone(),
        );
        r.register(
            "fetched_leaves",
            "Remote leaves fetched by workers",
            m.fetched_leaves.clone(),
        );
        r.register(
            "fetched_bytes",
            "Bytes of remote leaves fetched",
            m.fetched_bytes.clone(),
        );
        r.register(
            "cache",
            "Directional cache lookups and hits (lookup, local_hit, global_hit)",
            m.cache.clone(),
        );
        Metrics { registry: r, ..m }
    }

    /// The Prometheus text exposition.
    pub fn encode(&self) -> String {
        let mut s = String::new();
        // Writing into a String cannot fail.
        let _ = encode(&mut s, &self.registry);
        s
    }

    pub fn worker_joined(&self, worker: &str) {
        self.worker_up
            .get_or_create(&labels(&[("worker", worker)]))
            .set(1);
        let mut d = self.departed.lock().unwrap_or_else(|e| e.into_inner());
        d.retain(|w| w != worker);
    }

    pub fn worker_left(&self, worker: &str) {
        self.worker_up
            .get_or_create(&labels(&[("worker", worker)]))
            .set(0);
        let mut d = self.departed.lock().unwrap_or_else(|e| e.into_inner());
        d.push_back(worker.to_string());
        while d.len() > DEPARTED_KEPT {
            let old = d.pop_front().expect("longer than the bound");
            let l = labels(&[("worker", &old)]);
            self.worker_up.remove(&l);
            self.bytes_sent.remove(&l);
        }
    }

    /// The registry's counts: idle and busy workers, queued and running
    /// jobs.
    pub fn set_load(&self, idle: usize, busy: usize, queued: usize, running: bool) {
        self.idle.set(idle as i64);
        self.busy.set(busy as i64);
        self.queued.set(queued as i64);
        self.running.set(running as i64);
    }

    pub fn tile(&self) {
        self.tiles.inc();
    }

    pub fn tile_ignored(&self, why: &str) {
        self.tiles_ignored
            .get_or_create(&labels(&[("why", why)]))
            .inc();
    }

    pub fn worker_lost(&self) {
        self.workers_lost.inc();
    }

    pub fn attempt_restarted(&self) {
        self.attempts_restarted.inc();
    }

    pub fn stale_message(&self) {
        self.stale_messages.inc();
    }

    pub fn job_failed(&self) {
        self.jobs
            .get_or_create(&labels(&[("outcome", "failed")]))
            .inc();
    }

    /// A finished job's counts; `workers[w]` names worker `w` of the job.
    pub fn job_done(&self, r: &FarmReport, seconds: f64, workers: &[String]) {
        self.jobs
            .get_or_create(&labels(&[("outcome", "done")]))
            .inc();
        self.job_seconds.observe(seconds);
        let t = &r.totals.trace;
        self.samples.inc_by(t.samples);
        for (kind, n) in [
            ("camera", t.camera_rays),
            ("shadow", t.shadow_rays),
            ("indirect", t.indirect_rays),
        ] {
            self.rays
                .get_or_create(&labels(&[("kind", kind)]))
                .inc_by(n);
        }
        self.forwarded.inc_by(r.totals.forwarded_out);
        self.fetched_leaves.inc_by(r.totals.fetched_leaves);
        self.fetched_bytes.inc_by(r.totals.fetched_bytes);
        for (what, n) in [
            ("lookup", t.cache.lookups),
            ("local_hit", t.cache.local),
            ("global_hit", t.cache.global),
        ] {
            self.cache
                .get_or_create(&labels(&[("kind", what)]))
                .inc_by(n);
        }
        for (w, s) in r.workers.iter().enumerate() {
            let sent: u64 = s.stats.peers.iter().map(|p| p.bytes_sent).sum();
            if let Some(name) = workers.get(w) {
                self.bytes_sent
                    .get_or_create(&labels(&[("worker", name)]))
                    .inc_by(sent);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Counters appear in the exposition with their values, and a departed
    /// worker's series go once more than the bound have left after it.
    #[test]
    fn exposition_counts_and_bounds_departed_workers() {
        let m = Metrics::new();
        m.worker_joined("w-a");
        m.tile();
        m.tile();
        m.set_load(1, 0, 2, false);
        let text = m.encode();
        assert!(text.contains("locus_tile_passes_total 2"), "{text}");
        assert!(text.contains("locus_worker_up{worker=\"w-a\"} 1"), "{text}");
        assert!(text.contains("locus_jobs_queued 2"), "{text}");
        m.worker_left("w-a");
        assert!(m.encode().contains("locus_worker_up{worker=\"w-a\"} 0"));
        for i in 0..DEPARTED_KEPT {
            let w = format!("w-{i}");
            m.worker_joined(&w);
            m.worker_left(&w);
        }
        let text = m.encode();
        assert!(!text.contains("worker=\"w-a\""), "{text}");
        assert!(text.contains("locus_worker_up{worker=\"w-0\"} 0"));
        let up = text.matches("locus_worker_up{").count();
        assert_eq!(up, DEPARTED_KEPT);
    }
}
