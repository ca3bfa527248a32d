//! Random polling for hot regions (paper 003, section 5.2, offered to the
//! render job): a worker with nothing to trace asks a random peer for
//! work; a peer with a long queue (forwarded queries and camera samples)
//! hands some of it over, and one without answers with the workers it
//! knows to be idle, so that the poller does not try them next.
//!
//! Handed work is traced by the poller through its own route. The
//! hander's leaves it crosses are fetched (as under the `fetch` policy),
//! not forwarded back, and stay for the job: each hit is the one the owner
//! would find, so the image keeps its bits. Leaves of other workers are
//! forwarded to their owners as usual, and answers go to the query's
//! origin or the sample's slot, which cannot tell who traced them.
//!
//! Nothing here can hang: a poll is answered by exactly one message, and
//! one that is not (its peer's queue is long) is given up after
//! [`POLL_TIMEOUT`]. A peer that had nothing to spare is not polled again
//! for [`QUIET`]. Nothing grows without bound either: handed work belongs
//! to samples open at its origin, and a worker polls only while it has
//! fewer than `max_inflight` slots waiting.

use super::kernel::Work;
use super::state::Engine;
use super::{EngineError, Received};
use locus_core::path::Task;
use locus_core::region::{Resume, WorkerId};
use locus_protocol::rays::{HandedSample, Packet, PeerMsg, RayItem, ReplyTo};
use std::time::{Duration, Instant};

/// Queued items a worker keeps before it hands any over: fewer are
/// traced here in about the time a poller would need to fetch their
/// leaves.
const HAND_MIN: usize = 1024;
/// Most items handed over for one poll (and at most half the queue).
const HAND_MAX: usize = 4096;
/// A peer that had nothing to spare, or was named idle, is left alone for
/// this long.
const QUIET: Duration = Duration::from_millis(2);
/// An unanswered poll is given up after this long.
const POLL_TIMEOUT: Duration = Duration::from_millis(50);

/// A worker's side of random polling.
pub(super) struct Polling {
    pub(super) on: bool,
    /// The peer polled, and when, until it answers.
    outstanding: Option<(WorkerId, Instant)>,
    /// Per peer: not to be polled before this.
    quiet_until: Vec<Option<Instant>>,
    /// Per peer: when it last polled this worker (it was idle then).
    polled_at: Vec<Option<Instant>>,
    rng: u64,
}

impl Polling {
    pub(super) fn new(on: bool, workers: usize, me: WorkerId, seed: u64) -> Self {
        Self {
            on: on && workers > 1,
            outstanding: None,
            quiet_until: vec![None; workers],
            polled_at: vec![None; workers],
            // Which peer is polled changes no bit of the image; the seed
            // only keeps runs alike.
            rng: (seed ^ (me as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15)) | 1,
        }
    }

    /// When the loop must wake to poll again: the end of the outstanding
    /// poll's wait, or of the next quiet peer's. A quiet time already past
    /// wakes nothing (the next idle turn polls anyway); counting it would
    /// spin the loop while it may not poll, waiting for fetched leaves.
    pub(super) fn wake(&self, now: Instant) -> Option<Duration> {
        if !self.on {
            return None;
        }
        let at = match self.outstanding {
            Some((_, t)) => t + POLL_TIMEOUT,
            None => *self
                .quiet_until
                .iter()
                .flatten()
                .filter(|&&t| t > now)
                .min()?,
        };
        Some(at.saturating_duration_since(now))
    }

    /// A random peer that may be polled now.
    fn pick(&mut self, me: WorkerId, now: Instant) -> Option<WorkerId> {
        let free = |w: usize, q: &Option<Instant>| w != me as usize && q.is_none_or(|t| t <= now);
        let n = self
            .quiet_until
            .iter()
            .enumerate()
            .filter(|(w, q)| free(*w, q))
            .count();
        if n == 0 {
            return None;
        }
        self.rng ^= self.rng << 13;
        self.rng ^= self.rng >> 7;
        self.rng ^= self.rng << 17;
        let k = (self.rng % n as u64) as usize;
        self.quiet_until
            .iter()
            .enumerate()
            .filter(|(w, q)| free(*w, q))
            .nth(k)
            .map(|(w, _)| w as WorkerId)
    }
}

