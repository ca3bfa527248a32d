//! A framed TCP (or TLS) connection carrying postcard messages.
//!
//! [`Connection`] is used whole for request/response exchanges (the
//! handshake, registration); [`Connection::into_split`] gives a reader and a
//! writer half for the long-lived links where a reader task and a writer
//! task run side by side.

use crate::error::ProtocolError;
use crate::stream::{ReadSide, Stream, WriteSide};
use bytes::BytesMut;
use futures_util::{SinkExt, StreamExt};
use serde::Serialize;
use serde::de::DeserializeOwned;
use std::net::SocketAddr;
use tokio_util::codec::{Framed, FramedParts, FramedWrite, LengthDelimitedCodec};

/// Bytes a frame occupies on the wire besides its payload.
pub const FRAME_HEADER_LEN: usize = 4;

pub struct Connection {
    framed: Framed<Stream, LengthDelimitedCodec>,
    peer: SocketAddr,
    max_frame: usize,
}

pub struct ConnReader {
    /// A `Framed` over the read half only: built from the whole
    /// connection's parts, it decodes bytes already buffered before it
    /// reads the socket again (a `FramedRead` with a pre-filled buffer
    /// waits for new bytes first, which strands a frame that arrived
    /// together with the one read before the split).
    framed: Framed<ReadSide, LengthDelimitedCodec>,
    peer: SocketAddr,
    max_frame: usize,
}

pub struct ConnWriter {
    framed: FramedWrite<WriteSide, LengthDelimitedCodec>,
    peer: SocketAddr,
    max_frame: usize,
}

fn codec(max_frame: usize) -> LengthDelimitedCodec {
    LengthDelimitedCodec::builder()
        .length_field_type::<u32>()
        .max_frame_length(max_frame)
        .new_codec()
}

fn decode<T: DeserializeOwned>(
    frame: Option<std::io::Result<BytesMut>>,
    peer: SocketAddr,
    max: usize,
    what: &'static str,
) -> Result<Option<(T, usize)>, ProtocolError> {
    let frame = match frame {
        None => return Ok(None),
        // A TLS peer that closed without close_notify, between frames: a
        // close, as a plain TCP peer's FIN is (a frame cut short is still
        // an error of the codec's).
        Some(Err(e)) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(None),
        Some(f) => f,
    };
    let frame = frame.map_err(|e| {
        // The codec reports an oversized length prefix as InvalidData.
        if e.kind() == std::io::ErrorKind::InvalidData {
            ProtocolError::FrameTooLarge { peer, max }
        } else {
            ProtocolError::Io { peer, source: e }
        }
    })?;
    let len = frame.len() + FRAME_HEADER_LEN;
    postcard::from_bytes(&frame)
        .map(|m| Some((m, len)))
        .map_err(|e| ProtocolError::Decode {
            peer,
            what,
            message: e.to_string(),
        })
}

fn encode<T: Serialize>(
    msg: &T,
    peer: SocketAddr,
    max: usize,
) -> Result<bytes::Bytes, ProtocolError> {
    let fail = |e: postcard::Error| ProtocolError::Decode {
        peer,
        what: "outgoing",
        message: e.to_string(),
    };
    // Sized first, so that a packet of ray items is written once rather
    // than copied each time a growing buffer doubles.
    let len = postcard::experimental::serialized_size(msg).map_err(fail)?;
    if len > max {
        return Err(ProtocolError::FrameTooLarge { peer, max });
    }
    let bytes = postcard::to_extend(msg, Vec::with_capacity(len)).map_err(fail)?;
    if bytes.len() > max {
        return Err(ProtocolError::FrameTooLarge { peer, max });
    }
    Ok(bytes::Bytes::from(bytes))
}

/// Encodes `msg` and sends it as one frame on either a whole connection or
/// a writer half; returns the bytes it took on the wire.
async fn send<T, S>(
    sink: &mut S,
    msg: &T,
    peer: SocketAddr,
    max: usize,
) -> Result<usize, ProtocolError>
where
    T: Serialize,
    S: futures_util::Sink<bytes::Bytes, Error = std::io::Error> + Unpin,
{
    let b = encode(msg, peer, max)?;
    let n = b.len() + FRAME_HEADER_LEN;
    sink.send(b)
        .await
        .map_err(|e| ProtocolError::Io { peer, source: e })?;
    Ok(n)
}

