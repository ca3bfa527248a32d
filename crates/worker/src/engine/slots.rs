//! What a worker keeps pending in one job: the camera samples of its tiles,
//! and the vertices shaded here that wait for answers from other workers.
//!
//! A slot is either a camera sample (its radiance goes into the tile) or a
//! vertex (its shadow answer and its continuation's radiance are awaited;
//! when both are in, [`ShadedVertex::finish`] gives its radiance, which
//! answers whoever asked). Answers cascade within the worker without
//! recursion: a finished vertex answers exactly one asker. A tile is done
//! when all its samples are in; each pixel's samples are summed by the
//! core's [`pass_sum`], as one machine sums them.

use glam::Vec3;
use locus_core::integrator::PathRay;
use locus_core::integrator::ShadedVertex;
use locus_core::passes::pass_sum;
use locus_core::path::{Answer, CacheKey, ChainVertex, Child, Dest, Query};
use locus_core::region::{Resume, WorkerId};
use locus_core::stats::TraceStats;
use locus_protocol::control::{TileAssignment, TileResult};
use locus_protocol::rays::ReplyTo;
use std::collections::{HashMap, VecDeque};

#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("worker {from} sent an answer for slot {slot}, which is not waiting for one")]
pub struct UnknownSlot {
    pub from: WorkerId,
    pub slot: u32,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Wait<T> {
    Pending,
    Done(T),
}

/// One slot, aligned to a cache line so that an answer costs one line.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(align(64))]
enum Slot {
    Free,
    Sample {
        tile: u32,
        index: u32,
    },
    /// A vertex waiting for answers. Its directional cache entry, if its
    /// continuation updates one, is kept aside in `Slots::updates`: a slot
    /// fits a cache line, and answers touch slots at random.
    Vertex {
        reply: ReplyTo,
        vertex: ShadedVertex,
        shadow: Wait<bool>,
        next: Wait<Vec3>,
    },
}

struct TileState {
    a: TileAssignment,
    values: Vec<Vec3>,
    remaining: u32,
    /// The next sample to start: its index in `values`, its pixel, and
    /// how many of that pixel's samples have started.
    next: u32,
    pixel: u32,
    within: u32,
}

/// What an answer set off besides the slots it filled.
#[derive(Clone, Debug, PartialEq)]
pub enum Effect {
    /// A finished vertex answers an asker on another worker.
    Reply(ReplyTo, Answer),
    /// A vertex's segment query got beyond its perimeter: the cache `key`
    /// answers for `slot`, or `ray` is traced on from the perimeter (and
    /// then updates the cache, as [`Slots::expect_update`] arranges).
    Beyond {
        slot: u32,
        key: CacheKey,
        ray: PathRay,
    },
    /// A continuation's radiance, for the directional cache entry that
    /// asked for it.
    CacheUpdate(CacheKey, Vec3),
    TileDone(TileResult),
}

/// A camera sample to start: where it is and where its radiance goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NewSample {
    pub x: u32,
    pub y: u32,
    pub sample: u32,
    pub reply: ReplyTo,
}

pub struct Slots {
    me: WorkerId,
    job: u64,
    /// The image's width, height and samples per pixel, that tiles must
    /// fit.
    image: [u32; 3],
    slots: Vec<Slot>,
    free: Vec<u32>,
    /// Cache entries that pending continuations update, by slot.
    updates: HashMap<u32, CacheKey>,
    /// Continuations that went on as segment queries, by slot: the cache
    /// that answers if the segment gets beyond its perimeter, and the ray
    /// to trace on if the cache cannot.
    segments: HashMap<u32, (CacheKey, PathRay)>,
    tiles: Vec<Option<TileState>>,
    /// Held tiles with samples not started yet, in arrival order: the
    /// front one starts next.
    fresh: VecDeque<u32>,
    /// Tiles held, and the samples of the largest tile ever held.
    held: usize,
    largest: usize,
    samples_open: usize,
}

