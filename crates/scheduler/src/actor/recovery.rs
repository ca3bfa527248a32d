//! Recovery: a member lost (its connection closed, or its heartbeats
//! stopped) or an attempt failed. The attempt is aborted on the members
//! left, the finished tiles stay in the film, and a new attempt, under a
//! new run id, is prepared over the workers there are and renders only the
//! tiles not yet in. Every sample is a pure function of its pixel, index,
//! dimension and seed, so the image is the same bits whichever worker
//! renders a tile, and in whichever attempt.

use super::{Actor, Attempt, MAX_FAILED_ATTEMPTS, Phase, WORKER_WAIT};
use tracing::{info, warn};

/// What went wrong with the running attempt.
pub(super) enum Setback {
    /// Member `w` is gone from the registry; `addr` is where its peers
    /// dialed it.
    Lost { w: usize, addr: String },
    /// Member `w` failed the attempt (or broke its protocol).
    Failed { w: usize },
}

impl Actor {
    /// Recovers the running job from `setback`, whose cause is `reason`.
    pub(super) fn recover(&mut self, setback: Setback, reason: String) {
        let Some(j) = self.job.as_mut() else { return };
        let (w, lost) = match &setback {
            Setback::Lost { w, addr } => {
                j.recovery.lost.push((addr.clone(), reason.clone()));
                (*w, true)
            }
            Setback::Failed { w } => (*w, false),
        };
        if j.attempt.phase == Phase::Collecting {
            // Every tile is in: the image is done, and a member that cannot
            // report is only missing from the report.
            warn!(job = j.id, worker = w, %reason, "no report from a worker after the last tile");
            let a = &mut j.attempt;
            a.reports[w].get_or_insert_with(Default::default);
            if a.reports.iter().all(Option::is_some) {
                self.finish();
            }
            return;
        }
        warn!(job = j.id, run = j.attempt.run, worker = w, %reason, "attempt aborted");
        j.failures = if lost { 0 } else { j.failures + 1 };
        if j.failures >= MAX_FAILED_ATTEMPTS {
            // `fail` tells the members to drop the attempt.
            let n = j.failures;
            self.fail(format!(
                "{reason} ({n} attempts in a row failed without a worker lost)"
            ));
            return;
        }
        self.abort_members(&reason);
        self.release_members();
        let j = self.job.as_mut().expect("checked above");
        j.past_runs.push(j.attempt.run);
        self.metrics.attempt_restarted();
        j.attempt = Attempt::waiting(j.film.done());
        self.restart();
    }

    /// Starts the next attempt of a job waiting between attempts, on every
    /// idle worker up to the number it asked for; with none, waits up to
    /// [`WORKER_WAIT`] for one to register.
    pub(super) fn restart(&mut self) {
        let Some(j) = self
            .job
            .as_ref()
            .filter(|j| j.attempt.phase == Phase::Waiting)
        else {
            return;
        };
        let idle = self.idle();
        if idle.is_empty() {
            if j.attempt.waiting_since.elapsed() >= WORKER_WAIT {
                let lost = j.recovery.lost.len();
                self.fail(format!(
                    "the job lost {lost} workers and no worker was free for {} s: \
                     start workers (they register with the scheduler) and submit it again",
                    WORKER_WAIT.as_secs()
                ));
            }
            return;
        }
        let want = match j.req.options.workers as usize {
            0 => idle.len(),
            n => n.min(idle.len()),
        };
        info!(job = j.id, workers = want, "job resumes");
        self.start_attempt(idle[..want].to_vec());
    }
}
