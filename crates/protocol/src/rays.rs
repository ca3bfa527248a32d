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
    /// Random polling for hot regions (paper 003, section 5.2, offered
    /// to the render job): the sender has nothing to trace and asks for
    /// queries the receiver has queued.
    Poll,
    /// The answer to `Poll`: work the sender had queued, for the receiver
    /// to trace: `Trace` items, and camera samples whose answers go to
    /// the sender's slots. The receiver fetches the sender's leaves they
    /// cross rather than forward them back, so each hit is the one the
    /// owner would find.
    Handed {
        queries: Packet,
        samples: Vec<HandedSample>,
    },
    /// The answer to `Poll` from a worker with no queries to spare, with
    /// the workers it knows to be idle (so that the poller does not try
    /// them next).
    NoWork { idle: Vec<WorkerId> },
}

/// A camera sample handed over by random polling; its radiance goes to
/// the hander's `slot`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct HandedSample {
    pub x: u32,
    pub y: u32,
    pub sample: u32,
    pub slot: u32,
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
