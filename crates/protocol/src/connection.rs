//! A framed TCP (or TLS) connection carrying postcard messages.
//!
//! [`Connection`] is used whole for request/response exchanges (the
//! handshake, registration); [`Connection::into_split`] gives a reader and a
//! writer half for the long-lived links where a reader task and a writer
//! task run side by side.

use crate::error::ProtocolError;
use crate::stream::{ReadSide, Stream, WriteSide};
use bytes::{Buf, BytesMut};
use futures_util::{SinkExt, StreamExt};
use serde::Serialize;
use serde::de::DeserializeOwned;
use std::net::SocketAddr;
use tokio::io::{AsyncWrite, AsyncWriteExt};
use tokio_util::codec::{Framed, FramedParts, FramedWrite, LengthDelimitedCodec};

/// Bytes a frame occupies on the wire besides its payload.
pub const FRAME_HEADER_LEN: usize = 4;

/// A frame at least this long is written straight to the socket from its
/// own bytes instead of being copied into the codec's write buffer, which
/// would otherwise keep the largest frame's allocation for the
/// connection's life: a region part ships in up to 48 MiB, on one link per
/// worker of the scheduler. (The codec's read buffer does not keep one: a
/// frame is split off it whole.)
pub const LARGE_FRAME: usize = 256 << 10;

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

