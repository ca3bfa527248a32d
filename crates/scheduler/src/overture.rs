//! The irradiance cache's overture on the scheduler's side: the levels a
//! job knows (kept across its attempts), and the level its workers are
//! measuring, merged in candidate order once every member's share is in.
//! The wire side is `locus_protocol::overture`.

use locus_core::irradiance::IrradianceParams;
use locus_core::irradiance::overture::{Measured, measurer};
use locus_protocol::overture::{LevelChunk, MeasuredChunk, chunks};
use locus_protocol::report::IrradianceReport;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use tokio::sync::mpsc;

/// A job's overture: what outlives its attempts.
#[derive(Debug)]
pub struct Overture {
    pub params: IrradianceParams,
    /// The levels measured so far, each merged in candidate order.
    pub levels: Vec<Arc<Vec<Measured>>>,
    pub rays: u64,
    pub seconds: f64,
    pub by_workers: bool,
    pub bytes_gathered: u64,
    /// Counted by the tasks that send the levels.
    pub bytes_sent: Arc<AtomicU64>,
}

impl Overture {
    pub fn new(params: IrradianceParams) -> Self {
        Self {
            params,
            levels: Vec::new(),
            rays: 0,
            seconds: 0.0,
            by_workers: false,
            bytes_gathered: 0,
            bytes_sent: Arc::default(),
        }
    }

    pub fn records(&self) -> usize {
        self.levels.iter().map(|l| l.len()).sum()
    }

    pub fn report(&self) -> IrradianceReport {
        IrradianceReport {
            records: self.records() as u64,
            rays: self.rays,
            seconds: self.seconds,
            by_workers: self.by_workers,
            bytes_gathered: self.bytes_gathered,
            bytes_sent: self.bytes_sent.load(Ordering::Relaxed),
        }
    }
}

/// Sends `levels` (numbered from `first`) to one worker, chunk by chunk,
/// counting their encoded bytes in `sent`.
pub async fn send_levels(
    tx: &mpsc::Sender<locus_protocol::control::SchedulerToWorker>,
    job: u64,
    first: u32,
    levels: &[Arc<Vec<Measured>>],
    sent: &AtomicU64,
) -> Result<(), mpsc::error::SendError<locus_protocol::control::SchedulerToWorker>> {
    use locus_protocol::control::SchedulerToWorker;
    for (k, level) in levels.iter().enumerate() {
        for (records, last) in chunks(level) {
            let msg = SchedulerToWorker::Level(Box::new(LevelChunk {
                job,
                level: first + k as u32,
                records,
                last,
            }));
            let n = postcard::experimental::serialized_size(&msg).unwrap_or(0);
            tx.send(msg).await?;
            sent.fetch_add(n as u64, Ordering::Relaxed);
        }
    }
    Ok(())
}

/// The level an attempt's members are measuring.
#[derive(Debug)]
pub struct Round {
    pub level: u32,
    /// Each member's weight (its threads), as its setup said.
    pub shares: Vec<u32>,
    got: Vec<(u32, Measured)>,
    done: Vec<bool>,
    /// The slowest member's seconds so far.
    pub slowest: f64,
}

impl Round {
    pub fn new(level: u32, shares: Vec<u32>) -> Self {
        Self {
            level,
            got: Vec::new(),
            done: vec![false; shares.len()],
            shares,
            slowest: 0.0,
        }
    }

    /// Takes member `w`'s chunk of a job that has room for `room` more
    /// records; true when every member's share is in. An error names what
    /// is wrong with the chunk.
    pub fn take(&mut self, w: usize, c: MeasuredChunk, room: usize) -> Result<bool, String> {
        if c.level != self.level {
            return Err(format!(
                "measurements of overture level {} while level {} is measured",
                c.level, self.level
            ));
        }
        if self.done.get(w) != Some(&false) {
            return Err(format!(
                "measurements of overture level {} after its last",
                c.level
            ));
        }
        if self.got.len() + c.records.len() > room {
            return Err(format!(
                "more overture measurements than the {room} records left"
            ));
        }
        for (i, m) in &c.records {
            if measurer(*i, &self.shares) != w {
                return Err(format!("overture candidate {i} is another worker's"));
            }
            m.check()?;
        }
        self.got.extend(c.records);
        if c.last {
            self.done[w] = true;
            self.slowest = self.slowest.max(c.seconds);
        }
        Ok(self.done.iter().all(|&d| d))
    }

