//! locus-scheduler: the scheduler daemon of the locus farm, and the client
//! that submits jobs to it.
//!
//! Connections are accepted here and served by [`server`]: the handshake,
//! then the first message says whether the peer is a worker
//! ([`Opening::Register`](locus_protocol::control::Opening::Register)) or a
//! client ([`Opening::Submit`](locus_protocol::control::Opening::Submit)); workers are
//! watched by heartbeats. Every connection task talks to the [`actor`]
//! through a bounded channel; the actor owns the worker registry and the
//! running job, so no state is shared between tasks. A job runs in
//! attempts (a lost worker's attempt is aborted and the unfinished tiles
//! are rendered by a new one on the workers left); each goes through
//! [`job::prepare`] (octree, [`cost`] prediction, [`partition`]
//! within the workers' [`memory`] budgets) on a blocking thread, then
//! [`distribute`] (processor map plus each region's geometry, part by
//! part; a part several workers are sent alike is gathered and encoded
//! once, `frames`), then demand-driven tiles in progressive passes into the [`film`], then
//! the workers' reports, which
//! become the [`report`]. [`client`] is the submitting side used by `locus
//! submit`; [`SchedulerHandle`] submits from the same process (the
//! embedded farm) without copying or re-parsing the scene. [`http`] serves
//! the read-only status page, [`status`] (asked of the actor through the
//! same channel) and [`metrics`] (kept by the actor as events happen).

// These docs are for the crate's developers, who read them with
// `cargo doc --document-private-items`: links to private items resolve there.
#![allow(rustdoc::private_intra_doc_links)]

pub mod actor;
pub mod client;
pub mod cost;
pub mod distribute;
pub mod film;
mod frames;
pub mod http;
pub mod job;
pub mod memory;
pub mod metrics;
pub mod overture;
pub mod partition;
pub mod radiosity;
pub mod report;
mod server;
pub mod status;
pub mod store;
pub mod tiles;

/// The Cornell box of `scenes/`, which the unit tests plan jobs over.
#[cfg(test)]
pub(crate) fn cornell_box() -> locus_core::scene::Scene {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    locus_core::scene::Scene::load(&root.join("scenes/cornell-box/cornell.toml"))
        .expect("the Cornell box in scenes/")
}

use actor::{Actor, Event};
use anyhow::Context;
use locus_protocol::submit::{JobRequest, SchedulerToClient};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

#[derive(Clone, Debug)]
pub struct SchedulerConfig {
    pub listen: String,
    pub token: String,
    /// TLS for every connection (None: plain TCP).
    pub tls: Option<locus_protocol::tls::Tls>,
    /// Jobs that may wait behind the running one.
    pub max_queued_jobs: usize,
    /// Where to serve the read-only status page, `/status`, `/metrics` and
    /// previews ([`http`]); None: nowhere.
    pub http: Option<String>,
    /// How long a worker may be silent (no message, no heartbeat) before
    /// it is lost and its job recovers without it.
    pub worker_timeout: Duration,
    /// Where jobs and their finished tiles are kept ([`store`]), so that a
    /// restarted scheduler resumes them; None: in memory only.
    pub state: Option<std::path::PathBuf>,
}

/// The default of [`SchedulerConfig::worker_timeout`]: heartbeats go every
/// second, so five are missed.
pub const WORKER_TIMEOUT: Duration = Duration::from_secs(5);

pub struct Scheduler {
    cfg: SchedulerConfig,
    /// The opened store, its next job id and the jobs it held.
    store: Option<(store::Store, u64, Vec<store::Restored>, Vec<store::Kept>)>,
    listener: TcpListener,
    http: Option<TcpListener>,
    events: (mpsc::Sender<Event>, mpsc::Receiver<Event>),
}

/// Submits jobs to a scheduler in this process.
#[derive(Clone)]
pub struct SchedulerHandle {
    events: mpsc::Sender<Event>,
}

impl SchedulerHandle {
    /// A handle on an actor's event channel: the scheduler's own
    /// ([`Scheduler::handle`]), or that of an actor a test drives alone.
    pub fn new(events: mpsc::Sender<Event>) -> Self {
        Self { events }
    }

