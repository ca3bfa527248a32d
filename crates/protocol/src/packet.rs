//! The compact encoding of ray items, the bulk of the traffic between
//! workers.
//!
//! A packet is a byte string of items, each a tag byte followed by its
//! fields: floats as their exact little-endian bits, integers (pixel,
//! sample, depth, slot, worker) as LEB128 varints, since they are mostly
//! small. Nothing is spent on a serde visitor per field. The sample key's
//! seed is the job's and is not sent (the receiver supplies it), and a path
//! query whose emission bound is infinite (no directional cache) leaves it
//! out and says so in its tag. Items are
//! self-delimiting, so packets encoded apart (on a worker's tracing
//! threads) concatenate ([`Packet::append`]). A malformed packet (an unknown tag, a cut-off item) is an error
//! naming the byte where it went wrong, never a panic.
//!
//! | item | fields | bytes, typically |
//! |---|---|---:|
//! | path query | tag, resume, [span end], reply, origin, direction, pixel, sample, depth, pdf, throughput, [emission bound] | 59-68 |
//! | shadow query | tag, resume, [span end], reply, origin, direction, t_max | 41-43 |
//! | segment query | as a path query with its emission bound | 63-68 |
//!
//! A query forwarded into a route node carries where that node ends on
//! its ray (the [`Resume`]'s `local_until`), flagged in its tag, so that
//! its receiver need not walk the route over it again.
//! | radiance answer | tag, slot, RGB | 15-16 |
//! | visibility answer | tag, slot | 3-4 |
//! | beyond answer (a segment reached its perimeter) | tag, slot | 3-4 |

use crate::rays::{RayItem, ReplyTo};
use glam::Vec3;
use locus_core::geometry::Ray;
use locus_core::integrator::{PathRay, ShadowRay};
use locus_core::path::{Answer, Query};
use locus_core::region::Resume;
use locus_core::sampler::{SampleKey, Sampler};
use serde::{Deserialize, Serialize};

const PATH: u8 = 1;
/// A path query with an infinite emission bound, which is not sent.
const PATH_UNBOUNDED: u8 = 2;
const SHADOW: u8 = 3;
const RADIANCE: u8 = 4;
const VISIBLE: u8 = 5;
const BLOCKED: u8 = 6;
/// A segment query (always bounded by its perimeter).
const SEGMENT: u8 = 7;
const BEYOND: u8 = 8;
/// Flag on a query's tag: the item carries its span's end.
const SPAN: u8 = 0x10;

/// The longest item: a path query with every varint at its longest.
pub const MAX_ITEM: usize = 1 + 4 + 4 + 3 + 5 + 24 + 10 + 5 + 5 + 4 + 12 + 4;

/// Bytes of a path query (without caches) and of its radiance answer as a
/// typical job encodes them (a pixel index below 2^21, a sample and depth
/// below 128, a slot below 2^21): what one forwarded query costs on the
/// wire, for the adaptive policy's rent-or-buy rule.
pub const TYPICAL_FORWARD_BYTES: u64 = 1 + 4 + 4 + 1 + 3 + 24 + 3 + 1 + 1 + 4 + 12 + 1 + 3 + 12;

/// Ray items in the compact encoding.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Packet {
    bytes: Vec<u8>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum PacketError {
    #[error("unknown item tag {tag} at byte {at}")]
    BadTag { tag: u8, at: usize },
    #[error("an item cut off at byte {at}")]
    Truncated { at: usize },
    #[error("an integer out of range in the item at byte {at}")]
    BadInteger { at: usize },
}

/// Whether a resume carries a span beyond its start (NaN ends never do).
#[inline(always)]
fn spans(r: Resume) -> bool {
    r.local_until > r.at
}

/// Writes an item's fields into a buffer long enough for any item.
struct Writer {
    buf: [u8; MAX_ITEM],
    at: usize,
}

