//! The bounded per-session frame queue between ingest and the session's pipeline
//! (run by the pipeline pool, which takes work with `try_pop` and never waits here).
//!
//! At most `capacity` frames wait. When a frame finds the queue full the
//! [`OverloadPolicy`] picks a victim, whose payload is freed at once and whose
//! place in line is kept by a small notice, so the worker answers every frame —
//! processed or dropped — in the order it arrived. Notices are bounded too: a
//! client that never reads its results makes `push` fail with
//! [`QueueError::Overloaded`] instead of growing memory.

use std::collections::VecDeque;
use std::sync::{Mutex, MutexGuard};
use std::time::Instant;

use stillmap_proto::pb;

use crate::config::OverloadPolicy;

/// A frame waiting for the pipeline.
#[derive(Debug)]
pub struct QueuedFrame {
    pub frame: pb::Frame,
    pub received_at: Instant,
}

/// What the worker gets next.
#[derive(Debug)]
pub enum Work {
    Frame(QueuedFrame),
    /// A frame the overload policy dropped: answer it, do not process it.
    Dropped {
        sequence: u64,
        capture_time_ns: u64,
    },
}

#[derive(Debug, PartialEq, Eq, thiserror::Error)]
pub enum QueueError {
    #[error("session overloaded: {0} dropped-frame notices are waiting for a client that does not read its results")]
    Overloaded(usize),
    #[error("session is closed")]
    Closed,
}

/// What `push` did.
#[derive(Debug, PartialEq, Eq)]
pub enum PushOutcome {
    Queued,
    /// The frame was queued and this older one was dropped.
    DroppedOldest {
        sequence: u64,
    },
    /// The arriving frame itself was dropped.
    DroppedNewest,
}

pub struct FrameQueue {
    capacity: usize,
    max_notices: usize,
    policy: OverloadPolicy,
    inner: Mutex<Inner>,
}

#[derive(Default)]
struct Inner {
    items: VecDeque<Work>,
    frames: usize,
    closed: bool,
}

impl FrameQueue {
    pub fn new(capacity: usize, max_notices: usize, policy: OverloadPolicy) -> Self {
        Self { capacity: capacity.max(1), max_notices, policy, inner: Mutex::default() }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        // A worker that panicked mid-push leaves consistent data (every update is a
        // single VecDeque operation), so a poisoned lock is still usable.
        crate::lock(&self.inner)
    }

    /// Queues a frame, applying the overload policy when full. Never blocks.
    pub fn push(&self, frame: QueuedFrame) -> Result<PushOutcome, QueueError> {
        let mut inner = self.lock();
        if inner.closed {
            return Err(QueueError::Closed);
        }
        let notices = inner.items.len() - inner.frames;
        let outcome = if inner.frames < self.capacity {
            inner.items.push_back(Work::Frame(frame));
            inner.frames += 1;
            PushOutcome::Queued
        } else if notices >= self.max_notices {
            return Err(QueueError::Overloaded(notices));
        } else {
            match self.policy {
                OverloadPolicy::DropOldest => {
                    // frames == capacity >= 1, so a frame is always found.
                    let mut dropped = None;
                    if let Some(slot) = inner.items.iter_mut().find(|w| matches!(w, Work::Frame(_)))
                        && let Work::Frame(old) = slot
                    {
                        let (sequence, capture_time_ns) = (old.frame.sequence, old.frame.capture_time_ns);
                        *slot = Work::Dropped { sequence, capture_time_ns };
                        dropped = Some(sequence);
                    }
                    inner.frames -= usize::from(dropped.is_some());
                    inner.items.push_back(Work::Frame(frame));
                    inner.frames += 1;
                    match dropped {
                        Some(sequence) => PushOutcome::DroppedOldest { sequence },
                        None => PushOutcome::Queued,
                    }
                }
                OverloadPolicy::DropNewest => {
                    inner.items.push_back(Work::Dropped { sequence: frame.frame.sequence, capture_time_ns: frame.frame.capture_time_ns });
                    PushOutcome::DroppedNewest
                }
            }
        };
        Ok(outcome)
    }

    /// The next work without waiting (the pool's pipeline slices).
    pub fn try_pop(&self) -> Option<Work> {
        let mut inner = self.lock();
        let work = inner.items.pop_front()?;
        if matches!(work, Work::Frame(_)) {
            inner.frames -= 1;
        }
        Some(work)
    }

    /// Whether nothing waits, frames or drop notices.
    pub fn is_empty_of_work(&self) -> bool {
        self.lock().items.is_empty()
    }

    /// Frames waiting (not counting drop notices).
    pub fn len(&self) -> usize {
        self.lock().frames
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Stops accepting frames; the pipeline still drains what is queued.
    pub fn close(&self) {
        self.lock().closed = true;
    }

    /// Whether [`close`](Self::close) was called.
    pub fn is_closed(&self) -> bool {
        self.lock().closed
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(sequence: u64) -> QueuedFrame {
        QueuedFrame { frame: pb::Frame { sequence, capture_time_ns: sequence * 10, ..Default::default() }, received_at: Instant::now() }
    }

    fn drain(q: &FrameQueue) -> Vec<String> {
        q.close();
        std::iter::from_fn(|| q.try_pop())
            .map(|w| match w {
                Work::Frame(f) => format!("F{}", f.frame.sequence),
                Work::Dropped { sequence, .. } => format!("D{sequence}"),
            })
            .collect()
    }

    #[test]
    fn drop_oldest_keeps_arrival_order_and_capacity() {
        let q = FrameQueue::new(2, 10, OverloadPolicy::DropOldest);
        assert_eq!(q.push(frame(1)).unwrap(), PushOutcome::Queued);
        assert_eq!(q.push(frame(2)).unwrap(), PushOutcome::Queued);
        assert_eq!(q.push(frame(3)).unwrap(), PushOutcome::DroppedOldest { sequence: 1 });
        assert_eq!(q.push(frame(4)).unwrap(), PushOutcome::DroppedOldest { sequence: 2 });
        assert_eq!(q.len(), 2);
        assert_eq!(drain(&q), ["D1", "D2", "F3", "F4"]);
    }

    #[test]
    fn drop_newest_answers_the_new_frame_in_its_place() {
        let q = FrameQueue::new(1, 10, OverloadPolicy::DropNewest);
        q.push(frame(1)).unwrap();
        assert_eq!(q.push(frame(2)).unwrap(), PushOutcome::DroppedNewest);
        assert_eq!(drain(&q), ["F1", "D2"]);
    }

    #[test]
    fn notices_are_bounded() {
        let q = FrameQueue::new(1, 2, OverloadPolicy::DropOldest);
        for s in 1..=3 {
            q.push(frame(s)).unwrap();
        }
        assert_eq!(q.push(frame(4)).unwrap_err(), QueueError::Overloaded(2));
        assert_eq!(drain(&q), ["D1", "D2", "F3"]);
        assert_eq!(q.push(frame(5)).unwrap_err(), QueueError::Closed);
    }
}
