//! A radiosity farm in one process: one thread per node, bounded channels
//! for links, and the [`Coordinator`] on the caller's thread as the
//! [`Shots`] of the core's solve loop.
//!
//! [`Shots`]: locus_core::radiosity::Shots

use super::coordinator::{Coordinator, NodeLinks};
use super::node::{Layout, Node, NodeSetup, Outbox, WINDOW};
use super::runner::run_node;
use locus_core::accel::Accel;
use locus_core::accel_set::AccelSet;
use locus_core::octree::Octree;
use locus_core::radiosity::Solver;
use locus_core::region::{ProcessorMap, Route};
use locus_core::scene::Scene;
use locus_protocol::radiosity::{NodeId, ToCoordinator, ToNode};
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

/// The coordinator's side of the threads: their inboxes, its own, and the
/// threads themselves (a thread that ends with an error or a panic ends
/// the farm at once, not after a stall).
pub struct ThreadLinks {
    to_nodes: Vec<flume::Sender<ToNode>>,
    from_nodes: flume::Receiver<ToCoordinator>,
    threads: Vec<Option<JoinHandle<Result<(), String>>>>,
}

impl NodeLinks for ThreadLinks {
    fn nodes(&self) -> usize {
        self.to_nodes.len()
    }

    fn send(&mut self, n: NodeId, msg: ToNode) -> bool {
        self.to_nodes[n as usize].send(msg).is_ok()
    }

    fn recv(&mut self, wait: Duration) -> Result<ToCoordinator, String> {
        let until = Instant::now() + wait;
        loop {
            let slice = until
                .saturating_duration_since(Instant::now())
                .min(Duration::from_millis(100));
            match self.from_nodes.recv_timeout(slice) {
                Ok(m) => return Ok(m),
                Err(flume::RecvTimeoutError::Disconnected) => return Err("every node ended".into()),
                Err(flume::RecvTimeoutError::Timeout) => {}
            }
            for (id, slot) in self.threads.iter_mut().enumerate() {
                if slot.as_ref().is_some_and(|t| t.is_finished()) {
                    let t = slot.take().expect("checked");
                    match t.join() {
                        Ok(Ok(())) => {}
                        Ok(Err(why)) => return Err(format!("node {id}: {why}")),
                        Err(_) => return Err(format!("node {id} panicked")),
                    }
                }
            }
            if Instant::now() >= until {
                return Err(format!("no word for {:.0} s", wait.as_secs_f64()));
            }
        }
    }
}

impl Drop for ThreadLinks {
    fn drop(&mut self) {
        // Closing the inboxes ends any node still waiting.
        self.to_nodes.clear();
        for t in self.threads.iter_mut().filter_map(Option::take) {
            let _ = t.join();
        }
    }
}

/// The in-process farm.
pub type Farm = Coordinator<ThreadLinks>;

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

/// Hands `solver`'s patches to nodes (`patch_owner[patch]`) and starts
/// them on threads, each with its ring position's region of `tree` (leaf
/// `l` in position `positions[l]`).
pub fn start(
    solver: &mut Solver,
    scene: &Scene,
    tree: &Octree,
    positions: &[u16],
    patch_owner: &[u32],
    cfg: FarmConfig,
) -> Farm {
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
    let inbox = inbox_capacity(n);
    let (to_coord, from_nodes) = flume::bounded(4 * n + 8);
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
        let mut links = Links {
            peers: txs.clone(),
            coordinator: to_coord.clone(),
        };
        let stall = cfg.stall;
        threads.push(Some(std::thread::spawn(move || {
            run_node(Node::new(setup), &rx, &mut links, stall)
        })));
    }
    threads.reverse();
    let links = ThreadLinks {
        to_nodes: txs,
        from_nodes,
        threads,
    };
    Coordinator::new(links, cfg.stall)
}

/// A node inbox that holds every message that can be in flight to it:
/// every packet is some node's, at most [`WINDOW`] each; each node has at
/// most one poll out and one answer due; one shot at a time.
pub fn inbox_capacity(nodes: usize) -> usize {
    nodes * (WINDOW + 2) + 8
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
