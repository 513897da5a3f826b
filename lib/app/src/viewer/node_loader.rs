//! The per-node work of a view, done off the frame thread: a store view's node colours, a COPC
//! or EPT view's decoded nodes.
//!
//! A store node's coordinate words are borrowed from the store's map (no work), but its colours
//! are decoded from its records ([`draw::lod::node_colors`](crate::draw::lod::node_colors)): the
//! part of an upload that costs, and, while a build keeps every core busy, the part that made
//! frames late when the frame thread did it. A COPC or EPT node must be decoded whole (a LAZ
//! chunk or file). A [`NodeLoader`] runs a few threads that take jobs in the order asked and
//! hand back their results; the frame thread uploads whatever is ready and never waits.
//! Dropping the loader cancels the jobs not started. Results of nodes asked for and then no
//! longer selected (the camera moved on) stay ready until the owner lets them go
//! ([`retain`](NodeLoader::retain)) or drops the loader (a new colour mode).

use std::collections::{HashMap, HashSet};
use std::hash::Hash;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::{Arc, Mutex};

/// The threads a loader beside a build takes on this machine: an eighth of the cores, 1 to
/// 2 (more take from the build's throughput).
pub fn threads_beside_a_build() -> usize {
    std::thread::available_parallelism().map_or(1, |n| (n.get() / 8).clamp(1, 2))
}

/// The threads a loader of a view with nothing beside it takes: all cores but the frame
/// thread's, 1 to 8.
pub fn threads_alone() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get().saturating_sub(1).clamp(1, 8))
}

/// One job: what to compute for a key.
type Job<K, V> = (K, Box<dyn FnOnce() -> anyhow::Result<V> + Send>);

/// Results per key `K` (a payload's place, a node), computed by background threads.
pub struct NodeLoader<K, V> {
    jobs: Option<Sender<Job<K, V>>>,
    done: Receiver<(K, anyhow::Result<V>)>,
    /// Asked and not yet taken.
    asked: HashSet<K>,
    ready: HashMap<K, V>,
    cancel: Arc<AtomicBool>,
}

impl<K, V> NodeLoader<K, V>
where
    K: Copy + Eq + Hash + Send + 'static,
    V: Send + 'static,
{
    /// A loader on `threads` threads (at least one), each below the frame thread's priority.
    pub fn new(threads: usize) -> NodeLoader<K, V> {
        let (jobs, rx) = channel::<Job<K, V>>();
        let (tx, done) = channel();
        let rx = Arc::new(Mutex::new(rx));
        let cancel = Arc::new(AtomicBool::new(false));
        for _ in 0..threads.max(1) {
            let (rx, tx, cancel) = (rx.clone(), tx.clone(), cancel.clone());
            std::thread::spawn(move || {
                // Below the frame thread, as the build's threads (mortar_io::threads).
                mortar_io::threads::lower_priority();
                loop {
                    let job = match rx.lock() {
                        Ok(r) => r.recv(),
                        Err(_) => return,
                    };
                    let Ok((key, work)) = job else { return };
                    if cancel.load(Ordering::Relaxed) {
                        return;
                    }
                    if tx.send((key, work())).is_err() {
                        return;
                    }
                }
            });
        }
        NodeLoader { jobs: Some(jobs), done, asked: HashSet::new(), ready: HashMap::new(), cancel }
    }

    /// Takes the results computed so far; the first error a job met.
    pub fn collect(&mut self) -> anyhow::Result<()> {
        while let Ok((key, v)) = self.done.try_recv() {
            if self.asked.remove(&key) {
                self.ready.insert(key, v?);
            }
        }
        Ok(())
    }

    /// The result for `key` if it is ready (taken out of the loader); else asks for it once
    /// (`work` makes the job) and returns `None`.
    pub fn take<W>(&mut self, key: K, work: impl FnOnce() -> W) -> Option<V>
    where
        W: FnOnce() -> anyhow::Result<V> + Send + 'static,
    {
        if let Some(v) = self.ready.remove(&key) {
            return Some(v);
        }
        self.ask(key, work);
        None
    }

    /// Asks for the result for `key` (`work` makes the job) unless it is ready or asked for
    /// already.
    pub fn ask<W>(&mut self, key: K, work: impl FnOnce() -> W)
    where
        W: FnOnce() -> anyhow::Result<V> + Send + 'static,
    {
        if !self.ready.contains_key(&key) && self.asked.insert(key) {
            if let Some(jobs) = &self.jobs {
                // The threads only end when this loader is dropped.
                let _ = jobs.send((key, Box::new(work())));
            }
        }
    }

    /// Forgets ready results of keys `keep` rejects.
    pub fn retain(&mut self, keep: impl Fn(&K) -> bool) {
        self.ready.retain(|k, _| keep(k));
    }
}

impl<K, V> Drop for NodeLoader<K, V> {
    fn drop(&mut self) {
        self.cancel.store(true, Ordering::Relaxed);
        self.jobs = None;
    }
}