impl Slots {
    pub fn new(me: WorkerId, job: u64, image: [u32; 3]) -> Self {
        Self {
            me,
            job,
            image,
            slots: Vec::new(),
            free: Vec::new(),
            updates: HashMap::new(),
            segments: HashMap::new(),
            tiles: Vec::new(),
            fresh: VecDeque::new(),
            held: 0,
            largest: 0,
            samples_open: 0,
        }
    }

    /// Camera samples started and not yet answered.
    pub fn samples_open(&self) -> usize {
        self.samples_open
    }

    /// Asks the processor to bring `slot` into cache ahead of its answer:
    /// answers arrive for slots at random, and a packet's worth of them
    /// otherwise waits on memory one after another.
    #[inline(always)]
    pub fn prefetch(&self, slot: u32) {
        #[cfg(target_arch = "x86_64")]
        if let Some(s) = self.slots.get(slot as usize) {
            // SAFETY: a prefetch never faults and has no other effect; the
            // address is in bounds besides.
            unsafe {
                use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
                _mm_prefetch::<_MM_HINT_T0>((s as *const Slot).cast());
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = slot;
    }

    /// The second stage of a prefetch, a few items after [`Self::prefetch`]
    /// brought `slot` in: what its answer will write next, the parent
    /// vertex's slot or the tile's sample value. Without it, the cascade
    /// from a finished vertex to its parent waits on memory: in a profile
    /// of two workers that load was most of [`Self::answer`]'s time.
    #[inline(always)]
    pub fn prefetch_next(&self, slot: u32) {
        #[cfg(target_arch = "x86_64")]
        {
            let p: *const u8 = match self.slots.get(slot as usize) {
                Some(Slot::Vertex { reply, .. }) if reply.worker == self.me => {
                    match self.slots.get(reply.slot as usize) {
                        Some(s) => (s as *const Slot).cast(),
                        None => return,
                    }
                }
                Some(Slot::Sample { tile, index }) => match self.tiles.get(*tile as usize) {
                    Some(Some(t)) => match t.values.get(*index as usize) {
                        Some(v) => (v as *const Vec3).cast(),
                        None => return,
                    },
                    _ => return,
                },
                _ => return,
            };
            // SAFETY: as in `prefetch`: no fault, no effect, in bounds.
            unsafe {
                use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
                _mm_prefetch::<_MM_HINT_T0>(p.cast());
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = slot;
    }

    /// Slots waiting for an answer.
    pub fn pending(&self) -> usize {
        self.slots.len() - self.free.len()
    }

    /// Whether a tile is held (started or not).
    pub fn has_tiles(&self) -> bool {
        self.held > 0
    }

    /// Tiles held: all of them, those with samples not started yet, and
    /// the samples of the largest held so far.
    pub fn tiles_held(&self) -> (usize, usize, usize) {
        (self.held, self.fresh.len(), self.largest)
    }

    fn alloc(&mut self, s: Slot) -> u32 {
        match self.free.pop() {
            Some(i) => {
                self.slots[i as usize] = s;
                // The next slot handed out is known now: a chain opens a
                // slot per vertex, and a freed slot is cold by then.
                if let Some(&next) = self.free.last() {
                    self.prefetch(next);
                }
                i
            }
            None => {
                self.slots.push(s);
                (self.slots.len() - 1) as u32
            }
        }
    }

    fn release(&mut self, slot: u32) {
        self.slots[slot as usize] = Slot::Free;
        self.free.push(slot);
    }

    /// Holds tile `a` until its pass's samples are in, if it fits the
    /// image. A tile whose pass gives its pixels no samples (adaptive
    /// sampling can) is not held: its result, every sum zero, is returned
    /// at once.
    pub fn add_tile(&mut self, a: TileAssignment) -> Result<Option<TileResult>, String> {
        let [w, h, spp] = self.image;
        if let Some(p) = a.problem(w, h, spp) {
            return Err(p);
        }
        // At most MAX_TILE_PASS_SAMPLES, which `problem` checked.
        let n = a.total_samples() as u32;
        if n == 0 {
            return Ok(Some(TileResult {
                job: self.job,
                tile: a.tile,
                pass: a.pass,
                sums: vec![Default::default(); a.pixels() as usize],
            }));
        }
        // Room for the samples' values is made when the first starts: a
        // tile traced whole ([`Slots::take_whole`]) never needs it.
        let st = TileState {
            a,
            values: Vec::new(),
            remaining: n,
            next: 0,
            pixel: 0,
            within: 0,
        };
        let i = match self.tiles.iter().position(Option::is_none) {
            Some(i) => {
                self.tiles[i] = Some(st);
                i
            }
            None => {
                self.tiles.push(Some(st));
                self.tiles.len() - 1
            }
        };
        self.fresh.push_back(i as u32);
        self.held += 1;
        self.largest = self.largest.max(n as usize);
        Ok(None)
    }

    /// Whether the next tile to start has started some of its samples
    /// already: its others go on one by one.
    pub fn front_started(&self) -> bool {
        self.fresh
            .front()
            .and_then(|&ti| self.tiles[ti as usize].as_ref())
            .is_some_and(|t| t.next > 0)
    }

    /// The next tile to start, to be traced whole, if none of its samples
    /// has started. It stays counted as held until [`Slots::whole_done`].
    pub fn take_whole(&mut self) -> Option<TileAssignment> {
        if !self.whole_ready() {
            return None;
        }
        let ti = self.fresh.pop_front()?;
        let t = self.tiles[ti as usize]
            .take()
            .expect("a fresh tile is held");
        Some(t.a)
    }

    /// Whether [`Slots::take_whole`] would hand out a tile.
    pub fn whole_ready(&self) -> bool {
        !self.fresh.is_empty() && !self.front_started()
    }

    /// A tile taken by [`Slots::take_whole`] is done.
    pub fn whole_done(&mut self) {
        self.held -= 1;
    }

    /// The next camera sample of a held tile that has not started, with
    /// the slot its radiance goes to; pixel by pixel, sample by sample.
    pub fn start_sample(&mut self) -> Option<NewSample> {
        let ti = *self.fresh.front()?;
        let t = self.tiles[ti as usize]
            .as_mut()
            .expect("a fresh tile is held");
        if t.next == 0 {
            t.values = vec![Vec3::ZERO; t.remaining as usize];
        }
        // Past the pixels whose samples have all started, or that take
        // none in this pass: a held tile has a sample left to start.
        let mut range = t.a.pixel_samples(t.pixel);
        while t.within >= range.len() as u32 {
            t.pixel += 1;
            t.within = 0;
            range = t.a.pixel_samples(t.pixel);
        }
        let (index, (x, y)) = (t.next, t.a.pixel(t.pixel));
        let sample = range.start + t.within;
        t.next += 1;
        t.within += 1;
        if t.next as usize >= t.values.len() {
            self.fresh.pop_front();
        }
        let slot = self.alloc(Slot::Sample { tile: ti, index });
        self.samples_open += 1;
        Some(NewSample {
            x,
            y,
            sample,
            reply: ReplyTo {
                worker: self.me,
                slot,
            },
        })
    }

    /// Opens a slot per vertex of `chain` (vertex k+1 answers vertex k, the
    /// first answers `reply`) and lists the children that must be sent on,
    /// each with the slot its answer goes to.
    pub fn open_chain(
        &mut self,
        reply: ReplyTo,
        chain: &[ChainVertex],
        out: &mut Vec<(Dest, Query, Resume, ReplyTo)>,
    ) {
        let mut parent = reply;
        for cv in chain {
            let wait = |c: &Child<bool>| match c {
                Child::Done(b) => Wait::Done(*b),
                _ => Wait::Pending,
            };
            let slot = self.alloc(Slot::Vertex {
                reply: parent,
                vertex: cv.vertex,
                shadow: wait(&cv.shadow),
                next: match cv.next {
                    Child::Done(l) => Wait::Done(l),
                    _ => Wait::Pending,
                },
            });
            match (cv.update, cv.next) {
                (Some(k), Child::Forward(_, Query::Segment(q), _)) => {
                    self.segments.insert(slot, (k, q));
                }
                (Some(k), _) => {
                    self.updates.insert(slot, k);
                }
                (None, _) => {}
            }
            let mine = ReplyTo {
                worker: self.me,
                slot,
            };
            if let Child::Forward(d, q, t) = cv.shadow {
                out.push((d, q, t, mine));
            }
            if let Child::Forward(d, q, t) = cv.next {
                out.push((d, q, t, mine));
            }
            parent = mine;
        }
    }

    /// The continuation of vertex `slot`, traced on from its perimeter,
    /// updates cache entry `key` when its radiance comes.
    pub fn expect_update(&mut self, slot: u32, key: CacheKey) {
        self.updates.insert(slot, key);
    }

    /// Applies answer `a` (from worker `from`) to `slot`, and whatever it
    /// finishes in turn here; replies to other workers, cache updates and
    /// finished tiles are pushed to `effects`. Samples are counted into
    /// `st` as tiles finish.
    pub fn answer(
        &mut self,
        from: WorkerId,
        slot: u32,
        a: Answer,
        effects: &mut Vec<Effect>,
        st: &mut TraceStats,
    ) -> Result<(), UnknownSlot> {
        let mut todo = Some((from, slot, a));
        while let Some((from, slot, a)) = todo.take() {
            let bad = UnknownSlot { from, slot };
            let Some(s) = self.slots.get_mut(slot as usize) else {
                return Err(bad);
            };
            match s {
                Slot::Free => return Err(bad),
                Slot::Sample { tile, index } => {
                    let Answer::Radiance(l) = a else {
                        return Err(bad);
                    };
                    let (tile, index) = (*tile, *index);
                    self.release(slot);
                    self.samples_open -= 1;
                    let Some(t) = self.tiles[tile as usize].as_mut() else {
                        return Err(bad);
                    };
                    t.values[index as usize] = l;
                    t.remaining -= 1;
                    if t.remaining == 0 {
                        let done = self.finish_tile(tile, st);
                        effects.push(Effect::TileDone(done));
                    }
                }
                Slot::Vertex {
                    reply,
                    vertex,
                    shadow,
                    next,
                } => {
                    match (a, &*shadow, &*next) {
                        (Answer::Visible(v), Wait::Pending, _) => *shadow = Wait::Done(v),
                        (Answer::Radiance(l), _, Wait::Pending) => {
                            *next = Wait::Done(l);
                            if !self.updates.is_empty()
                                && let Some(k) = self.updates.remove(&slot)
                            {
                                effects.push(Effect::CacheUpdate(k, l));
                            }
                            // A segment that hit inside its sphere: its
                            // radiance is no cache's.
                            if !self.segments.is_empty() {
                                self.segments.remove(&slot);
                            }
                        }
                        (Answer::Beyond, _, Wait::Pending) => {
                            let Some((key, ray)) = self.segments.remove(&slot) else {
                                return Err(bad);
                            };
                            effects.push(Effect::Beyond { slot, key, ray });
                            continue;
                        }
                        _ => return Err(bad),
                    }
                    let (Wait::Done(visible), Wait::Done(nl)) = (*shadow, *next) else {
                        continue;
                    };
                    let l = vertex.finish(visible, nl);
                    let reply = *reply;
                    self.release(slot);
                    if reply.worker == self.me {
                        todo = Some((self.me, reply.slot, Answer::Radiance(l)));
                    } else {
                        effects.push(Effect::Reply(reply, Answer::Radiance(l)));
                    }
                }
            }
        }
        Ok(())
    }

    /// Each pixel's samples of the pass summed in index order, as one
    /// machine does ([`locus_core::passes`]).
    fn finish_tile(&mut self, tile: u32, st: &mut TraceStats) -> TileResult {
        let t = self.tiles[tile as usize]
            .take()
            .expect("a tile with samples in flight is held");
        self.held -= 1;
        let mut rest = &t.values[..];
        let sums = (0..t.a.pixels())
            .map(|p| {
                let (samples, after) = rest.split_at(t.a.pixel_samples(p).len());
                rest = after;
                pass_sum(0..samples.len() as u32, st, |s, _| samples[s as usize])
            })
            .collect();
        TileResult {
            job: self.job,
            tile: t.a.tile,
            pass: t.a.pass,
            sums,
        }
    }
}

#[cfg(test)]
mod tests;
