//! A framed TCP connection carrying postcard messages.

use crate::error::ProtocolError;
use futures_util::{SinkExt, StreamExt};
use serde::Serialize;
use serde::de::DeserializeOwned;
use std::net::SocketAddr;
use tokio::net::TcpStream;
use tokio_util::codec::{Framed, LengthDelimitedCodec};

pub struct Connection {
    framed: Framed<TcpStream, LengthDelimitedCodec>,
    peer: SocketAddr,
    max_frame: usize,
}

impl Connection {
    pub fn new(stream: TcpStream, max_frame: usize) -> std::io::Result<Self> {
        let peer = stream.peer_addr()?;
        stream.set_nodelay(true)?;
        let codec = LengthDelimitedCodec::builder()
            .length_field_type::<u32>()
            .max_frame_length(max_frame)
            .new_codec();
        Ok(Self {
            framed: Framed::new(stream, codec),
            peer,
            max_frame,
        })
    }

    pub fn peer(&self) -> SocketAddr {
        self.peer
    }

    /// The next message, or `None` when the peer closed the connection
    /// cleanly between frames. `what` names the message family in errors.
    pub async fn read_msg<T: DeserializeOwned>(
        &mut self,
        what: &'static str,
    ) -> Result<Option<T>, ProtocolError> {
        let Some(frame) = self.framed.next().await else {
            return Ok(None);
        };
        let frame = frame.map_err(|e| {
            // The codec reports an oversized length prefix as InvalidData.
            if e.kind() == std::io::ErrorKind::InvalidData {
                ProtocolError::FrameTooLarge {
                    peer: self.peer,
                    max: self.max_frame,
                }
            } else {
                ProtocolError::Io {
                    peer: self.peer,
                    source: e,
                }
            }
        })?;
        postcard::from_bytes(&frame)
            .map(Some)
            .map_err(|e| ProtocolError::Decode {
                peer: self.peer,
                what,
                message: e.to_string(),
            })
    }

    pub async fn write_msg<T: Serialize>(&mut self, msg: &T) -> Result<(), ProtocolError> {
        let bytes = postcard::to_stdvec(msg).map_err(|e| ProtocolError::Decode {
            peer: self.peer,
            what: "outgoing",
            message: e.to_string(),
        })?;
        if bytes.len() > self.max_frame {
            return Err(ProtocolError::FrameTooLarge {
                peer: self.peer,
                max: self.max_frame,
            });
        }
        self.framed
            .send(bytes::Bytes::from(bytes))
            .await
            .map_err(|e| ProtocolError::Io {
                peer: self.peer,
                source: e,
            })
    }
}
