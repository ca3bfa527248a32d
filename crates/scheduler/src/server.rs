//! One task per connection: the handshake, then the opening message says
//! whether the peer is a worker or a client. A worker's link carries
//! heartbeats both ways: the scheduler sends one every interval, and a
//! worker silent for [`HEARTBEATS_MISSED`] intervals (stopped, crashed
//! without closing its socket, cut off) is dropped, which the actor sees
//! as the worker leaving. A client's link carries its job's messages; the
//! client closing it cancels the job.

use crate::actor::Event;
use crate::frames::SharedFrames;
use locus_core::geometry::NORMALS_BYTES;
use locus_protocol::connection::encode;
use locus_protocol::control::{
    HEARTBEATS_MISSED, Opening, Registration, SchedulerToWorker, WorkerToScheduler,
};
use locus_protocol::submit::{JobRequest, SchedulerToClient, TrianglePart};
use locus_protocol::{ConnReader, ConnWriter, Connection, MAX_FRAME_LEN, handshake};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{info, instrument};

/// What every connection task shares.
#[derive(Clone)]
pub(crate) struct Shared {
    pub creds: std::sync::Arc<handshake::Credentials>,
    pub events: mpsc::Sender<Event>,
    pub shutdown: CancellationToken,
    /// How long a worker may be silent before it is lost.
    pub worker_timeout: Duration,
    /// Whether jobs are kept in a store: then requests are encoded here.
    pub store: bool,
    /// Parts several workers are sent alike, encoded once for all.
    pub frames: Arc<SharedFrames>,
}

impl Shared {
    /// `req` and, with a store, its encoding for it, made on a blocking
    /// thread (a scene of millions of triangles takes a while).
    async fn encoded(&self, req: Box<JobRequest>) -> (Box<JobRequest>, Option<Vec<u8>>) {
        if !self.store {
            return (req, None);
        }
        tokio::task::spawn_blocking(move || {
            let bytes = postcard::to_allocvec(&*req).ok();
            (req, bytes)
        })
        .await
        .expect("encoding a request does not panic")
    }
}

#[instrument(skip_all, fields(conn = id, peer = %stream.peer_addr().map(|a| a.to_string()).unwrap_or_default()))]
pub(crate) async fn serve(
    stream: tokio::net::TcpStream,
    id: u32,
    sh: Shared,
) -> anyhow::Result<()> {
    let mut conn = handshake::accept(stream, &sh.creds, MAX_FRAME_LEN).await?;
    let opening = tokio::select! {
        _ = sh.shutdown.cancelled() => return Ok(()),
        m = tokio::time::timeout(handshake::HANDSHAKE_TIMEOUT, conn.read_msg::<Opening>("opening")) => m
            .map_err(|_| anyhow::anyhow!("{}: no opening message after the handshake", conn.peer()))??,
    };
    match opening {
        None => Ok(()),
        Some(Opening::Register(reg)) => worker(conn, id, reg, sh).await,
        Some(Opening::Submit(req)) => submitted(conn, req, sh).await,
        Some(Opening::SubmitInParts {
            request,
            triangles,
            normals,
        }) => match receive_parts(&mut conn, request, triangles, normals).await {
            Ok(req) => submitted(conn, req, sh).await,
            Err(reason) => {
                info!(peer = %conn.peer(), "request refused: {reason}");
                let _ = conn
                    .write_msg(&SchedulerToClient::Failed { job: 0, reason })
                    .await;
                Ok(())
            }
        },
        Some(Opening::Attach { job }) => {
            client(conn, |client| Event::Attach { job, client }, sh).await
        }
    }
}

/// A request received whole: encoded for the store, handed to the actor,
/// and its job's messages served to the client.
async fn submitted(conn: Connection, req: Box<JobRequest>, sh: Shared) -> anyhow::Result<()> {
    let (req, encoded) = sh.encoded(req).await;
    let submit = |client| Event::Submit {
        req,
        client,
        encoded,
    };
    client(conn, submit, sh).await
}

/// The heartbeat interval for a worker timeout.
fn interval(timeout: Duration) -> Duration {
    (timeout / HEARTBEATS_MISSED).max(Duration::from_millis(10))
}

async fn worker(
    mut conn: Connection,
    id: u32,
    reg: Registration,
    sh: Shared,
) -> anyhow::Result<()> {
    let every = interval(sh.worker_timeout);
    conn.write_msg(&SchedulerToWorker::Welcome {
        worker: id,
        heartbeat_ms: every.as_millis().min(u32::MAX as u128) as u32,
    })
    .await?;
    let addr = conn.peer();
    let (r, w) = conn.into_split();
    let (tx, rx) = mpsc::channel::<SchedulerToWorker>(256);
    info!(worker = id, listen = %reg.listen, cores = reg.cores, "worker registered");
    sh.events.send(Event::Joined { id, reg, addr, tx }).await?;
    let writer = tokio::spawn(write_worker(w, rx, every, sh.frames.clone()));
    let reason = read_worker(r, id, &sh).await;
    writer.abort();
    let _ = sh.events.send(Event::Left { id, reason }).await;
    Ok(())
}

/// Writes the actor's messages to a worker, and a heartbeat whenever the
/// link has been quiet for an interval.
async fn write_worker(
    mut w: ConnWriter,
    mut rx: mpsc::Receiver<SchedulerToWorker>,
    every: Duration,
    frames: Arc<SharedFrames>,
) -> Result<(), locus_protocol::ProtocolError> {
    let (peer, max) = (w.peer(), w.max_frame());
    loop {
        let m = match tokio::time::timeout(every, rx.recv()).await {
            Ok(Some(m)) => m,
            Ok(None) => return Ok(()),
            Err(_) => SchedulerToWorker::Heartbeat,
        };
        // The tiles of one request (and whatever else is queued) go in one
        // write: the worker's runtime wakes once for them. A part other
        // workers are sent too is encoded once for all of them.
        let frame = |m: &SchedulerToWorker| frames.frame(m, |m| encode(m, peer, max));
        let written = w
            .write_burst_frames(&m, || rx.try_recv().ok(), BURST, frame)
            .await;
        drop(m);
        frames.prune();
        written?;
    }
}

