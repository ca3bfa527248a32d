//! The opening exchange of every connection: protocol version, then mutual
//! proof of the cluster token.
//!
//! ```text
//! client -> server  Hello     { version, nonce_c }
//! server -> client  Challenge { version, nonce_s, proof_s = HMAC(token, "locus-server" | nonce_c | nonce_s) }
//! client -> server  Proof     { proof_c = HMAC(token, "locus-client" | nonce_c | nonce_s) }
//! server -> client  Welcome
//! ```
//! Either side answers a wrong version or a failed proof with `Refused {
//! reason }` and closes; both sides return an error naming the cause. The
//! token itself never crosses the wire, and fresh nonces make a recorded
//! exchange useless.

use crate::PROTOCOL_VERSION;
use crate::connection::Connection;
use crate::error::ProtocolError;
use crate::stream::Stream;
use crate::tls::Tls;
use hmac::{Hmac, KeyInit, Mac};
use serde::{Deserialize, Serialize};
use sha2::Sha256;
use std::time::Duration;

/// Handshake messages. Append new variants only.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Handshake {
    Hello {
        version: u32,
        nonce: [u8; 32],
    },
    Challenge {
        version: u32,
        nonce: [u8; 32],
        proof: [u8; 32],
    },
    Proof {
        proof: [u8; 32],
    },
    Welcome,
    Refused {
        reason: String,
    },
}

impl Handshake {
    fn name(&self) -> &'static str {
        match self {
            Handshake::Hello { .. } => "Hello",
            Handshake::Challenge { .. } => "Challenge",
            Handshake::Proof { .. } => "Proof",
            Handshake::Welcome => "Welcome",
            Handshake::Refused { .. } => "Refused",
        }
    }
}

/// How long a peer may take over the whole handshake.
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// The largest frame either side reads before the peer has proved the
/// token: handshake messages take under 100 bytes (a refusal's reason a few
/// hundred), and an unauthenticated peer must not make a daemon buffer
/// more (with the 64 MiB of an authenticated frame, eight connections once
/// held 500 MB of a scheduler's memory in under a second).
pub const MAX_HANDSHAKE_FRAME: usize = 2048;

/// Runs `f` with the connection's frames limited to
/// [`MAX_HANDSHAKE_FRAME`], restoring its own limit only on success.
async fn limited<T>(
    conn: &mut Connection,
    f: impl AsyncFnOnce(&mut Connection) -> Result<T, ProtocolError>,
) -> Result<T, ProtocolError> {
    let full = conn.max_frame();
    conn.set_max_frame(full.min(MAX_HANDSHAKE_FRAME));
    let r = f(conn).await?;
    conn.set_max_frame(full);
    Ok(r)
}

fn nonce() -> [u8; 32] {
    let mut n = [0u8; 32];
    // The OS generator only fails on platforms locus does not run on; a
    // zero nonce would then still authenticate, only without freshness.
    if getrandom::fill(&mut n).is_err() {
        tracing::warn!("OS random generator unavailable; handshake nonce is not fresh");
    }
    n
}

fn mac(token: &[u8], label: &[u8], a: &[u8; 32], b: &[u8; 32]) -> Hmac<Sha256> {
    let mut m =
        <Hmac<Sha256> as KeyInit>::new_from_slice(token).expect("HMAC takes keys of any length");
    m.update(label);
    m.update(a);
    m.update(b);
    m
}

fn proof(token: &[u8], label: &[u8], a: &[u8; 32], b: &[u8; 32]) -> [u8; 32] {
    let out = mac(token, label, a, b).finalize().into_bytes();
    let mut p = [0u8; 32];
    p.copy_from_slice(&out);
    p
}

fn verify(token: &[u8], label: &[u8], a: &[u8; 32], b: &[u8; 32], tag: &[u8; 32]) -> bool {
    mac(token, label, a, b).verify_slice(tag).is_ok()
}

async fn next(conn: &mut Connection, during: &'static str) -> Result<Handshake, ProtocolError> {
    let peer = conn.peer();
    conn.read_msg::<Handshake>("handshake")
        .await?
        .ok_or(ProtocolError::Closed { peer, during })
}

async fn with_timeout<T>(
    conn_peer: std::net::SocketAddr,
    f: impl Future<Output = Result<T, ProtocolError>>,
) -> Result<T, ProtocolError> {
    tokio::time::timeout(HANDSHAKE_TIMEOUT, f)
        .await
        .map_err(|_| ProtocolError::Timeout {
            peer: conn_peer,
            what: "handshake",
        })?
}

/// The connecting side. `version` is [`PROTOCOL_VERSION`] except in tests.
pub async fn client(
    conn: &mut Connection,
    token: &[u8],
    version: u32,
) -> Result<(), ProtocolError> {
    limited(conn, async |conn| {
        client_exchange(conn, token, version).await
    })
    .await
}

async fn client_exchange(
    conn: &mut Connection,
    token: &[u8],
    version: u32,
) -> Result<(), ProtocolError> {
    let peer = conn.peer();
    with_timeout(peer, async {
        let nc = nonce();
        conn.write_msg(&Handshake::Hello { version, nonce: nc })
            .await?;
        let (ns, proof_s) = match next(conn, "handshake").await? {
            Handshake::Challenge {
                version: v,
                nonce,
                proof,
            } if v == version => (nonce, proof),
            Handshake::Challenge { version: v, .. } => {
                return Err(ProtocolError::Version {
                    peer,
                    ours: version,
                    theirs: v,
                });
            }
            Handshake::Refused { reason } => return Err(ProtocolError::Refused { peer, reason }),
            other => {
                return Err(ProtocolError::OutOfOrder {
                    peer,
                    expected: "Challenge",
                    got: other.name().into(),
                });
            }
        };
        if !verify(token, b"locus-server", &nc, &ns, &proof_s) {
            let reason = "wrong cluster token: the server could not prove it; give every node the same token".to_string();
            let _ = conn.write_msg(&Handshake::Refused { reason }).await;
            return Err(ProtocolError::WrongToken { peer });
        }
        conn.write_msg(&Handshake::Proof {
            proof: proof(token, b"locus-client", &nc, &ns),
        })
        .await?;
        match next(conn, "handshake").await? {
            Handshake::Welcome => Ok(()),
            Handshake::Refused { reason } => Err(ProtocolError::Refused { peer, reason }),
            other => Err(ProtocolError::OutOfOrder {
                peer,
                expected: "Welcome",
                got: other.name().into(),
            }),
        }
    })
    .await
}

