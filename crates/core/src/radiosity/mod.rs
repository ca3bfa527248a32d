//! Progressive refinement radiosity (Stürzlinger, Schaufler and Volkert,
//! *Load Balancing for a Parallel Radiosity Algorithm*, sections 1-3): the
//! second kind of job locus runs.
//!
//! Every scene triangle is split into patches, the shooters, and each patch
//! is meshed into elements whose corners carry radiosity on both sides
//! ([`mesh`]). Each iteration the patch side
//! with the most unshot power shoots it ([`solve`](mod@solve)): every other patch
//! receives, at each of its corners, the analytic form factor
//! ([`formfactor`]) of the shooter's visible parts (M of them, 16 or 64,
//! one visibility ray each), splits elements whose corners now differ by
//! more than a threshold, and keeps what it reflects as its own unshot
//! radiosity ([`shoot`]). Iteration stops when the unshot power falls
//! below a fraction of the emitted power. [`output`] renders the solution
//! from the scene's camera and writes the meshed solution as a PLY.
//!
//! A receiving patch needs only the shooter and visibility answers, so a
//! farm spreads patches over workers and answers visibility through its
//! regions; the solution does not depend on that spread.

pub mod formfactor;
pub mod mesh;
pub mod output;
pub mod shoot;
pub mod solve;

pub use solve::{Convergence, Ledger, LocalShots, Record, Shots, Solver, solve, solve_with};

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// What a radiosity solution is computed with.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RadiosityParams {
    /// Scene triangles are split into patches (the shooters, whose unshot
    /// radiosity is one value) with edges at most the scene's largest
    /// extent divided by this: a whole floor shooting its mean radiosity
    /// would send light from its shadowed parts as well.
    pub patches: u32,
    /// The initial mesh: patches are split until no element edge is longer
    /// than the scene's largest extent divided by this.
    pub mesh: u32,
    /// Adaptive subdivision levels allowed below the initial mesh.
    pub subdivide: u32,
    /// Split an element when its corners' radiosity differs by more than
    /// this fraction of their mean.
    pub threshold: f32,
    /// Parts of the shooter whose visibility is sampled (M: 1, 4, 16, 64).
    pub shooter_parts: u32,
    /// Stop when the unshot power is below this fraction of the emitted.
    pub stop: f64,
    pub max_iterations: u64,
    /// Elements the whole solution may hold.
    pub max_elements: u64,
}

impl Default for RadiosityParams {
    fn default() -> Self {
        Self::DEFAULT
    }
}

impl RadiosityParams {
    /// The defaults, as a constant so the command line can show them.
    pub const DEFAULT: Self = Self {
        patches: 2,
        mesh: 8,
        subdivide: 2,
        threshold: 0.5,
        shooter_parts: 16,
        stop: 1e-3,
        max_iterations: 1_000_000,
        max_elements: 4_000_000,
    };

    /// A coarse solve that still exercises every part (patches, elements,
    /// adaptive subdivision) and finishes in a fraction of a second on the
    /// Cornell box: what the farm tests compare one machine with.
    pub const COARSE: Self = Self {
        mesh: 4,
        stop: 3e-2,
        ..Self::DEFAULT
    };
}

/// Finest lattice a patch may use: `2^30` divisions per edge still fits
/// the lattice's `u32` coordinates with room for a midpoint sum.
pub const MAX_LEVELS: u32 = 30;

impl RadiosityParams {
    /// Rejects settings that cannot work or would not finish.
    pub fn check(&self) -> Result<(), RadiosityError> {
        let bad = |what: &str| Err(RadiosityError::Invalid(what.to_string()));
        if !(1..=65_536).contains(&self.patches) {
            return bad("patches must be between 1 and 65536 divisions of the scene's extent");
        }
        if !(1..=65_536).contains(&self.mesh) {
            return bad("mesh must be between 1 and 65536 divisions of the scene's extent");
        }
        if self.subdivide > 12 {
            return bad("subdivide must be at most 12 levels");
        }
        if !(self.threshold.is_finite() && self.threshold > 0.0) {
            return bad("threshold must be a positive number");
        }
        if ![1, 4, 16, 64].contains(&self.shooter_parts) {
            return bad("shooter parts must be 1, 4, 16 or 64");
        }
        if !(self.stop > 0.0 && self.stop < 1.0) {
            return bad("stop must be a fraction between 0 and 1 (exclusive)");
        }
        if self.max_iterations == 0 || self.max_iterations > 100_000_000 {
            return bad("max iterations must be between 1 and 100000000");
        }
        if self.max_elements == 0 || self.max_elements > 1 << 32 {
            return bad("max elements must be between 1 and 2^32");
        }
        Ok(())
    }

    /// Levels of midpoint subdivision of the shooter into `shooter_parts`.
    pub fn part_levels(&self) -> u32 {
        self.shooter_parts.trailing_zeros() / 2
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RadiosityError {
    #[error("{0}")]
    Invalid(String),
    #[error("{scene}: no material emits light, so radiosity has nothing to shoot")]
    NoEmitter { scene: PathBuf },
    #[error("{scene}: triangle {triangle} has zero area and cannot be a patch")]
    ZeroArea { scene: PathBuf, triangle: usize },
    #[error(
        "{scene}: the initial mesh needs {needed} elements, more than the limit of {limit} (use a coarser --mesh or raise --max-elements)"
    )]
    TooManyElements {
        scene: PathBuf,
        needed: u64,
        limit: u64,
    },
}
