//! A fixed pool of worker threads that runs the work of many sessions, each
//! session's in order.
//!
//! A session does not own a thread: its work sits in a [`Lane`] (its frame queue,
//! or its map jobs), and a lane with work is put on the pool's ready list once. A
//! pool thread takes a lane, runs a bounded slice of its work (so one busy robot
//! cannot starve the others), and puts it back at the end of the list if work is
//! left. A lane is never on the list twice and never run by two threads at once,
//! so a session's frames stay in order. The pool has as many threads as it is
//! configured with, however many sessions there are.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};

use crate::lock;

/// Work of one session that must run in order.
pub trait Lane: Send + Sync + 'static {
    /// Runs a bounded slice of the waiting work.
    fn run_slice(&self);
    /// Whether work is waiting.
    fn has_work(&self) -> bool;
    /// Set while the lane is on the ready list or running; owned by the pool.
    fn scheduled(&self) -> &AtomicBool;
    /// A slice panicked (a bug: `panic` is its message). The pool thread carries on
    /// with other lanes; the lane decides what becomes of its own work.
    fn failed(&self, panic: &str);
}

/// What a caught panic says (its `&str` or `String` payload).
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| (*s).to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic without a message".to_string())
}

/// Runs `f`, catching a panic as its message: a bug in one robot's work must not
/// take a shared thread (a pool's, the fleet's) with it.
pub fn caught<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).map_err(|p| panic_message(&*p))
}

#[derive(Default)]
struct State {
    ready: VecDeque<Arc<dyn Lane>>,
    closed: bool,
}

struct Shared {
    state: Mutex<State>,
    wake: Condvar,
}

pub struct Pool {
    shared: Arc<Shared>,
    threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
    size: usize,
}

impl Pool {
    /// Starts `size` threads named `<name>-<n>`.
    pub fn new(name: &str, size: usize) -> std::io::Result<Arc<Self>> {
        let shared = Arc::new(Shared { state: Mutex::default(), wake: Condvar::new() });
        let mut threads = Vec::new();
        for n in 0..size.max(1) {
            let shared = shared.clone();
            threads.push(std::thread::Builder::new().name(format!("{name}-{n}")).spawn(move || worker(&shared))?);
        }
        Ok(Arc::new(Self { shared, threads: Mutex::new(threads), size: size.max(1) }))
    }

    pub fn size(&self) -> usize {
        self.size
    }

    /// Puts `lane` on the ready list unless it is there or running already. Call it
    /// after adding work to the lane.
    pub fn schedule(&self, lane: Arc<dyn Lane>) {
        if lane.scheduled().swap(true, Ordering::SeqCst) {
            return;
        }
        lock(&self.shared.state).ready.push_back(lane);
        self.shared.wake.notify_one();
    }

    /// Runs what is on the ready list (and what that work schedules), then stops
    /// the threads and waits for them.
    pub fn close(&self) {
        lock(&self.shared.state).closed = true;
        self.shared.wake.notify_all();
        let threads = std::mem::take(&mut *lock(&self.threads));
        for t in threads {
            if t.join().is_err() {
                tracing::error!("a pool thread panicked");
            }
        }
    }
}

