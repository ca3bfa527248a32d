//! A radiosity job in the actor: it starts on idle workers like a render
//! job, but its coordinator runs on a blocking thread
//! ([`crate::radiosity::solve`]) and the actor only passes the members'
//! messages to it and delivers what it returns. A lost member ends the
//! attempt, and the job starts again from the start on the workers there
//! are, in whole rings: the solution is deterministic, so it comes out the
//! same bits.

use super::clients::{Client, Finished, send_result_with};
use super::{Actor, Event, Queued};
use crate::job;
use crate::radiosity::{self, FromMember, Members, Solved};
use crate::status::{self, EndedJob};
use locus_core::scene::Scene;
use locus_protocol::control::{SchedulerToWorker, WorkerToScheduler};
use locus_protocol::radiosity::RadiosityJob;
use locus_protocol::report::FarmReport;
use locus_protocol::submit::{JobKind, JobRequest, SchedulerToClient};
use std::sync::Arc;
use std::time::Instant;
use tracing::{info, warn};

/// A running radiosity job.
pub(crate) struct RadiosityRunning {
    pub id: u64,
    pub run: u64,
    /// Registry ids; the position is the node id.
    pub members: Vec<u32>,
    /// The request without its triangles.
    pub req: Box<JobRequest>,
    client: Client,
    /// Where members' messages go; dropped when the job ends, which ends
    /// the coordinator's wait.
    to_coordinator: flume::Sender<FromMember>,
    pub started: Instant,
    scene: Arc<Scene>,
    rj: RadiosityJob,
    /// Attempts so far, and the workers lost in them.
    pub attempts: u32,
    pub lost: Vec<String>,
}

/// What outlives a radiosity job's attempts.
struct Restartable {
    id: u64,
    req: Box<JobRequest>,
    scene: Arc<Scene>,
    rj: RadiosityJob,
    client: Client,
    started: Instant,
    attempts: u32,
    lost: Vec<String>,
}

/// Attempts a radiosity job may take (each after a lost worker).
const MAX_ATTEMPTS: u32 = 3;

/// Messages of the members the coordinator may not have taken yet: per
/// shot each node sends at most a `Done`, a `Time` and a `Failed`, and at
/// the end its patches in runs.
const BACKLOG: usize = 1024;

impl RadiosityRunning {
    pub(super) fn client_left(&self) -> bool {
        self.client.left()
    }
}

impl Actor {
    /// Starts queued radiosity job `q` on `members` (idle registry ids).
    pub(super) fn start_radiosity(&mut self, q: Queued, rj: RadiosityJob, members: Vec<u32>) {
        let mut req = q.req;
        let scene = job::scene_of(&mut req);
        let job = Restartable {
            id: q.id,
            req,
            scene,
            rj,
            client: q.client,
            started: Instant::now(),
            attempts: 0,
            lost: Vec::new(),
        };
        self.launch_radiosity(job, members);
    }

    /// Runs an attempt of `j` on `members` under a fresh run id: the
    /// coordinator on a blocking thread, the members marked busy.
    fn launch_radiosity(&mut self, j: Restartable, members: Vec<u32>) {
        let run = self.next_run;
        self.next_run += 1;
        let (mut links, mut addrs) = (Vec::new(), Vec::new());
        for m in &members {
            let w = self.workers.get_mut(m).expect("an idle worker");
            w.busy = true;
            links.push(w.tx.clone());
            addrs.push(w.reg.listen.clone());
        }
        let (tx, rx) = flume::bounded(BACKLOG + 4 * members.len());
        let (id, events, progress_to) = (j.id, self.events.clone(), j.client.sender());
        info!(
            job = id,
            run,
            nodes = members.len(),
            attempt = j.attempts + 1,
            "radiosity job starting"
        );
        let m = Members {
            run,
            addrs,
            links,
            from: rx,
        };
        let (scene, rj) = (j.scene.clone(), j.rj.clone());
        tokio::task::spawn_blocking(move || {
            let progress = |f: f64| {
                if let Some(c) = &progress_to {
                    let _ = c.try_send(SchedulerToClient::Progress {
                        job: id,
                        samples_done: (f * 1000.0) as u64,
                        samples: 1000,
                        pass: 0,
                        passes: 1,
                    });
                }
            };
            let seed = scene.settings.seed;
            let outcome = radiosity::solve(&scene, &rj, seed, m, &progress).map(Box::new);
            let _ = events.blocking_send(Event::RadiosityEnded { run, outcome });
        });
        self.radiosity = Some(RadiosityRunning {
            id,
            run,
            members,
            req: j.req,
            scene: j.scene,
            rj: j.rj,
            client: j.client,
            to_coordinator: tx,
            started: j.started,
            attempts: j.attempts + 1,
            lost: j.lost,
        });
    }

