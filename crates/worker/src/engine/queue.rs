//! The engine's queue of work to trace.
//!
//! A peer's packet of queries arrives decoded as a list of [`Work`] (the
//! link's reader decodes it on the async runtime), and goes to the pool
//! as that list, or as pieces cut from its end, never item by item: the
//! engine's thread is serial, and in a worker of eight tracing threads
//! moving each query into a queue and out again into a batch was about
//! 8% of that thread's instructions. Single items (camera samples,
//! queries whose fetched leaf came, handed work) wait behind the lists.
//! Peers' queries go first, so that a peer whose samples all wait here
//! does not run dry while they queue behind samples this worker started;
//! which order the rest go in changes no answer (every answer is a pure
//! function of its query).

use super::kernel::Work;
use std::collections::VecDeque;

#[derive(Default)]
pub struct WorkQueue {
    /// Peers' packets of queries, whole or what is left of them.
    lists: VecDeque<Vec<Work>>,
    /// Items in `lists`.
    listed: usize,
    items: VecDeque<Work>,
}

impl WorkQueue {
    pub fn len(&self) -> usize {
        self.listed + self.items.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// A peer's packet of queries, ahead of every single item.
    pub fn push_list(&mut self, list: Vec<Work>) {
        if !list.is_empty() {
            self.listed += list.len();
            self.lists.push_back(list);
        }
    }

    /// An item to trace before the other single items.
    pub fn push_front(&mut self, w: Work) {
        self.items.push_front(w);
    }

    /// An item to trace after everything queued.
    pub fn push_back(&mut self, w: Work) {
        self.items.push_back(w);
    }

    /// At most `max` items (at least one while any is queued): the first
    /// list whole if it holds no more, else its last `max` (moving only
    /// those), else single items from the front.
    pub fn take(&mut self, max: usize) -> Vec<Work> {
        let max = max.max(1);
        if let Some(list) = self.lists.front_mut() {
            let batch = if list.len() <= max {
                self.lists.pop_front().unwrap_or_default()
            } else {
                list.split_off(list.len() - max)
            };
            self.listed -= batch.len();
            return batch;
        }
        let n = max.min(self.items.len());
        self.items.drain(..n).collect()
    }

    /// The single items, with every list moved in front of them first:
    /// for random polling, which looks through the queue from its back and
    /// hands work over (rarely: once a poll).
    pub fn items(&mut self) -> &mut VecDeque<Work> {
        while let Some(list) = self.lists.pop_back() {
            for w in list.into_iter().rev() {
                self.items.push_front(w);
            }
        }
        self.listed = 0;
        &mut self.items
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use locus_core::path::Task;
    use locus_core::region::Resume;
    use locus_protocol::rays::ReplyTo;

    fn work(slot: u32) -> Work {
        Work {
            task: Task::Camera {
                x: 0,
                y: 0,
                sample: slot,
            },
            resume: Resume::START,
            reply: ReplyTo { worker: 0, slot },
            from: 0,
            pinned: None,
            handed_by: None,
        }
    }

    fn slots(v: &[Work]) -> Vec<u32> {
        v.iter().map(|w| w.reply.slot).collect()
    }

    /// A queue of camera sample 100 at the back, item 101 at the front,
    /// and a peer's list of each range, in order.
    fn queue(lists: &[std::ops::Range<u32>]) -> WorkQueue {
        let mut q = WorkQueue::default();
        q.push_back(work(100));
        q.push_front(work(101));
        for r in lists {
            q.push_list(r.clone().map(work).collect());
        }
        q
    }

    #[test]
    fn lists_go_first_whole_or_cut_from_their_end() {
        // The empty list is not kept.
        let mut q = queue(&[0..5, 0..0, 10..12]);
        assert_eq!(q.len(), 9);
        // The first list is longer than asked: its last three.
        assert_eq!(slots(&q.take(3)), [2, 3, 4]);
        assert_eq!(q.len(), 6);
        // What is left of it fits: whole, though more was asked for.
        assert_eq!(slots(&q.take(8)), [0, 1]);
        // Asking for none still takes one.
        assert_eq!(slots(&q.take(0)), [11]);
        assert_eq!(slots(&q.take(5)), [10]);
        // Then the single items, the front one first.
        assert_eq!(slots(&q.take(5)), [101, 100]);
        assert!(q.is_empty());
        assert!(q.take(4).is_empty());
    }

    #[test]
    fn polling_sees_every_item_in_the_order_they_would_go() {
        let mut q = queue(&[0..3, 3..5]);
        let order: Vec<u32> = q.items().iter().map(|w| w.reply.slot).collect();
        assert_eq!(order, [0, 1, 2, 3, 4, 101, 100]);
        assert_eq!(q.len(), 7);
        q.items().pop_back();
        assert_eq!(q.len(), 6);
        assert_eq!(slots(&q.take(2)), [0, 1]);
    }
}
