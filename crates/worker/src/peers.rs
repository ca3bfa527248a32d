//! Links between workers: one TCP connection per ordered pair, written by
//! the dialing side and read by the accepting side, each opened with the
//! authenticated handshake and a `Hello` naming the job and the sender.
//! Frames and bytes are counted per peer as they cross the socket.

use crate::engine::{Event, Input, Received};
use locus_core::sampler::Sampler;
use locus_protocol::handshake::Credentials;
use locus_protocol::radiosity::ToNode;
use locus_protocol::rays::{Packet, PeerMsg, RayItem};
use locus_protocol::report::PeerTraffic;
use locus_protocol::{MAX_FRAME_LEN, ProtocolError, handshake};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tracing::{debug, warn};

/// What a link's writer task is handed: a message, or a packet of ray
/// items of which the engine's own are still to be encoded. The writer
/// encodes them, so that the engine's serial thread only moves them.
pub enum Outgoing {
    Msg(PeerMsg),
    /// Items the pool encoded, then the engine's, as one packet.
    Items {
        encoded: Packet,
        raw: Vec<RayItem>,
    },
}

impl From<PeerMsg> for Outgoing {
    fn from(m: PeerMsg) -> Self {
        Outgoing::Msg(m)
    }
}

impl Outgoing {
    /// The message as it goes on the wire.
    pub fn into_msg(self) -> PeerMsg {
        match self {
            Outgoing::Msg(m) => m,
            Outgoing::Items { mut encoded, raw } => {
                for item in &raw {
                    encoded.push(item);
                }
                PeerMsg::Packet(encoded)
            }
        }
    }
}

/// What incoming links of the running job feed.
pub struct JobLink {
    pub job: u64,
    pub inbox: Inbox,
    pub traffic: Arc<Traffic>,
    pub cancel: CancellationToken,
}

/// A render job's engine (with the job's seed and sampler, which the
/// packets' path queries leave out), or a radiosity job's node.
pub enum Inbox {
    Engine {
        tx: flume::Sender<Event>,
        seed: u64,
        sampler: Sampler,
        workers: usize,
    },
    Node(flume::Sender<ToNode>),
}

#[derive(Default)]
struct Counters {
    msgs_sent: AtomicU64,
    bytes_sent: AtomicU64,
    msgs_recv: AtomicU64,
    bytes_recv: AtomicU64,
}

/// Per-peer frame and byte counters.
pub struct Traffic(Vec<Counters>);

impl Traffic {
    pub fn new(n: usize) -> Self {
        Self((0..n).map(|_| Counters::default()).collect())
    }

    pub fn snapshot(&self) -> Vec<PeerTraffic> {
        self.0
            .iter()
            .map(|c| PeerTraffic {
                msgs_sent: c.msgs_sent.load(Relaxed),
                bytes_sent: c.bytes_sent.load(Relaxed),
                msgs_recv: c.msgs_recv.load(Relaxed),
                bytes_recv: c.bytes_recv.load(Relaxed),
            })
            .collect()
    }
}

/// What a job does when a write to one of its peers fails.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OnBreak {
    /// The job ends: a render job's engine stops and reports what it did,
    /// and the scheduler recovers the rest (its fault tolerance).
    CancelJob,
    /// Only that link ends; what is sent to it after fails at once (its
    /// receiver is gone), so the sender never waits on it. A radiosity
    /// node: a peer that has finished closes its links, and a poll
    /// answered to it a moment later must not end the node before it has
    /// sent its patches back. A peer lost for real is the coordinator's to
    /// find (the worker's scheduler link, or the node's stall).
    DropPeer,
}