/// `msg` encoded as the payload of one frame for `peer`, at most `max`
/// bytes: what [`ConnWriter::write_burst_frames`] writes, for a caller that
/// writes one message to several peers and encodes it once.
pub fn encode<T: Serialize>(
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

/// A framed sink whose socket can also be written directly.
trait FrameSink: futures_util::Sink<bytes::Bytes, Error = std::io::Error> + Unpin {
    type Io: AsyncWrite + Unpin;
    fn io(&mut self) -> &mut Self::Io;
}

impl FrameSink for Framed<Stream, LengthDelimitedCodec> {
    type Io = Stream;
    fn io(&mut self) -> &mut Stream {
        self.get_mut()
    }
}

impl FrameSink for FramedWrite<WriteSide, LengthDelimitedCodec> {
    type Io = WriteSide;
    fn io(&mut self) -> &mut WriteSide {
        self.get_mut()
    }
}

/// Queues one encoded frame: a small one in the codec's buffer, a
/// [`LARGE_FRAME`] after what is buffered, written from its own bytes
/// (the codec's header, a big-endian u32 length, then the payload).
async fn put<S: FrameSink>(sink: &mut S, b: bytes::Bytes) -> std::io::Result<()> {
    if b.len() < LARGE_FRAME {
        return sink.feed(b).await;
    }
    SinkExt::<bytes::Bytes>::flush(sink).await?;
    let len = u32::try_from(b.len()).map_err(|_| std::io::ErrorKind::InvalidInput)?;
    let header = len.to_be_bytes();
    sink.io()
        .write_all_buf(&mut header.as_slice().chain(b))
        .await
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
    S: FrameSink,
{
    let b = encode(msg, peer, max)?;
    let n = b.len() + FRAME_HEADER_LEN;
    let io = |e| ProtocolError::Io { peer, source: e };
    put(sink, b).await.map_err(io)?;
    SinkExt::<bytes::Bytes>::flush(sink).await.map_err(io)?;
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

    /// The largest frame this writer writes.
    pub fn max_frame(&self) -> usize {
        self.max_frame
    }

    /// Writes `first` and up to `most - 1` more messages that `next` has
    /// ready, then flushes once: a burst goes out in one write where each
    /// message alone would be a write of its own and, on the other side, a
    /// wake-up of its own. Returns the bytes written.
    pub async fn write_burst<T: Serialize>(
        &mut self,
        first: &T,
        next: impl FnMut() -> Option<T>,
        most: usize,
    ) -> Result<usize, ProtocolError> {
        let (peer, max) = (self.peer, self.max_frame);
        self.write_burst_frames(first, next, most, |m| encode(m, peer, max))
            .await
    }

    /// [`Self::write_burst`] with each message's frame from `frame`, which
    /// may hand back one [`encode`]d before for another peer (a message
    /// several peers are sent alike, encoded once). A frame longer than
    /// this writer's largest is refused as [`encode`] refuses it.
    pub async fn write_burst_frames<T>(
        &mut self,
        first: &T,
        mut next: impl FnMut() -> Option<T>,
        most: usize,
        mut frame: impl FnMut(&T) -> Result<bytes::Bytes, ProtocolError>,
    ) -> Result<usize, ProtocolError> {
        let (peer, max) = (self.peer, self.max_frame);
        let io = |e| ProtocolError::Io { peer, source: e };
        let mut n = 0;
        let mut feed = |b: bytes::Bytes| {
            if b.len() > max {
                return Err(ProtocolError::FrameTooLarge { peer, max });
            }
            n += b.len() + FRAME_HEADER_LEN;
            Ok(b)
        };
        let b = feed(frame(first)?)?;
        put(&mut self.framed, b).await.map_err(io)?;
        for _ in 1..most {
            let Some(m) = next() else { break };
            let b = feed(frame(&m)?)?;
            put(&mut self.framed, b).await.map_err(io)?;
        }
        SinkExt::<bytes::Bytes>::flush(&mut self.framed)
            .await
            .map_err(io)?;
        Ok(n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::net::{TcpListener, TcpStream};

    /// A large frame crosses whole between small ones, in order, from a
    /// whole connection and in a burst from a writer half; afterwards
    /// neither side's buffer keeps its size.
    #[tokio::test]
    async fn a_large_frame_leaves_no_large_buffer_behind() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let max = 64 << 20;
        let big: Vec<u32> = (0..3_000_000u32)
            .map(|i| i.wrapping_mul(2_654_435_761))
            .collect();
        let expect = big.clone();
        let reader = tokio::spawn(async move {
            let (s, _) = listener.accept().await.unwrap();
            let (mut r, _w) = Connection::new(s, max).unwrap().into_split();
            let mut got = Vec::new();
            for _ in 0..6 {
                let (m, n) = r.read_msg::<Vec<u32>>("test").await.unwrap().unwrap();
                got.push((m, n));
            }
            (got, keeps_a_megabyte(r.framed.read_buffer_mut()))
        });
        let mut conn = Connection::new(TcpStream::connect(addr).await.unwrap(), max).unwrap();
        let sizes = [
            conn.write_msg(&vec![1u32, 2]).await.unwrap(),
            conn.write_msg(&big).await.unwrap(),
        ];
        let whole_buffer = keeps_a_megabyte(conn.framed.write_buffer_mut());
        let (_r, mut w) = conn.into_split();
        let mut rest = vec![big.clone(), vec![3u32], vec![]].into_iter();
        let burst = w
            .write_burst(&vec![7u32; 10], || rest.next(), 8)
            .await
            .unwrap();
        let half_buffer = keeps_a_megabyte(w.framed.write_buffer_mut());
        let (got, read_buffer) = reader.await.unwrap();
        let msgs: Vec<&Vec<u32>> = got.iter().map(|(m, _)| m).collect();
        let want: Vec<Vec<u32>> = vec![
            vec![1, 2],
            expect.clone(),
            vec![7; 10],
            expect,
            vec![3],
            vec![],
        ];
        assert!(
            msgs.iter().zip(&want).all(|(a, b)| *a == b),
            "frames differ"
        );
        assert_eq!(got[0].1, sizes[0]);
        assert_eq!(got[1].1, sizes[1]);
        assert_eq!(got[2..].iter().map(|(_, n)| n).sum::<usize>(), burst);
        assert!(sizes[1] > 4 * 3_000_000, "{sizes:?}");
        for (what, keeps) in [
            ("a connection's write buffer", whole_buffer),
            ("a writer half's buffer", half_buffer),
            ("the read buffer", read_buffer),
        ] {
            assert!(!keeps, "{what} kept the large frame's allocation");
        }
    }

    /// Whether a buffer holds an allocation with room for a megabyte (the
    /// big frame takes 15 MB), reachable without allocating anew:
    /// `capacity` alone shows only what lies beyond the buffer's start.
    fn keeps_a_megabyte(b: &mut BytesMut) -> bool {
        b.try_reclaim(1 << 20)
    }
}
