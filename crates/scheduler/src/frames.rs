//! Frames of the large messages that several workers are sent alike,
//! encoded once.
//!
//! A job that replicates the scene ships every worker the same parts: the
//! same `Geometry` message (job, leaves, triangles, last), its triangles
//! one allocation that the workers' messages share
//! ([`crate::job::PartRun::gather`]). Each worker's connection encoded it
//! into a frame of its own, up to 48 MiB, all at about the same time, so
//! the scheduler's memory grew by a part per worker. [`SharedFrames`] keeps
//! a part's frame while the triangles it was encoded from are alive (some
//! worker's message still holds them) and hands it to every writer of the
//! same message, which writes it from those bytes.

use bytes::Bytes;
use locus_protocol::ProtocolError;
use locus_protocol::control::{SchedulerToWorker, TriangleSet};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError, Weak};

/// Frames of parts, shared by the scheduler's worker connections.
#[derive(Default)]
pub(crate) struct SharedFrames {
    frames: Mutex<Vec<Frame>>,
}

/// One part's frame, and what it was encoded from.
struct Frame {
    chunk: Weak<TriangleSet>,
    job: u64,
    leaves: Vec<u32>,
    last: bool,
    bytes: Bytes,
}

impl SharedFrames {
    /// The frame of `m`: for a part, one encoded before for another worker
    /// from the very same triangles, if any; otherwise `encode(m)`, kept
    /// for the others when `m` is a part.
    pub fn frame(
        &self,
        m: &SchedulerToWorker,
        encode: impl FnOnce(&SchedulerToWorker) -> Result<Bytes, ProtocolError>,
    ) -> Result<Bytes, ProtocolError> {
        let SchedulerToWorker::Geometry {
            job,
            leaves,
            chunk,
            last,
        } = m
        else {
            return encode(m);
        };
        let same = |f: &Frame| {
            // A live allocation is never reused: the same address is the
            // same triangles.
            f.chunk.strong_count() > 0
                && std::ptr::eq(f.chunk.as_ptr(), Arc::as_ptr(chunk))
                && (f.job, f.last) == (*job, *last)
                && f.leaves == *leaves
        };
        if let Some(f) = self.lock().iter().find(|f| same(f)) {
            return Ok(f.bytes.clone());
        }
        // Encoded outside the lock, so that no other connection's writer
        // waits on it; two that race may both encode.
        let bytes = encode(m)?;
        let mut frames = self.lock();
        frames.retain(|f| f.chunk.strong_count() > 0);
        frames.push(Frame {
            chunk: Arc::downgrade(chunk),
            job: *job,
            leaves: leaves.clone(),
            last: *last,
            bytes: bytes.clone(),
        });
        Ok(bytes)
    }

    /// Drops the frames whose triangles no message holds any longer: the
    /// last writer of a part calls it once its message is gone.
    pub fn prune(&self) {
        self.lock().retain(|f| f.chunk.strong_count() > 0);
    }

    /// Frames held (for tests).
    #[cfg(test)]
    fn len(&self) -> usize {
        self.lock().len()
    }

    fn lock(&self) -> MutexGuard<'_, Vec<Frame>> {
        self.frames.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::cell::Cell;

    fn part(chunk: &Arc<TriangleSet>, leaves: Vec<u32>) -> SchedulerToWorker {
        SchedulerToWorker::Geometry {
            job: 7,
            leaves,
            chunk: chunk.clone(),
            last: true,
        }
    }

    /// Two workers' messages of one part share one encoding; a part of
    /// other triangles or leaves, and other messages, are encoded apart;
    /// a frame is let go once no message holds its triangles.
    #[test]
    fn a_part_sent_to_several_workers_is_encoded_once() {
        let encodings = Cell::new(0);
        let encode = |m: &SchedulerToWorker| {
            encodings.set(encodings.get() + 1);
            Ok(Bytes::from(postcard::to_allocvec(m).unwrap()))
        };
        let frames = SharedFrames::default();
        let set = TriangleSet {
            ids: vec![1, 4],
            verts: vec![[glam::Vec3::X, glam::Vec3::Y, glam::Vec3::Z]; 2],
            material: vec![0, 0],
            normals: Vec::new(),
        };
        let chunk = Arc::new(set.clone());
        let (a, b) = (part(&chunk, vec![3]), part(&chunk, vec![3]));
        let fa = frames.frame(&a, encode).unwrap();
        let fb = frames.frame(&b, encode).unwrap();
        assert_eq!(encodings.get(), 1);
        assert_eq!(fa.as_ptr(), fb.as_ptr(), "one buffer for both");
        let decoded: SchedulerToWorker = postcard::from_bytes(&fb).unwrap();
        assert!(matches!(decoded, SchedulerToWorker::Geometry { chunk: c, .. } if *c == set));
        // The same triangles but other leaves; equal triangles elsewhere.
        frames.frame(&part(&chunk, vec![4]), encode).unwrap();
        let copy = Arc::new(set.clone());
        frames.frame(&part(&copy, vec![3]), encode).unwrap();
        frames.frame(&SchedulerToWorker::Heartbeat, encode).unwrap();
        assert_eq!(encodings.get(), 4);
        drop((a, b, copy));
        frames.prune();
        assert_eq!(frames.len(), 2, "the two frames of `chunk` are kept");
        drop(chunk);
        frames.prune();
        assert_eq!(frames.len(), 0);
    }
}
