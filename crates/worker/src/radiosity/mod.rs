//! Progressive refinement radiosity on a farm (Stürzlinger, Schaufler and
//! Volkert, sections 2-5).
//!
//! The scene is held in rings: each ring of `R` nodes holds it once, one
//! region per ring position, and every node computes the patches it is
//! given. [`node`] is one node as a state machine (its patches' rounds of
//! sample packets, the ring that computes their visibility, random polling
//! for packets of other rings when it is idle) and [`runner`] its loop;
//! [`coordinator`] chooses shooters and books receipts over any
//! [`coordinator::NodeLinks`]. [`farm`] runs nodes on threads in one
//! process with the coordinator on the caller's thread; [`daemon`] runs a
//! worker daemon's node, linked to the other workers' nodes, for a
//! coordinator in the scheduler.
//! This module spreads patches over nodes: equal numbers of patches (no
//! balancing) or equal numbers of elements (static balancing).

pub mod coordinator;
pub mod daemon;
pub mod farm;
pub mod node;
pub mod runner;

use locus_core::radiosity::Solver;

pub use locus_protocol::radiosity::Balance;

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
