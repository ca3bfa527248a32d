//! How a job ends: failed, with its reason sent to the client and its
//! workers told to drop it, or finished, with its report and its image,
//! which is sent to the client in runs and kept for the preview and for a
//! client that attaches late. Either way the job leaves the store.

use super::clients::{Finished, send_result};
use super::{Actor, Running};
use crate::report::build_report;
use crate::status::{self, EndedJob};
use locus_protocol::submit::SchedulerToClient;
use std::sync::Arc;
use tracing::{info, warn};

impl Actor {
    /// Ends the running job: its workers are idle again.
    fn release(&mut self) -> Option<Running> {
        self.release_members();
        self.job.take()
    }

    /// The attempt's workers' peer addresses, in job order.
    fn member_names(&self, j: &Running) -> Vec<String> {
        j.attempt
            .members
            .iter()
            .map(|m| {
                self.workers
                    .get(m)
                    .map_or_else(|| format!("worker {m}"), |w| w.reg.listen.clone())
            })
            .collect()
    }

    /// The history entry of job `j`, run last on `workers`.
    fn ended(j: &Running, outcome: &str, workers: Vec<String>) -> EndedJob {
        EndedJob {
            id: j.id,
            scene: j.req.name.clone(),
            width: j.req.camera.width,
            height: j.req.camera.height,
            spp: j.req.settings.spp,
            target_rel_mse: j.req.settings.target_rel_mse,
            outcome: outcome.to_string(),
            reason: None,
            seconds: j.started.elapsed().as_secs_f64(),
            workers,
            traffic: Vec::new(),
            forwarded_fraction: None,
            load_imbalance: None,
            rel_mse_estimate: None,
            attempts: j.recovery.attempts,
            lost: j.recovery.lost.iter().map(|(a, _)| a.clone()).collect(),
        }
    }

    pub(super) fn fail(&mut self, reason: String) {
        self.abort_members(&reason);
        let Some(j) = self.release() else { return };
        warn!(job = j.id, %reason, "job failed");
        self.metrics.job_failed();
        let ended = EndedJob {
            reason: Some(reason.clone()),
            ..Self::ended(&j, "failed", self.member_names(&j))
        };
        status::push_history(&mut self.history, ended);
        self.forget(j.id);
        j.client
            .send(SchedulerToClient::Failed { job: j.id, reason });
        self.try_start();
    }

    pub(super) fn finish(&mut self) {
        let Some(mut j) = self.release() else { return };
        let names = self.member_names(&j);
        j.recovery.tile_passes_kept = j.attempt.before.0;
        let report = build_report(&j, &names);
        let ended = EndedJob {
            traffic: report
                .workers
                .iter()
                .map(|w| w.stats.peers.iter().map(|p| p.bytes_sent).collect())
                .collect(),
            forwarded_fraction: Some(report.forwarded_fraction),
            load_imbalance: Some(report.load_imbalance),
            rel_mse_estimate: report.error_estimate.map(|e| e.rel_mse),
            spp: report.spp_rendered,
            ..Self::ended(&j, "done", names)
        };
        self.metrics
            .job_done(&report, ended.seconds, &ended.workers);
        status::push_history(&mut self.history, ended);
        info!(
            job = j.id,
            render_s = report.phases.render_s,
            imbalance = report.load_imbalance,
            forwarded = report.forwarded_fraction,
            attempts = j.recovery.attempts,
            "job done"
        );
        // One image serves the client, the preview and a late client: the
        // client's copy is sent from it in runs, never copied whole.
        let image = Arc::new(j.film.image());
        let report = Arc::new(report);
        self.forget(j.id);
        let f = Finished {
            id: j.id,
            image,
            report,
            counts: j.film.sample_counts().map(|c| Arc::new(c.to_vec())),
        };
        let stored = self.keep_finished(f.clone());
        if let Some(tx) = j.client.take() {
            send_result(tx, f, stored);
        }
        self.try_start();
    }
}
