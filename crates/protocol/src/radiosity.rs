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

use locus_core::geometry::TriangleSet;
use locus_core::radiosity::mesh::Patch;
use locus_core::radiosity::shoot::{Receipt, Refine, ShotSpec, VisSample};
use locus_core::radiosity::{Ledger, RadiosityParams, Record};
use locus_core::region::ProcessorMap;
use locus_core::stats::TraceStats;
use serde::{Deserialize, Serialize};

/// Which of the paper's load balancing schemes a farm uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
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

/// A radiosity job as a client asks for it (`locus submit --kind
/// radiosity`): the scheduler coordinates, the job's workers are its nodes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RadiosityJob {
    pub params: RadiosityParams,
    /// Ring length R (0: one ring of all the job's workers).
    pub ring: u32,
    pub balance: Balance,
    /// Samples per pixel of the image rendered from the solution.
    pub spp: u32,
}

/// How a radiosity job on the farm went, beside its image and mesh.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RadiosityReport {
    pub params: RadiosityParams,
    pub nodes: u32,
    pub ring: u32,
    pub balance: Balance,
    pub patches: u64,
    pub elements: u64,
    pub vertices: u64,
    pub iterations: u64,
    /// Why iteration stopped.
    pub stopped: String,
    pub unshot_fraction: f64,
    pub ledger: Ledger,
    pub convergence: Vec<Record>,
    pub visibility_rays: u64,
    /// Packets sent around rings, and those routed by a helper's ring.
    pub packets: u64,
    pub helped: u64,
    /// Per node, summed over shots: CPU seconds working, of which helping
    /// other rings, and seconds waiting or idle.
    pub node_times: Vec<NodeTime>,
    pub mesh_s: f64,
    pub solve_s: f64,
    pub image_s: f64,
    /// Attempts the job took (one more per worker lost), and the workers
    /// lost; the solution is the same bits either way.
    pub attempts: u32,
    pub lost: Vec<String>,
    /// The meshed solution (each corner's position and radiance): it
    /// travels in [`crate::submit::SchedulerToClient::Mesh`] runs, not in
    /// the report, and the client puts it here.
    #[serde(skip)]
    pub mesh: Vec<[(glam::Vec3, glam::Vec3); 3]>,
}

/// A worker's part in a radiosity job: it is node `me` of `nodes`, in
/// rings of `ring`, holding the region of its ring position and the
/// patches it computes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NodeJob {
    /// The run id the job's messages carry.
    pub job: u64,
    pub me: NodeId,
    /// Every node's listen address, by node id.
    pub peers: Vec<String>,
    pub ring: u32,
    /// The octree top with each leaf's ring position as its owner.
    pub map: ProcessorMap,
    /// The triangles of this node's ring position.
    pub region: TriangleSet,
    /// Largest coordinate of the scene, for BVH padding.
    pub magnitude: f32,
    /// The patches this node computes, by global index, as meshed.
    pub patches: Vec<(u32, Patch)>,
    pub part_levels: u32,
    /// Random polling for packets of other rings.
    pub dynamic: bool,
    pub seed: u64,
    /// A node with no message for this long gives up.
    pub stall_ms: u64,
}

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
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
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
    /// After `Finish`, a node's patches as they are now and (in the last
    /// run) its snapshots: in runs, so that no message outgrows a frame.
    End {
        node: NodeId,
        patches: Vec<(u32, Patch)>,
        snapshots: Vec<Vec<(u32, [f32; 2])>>,
        last: bool,
    },
}
