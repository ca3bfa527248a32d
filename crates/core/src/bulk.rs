//! Serde forms for the long lists a job ships (triangles, their ids and
//! materials, shading normals): each list as one byte string of
//! little-endian words, for `#[serde(with = "...")]`.
//!
//! Derived, a list of triangles goes through the serializer one float at a
//! time, and postcard writes the ids and materials as varints: sending the
//! 325,000-triangle room whole to two workers cost the scheduler 177 M
//! instructions on its async runtime (the message's size computed, then
//! each float written), and the workers 102 M to read it back (callgrind,
//! the embedded farm). As byte strings, the list's own bytes go out and
//! one copy comes in: 40 M and 11 M. The words are the values' exact bits, so nothing
//! changes on the way; a byte string whose length is not a whole number
//! of items is an error, never a panic.

use glam::Vec3;
use serde::de::{Error, SeqAccess, Visitor};
use serde::{Deserializer, Serializer};
use std::fmt;
use std::marker::PhantomData;

/// An item made of 32-bit words and nothing else (no padding), which
/// travels as those words: a triangle's corners, an id, a material.
pub trait Words: bytemuck::Pod {}

impl Words for u32 {}
impl Words for [Vec3; 3] {}
// A BVH node as it travels (`accel::Layout`).
impl Words for [u32; 20] {}

// Both are whole 32-bit words, aligned as words: `cast_slice` to and from
// `u32` below cannot fail for them.
const _: () = assert!(size_of::<[Vec3; 3]>() == 36 && align_of::<[Vec3; 3]>() == 4);

/// Serializes `items` as one byte string: on a little-endian processor
/// their own bytes, with no copy.
pub fn serialize<T: Words, S: Serializer>(items: &[T], s: S) -> Result<S::Ok, S::Error> {
    let words: &[u32] = bytemuck::cast_slice(items);
    if cfg!(target_endian = "little") {
        s.serialize_bytes(bytemuck::cast_slice(words))
    } else {
        let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        s.serialize_bytes(&bytes)
    }
}

/// Reads a list [`serialize`] wrote.
pub fn deserialize<'de, T: Words, D: Deserializer<'de>>(d: D) -> Result<Vec<T>, D::Error> {
    d.deserialize_bytes(ListVisitor(PhantomData))
}

/// The items of `bytes`, or why it holds no whole number of them.
fn items<T: Words>(bytes: &[u8]) -> Result<Vec<T>, String> {
    let item = size_of::<T>();
    if !bytes.len().is_multiple_of(item) {
        return Err(format!(
            "a list of {} bytes, not a whole number of {item}-byte items",
            bytes.len()
        ));
    }
    // One copy into storage aligned for `T` (the frame's bytes need not
    // be), then the words put in this processor's order.
    let mut out: Vec<T> = bytemuck::pod_collect_to_vec(bytes);
    if cfg!(target_endian = "big") {
        for w in bytemuck::cast_slice_mut::<T, u32>(&mut out) {
            *w = u32::from_le(*w);
        }
    }
    Ok(out)
}

struct ListVisitor<T>(PhantomData<T>);

impl<'de, T: Words> Visitor<'de> for ListVisitor<T> {
    type Value = Vec<T>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        write!(f, "a byte string of {}-byte items", size_of::<T>())
    }

    fn visit_bytes<E: Error>(self, v: &[u8]) -> Result<Self::Value, E> {
        items(v).map_err(E::custom)
    }

    fn visit_borrowed_bytes<E: Error>(self, v: &'de [u8]) -> Result<Self::Value, E> {
        self.visit_bytes(v)
    }

    fn visit_byte_buf<E: Error>(self, v: Vec<u8>) -> Result<Self::Value, E> {
        self.visit_bytes(&v)
    }

    /// Formats without byte strings (JSON) write them as lists of numbers.
    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        let mut bytes = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(1 << 20));
        while let Some(b) = seq.next_element::<u8>()? {
            bytes.push(b);
        }
        self.visit_bytes(&bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::{Deserialize, Serialize};

    #[derive(Debug, PartialEq, Serialize, Deserialize)]
    struct Lists {
        #[serde(with = "crate::bulk")]
        tris: Vec<[Vec3; 3]>,
        #[serde(with = "crate::bulk")]
        ids: Vec<u32>,
        after: u8,
    }

    fn lists() -> Lists {
        // Values whose bits a careless conversion would lose: negative
        // zero, a NaN payload, infinities, subnormals, large ids.
        let odd = [
            -0.0,
            f32::from_bits(0x7fc0_1234),
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::from_bits(1),
            1.0e-30,
            -3.5,
            123_456.78,
            f32::MAX,
        ];
        let tris = (0..50)
            .map(|i| {
                let f = |k: usize| odd[(i + k) % odd.len()] * if i % 2 == 0 { 1.0 } else { -1.0 };
                [
                    Vec3::new(f(0), f(1), f(2)),
                    Vec3::new(f(3), f(4), f(5)),
                    Vec3::new(f(6), f(7), f(8)),
                ]
            })
            .collect();
        Lists {
            tris,
            ids: vec![0, 1, 127, 128, 1 << 20, u32::MAX],
            after: 7,
        }
    }

    fn bits(l: &Lists) -> Vec<u32> {
        let f = l.tris.iter().flatten().flat_map(|v| v.to_array());
        f.map(f32::to_bits).chain(l.ids.iter().copied()).collect()
    }

    /// Every list comes back bit for bit through postcard (borrowed bytes)
    /// and JSON (a list of numbers), and the field after them too.
    #[test]
    fn lists_come_back_bit_for_bit() {
        let l = lists();
        let p = postcard::to_allocvec(&l).unwrap();
        // One length and 4 bytes a word: nothing per item.
        assert_eq!(p.len(), 2 + 50 * 36 + 1 + 6 * 4 + 1);
        let back: Lists = postcard::from_bytes(&p).unwrap();
        assert_eq!(bits(&back), bits(&l));
        assert_eq!(back.after, 7);
        let j = serde_json::to_string(&l).unwrap();
        let back: Lists = serde_json::from_str(&j).unwrap();
        assert_eq!(bits(&back), bits(&l));
    }

    /// A byte string cut inside an item is an error naming the item size,
    /// and so is one cut short of its length.
    #[test]
    fn a_cut_list_is_an_error() {
        let l = lists();
        let mut p = postcard::to_allocvec(&l).unwrap();
        // The triangle list's length prefix (a varint of 2 bytes): one
        // byte fewer, then the payload re-read as a shorter string.
        let len = 50 * 36 - 1;
        p[0] = (len & 0x7f) as u8 | 0x80;
        p[1] = (len >> 7) as u8;
        let e = postcard::from_bytes::<Lists>(&p).unwrap_err();
        assert!(matches!(e, postcard::Error::SerdeDeCustom), "{e:?}");
        let j = serde_json::to_string(&l).unwrap();
        let cut = j.replacen("[", "[1,", 2);
        let e = serde_json::from_str::<Lists>(&cut).unwrap_err();
        assert!(e.to_string().contains("36-byte items"), "{e}");
        let whole = postcard::to_allocvec(&l).unwrap();
        for n in 0..whole.len() {
            assert!(
                postcard::from_bytes::<Lists>(&whole[..n]).is_err(),
                "cut at {n}"
            );
        }
    }
}