impl Writer {
    #[inline(always)]
    fn new(tag: u8) -> Self {
        let mut buf = [0; MAX_ITEM];
        buf[0] = tag;
        Self { buf, at: 1 }
    }
    #[inline(always)]
    fn f32(&mut self, x: f32) {
        self.buf[self.at..self.at + 4].copy_from_slice(&x.to_le_bytes());
        self.at += 4;
    }
    #[inline(always)]
    fn v3(&mut self, v: Vec3) {
        self.f32(v.x);
        self.f32(v.y);
        self.f32(v.z);
    }
    #[inline(always)]
    fn var(&mut self, mut x: u64) {
        while x >= 0x80 {
            self.buf[self.at] = x as u8 | 0x80;
            self.at += 1;
            x >>= 7;
        }
        self.buf[self.at] = x as u8;
        self.at += 1;
    }
    #[inline(always)]
    fn head(&mut self, resume: Resume, reply: ReplyTo, ray: &Ray) {
        self.f32(resume.at);
        if spans(resume) {
            self.buf[0] |= SPAN;
            self.f32(resume.local_until);
        }
        self.var(reply.worker as u64);
        self.var(reply.slot as u64);
        self.v3(ray.origin);
        self.v3(ray.dir);
    }
    #[inline(always)]
    fn done(&self) -> &[u8] {
        &self.buf[..self.at]
    }
}

/// Why an item could not be read.
enum Fail {
    Truncated,
    Range,
}

/// Reads an item's fields.
struct Reader<'a> {
    b: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    #[inline(always)]
    fn f32(&mut self) -> Result<f32, Fail> {
        let x = self.b.get(self.at..self.at + 4).ok_or(Fail::Truncated)?;
        self.at += 4;
        Ok(f32::from_le_bytes([x[0], x[1], x[2], x[3]]))
    }
    #[inline(always)]
    fn v3(&mut self) -> Result<Vec3, Fail> {
        Ok(Vec3::new(self.f32()?, self.f32()?, self.f32()?))
    }
    /// A LEB128 varint of at most `bits` bits.
    #[inline(always)]
    fn var(&mut self, bits: u32) -> Result<u64, Fail> {
        let mut x = 0u64;
        let mut shift = 0;
        loop {
            let &b = self.b.get(self.at).ok_or(Fail::Truncated)?;
            self.at += 1;
            let v = (b & 0x7f) as u64;
            if shift >= bits || v.checked_shr(bits - shift).unwrap_or(0) != 0 {
                return Err(Fail::Range);
            }
            x |= v << shift;
            if b & 0x80 == 0 {
                return Ok(x);
            }
            shift += 7;
        }
    }
    #[inline(always)]
    fn head(&mut self, span: bool) -> Result<(Resume, ReplyTo, Ray), Fail> {
        let at = self.f32()?;
        let resume = if span {
            Resume::within(at, self.f32()?)
        } else {
            Resume::at(at)
        };
        let worker = self.var(16)? as u16;
        let slot = self.var(32)? as u32;
        let origin = self.v3()?;
        let dir = self.v3()?;
        Ok((resume, ReplyTo { worker, slot }, Ray { origin, dir }))
    }
}

impl Packet {
    pub fn with_capacity(bytes: usize) -> Self {
        Self {
            bytes: Vec::with_capacity(bytes),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.bytes.is_empty()
    }

    /// Drops the items and keeps the room they took, for the next ones.
    pub fn clear(&mut self) {
        self.bytes.clear();
    }

    /// The packet of `items`, in order.
    pub fn from_items<'a>(items: impl IntoIterator<Item = &'a RayItem>) -> Self {
        let mut p = Self::default();
        for i in items {
            p.push(i);
        }
        p
    }

    /// A packet of bytes as they came (decoding checks them).
    pub fn from_bytes(bytes: Vec<u8>) -> Self {
        Self { bytes }
    }

    /// The encoded items.
    pub fn as_bytes(&self) -> &[u8] {
        &self.bytes
    }

    /// Encoded bytes.
    pub fn len(&self) -> usize {
        self.bytes.len()
    }

