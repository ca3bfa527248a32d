//! An attempt of the running job: preparation on a blocking thread for the
//! attempt's workers, distribution, demand-driven tiles of those not yet
//! in the film, and the workers' reports. Every worker message names a
//! run; one that does not name the running attempt's is stale.

use super::recovery::Setback;
use super::{Actor, Attempt, Event, MAX_TILE_REQUEST, Phase};
use crate::distribute;
use crate::film::{Refused, Unit};
use crate::job::{self, Member};
use crate::store::Write;
use crate::tiles::TileQueue;
use locus_protocol::control::{SchedulerToWorker, TileResult, WorkerToScheduler};
use std::time::Instant;
use tracing::{info, warn};

impl Actor {
    /// Starts an attempt of the running job on `members` (registry ids,
    /// idle): marks them busy, gives the attempt a fresh run id and
    /// prepares it on a blocking thread, for the tiles not yet in.
    pub(super) fn start_attempt(&mut self, members: Vec<u32>) {
        let run = self.next_run;
        self.next_run += 1;
        let info: Vec<Member> = members
            .iter()
            .map(|m| {
                let w = self.workers.get_mut(m).expect("an idle worker");
                w.busy = true;
                Member {
                    cores: w.reg.cores,
                    budget: w.reg.memory_budget,
                    resident: w.reg.resident,
                }
            })
            .collect();
        let j = self.job.as_mut().expect("a running job");
        let n = members.len();
        j.recovery.attempts += 1;
        j.attempt = Attempt {
            run,
            members,
            phase: Phase::Preparing,
            reports: vec![None; n],
            told_no_more: vec![false; n],
            owed: vec![0; n],
            ready: vec![false; n],
            ended: vec![false; n],
            tiles_by: vec![0; n],
            ..Attempt::waiting(j.film.done())
        };
        if j.recovery.attempts > 1 {
            info!(
                job = j.id,
                run,
                workers = n,
                tile_passes_left = j.film.units().1 - j.film.units().0,
                "job restarting on the workers left"
            );
        }
        let (events, scene, options) =
            (self.events.clone(), j.scene.clone(), j.req.options.clone());
        let rects = j.film.tiles().to_vec();
        let known = j
            .overture
            .as_ref()
            .map(|o| o.levels.clone())
            .unwrap_or_default();
        tokio::spawn(async move {
            let prep = tokio::task::spawn_blocking(move || {
                job::prepare(scene, &options, &info, &rects, &known)
            })
            .await;
            let prep = match prep {
                Ok(Ok(p)) => Ok(Box::new(p)),
                Ok(Err(e)) => Err(e),
                Err(e) => Err(format!("preparation crashed: {e}")),
            };
            let _ = events.send(Event::Prepared { run, prep }).await;
        });
    }

    pub(super) fn on_prepared(&mut self, run: u64, prep: Result<Box<job::Prepared>, String>) {
        let Some(j) = self.job.as_mut().filter(|j| j.attempt.run == run) else {
            return;
        };
        let mut prep = match prep {
            Ok(p) => p,
            Err(e) => {
                let id = j.id;
                self.fail(format!("job {id} could not be prepared: {e}"));
                return;
            }
        };
        j.take_overture(&mut prep);
        let a = &mut j.attempt;
        a.t_prepared = Some(Instant::now());
        a.advance(Phase::Distributing);
        a.queue = TileQueue::new(
            j.film.missing(),
            &prep.tile_affinity,
            a.members.len(),
            j.film.sizes(),
        )
        .with_votes(prep.tile_votes.clone());
        info!(
            job = j.id,
            run,
            leaves = prep.leaves,
            seconds = prep.timings.total_s,
            "partitioned"
        );
        let members: Vec<_> = a
            .members
            .iter()
            .map(|m| {
                let w = &self.workers[m];
                distribute::Member {
                    listen: w.reg.listen.clone(),
                    tx: w.tx.clone(),
                    layouts: w.reg.layouts,
                }
            })
            .collect();
        distribute::ship(run, &j.req, &mut prep, members, j.overture.as_ref());
        a.prep = Some(prep);
    }