    /// A member of the running radiosity job was lost: the attempt is
    /// dropped and the job starts again from the start on the workers
    /// there are (the solution is deterministic, so it comes out the same
    /// bits), in whole rings; with none, or after [`MAX_ATTEMPTS`], it
    /// fails naming the workers lost.
    pub(super) fn radiosity_lost(&mut self, addr: String, reason: String) {
        let Some(r) = self.radiosity.take() else {
            return;
        };
        warn!(job = r.id, worker = %addr, %reason, "radiosity node lost; starting again");
        for m in &r.members {
            if let Some(w) = self.workers.get_mut(m) {
                w.busy = false;
                let _ = w.tx.try_send(SchedulerToWorker::AbortJob {
                    job: r.run,
                    reason: format!("node worker {addr} was lost"),
                });
            }
        }
        let RadiosityRunning {
            id,
            req,
            scene,
            rj,
            client,
            started,
            attempts,
            mut lost,
            ..
        } = r;
        lost.push(addr);
        let idle = self.idle();
        let n = match rj.ring {
            0 => idle.len(),
            ring => idle.len() - idle.len() % ring as usize,
        };
        let j = Restartable {
            id,
            req,
            scene,
            rj,
            client,
            started,
            attempts,
            lost,
        };
        if n == 0 || attempts >= MAX_ATTEMPTS {
            let why = format!(
                "lost node workers {:?} ({reason}) in {attempts} attempts, and {} idle workers \
                 left to form rings of {}",
                j.lost,
                idle.len(),
                j.rj.ring
            );
            // Put it back as running so that it fails the one way.
            self.launch_radiosity_failed(j, why);
            return;
        }
        self.launch_radiosity(j, idle[..n].to_vec());
    }

    /// Fails job `j`, which has no attempt running.
    fn launch_radiosity_failed(&mut self, j: Restartable, why: String) {
        let (tx, _) = flume::bounded(1);
        self.radiosity = Some(RadiosityRunning {
            id: j.id,
            run: 0,
            members: Vec::new(),
            req: j.req,
            scene: j.scene,
            rj: j.rj,
            client: j.client,
            to_coordinator: tx,
            started: j.started,
            attempts: j.attempts,
            lost: j.lost,
        });
        self.fail_radiosity(why);
    }

    /// Passes a member's message to the running radiosity job; gives it
    /// back when it is not for that job.
    pub(super) fn radiosity_message(
        &mut self,
        id: u32,
        msg: WorkerToScheduler,
    ) -> Option<WorkerToScheduler> {
        let Some(r) = self.radiosity.as_ref() else {
            return Some(msg);
        };
        let run = match &msg {
            WorkerToScheduler::Ready { job }
            | WorkerToScheduler::Failed { job, .. }
            | WorkerToScheduler::Node { job, .. } => *job,
            _ => return Some(msg),
        };
        let Some(n) = r.members.iter().position(|&m| m == id) else {
            return Some(msg);
        };
        if run != r.run {
            return Some(msg);
        }
        let n = n as u32;
        let fwd = match msg {
            WorkerToScheduler::Ready { .. } => FromMember::Ready(n),
            WorkerToScheduler::Failed { reason, .. } => FromMember::Failed(n, reason),
            WorkerToScheduler::Node { msg, .. } => FromMember::Node(n, *msg),
            _ => unreachable!("matched above"),
        };
        if r.to_coordinator.try_send(fwd).is_err() {
            self.fail_radiosity(format!(
                "the coordinator fell {BACKLOG} messages behind its nodes"
            ));
        }
        None
    }

