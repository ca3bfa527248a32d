//! The engine's loop. A turn hands batches to the pool, traces a batch on
//! the engine's own thread when it traces at all, sends what waits when
//! nothing is being traced, then takes what has arrived: it waits for an
//! event only when there is nothing to trace, and never longer than the
//! engine's next deadline ([`Engine::wait_bound`]).

use super::kernel::{trace_batch, trace_tile};
use super::state::{Engine, STALL_REPORT};
use super::{BATCH, EVENTS_PER_TURN, EngineError, Event, INLINE_BATCH, Input, MIN_BATCH};
use locus_protocol::report::WorkerStats;
use std::time::{Duration, Instant};

/// What the loop keeps between turns: its clock and how many pool tasks
/// are out.
struct Turns<'i> {
    inbox: &'i flume::Receiver<Event>,
    pool_threads: usize,
    /// Whether this thread traces too (beside a small pool, or alone).
    engine_traces: bool,
    start: Instant,
    /// Time spent waiting with nothing out (idle) and waiting for the
    /// pool's batches while they are out (see
    /// `WorkerStats::engine_wait_s`).
    idle: Duration,
    waited: Duration,
    /// Pool tasks handed out and not yet back.
    out: usize,
    last_event: Instant,
    /// Whether the present stall has been reported.
    warned: bool,
}

/// Runs turns until the scheduler ends the job (the worker's counters) or
/// something fails. `scope` is the pool's, of `pool_threads` threads.
pub(super) fn turns<'a: 's, 's>(
    mut e: Engine<'a>,
    inbox: flume::Receiver<Event>,
    cancel: &tokio_util::sync::CancellationToken,
    scope: Option<&rayon::Scope<'s>>,
    pool_threads: usize,
    engine_traces: bool,
) -> Result<WorkerStats, EngineError> {
    let now = Instant::now();
    let mut t = Turns {
        inbox: &inbox,
        pool_threads,
        engine_traces,
        start: now,
        idle: Duration::ZERO,
        waited: Duration::ZERO,
        out: 0,
        last_event: now,
        warned: false,
    };
    loop {
        if cancel.is_cancelled() {
            return Err(EngineError::Cancelled(Box::new(t.counters(&mut e))));
        }
        e.outbox.retry_stalled()?;
        if !e.outbox.is_stalled() {
            e.originate();
        }
        e.top_up_tiles()?;
        e.maybe_merge();
        if e.reach_dirty {
            e.republish();
        }
        if let Some(scope) = scope {
            t.hand_out(&mut e, scope);
        }
        let traced_here = t.trace_here(&mut e)?;
        // Idle: nothing out, nothing queued, no tile waiting to be traced
        // whole (a worker tracing tiles whole has an empty queue between
        // them).
        if t.out == 0 && e.work.is_empty() && !e.whole_ready() {
            // Nothing is being traced: what waits in packets must go, and
            // a peer may have queries to spare.
            e.outbox.flush_all()?;
            e.send_tiles_done()?;
            e.now = Instant::now();
            e.maybe_poll()?;
        }
        let first = t.first_event(&mut e, traced_here)?;
        if let Some(stats) = t.handle(&mut e, first, scope)? {
            return Ok(stats);
        }
        e.outbox.flush_due(e.now)?;
        e.send_tiles_due(e.now)?;
    }
}