/// Dials peer `to` and starts the task that writes our packets to it; the
/// task ends when the engine drops its sender, after the last write, or
/// when a write fails (then as `on_break` says).
#[allow(clippy::too_many_arguments)]
pub async fn dial(
    addr: &str,
    creds: &Credentials,
    job: u64,
    me: u16,
    to: u16,
    rx: flume::Receiver<Outgoing>,
    traffic: Arc<Traffic>,
    cancel: CancellationToken,
    on_break: OnBreak,
) -> Result<tokio::task::JoinHandle<()>, ProtocolError> {
    let mut conn = handshake::dial(addr, creds, MAX_FRAME_LEN).await?;
    conn.write_msg(&PeerMsg::Hello { job, from: me }).await?;
    let (_r, mut w) = conn.into_split();
    Ok(tokio::spawn(async move {
        let c = &traffic.0[to as usize];
        loop {
            let msg = tokio::select! {
                _ = cancel.cancelled() => break,
                m = rx.recv_async() => match m { Ok(m) => m.into_msg(), Err(_) => break },
            };
            // A peer that stopped reading (stopped, cut off) must not
            // hold this task once the job is aborted.
            let written = tokio::select! {
                _ = cancel.cancelled() => break,
                r = w.write_msg(&msg) => r,
            };
            match written {
                Ok(n) => {
                    c.msgs_sent.fetch_add(1, Relaxed);
                    c.bytes_sent.fetch_add(n as u64, Relaxed);
                }
                Err(e) => {
                    match on_break {
                        OnBreak::CancelJob => {
                            warn!(peer = to, "peer link: {e}");
                            cancel.cancel();
                        }
                        // Usually a peer that has finished; a loss that
                        // matters is said when the node stalls.
                        OnBreak::DropPeer => debug!(peer = to, "peer link closed: {e}"),
                    }
                    break;
                }
            }
        }
        drop(_r);
    }))
}

