//! The engine's tiles: asking the scheduler for them ahead of need, and
//! sending finished ones back in bursts. Every message to the scheduler
//! wakes a thread of the worker's runtime and one of the scheduler's,
//! which on a busy machine preempts a tracing thread, so both sides are
//! batched.

use super::EngineError;
use super::state::{Engine, LOCAL_INFLIGHT_PER_THREAD};
use locus_protocol::control::{TileResult, WorkerToScheduler};
use std::time::{Duration, Instant};

/// Samples' worth of tiles a worker may hold, in units of `max_inflight`,
/// besides the tiles ahead (see [`Engine::top_up_tiles`]).
const TILES_PER_INFLIGHT: usize = 8;

/// Finished tiles are held back until this many are in, or the oldest has
/// waited [`TILES_DONE_HOLD`], or the engine asks for tiles or is about to
/// wait: each message to the scheduler wakes a thread of this worker's
/// runtime and one of the scheduler's, which on a busy machine preempts a
/// tracing thread. A render of the conference room at 320x240 and 16 spp
/// is 1,500 tile passes; sent one by one (with a request for tiles after
/// each) they cost a worker of 2 threads about 15,000 context switches.
const TILES_DONE_BATCH: usize = 16;

/// The most tiles a worker keeps ahead however small they are: a request
/// is then at most one and a half times this, well within the
/// scheduler's queue to a worker (256 messages).
const MAX_TILES_AHEAD: usize = 32;

/// The longest a finished tile is held back (see [`TILES_DONE_BATCH`]).
pub(super) const TILES_DONE_HOLD: Duration = Duration::from_millis(5);

/// Tiles a worker holds, as [`Slots::tiles_held`](super::slots::Slots::tiles_held) counts them, and those
/// asked for and not yet received.
#[derive(Clone, Copy, Debug)]
struct Held {
    all: usize,
    fresh: usize,
    asked: usize,
    /// Samples of the largest tile held so far.
    largest: usize,
}

/// How many tiles to ask for (see [`Engine::top_up_tiles`]): none while at
/// least `ahead` tiles with samples not yet started are held or on their
/// way, else enough for half as many again. `ahead` is `tiles_ahead`, or
/// more where tiles are small: enough that their samples would fill what
/// `threads` keep in flight. A first pass's tile is one sample a pixel
/// (256 samples at 16x16), and `tiles_ahead` of those were started within
/// one turn, leaving the threads to wait for the next (the conference room
/// at 16 spp on a worker of 2 threads: 12% of its render, and 15,000
/// context switches where it now has 6,000 to 8,000).
fn tiles_to_ask(tiles_ahead: usize, max_inflight: usize, threads: usize, h: Held) -> usize {
    let tile = h.largest.max(1);
    let fill = (LOCAL_INFLIGHT_PER_THREAD * threads.max(1)).div_ceil(tile);
    let ahead = tiles_ahead.max(1).max(fill.min(MAX_TILES_AHEAD));
    let have = h.fresh + h.asked;
    if have >= ahead {
        return 0;
    }
    let more = ahead + ahead.div_ceil(2);
    let cap = more + TILES_PER_INFLIGHT * max_inflight.max(1).div_ceil(tile);
    (more - have).min(cap.saturating_sub(h.all + h.asked))
}

/// Camera samples a worker keeps open, of the `cap` its tiles call for,
/// as the job nears its end: no more than `queue_share`, an even share of
/// the samples the scheduler still holds (the tile that brought it said
/// so; `NoMoreTiles` says none), and no fewer than half of what keeps
/// `threads` busy. The samples in flight when the scheduler runs dry are
/// the job's tail, which no idle worker can take over, and the windows
/// are shared out by the tiles each worker originates
/// (`locus_scheduler::tiles::inflight`): on the room at 4 and 8 workers
/// under `forward` the worker with the most tiles was still draining
/// its window while the others idled, half a second of a five-second
/// render. Shrinking every window with the queue ends them together.
pub(super) fn window(cap: usize, queue_share: Option<u64>, threads: usize) -> usize {
    let floor = LOCAL_INFLIGHT_PER_THREAD / 2 * threads.max(1);
    match queue_share {
        Some(share) => cap.min(usize::try_from(share).unwrap_or(usize::MAX).max(floor)),
        None => cap,
    }
}