    /// Whether registry worker `id` is a node of the running radiosity job.
    pub(super) fn radiosity_member(&self, id: u32) -> bool {
        self.radiosity
            .as_ref()
            .is_some_and(|r| r.members.contains(&id))
    }

    fn end_radiosity(&mut self, outcome: &str, reason: Option<String>) -> Option<RadiosityRunning> {
        let r = self.radiosity.take()?;
        let workers = r
            .members
            .iter()
            .map(|m| {
                let w = self.workers.get_mut(m);
                w.map_or_else(
                    || format!("worker {m}"),
                    |w| {
                        w.busy = false;
                        w.reg.listen.clone()
                    },
                )
            })
            .collect();
        let ended = EndedJob {
            id: r.id,
            scene: r.req.name.clone(),
            width: r.req.camera.width,
            height: r.req.camera.height,
            spp: 0,
            outcome: outcome.to_string(),
            reason,
            seconds: r.started.elapsed().as_secs_f64(),
            workers,
            traffic: Vec::new(),
            forwarded_fraction: None,
            load_imbalance: None,
            attempts: r.attempts,
            lost: r.lost.clone(),
        };
        status::push_history(&mut self.history, ended);
        self.forget(r.id);
        Some(r)
    }

    /// Fails the running radiosity job: its members drop it.
    pub(super) fn fail_radiosity(&mut self, reason: String) {
        let Some(r) = self.end_radiosity("failed", Some(reason.clone())) else {
            return;
        };
        for m in &r.members {
            if let Some(w) = self.workers.get(m) {
                let _ = w.tx.try_send(SchedulerToWorker::AbortJob {
                    job: r.run,
                    reason: reason.clone(),
                });
            }
        }
        warn!(job = r.id, %reason, "radiosity job failed");
        self.metrics.job_failed();
        r.client
            .send(SchedulerToClient::Failed { job: r.id, reason });
        self.try_start();
    }

    /// The coordinator returned: the solution goes to the client, or the
    /// job fails.
    pub(super) fn radiosity_ended(&mut self, run: u64, outcome: Result<Box<Solved>, String>) {
        if self.radiosity.as_ref().is_none_or(|r| r.run != run) {
            return;
        }
        let solved = match outcome {
            Ok(s) => s,
            Err(why) => return self.fail_radiosity(why),
        };
        let r = self.end_radiosity("done", None).expect("checked");
        let Solved {
            image,
            mesh,
            mut report,
        } = *solved;
        report.attempts = r.attempts;
        report.lost = r.lost.clone();
        info!(
            job = r.id,
            iterations = report.iterations,
            elements = report.elements,
            solve_s = report.solve_s,
            "radiosity job done"
        );
        let s = &r.req.settings;
        let spp = match &r.req.kind {
            JobKind::Radiosity(rj) => rj.spp.max(1),
            JobKind::Render => s.spp,
        };
        let farm = FarmReport {
            scene: r.req.name.clone(),
            width: image.width,
            height: image.height,
            spp,
            seed: s.seed,
            sampler: format!("{:?}", s.sampler).to_lowercase(),
            ..Default::default()
        };
        let (image, farm) = (Arc::new(image), Arc::new(farm));
        let stored = self.keep_finished(Finished {
            id: r.id,
            image: image.clone(),
            report: farm.clone(),
        });
        if let Some(tx) = r.client.take() {
            send_result_with(
                tx,
                image,
                farm,
                r.id,
                stored,
                Some((mesh, Box::new(report))),
            );
        }
        self.try_start();
    }
}
