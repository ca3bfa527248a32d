//! The irradiance cache's overture on the farm (part of the [`control`]
//! family): how a job's records are set up, measured by the workers and
//! shared.
//!
//! Ward's records are placed level by level, coarse to fine, each level
//! against the levels before it only (`locus_core::irradiance::overture`).
//! Where every worker holds the whole scene, the workers measure a level's
//! candidates between them ([`IrradianceSetup::shares`]): each sends its
//! measurements up ([`MeasuredChunk`]); the scheduler checks and merges
//! them in candidate order and sends the whole level to every worker
//! ([`LevelChunk`]), which adds it and goes on to the next. Where they do
//! not, the scheduler measures every level itself, and workers only
//! receive. Levels already measured in an earlier attempt of the job are
//! sent before the worker measures anything ([`IrradianceSetup::known`]),
//! so a worker lost mid-overture costs only the level in progress.
//!
//! [`control`]: crate::control

use locus_core::geometry::Bounds;
use locus_core::irradiance::IrradianceParams;
use locus_core::irradiance::overture::{Measured, level_spacings};
use serde::{Deserialize, Serialize};

/// Measurements per chunk, either way: about 2 MB, well within a frame
/// whatever `max_records` allows.
pub const CHUNK: usize = 16_384;

/// A job's irradiance cache, in its setup.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IrradianceSetup {
    pub params: IrradianceParams,
    /// The scene's bounds: the record octree's, as on one machine.
    pub bounds: Bounds,
    /// Levels the scheduler sends before the worker measures: all of them
    /// when the workers do not hold the whole scene.
    pub known: u32,
    /// Each member's weight in measuring a level (its threads), indexed by
    /// worker id.
    pub shares: Vec<u32>,
}

impl IrradianceSetup {
    /// The overture's number of levels.
    pub fn levels(&self) -> u32 {
        level_spacings(&self.params).len() as u32
    }

    /// Whether this worker measures any level.
    pub fn measures(&self) -> bool {
        self.known < self.levels()
    }

    /// Checks a setup for a job of `members` workers.
    pub fn check(&self, members: usize) -> Result<(), String> {
        self.params.check()?;
        if self.known > self.levels() {
            return Err(format!(
                "{} known levels of an overture of {}",
                self.known,
                self.levels()
            ));
        }
        if self.shares.len() != members || self.shares.iter().all(|&s| s == 0) {
            return Err(format!(
                "{} irradiance shares for {members} workers",
                self.shares.len()
            ));
        }
        let finite = self.bounds.min.is_finite() && self.bounds.max.is_finite();
        if !(finite || self.bounds.is_empty()) {
            return Err("the irradiance cache's bounds are not finite".into());
        }
        Ok(())
    }
}

/// Part of one level, merged, from the scheduler to a worker.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LevelChunk {
    pub job: u64,
    pub level: u32,
    pub records: Vec<Measured>,
    /// The level's last chunk.
    pub last: bool,
}

/// Part of one worker's measurements of a level, each with its candidate
/// index, from a worker to the scheduler.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MeasuredChunk {
    pub job: u64,
    pub level: u32,
    pub records: Vec<(u32, Measured)>,
    /// The worker's last chunk of the level; it carries the level's rays
    /// and seconds.
    pub last: bool,
    /// Rays the worker traced for the level: its candidates and its
    /// measurements.
    pub rays: u64,
    /// The worker's seconds on the level.
    pub seconds: f64,
}

/// Splits a level into chunks of at most [`CHUNK`] (one, possibly empty,
/// for an empty level), the last one marked.
pub fn chunks<T: Clone>(records: &[T]) -> impl Iterator<Item = (Vec<T>, bool)> + '_ {
    let n = records.len().div_ceil(CHUNK).max(1);
    (0..n).map(move |k| {
        let part = &records[(k * CHUNK).min(records.len())..((k + 1) * CHUNK).min(records.len())];
        (part.to_vec(), k + 1 == n)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunks_cover_a_level_once_and_mark_its_end() {
        for n in [0usize, 1, CHUNK - 1, CHUNK, CHUNK + 1, 3 * CHUNK + 7] {
            let v: Vec<u32> = (0..n as u32).collect();
            let parts: Vec<_> = chunks(&v).collect();
            assert_eq!(parts.len(), n.div_ceil(CHUNK).max(1), "{n}");
            assert!(parts.iter().all(|(c, _)| c.len() <= CHUNK));
            let lasts: Vec<bool> = parts.iter().map(|(_, l)| *l).collect();
            assert_eq!(lasts.iter().filter(|&&l| l).count(), 1);
            assert!(*lasts.last().unwrap());
            let joined: Vec<u32> = parts.into_iter().flat_map(|(c, _)| c).collect();
            assert_eq!(joined, v);
        }
    }

    #[test]
    fn a_setup_is_checked_against_its_job() {
        let ok = IrradianceSetup {
            params: IrradianceParams::default(),
            bounds: Bounds::new(glam::Vec3::ZERO, glam::Vec3::ONE),
            known: 0,
            shares: vec![2, 2],
        };
        assert!(ok.check(2).is_ok());
        assert!(ok.measures());
        assert!(ok.check(3).is_err());
        let all_known = IrradianceSetup {
            known: ok.levels(),
            ..ok.clone()
        };
        assert!(all_known.check(2).is_ok() && !all_known.measures());
        let past = IrradianceSetup {
            known: ok.levels() + 1,
            ..ok.clone()
        };
        assert!(past.check(2).is_err());
        let nan = IrradianceSetup {
            bounds: Bounds::new(glam::Vec3::ZERO, glam::Vec3::splat(f32::NAN)),
            ..ok
        };
        assert!(nan.check(2).is_err());
    }
}