impl Connection {
    /// A connection over a TCP stream, or TLS over one.
    pub fn new(stream: impl Into<Stream>, max_frame: usize) -> std::io::Result<Self> {
        let stream = stream.into();
        let peer = stream.tcp().peer_addr()?;
        stream.tcp().set_nodelay(true)?;
        Ok(Self {
            framed: Framed::new(stream, codec(max_frame)),
            peer,
            max_frame,
        })
    }

    pub fn peer(&self) -> SocketAddr {
        self.peer
    }

    /// Changes the largest frame this connection reads or writes: small
    /// until the handshake has authenticated the peer (see
    /// [`crate::handshake::MAX_HANDSHAKE_FRAME`]), then the caller's.
    pub fn set_max_frame(&mut self, max: usize) {
        self.framed.codec_mut().set_max_frame_length(max);
        self.max_frame = max;
    }

    pub fn max_frame(&self) -> usize {
        self.max_frame
    }

    /// This end's address: the interface the peer is reached through.
    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.framed.get_ref().tcp().local_addr()
    }

    /// The next message, or `None` when the peer closed the connection
    /// cleanly between frames. `what` names the message family in errors.
    pub async fn read_msg<T: DeserializeOwned>(
        &mut self,
        what: &'static str,
    ) -> Result<Option<T>, ProtocolError> {
        Ok(decode(self.framed.next().await, self.peer, self.max_frame, what)?.map(|(m, _)| m))
    }

    /// Writes one message; returns the bytes it took on the wire.
    pub async fn write_msg<T: Serialize>(&mut self, msg: &T) -> Result<usize, ProtocolError> {
        send(&mut self.framed, msg, self.peer, self.max_frame).await
    }

    /// Splits into independent reader and writer halves, keeping any bytes
    /// already read past the last frame.
    pub fn into_split(self) -> (ConnReader, ConnWriter) {
        let parts = self.framed.into_parts();
        let (rd, wr) = parts.io.into_split();
        let mut read = FramedParts::new::<bytes::Bytes>(rd, parts.codec);
        read.read_buf = parts.read_buf;
        let reader = Framed::from_parts(read);
        (
            ConnReader {
                framed: reader,
                peer: self.peer,
                max_frame: self.max_frame,
            },
            ConnWriter {
                framed: FramedWrite::new(wr, codec(self.max_frame)),
                peer: self.peer,
                max_frame: self.max_frame,
            },
        )
    }
}

impl ConnReader {
    pub fn peer(&self) -> SocketAddr {
        self.peer
    }

    /// The next message and the bytes it took on the wire; `None` on a
    /// clean close.
    pub async fn read_msg<T: DeserializeOwned>(
        &mut self,
        what: &'static str,
    ) -> Result<Option<(T, usize)>, ProtocolError> {
        decode(self.framed.next().await, self.peer, self.max_frame, what)
    }
}

impl ConnWriter {
    pub fn peer(&self) -> SocketAddr {
        self.peer
    }

    pub async fn write_msg<T: Serialize>(&mut self, msg: &T) -> Result<usize, ProtocolError> {
        send(&mut self.framed, msg, self.peer, self.max_frame).await
    }

    /// Writes `first` and up to `most - 1` more messages that `next` has
    /// ready, then flushes once: a burst goes out in one write where each
    /// message alone would be a write of its own and, on the other side, a
    /// wake-up of its own. Returns the bytes written.
    pub async fn write_burst<T: Serialize>(
        &mut self,
        first: &T,
        mut next: impl FnMut() -> Option<T>,
        most: usize,
    ) -> Result<usize, ProtocolError> {
        let io = |e| ProtocolError::Io {
            peer: self.peer,
            source: e,
        };
        let mut n = 0;
        let mut feed = |b: bytes::Bytes| {
            n += b.len() + FRAME_HEADER_LEN;
            b
        };
        let b = feed(encode(first, self.peer, self.max_frame)?);
        self.framed.feed(b).await.map_err(io)?;
        for _ in 1..most {
            let Some(m) = next() else { break };
            let b = feed(encode(&m, self.peer, self.max_frame)?);
            self.framed.feed(b).await.map_err(io)?;
        }
        SinkExt::<bytes::Bytes>::flush(&mut self.framed)
            .await
            .map_err(io)?;
        Ok(n)
    }
}
