//! The running job's irradiance overture: the levels its preparation
//! measured, and a level its workers measure, merged and sent to every
//! member ([`crate::overture`]).

use super::recovery::Setback;
use super::{Actor, Running};
use crate::job::Prepared;
use crate::overture::{Round, send_levels};
use locus_core::irradiance::overture::level_spacings;
use locus_protocol::overture::MeasuredChunk;
use std::sync::Arc;
use tracing::info;

impl Running {
    /// Takes what preparing the attempt measured, and starts the round of
    /// the first level not known when the workers measure.
    pub(super) fn take_overture(&mut self, prep: &mut Prepared) {
        let (Some(o), Some(p)) = (self.overture.as_mut(), prep.irradiance.as_mut()) else {
            return;
        };
        o.by_workers = p.by_workers;
        o.levels.extend(p.measured.drain(..).map(Arc::new));
        if let Some(s) = p.stats.take() {
            o.rays += s.trace.rays();
            o.seconds += s.seconds;
        }
        let levels = level_spacings(&o.params).len();
        let a = &mut self.attempt;
        a.round = (p.by_workers && o.levels.len() < levels)
            .then(|| Round::new(o.levels.len() as u32, shares(&prep.member_cores)));
    }
}

/// Each member's weight in measuring: its threads.
pub(crate) fn shares(cores: &[u32]) -> Vec<u32> {
    cores.iter().map(|&c| c.max(1)).collect()
}

impl Actor {
    /// Member `w`'s measurements of the level in progress: checked, and
    /// once every member's are in, merged, kept and sent to every member.
    pub(super) fn on_measured(&mut self, w: usize, c: MeasuredChunk) {
        // As encoded: the chunk and its one-byte variant tag (no copy of
        // the chunk to wrap it).
        let bytes = postcard::experimental::serialized_size(&c).map_or(0, |n| n as u64 + 1);
        let j = self.job.as_mut().expect("a member's job");
        let (Some(o), Some(round)) = (j.overture.as_mut(), j.attempt.round.as_mut()) else {
            let why = format!("worker {w} sent irradiance measurements no level waits for");
            return self.recover(Setback::Failed { w }, why);
        };
        // Counted as they come: a level cut short by a lost member still
        // cost its rays.
        o.bytes_gathered += bytes;
        o.rays += c.rays;
        let room = o.params.max_records.saturating_sub(o.records());
        let complete = match round.take(w, c, room) {
            Ok(c) => c,
            Err(e) => return self.recover(Setback::Failed { w }, format!("worker {w}: {e}")),
        };
        if !complete {
            return;
        }
        let mut round = j.attempt.round.take().expect("checked above");
        let (level, shares, slowest) = (
            round.level,
            std::mem::take(&mut round.shares),
            round.slowest,
        );
        let merged = match round.merge() {
            Ok(m) => Arc::new(m),
            Err(e) => return self.recover(Setback::Failed { w }, e),
        };
        o.seconds += slowest;
        o.levels.push(merged.clone());
        info!(
            job = j.id,
            level,
            records = merged.len(),
            seconds = slowest,
            "irradiance overture level measured"
        );
        if o.levels.len() < level_spacings(&o.params).len() {
            j.attempt.round = Some(Round::new(level + 1, shares));
        }
        let (run, sent) = (j.attempt.run, o.bytes_sent.clone());
        for w in j.attempt.members.iter().filter_map(|m| self.workers.get(m)) {
            let (tx, sent, merged) = (w.tx.clone(), sent.clone(), merged.clone());
            // A member gone meanwhile is recovered from; its sends fail.
            tokio::spawn(async move { send_levels(&tx, run, level, &[merged], &sent).await });
        }
    }
}