    /// Appends `item`. A path query's sample key must carry the job's seed
    /// (it is not sent).
    #[inline]
    pub fn push(&mut self, item: &RayItem) {
        let w = match item {
            RayItem::Trace {
                query: query @ (Query::Path(q) | Query::Segment(q)),
                resume,
                reply,
            } => {
                let tag = match query {
                    Query::Segment(_) => SEGMENT,
                    _ if q.emit_within != f32::INFINITY => PATH,
                    _ => PATH_UNBOUNDED,
                };
                let mut w = Writer::new(tag);
                w.head(*resume, *reply, &q.ray);
                w.var(q.key.pixel);
                w.var(q.key.sample as u64);
                w.var(q.depth as u64);
                w.f32(q.prev_pdf);
                w.v3(q.beta);
                if tag != PATH_UNBOUNDED {
                    w.f32(q.emit_within);
                }
                w
            }
            RayItem::Trace {
                query: Query::Shadow(s),
                resume,
                reply,
            } => {
                let mut w = Writer::new(SHADOW);
                w.head(*resume, *reply, &s.ray);
                w.f32(s.t_max);
                w
            }
            RayItem::Answer {
                to,
                answer: Answer::Radiance(l),
            } => {
                let mut w = Writer::new(RADIANCE);
                w.var(*to as u64);
                w.v3(*l);
                w
            }
            RayItem::Answer {
                to,
                answer: Answer::Visible(v),
            } => {
                let mut w = Writer::new(if *v { VISIBLE } else { BLOCKED });
                w.var(*to as u64);
                w
            }
            RayItem::Answer {
                to,
                answer: Answer::Beyond,
            } => {
                let mut w = Writer::new(BEYOND);
                w.var(*to as u64);
                w
            }
        };
        self.bytes.extend_from_slice(w.done());
    }

    /// Appends another packet's items after this one's (items carry their
    /// own tags and lengths, so packets concatenate).
    pub fn append(&mut self, other: &Packet) {
        self.bytes.extend_from_slice(&other.bytes);
    }

    /// The items, in order; path queries get `seed` and `sampler` (the
    /// job's) in their keys.
    pub fn items(&self, seed: u64, sampler: Sampler) -> Items<'_> {
        Items {
            b: &self.bytes,
            at: 0,
            seed,
            sampler,
        }
    }
}

/// Decodes a packet item by item; stops after the first error.
pub struct Items<'a> {
    b: &'a [u8],
    at: usize,
    seed: u64,
    sampler: Sampler,
}

impl Items<'_> {
    #[inline(always)]
    fn item(&self, tag: u8, r: &mut Reader) -> Result<RayItem, Fail> {
        let span = tag & SPAN != 0;
        Ok(match tag & !SPAN {
            PATH | PATH_UNBOUNDED | SEGMENT => {
                let (resume, reply, ray) = r.head(span)?;
                let pixel = r.var(64)?;
                let sample = r.var(32)? as u32;
                let depth = r.var(32)? as u32;
                let prev_pdf = r.f32()?;
                let beta = r.v3()?;
                let emit_within = if tag & !SPAN == PATH_UNBOUNDED {
                    f32::INFINITY
                } else {
                    r.f32()?
                };
                let q = PathRay {
                    ray,
                    key: SampleKey::new(pixel, sample, self.seed, self.sampler),
                    depth,
                    prev_pdf,
                    beta,
                    emit_within,
                };
                RayItem::Trace {
                    query: if tag & !SPAN == SEGMENT {
                        Query::Segment(q)
                    } else {
                        Query::Path(q)
                    },
                    resume,
                    reply,
                }
            }
            SHADOW => {
                let (resume, reply, ray) = r.head(span)?;
                let t_max = r.f32()?;
                RayItem::Trace {
                    query: Query::Shadow(ShadowRay { ray, t_max }),
                    resume,
                    reply,
                }
            }
            RADIANCE => RayItem::Answer {
                to: r.var(32)? as u32,
                answer: Answer::Radiance(r.v3()?),
            },
            BEYOND => RayItem::Answer {
                to: r.var(32)? as u32,
                answer: Answer::Beyond,
            },
            _ => RayItem::Answer {
                to: r.var(32)? as u32,
                answer: Answer::Visible(tag == VISIBLE),
            },
        })
    }
}