fn worker(shared: &Shared) {
    loop {
        let lane = {
            let mut state = lock(&shared.state);
            loop {
                if let Some(lane) = state.ready.pop_front() {
                    break lane;
                }
                if state.closed {
                    return;
                }
                state = crate::wait(&shared.wake, state, None);
            }
        };
        if let Err(panic) = caught(|| lane.run_slice()) {
            tracing::error!("a pool thread caught a panic (a bug): {panic}");
            lane.failed(&panic);
        }
        // Work added while the slice ran found the flag set and did not schedule:
        // clear it, then look again.
        lane.scheduled().store(false, Ordering::SeqCst);
        if lane.has_work() && !lane.scheduled().swap(true, Ordering::SeqCst) {
            lock(&shared.state).ready.push_back(lane);
            shared.wake.notify_one();
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicUsize;
    use std::time::{Duration, Instant};

    use super::*;

    /// A lane of numbered items; records the order it ran them and how many of its
    /// slices ran at once.
    #[derive(Default)]
    struct Numbers {
        waiting: Mutex<VecDeque<u32>>,
        ran: Mutex<Vec<u32>>,
        running: AtomicUsize,
        overlap: AtomicBool,
        scheduled: AtomicBool,
    }

    impl Lane for Numbers {
        fn run_slice(&self) {
            if self.running.fetch_add(1, Ordering::SeqCst) > 0 {
                self.overlap.store(true, Ordering::SeqCst);
            }
            for _ in 0..3 {
                let Some(n) = self.waiting.lock().expect("lock").pop_front() else { break };
                std::thread::sleep(Duration::from_micros(50));
                self.ran.lock().expect("lock").push(n);
            }
            self.running.fetch_sub(1, Ordering::SeqCst);
        }
        fn has_work(&self) -> bool {
            !self.waiting.lock().expect("lock").is_empty()
        }
        fn scheduled(&self) -> &AtomicBool {
            &self.scheduled
        }
        fn failed(&self, _: &str) {
            unreachable!("a Numbers lane never panics")
        }
    }

    /// A lane whose first item panics; it records the panic and runs the rest.
    #[derive(Default)]
    struct PanicsOnce {
        waiting: Mutex<VecDeque<u32>>,
        ran: Mutex<Vec<u32>>,
        failures: Mutex<Vec<String>>,
        scheduled: AtomicBool,
    }

    impl Lane for PanicsOnce {
        fn run_slice(&self) {
            let Some(n) = lock(&self.waiting).pop_front() else { return };
            if n == 0 {
                panic!("item {n} is a bug");
            }
            lock(&self.ran).push(n);
        }
        fn has_work(&self) -> bool {
            !lock(&self.waiting).is_empty()
        }
        fn scheduled(&self) -> &AtomicBool {
            &self.scheduled
        }
        fn failed(&self, panic: &str) {
            lock(&self.failures).push(panic.to_string());
        }
    }

    /// A slice that panics is the lane's to handle (`failed`, with the message); the
    /// pool's only thread survives it and runs that lane's remaining work and
    /// another lane's.
    #[test]
    fn a_panicking_slice_is_reported_to_its_lane_and_the_thread_carries_on() {
        let pool = Pool::new("test-pool", 1).expect("pool");
        let panicking: Arc<PanicsOnce> = Arc::default();
        lock(&panicking.waiting).extend(0..3);
        let other: Arc<Numbers> = Arc::default();
        lock(&other.waiting).extend(0..5);
        pool.schedule(panicking.clone());
        pool.schedule(other.clone());
        pool.close();
        assert_eq!(*lock(&panicking.failures), ["item 0 is a bug"]);
        assert_eq!(*lock(&panicking.ran), [1, 2]);
        assert_eq!(*lock(&other.ran), [0, 1, 2, 3, 4]);
        assert_eq!(caught(|| std::panic::panic_any(7_u8)), Err::<(), _>("a panic without a message".to_string()));
        assert_eq!(caught(|| panic!("{}", String::from("owned"))), Err::<(), _>("owned".to_string()));
    }

    /// Many lanes fed from several threads on a pool of 2: every item runs once,
    /// each lane's in order, and no lane runs on two threads at once.
    #[test]
    #[allow(clippy::disallowed_methods)] // the test's feeder threads need no names
    fn lanes_run_in_order_and_never_twice_at_once() {
        let pool = Pool::new("test-pool", 2).expect("pool");
        let lanes: Vec<Arc<Numbers>> = (0..6).map(|_| Arc::default()).collect();
        std::thread::scope(|s| {
            for lane in &lanes {
                let pool = &pool;
                s.spawn(move || {
                    for n in 0..200 {
                        lane.waiting.lock().expect("lock").push_back(n);
                        pool.schedule(lane.clone());
                        if n % 50 == 0 {
                            std::thread::sleep(Duration::from_millis(1));
                        }
                    }
                });
            }
        });
        let deadline = Instant::now() + Duration::from_secs(20);
        while lanes.iter().any(|l| l.ran.lock().expect("lock").len() < 200) {
            assert!(Instant::now() < deadline, "work left undone");
            std::thread::sleep(Duration::from_millis(2));
        }
        pool.close();
        for lane in &lanes {
            assert_eq!(*lane.ran.lock().expect("lock"), (0..200).collect::<Vec<_>>());
            assert!(!lane.overlap.load(Ordering::SeqCst), "a lane ran on two threads at once");
        }
    }

    /// Closing runs what is waiting first.
    #[test]
    fn close_drains_the_ready_list() {
        let pool = Pool::new("test-pool", 1).expect("pool");
        let lane: Arc<Numbers> = Arc::default();
        lane.waiting.lock().expect("lock").extend(0..10);
        pool.schedule(lane.clone());
        pool.close();
        assert_eq!(lane.ran.lock().expect("lock").len(), 10);
    }
}