pub async fn accept_loop(
    listener: TcpListener,
    creds: Arc<Credentials>,
    job: watch::Receiver<Option<Arc<JobLink>>>,
    shutdown: CancellationToken,
) {
    let permits = Arc::new(tokio::sync::Semaphore::new(locus_protocol::MAX_CONNECTIONS));
    loop {
        let permit = tokio::select! {
            _ = shutdown.cancelled() => return,
            p = permits.clone().acquire_owned() => p.expect("the semaphore is never closed"),
        };
        let (stream, addr) = tokio::select! {
            _ = shutdown.cancelled() => return,
            r = listener.accept() => match r {
                Ok(x) => x,
                Err(e) => {
                    warn!("peer listener: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
        };
        let (creds, job, shutdown) = (creds.clone(), job.clone(), shutdown.clone());
        tokio::spawn(async move {
            let _permit = permit;
            if let Err(e) = serve_peer(stream, &creds, job, shutdown).await {
                warn!(%addr, "peer link dropped: {e}");
            }
        });
    }
}

async fn serve_peer(
    stream: tokio::net::TcpStream,
    creds: &Credentials,
    mut job: watch::Receiver<Option<Arc<JobLink>>>,
    shutdown: CancellationToken,
) -> anyhow::Result<()> {
    let mut conn = handshake::accept(stream, creds, MAX_FRAME_LEN).await?;
    let hello = tokio::time::timeout(
        handshake::HANDSHAKE_TIMEOUT,
        conn.read_msg::<PeerMsg>("peer"),
    )
    .await
    .map_err(|_| anyhow::anyhow!("{}: no Hello after the handshake", conn.peer()))??;
    let Some(PeerMsg::Hello { job: id, from }) = hello else {
        anyhow::bail!("{}: expected Hello, got {hello:?}", conn.peer());
    };
    // The peer may have started the job a moment before we did.
    let link = tokio::time::timeout(
        Duration::from_secs(60),
        job.wait_for(|j| j.as_ref().is_some_and(|j| j.job == id)),
    )
    .await
    .map_err(|_| anyhow::anyhow!("{}: job {id} never started here", conn.peer()))??
    .clone()
    .expect("waited for Some");
    if from as usize >= link.traffic.0.len() {
        anyhow::bail!("{}: Hello from worker {from}, outside the job", conn.peer());
    }
    debug!(from, job = id, "peer link up");
    let (mut r, _w) = conn.into_split();
    let c = &link.traffic.0[from as usize];
    loop {
        let m = tokio::select! {
            _ = shutdown.cancelled() => return Ok(()),
            _ = link.cancel.cancelled() => return Ok(()),
            m = r.read_msg::<PeerMsg>("peer") => m?,
        };
        let Some((m, n)) = m else {
            return Ok(());
        };
        c.msgs_recv.fetch_add(1, Relaxed);
        c.bytes_recv.fetch_add(n as u64, Relaxed);
        let (engine, seed, sampler, workers) = match &link.inbox {
            Inbox::Engine {
                tx,
                seed,
                sampler,
                workers,
            } => (tx, *seed, *sampler, *workers),
            Inbox::Node(tx) => {
                let PeerMsg::Node(msg) = m else {
                    anyhow::bail!("{}: a render message in a radiosity job", r.peer());
                };
                if tx.send_async(*msg).await.is_err() {
                    return Ok(());
                }
                continue;
            }
        };
        let input = match m {
            PeerMsg::Node(_) => anyhow::bail!("{}: a radiosity message in a render job", r.peer()),
            PeerMsg::Packet(packet) => Input::Packet {
                from,
                items: Received::decode(from, &packet, seed, sampler, workers),
            },
            PeerMsg::Fetch(leaves) => Input::Fetch { from, leaves },
            PeerMsg::Leaf(leaf) => Input::Leaf {
                from,
                bytes: n as u64,
                leaf,
            },
            PeerMsg::Poll => Input::Poll { from },
            PeerMsg::Handed { queries, samples } => Input::Handed {
                from,
                queries,
                samples,
            },
            PeerMsg::NoWork { idle } => Input::NoWork { from, idle },
            PeerMsg::Hello { .. } => anyhow::bail!("{}: a second Hello", r.peer()),
        };
        if engine.send_async(Event::Input(input)).await.is_err() {
            return Ok(());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A peer that reads the `Hello` and closes its end (as a finished
    /// peer does): the writer's failed write cancels a render job, but only
    /// drops the link of a radiosity node; either way later sends fail at
    /// once rather than wait.
    #[tokio::test]
    async fn a_broken_link_ends_the_job_or_only_itself() {
        for (on_break, cancels) in [(OnBreak::CancelJob, true), (OnBreak::DropPeer, false)] {
            let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
            let addr = listener.local_addr().unwrap().to_string();
            let creds = Arc::new(Credentials::new("token", None));
            let server = creds.clone();
            let peer = tokio::spawn(async move {
                let (stream, _) = listener.accept().await.unwrap();
                let mut conn = handshake::accept(stream, &server, MAX_FRAME_LEN)
                    .await
                    .unwrap();
                let hello = conn.read_msg::<PeerMsg>("peer").await.unwrap();
                assert!(matches!(hello, Some(PeerMsg::Hello { job: 7, from: 0 })));
            });
            let (tx, rx) = flume::bounded(4);
            let cancel = CancellationToken::new();
            let traffic = Arc::new(Traffic::new(2));
            let writer = dial(
                &addr,
                &creds,
                7,
                0,
                1,
                rx,
                traffic,
                cancel.clone(),
                on_break,
            )
            .await
            .unwrap();
            peer.await.unwrap();
            let mut sent = 0;
            let gave_up = tokio::time::timeout(Duration::from_secs(20), async {
                while tx.send_async(PeerMsg::Poll.into()).await.is_ok() {
                    sent += 1;
                    tokio::time::sleep(Duration::from_millis(5)).await;
                }
            })
            .await;
            assert!(gave_up.is_ok(), "{on_break:?}: the writer never gave up");
            writer.await.unwrap();
            assert_eq!(
                cancel.is_cancelled(),
                cancels,
                "{on_break:?} after {sent} sends"
            );
            assert!(
                tx.send(PeerMsg::Poll.into()).is_err(),
                "a send after the break fails"
            );
        }
    }
}
