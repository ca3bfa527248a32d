//! One node of a radiosity farm, as a state machine: messages in, messages
//! out through an [`Outbox`], no threads or sockets of its own.
//!
//! Per shot, the node's patches receive in rounds ([`Reception`]): each
//! round's receiving points are cut into sample packets of
//! [`PACKET_SAMPLES`], each with the processor vector of the ring positions
//! its rays cross. At most [`WINDOW`] of its packets are away at once; the
//! rest wait in a queue, which is what an idle node polling for work may
//! be handed. When every packet of a round is back the receptions advance
//! (lighting, subdivision) and make the next round; when none makes more,
//! the node's own work for the shot is done and it reports its receipts.

use locus_core::accel_set::AccelSet;
use locus_core::geometry::Ray;
use locus_core::radiosity::mesh::Patch;
use locus_core::radiosity::shoot::{
    Reception, Refine, RegionVisibility, Shooter, VisSample, Visibility,
};
use locus_core::radiosity::solve::patch_levels;
use locus_core::region::Route;
use locus_core::stats::TraceStats;
use locus_protocol::radiosity::{NodeDone, NodeId, SamplePacket, ToCoordinator, ToNode};
use std::collections::VecDeque;
use std::ops::ControlFlow;

/// Samples per packet, as in the paper's measurements.
pub const PACKET_SAMPLES: usize = 50;

/// A node's own packets away at once (in its ring or handed to a helper).
pub const WINDOW: usize = 8;

/// Where a node's messages go.
pub trait Outbox {
    fn to_node(&mut self, to: NodeId, msg: ToNode);
    fn to_coordinator(&mut self, msg: ToCoordinator);
    /// The links that broke and the messages lost on them, said when the
    /// node stalls (a lost packet or answer is the likely cause).
    fn lost(&self) -> Option<String> {
        None
    }
}

/// How the farm is laid out, the same on every node.
#[derive(Clone, Copy, Debug)]
pub struct Layout {
    pub nodes: u32,
    /// Ring length: regions per copy of the scene.
    pub ring: u32,
}

impl Layout {
    pub fn position(&self, n: NodeId) -> u32 {
        n % self.ring
    }

    pub fn ring_base(&self, n: NodeId) -> NodeId {
        n - n % self.ring
    }

    pub fn rings(&self) -> u32 {
        self.nodes / self.ring
    }
}

/// What a node is given for the whole job.
pub struct NodeSetup {
    pub id: NodeId,
    pub layout: Layout,
    /// The octree top collapsed by ring position.
    pub route: Route<u16>,
    /// The triangles of this node's region.
    pub region: AccelSet,
    /// The patches this node computes, by global index.
    pub patches: Vec<(u32, Patch)>,
    pub part_levels: u32,
    /// Random polling for packets of other rings when idle.
    pub dynamic: bool,
    /// Seed of the polling choices.
    pub seed: u64,
}

/// Each patch's two side levels after a shot, by patch.
pub type Snapshot = Vec<(u32, [f32; 2])>;

/// Which packet pieces belong to which reception: (reception, first
/// sample, samples).
type Pieces = Vec<(u32, u32, u32)>;

/// The current shot.
struct Shot {
    shooter: Shooter,
    refine: Refine,
    snapshot: bool,
}

pub struct Node {
    s: NodeSetup,
    iteration: u64,
    shot: Option<Shot>,
    receptions: Vec<Reception>,
    /// Own packets made but not yet sent.
    queue: VecDeque<SamplePacket>,
    /// Packets waiting for this node's region, own or not.
    local: VecDeque<SamplePacket>,
    pieces: Vec<Pieces>,
    /// Own packets away, and packets of the round not yet back.
    away: usize,
    round_left: usize,
    /// Own work of this shot is done.
    pub finished: bool,
    /// A poll sent and not answered; a packet routed for another node.
    polling: bool,
    helping: bool,
    known_idle: Vec<NodeId>,
    /// Polls to answer once this node has a packet to spare or is done.
    held_polls: Vec<NodeId>,
    /// Messages of a shot not yet announced here.
    early: Vec<ToNode>,
    rng: u64,
    pub stats: TraceStats,
    pub packets: u64,
    pub helped: u64,
    /// Per snapshot: each patch's two side levels.
    pub snapshots: Vec<Snapshot>,
}

