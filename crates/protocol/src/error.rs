//! Errors of a connection; each names the peer.

use std::net::SocketAddr;

impl ProtocolError {
    /// Whether the peer refused us (another protocol version, a wrong
    /// token, a stated refusal): trying again cannot help, unlike a peer
    /// that cannot be reached or a link that broke.
    pub fn is_refusal(&self) -> bool {
        matches!(
            self,
            Self::Version { .. }
                | Self::WrongToken { .. }
                | Self::Refused { .. }
                | Self::Tls { fatal: true, .. }
        )
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ProtocolError {
    #[error("{peer}: {source}")]
    Io {
        peer: SocketAddr,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{peer}: frame exceeds the maximum of {max} bytes; the peer is not speaking the locus protocol or needs a larger frame limit"
    )]
    FrameTooLarge { peer: SocketAddr, max: usize },
    #[error("{peer}: undecodable {what} message: {message}")]
    Decode {
        peer: SocketAddr,
        what: &'static str,
        message: String,
    },
    #[error("{peer}: connection closed during {during}")]
    Closed {
        peer: SocketAddr,
        during: &'static str,
    },
    #[error("{peer}: expected {expected}, got {got}")]
    OutOfOrder {
        peer: SocketAddr,
        expected: &'static str,
        got: String,
    },
    #[error(
        "{peer}: protocol version mismatch: we speak {ours}, peer speaks {theirs}; run the same locus release on every node"
    )]
    Version {
        peer: SocketAddr,
        ours: u32,
        theirs: u32,
    },
    #[error(
        "{peer}: wrong cluster token (the peer could not prove it); give every node the same token"
    )]
    WrongToken { peer: SocketAddr },
    #[error("{peer}: refused by peer: {reason}")]
    Refused { peer: SocketAddr, reason: String },
    #[error("{peer}: {what} timed out")]
    Timeout {
        peer: SocketAddr,
        what: &'static str,
    },
    #[error("{peer}: {message}")]
    Tls {
        peer: SocketAddr,
        message: String,
        /// TLS refused (see `tls`), rather than the link failing.
        fatal: bool,
    },
    #[error("cannot connect to {addr}: {source}")]
    Connect {
        addr: String,
        #[source]
        source: std::io::Error,
    },
}
