//! Worker to worker: ray queries travelling along their processor vector
//! and the answers travelling back to where each query started.
//!
//! A `Trace` item asks its receiver to trace the run of its own leaves that
//! starts at `resume` on the query's ray; the receiver either answers
//! (`Answer` to `reply`), shades a hit it found (spawning child queries of
//! its own) or forwards the item unchanged but for `resume` to the next
//! owner. Rays travel with their exact bits.

pub use crate::packet::Packet;
pub use locus_core::path::{Answer, Query};
use locus_core::region::{Resume, WorkerId};
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum PeerMsg {
    /// First message on a peer link, after the handshake.
    Hello { job: u64, from: WorkerId },
    /// Ray items in the compact encoding of [`crate::packet`].
    Packet(Packet),
    /// Demand-driven: send me the geometry of these leaves of yours.
    Fetch(Vec<u32>),
    /// The answer to `Fetch`: one leaf's triangles.
    Leaf(Box<LeafGeometry>),
    /// A radiosity job's message between nodes (sample packets, polls).
    Node(Box<crate::radiosity::ToNode>),
}

/// A leaf's triangles as its owner holds them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LeafGeometry {
    pub leaf: u32,
    pub geometry: locus_core::geometry::TriangleSet,
}

/// Where an answer goes: the pending slot of the worker that asked.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ReplyTo {
    pub worker: WorkerId,
    pub slot: u32,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum RayItem {
    Trace {
        query: Query,
        /// Where on the ray the receiver's run begins (`-inf` for a query
        /// not yet routed), and how far it is known to lie in the
        /// receiver's leaves.
        resume: Resume,
        reply: ReplyTo,
    },
    Answer {
        to: u32,
        answer: Answer,
    },
}