    /// Submits `req` without a socket; the job's messages arrive on the
    /// returned channel, as a remote client would read them.
    pub async fn submit(
        &self,
        req: JobRequest,
    ) -> anyhow::Result<mpsc::Receiver<SchedulerToClient>> {
        let (tx, rx) = mpsc::channel(64);
        self.events
            .send(Event::Submit {
                req: Box::new(req),
                client: tx,
                encoded: None,
            })
            .await
            .map_err(|_| anyhow::anyhow!("the scheduler has stopped"))?;
        Ok(rx)
    }
}

impl Scheduler {
    pub async fn bind(cfg: SchedulerConfig) -> anyhow::Result<Self> {
        let listener = TcpListener::bind(&cfg.listen)
            .await
            .with_context(|| format!("scheduler: cannot listen on {}", cfg.listen))?;
        let http = match &cfg.http {
            Some(a) => Some(
                TcpListener::bind(a)
                    .await
                    .with_context(|| format!("scheduler: cannot serve HTTP on {a}"))?,
            ),
            None => None,
        };
        let store = match cfg.state.clone() {
            Some(dir) => Some(
                tokio::task::spawn_blocking(move || store::Store::open(&dir))
                    .await
                    .context("opening the state store")??,
            ),
            None => None,
        };
        Ok(Self {
            cfg,
            store,
            listener,
            http,
            events: mpsc::channel::<Event>(1024),
        })
    }

    /// The status server's bound address, when there is one.
    pub fn http_addr(&self) -> Option<SocketAddr> {
        self.http.as_ref().and_then(|l| l.local_addr().ok())
    }

    /// A handle to submit jobs from this process.
    pub fn handle(&self) -> SchedulerHandle {
        SchedulerHandle::new(self.events.0.clone())
    }

    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    pub async fn run(self, shutdown: CancellationToken) -> anyhow::Result<()> {
        info!(addr = %self.local_addr()?, "scheduler listening");
        let (ev_tx, ev_rx) = self.events;
        let metrics = Arc::new(metrics::Metrics::new());
        let mut actor = Actor::new(self.cfg.max_queued_jobs, ev_tx.clone(), metrics.clone());
        let stored = self.store.is_some();
        if let Some((store, next, jobs, kept)) = self.store {
            actor = actor.with_store(store, next, jobs, kept);
        }
        let actor = tokio::spawn(actor.run(ev_rx, shutdown.clone()));
        if let Some(l) = self.http {
            info!("status page on http://{}/", l.local_addr()?);
            let (ev, sd) = (ev_tx.clone(), shutdown.clone());
            tokio::spawn(async move {
                if let Err(e) = http::serve(l, ev, metrics, sd).await {
                    warn!("status server stopped: {e}");
                }
            });
        }
        let shared = server::Shared {
            creds: Arc::new(locus_protocol::handshake::Credentials::new(
                &self.cfg.token,
                self.cfg.tls.clone(),
            )),
            events: ev_tx.clone(),
            shutdown: shutdown.clone(),
            worker_timeout: self.cfg.worker_timeout,
            store: stored,
            frames: Default::default(),
        };
        let mut next_id = 0u32;
        let permits = Arc::new(tokio::sync::Semaphore::new(locus_protocol::MAX_CONNECTIONS));
        loop {
            let permit = tokio::select! {
                _ = shutdown.cancelled() => break,
                p = permits.clone().acquire_owned() => p.expect("the semaphore is never closed"),
            };
            let (stream, addr) = tokio::select! {
                _ = shutdown.cancelled() => break,
                r = self.listener.accept() => match r {
                    Ok(x) => x,
                    Err(e) => {
                        warn!("accept: {e}");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                        continue;
                    }
                },
            };
            next_id += 1;
            let (sh, id) = (shared.clone(), next_id);
            tokio::spawn(async move {
                let _permit = permit;
                if let Err(e) = server::serve(stream, id, sh).await {
                    warn!(%addr, "connection dropped: {e:#}");
                }
            });
        }
        drop((ev_tx, shared));
        let _ = actor.await;
        Ok(())
    }
}
