//! What a worker sends to its peers: ray items gathered into packets per
//! peer, and the messages that did not fit a peer's channel yet.
//!
//! A packet leaves when it holds `packet_items` items, when its oldest item
//! has waited `flush_after`, or when the engine has nothing else to do
//! ([`Outbox::flush_all`]): full packets while the worker is busy (fewer
//! frames, fewer wake-ups), no waiting when it is idle.
//!
//! The engine's own items (the queries of vertices it opens, the replies
//! of vertices it completes) are handed to the link's writer task as they
//! are, and encoded there: the engine's thread is serial, and in a worker
//! of many tracing threads it is what `forward` waits for. Items the pool
//! encoded join the packet as bytes, and the writer puts the engine's
//! after them ([`Outgoing`]): the order of items within a packet means
//! nothing (a receiver takes its queries and answers apart anyway, and
//! every answer is a pure function of its query).
//!
//! Sends never block the engine: two workers blocked on sending to each
//! other would deadlock. A message that does not fit its peer's bounded
//! channel waits here, in order, and while any waits the engine starts no
//! new camera sample: that is the backpressure. What can wait here is
//! bounded by the work in flight in the whole farm (every worker keeps at
//! most `max_inflight` samples open, each with at most two queries per
//! path vertex), so these queues are bounded too.

use crate::peers::Outgoing;
use locus_core::region::WorkerId;
use locus_protocol::packet::MAX_ITEM;
use locus_protocol::rays::{Packet, PeerMsg, RayItem};
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// Items a packet's buffer is allocated for at most (larger packets grow).
const MAX_PACKET_ALLOC: usize = 4096;

/// A packet being filled: the items the pool encoded, the engine's own
/// (encoded by the writer), and how many in all.
#[derive(Default)]
struct Filling {
    encoded: Packet,
    raw: Vec<RayItem>,
    /// The most of the engine's own items a packet to this peer has held:
    /// the next packet's room for them, so that filling it seldom copies
    /// them (sizing it by the last packet's alone grew every packet that
    /// held more, about 3% of a dedicated engine thread's instructions).
    raw_most: usize,
    n: usize,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the link to worker {0} closed while the job was running")]
pub struct LinkClosed(pub WorkerId);

pub struct Outbox {
    peers: Vec<Option<flume::Sender<Outgoing>>>,
    /// Per peer: the packet being filled.
    out: Vec<Filling>,
    since: Vec<Option<Instant>>,
    stalled: Vec<VecDeque<Outgoing>>,
    packet_items: usize,
    flush_after: Duration,
    /// Times a message found its peer's channel full.
    pub stalls: u64,
    /// Packets sent, for reports.
    pub packets: u64,
    /// Messages handed to each peer's channel.
    pub sent: Vec<u64>,
}

impl Outbox {
    /// `peers[w]` is the channel to worker `w` (None for this worker).
    pub fn new(
        peers: Vec<Option<flume::Sender<Outgoing>>>,
        packet_items: usize,
        flush_after: Duration,
    ) -> Self {
        let n = peers.len();
        Self {
            peers,
            out: (0..n).map(|_| Filling::default()).collect(),
            since: vec![None; n],
            stalled: (0..n).map(|_| VecDeque::new()).collect(),
            packet_items: packet_items.max(1),
            flush_after,
            stalls: 0,
            packets: 0,
            sent: vec![0; n],
        }
    }

    /// Adds an item to `peer`'s packet, sending it when full. It is
    /// encoded by the link's writer, not here.
    pub fn push(&mut self, peer: WorkerId, item: RayItem, now: Instant) -> Result<(), LinkClosed> {
        self.add(peer, 1, now, |f| f.raw.push(item))
    }

    /// Adds `n` items encoded elsewhere (by the pool) to `peer`'s packet.
    pub fn push_encoded(
        &mut self,
        peer: WorkerId,
        items: &Packet,
        n: usize,
        now: Instant,
    ) -> Result<(), LinkClosed> {
        self.add(peer, n, now, |f| f.encoded.append(items))
    }

    /// Writes `n` items into `peer`'s packet with `write`: a packet that
    /// would exceed the packet size leaves first (so packets never hold
    /// more than that when no write does), and one that reaches it leaves
    /// after.
    fn add(
        &mut self,
        peer: WorkerId,
        n: usize,
        now: Instant,
        write: impl FnOnce(&mut Filling),
    ) -> Result<(), LinkClosed> {
        let p = peer as usize;
        let Some(held) = self.out.get(p).map(|f| f.n) else {
            return Err(LinkClosed(peer));
        };
        if held > 0 && held + n > self.packet_items {
            self.send_packet(p)?;
        }
        let f = &mut self.out[p];
        if f.n == 0 {
            self.since[p] = Some(now);
        }
        write(f);
        f.n += n;
        if f.n >= self.packet_items {
            self.send_packet(p)?;
        }
        Ok(())
    }

