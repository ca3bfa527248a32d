//! The library half of the `locus` command: the local farm of in-process or
//! child-process workers ([`farm`]), daemon configuration and presets
//! ([`config`]), the `locus status` client ([`status`]) and signal
//! handling, shared by the binary and the integration tests; the SVG line
//! plots every figure uses ([`plot`]); and apart from them, the benchmarks
//! ([`bench`](mod@bench)).

pub mod bench;
pub mod config;
pub mod farm;
pub mod plot;
pub mod status;

use tokio_util::sync::CancellationToken;

/// Cancels `token` on SIGINT or SIGTERM.
pub fn cancel_on_signals(token: CancellationToken) {
    tokio::spawn(async move {
        #[cfg(unix)]
        {
            use tokio::signal::unix::{SignalKind, signal};
            let mut term = match signal(SignalKind::terminate()) {
                Ok(s) => s,
                Err(e) => {
                    tracing::warn!("cannot watch SIGTERM: {e}");
                    let _ = tokio::signal::ctrl_c().await;
                    token.cancel();
                    return;
                }
            };
            tokio::select! {
                _ = tokio::signal::ctrl_c() => tracing::info!("SIGINT: shutting down"),
                _ = term.recv() => tracing::info!("SIGTERM: shutting down"),
                _ = token.cancelled() => {}
            }
        }
        #[cfg(not(unix))]
        {
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = token.cancelled() => {}
            }
        }
        token.cancel();
    });
}
