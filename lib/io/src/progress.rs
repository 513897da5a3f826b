//! How far a long job has got: a counter that the job's threads bump and that whoever shows
//! progress (a bar on a terminal, a test) reads from another thread.
//!
//! A job is a sequence of stages ("reading", "writing nodes", ...), each with a total in its own
//! unit (points, nodes, bytes). Reading a piece through a [`Dataset`](crate::dataset::Dataset)
//! counts its points; the job names the stages and counts the rest. Updates are relaxed atomics:
//! a job that nobody watches pays one atomic add per piece or per chunk.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// A shared progress counter; clones share it.
#[derive(Clone, Debug, Default)]
pub struct Progress(Arc<Inner>);

#[derive(Debug, Default)]
struct Inner {
    stage: Mutex<Stage>,
    done: AtomicU64,
}

/// One stage of a job, as [`Progress::snapshot`] reads it.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Stage {
    /// What the job does now ("reading", "sorting", "writing nodes"); empty before the first stage.
    pub name: &'static str,
    /// How much the stage will do in all (0: unknown).
    pub total: u64,
    /// What the unit counts ("points", "nodes").
    pub unit: &'static str,
    /// Which stage this is, counting from 1 (a bar starts over when it changes).
    pub number: u64,
}

impl Progress {
    /// A counter that has not started a stage.
    pub fn new() -> Progress {
        Progress::default()
    }

    /// Starts a stage of `total` units (0 when unknown); what was done is reset to 0.
    pub fn stage(&self, name: &'static str, total: u64, unit: &'static str) {
        let mut s = self.0.stage.lock().unwrap_or_else(|e| e.into_inner());
        let number = s.number + 1;
        *s = Stage { name, total, unit, number };
        self.0.done.store(0, Ordering::Relaxed);
    }

    /// Counts `n` more units of the current stage.
    #[inline]
    pub fn add(&self, n: u64) {
        self.0.done.fetch_add(n, Ordering::Relaxed);
    }

    /// The current stage and how much of it is done.
    pub fn snapshot(&self) -> (Stage, u64) {
        let s = self.0.stage.lock().unwrap_or_else(|e| e.into_inner()).clone();
        (s, self.0.done.load(Ordering::Relaxed))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stages_reset_the_count_and_clones_share_it() {
        let p = Progress::new();
        assert_eq!(p.snapshot().0.number, 0);
        p.stage("reading", 10, "points");
        let q = p.clone();
        std::thread::scope(|s| {
            for _ in 0..4 {
                s.spawn(|| q.add(2));
            }
        });
        let (st, done) = p.snapshot();
        assert_eq!((st.name, st.total, st.number, done), ("reading", 10, 1, 8));
        p.stage("writing", 3, "nodes");
        let (st, done) = q.snapshot();
        assert_eq!((st.name, st.unit, st.number, done), ("writing", "nodes", 2, 0));
    }
}
