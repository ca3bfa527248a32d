//! Clients and their jobs: the link a job's messages go to (none for a job
//! restored from the store until its client attaches), attaching a client
//! to a job it submitted earlier, and the last results, kept for clients
//! that attach after their job ended.

use super::Actor;
use crate::store::Write;
use locus_core::image_io::Image;
use locus_core::radiosity::output::MeshCorner;
use locus_protocol::radiosity::RadiosityReport;
use locus_protocol::report::FarmReport;
use locus_protocol::submit::{
    JobResult, RESULT_CHUNK_COUNTS, RESULT_CHUNK_PIXELS, RESULT_CHUNK_TRIANGLES, SchedulerToClient,
};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{mpsc, oneshot};
use tokio::time::timeout;
use tracing::{info, warn};

/// Finished results kept for late clients and previews (each holds its
/// image).
pub const FINISHED_KEPT: usize = 4;

/// How long a result waits for the state store to commit it before it is
/// sent anyway (a disk that stalls must not hold a client forever).
const STORE_WAIT: Duration = Duration::from_secs(30);

/// The client of a job, if one is attached.
pub(crate) struct Client(Option<mpsc::Sender<SchedulerToClient>>);

impl Client {
    pub(crate) fn some(tx: mpsc::Sender<SchedulerToClient>) -> Self {
        Self(Some(tx))
    }

    pub(crate) fn none() -> Self {
        Self(None)
    }

    /// Sends without waiting; a message for a full or absent client is
    /// dropped (progress only: results go through [`send_result`]).
    pub(crate) fn send(&self, m: SchedulerToClient) {
        if let Some(tx) = &self.0 {
            let _ = tx.try_send(m);
        }
    }

    /// Whether an attached client has gone away (which cancels its job);
    /// a job with none attached is waiting for one, not abandoned.
    pub(crate) fn left(&self) -> bool {
        self.0.as_ref().is_some_and(|tx| tx.is_closed())
    }

    pub(crate) fn take(self) -> Option<mpsc::Sender<SchedulerToClient>> {
        self.0
    }

    /// A copy of the link, for a task that reports progress.
    pub(crate) fn sender(&self) -> Option<mpsc::Sender<SchedulerToClient>> {
        self.0.clone()
    }
}

/// A finished job's result.
#[derive(Clone)]
pub(crate) struct Finished {
    pub id: u64,
    pub image: Arc<Image>,
    pub report: Arc<FarmReport>,
    /// With adaptive sampling, the samples each pixel got.
    pub counts: Option<Arc<Vec<u32>>>,
}

/// Sends a finished image in runs (and its pixels' sample counts, with
/// adaptive sampling), then `Done` without them, waiting for room: a
/// dedicated task, since the image can be large. `Done` waits for
/// `stored` too, where the result goes to the state store.
pub(crate) fn send_result(
    client: mpsc::Sender<SchedulerToClient>,
    f: Finished,
    stored: Option<oneshot::Receiver<()>>,
) {
    send_result_with(client, f, stored, None)
}

/// A radiosity job's meshed solution and report, sent with its image.
pub(crate) type RadiosityPart = (Vec<[MeshCorner; 3]>, Box<RadiosityReport>);