    fn send_packet(&mut self, p: usize) -> Result<(), LinkClosed> {
        self.since[p] = None;
        let f = &mut self.out[p];
        if f.n == 0 {
            return Ok(());
        }
        // Room for a full packet, so that filling it never copies it; for
        // the engine's items, room for as many as a packet has held.
        let bytes = self.packet_items.min(MAX_PACKET_ALLOC) * MAX_ITEM;
        let encoded = std::mem::replace(&mut f.encoded, Packet::with_capacity(bytes));
        f.raw_most = f.raw_most.max(f.raw.len());
        let next_raw = Vec::with_capacity(f.raw_most);
        let raw = std::mem::replace(&mut f.raw, next_raw);
        f.n = 0;
        self.packets += 1;
        self.send_out(p as WorkerId, Outgoing::Items { encoded, raw })
    }

    /// Sends `msg` behind whatever already waits for `peer`, keeping order.
    pub fn send(&mut self, peer: WorkerId, msg: PeerMsg) -> Result<(), LinkClosed> {
        self.send_out(peer, Outgoing::Msg(msg))
    }

    fn send_out(&mut self, peer: WorkerId, msg: Outgoing) -> Result<(), LinkClosed> {
        let p = peer as usize;
        if !self.stalled[p].is_empty() {
            self.stalled[p].push_back(msg);
            return Ok(());
        }
        let Some(tx) = self.peers.get(p).and_then(Option::as_ref) else {
            return Err(LinkClosed(peer));
        };
        match tx.try_send(msg) {
            Ok(()) => {
                self.sent[p] += 1;
                Ok(())
            }
            Err(flume::TrySendError::Full(msg)) => {
                self.stalls += 1;
                self.stalled[p].push_back(msg);
                Ok(())
            }
            Err(flume::TrySendError::Disconnected(_)) => Err(LinkClosed(peer)),
        }
    }

    /// Moves waiting messages into channels that have room again.
    pub fn retry_stalled(&mut self) -> Result<(), LinkClosed> {
        for p in 0..self.stalled.len() {
            while let Some(msg) = self.stalled[p].pop_front() {
                let Some(tx) = &self.peers[p] else {
                    return Err(LinkClosed(p as WorkerId));
                };
                match tx.try_send(msg) {
                    Ok(()) => self.sent[p] += 1,
                    Err(flume::TrySendError::Full(msg)) => {
                        self.stalled[p].push_front(msg);
                        break;
                    }
                    Err(flume::TrySendError::Disconnected(_)) => {
                        return Err(LinkClosed(p as WorkerId));
                    }
                }
            }
        }
        Ok(())
    }

    /// Whether any message waits for room.
    pub fn is_stalled(&self) -> bool {
        self.stalled.iter().any(|s| !s.is_empty())
    }

    /// Sends every packet whose oldest item has waited long enough.
    pub fn flush_due(&mut self, now: Instant) -> Result<(), LinkClosed> {
        for p in 0..self.out.len() {
            if self.since[p].is_some_and(|t| now.duration_since(t) >= self.flush_after) {
                self.send_packet(p)?;
            }
        }
        Ok(())
    }

    /// Sends every packet, full or not.
    pub fn flush_all(&mut self) -> Result<(), LinkClosed> {
        for p in 0..self.out.len() {
            self.send_packet(p)?;
        }
        Ok(())
    }

    /// When the oldest waiting item is due.
    pub fn next_deadline(&self) -> Option<Instant> {
        self.since
            .iter()
            .flatten()
            .min()
            .map(|t| *t + self.flush_after)
    }

