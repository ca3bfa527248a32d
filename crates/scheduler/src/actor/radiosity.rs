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
use locus_protocol::submit::{JobRequest, SchedulerToClient};
use std::sync::Arc;
use std::time::Instant;
use tracing::{info, warn};

/// A running radiosity job: what outlives its attempts, and the attempt
/// running now.
pub(crate) struct RadiosityRunning {
    pub id: u64,
    /// The request without its triangles (the scene holds them).
    pub req: Box<JobRequest>,
    scene: Arc<Scene>,
    rj: RadiosityJob,
    client: Client,
    pub started: Instant,
    /// Attempts so far, and the workers lost in them.
    pub attempts: u32,
    pub lost: Vec<String>,
    /// The attempt's run id and members (registry ids; the position is
    /// the node id).
    pub run: u64,
    pub members: Vec<u32>,
    /// Where members' messages go; dropped when the attempt ends, which
    /// ends the coordinator's wait.
    to_coordinator: Option<flume::Sender<FromMember>>,
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
        self.radiosity = Some(RadiosityRunning {
            id: q.id,
            req,
            scene,
            rj,
            client: q.client,
            started: Instant::now(),
            attempts: 0,
            lost: Vec::new(),
            run: 0,
            members: Vec::new(),
            to_coordinator: None,
        });
        self.launch_radiosity(members);
    }

    /// Runs an attempt of the radiosity job on `members` under a fresh run
    /// id: the coordinator on a blocking thread, the members marked busy.
    fn launch_radiosity(&mut self, members: Vec<u32>) {
        let run = self.next_run;
        self.next_run += 1;
        let (mut links, mut addrs) = (Vec::new(), Vec::new());
        for m in &members {
            let w = self.workers.get_mut(m).expect("an idle worker");
            w.busy = true;
            links.push(w.tx.clone());
            addrs.push(w.reg.listen.clone());
        }
        let events = self.events.clone();
        let j = self.radiosity.as_mut().expect("a radiosity job");
        let (tx, rx) = flume::bounded(BACKLOG + 4 * members.len());
        j.attempts += 1;
        j.run = run;
        j.members = members;
        j.to_coordinator = Some(tx);
        let (id, progress_to) = (j.id, j.client.sender());
        info!(
            job = id,
            run,
            nodes = j.members.len(),
            attempt = j.attempts,
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
            let outcome = radiosity::solve(&scene, &rj, m, &progress).map(Box::new);
            let _ = events.blocking_send(Event::RadiosityEnded { run, outcome });
        });
    }

    /// Marks the attempt's members idle and, with a reason, tells them to
    /// drop it (a finished attempt's nodes have ended on their own).
    fn drop_radiosity_attempt(&mut self, reason: Option<&str>) {
        let Some(r) = self.radiosity.as_mut() else {
            return;
        };
        r.to_coordinator = None;
        for m in std::mem::take(&mut r.members) {
            if let Some(w) = self.workers.get_mut(&m) {
                w.busy = false;
                if let Some(reason) = reason {
                    let _ = w.tx.try_send(SchedulerToWorker::AbortJob {
                        job: r.run,
                        reason: reason.to_string(),
                    });
                }
            }
        }
    }

    /// A member of the running radiosity job was lost: the attempt is
    /// dropped and the job starts again from the start on the workers
    /// there are (the solution is deterministic, so it comes out the same
    /// bits), in whole rings; with none, or after [`MAX_ATTEMPTS`], it
    /// fails naming the workers lost.
    pub(super) fn radiosity_lost(&mut self, addr: String, reason: String) {
        self.drop_radiosity_attempt(Some(&format!("node worker {addr} was lost")));
        let Some(r) = self.radiosity.as_mut() else {
            return;
        };
        warn!(job = r.id, worker = %addr, %reason, "radiosity node lost");
        r.lost.push(addr);
        let (ring, attempts) = (r.rj.ring as usize, r.attempts);
        let idle = self.idle();
        let n = match ring {
            0 => idle.len(),
            ring => idle.len() - idle.len() % ring,
        };
        if n == 0 || attempts >= MAX_ATTEMPTS {
            let lost = &self.radiosity.as_ref().expect("checked").lost;
            let why = format!(
                "lost node workers {lost:?} ({reason}) in {attempts} attempts, with {} idle \
                 workers left for rings of {ring}: start more workers and submit again",
                idle.len()
            );
            return self.fail_radiosity(why);
        }
        self.launch_radiosity(idle[..n].to_vec());
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
        if r.to_coordinator
            .as_ref()
            .is_none_or(|tx| tx.try_send(fwd).is_err())
        {
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

    /// Ends the running radiosity job (its attempt dropped with `reason`,
    /// if one runs) and records it in the history.
    fn end_radiosity(&mut self, outcome: &str, reason: Option<String>) -> Option<RadiosityRunning> {
        let workers = self.radiosity.as_ref()?.members.iter().map(|m| {
            self.workers
                .get(m)
                .map_or_else(|| format!("worker {m}"), |w| w.reg.listen.clone())
        });
        let workers = workers.collect();
        self.drop_radiosity_attempt(reason.as_deref());
        let r = self.radiosity.take()?;
        let ended = EndedJob {
            id: r.id,
            scene: r.req.name.clone(),
            width: r.req.camera.width,
            height: r.req.camera.height,
            spp: r.rj.spp.max(1),
            target_rel_mse: None,
            outcome: outcome.to_string(),
            reason,
            seconds: r.started.elapsed().as_secs_f64(),
            workers,
            traffic: Vec::new(),
            forwarded_fraction: None,
            load_imbalance: None,
            rel_mse_estimate: None,
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
        let farm = FarmReport {
            scene: r.req.name.clone(),
            width: image.width,
            height: image.height,
            spp: r.rj.spp.max(1),
            seed: s.seed,
            sampler: s.sampler.name().into(),
            ..Default::default()
        };
        let (image, farm) = (Arc::new(image), Arc::new(farm));
        let f = Finished {
            id: r.id,
            image,
            report: farm,
            counts: None,
        };
        let stored = self.keep_finished(f.clone());
        if let Some(tx) = r.client.take() {
            send_result_with(tx, f, stored, Some((mesh, Box::new(report))));
        }
        self.try_start();
    }
}