/// [`send_result`], with a radiosity job's mesh (in runs after the image)
/// and report.
pub(crate) fn send_result_with(
    client: mpsc::Sender<SchedulerToClient>,
    f: Finished,
    stored: Option<oneshot::Receiver<()>>,
    radiosity: Option<RadiosityPart>,
) {
    let Finished {
        id: job,
        image,
        report,
        counts,
    } = f;
    tokio::spawn(async move {
        let pixels = |offset, run: &[[f32; 3]]| SchedulerToClient::Pixels {
            job,
            offset,
            pixels: run.to_vec(),
        };
        if !send_runs(&client, &image.pixels, RESULT_CHUNK_PIXELS, pixels).await {
            return;
        }
        if let Some(c) = counts {
            let run = |offset, run: &[u32]| SchedulerToClient::Counts {
                job,
                offset,
                counts: run.to_vec(),
            };
            if !send_runs(&client, &c, RESULT_CHUNK_COUNTS, run).await {
                return;
            }
        }
        let mut part = None;
        if let Some((mesh, r)) = radiosity {
            let tris = |offset, run: &[[MeshCorner; 3]]| SchedulerToClient::Mesh {
                job,
                offset,
                tris: run.to_vec(),
            };
            if !send_runs(&client, &mesh, RESULT_CHUNK_TRIANGLES, tris).await {
                return;
            }
            part = Some(r);
        }
        let result = JobResult {
            job,
            width: image.width,
            height: image.height,
            pixels: Vec::new(),
            report: (*report).clone(),
            sample_counts: None,
            radiosity: part,
        };
        drop(image);
        // `Done` tells the client the job is over: not before the result
        // is on disk, so that a scheduler killed after it still has it.
        if let Some(stored) = stored
            && !matches!(timeout(STORE_WAIT, stored).await, Ok(Ok(())))
        {
            warn!(
                job,
                "the result is sent before the state store committed it"
            );
        }
        let _ = client.send(SchedulerToClient::Done(Box::new(result))).await;
    });
}

/// Sends `all` in runs of `per`, each made by `msg(offset, run)`; false
/// when the client has gone.
async fn send_runs<T>(
    client: &mpsc::Sender<SchedulerToClient>,
    all: &[T],
    per: usize,
    msg: impl Fn(u64, &[T]) -> SchedulerToClient,
) -> bool {
    for (k, run) in all.chunks(per).enumerate() {
        if client.send(msg((k * per) as u64, run)).await.is_err() {
            return false;
        }
    }
    true
}

impl Actor {
    /// A client takes up job `job`: the running or a queued job's messages
    /// go to it from now on; a finished one's result is sent at once.
    pub(super) fn attach(&mut self, job: u64, tx: mpsc::Sender<SchedulerToClient>) {
        if let Some(j) = self.job.as_mut().filter(|j| j.id == job) {
            info!(job, "client attached to the running job");
            let _ = tx.try_send(SchedulerToClient::Accepted {
                job,
                workers: j.attempt.members.len() as u32,
            });
            let _ = tx.try_send(j.progress());
            j.client = Client::some(tx);
        } else if let Some((ahead, q)) =
            self.queue.iter_mut().enumerate().find(|(_, q)| q.id == job)
        {
            info!(job, "client attached to a queued job");
            let ahead = ahead as u32 + self.job.is_some() as u32;
            let _ = tx.try_send(SchedulerToClient::Queued { job, ahead });
            q.client = Client::some(tx);
        } else if let Some(f) = self.finished.iter().find(|f| f.id == job) {
            info!(job, "client attached to a finished job");
            send_result(tx, f.clone(), None);
        } else {
            let reason = format!(
                "no job {job} here: it failed, or finished more than {FINISHED_KEPT} jobs ago, \
                 or was never submitted to this scheduler"
            );
            let _ = tx.try_send(SchedulerToClient::Failed { job, reason });
        }
    }

    /// Keeps a finished result for late clients (in the store too, so it
    /// outlives a restart), dropping the oldest. Returns what resolves
    /// once the store has committed it, where there is a store.
    pub(super) fn keep_finished(&mut self, f: Finished) -> Option<oneshot::Receiver<()>> {
        let stored = self.store.as_ref().and_then(|s| {
            let queued = s.write(Write::Finished {
                job: f.id,
                image: f.image.clone(),
                report: f.report.clone(),
                counts: f.counts.clone(),
            });
            queued.then(|| s.synced())
        });
        self.finished.push_front(f);
        self.finished.truncate(FINISHED_KEPT);
        stored
    }

    /// The job ended: its record and tiles leave the store.
    pub(super) fn forget(&self, job: u64) {
        if let Some(s) = &self.store {
            s.write(Write::End { job });
        }
    }
}
