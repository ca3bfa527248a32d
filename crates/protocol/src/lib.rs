//! locus-protocol: how the scheduler, the workers and `locus submit` talk.
//!
//! Messages are postcard-encoded and carried in length-delimited frames with
//! an explicit maximum length ([`connection::Connection`], after
//! mini-redis). Every connection opens with the [`handshake`]: protocol
//! version plus mutual proof of the shared cluster token by HMAC-SHA256 over
//! fresh nonces, so the token never crosses the wire; with [`tls`] on, the
//! link is TLS first ([`stream`] is either). Then one message
//! family per kind of link: [`control`] (scheduler and workers), [`submit`]
//! (client and scheduler), [`overture`] (the irradiance cache's records,
//! measured and shared level by level), [`rays`] (worker to worker, its ray items in
//! the compact encoding of [`packet`]), [`radiosity`] (the radiosity job's
//! shots, sample packets and random polling); [`report`] holds the
//! counters a job reports. postcard is not self-describing: enum variants
//! are only ever appended, never reordered or removed.

pub mod backoff;
pub mod connection;
pub mod control;
pub mod error;
pub mod handshake;
pub mod overture;
pub mod packet;
pub mod radiosity;
pub mod rays;
pub mod report;
pub mod stream;
pub mod submit;
#[cfg(feature = "testing")]
pub mod testing;
pub mod tls;

pub use backoff::Backoff;
pub use connection::{ConnReader, ConnWriter, Connection};
pub use error::ProtocolError;

/// Bumped on any incompatible change of any message family.
pub const PROTOCOL_VERSION: u32 = 28;

/// Default maximum frame length: large enough for a geometry shipment of a
/// big octree leaf, small enough that a bad length prefix cannot make a peer
/// allocate gigabytes.
pub const MAX_FRAME_LEN: usize = 64 << 20;

/// Connections a daemon serves at once (a semaphore, as in mini-redis);
/// more wait in the kernel's backlog until one closes, so no number of
/// clients can exhaust its memory or file descriptors.
pub const MAX_CONNECTIONS: usize = 1024;
