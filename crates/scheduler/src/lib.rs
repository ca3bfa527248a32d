//! locus-scheduler: the scheduler daemon of the locus farm, and the client
//! that submits jobs to it.
//!
//! Connections are accepted here and authenticated by the handshake; the
//! first message says whether the peer is a worker ([`Opening::Register`])
//! or a client ([`Opening::Submit`]). Every connection task talks to the
//! [`actor`] through a bounded channel; the actor owns the worker registry
//! and the running job, so no state is shared between tasks. A job goes
//! through [`job::prepare`] (octree, [`cost`] prediction, [`partition`]
//! within the workers' [`memory`] budgets) on a blocking thread, then
//! [`distribute`] (processor map plus each region's geometry, part by
//! part), then demand-driven tiles, then the workers' reports, which
//! become the [`report`]. [`client`] is the submitting side used by `locus
//! submit`; [`SchedulerHandle`] submits from the same process (the
//! embedded farm) without copying or re-parsing the scene. [`http`] serves
//! the read-only status page, [`status`] (asked of the actor through the
//! same channel) and [`metrics`] (kept by the actor as events happen).

pub mod actor;
pub mod client;
pub mod cost;
pub mod distribute;
pub mod http;
pub mod job;
pub mod memory;
pub mod metrics;
pub mod partition;
pub mod report;
pub mod status;
pub mod tiles;

use actor::{Actor, Event};
use anyhow::Context;
use locus_protocol::control::{Opening, SchedulerToWorker, WorkerToScheduler};
use locus_protocol::submit::{JobRequest, SchedulerToClient};
use locus_protocol::{Connection, MAX_FRAME_LEN, handshake};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{info, instrument, warn};

#[derive(Clone, Debug)]
pub struct SchedulerConfig {
    pub listen: String,
    pub token: String,
    /// Jobs that may wait behind the running one.
    pub max_queued_jobs: usize,
    /// Where to serve the read-only status page, `/status`, `/metrics` and
    /// previews ([`http`]); None: nowhere.
    pub http: Option<String>,
}

pub struct Scheduler {
    cfg: SchedulerConfig,
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
        Ok(Self {
            cfg,
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
        SchedulerHandle {
            events: self.events.0.clone(),
        }
    }

    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    pub async fn run(self, shutdown: CancellationToken) -> anyhow::Result<()> {
        info!(addr = %self.local_addr()?, "scheduler listening");
        let (ev_tx, ev_rx) = self.events;
        let metrics = Arc::new(metrics::Metrics::new());
        let actor = tokio::spawn(
            Actor::new(self.cfg.max_queued_jobs, ev_tx.clone(), metrics.clone())
                .run(ev_rx, shutdown.clone()),
        );
        if let Some(l) = self.http {
            info!("status page on http://{}/", l.local_addr()?);
            let (ev, sd) = (ev_tx.clone(), shutdown.clone());
            tokio::spawn(async move {
                if let Err(e) = http::serve(l, ev, metrics, sd).await {
                    warn!("status server stopped: {e}");
                }
            });
        }
        let token = Arc::new(self.cfg.token.into_bytes());
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
            let (token, ev, sd) = (token.clone(), ev_tx.clone(), shutdown.clone());
            let id = next_id;
            tokio::spawn(async move {
                let _permit = permit;
                if let Err(e) = serve(stream, id, &token, ev, sd).await {
                    warn!(%addr, "connection dropped: {e:#}");
                }
            });
        }
        drop(ev_tx);
        let _ = actor.await;
        Ok(())
    }
}

#[instrument(skip_all, fields(conn = id, peer = %stream.peer_addr().map(|a| a.to_string()).unwrap_or_default()))]
async fn serve(
    stream: tokio::net::TcpStream,
    id: u32,
    token: &[u8],
    ev: mpsc::Sender<Event>,
    shutdown: CancellationToken,
) -> anyhow::Result<()> {
    let mut conn = Connection::new(stream, MAX_FRAME_LEN)?;
    handshake::server(&mut conn, token).await?;
    let addr = conn.peer();
    let opening = tokio::select! {
        _ = shutdown.cancelled() => return Ok(()),
        m = conn.read_msg::<Opening>("opening") => m?,
    };
    match opening {
        None => Ok(()),
        Some(Opening::Register(reg)) => {
            conn.write_msg(&SchedulerToWorker::Welcome { worker: id })
                .await?;
            let (mut r, mut w) = conn.into_split();
            let (tx, mut rx) = mpsc::channel::<SchedulerToWorker>(256);
            info!(worker = id, listen = %reg.listen, cores = reg.cores, "worker registered");
            ev.send(Event::Joined { id, reg, addr, tx }).await?;
            let writer = tokio::spawn(async move {
                while let Some(m) = rx.recv().await {
                    w.write_msg(&m).await?;
                }
                Ok::<(), locus_protocol::ProtocolError>(())
            });
            let reason = loop {
                let m = tokio::select! {
                    _ = shutdown.cancelled() => break "scheduler shutting down".to_string(),
                    m = r.read_msg::<WorkerToScheduler>("control") => m,
                };
                match m {
                    Ok(Some((msg, _))) => {
                        if ev.send(Event::FromWorker { id, msg }).await.is_err() {
                            break "scheduler shutting down".into();
                        }
                    }
                    Ok(None) => break "closed the connection".into(),
                    Err(e) => break e.to_string(),
                }
            };
            writer.abort();
            let _ = ev.send(Event::Left { id, reason }).await;
            Ok(())
        }
        Some(Opening::Submit(req)) => {
            let (tx, mut rx) = mpsc::channel::<SchedulerToClient>(64);
            ev.send(Event::Submit { req, client: tx }).await?;
            let (mut r, mut conn) = conn.into_split();
            loop {
                let m = tokio::select! {
                    _ = shutdown.cancelled() => return Ok(()),
                    m = rx.recv() => m,
                    // A client says nothing after its request: a read
                    // that ends is the client gone, and dropping `rx`
                    // tells the actor to cancel its job.
                    gone = r.read_msg::<Opening>("submit") => {
                        let why = match gone {
                            Ok(None) => "closed the connection".to_string(),
                            Ok(Some(_)) => "sent a second request".to_string(),
                            Err(e) => e.to_string(),
                        };
                        info!(%addr, "client {why}; its job is cancelled");
                        return Ok(());
                    }
                };
                let Some(m) = m else { return Ok(()) };
                let last = matches!(
                    m,
                    SchedulerToClient::Done(_) | SchedulerToClient::Failed { .. }
                );
                conn.write_msg(&m).await?;
                if last {
                    return Ok(());
                }
            }
        }
    }
}
