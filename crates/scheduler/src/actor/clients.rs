//! Clients and their jobs: the link a job's messages go to (none for a job
//! restored from the store until its client attaches), attaching a client
//! to a job it submitted earlier, and the last results, kept for clients
//! that attach after their job ended.

use super::Actor;
use crate::store::Write;
use locus_core::image_io::Image;
use locus_protocol::control::TileAssignment;
use locus_protocol::report::FarmReport;
use locus_protocol::submit::{JobResult, RESULT_CHUNK_PIXELS, SchedulerToClient};
use std::sync::Arc;
use tokio::sync::mpsc;
use tracing::info;

/// Finished results kept for late clients and previews (each holds its
/// image).
pub const FINISHED_KEPT: usize = 4;

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
}

/// A finished job's result.
pub(crate) struct Finished {
    pub id: u64,
    pub image: Arc<Image>,
    pub report: Arc<FarmReport>,
}

/// Copies a tile's row-major pixels into the film.
pub(crate) fn paste(film: &mut [[f32; 3]], width: u32, t: &TileAssignment, pixels: &[[f32; 3]]) {
    let w = (t.x1 - t.x0) as usize;
    for (row, y) in (t.y0..t.y1).enumerate() {
        let at = (y * width + t.x0) as usize;
        film[at..at + w].copy_from_slice(&pixels[row * w..(row + 1) * w]);
    }
}

/// Sends a finished image in runs, then `Done` without pixels, waiting for
/// room: a dedicated task, since the image can be large.
pub(crate) fn send_result(
    client: mpsc::Sender<SchedulerToClient>,
    image: Arc<Image>,
    report: Arc<FarmReport>,
    job: u64,
) {
    tokio::spawn(async move {
        for (k, run) in image.pixels.chunks(RESULT_CHUNK_PIXELS).enumerate() {
            let chunk = SchedulerToClient::Pixels {
                job,
                offset: (k * RESULT_CHUNK_PIXELS) as u64,
                pixels: run.to_vec(),
            };
            if client.send(chunk).await.is_err() {
                return;
            }
        }
        let result = JobResult {
            job,
            width: image.width,
            height: image.height,
            pixels: Vec::new(),
            report: (*report).clone(),
        };
        drop(image);
        let _ = client.send(SchedulerToClient::Done(Box::new(result))).await;
    });
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
            let _ = tx.try_send(SchedulerToClient::Progress {
                job,
                tiles_done: j.done,
                tiles: j.tiles.len() as u32,
            });
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
            send_result(tx, f.image.clone(), f.report.clone(), job);
        } else {
            let reason = format!(
                "no job {job} here: it failed, or finished more than {FINISHED_KEPT} jobs ago, \
                 or was never submitted to this scheduler"
            );
            let _ = tx.try_send(SchedulerToClient::Failed { job, reason });
        }
    }

    /// Keeps a finished result for late clients, dropping the oldest.
    pub(super) fn keep_finished(&mut self, f: Finished) {
        self.finished.push_front(f);
        self.finished.truncate(FINISHED_KEPT);
    }

    /// The job ended: its record and tiles leave the store.
    pub(super) fn forget(&self, job: u64) {
        if let Some(s) = &self.store {
            s.write(Write::End { job });
        }
    }
}
