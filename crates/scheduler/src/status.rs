//! What `/status` answers: the farm as the actor sees it at one moment,
//! workers, the queue, the running job with its progress and estimated time
//! left, and the last jobs that ended (with the traffic between their
//! workers). Built by the actor on request, so it is always consistent.

use crate::actor::{Actor, Running};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::time::Instant;

/// Ended jobs `/status` lists.
pub const HISTORY: usize = 16;

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Status {
    pub version: String,
    pub uptime_s: f64,
    pub workers: Vec<WorkerStatus>,
    pub queued: Vec<QueuedJob>,
    pub running: Option<RunningJob>,
    /// Newest first.
    pub ended: Vec<EndedJob>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WorkerStatus {
    pub id: u32,
    pub name: String,
    /// The address its peers dial.
    pub listen: String,
    pub cores: u32,
    /// Bytes; 0 for no limit.
    pub memory_budget: u64,
    /// `idle` or `busy`.
    pub state: String,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct QueuedJob {
    pub scene: String,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    /// Workers asked for (0: every registered one).
    pub workers: u32,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunningJob {
    pub id: u64,
    pub scene: String,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    /// The noise target the job stops at, if it has one.
    #[serde(default)]
    pub target_rel_mse: Option<f64>,
    pub policy: String,
    /// waiting for workers, preparing, distributing, rendering or
    /// collecting.
    pub phase: String,
    /// Attempts so far (more than 1 after a lost worker).
    pub attempt: u32,
    /// Peer addresses of the workers the job lost.
    pub lost: Vec<String>,
    pub elapsed_s: f64,
    /// The image's tiles, rendered in `passes` progressive passes; `pass`
    /// (from 0) is the earliest pass not complete.
    pub tiles: u32,
    pub passes: u32,
    pub pass: u32,
    /// Tiles times passes, and how many of them are in the film.
    pub tile_passes: u64,
    pub tile_passes_done: u64,
    /// Pixel samples, and how many of them are in the film.
    pub samples: u64,
    pub samples_done: u64,
    /// From the rate of samples since the attempt's first tile; None
    /// before it.
    pub eta_s: Option<f64>,
    pub members: Vec<Member>,
}

/// A worker of the running job: its registry id, the share of the
/// predicted cost its region holds, and the tile passes it has returned in
/// this attempt.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Member {
    pub worker: u32,
    pub listen: String,
    pub predicted_share: Option<f64>,
    pub tile_passes_done: u32,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EndedJob {
    pub id: u64,
    pub scene: String,
    pub width: u32,
    pub height: u32,
    /// Samples per pixel: the image's for a done job (fewer than asked
    /// where a noise target was met), else those asked for.
    pub spp: u32,
    /// The noise target the job stopped at, if it had one.
    #[serde(default)]
    pub target_rel_mse: Option<f64>,
    /// `done` or `failed`.
    pub outcome: String,
    pub reason: Option<String>,
    pub seconds: f64,
    /// The job's workers' peer addresses, in job order.
    pub workers: Vec<String>,
    /// `traffic[a][b]`: bytes worker `a` sent to worker `b` (done jobs).
    pub traffic: Vec<Vec<u64>>,
    pub forwarded_fraction: Option<f64>,
    pub load_imbalance: Option<f64>,
    /// The relMSE the image carries, from its samples' spread (done jobs
    /// of more than one sample a pixel).
    pub rel_mse_estimate: Option<f64>,
    pub attempts: u32,
    /// Peer addresses of the workers the job lost.
    pub lost: Vec<String>,
}

impl Running {
    /// Seconds left at the rate samples have come in since the attempt's
    /// first tile (samples, not tiles: later passes are larger).
    fn eta(&self, now: Instant) -> Option<f64> {
        let first = self.attempt.t_first_tile?;
        let (done, all) = self.film.samples();
        let since = done - self.attempt.before.1;
        if since == 0 {
            return None;
        }
        let rate = since as f64 / now.duration_since(first).as_secs_f64().max(1e-3);
        Some((all - done) as f64 / rate)
    }
}

pub(crate) fn push_history(h: &mut VecDeque<EndedJob>, e: EndedJob) {
    h.push_front(e);
    h.truncate(HISTORY);
}

impl Actor {
    /// Registry worker `m`'s peer address (empty once it has left).
    fn listen_of(&self, m: u32) -> String {
        self.workers
            .get(&m)
            .map(|e| e.reg.listen.clone())
            .unwrap_or_default()
    }

    /// A running radiosity job as the status shows it: its phase is
    /// "radiosity", and it has no tiles.
    fn radiosity_status(&self, now: Instant) -> Option<RunningJob> {
        let r = self.radiosity.as_ref()?;
        Some(RunningJob {
            id: r.id,
            scene: r.req.name.clone(),
            width: r.req.camera.width,
            height: r.req.camera.height,
            spp: 0,
            target_rel_mse: None,
            policy: "radiosity".into(),
            phase: "radiosity".into(),
            attempt: r.attempts,
            lost: r.lost.clone(),
            elapsed_s: now.duration_since(r.started).as_secs_f64(),
            tiles: 0,
            passes: 0,
            pass: 0,
            tile_passes: 0,
            tile_passes_done: 0,
            samples: 0,
            samples_done: 0,
            eta_s: None,
            members: r
                .members
                .iter()
                .map(|m| Member {
                    worker: *m,
                    listen: self.listen_of(*m),
                    predicted_share: None,
                    tile_passes_done: 0,
                })
                .collect(),
        })
    }

    pub(crate) fn status(&self) -> Status {
        let now = Instant::now();
        let workers = self
            .workers
            .iter()
            .map(|(&id, w)| WorkerStatus {
                id,
                name: w.reg.name.clone(),
                listen: w.reg.listen.clone(),
                cores: w.reg.cores,
                memory_budget: w.reg.memory_budget,
                state: if w.busy { "busy" } else { "idle" }.to_string(),
            })
            .collect();
        let queued = self
            .queue
            .iter()
            .map(|q| QueuedJob {
                scene: q.req.name.clone(),
                width: q.req.camera.width,
                height: q.req.camera.height,
                spp: q.req.settings.spp,
                workers: q.req.options.workers,
            })
            .collect();
        let running = self.job.as_ref().map(|j| RunningJob {
            id: j.id,
            scene: j.req.name.clone(),
            width: j.req.camera.width,
            height: j.req.camera.height,
            spp: j.req.settings.spp,
            target_rel_mse: j.req.settings.target_rel_mse,
            policy: j.req.options.fetch.name().to_string(),
            phase: j.attempt.phase.name().to_string(),
            attempt: j.recovery.attempts,
            lost: j.recovery.lost.iter().map(|(a, _)| a.clone()).collect(),
            elapsed_s: now.duration_since(j.started).as_secs_f64(),
            tiles: j.film.tiles().len() as u32,
            passes: j.film.passes().len() as u32,
            pass: j.film.pass(),
            tile_passes: j.film.units().1,
            tile_passes_done: j.film.units().0,
            samples: j.film.samples().1,
            samples_done: j.film.samples().0,
            eta_s: j.eta(now),
            members: j
                .attempt
                .members
                .iter()
                .enumerate()
                .map(|(w, m)| Member {
                    worker: *m,
                    listen: self.listen_of(*m),
                    predicted_share: j.attempt.prep.as_ref().map(|p| p.predicted_share(w)),
                    tile_passes_done: j.attempt.tiles_by[w],
                })
                .collect(),
        });
        let running = running.or_else(|| self.radiosity_status(now));
        Status {
            version: env!("CARGO_PKG_VERSION").to_string(),
            uptime_s: now.duration_since(self.started).as_secs_f64(),
            workers,
            queued,
            running,
            ended: self.history.iter().cloned().collect(),
        }
    }
}
