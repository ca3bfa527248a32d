//! A node's loop, the same on a thread of the in-process farm and in a
//! worker daemon: handle messages until `Finish`, stepping through local
//! visibility when none waits, time each shot, and at the end send the
//! patches back in runs.

use super::node::{Node, Outbox};
use crate::sys::thread_cpu_s;
use locus_protocol::radiosity::{NodeTime, ToCoordinator, ToNode};
use std::time::{Duration, Instant};

/// Bytes of patches per [`ToCoordinator::End`] run: well within a frame.
const END_RUN_BYTES: usize = 16 << 20;

/// Runs `node` until `Finish` (Ok) or until it cannot go on (Err: why,
/// also told to the coordinator when it is a stall).
pub fn run_node(
    mut node: Node,
    inbox: &flume::Receiver<ToNode>,
    out: &mut dyn Outbox,
    stall: Duration,
) -> Result<(), String> {
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
                    let mut reason = format!("no message for {:.0} s", stall.as_secs_f64());
                    if let Some(lost) = out.lost() {
                        reason += &format!(" ({lost})");
                    }
                    out.to_coordinator(ToCoordinator::Failed {
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
            node.step(out);
            let spent = thread_cpu_s() - cpu;
            time.work_s += spent;
            if help {
                time.helping_s += spent;
            }
            continue;
        };
        let ends_shot = matches!(msg, ToNode::Shoot { .. } | ToNode::Finish);
        if ends_shot && node.iteration() > 0 {
            out.to_coordinator(ToCoordinator::Time {
                node: node.id(),
                iteration: node.iteration(),
                time: std::mem::take(&mut time),
            });
        }
        if msg == ToNode::Finish {
            send_end(node, out);
            return Ok(());
        }
        let cpu = thread_cpu_s();
        node.handle(msg, out);
        time.work_s += thread_cpu_s() - cpu;
    }
}

/// Sends the node's patches to the coordinator in runs of about
/// [`END_RUN_BYTES`], the snapshots with the last.
fn send_end(node: Node, out: &mut dyn Outbox) {
    let id = node.id();
    let (patches, snapshots) = node.into_patches();
    let mut run = Vec::new();
    let mut bytes = 0;
    for (i, p) in patches {
        bytes += p.bytes();
        run.push((i, p));
        if bytes >= END_RUN_BYTES {
            out.to_coordinator(ToCoordinator::End {
                node: id,
                patches: std::mem::take(&mut run),
                snapshots: Vec::new(),
                last: false,
            });
            bytes = 0;
        }
    }
    out.to_coordinator(ToCoordinator::End {
        node: id,
        patches: run,
        snapshots,
        last: true,
    });
}