impl Iterator for Items<'_> {
    type Item = Result<RayItem, PacketError>;

    #[inline]
    fn next(&mut self) -> Option<Self::Item> {
        let at = self.at;
        let &tag = self.b.get(at)?;
        let query = (PATH..=SHADOW).contains(&(tag & !SPAN)) || tag & !SPAN == SEGMENT;
        let answer = (RADIANCE..=BLOCKED).contains(&tag) || tag == BEYOND;
        if !query && !answer {
            self.at = self.b.len();
            return Some(Err(PacketError::BadTag { tag, at }));
        }
        let mut r = Reader {
            b: self.b,
            at: at + 1,
        };
        match self.item(tag, &mut r) {
            Ok(item) => {
                self.at = r.at;
                Some(Ok(item))
            }
            Err(f) => {
                self.at = self.b.len();
                Some(Err(match f {
                    Fail::Truncated => PacketError::Truncated { at },
                    Fail::Range => PacketError::BadInteger { at },
                }))
            }
        }
    }
}

impl Serialize for Packet {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(&self.bytes)
    }
}

impl<'de> Deserialize<'de> for Packet {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Bytes;
        impl<'de> serde::de::Visitor<'de> for Bytes {
            type Value = Packet;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a packet's bytes")
            }
            fn visit_bytes<E: serde::de::Error>(self, v: &[u8]) -> Result<Packet, E> {
                Ok(Packet { bytes: v.to_vec() })
            }
            fn visit_byte_buf<E: serde::de::Error>(self, v: Vec<u8>) -> Result<Packet, E> {
                Ok(Packet { bytes: v })
            }
        }
        d.deserialize_bytes(Bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn path(pixel: u64, emit_within: f32) -> PathRay {
        PathRay {
            ray: Ray::new(Vec3::new(1.0, -2.5, 1e-30), Vec3::new(0.0, -0.0, 1.0)),
            key: SampleKey::independent(pixel, 17, 99),
            depth: 5,
            prev_pdf: f32::MIN_POSITIVE,
            beta: Vec3::new(0.5, f32::MAX, 3.0),
            emit_within,
        }
    }

    fn items() -> Vec<RayItem> {
        let ray = Ray::new(Vec3::new(1.0, -2.5, 1e-30), Vec3::new(0.0, -0.0, 1.0));
        let reply = ReplyTo {
            worker: u16::MAX,
            slot: u32::MAX,
        };
        vec![
            RayItem::Trace {
                query: Query::Path(path(u64::MAX, f32::INFINITY)),
                resume: Resume::START,
                reply,
            },
            RayItem::Trace {
                query: Query::Path(path(3, 2.5)),
                resume: Resume::at(0.0),
                reply: ReplyTo { worker: 0, slot: 0 },
            },
            RayItem::Trace {
                query: Query::Path(path(4, f32::INFINITY)),
                resume: Resume::within(0.5, f32::INFINITY),
                reply,
            },
            RayItem::Trace {
                query: Query::Segment(path(5, 0.75)),
                resume: Resume::within(0.25, 0.5),
                reply,
            },
            RayItem::Trace {
                query: Query::Segment(path(6, 1.5)),
                resume: Resume::START,
                reply: ReplyTo { worker: 1, slot: 7 },
            },
            RayItem::Answer {
                to: 12,
                answer: Answer::Beyond,
            },
            RayItem::Trace {
                query: Query::Shadow(ShadowRay { ray, t_max: 2.0 }),
                resume: Resume::within(0.25, 1.5),
                reply,
            },
            RayItem::Answer {
                to: 3,
                answer: Answer::Radiance(Vec3::new(f32::NAN, 1.0, -0.0)),
            },
            RayItem::Answer {
                to: 1 << 20,
                answer: Answer::Visible(true),
            },
            RayItem::Answer {
                to: 5,
                answer: Answer::Visible(false),
            },
        ]
    }

    /// The item with every float as its bits, so that NaN and -0 compare
    /// exactly.
    fn bits(i: &RayItem) -> String {
        let f = |x: f32| x.to_bits();
        match i {
            RayItem::Trace {
                query: Query::Path(q),
                resume,
                reply,
            } => format!(
                "{:?}",
                (
                    f(resume.at),
                    f(resume.local_until),
                    reply,
                    q.ray.origin.to_array().map(f),
                    q.ray.dir.to_array().map(f),
                    q.key,
                    q.depth,
                    f(q.prev_pdf),
                    q.beta.to_array().map(f),
                    f(q.emit_within)
                )
            ),
            RayItem::Answer {
                to,
                answer: Answer::Radiance(l),
            } => format!("{to} {:?}", l.to_array().map(f)),
            other => format!("{other:?}"),
        }
    }

    fn packet(items: &[RayItem]) -> Packet {
        Packet::from_items(items)
    }

    #[test]
    fn items_roundtrip_bit_for_bit_with_the_jobs_seed() {
        let src = items();
        let p = packet(&src);
        let back: Vec<RayItem> = p
            .items(99, Sampler::Independent)
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(back.len(), src.len());
        for (a, b) in src.iter().zip(&back) {
            assert_eq!(bits(a), bits(b));
        }
        // Through postcard, as a frame carries it.
        let wire = postcard::to_stdvec(&p).unwrap();
        assert_eq!(postcard::from_bytes::<Packet>(&wire).unwrap(), p);
        // Packets encoded apart (on pool threads) concatenate to the
        // packet of all their items.
        for cut in 0..=src.len() {
            let mut joined = packet(&src[..cut]);
            joined.append(&packet(&src[cut..]));
            assert_eq!(joined, p, "cut at item {cut}");
        }
    }

    #[test]
    fn a_typical_forward_costs_what_the_adaptive_rule_assumes() {
        let q = RayItem::Trace {
            query: Query::Path(PathRay {
                key: SampleKey::independent(320 * 240 - 1, 15, 1),
                depth: 3,
                ..path(0, f32::INFINITY)
            }),
            resume: Resume::within(1.0, 2.0),
            reply: ReplyTo {
                worker: 1,
                slot: 30_000,
            },
        };
        let a = RayItem::Answer {
            to: 30_000,
            answer: Answer::Radiance(Vec3::ONE),
        };
        assert_eq!(packet(&[q, a]).len() as u64, TYPICAL_FORWARD_BYTES);
    }

    #[test]
    fn malformed_packets_are_errors_at_their_byte() {
        let p = packet(&items());
        let first = packet(&items()[..1]).len();
        // A span flag on an answer is an unknown tag.
        let flagged = Packet {
            bytes: vec![RADIANCE | SPAN, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0],
        };
        assert_eq!(
            flagged.items(1, Sampler::Independent).next(),
            Some(Err(PacketError::BadTag {
                tag: RADIANCE | SPAN,
                at: 0
            }))
        );
        let cut = Packet {
            bytes: p.bytes[..first + 10].to_vec(),
        };
        let r: Vec<_> = cut.items(1, Sampler::Independent).collect();
        assert!(r[0].is_ok());
        assert_eq!(r[1], Err(PacketError::Truncated { at: first }));
        assert_eq!(r.len(), 2, "decoding stops at the first error");
        let mut bad = p.clone();
        bad.bytes[first] = 200;
        let r: Vec<_> = bad.items(1, Sampler::Independent).collect();
        assert_eq!(
            r[1],
            Err(PacketError::BadTag {
                tag: 200,
                at: first
            })
        );
        // A slot of more than 32 bits.
        let wide = Packet {
            bytes: vec![RADIANCE, 0xff, 0xff, 0xff, 0xff, 0x7f],
        };
        assert_eq!(
            wide.items(1, Sampler::Independent).next(),
            Some(Err(PacketError::BadInteger { at: 0 }))
        );
        // A varint that never ends.
        let endless = Packet {
            bytes: vec![VISIBLE, 0x80, 0x80],
        };
        assert_eq!(
            endless.items(1, Sampler::Independent).next(),
            Some(Err(PacketError::Truncated { at: 0 }))
        );
    }
}