impl Engine<'_> {
    /// Polls a random peer, when this worker has nothing to trace and no
    /// poll is out.
    pub(super) fn maybe_poll(&mut self) -> Result<(), EngineError> {
        let now = self.now;
        let p = &mut self.polling;
        // Work waiting for fetched leaves will soon be traced here. Handed
        // work opens slots here beyond this worker's own samples: it is
        // taken only while the slots waiting for answers are fewer than
        // `max_inflight`, so that what a worker holds stays bounded by
        // twice its own share (and what one poll hands over).
        let full = self.slots.pending() >= self.job.setup.tuning.max_inflight as usize;
        if !p.on
            || full
            || !self.waiting.is_empty()
            || p.outstanding.is_some_and(|(_, t)| now < t + POLL_TIMEOUT)
        {
            return Ok(());
        }
        p.outstanding = None;
        let Some(to) = p.pick(self.job.setup.me, now) else {
            return Ok(());
        };
        p.outstanding = Some((to, now));
        self.stats.polls += 1;
        Ok(self.outbox.send(to, PeerMsg::Poll)?)
    }

    /// Answers a poll: with queued work when there is much, otherwise
    /// with the workers known to be idle.
    pub(super) fn polled(&mut self, from: WorkerId) -> Result<(), EngineError> {
        let now = self.now;
        if let Some(t) = self.polling.polled_at.get_mut(from as usize) {
            *t = Some(now);
        }
        // Work is taken from the back of the queue, where camera samples
        // wait (queries go to the front); a bounded stretch is looked at,
        // so that a poll costs little however long the queue.
        let work = self.work.items();
        let scan = work.len().min(2 * HAND_MAX);
        let spare = if work.len() < HAND_MIN {
            0
        } else {
            work.iter().rev().take(scan).filter(|w| handable(w)).count()
        };
        if spare < HAND_MIN {
            let me = self.job.setup.me;
            let idle = self
                .polling
                .polled_at
                .iter()
                .enumerate()
                .filter(|&(w, t)| w != from as usize && t.is_some_and(|t| now < t + QUIET))
                .map(|(w, _)| w as WorkerId)
                .chain(self.work.is_empty().then_some(me))
                .collect();
            return Ok(self.outbox.send(from, PeerMsg::NoWork { idle })?);
        }
        let n = (spare / 2).min(HAND_MAX);
        let work = self.work.items();
        let tail: Vec<Work> = work.drain(work.len() - scan..).collect();
        let mut queries = Packet::default();
        let mut samples = Vec::new();
        let mut handed = 0;
        for w in tail {
            if handed == n || !handable(&w) {
                self.work.push_back(w);
                continue;
            }
            handed += 1;
            match w.task {
                // What the sender's walk showed to lie in this worker's
                // leaves is not the poller's.
                Task::Query(query) => queries.push(&RayItem::Trace {
                    query,
                    resume: Resume::at(w.resume.at),
                    reply: w.reply,
                }),
                Task::Camera { x, y, sample } => samples.push(HandedSample {
                    x,
                    y,
                    sample,
                    slot: w.reply.slot,
                }),
            }
        }
        self.stats.handed_out += handed as u64;
        Ok(self
            .outbox
            .send(from, PeerMsg::Handed { queries, samples })?)
    }

    /// Work a polled peer handed over: traced here, fetching its leaves.
    pub(super) fn handed(
        &mut self,
        from: WorkerId,
        queries: Packet,
        samples: Vec<HandedSample>,
    ) -> Result<(), EngineError> {
        self.answered(from);
        self.stats.polls_answered += 1;
        let job = self.job;
        let s = &job.setup;
        let bad = |what: String| EngineError::BadHanded { from, what };
        let r = Received::decode(from, &queries, s.seed, s.sampler, job.workers)?;
        if !r.answers.is_empty() {
            return Err(bad("an answer".into()));
        }
        for mut w in r.queries {
            self.stats.handed_in += 1;
            // Whatever span the sender claims lies in its leaves, not in
            // this worker's.
            w.resume = Resume::at(w.resume.at);
            w.handed_by = Some(from);
            self.work.push_front(w);
        }
        for h in samples {
            let (w, ht, spp) = (s.camera.width, s.camera.height, s.spp);
            if h.x >= w || h.y >= ht || h.sample >= spp {
                return Err(bad(format!(
                    "sample {} of pixel ({}, {}), outside the {w}x{ht} image at {spp} spp",
                    h.sample, h.x, h.y
                )));
            }
            self.stats.handed_in += 1;
            self.work.push_back(Work {
                task: Task::Camera {
                    x: h.x,
                    y: h.y,
                    sample: h.sample,
                },
                resume: Resume::START,
                reply: ReplyTo {
                    worker: from,
                    slot: h.slot,
                },
                from,
                pinned: None,
                handed_by: Some(from),
            });
        }
        Ok(())
    }

    /// A polled peer had nothing to spare: it and the idle workers it
    /// named are left alone for a while.
    pub(super) fn no_work(
        &mut self,
        from: WorkerId,
        idle: Vec<WorkerId>,
    ) -> Result<(), EngineError> {
        self.answered(from);
        let until = self.now + QUIET;
        for w in std::iter::once(from).chain(idle) {
            let Some(q) = self.polling.quiet_until.get_mut(w as usize) else {
                return Err(EngineError::BadIdle { from, worker: w });
            };
            *q = Some(until);
        }
        Ok(())
    }

    fn answered(&mut self, from: WorkerId) {
        if self.polling.outstanding.is_some_and(|(w, _)| w == from) {
            self.polling.outstanding = None;
        }
    }
}

/// Queued work that may be handed over: not waiting on a leaf this
/// worker fetched, and not itself handed here (it would travel on and on).
fn handable(w: &Work) -> bool {
    w.pinned.is_none() && w.handed_by.is_none()
}
