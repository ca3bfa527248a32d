//! The coordinator of a radiosity farm, whatever carries its messages:
//! threads in one process ([`super::farm`]) or the scheduler's links to
//! worker daemons. It is the [`Shots`] of the core's solve loop.
//!
//! The coordinator keeps each patch's shell (area, albedo, unshot power),
//! chooses the shooter, tells every node, waits for every node's receipts
//! and books them in patch order, exactly as one machine does; so the
//! solution is the one machine's, bit for bit, whatever the layout and
//! balancing. Every node finishing its own packets ends a shot: a packet in
//! flight belongs to a node that has not finished (it waits for it), so
//! when all have, none is left anywhere. At the end each node sends its
//! patches back in runs ([`ToCoordinator::End`]).

use locus_core::radiosity::shoot::Receipt;
use locus_core::radiosity::{Shots, Solver};
use locus_protocol::radiosity::{NodeId, NodeTime, ToCoordinator, ToNode};
use std::time::{Duration, Instant};

/// How the coordinator reaches its nodes.
pub trait NodeLinks {
    fn nodes(&self) -> usize;
    /// Sends to node `n`; false when it is gone.
    fn send(&mut self, n: NodeId, msg: ToNode) -> bool;
    /// The next message from any node, or why none came within `wait`.
    fn recv(&mut self, wait: Duration) -> Result<ToCoordinator, String>;
}

/// What the farm measured, per shot and node.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct FarmTimes {
    /// `times[shot][node]`.
    pub times: Vec<Vec<NodeTime>>,
    /// Packets sent around rings, and those routed by a helper's ring.
    pub packets: u64,
    pub helped: u64,
    /// Seconds from each shot's announcement to its last receipt.
    pub shot_s: Vec<f64>,
}

impl FarmTimes {
    /// Each node's times summed over the shots.
    pub fn per_node(&self) -> Vec<NodeTime> {
        let n = self.times.iter().map(Vec::len).max().unwrap_or(0);
        let mut sum = vec![NodeTime::default(); n];
        for shot in &self.times {
            for (s, t) in sum.iter_mut().zip(shot) {
                s.work_s += t.work_s;
                s.helping_s += t.helping_s;
                s.waiting_s += t.waiting_s;
                s.idle_s += t.idle_s;
            }
        }
        sum
    }
}

pub struct Coordinator<L> {
    pub links: L,
    /// A shot with no word from some node for this long fails.
    stall: Duration,
    iteration: u64,
    pub measured: FarmTimes,
    /// Why the farm stopped early, if it did.
    pub error: Option<String>,
}

/// Whether candidate `a` beats `b`: more power, then the lower patch and
/// side, the order in which one machine scans patches.
fn better(a: (u32, u8, f64), b: Option<(u32, u8, f64)>) -> bool {
    b.is_none_or(|b| a.2 > b.2 || (a.2 == b.2 && (a.0, a.1) < (b.0, b.1)))
}

impl<L: NodeLinks> Coordinator<L> {
    pub fn new(links: L, stall: Duration) -> Self {
        Self {
            links,
            stall,
            iteration: 0,
            measured: FarmTimes::default(),
            error: None,
        }
    }

    fn fail(&mut self, why: String) -> bool {
        self.error.get_or_insert(why);
        false
    }

    fn record_time(&mut self, node: NodeId, iteration: u64, time: NodeTime) {
        let nodes = self.links.nodes();
        let (Some(shot), true) = ((iteration as usize).checked_sub(1), (node as usize) < nodes)
        else {
            return;
        };
        while self.measured.times.len() <= shot {
            self.measured.times.push(vec![NodeTime::default(); nodes]);
        }
        self.measured.times[shot][node as usize] = time;
    }

    /// Every node's receipts of the current shot, booked by patch, and the
    /// best of their candidates for the next; false when the farm failed.
    fn gather(
        &mut self,
        solver: &mut Solver,
        receipts: &mut [Receipt],
        best: &mut Option<(u32, u8, f64)>,
    ) -> bool {
        let nodes = self.links.nodes();
        let mut done = vec![false; nodes];
        let mut left = nodes;
        while left > 0 {
            match self.links.recv(self.stall) {
                Ok(ToCoordinator::Done(d))
                    if d.iteration == self.iteration
                        && done.get(d.node as usize) == Some(&false) =>
                {
                    for (i, r) in d.receipts {
                        let Some(slot) = receipts.get_mut(i as usize) else {
                            return self.fail(format!("node {} names patch {i}", d.node));
                        };
                        *slot = r;
                    }
                    if let Some(c) = d.candidate
                        && better(c, *best)
                    {
                        *best = Some(c);
                    }
                    solver.stats += d.stats;
                    self.measured.packets += d.packets;
                    self.measured.helped += d.helped;
                    done[d.node as usize] = true;
                    left -= 1;
                }
                Ok(ToCoordinator::Done(d)) => {
                    let why = format!(
                        "node {} answered shot {} in {} (or twice)",
                        d.node, d.iteration, self.iteration
                    );
                    return self.fail(why);
                }
                Ok(ToCoordinator::Time {
                    node,
                    iteration,
                    time,
                }) => self.record_time(node, iteration, time),
                Ok(ToCoordinator::Failed { node, reason }) => {
                    return self.fail(format!("node {node}: {reason}"));
                }
                Ok(ToCoordinator::End { node, .. }) => {
                    return self.fail(format!("node {node} ended during shot {}", self.iteration));
                }
                Err(why) => {
                    let why = format!(
                        "shot {}: {} of {nodes} nodes answered: {why}",
                        self.iteration,
                        nodes - left
                    );
                    return self.fail(why);
                }
            }
        }
        true
    }

