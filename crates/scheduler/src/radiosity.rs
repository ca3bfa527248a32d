//! A radiosity job on the farm (Stürzlinger, Schaufler and Volkert): the
//! scheduler meshes the scene, lays the job's workers out in rings of
//! region owners ([`plan`]), sends each its [`NodeJob`] and coordinates
//! the shots from a blocking thread ([`solve`]); the workers' messages
//! reach that thread through the actor ([`FromMember`]). The coordinator
//! is the in-process farm's ([`Coordinator`]), so the solution is the one
//! machine's bit for bit. At the end the scheduler renders the solution
//! from the scene's camera and sends the client the image, the meshed
//! solution and the report.

use crate::{cost, partition};
use locus_core::accel::Accel;
use locus_core::geometry::TriangleSet;
use locus_core::image_io::Image;
use locus_core::octree::{Octree, OctreeParams};
use locus_core::radiosity::output::{MeshCorner, mesh_triangles, render_image};
use locus_core::radiosity::{Solver, solve_with};
use locus_core::region::ProcessorMap;
use locus_core::scene::Scene;
use locus_protocol::MAX_FRAME_LEN;
use locus_protocol::control::SchedulerToWorker;
use locus_protocol::radiosity::{
    Balance, NodeId, NodeJob, RadiosityJob, RadiosityReport, ToCoordinator, ToNode,
};
use locus_worker::radiosity::assign_patches;
use locus_worker::radiosity::coordinator::{Coordinator, NodeLinks};
use std::time::{Duration, Instant};
use tokio::sync::mpsc;

/// How the job's leaves and patches are spread: `positions[leaf]` is the
/// leaf's ring position, `owner[patch]` the patch's node.
pub struct Rings {
    pub tree: Octree,
    pub positions: Vec<u16>,
    pub owner: Vec<u32>,
}

/// Cuts `nodes` nodes into rings of `ring`: an octree with leaves small
/// enough that every ring position gets a region, regions of equal
/// predicted tracing cost (static balancing of visibility, section 4.2) or
/// equal leaf counts, and patches spread by elements (section 4.1) or by
/// count.
pub fn plan(
    scene: &Scene,
    solver: &Solver,
    nodes: u32,
    ring: u32,
    balance: Balance,
) -> Result<Rings, String> {
    if nodes == 0 || ring == 0 || ring > 64 || !nodes.is_multiple_of(ring) {
        return Err(format!(
            "{nodes} nodes cannot form rings of {ring}: the node count (--workers) must be a \
             multiple of the ring length (--ring, 1 to 64)"
        ));
    }
    let tree = Octree::build(
        &scene.tris,
        OctreeParams {
            max_leaf_tris: (scene.tris.len() / (8 * ring as usize)).clamp(2, 512),
            max_depth: 7,
        },
    );
    let refs: Vec<u64> = tree.leaves.iter().map(|l| l.tris.len() as u64).collect();
    let leaf_cost = if balance.is_static() {
        cost::analytic(&tree)
    } else {
        vec![1.0; tree.leaves.len()]
    };
    let (targets, caps) = partition::even(ring as usize);
    let limits = partition::Limits {
        targets: &targets,
        caps: &caps,
        refs: &refs,
    };
    let positions = partition::morton(&leaf_cost, &limits)?;
    let owner = assign_patches(solver, nodes, balance.is_static());
    Ok(Rings {
        tree,
        positions,
        owner,
    })
}

/// What the actor passes on to a running radiosity job's coordinator,
/// by the member's node id.
pub enum FromMember {
    Ready(NodeId),
    Node(NodeId, ToCoordinator),
    Failed(NodeId, String),
}

/// The job's members as the coordinator reaches them.
pub struct Members {
    pub run: u64,
    /// Listen addresses, by node id.
    pub addrs: Vec<String>,
    pub links: Vec<mpsc::Sender<SchedulerToWorker>>,
    pub from: flume::Receiver<FromMember>,
}

/// A shot (or the start) with no word from some node for this long fails.
pub const STALL: Duration = Duration::from_secs(120);

impl NodeLinks for Members {
    fn nodes(&self) -> usize {
        self.links.len()
    }

    fn send(&mut self, n: NodeId, msg: ToNode) -> bool {
        let m = SchedulerToWorker::Node {
            job: self.run,
            msg: Box::new(msg),
        };
        self.links[n as usize].blocking_send(m).is_ok()
    }

    fn recv(&mut self, wait: Duration) -> Result<ToCoordinator, String> {
        let until = Instant::now() + wait;
        loop {
            let left = until.saturating_duration_since(Instant::now());
            match self.from.recv_timeout(left) {
                Ok(FromMember::Node(n, msg)) => {
                    let claimed = match &msg {
                        ToCoordinator::Done(d) => d.node,
                        ToCoordinator::Time { node, .. }
                        | ToCoordinator::Failed { node, .. }
                        | ToCoordinator::End { node, .. } => *node,
                    };
                    if claimed != n {
                        return Err(format!("the worker of node {n} spoke as node {claimed}"));
                    }
                    return Ok(msg);
                }
                Ok(FromMember::Failed(n, why)) => return Err(format!("node {n}: {why}")),
                Ok(FromMember::Ready(_)) => {}
                Err(flume::RecvTimeoutError::Timeout) => {
                    return Err(format!("no word for {:.0} s", wait.as_secs_f64()));
                }
                Err(flume::RecvTimeoutError::Disconnected) => {
                    return Err("the job was ended by the scheduler".into());
                }
            }
        }
    }
}