impl Node {
    pub fn new(s: NodeSetup) -> Self {
        let rng = s.seed ^ (s.id as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        Self {
            s,
            iteration: 0,
            shot: None,
            receptions: Vec::new(),
            queue: VecDeque::new(),
            local: VecDeque::new(),
            pieces: Vec::new(),
            away: 0,
            round_left: 0,
            finished: true,
            polling: false,
            helping: false,
            known_idle: Vec::new(),
            held_polls: Vec::new(),
            early: Vec::new(),
            rng,
            stats: TraceStats::default(),
            packets: 0,
            helped: 0,
            snapshots: Vec::new(),
        }
    }

    pub fn id(&self) -> NodeId {
        self.s.id
    }

    pub fn iteration(&self) -> u64 {
        self.iteration
    }

    pub fn into_patches(self) -> (Vec<(u32, Patch)>, Vec<Snapshot>) {
        (self.s.patches, self.snapshots)
    }

    /// Handles one message. `Finish` is the caller's to handle.
    pub fn handle(&mut self, msg: ToNode, out: &mut dyn Outbox) {
        match msg {
            ToNode::Shoot {
                iteration,
                spec,
                refine,
                snapshot,
            } => {
                let shooter = Shooter::from_spec(&spec, self.s.part_levels);
                self.start(iteration, shooter, refine, snapshot, out);
            }
            ToNode::Packet(p) if p.iteration > self.iteration => self.early.push(ToNode::Packet(p)),
            ToNode::Packet(p) if p.iteration == self.iteration => self.forward(p, out),
            ToNode::Packet(_) => {
                debug_assert!(false, "a packet of a finished shot");
            }
            ToNode::Idle {
                iteration,
                from,
                idle,
            } => self.polled(iteration, from, idle, out),
            ToNode::Handoff(p) if p.iteration == self.iteration => {
                self.polling = false;
                self.helping = true;
                self.forward(p, out);
            }
            ToNode::Handoff(p) => {
                debug_assert!(
                    false,
                    "a handoff of shot {} in {}",
                    p.iteration, self.iteration
                );
            }
            ToNode::NoWork {
                iteration,
                from: _,
                idle,
            } => {
                if iteration == self.iteration && self.polling {
                    self.polling = false;
                    self.learn_idle(&idle);
                    self.poll(out);
                }
            }
            ToNode::Finish => {}
        }
    }

    fn start(
        &mut self,
        iteration: u64,
        shooter: Shooter,
        refine: Refine,
        snapshot: bool,
        out: &mut dyn Outbox,
    ) {
        debug_assert!(
            self.finished && self.away == 0,
            "a shot before the last ended"
        );
        self.iteration = iteration;
        self.finished = false;
        self.polling = false;
        self.helping = false;
        self.known_idle.clear();
        self.held_polls.clear();
        // The shooter's owner takes the unshot radiosity it shoots, as
        // the one-machine solver's `take_shooter` does.
        if let Some((_, p)) = self.s.patches.iter_mut().find(|(i, _)| *i == shooter.patch) {
            p.unshot[shooter.side] = Default::default();
        }
        self.receptions = self
            .s
            .patches
            .iter()
            .map(|(i, p)| Reception::start(p, *i, &shooter))
            .collect();
        self.shot = Some(Shot {
            shooter,
            refine,
            snapshot,
        });
        self.next_round(out);
        for m in std::mem::take(&mut self.early) {
            self.handle(m, out);
        }
    }

    /// Makes the next round's packets, advancing receptions that have no
    /// points to ask about, until some packet is out or all are done.
    fn next_round(&mut self, out: &mut dyn Outbox) {
        loop {
            if self.receptions.iter().all(Reception::is_done) {
                self.finish_shot(out);
                return;
            }
            self.make_packets();
            if self.round_left > 0 {
                self.pump(out);
                self.answer_held(out);
                return;
            }
            self.advance_all();
        }
    }

    fn advance_all(&mut self) {
        let Some(shot) = &self.shot else { return };
        for (r, (_, p)) in self.receptions.iter_mut().zip(&mut self.s.patches) {
            if !r.is_done() {
                r.advance(p, &shot.shooter, shot.refine);
            }
        }
    }

    /// Cuts the pending samples of all receptions into packets.
    fn make_packets(&mut self) {
        let Some(shot) = &self.shot else { return };
        self.pieces.clear();
        let mut samples: Vec<VisSample> = Vec::new();
        let mut pieces: Pieces = Vec::new();
        let mut packets = Vec::new();
        for (ri, r) in self.receptions.iter_mut().enumerate() {
            if r.is_done() {
                continue;
            }
            let own = r.samples_mut();
            let mut at = 0;
            while at < own.len() {
                let take = (PACKET_SAMPLES - samples.len()).min(own.len() - at);
                samples.extend_from_slice(&own[at..at + take]);
                pieces.push((ri as u32, at as u32, take as u32));
                at += take;
                if samples.len() == PACKET_SAMPLES {
                    packets.push((std::mem::take(&mut samples), std::mem::take(&mut pieces)));
                }
            }
        }
        if !samples.is_empty() {
            packets.push((samples, pieces));
        }
        self.round_left = packets.len();
        for (seq, (samples, pieces)) in packets.into_iter().enumerate() {
            let positions = positions(&self.s.route, self.s.layout, &shot.shooter, &samples);
            self.pieces.push(pieces);
            self.queue.push_back(SamplePacket {
                iteration: self.iteration,
                origin: self.s.id,
                seq: seq as u32,
                helper: None,
                positions,
                samples,
            });
        }
    }

    /// Sends queued packets while fewer than [`WINDOW`] are away.
    fn pump(&mut self, out: &mut dyn Outbox) {
        while self.away < WINDOW {
            let Some(p) = self.queue.pop_front() else {
                break;
            };
            self.away += 1;
            self.packets += 1;
            self.forward(p, out);
        }
    }

    /// Queues `p` for this node's region if its position is flagged and
    /// this node is in the routing ring; sends it on otherwise.
    fn forward(&mut self, p: SamplePacket, out: &mut dyn Outbox) {
        let base = self.s.layout.ring_base(p.router());
        let bit = 1u64 << self.s.layout.position(self.s.id);
        if self.s.layout.ring_base(self.s.id) == base && p.positions & bit != 0 {
            self.local.push_back(p);
        } else {
            self.send_on(p, out);
        }
    }

    /// Whether packets wait for this node's region.
    pub fn has_local_work(&self) -> bool {
        !self.local.is_empty()
    }

    /// Whether the next local step is visibility for a packet routed by a
    /// helper (dynamic balancing), for the time split.
    pub fn next_step_helps(&self) -> bool {
        self.local.front().is_some_and(|p| p.helper.is_some())
    }

    /// One packet's visibility through this node's region: one step, so
    /// that messages (polls above all) are answered between packets.
    pub fn step(&mut self, out: &mut dyn Outbox) {
        let Some(mut p) = self.local.pop_front() else {
            return;
        };
        if let Some(shot) = &self.shot {
            RegionVisibility(&self.s.region).resolve(
                &shot.shooter,
                &mut p.samples,
                &mut self.stats,
            );
        }
        p.positions &= !(1u64 << self.s.layout.position(self.s.id));
        self.send_on(p, out);
    }

    /// Sends `p` to the next flagged position of its ring, or home.
    fn send_on(&mut self, p: SamplePacket, out: &mut dyn Outbox) {
        let base = self.s.layout.ring_base(p.router());
        if p.positions != 0 {
            let next = base + p.positions.trailing_zeros();
            out.to_node(next, ToNode::Packet(p));
        } else if p.origin == self.s.id {
            self.land(p, out);
        } else if p.helper == Some(self.s.id) {
            self.helping = false;
            self.helped += 1;
            out.to_node(p.origin, ToNode::Packet(p));
            self.poll(out);
        } else {
            out.to_node(p.router(), ToNode::Packet(p));
        }
    }

    /// One of this node's packets is back: its bits go to the receptions.
    fn land(&mut self, p: SamplePacket, out: &mut dyn Outbox) {
        let mut at = 0usize;
        for &(r, first, len) in &self.pieces[p.seq as usize] {
            let dst = &mut self.receptions[r as usize].samples_mut()
                [first as usize..(first + len) as usize];
            dst.copy_from_slice(&p.samples[at..at + len as usize]);
            at += len as usize;
        }
        self.away -= 1;
        self.round_left -= 1;
        if self.round_left == 0 {
            self.advance_all();
            self.next_round(out);
        } else {
            self.pump(out);
        }
    }

    fn finish_shot(&mut self, out: &mut dyn Outbox) {
        self.finished = true;
        let mut receipts = Vec::new();
        for (r, (i, p)) in self.receptions.iter().zip(&mut self.s.patches) {
            let receipt = r.receipt;
            if receipt != Default::default() {
                p.book(&receipt);
                receipts.push((*i, receipt));
            }
        }
        self.receptions.clear();
        let snapshot = self.shot.as_ref().is_some_and(|s| s.snapshot);
        if snapshot {
            let levels = self.s.patches.iter().map(|(i, p)| (*i, patch_levels(p)));
            self.snapshots.push(levels.collect());
        }
        out.to_coordinator(ToCoordinator::Done(Box::new(NodeDone {
            node: self.s.id,
            iteration: self.iteration,
            receipts,
            candidate: candidate(&self.s.patches),
            stats: std::mem::take(&mut self.stats),
            packets: std::mem::take(&mut self.packets),
            helped: std::mem::take(&mut self.helped),
        })));
        self.learn_idle(&[self.s.id]);
        self.answer_held(out);
        self.poll(out);
    }

    fn learn_idle(&mut self, idle: &[NodeId]) {
        for &n in idle {
            if !self.known_idle.contains(&n) {
                self.known_idle.push(n);
            }
        }
    }

    /// Random polling: a finished node, not already polling or helping,
    /// asks a random node at its position in another ring, not known to be
    /// idle, for a packet.
    fn poll(&mut self, out: &mut dyn Outbox) {
        if !self.s.dynamic || !self.finished || self.polling || self.helping {
            return;
        }
        let l = self.s.layout;
        let pos = l.position(self.s.id);
        let candidates: Vec<NodeId> = (0..l.rings())
            .map(|r| r * l.ring + pos)
            .filter(|&n| n != self.s.id && !self.known_idle.contains(&n))
            .collect();
        if candidates.is_empty() {
            return;
        }
        // xorshift64: the choice only spreads polls, the result does not
        // depend on it.
        self.rng ^= self.rng << 13;
        self.rng ^= self.rng >> 7;
        self.rng ^= self.rng << 17;
        let to = candidates[(self.rng % candidates.len() as u64) as usize];
        self.polling = true;
        out.to_node(
            to,
            ToNode::Idle {
                iteration: self.iteration,
                from: self.s.id,
                idle: self.known_idle.clone(),
            },
        );
    }

    fn polled(&mut self, iteration: u64, from: NodeId, idle: Vec<NodeId>, out: &mut dyn Outbox) {
        if iteration > self.iteration {
            self.early.push(ToNode::Idle {
                iteration,
                from,
                idle,
            });
            return;
        }
        if iteration < self.iteration {
            out.to_node(
                from,
                ToNode::NoWork {
                    iteration,
                    from: self.s.id,
                    idle: Vec::new(),
                },
            );
            return;
        }
        self.learn_idle(&idle);
        if !self.held_polls.contains(&from) {
            self.held_polls.push(from);
        }
        self.answer_held(out);
    }

    /// Hands a queued packet to each held poll while there are some, or
    /// tells them this node is idle once it is.
    fn answer_held(&mut self, out: &mut dyn Outbox) {
        while !self.held_polls.is_empty() {
            if let Some(mut p) = self.queue.pop_back() {
                let to = self.held_polls.remove(0);
                p.helper = Some(to);
                self.away += 1;
                self.packets += 1;
                out.to_node(to, ToNode::Handoff(p));
            } else if self.finished {
                let to = self.held_polls.remove(0);
                out.to_node(
                    to,
                    ToNode::NoWork {
                        iteration: self.iteration,
                        from: self.s.id,
                        idle: self.known_idle.clone(),
                    },
                );
            } else {
                break;
            }
        }
    }
}

/// The ring positions whose regions the rays of `samples` cross: the
/// packet's processor vector.
fn positions(route: &Route<u16>, layout: Layout, shooter: &Shooter, samples: &[VisSample]) -> u64 {
    if layout.ring == 1 {
        return 1;
    }
    let all = if layout.ring >= 64 {
        u64::MAX
    } else {
        (1u64 << layout.ring) - 1
    };
    let mut mask = 0u64;
    for s in samples {
        let mut bits = s.bits;
        while bits != 0 && mask != all {
            let k = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            let seg = shooter.targets[k] - s.origin;
            let len = seg.length();
            if len.is_nan() || len <= 0.0 {
                continue;
            }
            let ray = Ray::new(s.origin, seg / len);
            let _ = route.walk(&ray, 0.0, len, f32::NEG_INFINITY, |label, _, _| {
                mask |= 1u64 << label;
                ControlFlow::Continue(())
            });
        }
    }
    mask
}

/// The patch side with the most unshot power (ties to the lowest index),
/// as the one-machine solver chooses among all patches.
fn candidate(patches: &[(u32, Patch)]) -> Option<(u32, u8, f64)> {
    let mut best: Option<(u32, u8, f64)> = None;
    for (i, p) in patches {
        for s in 0..2u8 {
            let w = p.unshot_power(s as usize);
            if w > 0.0 && best.is_none_or(|b| w > b.2) {
                best = Some((*i, s, w));
            }
        }
    }
    best
}