    /// Sends `Finish` to every node and puts the patches they send back
    /// into `solver`; returns the snapshots, or why the farm could not end.
    fn take_patches(&mut self, solver: &mut Solver) -> Result<Vec<Vec<f32>>, String> {
        let nodes = self.links.nodes();
        for n in 0..nodes as NodeId {
            if !self.links.send(n, ToNode::Finish) {
                return Err(format!("node {n} stopped before the end"));
            }
        }
        let mut snapshots: Vec<Vec<f32>> = Vec::new();
        let mut ended = vec![false; nodes];
        let mut left = nodes;
        while left > 0 {
            let msg = self
                .links
                .recv(self.stall)
                .map_err(|why| format!("{left} of {nodes} nodes sent no patches back: {why}"))?;
            let (node, patches, snaps, last) = match msg {
                ToCoordinator::End {
                    node,
                    patches,
                    snapshots,
                    last,
                } if ended.get(node as usize) == Some(&false) => (node, patches, snapshots, last),
                ToCoordinator::Time {
                    node,
                    iteration,
                    time,
                } => {
                    self.record_time(node, iteration, time);
                    continue;
                }
                ToCoordinator::Failed { node, reason } => {
                    return Err(format!("node {node}: {reason}"));
                }
                ToCoordinator::Done(d) => {
                    return Err(format!("node {} reported a shot after the last", d.node));
                }
                ToCoordinator::End { node, .. } => {
                    return Err(format!("node {node} sent patches after its last run"));
                }
            };
            if patches
                .iter()
                .any(|(i, _)| *i as usize >= solver.patches.len())
            {
                return Err(format!(
                    "node {node} sent back a patch the job does not have"
                ));
            }
            solver.take_back(patches);
            for (j, snap) in snaps.into_iter().enumerate() {
                if snapshots.len() <= j {
                    snapshots.push(vec![0.0; 2 * solver.patches.len()]);
                }
                for (i, lv) in snap {
                    if let Some(slot) = snapshots[j].get_mut(2 * i as usize..2 * i as usize + 2) {
                        slot.copy_from_slice(&lv);
                    }
                }
            }
            if last {
                ended[node as usize] = true;
                left -= 1;
            }
        }
        Ok(snapshots)
    }
}

impl<L: NodeLinks> Shots for Coordinator<L> {
    fn shoot(&mut self, solver: &mut Solver, snapshot: bool) -> bool {
        if self.error.is_some() {
            return false;
        }
        let Some(shooter) = solver.take_shooter() else {
            return false;
        };
        let refine = solver.refine();
        self.iteration += 1;
        let started = Instant::now();
        for n in 0..self.links.nodes() as NodeId {
            let msg = ToNode::Shoot {
                iteration: self.iteration,
                spec: shooter.spec(),
                refine,
                snapshot,
            };
            if !self.links.send(n, msg) {
                return self.fail(format!("node {n} stopped before shot {}", self.iteration));
            }
        }
        let mut receipts = vec![Receipt::default(); solver.patches.len()];
        let mut best = None;
        if !self.gather(solver, &mut receipts, &mut best) {
            return false;
        }
        self.measured.shot_s.push(started.elapsed().as_secs_f64());
        solver.book(&shooter, &receipts);
        // The nodes' candidates and the coordinator's shells saw the same
        // arithmetic: a disagreement is a bug, not a choice.
        let mine = solver.next_shooter().map(|(i, s, w)| (i, s as u8, w));
        if mine.map(|c| (c.0, c.1, c.2.to_bits())) != best.map(|c| (c.0, c.1, c.2.to_bits())) {
            return self.fail(format!(
                "shot {}: the nodes' next shooter {best:?} is not the coordinator's {mine:?}",
                self.iteration
            ));
        }
        true
    }

    /// Tells every node to finish and takes their patches back; a node
    /// that fails to send them leaves the error set (and shells in place).
    fn finish(&mut self, solver: &mut Solver) -> Vec<Vec<f32>> {
        self.take_patches(solver).unwrap_or_else(|why| {
            self.fail(why);
            Vec::new()
        })
    }
}