impl Turns<'_> {
    /// The worker's counters when the job is cancelled.
    fn counters(&self, e: &mut Engine<'_>) -> WorkerStats {
        let mut stats = std::mem::take(&mut e.stats);
        stats.busy_s = self.start.elapsed().saturating_sub(self.idle).as_secs_f64();
        stats.idle_s = self.idle.as_secs_f64();
        stats.engine_wait_s = self.waited.as_secs_f64();
        stats
    }

    /// Hands the pool batches from the queue, then tiles traced whole.
    fn hand_out<'a: 's, 's>(&mut self, e: &mut Engine<'a>, scope: &rayon::Scope<'s>) {
        // Two batches per pool thread, and one more: a pool thread that
        // finishes finds the next batch queued, however long this thread's
        // own batch or bookkeeping takes. With one batch per thread they
        // waited for this thread to hand out more, and a worker of 16
        // threads traced at half of one machine's speed.
        let target = 2 * self.pool_threads + 1;
        // A dedicated engine hands out everything, however little.
        let least = if self.engine_traces { MIN_BATCH } else { 0 };
        while self.out < target && e.work.len() > least {
            let share = e.work.len().div_ceil(target + 1 - self.out);
            let take = share.clamp(MIN_BATCH, BATCH).min(e.work.len());
            let batch = e.work.take(take);
            let spare = e.spares.pop();
            let (job, reach, tx) = (e.job, e.reach.clone(), e.events.clone());
            scope.spawn(move |_| {
                let b = trace_batch(job, &reach, batch.into_iter(), spare);
                // A closed inbox means the job is over.
                let _ = tx.send(Event::Traced(b));
            });
            self.out += 1;
        }
        // Beside what waits in the queue (answers to peers first), tiles
        // traced whole, a task each.
        while self.out < target
            && e.work.len() <= least
            && let Some(a) = e.take_whole()
        {
            let (job, reach, tx) = (e.job, e.reach.clone(), e.events.clone());
            scope.spawn(move |_| {
                let _ = tx.send(Event::Tile(trace_tile(job, &reach, a)));
            });
            self.out += 1;
        }
    }

    /// Traces a batch, or else a tile whole, on this thread when it traces;
    /// whether it did. This thread's time is counted whole at the end, so
    /// what it traces here adds none.
    fn trace_here(&self, e: &mut Engine<'_>) -> Result<bool, EngineError> {
        if !self.engine_traces {
            return Ok(false);
        }
        if !e.work.is_empty() {
            let batch = e.work.take(e.work.len().min(INLINE_BATCH));
            let spare = e.spares.pop();
            let mut b = trace_batch(e.job, &e.reach, batch.into_iter(), spare);
            b.cpu_s = 0.0;
            e.now = Instant::now();
            e.apply(b)?;
        } else if let Some(a) = e.take_whole() {
            let mut t = trace_tile(e.job, &e.reach, a);
            t.cpu_s = 0.0;
            e.now = Instant::now();
            e.apply_tile(t)?;
        } else {
            return Ok(false);
        }
        Ok(true)
    }

    /// The first event of the turn: what has come when there is work here
    /// (without waiting), else whatever comes before the engine's next
    /// deadline. None when nothing came.
    fn first_event(
        &mut self,
        e: &mut Engine<'_>,
        traced_here: bool,
    ) -> Result<Option<Event>, EngineError> {
        let first = if traced_here || (self.engine_traces && !e.work.is_empty()) {
            self.inbox.try_recv().map_err(|err| match err {
                flume::TryRecvError::Empty => flume::RecvTimeoutError::Timeout,
                flume::TryRecvError::Disconnected => flume::RecvTimeoutError::Disconnected,
            })
        } else {
            // A dedicated engine whose pool is full waits for a batch back.
            let t = Instant::now();
            let r = self.inbox.recv_timeout(e.wait_bound(t));
            if self.out > 0 {
                self.waited += t.elapsed();
            } else {
                self.idle += t.elapsed();
                // Why a worker waits, for `RUST_LOG=locus_worker=trace`.
                tracing::trace!(
                    me = e.job.setup.me,
                    ms = t.elapsed().as_secs_f64() * 1e3,
                    open = e.slots.samples_open(),
                    pending = e.slots.pending(),
                    no_more_tiles = e.no_more_tiles,
                    stalled = e.outbox.is_stalled(),
                    "idle"
                );
            }
            r
        };
        e.now = Instant::now();
        let next = match first {
            Ok(ev) => Some(ev),
            Err(flume::RecvTimeoutError::Timeout) => None,
            Err(flume::RecvTimeoutError::Disconnected) => {
                return Err(EngineError::LinkClosed("the worker's inbox"));
            }
        };
        if next.is_some() || traced_here {
            self.last_event = e.now;
            self.warned = false;
        } else if !self.warned && e.now.duration_since(self.last_event) > STALL_REPORT {
            self.warned = true;
            e.report_stall(self.out);
        }
        Ok(next)
    }

    /// Handles `first` and what else has arrived, up to
    /// [`EVENTS_PER_TURN`]; the worker's counters when the job has ended.
    fn handle<'a: 's, 's>(
        &mut self,
        e: &mut Engine<'a>,
        first: Option<Event>,
        scope: Option<&rayon::Scope<'s>>,
    ) -> Result<Option<WorkerStats>, EngineError> {
        let mut next = first;
        let mut handled = 0;
        while let Some(ev) = next.take() {
            handled += 1;
            match ev {
                Event::Traced(b) => {
                    self.out -= 1;
                    e.apply(b)?;
                }
                Event::Tile(t) => {
                    self.out -= 1;
                    e.apply_tile(t)?;
                }
                Event::LeafBuilt(f, cpu) => e.leaf_built(f, cpu),
                Event::Merged(m) => e.merged(m),
                Event::Input(Input::End) => {
                    let waiting: usize = e.waiting.values().map(Vec::len).sum();
                    let left = e.slots.pending() + e.work.len() + waiting + self.out;
                    if left > 0 || e.building > 0 {
                        return Err(EngineError::EndedEarly(left));
                    }
                    let (took, idle, waited) = (self.start.elapsed(), self.idle, self.waited);
                    return Ok(Some(e.finish(took, idle, waited)));
                }
                Event::Input(i) => e.input(i, scope)?,
            }
            if handled < EVENTS_PER_TURN {
                next = self.inbox.try_recv().ok();
            }
        }
        Ok(None)
    }
}
