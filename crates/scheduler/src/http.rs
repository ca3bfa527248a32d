//! The scheduler's HTTP face (axum), on its own address, read-only:
//! - `/status`: the farm as JSON ([`crate::status::Status`]);
//! - `/metrics`: Prometheus text ([`crate::metrics`]);
//! - `/jobs/{id}/preview.png`: the job's image so far;
//! - `/`: a page that shows the workers, the running job's regions and
//!   progress, the traffic between the last job's workers, and the preview
//!   refining as tiles arrive.
//!
//! Nothing here changes the farm, so it needs no token; bind it where only
//! those who may watch can reach it. Like every daemon socket it is
//! bounded: at most [`MAX_CONNECTIONS`] connections (a semaphore, as in
//! mini-redis), each closed after [`IDLE`] without a byte, and every
//! request answered within [`ANSWER`] or refused.

use crate::actor::Event;
use crate::metrics::Metrics;
use axum::Router;
use axum::extract::{Path, State};
use axum::http::{StatusCode, header};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc, oneshot};
use tokio_io_timeout::TimeoutStream;
use tokio_util::sync::CancellationToken;

pub const MAX_CONNECTIONS: usize = 64;
pub const IDLE: Duration = Duration::from_secs(30);
pub const ANSWER: Duration = Duration::from_secs(10);

const PAGE: &str = include_str!("page.html");

#[derive(Clone)]
struct Ctx {
    events: mpsc::Sender<Event>,
    metrics: Arc<Metrics>,
}

/// Serves until `shutdown`.
pub async fn serve(
    listener: TcpListener,
    events: mpsc::Sender<Event>,
    metrics: Arc<Metrics>,
    shutdown: CancellationToken,
) -> std::io::Result<()> {
    let app = Router::new()
        .route("/", get(|| async { Html(PAGE) }))
        .route("/status", get(status))
        .route("/metrics", get(metrics_text))
        .route("/jobs/{id}/preview.png", get(preview))
        .with_state(Ctx { events, metrics });
    let limited = Limited {
        inner: listener,
        permits: Arc::new(Semaphore::new(MAX_CONNECTIONS)),
    };
    axum::serve(limited, app)
        .with_graceful_shutdown(async move { shutdown.cancelled().await })
        .await
}

/// Asks the actor and waits for its answer, within [`ANSWER`].
async fn ask<T>(
    events: &mpsc::Sender<Event>,
    make: impl FnOnce(oneshot::Sender<T>) -> Event,
) -> Result<T, Response> {
    let unavailable = || {
        (
            StatusCode::SERVICE_UNAVAILABLE,
            "the scheduler did not answer in time",
        )
            .into_response()
    };
    let (tx, rx) = oneshot::channel();
    let asked = tokio::time::timeout(ANSWER, async {
        events.send(make(tx)).await.ok()?;
        rx.await.ok()
    });
    asked.await.ok().flatten().ok_or_else(unavailable)
}

async fn status(State(c): State<Ctx>) -> Response {
    match ask(&c.events, Event::Status).await {
        Ok(s) => axum::Json(s).into_response(),
        Err(r) => r,
    }
}

async fn metrics_text(State(c): State<Ctx>) -> Response {
    (
        [(
            header::CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )],
        c.metrics.encode(),
    )
        .into_response()
}

async fn preview(State(c): State<Ctx>, Path(id): Path<u64>) -> Response {
    let image = match ask(&c.events, |reply| Event::Preview { job: id, reply }).await {
        Ok(Some(i)) => i,
        Ok(None) => {
            return (
                StatusCode::NOT_FOUND,
                format!("job {id} is neither running nor the last one ended"),
            )
                .into_response();
        }
        Err(r) => return r,
    };
    // Encoding is CPU work: off the async runtime.
    match tokio::task::spawn_blocking(move || image.encode_png(1.0)).await {
        Ok(Ok(png)) => (
            [
                (header::CONTENT_TYPE, "image/png"),
                (header::CACHE_CONTROL, "no-store"),
            ],
            png,
        )
            .into_response(),
        Ok(Err(e)) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}

/// A listener that holds a permit per open connection and closes a
/// connection that sends or takes nothing for [`IDLE`].
struct Limited {
    inner: TcpListener,
    permits: Arc<Semaphore>,
}

/// A connection and the permit it holds until it is dropped.
struct Conn {
    io: Pin<Box<TimeoutStream<TcpStream>>>,
    _permit: OwnedSemaphorePermit,
}

impl axum::serve::Listener for Limited {
    type Io = Conn;
    type Addr = std::net::SocketAddr;

    async fn accept(&mut self) -> (Conn, Self::Addr) {
        loop {
            // Waiting for a permit first leaves further connections in
            // the kernel's backlog rather than in memory here.
            let permit = self
                .permits
                .clone()
                .acquire_owned()
                .await
                .expect("the semaphore is never closed");
            match self.inner.accept().await {
                Ok((s, addr)) => {
                    let mut io = TimeoutStream::new(s);
                    io.set_read_timeout(Some(IDLE));
                    io.set_write_timeout(Some(IDLE));
                    let conn = Conn {
                        io: Box::pin(io),
                        _permit: permit,
                    };
                    return (conn, addr);
                }
                Err(e) => {
                    tracing::warn!("status: accept: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            }
        }
    }

    fn local_addr(&self) -> std::io::Result<Self::Addr> {
        self.inner.local_addr()
    }
}

impl tokio::io::AsyncRead for Conn {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &mut tokio::io::ReadBuf<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        self.io.as_mut().poll_read(cx, buf)
    }
}

impl tokio::io::AsyncWrite for Conn {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &[u8],
    ) -> std::task::Poll<std::io::Result<usize>> {
        self.io.as_mut().poll_write(cx, buf)
    }

    fn poll_flush(
        mut self: Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        self.io.as_mut().poll_flush(cx)
    }

    fn poll_shutdown(
        mut self: Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        self.io.as_mut().poll_shutdown(cx)
    }
}