impl Engine<'_> {
    /// Asks the scheduler for tiles so that at least `ahead` tiles with
    /// samples not yet started are held or on their way (`tiles_ahead`,
    /// or more where tiles are small): when fewer are, it asks for half as
    /// many again less those, so that a request (and its reply, each a
    /// wake-up on both sides) comes once every few tiles rather than once
    /// a tile. A tile is asked
    /// for when the last sample of another has started, not when another
    /// finishes: a tile's last samples wait for answers from other workers,
    /// and a worker holding only such tiles would sit idle. A tile is done
    /// only when its slowest sample is, so tiles whose samples have all
    /// started pile up; they are bounded at `TILES_PER_INFLIGHT` times
    /// `max_inflight` samples' worth beyond the tiles ahead (12 bytes a
    /// sample).
    pub(super) fn top_up_tiles(&mut self) -> Result<(), EngineError> {
        if self.no_more_tiles {
            return Ok(());
        }
        let t = &self.job.setup.tuning;
        let (held, fresh, tile) = self.slots.tiles_held();
        let want = tiles_to_ask(
            t.tiles_ahead as usize,
            t.max_inflight as usize,
            self.threads,
            Held {
                all: held,
                fresh,
                asked: self.tiles_asked,
                largest: tile,
            },
        );
        if want > 0 {
            self.tiles_asked += want;
            // Finished tiles travel with the request: one wake-up for both.
            self.send_tiles_done()?;
            self.control(WorkerToScheduler::NeedTiles {
                job: self.job.setup.job,
                count: want as u32,
            })?;
        }
        Ok(())
    }

    /// Holds a finished tile back to go with others (see
    /// [`TILES_DONE_BATCH`]).
    pub(super) fn tile_done(&mut self, r: TileResult) -> Result<(), EngineError> {
        self.stats.tiles += 1;
        self.tiles_done.push(r);
        self.tiles_done_since.get_or_insert(self.now);
        if self.tiles_done.len() >= TILES_DONE_BATCH {
            self.send_tiles_done()?;
        }
        Ok(())
    }

    /// Sends the finished tiles held back, in the order they finished.
    pub(super) fn send_tiles_done(&mut self) -> Result<(), EngineError> {
        self.tiles_done_since = None;
        let done = std::mem::take(&mut self.tiles_done);
        for r in done {
            self.control(WorkerToScheduler::TileDone(r))?;
        }
        Ok(())
    }

    /// Sends the finished tiles held back once the oldest has waited
    /// [`TILES_DONE_HOLD`].
    pub(super) fn send_tiles_due(&mut self, now: Instant) -> Result<(), EngineError> {
        match self.tiles_done_since {
            Some(t) if now.saturating_duration_since(t) >= TILES_DONE_HOLD => {
                self.send_tiles_done()
            }
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn held(all: usize, fresh: usize, asked: usize, largest: usize) -> Held {
        Held {
            all,
            fresh,
            asked,
            largest,
        }
    }

    #[test]
    fn small_tiles_are_asked_for_by_the_samples_they_hold() {
        // First-pass tiles of 256 samples on 2 threads: the threads keep
        // 32,768 samples in flight, more than the most tiles kept ahead
        // hold, so that many are kept, and asked for half as many again.
        let n = tiles_to_ask(2, 65536, 2, held(0, 0, 0, 256));
        assert_eq!(n, MAX_TILES_AHEAD + MAX_TILES_AHEAD / 2);
        // Tiles of 2,048 samples on one thread: `ahead` of them fill what
        // it keeps in flight; one is held, so half as many again less one.
        let ahead = LOCAL_INFLIGHT_PER_THREAD / 2048;
        assert!(ahead > 2 && ahead < MAX_TILES_AHEAD);
        let n = tiles_to_ask(2, 65536, 1, held(3, 1, 0, 2048));
        assert_eq!(n, ahead + ahead / 2 - 1);
        // Tiles larger than what is in flight: `tiles_ahead` still holds.
        assert_eq!(tiles_to_ask(2, 65536, 1, held(0, 0, 0, 1 << 20)), 3);
    }

    #[test]
    fn no_request_while_enough_are_held_or_on_their_way() {
        let ahead = LOCAL_INFLIGHT_PER_THREAD / 2048;
        let ask = |fresh, asked| tiles_to_ask(2, 65536, 1, held(fresh + 2, fresh, asked, 2048));
        assert_eq!(ask(ahead / 2, ahead - ahead / 2), 0);
        assert_eq!(ask(ahead, 0), 0);
        // One fewer than kept ahead: a request for half as many again.
        assert_eq!(ask(ahead - 1, 0), ahead + ahead / 2 - (ahead - 1));
    }

    #[test]
    fn started_tiles_bound_what_is_asked_for() {
        // Tiles whose samples have all started wait for answers from other
        // workers; beyond the bound on what is in flight none are asked.
        let (inflight, tile) = (4096, 2048);
        let ahead = LOCAL_INFLIGHT_PER_THREAD / tile;
        let cap = ahead + ahead / 2 + TILES_PER_INFLIGHT * inflight / tile;
        assert_eq!(tiles_to_ask(2, inflight, 1, held(cap, 0, 0, tile)), 0);
        assert_eq!(tiles_to_ask(2, inflight, 1, held(cap - 3, 0, 0, tile)), 3);
    }

    #[test]
    fn windows_shrink_with_the_queue_down_to_what_keeps_threads_busy() {
        let floor = LOCAL_INFLIGHT_PER_THREAD / 2;
        // Before any tile says, and while the queue holds more than the
        // window, the window is what the tiles call for.
        assert_eq!(window(65536, None, 1), 65536);
        assert_eq!(window(65536, Some(1 << 40), 1), 65536);
        // Then it follows the share, down to the floor for its threads.
        assert_eq!(window(65536, Some(20_000), 1), 20_000);
        assert_eq!(window(65536, Some(100), 1), floor);
        assert_eq!(window(65536, Some(0), 2), 2 * floor);
        // A window already below the floor stays as it was.
        assert_eq!(window(1000, Some(0), 4), 1000);
    }
}
