//! A worker daemon's part in a radiosity job: the scheduler's coordinator
//! sends it a [`NodeJob`] (its region, its patches, the ring layout), the
//! node links to every other node of the job as a render job's engine
//! does, and runs the same [`runner`](super::runner) loop as a thread of
//! the in-process farm, its messages carried by the peer links and the
//! scheduler link instead of channels.

use super::farm::inbox_capacity;
use super::node::{Layout, Node, NodeSetup, Outbox};
use super::runner::run_node;
use crate::job::{Env, link_peers};
use crate::peers::{Inbox, JobLink, OnBreak, Traffic};
use anyhow::bail;
use locus_core::accel::Accel;
use locus_core::accel_set::AccelSet;
use locus_protocol::control::WorkerToScheduler;
use locus_protocol::radiosity::{NodeId, NodeJob, ToCoordinator, ToNode};
use locus_protocol::rays::PeerMsg;
use std::sync::Arc;
use std::time::Duration;
use tracing::{info, warn};

/// Why a node's job cannot run, if it cannot.
fn check(s: &NodeJob) -> anyhow::Result<()> {
    let n = s.peers.len();
    if n == 0 || n > u16::MAX as usize || s.me as usize >= n {
        bail!("node {} of a job of {n} nodes", s.me);
    }
    if !(1..=64).contains(&s.ring) || !n.is_multiple_of(s.ring as usize) {
        bail!("{n} nodes cannot form rings of {}", s.ring);
    }
    if s.map.owner.iter().any(|&p| p as u32 >= s.ring) {
        bail!("the ring map names a position outside a ring of {}", s.ring);
    }
    if !s.region.is_consistent() || s.region.verts.iter().flatten().any(|p| !p.is_finite()) {
        bail!("the node's region has inconsistent lists or a non-finite vertex");
    }
    if s.part_levels > 3 {
        bail!("shooters split into 4^{} parts (at most 64)", s.part_levels);
    }
    Ok(())
}

/// Builds the node's region, links to the other nodes and starts the node
/// on a blocking thread; its end (or failure) goes to the scheduler.
pub async fn start(mut setup: Box<NodeJob>, env: Env) -> anyhow::Result<Arc<JobLink>> {
    check(&setup)?;
    let n = setup.peers.len();
    let (job, me) = (setup.job, setup.me);
    let region = std::mem::take(&mut setup.region);
    let mag = setup.magnitude;
    let triangles = region.len();
    let accel =
        tokio::task::spawn_blocking(move || AccelSet::single(Accel::from_set(region, mag))).await?;
    let cancel = env.cancel.clone();
    let traffic = Arc::new(Traffic::new(n));
    let (tx, rx) = flume::bounded::<ToNode>(inbox_capacity(n));
    let link = Arc::new(JobLink {
        job,
        inbox: Inbox::Node(tx.clone()),
        traffic: traffic.clone(),
        cancel: cancel.clone(),
    });
    // Publish before dialing: peers dial us at the same time.
    env.links.send_replace(Some(link.clone()));
    // A finished peer closes its links while this node may still answer
    // its last poll: a broken link drops that peer, not the job.
    let (peers, writers) = link_peers(
        &setup.peers,
        job,
        me as u16,
        &env,
        &traffic,
        OnBreak::DropPeer,
    )
    .await?;
    info!(
        job,
        node = me,
        triangles,
        patches = setup.patches.len(),
        "radiosity node linked"
    );
    let stall = Duration::from_millis(setup.stall_ms.max(1000));
    let node = Node::new(NodeSetup {
        id: me,
        layout: Layout {
            nodes: n as u32,
            ring: setup.ring,
        },
        route: setup.map.route.clone(),
        region: accel,
        patches: std::mem::take(&mut setup.patches),
        part_levels: setup.part_levels,
        dynamic: setup.dynamic,
        seed: setup.seed,
    });
    let mut out = DaemonLinks {
        job,
        me,
        own: tx.clone(),
        peers,
        control: env.control.clone(),
        cancel: cancel.clone(),
        lost: vec![0; n],
    };
    let ctl = env.control.clone();
    tokio::spawn(async move {
        let mut thread = tokio::task::spawn_blocking(move || run_node(node, &rx, &mut out, stall));
        let res = tokio::select! {
            r = &mut thread => r,
            _ = cancel.cancelled() => {
                // Aborted: Finish ends the node's loop, and its links
                // send nothing more (no patches go back for nothing).
                let _ = tx.send_async(ToNode::Finish).await;
                thread.await
            }
        };
        let failed = match res {
            Ok(Ok(())) => None,
            Ok(Err(why)) => Some(why),
            Err(e) => Some(format!("radiosity node crashed: {e}")),
        };
        if let Some(reason) = failed {
            warn!(job, node = me, "radiosity node failed: {reason}");
            let _ = ctl
                .send_async(WorkerToScheduler::Failed { job, reason })
                .await;
        }
        for h in writers {
            let _ = tokio::time::timeout(Duration::from_secs(10), h).await;
        }
        cancel.cancel();
    });
    env.control
        .send_async(WorkerToScheduler::Ready { job })
        .await
        .map_err(|_| anyhow::anyhow!("scheduler link closed"))?;
    Ok(link)
}

/// A daemon node's links: its own inbox, the peer writers and the
/// scheduler link.
struct DaemonLinks {
    job: u64,
    me: NodeId,
    own: flume::Sender<ToNode>,
    peers: Vec<Option<flume::Sender<crate::peers::Outgoing>>>,
    control: flume::Sender<WorkerToScheduler>,
    /// The job's abort (by the scheduler): nothing leaves the node after
    /// it. A broken peer link does not set it (`OnBreak::DropPeer`).
    cancel: tokio_util::sync::CancellationToken,
    /// Messages lost on each peer's broken link.
    lost: Vec<u64>,
}

impl Outbox for DaemonLinks {
    fn to_node(&mut self, to: NodeId, msg: ToNode) {
        if self.cancel.is_cancelled() {
            return;
        }
        // Every inbox holds every message that can be in flight to it
        // (see `inbox_capacity`), so these waits end. A peer's link closes
        // when its writer failed (`OnBreak::DropPeer`): what it would have
        // carried is counted as lost.
        if to == self.me {
            let _ = self.own.send(msg);
        } else if let Some(Some(tx)) = self.peers.get(to as usize)
            && tx.send(PeerMsg::Node(Box::new(msg)).into()).is_err()
        {
            // Its writer ended on a failed write.
            self.lost[to as usize] += 1;
        }
    }

    fn to_coordinator(&mut self, msg: ToCoordinator) {
        if self.cancel.is_cancelled() {
            return;
        }
        let _ = self.control.send(WorkerToScheduler::Node {
            job: self.job,
            msg: Box::new(msg),
        });
    }

    fn lost(&self) -> Option<String> {
        let lost: Vec<String> = (self.lost.iter().enumerate())
            .filter(|(_, n)| **n > 0)
            .map(|(p, n)| format!("{n} to node {p}"))
            .collect();
        (!lost.is_empty()).then(|| format!("links broke, messages lost: {}", lost.join(", ")))
    }
}