    pub(super) fn on_worker(&mut self, id: u32, msg: WorkerToScheduler) {
        let Some(msg) = self.radiosity_message(id, msg) else {
            return;
        };
        // A report of an aborted attempt of this job: its work is counted
        // in the job's recovery, not in the last attempt's totals.
        if let WorkerToScheduler::Report { job: run, stats } = &msg
            && let Some(j) = self.job.as_mut()
            && j.past_runs.contains(run)
        {
            j.recovery.aborted += stats.trace;
            j.recovery.aborted_reports += 1;
            return;
        }
        let run_of = match &msg {
            WorkerToScheduler::Ready { job }
            | WorkerToScheduler::NeedTiles { job, .. }
            | WorkerToScheduler::Report { job, .. }
            | WorkerToScheduler::Failed { job, .. }
            | WorkerToScheduler::Node { job, .. } => *job,
            WorkerToScheduler::TileDone(t) => t.job,
            WorkerToScheduler::Measured(c) => c.job,
            WorkerToScheduler::Heartbeat => return,
        };
        let (Some(w), Some(j)) = (self.member(id), self.job.as_mut()) else {
            self.stale(id, run_of);
            return;
        };
        if run_of != j.attempt.run {
            self.stale(id, run_of);
            return;
        }
        let a = &mut j.attempt;
        match msg {
            WorkerToScheduler::Ready { .. } => {
                if std::mem::replace(&mut a.ready[w], true) {
                    return;
                }
                if a.ready.iter().all(|&r| r) {
                    a.t_ready = Some(Instant::now());
                    a.advance(Phase::Rendering);
                    info!(job = j.id, run = a.run, "all workers ready");
                    if j.film.is_complete() {
                        // Restored whole from the store (the scheduler
                        // stopped after the last tile was kept, before the
                        // job's end was): no tile will come to end it.
                        a.advance(Phase::Collecting);
                        a.t_rendered = Some(Instant::now());
                    }
                }
                // The others may have rendered every tile while this one
                // was still receiving its region.
                self.send_ends();
            }
            WorkerToScheduler::NeedTiles { count, .. } => self.hand_tiles(id, w, count),
            WorkerToScheduler::TileDone(r) => self.on_tile(id, w, r),
            WorkerToScheduler::Report { stats, .. } => {
                if a.phase != Phase::Collecting {
                    let reason = format!("worker {w} reported before the last tile was in");
                    self.recover(Setback::Failed { w }, reason);
                    return;
                }
                a.reports[w] = Some(*stats);
                if a.reports.iter().all(Option::is_some) {
                    self.finish();
                }
            }
            WorkerToScheduler::Failed { reason, .. } => {
                let addr = self.workers[&id].reg.listen.clone();
                self.recover(
                    Setback::Failed { w },
                    format!("worker {w} ({addr}): {reason}"),
                );
            }
            WorkerToScheduler::Node { .. } => {
                let why = format!("worker {w} sent a radiosity message in a render job");
                self.recover(Setback::Failed { w }, why);
            }
            WorkerToScheduler::Measured(c) => self.on_measured(w, *c),
            WorkerToScheduler::Heartbeat => {}
        }
    }

    /// Hands member `w` (registry id `id`) up to `count` tile passes, and
    /// at most its share of those left (the rest is owed, and handed out
    /// as tiles come in): a worker asking far ahead would otherwise hold
    /// tiles not yet started while another, with none, waits (a small
    /// image's every tile went to the first to ask). What a closed pass
    /// holds back (a noise target's barrier) is owed too and handed out
    /// when the pass opens; a worker with none left at all is told so.
    fn hand_tiles(&mut self, id: u32, w: usize, count: u32) {
        let Some(j) = self.job.as_mut() else { return };
        let a = &mut j.attempt;
        let Some(entry) = self.workers.get(&id) else {
            return;
        };
        let tx = &entry.tx;
        let open = j.film.open_passes();
        let count = count.min(MAX_TILE_REQUEST);
        let share = a.queue.len().div_ceil(a.members.len().max(1)).max(1);
        for given in 0..count {
            // Beyond its share, and only while tiles are left (with none,
            // the worker is told so below).
            if given as usize >= share && !a.queue.is_empty() {
                a.owed[w] = (a.owed[w] + count - given).min(MAX_TILE_REQUEST);
                break;
            }
            if let Some(u) = a.queue.next_for(w, open) {
                let share = a.queue.samples().div_ceil(a.members.len().max(1) as u64);
                let t = j.film.assignment(u, a.run, share);
                if tx.try_send(SchedulerToWorker::Tile(t)).is_err() {
                    // A full channel (a worker asking far ahead, or
                    // one whose socket is slow): the tile waits for
                    // the next request, its own or another's. Lost
                    // here, it would never be rendered and the job
                    // would never end.
                    a.queue.put_back(u);
                    break;
                }
                a.t_first_tile.get_or_insert_with(Instant::now);
            } else if !a.queue.is_empty() {
                // Tiles are left (any of them this worker's to take, a
                // worker out of its own taking others'), but the next pass
                // is closed until this one is in: the worker, which does
                // not ask again while its request is open, gets the rest
                // when it opens.
                a.owed[w] = (a.owed[w] + count - given).min(MAX_TILE_REQUEST);
                break;
            } else {
                // A full channel: the worker asks again when it
                // runs out, and is told then.
                if !a.told_no_more[w]
                    && tx
                        .try_send(SchedulerToWorker::NoMoreTiles { job: a.run })
                        .is_ok()
                {
                    a.told_no_more[w] = true;
                }
                break;
            }
        }
    }