/// A solved job: what its client gets.
pub struct Solved {
    pub image: Image,
    pub mesh: Vec<[MeshCorner; 3]>,
    pub report: RadiosityReport,
}

/// Solves `job` on `members` (blocking: the scheduler runs it on its own
/// thread); `progress` gets the fraction of the way, on a log scale of the
/// unshot power, from the first to the stopping one.
pub fn solve(
    scene: &Scene,
    job: &RadiosityJob,
    members: Members,
    progress: &(dyn Fn(f64) + Sync),
) -> Result<Solved, String> {
    let t = Instant::now();
    let p = job.params;
    let mut solver = Solver::new(scene, p).map_err(|e| e.to_string())?;
    let nodes = members.links.len() as u32;
    let ring = if job.ring == 0 { nodes } else { job.ring };
    let rings = plan(scene, &solver, nodes, ring, job.balance)?;
    let mesh_s = t.elapsed().as_secs_f64();
    start_nodes(scene, job, &mut solver, &rings, ring, &members)?;
    // Every node linked to every other before the first shot.
    let mut ready = vec![false; nodes as usize];
    while ready.iter().any(|r| !r) {
        match members.from.recv_timeout(STALL) {
            Ok(FromMember::Ready(n)) => ready[n as usize] = true,
            Ok(FromMember::Failed(n, why)) => return Err(format!("node {n}: {why}")),
            Ok(FromMember::Node(n, _)) => {
                return Err(format!("node {n} spoke before it was ready"));
            }
            Err(_) => {
                let n = ready.iter().filter(|r| **r).count();
                return Err(format!("{n} of {nodes} nodes were ready within {STALL:?}"));
            }
        }
    }
    members.from.drain();
    let t = Instant::now();
    let first = solver.unshot_fraction();
    let mut coord = Coordinator::new(members, STALL);
    let conv = solve_with(&mut solver, &mut coord, &mut |s| {
        let f = s.unshot_fraction().max(p.stop);
        progress(((first / f).ln() / (first / p.stop).ln()).clamp(0.0, 1.0));
    });
    if let Some(e) = coord.error {
        return Err(e);
    }
    let solve_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let all: Vec<u32> = (0..scene.tris.len() as u32).collect();
    let accel = Accel::build(&scene.tris, &all, scene.magnitude());
    let s = &scene.settings;
    let (image, _) = render_image(
        &solver,
        &accel,
        &scene.camera,
        job.spp.max(1),
        s.seed,
        s.sampler,
    );
    let image_s = t.elapsed().as_secs_f64();
    let m = &coord.measured;
    let report = RadiosityReport {
        params: p,
        nodes,
        ring,
        balance: job.balance,
        patches: solver.patches.len() as u64,
        elements: solver.elements,
        vertices: solver.vertices(),
        iterations: solver.iterations,
        stopped: conv.stopped.to_string(),
        unshot_fraction: solver.unshot_fraction(),
        ledger: solver.ledger(),
        convergence: conv.records,
        visibility_rays: solver.stats.rays(),
        packets: m.packets,
        helped: m.helped,
        node_times: m.per_node(),
        mesh_s,
        solve_s,
        image_s,
        attempts: 1,
        lost: Vec::new(),
        mesh: Vec::new(),
    };
    Ok(Solved {
        image,
        mesh: mesh_triangles(&solver),
        report,
    })
}

/// Hands out the patches and sends every node its part, each within a
/// frame.
fn start_nodes(
    scene: &Scene,
    job: &RadiosityJob,
    solver: &mut Solver,
    rings: &Rings,
    ring: u32,
    members: &Members,
) -> Result<(), String> {
    let nodes = members.links.len();
    let map = ProcessorMap::new(&rings.tree, rings.positions.clone());
    let mut patches = solver.hand_out(&rings.owner, nodes);
    let regions: Vec<TriangleSet> = (0..ring as u16)
        .map(|k| {
            let ids = ProcessorMap::region_triangles(&rings.tree, &rings.positions, k);
            TriangleSet {
                verts: ids.iter().map(|&i| scene.tris[i as usize]).collect(),
                material: vec![0; ids.len()],
                normals: Vec::new(),
                ids,
            }
        })
        .collect();
    for (n, link) in members.links.iter().enumerate() {
        let setup = NodeJob {
            job: members.run,
            me: n as NodeId,
            peers: members.addrs.clone(),
            ring,
            map: map.clone(),
            region: regions[n % ring as usize].clone(),
            magnitude: scene.magnitude(),
            patches: std::mem::take(&mut patches[n]),
            part_levels: job.params.part_levels(),
            dynamic: job.balance.is_dynamic(),
            seed: scene.settings.seed,
            stall_ms: STALL.as_millis() as u64,
        };
        let size = postcard::experimental::serialized_size(&setup).unwrap_or(usize::MAX);
        if size > MAX_FRAME_LEN - 1024 {
            return Err(format!(
                "node {n}'s part (region and patches) is {} MiB, more than a frame's {} MiB: \
                 use a coarser mesh, or more workers or shorter rings",
                size >> 20,
                MAX_FRAME_LEN >> 20
            ));
        }
        if link
            .blocking_send(SchedulerToWorker::StartNode(Box::new(setup)))
            .is_err()
        {
            return Err(format!("node {n}'s worker left before the job started"));
        }
    }
    Ok(())
}