/// The accepting side.
pub async fn server(conn: &mut Connection, token: &[u8]) -> Result<(), ProtocolError> {
    limited(conn, async |conn| server_exchange(conn, token).await).await
}

async fn server_exchange(conn: &mut Connection, token: &[u8]) -> Result<(), ProtocolError> {
    let peer = conn.peer();
    with_timeout(peer, async {
        let nc = match next(conn, "handshake").await? {
            Handshake::Hello { version, nonce } if version == PROTOCOL_VERSION => nonce,
            Handshake::Hello { version, .. } => {
                let reason = format!("protocol version mismatch: server speaks {PROTOCOL_VERSION}, client speaks {version}; run the same locus release on every node");
                let _ = conn.write_msg(&Handshake::Refused { reason }).await;
                return Err(ProtocolError::Version { peer, ours: PROTOCOL_VERSION, theirs: version });
            }
            other => return Err(ProtocolError::OutOfOrder { peer, expected: "Hello", got: other.name().into() }),
        };
        let ns = nonce();
        conn.write_msg(&Handshake::Challenge { version: PROTOCOL_VERSION, nonce: ns, proof: proof(token, b"locus-server", &nc, &ns) }).await?;
        match next(conn, "handshake").await? {
            Handshake::Proof { proof } if verify(token, b"locus-client", &nc, &ns, &proof) => {
                conn.write_msg(&Handshake::Welcome).await?;
                Ok(())
            }
            Handshake::Proof { .. } => {
                let reason = "wrong cluster token; give every node the same token".to_string();
                let _ = conn.write_msg(&Handshake::Refused { reason }).await;
                Err(ProtocolError::WrongToken { peer })
            }
            Handshake::Refused { reason } => Err(ProtocolError::Refused { peer, reason }),
            other => Err(ProtocolError::OutOfOrder { peer, expected: "Proof", got: other.name().into() }),
        }
    })
    .await
}

/// What a node needs to open a link: the cluster token, and the farm's
/// TLS when it is on.
#[derive(Clone, Debug)]
pub struct Credentials {
    pub token: Vec<u8>,
    pub tls: Option<Tls>,
}

impl Credentials {
    pub fn new(token: &str, tls: Option<Tls>) -> Self {
        Self {
            token: token.as_bytes().to_vec(),
            tls,
        }
    }
}

/// A token alone: plain TCP.
impl From<&str> for Credentials {
    fn from(token: &str) -> Self {
        Self::new(token, None)
    }
}

impl From<&String> for Credentials {
    fn from(token: &String) -> Self {
        Self::new(token, None)
    }
}

/// Connects to `addr`, with TLS when `creds` has it, and runs the client
/// side of the handshake with the current protocol version.
pub async fn dial(
    addr: &str,
    creds: &Credentials,
    max_frame: usize,
) -> Result<Connection, ProtocolError> {
    let connect_err = |source| ProtocolError::Connect {
        addr: addr.to_string(),
        source,
    };
    // A host that vanished answers no SYN: the kernel would retry for
    // minutes.
    let stream = tokio::time::timeout(HANDSHAKE_TIMEOUT, tokio::net::TcpStream::connect(addr))
        .await
        .map_err(|_| connect_err(std::io::ErrorKind::TimedOut.into()))?
        .map_err(connect_err)?;
    let stream = match &creds.tls {
        None => Stream::from(stream),
        Some(tls) => {
            let peer = stream.peer_addr().map_err(connect_err)?;
            tokio::time::timeout(HANDSHAKE_TIMEOUT, tls.connect(stream, peer))
                .await
                .map_err(|_| ProtocolError::Timeout {
                    peer,
                    what: "TLS handshake",
                })??
        }
    };
    let mut conn = Connection::new(stream, max_frame).map_err(connect_err)?;
    client(&mut conn, &creds.token, PROTOCOL_VERSION).await?;
    Ok(conn)
}

/// Serves an accepted connection: TLS first when `creds` has it, then the
/// server side of the handshake; both under [`HANDSHAKE_TIMEOUT`].
pub async fn accept(
    stream: tokio::net::TcpStream,
    creds: &Credentials,
    max_frame: usize,
) -> Result<Connection, ProtocolError> {
    let peer = stream.peer_addr().map_err(|e| ProtocolError::Connect {
        addr: "an accepted peer".into(),
        source: e,
    })?;
    let stream = match &creds.tls {
        None => Stream::from(stream),
        Some(tls) => tokio::time::timeout(HANDSHAKE_TIMEOUT, tls.accept(stream, peer))
            .await
            .map_err(|_| ProtocolError::Timeout {
                peer,
                what: "TLS handshake",
            })??,
    };
    let mut conn =
        Connection::new(stream, max_frame).map_err(|source| ProtocolError::Io { peer, source })?;
    server(&mut conn, &creds.token).await?;
    Ok(conn)
}
