//! The handshake and framing over real loopback sockets (127.0.0.1:0):
//! right token and version pass; a wrong token or version is refused with a
//! message on both sides; garbage, an oversized length prefix and a
//! truncated frame close that connection with an error, never a panic, and
//! the listener keeps serving.

use locus_protocol::handshake::{self, Handshake};
use locus_protocol::{Connection, MAX_FRAME_LEN, PROTOCOL_VERSION, ProtocolError};
use proptest::prelude::*;
use tokio::io::AsyncWriteExt;
use tokio::net::{TcpListener, TcpStream};

async fn pair() -> (TcpListener, std::net::SocketAddr) {
    let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let a = l.local_addr().unwrap();
    (l, a)
}

async fn run(
    server_token: &'static [u8],
    client_token: &'static [u8],
    version: u32,
) -> (Result<(), ProtocolError>, Result<(), ProtocolError>) {
    let (l, addr) = pair().await;
    let srv = tokio::spawn(async move {
        let (s, _) = l.accept().await.unwrap();
        let mut c = Connection::new(s, MAX_FRAME_LEN).unwrap();
        handshake::server(&mut c, server_token).await
    });
    let mut c = Connection::new(TcpStream::connect(addr).await.unwrap(), MAX_FRAME_LEN).unwrap();
    let client = handshake::client(&mut c, client_token, version).await;
    (srv.await.unwrap(), client)
}

#[tokio::test]
async fn right_token_and_version_pass() {
    let (s, c) = run(b"cluster-secret", b"cluster-secret", PROTOCOL_VERSION).await;
    assert!(s.is_ok(), "{s:?}");
    assert!(c.is_ok(), "{c:?}");
}

#[tokio::test]
async fn wrong_token_is_refused_on_both_sides() {
    let (s, c) = run(b"cluster-secret", b"guess", PROTOCOL_VERSION).await;
    // The server's proof fails first, at the client: it refuses and says so.
    let c = c.unwrap_err();
    assert!(matches!(c, ProtocolError::WrongToken { .. }), "{c}");
    assert!(c.to_string().contains("wrong cluster token"));
    let s = s.unwrap_err();
    assert!(
        matches!(&s, ProtocolError::Refused { reason, .. } if reason.contains("token")),
        "{s}"
    );
}

#[tokio::test]
async fn wrong_version_is_refused_on_both_sides() {
    let (s, c) = run(b"t", b"t", PROTOCOL_VERSION + 7).await;
    let s = s.unwrap_err();
    assert!(
        matches!(s, ProtocolError::Version { theirs, .. } if theirs == PROTOCOL_VERSION + 7),
        "{s}"
    );
    let c = c.unwrap_err();
    assert!(
        matches!(&c, ProtocolError::Refused { reason, .. } if reason.contains("version")),
        "{c}"
    );
}

/// Sends raw bytes to a server doing the handshake; returns its error.
async fn server_error_for(bytes: &'static [u8]) -> ProtocolError {
    let (l, addr) = pair().await;
    let srv = tokio::spawn(async move {
        let mut errors = Vec::new();
        // Serve the bad client, then a good one: one bad peer must not stop
        // the listener.
        for _ in 0..2 {
            let (s, _) = l.accept().await.unwrap();
            let mut c = Connection::new(s, 1024).unwrap();
            if let Err(e) = handshake::server(&mut c, b"k").await {
                errors.push(e);
            }
        }
        errors
    });
    let mut raw = TcpStream::connect(addr).await.unwrap();
    raw.write_all(bytes).await.unwrap();
    raw.shutdown().await.unwrap();
    let mut good = Connection::new(TcpStream::connect(addr).await.unwrap(), 1024).unwrap();
    handshake::client(&mut good, b"k", PROTOCOL_VERSION)
        .await
        .expect("good client after a bad one");
    let mut errors = srv.await.unwrap();
    assert_eq!(errors.len(), 1);
    errors.remove(0)
}

#[tokio::test]
async fn garbage_is_a_decode_error() {
    // A well-formed frame of 4 bytes whose content is no Handshake variant.
    let e = server_error_for(&[0, 0, 0, 4, 0xff, 0xff, 0xff, 0xff]).await;
    assert!(matches!(e, ProtocolError::Decode { .. }), "{e}");
}

#[tokio::test]
async fn oversized_length_prefix_is_refused() {
    let e = server_error_for(&[0xff, 0xff, 0xff, 0xf0, 1, 2, 3]).await;
    assert!(
        matches!(e, ProtocolError::FrameTooLarge { max: 1024, .. }),
        "{e}"
    );
}

#[tokio::test]
async fn truncated_frame_is_an_error() {
    let e = server_error_for(&[0, 0, 0, 100, 1, 2, 3]).await;
    assert!(
        matches!(e, ProtocolError::Io { .. } | ProtocolError::Closed { .. }),
        "{e}"
    );
}

#[tokio::test]
async fn out_of_order_message_is_refused() {
    // Welcome before Hello.
    let bytes: &'static [u8] = Box::leak(framed(&Handshake::Welcome).into_boxed_slice());
    let e = server_error_for(bytes).await;
    assert!(
        matches!(
            e,
            ProtocolError::OutOfOrder {
                expected: "Hello",
                ..
            }
        ),
        "{e}"
    );
}