    /// The level in candidate order, once every share is in: its indices
    /// must be exactly `0..n` (each candidate measured once, none left).
    pub fn merge(mut self) -> Result<Vec<Measured>, String> {
        self.got.sort_by_key(|(i, _)| *i);
        if let Some((k, (i, _))) = (0u32..).zip(&self.got).find(|(k, (i, _))| k != i) {
            return Err(format!(
                "overture level {}: candidate {k} is missing or measured twice (found {i})",
                self.level
            ));
        }
        Ok(self.got.into_iter().map(|(_, m)| m).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use locus_core::irradiance::hemisphere::Estimate;

    fn m(x: f32) -> Measured {
        Measured {
            p: Vec3::splat(x),
            n: Vec3::Z,
            footprint: 0.01,
            est: Estimate {
                e: Vec3::ONE,
                harmonic: 1.0,
                grad_t: [Vec3::ZERO; 3],
                grad_r: [Vec3::ZERO; 3],
            },
        }
    }

    fn chunk(level: u32, records: Vec<(u32, Measured)>, last: bool) -> MeasuredChunk {
        MeasuredChunk {
            job: 1,
            level,
            records,
            last,
            rays: 10,
            seconds: 0.5,
        }
    }

    fn share(w: usize, n: u32, shares: &[u32]) -> Vec<(u32, Measured)> {
        (0..n)
            .filter(|&i| measurer(i, shares) == w)
            .map(|i| (i, m(i as f32)))
            .collect()
    }

    #[test]
    fn a_level_merges_in_candidate_order_once_every_share_is_in() {
        let shares = [1, 3];
        let mut r = Round::new(2, shares.to_vec());
        let (a, b) = (share(0, 11, &shares), share(1, 11, &shares));
        let (b1, b2) = b.split_at(4);
        assert!(!r.take(1, chunk(2, b1.to_vec(), false), 100).unwrap());
        assert!(!r.take(0, chunk(2, a, true), 100).unwrap());
        assert!(r.take(1, chunk(2, b2.to_vec(), true), 100).unwrap());
        assert_eq!(r.slowest, 0.5);
        let level = r.merge().unwrap();
        let xs: Vec<f32> = level.iter().map(|m| m.p.x).collect();
        assert_eq!(xs, (0..11).map(|i| i as f32).collect::<Vec<_>>());
    }

    #[test]
    fn a_bad_share_is_refused_with_a_reason() {
        let shares = [1, 1];
        let round = || Round::new(0, shares.to_vec());
        let wrong_level = round().take(0, chunk(1, vec![], true), 9);
        assert!(wrong_level.unwrap_err().contains("level 1"));
        let theirs = round().take(0, chunk(0, vec![(1, m(1.0))], true), 9);
        assert!(theirs.unwrap_err().contains("another worker's"));
        let mut r = round();
        r.take(0, chunk(0, vec![], true), 9).unwrap();
        let twice = r.take(0, chunk(0, vec![], true), 9);
        assert!(twice.unwrap_err().contains("after its last"));
        let full = round().take(0, chunk(0, share(0, 8, &shares), true), 3);
        assert!(full.unwrap_err().contains("records left"));
        let mut nan = m(0.0);
        nan.est.e.x = f32::NAN;
        let bad = round().take(0, chunk(0, vec![(0, nan)], true), 9);
        assert!(bad.is_err());
        // Candidate 2 (worker 0's) never came.
        let mut gap = round();
        gap.take(0, chunk(0, vec![(0, m(0.0))], true), 9).unwrap();
        gap.take(1, chunk(0, vec![(1, m(1.0)), (3, m(3.0))], true), 9)
            .unwrap();
        assert!(gap.merge().unwrap_err().contains("candidate 2"));
    }
}