    /// Hands out the tiles owed to members (beyond their share, or while a
    /// pass was closed), as tiles come in or the film opens the next pass.
    fn serve_owed(&mut self) {
        let Some(j) = self.job.as_mut() else { return };
        let a = &mut j.attempt;
        let owed: Vec<(usize, u32)> = a
            .owed
            .iter_mut()
            .enumerate()
            .filter(|(_, n)| **n > 0)
            .map(|(w, n)| (w, std::mem::take(n)))
            .collect();
        let members = a.members.clone();
        for (w, n) in owed {
            self.hand_tiles(members[w], w, n);
        }
    }

    /// A message of another attempt, a finished job, or from a worker
    /// outside the running attempt: ignored and counted.
    fn stale(&self, id: u32, run: u64) {
        tracing::debug!(worker = id, run, "stale message ignored");
        self.metrics.stale_message();
    }

    fn on_tile(&mut self, id: u32, w: usize, r: TileResult) {
        let j = self.job.as_mut().expect("member of a job");
        let u = Unit {
            tile: r.tile,
            pass: r.pass,
        };
        let open = j.film.open_passes();
        let changed = match j.film.add(u, r.sums) {
            Ok(changed) => changed,
            Err(Refused::Size { got, want }) => {
                let reason = format!(
                    "worker {id} sent pass {} of tile {} with {got} pixels, expected {want}",
                    r.pass, r.tile
                );
                self.fail(reason);
                return;
            }
            Err(e) => {
                let why = match e {
                    Refused::Duplicate => "duplicate",
                    _ => "unknown",
                };
                warn!(
                    worker = id,
                    tile = r.tile,
                    pass = r.pass,
                    why,
                    "tile result ignored"
                );
                self.metrics.tile_ignored(why);
                return;
            }
        };
        let opened = j.film.open_passes() > open;
        if let Some(s) = &self.store {
            if changed {
                s.write(Write::Tile {
                    job: j.id,
                    tile: r.tile,
                    sums: j.film.tile_sums(r.tile),
                });
            }
            // A spread pass that opened is kept before any tile holds it:
            // a restart cannot make it again once one does.
            if opened && let Some(spread) = j.film.pass_spread() {
                s.write(Write::Spread {
                    job: j.id,
                    spread: spread.clone(),
                });
            }
        }
        j.attempt.tiles_by[w] += 1;
        self.metrics.tile();
        j.client.send(j.progress());
        if j.film.is_complete() {
            let a = &mut j.attempt;
            a.advance(Phase::Collecting);
            a.t_rendered = Some(Instant::now());
            self.send_ends();
        } else if opened || j.attempt.owed.iter().any(|&n| n > 0) {
            self.serve_owed();
        }
    }

    /// Once every tile is in, tells each ready member that has not been
    /// told to end the job. A member not yet ready is told when it is:
    /// before, its region may still be on the way, behind this message's
    /// place in its channel, and it would drop an `EndJob` for a job it
    /// does not have yet, then start the job and wait for the end for
    /// ever (a tiny job rendered whole by the first worker ready hung so,
    /// about once in a few hundred). A full channel is retried on the
    /// next tick.
    pub(super) fn send_ends(&mut self) {
        let Some(j) = self.job.as_mut() else { return };
        let a = &mut j.attempt;
        if a.phase != Phase::Collecting {
            return;
        }
        for (w, m) in a.members.iter().enumerate() {
            if a.ready[w] && !a.ended[w] && a.reports[w].is_none() {
                let Some(entry) = self.workers.get(m) else {
                    continue;
                };
                a.ended[w] = entry
                    .tx
                    .try_send(SchedulerToWorker::EndJob { job: a.run })
                    .is_ok();
            }
        }
    }
}