fn framed(m: &Handshake) -> Vec<u8> {
    let body = postcard::to_stdvec(m).unwrap();
    let mut v = (body.len() as u32).to_be_bytes().to_vec();
    v.extend(body);
    v
}

fn arb_handshake() -> impl Strategy<Value = Handshake> {
    let n = any::<[u8; 32]>();
    prop_oneof![
        (any::<u32>(), n).prop_map(|(version, nonce)| Handshake::Hello { version, nonce }),
        (any::<u32>(), n, n).prop_map(|(version, nonce, proof)| Handshake::Challenge {
            version,
            nonce,
            proof
        }),
        n.prop_map(|proof| Handshake::Proof { proof }),
        Just(Handshake::Welcome),
        ".*".prop_map(|reason| Handshake::Refused { reason }),
    ]
}

proptest! {
    #[test]
    fn handshake_messages_round_trip(m in arb_handshake()) {
        let bytes = postcard::to_stdvec(&m).unwrap();
        prop_assert_eq!(postcard::from_bytes::<Handshake>(&bytes).unwrap(), m);
    }

    #[test]
    fn arbitrary_bytes_never_panic_the_decoder(b in proptest::collection::vec(any::<u8>(), 0..200)) {
        let _ = postcard::from_bytes::<Handshake>(&b);
    }
}

/// Two frames that arrive in one segment: the first read on the whole
/// connection, the second after `into_split`, while the peer sends nothing
/// more and waits (as a worker waits for the answer to its only packet).
/// A reader that looked at the socket before its buffer would wait forever.
#[tokio::test]
async fn a_frame_buffered_before_the_split_is_read_after_it() {
    let (l, addr) = pair().await;
    let client = tokio::spawn(async move {
        let mut s = TcpStream::connect(addr).await.unwrap();
        let mut bytes = Vec::new();
        for v in [7u32, 1234567] {
            let body = postcard::to_stdvec(&v).unwrap();
            bytes.extend_from_slice(&(body.len() as u32).to_be_bytes());
            bytes.extend_from_slice(&body);
        }
        s.write_all(&bytes).await.unwrap();
        // Keep the connection open and silent until the server is done.
        tokio::time::sleep(std::time::Duration::from_secs(5)).await;
        drop(s);
    });
    let (s, _) = l.accept().await.unwrap();
    let mut c = Connection::new(s, MAX_FRAME_LEN).unwrap();
    assert_eq!(c.read_msg::<u32>("first").await.unwrap(), Some(7));
    let (mut r, _w) = c.into_split();
    let second = tokio::time::timeout(
        std::time::Duration::from_secs(2),
        r.read_msg::<u32>("second"),
    )
    .await
    .expect("the buffered frame is read without waiting for more bytes")
    .unwrap();
    assert_eq!(second.map(|(v, _)| v), Some(1234567));
    client.abort();
}

/// Before the handshake a frame may be at most `MAX_HANDSHAKE_FRAME`, even
/// on a connection whose authenticated frames may be 64 MiB; after it, the
/// connection's own limit holds again, on both sides.
#[tokio::test]
async fn frames_before_the_handshake_are_small() {
    use handshake::MAX_HANDSHAKE_FRAME;
    let (l, addr) = pair().await;
    let srv = tokio::spawn(async move {
        let (s, _) = l.accept().await.unwrap();
        let mut c = Connection::new(s, MAX_FRAME_LEN).unwrap();
        let e = handshake::server(&mut c, b"k").await.unwrap_err();
        let (s, _) = l.accept().await.unwrap();
        let mut good = Connection::new(s, MAX_FRAME_LEN).unwrap();
        handshake::server(&mut good, b"k").await.unwrap();
        assert_eq!(good.max_frame(), MAX_FRAME_LEN);
        let big: Vec<u8> = good.read_msg("test").await.unwrap().unwrap();
        (e, big.len())
    });
    // A frame one byte over the bound, announced before any Hello.
    let mut raw = TcpStream::connect(addr).await.unwrap();
    let len = (MAX_HANDSHAKE_FRAME as u32 + 1).to_be_bytes();
    raw.write_all(&len).await.unwrap();
    raw.write_all(&vec![0u8; MAX_HANDSHAKE_FRAME + 1])
        .await
        .unwrap();
    let mut c = Connection::new(TcpStream::connect(addr).await.unwrap(), MAX_FRAME_LEN).unwrap();
    handshake::client(&mut c, b"k", PROTOCOL_VERSION)
        .await
        .unwrap();
    assert_eq!(c.max_frame(), MAX_FRAME_LEN);
    c.write_msg(&vec![7u8; 1 << 20]).await.unwrap();
    let (e, n) = srv.await.unwrap();
    assert!(
        matches!(e, ProtocolError::FrameTooLarge { max, .. } if max == MAX_HANDSHAKE_FRAME),
        "{e}"
    );
    assert!(n == 1 << 20, "{n}");
}