/// The most messages written to a worker with one flush.
const BURST: usize = 64;

/// Reads a worker's messages into the actor until the link ends; returns
/// why it ended.
async fn read_worker(mut r: ConnReader, id: u32, sh: &Shared) -> String {
    loop {
        let m = tokio::select! {
            _ = sh.shutdown.cancelled() => return "scheduler shutting down".into(),
            m = tokio::time::timeout(sh.worker_timeout, r.read_msg::<WorkerToScheduler>("control")) => m,
        };
        match m {
            Err(_) => {
                return format!(
                    "no heartbeat for {:.1} s (stopped, crashed or cut off)",
                    sh.worker_timeout.as_secs_f64()
                );
            }
            Ok(Ok(Some((WorkerToScheduler::Heartbeat, _)))) => {}
            Ok(Ok(Some((msg, _)))) => {
                if sh.events.send(Event::FromWorker { id, msg }).await.is_err() {
                    return "scheduler shutting down".into();
                }
            }
            Ok(Ok(None)) => return "closed the connection".into(),
            Ok(Err(e)) => return e.to_string(),
        }
    }
}

/// How long the next part of a request may take to arrive.
const PART_TIMEOUT: Duration = Duration::from_secs(60);

/// Reads the `triangles` triangles of a request sent in parts (each with
/// its shading normals when `normals`); refuses a request the memory
/// available cannot hold (its triangles twice: the request, and the
/// store's copy as it is written), a part longer than announced or whose
/// lists differ in length, and a link that stalls.
async fn receive_parts(
    conn: &mut Connection,
    mut req: Box<JobRequest>,
    triangles: u64,
    normals: bool,
) -> Result<Box<JobRequest>, String> {
    let each = TRIANGLE_REQUEST_BYTES + if normals { NORMALS_BYTES } else { 0 };
    let bytes = triangles.saturating_mul(2 * each);
    if let Some(have) = locus_core::limits::available_memory()
        && bytes > have
    {
        return Err(format!(
            "{}: {triangles} triangles need {:.2} GiB on the scheduler, but {:.2} GiB of memory is available",
            req.name,
            bytes as f64 / (1u64 << 30) as f64,
            have as f64 / (1u64 << 30) as f64
        ));
    }
    req.tris.clear();
    req.tri_material.clear();
    req.tri_normals.clear();
    while (req.tris.len() as u64) < triangles {
        let part =
            tokio::time::timeout(PART_TIMEOUT, conn.read_msg::<TrianglePart>("request part"))
                .await
                .map_err(|_| format!("no part of the request for {PART_TIMEOUT:?}"))?
                .map_err(|e| e.to_string())?
                .ok_or("the client closed the connection within its request")?;
        let left = triangles - req.tris.len() as u64;
        let shading = if normals { part.tris.len() } else { 0 };
        if part.tris.len() != part.material.len()
            || part.normals.len() != shading
            || part.tris.len() as u64 > left
        {
            return Err(format!(
                "a request part of {} triangles, {} materials and {} sets of normals \
                 (announced: {}), with {left} triangles left",
                part.tris.len(),
                part.material.len(),
                part.normals.len(),
                if normals { "with normals" } else { "without" }
            ));
        }
        if part.tris.is_empty() {
            return Err("an empty request part".into());
        }
        req.tris.extend_from_slice(&part.tris);
        req.tri_material.extend_from_slice(&part.material);
        req.tri_normals.extend_from_slice(&part.normals);
    }
    Ok(req)
}

/// Bytes a request holds per triangle: three corners and a material.
const TRIANGLE_REQUEST_BYTES: u64 = 3 * 12 + 4;

/// A client's link: `opening` is its request (a job, or a job to attach
/// to) with the channel its job's messages come on.
async fn client(
    conn: Connection,
    opening: impl FnOnce(mpsc::Sender<SchedulerToClient>) -> Event,
    sh: Shared,
) -> anyhow::Result<()> {
    let addr = conn.peer();
    let (tx, mut rx) = mpsc::channel::<SchedulerToClient>(64);
    sh.events.send(opening(tx)).await?;
    let (mut r, mut conn) = conn.into_split();
    loop {
        let m = tokio::select! {
            _ = sh.shutdown.cancelled() => return Ok(()),
            m = rx.recv() => m,
            // A client says nothing after its request: a read that ends
            // is the client gone, and dropping `rx` tells the actor to
            // cancel its job.
            gone = r.read_msg::<Opening>("submit") => {
                let why = match gone {
                    Ok(None) => "closed the connection".to_string(),
                    Ok(Some(_)) => "sent a second request".to_string(),
                    Err(e) => e.to_string(),
                };
                info!(%addr, "client {why}; its job is cancelled");
                return Ok(());
            }
        };
        let Some(m) = m else { return Ok(()) };
        let last = matches!(
            m,
            SchedulerToClient::Done(_) | SchedulerToClient::Failed { .. }
        );
        conn.write_msg(&m).await?;
        if last {
            return Ok(());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::interval;
    use std::time::Duration;

    #[test]
    fn heartbeats_come_several_times_within_the_timeout() {
        assert_eq!(interval(Duration::from_secs(5)), Duration::from_secs(1));
        assert_eq!(
            interval(Duration::from_millis(1)),
            Duration::from_millis(10)
        );
    }
}
