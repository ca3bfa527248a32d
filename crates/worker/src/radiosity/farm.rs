//! A radiosity farm in one process: one thread per node, bounded channels
//! for links, and the coordinator on the caller's thread as the
//! [`Shots`] of the core's solve loop.
//!
//! The coordinator keeps each patch's shell (area, albedo, unshot power),
//! chooses the shooter, tells every node, waits for every node's receipts
//! and books them in patch order, exactly as one machine does; so the
//! solution is the one machine's, bit for bit, whatever the layout and
//! balancing. Every node finishing its own packets ends a shot: a packet in
//! flight belongs to a node that has not finished (it waits for it), so
//! when all have, none is left anywhere.

use super::node::{Layout, Node, NodeSetup, Outbox, WINDOW};
use crate::sys::thread_cpu_s;
use locus_core::accel::Accel;
use locus_core::accel_set::AccelSet;
use locus_core::octree::Octree;
use locus_core::radiosity::shoot::Receipt;
use locus_core::radiosity::{Shots, Solver};
use locus_core::region::{ProcessorMap, Route};
use locus_core::scene::Scene;
use locus_protocol::radiosity::{NodeId, NodeTime, ToCoordinator, ToNode};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// How a farm is laid out and balanced.
#[derive(Clone, Copy, Debug)]
pub struct FarmConfig {
    pub layout: Layout,
    /// Random polling for packets of other rings (section 5.2).
    pub dynamic: bool,
    pub seed: u64,
    /// A shot with no word from some node for this long fails.
    pub stall: Duration,
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

/// The coordinator side: the nodes' links and threads.
pub struct Farm {
    to_nodes: Vec<flume::Sender<ToNode>>,
    from_nodes: flume::Receiver<ToCoordinator>,
    threads: Vec<JoinHandle<Result<Node, String>>>,
    stall: Duration,
    iteration: u64,
    pub measured: FarmTimes,
    /// Why the farm stopped early, if it did.
    pub error: Option<String>,
}

/// The regions: ring position `k` holds the triangles of the leaves
/// `positions` gives `k`.
fn regions(scene: &Scene, tree: &Octree, positions: &[u16], ring: u32) -> Vec<AccelSet> {
    (0..ring as u16)
        .map(|k| {
            let ids = ProcessorMap::region_triangles(tree, positions, k);
            AccelSet::single(Accel::build(&scene.tris, &ids, scene.magnitude()))
        })
        .collect()
}

impl Farm {
    /// Hands `solver`'s patches to nodes (`patch_owner[patch]`) and starts
    /// them, each with its ring position's region of `tree` (leaf `l` in
    /// position `positions[l]`).
    pub fn start(
        solver: &mut Solver,
        scene: &Scene,
        tree: &Octree,
        positions: &[u16],
        patch_owner: &[u32],
        cfg: FarmConfig,
    ) -> Self {
        let l = cfg.layout;
        assert!(
            l.ring >= 1 && l.ring <= 64 && l.nodes.is_multiple_of(l.ring),
            "whole rings of 1 to 64"
        );
        let n = l.nodes as usize;
        let route = Route::new(tree, positions);
        let regions = regions(scene, tree, positions, l.ring);
        let part_levels = solver.params.part_levels();
        let mut patches = solver.hand_out(patch_owner, n);
        // Every packet is some node's, at most WINDOW each; each node has
        // at most one poll out and one answer due; one shot at a time.
        let inbox = n * (WINDOW + 2) + 8;
        let (to_coord, from_nodes) = flume::bounded(3 * n + 8);
        let (txs, rxs): (Vec<_>, Vec<_>) = (0..n).map(|_| flume::bounded(inbox)).unzip();
        let mut threads = Vec::with_capacity(n);
        for (id, rx) in rxs.into_iter().enumerate().rev() {
            let setup = NodeSetup {
                id: id as NodeId,
                layout: l,
                route: route.clone(),
                region: regions[l.position(id as NodeId) as usize].clone(),
                patches: patches.pop().unwrap_or_default(),
                part_levels,
                dynamic: cfg.dynamic,
                seed: cfg.seed,
            };
            let links = Links {
                peers: txs.clone(),
                coordinator: to_coord.clone(),
            };
            let stall = cfg.stall;
            threads.push(std::thread::spawn(move || {
                run_node(Node::new(setup), rx, links, stall)
            }));
        }
        threads.reverse();
        Self {
            to_nodes: txs,
            from_nodes,
            threads,
            stall: cfg.stall,
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
        let shot = iteration as usize - 1;
        let nodes = self.to_nodes.len();
        while self.measured.times.len() <= shot {
            self.measured.times.push(vec![NodeTime::default(); nodes]);
        }
        self.measured.times[shot][node as usize] = time;
    }
}

/// Whether candidate `a` beats `b`: more power, then the lower patch and
/// side, the order in which one machine scans patches.
fn better(a: (u32, u8, f64), b: Option<(u32, u8, f64)>) -> bool {
    b.is_none_or(|b| a.2 > b.2 || (a.2 == b.2 && (a.0, a.1) < (b.0, b.1)))
}

impl Shots for Farm {
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
        for tx in &self.to_nodes {
            let msg = ToNode::Shoot {
                iteration: self.iteration,
                spec: shooter.spec(),
                refine,
                snapshot,
            };
            if tx.send(msg).is_err() {
                return self.fail("a node stopped before the shot".into());
            }
        }
        let mut receipts = vec![Receipt::default(); solver.patches.len()];
        let mut best = None;
        let mut done = 0;
        while done < self.to_nodes.len() {
            match self.from_nodes.recv_timeout(self.stall) {
                Ok(ToCoordinator::Done(d)) if d.iteration == self.iteration => {
                    for (i, r) in d.receipts {
                        receipts[i as usize] = r;
                    }
                    if let Some(c) = d.candidate
                        && better(c, best)
                    {
                        best = Some(c);
                    }
                    solver.stats += d.stats;
                    self.measured.packets += d.packets;
                    self.measured.helped += d.helped;
                    done += 1;
                }
                Ok(ToCoordinator::Done(d)) => {
                    let why = format!(
                        "node {} answered shot {} in {}",
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
                Err(_) => {
                    let why = format!(
                        "shot {}: {} of {} nodes answered within {:.0} s",
                        self.iteration,
                        done,
                        self.to_nodes.len(),
                        self.stall.as_secs_f64()
                    );
                    return self.fail(why);
                }
            }
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

    fn finish(&mut self, solver: &mut Solver) -> Vec<Vec<f32>> {
        for tx in &self.to_nodes {
            let _ = tx.send(ToNode::Finish);
        }
        let mut snapshots: Vec<Vec<f32>> = Vec::new();
        for (id, t) in std::mem::take(&mut self.threads).into_iter().enumerate() {
            match t.join() {
                Ok(Ok(node)) => {
                    let (patches, snaps) = node.into_patches();
                    solver.take_back(patches);
                    for (j, snap) in snaps.into_iter().enumerate() {
                        if snapshots.len() <= j {
                            snapshots.push(vec![0.0; 2 * solver.patches.len()]);
                        }
                        for (i, lv) in snap {
                            snapshots[j][2 * i as usize..2 * i as usize + 2].copy_from_slice(&lv);
                        }
                    }
                }
                Ok(Err(why)) => {
                    self.fail(format!("node {id}: {why}"));
                }
                Err(_) => {
                    self.fail(format!("node {id} panicked"));
                }
            }
        }
        while let Ok(m) = self.from_nodes.try_recv() {
            if let ToCoordinator::Time {
                node,
                iteration,
                time,
            } = m
            {
                self.record_time(node, iteration, time);
            }
        }
        snapshots
    }
}

/// A node's links: every node's inbox and the coordinator's.
struct Links {
    peers: Vec<flume::Sender<ToNode>>,
    coordinator: flume::Sender<ToCoordinator>,
}

impl Outbox for Links {
    fn to_node(&mut self, to: NodeId, msg: ToNode) {
        // Capacity covers every message that can be in flight, so this
        // never waits; a closed inbox means the farm is ending anyway.
        let _ = self.peers[to as usize].send(msg);
    }

    fn to_coordinator(&mut self, msg: ToCoordinator) {
        let _ = self.coordinator.send(msg);
    }
}

/// A node's thread: handle messages until `Finish`, stepping through
/// local visibility when none waits, and time each shot.
fn run_node(
    mut node: Node,
    inbox: flume::Receiver<ToNode>,
    mut links: Links,
    stall: Duration,
) -> Result<Node, String> {
    let mut time = NodeTime::default();
    loop {
        let msg = if node.has_local_work() {
            match inbox.try_recv() {
                Ok(m) => Some(m),
                Err(flume::TryRecvError::Empty) => None,
                Err(flume::TryRecvError::Disconnected) => return Err("the farm closed".into()),
            }
        } else {
            let waited = Instant::now();
            let m = match inbox.recv_timeout(stall) {
                Ok(m) => m,
                Err(flume::RecvTimeoutError::Timeout) => {
                    let reason = format!("no message for {:.0} s", stall.as_secs_f64());
                    links.to_coordinator(ToCoordinator::Failed {
                        node: node.id(),
                        reason: reason.clone(),
                    });
                    return Err(reason);
                }
                Err(flume::RecvTimeoutError::Disconnected) => {
                    return Err("the farm closed".into());
                }
            };
            let blocked = waited.elapsed().as_secs_f64();
            if node.finished {
                time.idle_s += blocked;
            } else {
                time.waiting_s += blocked;
            }
            Some(m)
        };
        let Some(msg) = msg else {
            let help = node.next_step_helps();
            let cpu = thread_cpu_s();
            node.step(&mut links);
            let spent = thread_cpu_s() - cpu;
            time.work_s += spent;
            if help {
                time.helping_s += spent;
            }
            continue;
        };
        let ends_shot = matches!(msg, ToNode::Shoot { .. } | ToNode::Finish);
        if ends_shot && node.iteration() > 0 {
            links.to_coordinator(ToCoordinator::Time {
                node: node.id(),
                iteration: node.iteration(),
                time: std::mem::take(&mut time),
            });
        }
        if msg == ToNode::Finish {
            return Ok(node);
        }
        let cpu = thread_cpu_s();
        node.handle(msg, &mut links);
        time.work_s += thread_cpu_s() - cpu;
    }
}