    /// Whether anything is buffered or waiting.
    pub fn is_empty(&self) -> bool {
        self.out.iter().all(|f| f.n == 0) && !self.is_stalled()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use locus_core::path::Answer;

    fn item(k: u32) -> RayItem {
        RayItem::Answer {
            to: k,
            answer: Answer::Radiance(Vec3::splat(k as f32)),
        }
    }

    fn items(m: Outgoing) -> Vec<u32> {
        match m.into_msg() {
            PeerMsg::Packet(v) => v
                .items(0, locus_core::sampler::Sampler::Independent)
                .map(|i| match i {
                    Ok(RayItem::Answer { to, .. }) => to,
                    other => panic!("{other:?}"),
                })
                .collect(),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn packets_leave_full_due_or_on_flush() {
        let (tx, rx) = flume::bounded(16);
        let mut o = Outbox::new(vec![None, Some(tx)], 3, Duration::from_millis(5));
        let t0 = Instant::now();
        for k in 0..4 {
            o.push(1, item(k), t0).unwrap();
        }
        assert_eq!(items(rx.try_recv().unwrap()), [0, 1, 2]);
        assert!(rx.try_recv().is_err(), "a partial packet waits");
        assert_eq!(o.next_deadline(), Some(t0 + Duration::from_millis(5)));
        o.flush_due(t0 + Duration::from_millis(4)).unwrap();
        assert!(rx.try_recv().is_err(), "not due yet");
        o.flush_due(t0 + Duration::from_millis(5)).unwrap();
        assert_eq!(items(rx.try_recv().unwrap()), [3]);
        o.push(1, item(9), t0).unwrap();
        o.flush_all().unwrap();
        assert_eq!(items(rx.try_recv().unwrap()), [9]);
        assert!(o.is_empty());
        assert_eq!(o.packets, 3);
    }

    #[test]
    fn a_full_channel_stalls_in_order_and_drains() {
        let (tx, rx) = flume::bounded(1);
        let mut o = Outbox::new(vec![Some(tx), None], 1, Duration::from_millis(1));
        let now = Instant::now();
        for k in 0..4 {
            o.push(0, item(k), now).unwrap();
        }
        assert!(o.is_stalled());
        assert_eq!(o.stalls, 1);
        let mut got = Vec::new();
        while got.len() < 4 {
            got.extend(items(rx.try_recv().unwrap()));
            o.retry_stalled().unwrap();
        }
        assert_eq!(got, [0, 1, 2, 3], "order kept through the stall");
        assert!(!o.is_stalled());
        drop(rx);
        assert_eq!(o.push(0, item(5), now), Err(LinkClosed(0)));
        // No channel to itself: a bug, reported, not a panic.
        assert_eq!(o.push(1, item(5), now), Err(LinkClosed(1)));
    }

    fn encoded(ks: std::ops::Range<u32>) -> (Packet, usize) {
        let items: Vec<RayItem> = ks.map(item).collect();
        (Packet::from_items(&items), items.len())
    }

    #[test]
    fn chunks_encoded_elsewhere_join_packets_without_overfilling_them() {
        let (tx, rx) = flume::bounded(16);
        let mut o = Outbox::new(vec![None, Some(tx)], 4, Duration::from_millis(5));
        let t0 = Instant::now();
        o.push(1, item(0), t0).unwrap();
        let (p, n) = encoded(1..3);
        o.push_encoded(1, &p, n, t0).unwrap();
        assert!(rx.try_recv().is_err(), "3 of 4 items wait");
        // Two more would make 5: the packet of 3 leaves first.
        let (p, n) = encoded(3..5);
        o.push_encoded(1, &p, n, t0).unwrap();
        // The pool's items, then the engine's (encoded by the writer).
        assert_eq!(items(rx.try_recv().unwrap()), [1, 2, 0]);
        // A full chunk fills the packet it joins and leaves at once.
        let (p, n) = encoded(5..7);
        o.push_encoded(1, &p, n, t0 + Duration::from_millis(1))
            .unwrap();
        assert_eq!(items(rx.try_recv().unwrap()), [3, 4, 5, 6]);
        let (p, n) = encoded(7..8);
        o.push_encoded(1, &p, n, t0 + Duration::from_millis(2))
            .unwrap();
        assert_eq!(
            o.next_deadline(),
            Some(t0 + Duration::from_millis(7)),
            "an empty packet's deadline starts with its first chunk"
        );
        o.flush_all().unwrap();
        assert_eq!(items(rx.try_recv().unwrap()), [7]);
        assert_eq!(o.packets, 3);
        // A peer outside the job: an error, not a panic.
        assert_eq!(o.push_encoded(2, &p, n, t0), Err(LinkClosed(2)));
    }

    /// What the engine hands over unencoded reaches the wire as the bytes
    /// it would have encoded itself.
    #[test]
    fn the_writer_encodes_the_engines_items_as_the_engine_would() {
        let (tx, rx) = flume::bounded(4);
        let mut o = Outbox::new(vec![None, Some(tx)], 8, Duration::from_millis(5));
        let t0 = Instant::now();
        let (p, n) = encoded(0..2);
        o.push_encoded(1, &p, n, t0).unwrap();
        for k in 2..5 {
            o.push(1, item(k), t0).unwrap();
        }
        o.flush_all().unwrap();
        let Outgoing::Items { encoded, raw } = rx.try_recv().unwrap() else {
            panic!("a packet was expected");
        };
        assert_eq!(raw.len(), 3, "the engine's items travel unencoded");
        let sent = Outgoing::Items { encoded, raw }.into_msg();
        let all: Vec<RayItem> = (0..5).map(item).collect();
        assert_eq!(sent, PeerMsg::Packet(Packet::from_items(&all)));
    }
}
