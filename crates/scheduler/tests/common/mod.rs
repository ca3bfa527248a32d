//! The scheduler's actor through its channels, without sockets, as the
//! actor tests drive it: a worker is a channel of `SchedulerToWorker`, a
//! client one of `SchedulerToClient`, and every event goes in as the
//! connection tasks would send it.
#![allow(dead_code)]

use locus_core::scene::Scene;
use locus_protocol::control::{Registration, SchedulerToWorker, WorkerToScheduler};
use locus_protocol::submit::{JobOptions, JobRequest, SchedulerToClient};
use locus_scheduler::SchedulerHandle;
use locus_scheduler::actor::{Actor, Event};
use locus_scheduler::metrics::Metrics;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{mpsc, oneshot};
use tokio::time::timeout;
use tokio_util::sync::CancellationToken;

pub struct Farm {
    pub events: mpsc::Sender<Event>,
    pub metrics: Arc<Metrics>,
    pub shutdown: CancellationToken,
}

pub fn start() -> Farm {
    let (tx, rx) = mpsc::channel(64);
    let metrics = Arc::new(Metrics::new());
    let shutdown = CancellationToken::new();
    tokio::spawn(Actor::new(4, tx.clone(), metrics.clone()).run(rx, shutdown.clone()));
    Farm {
        events: tx,
        metrics,
        shutdown,
    }
}

impl Farm {
    pub async fn worker(&self, id: u32) -> mpsc::Receiver<SchedulerToWorker> {
        self.worker_with_room(id, 1024).await
    }

    /// A worker whose control channel holds `room` messages.
    pub async fn worker_with_room(
        &self,
        id: u32,
        room: usize,
    ) -> mpsc::Receiver<SchedulerToWorker> {
        self.worker_as(id, room, false).await
    }

    /// A worker that takes BVH layouts (`layouts`) or not.
    pub async fn worker_as(
        &self,
        id: u32,
        room: usize,
        layouts: bool,
    ) -> mpsc::Receiver<SchedulerToWorker> {
        let (tx, rx) = mpsc::channel(room);
        let reg = Registration {
            listen: format!("w{id}:7879"),
            cores: 1,
            memory_budget: 0,
            resident: 0,
            name: format!("w{id}"),
            layouts,
        };
        let addr = "127.0.0.1:9".parse().unwrap();
        self.events
            .send(Event::Joined { id, reg, addr, tx })
            .await
            .unwrap();
        rx
    }

    pub async fn submit(&self, workers: u32) -> mpsc::Receiver<SchedulerToClient> {
        self.submit_request(request(workers, 1, None)).await
    }

    /// `req` submitted as the embedded farm submits it.
    pub async fn submit_request(&self, req: JobRequest) -> mpsc::Receiver<SchedulerToClient> {
        SchedulerHandle::new(self.events.clone())
            .submit(req)
            .await
            .unwrap()
    }

    pub async fn from(&self, id: u32, msg: WorkerToScheduler) {
        self.events
            .send(Event::FromWorker { id, msg })
            .await
            .unwrap();
    }

    pub async fn tiles_done(&self) -> u64 {
        let (tx, rx) = oneshot::channel();
        self.events.send(Event::Status(tx)).await.unwrap();
        rx.await.unwrap().running.map_or(0, |j| j.tile_passes_done)
    }
}

/// The Cornell box at 32x32 in four tiles of 16x16, at `spp` with the
/// noise target `target`, for `workers` workers.
pub fn request(workers: u32, spp: u32, target: Option<f64>) -> JobRequest {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut scene = Scene::load(&root.join("scenes/cornell-box/cornell.toml")).unwrap();
    scene.camera.width = 32;
    scene.camera.height = 32;
    scene.settings.spp = spp;
    scene.settings.target_rel_mse = target;
    let opts = JobOptions {
        workers,
        tile_size: 16,
        ..Default::default()
    };
    locus_scheduler::client::request(&scene, opts)
}

pub async fn recv<T>(rx: &mut mpsc::Receiver<T>) -> T {
    timeout(Duration::from_secs(20), rx.recv())
        .await
        .expect("a message within 20 s")
        .expect("channel open")
}

/// Waits for the job to start (after `Queued`); returns its id.
pub async fn accepted(client: &mut mpsc::Receiver<SchedulerToClient>) -> u64 {
    loop {
        match recv(client).await {
            SchedulerToClient::Queued { .. } => {}
            SchedulerToClient::Accepted { job, .. } => return job,
            other => panic!("expected the job accepted, got {other:?}"),
        }
    }
}
