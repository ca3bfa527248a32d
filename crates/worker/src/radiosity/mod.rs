//! Progressive refinement radiosity on a farm (Stürzlinger, Schaufler and
//! Volkert, sections 2-5).
//!
//! The scene is held in rings: each ring of `R` nodes holds it once, one
//! region per ring position, and every node computes the patches it is
//! given. [`node`] is one node as a state machine (its patches' rounds of
//! sample packets, the ring that computes their visibility, random polling
//! for packets of other rings when it is idle); [`farm`] runs nodes on
//! threads in one process with the coordinator on the caller's thread.
//! This module spreads patches over nodes: equal numbers of patches (no
//! balancing) or equal numbers of elements (static balancing).

pub mod farm;
pub mod node;

use locus_core::radiosity::Solver;

/// Which of the paper's load balancing schemes a farm uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Balance {
    /// Equal numbers of patches per node, regions of equal leaf counts.
    None,
    /// Equal numbers of elements per node (section 4.1), regions of equal
    /// predicted tracing cost (section 4.2).
    Static,
    /// Random polling for sample packets (section 5.2) only.
    Dynamic,
    /// Static and dynamic together.
    Both,
}

impl Balance {
    pub const ALL: [Balance; 4] = [
        Balance::None,
        Balance::Static,
        Balance::Dynamic,
        Balance::Both,
    ];

    pub fn is_static(self) -> bool {
        matches!(self, Balance::Static | Balance::Both)
    }

    pub fn is_dynamic(self) -> bool {
        matches!(self, Balance::Dynamic | Balance::Both)
    }

    pub fn name(self) -> &'static str {
        match self {
            Balance::None => "none",
            Balance::Static => "static",
            Balance::Dynamic => "dynamic",
            Balance::Both => "both",
        }
    }
}

/// Each patch's node: contiguous runs of patches (in index order, which
/// keeps a scene triangle's patches together) cut so that each node gets
/// an equal share of patches, or with `by_elements` of elements.
pub fn assign_patches(solver: &Solver, nodes: u32, by_elements: bool) -> Vec<u32> {
    let weight: Vec<f64> = solver
        .patches
        .iter()
        .map(|p| {
            if by_elements {
                p.leaves().len() as f64
            } else {
                1.0
            }
        })
        .collect();
    let total: f64 = weight.iter().sum();
    let share = total / nodes.max(1) as f64;
    let mut acc = 0.0;
    weight
        .iter()
        .map(|&w| {
            // A patch goes to the share its weight's midpoint falls in.
            let node = ((acc + 0.5 * w) / share) as u32;
            acc += w;
            node.min(nodes.saturating_sub(1))
        })
        .collect()
}
