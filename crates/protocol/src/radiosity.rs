//! The radiosity job's messages (Stürzlinger, Schaufler and Volkert,
//! sections 2-5): the coordinator tells every node the shot, nodes pass
//! sample packets around their ring of region owners, idle nodes poll for
//! packets of other rings, and each node reports what its patches received.
//!
//! A farm of `N` nodes is cut into rings of `R` consecutive nodes; each
//! ring holds the whole scene, one region per ring position, so node `n`
//! is position `n % R` of ring `n / R`. A packet's processor vector names
//! ring positions: it visits the node at each flagged position of the ring
//! that routes it, which is its origin's ring or, when an idle node took
//! it by random polling, the helper's.

use locus_core::radiosity::shoot::{Receipt, Refine, ShotSpec, VisSample};
use locus_core::stats::TraceStats;
use serde::{Deserialize, Serialize};

/// Node index in the farm.
pub type NodeId = u32;

/// Samples whose visibility a ring is computing.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SamplePacket {
    pub iteration: u64,
    /// The node whose elements the samples light; it gets the packet back.
    pub origin: NodeId,
    /// The origin's number for this packet within its round.
    pub seq: u32,
    /// The node routing the packet through its own ring for the origin
    /// (dynamic load balancing), if any.
    pub helper: Option<NodeId>,
    /// Ring positions still to visit (bit `k`: position `k`).
    pub positions: u64,
    pub samples: Vec<VisSample>,
}

impl SamplePacket {
    /// The node that routes this packet: its ring is the one visited.
    pub fn router(&self) -> NodeId {
        self.helper.unwrap_or(self.origin)
    }
}

/// To a node.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ToNode {
    /// Receive this shot. With `snapshot`, keep the patches' mean
    /// radiosity after it for the error series.
    Shoot {
        iteration: u64,
        spec: ShotSpec,
        refine: Refine,
        snapshot: bool,
    },
    /// A packet to process here (its position is flagged), or coming home
    /// to its router or origin once every position has seen it.
    Packet(SamplePacket),
    /// Random polling: `from` has finished its own packets of `iteration`;
    /// `idle` are the nodes it knows to be finished too.
    Idle {
        iteration: u64,
        from: NodeId,
        idle: Vec<NodeId>,
    },
    /// The answer to `Idle` from a node with packets to spare: route this
    /// one through your ring and send it back.
    Handoff(SamplePacket),
    /// The answer to `Idle` from a node with none: the nodes it knows to
    /// be finished (itself among them when it is).
    NoWork {
        iteration: u64,
        from: NodeId,
        idle: Vec<NodeId>,
    },
    /// Iteration is over: send the patches and the snapshots back.
    Finish,
}

/// A node's time in one iteration, split the way the paper's tables need.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NodeTime {
    /// Seconds computing: samples, form factors, visibility, subdivision.
    pub work_s: f64,
    /// Of which visibility for packets of other rings (dynamic balancing).
    pub helping_s: f64,
    /// Seconds waiting for messages while the node's own packets were out.
    pub waiting_s: f64,
    /// Seconds from finishing its own packets to the next shot (or the
    /// end), minus any helping.
    pub idle_s: f64,
}

/// What a node's patches received from one shot.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NodeDone {
    pub node: NodeId,
    pub iteration: u64,
    /// Receipts of the node's patches that received anything, by patch.
    pub receipts: Vec<(u32, Receipt)>,
    /// The node's patch side with the most unshot power after booking:
    /// (patch, side, power); the shooter is the maximum over nodes.
    pub candidate: Option<(u32, u8, f64)>,
    pub stats: TraceStats,
    /// Packets this node sent around its ring, and those it routed for
    /// other nodes.
    pub packets: u64,
    pub helped: u64,
}

/// To the coordinator.
#[derive(Debug, Serialize, Deserialize)]
pub enum ToCoordinator {
    Done(Box<NodeDone>),
    /// The time a node spent in an iteration, sent when the next shot (or
    /// the end) arrives, since idle time runs until then.
    Time {
        node: NodeId,
        iteration: u64,
        time: NodeTime,
    },
    Failed {
        node: NodeId,
        reason: String,
    },
}
