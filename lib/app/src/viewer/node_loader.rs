//! The colours of a store view's nodes, computed off the frame thread.
//!
//! A node's coordinate words are borrowed from the store's map (no work), but its colours are
//! decoded from its records ([`draw::lod::node_colors`]): the part of an upload that costs, and,
//! while a build keeps every core busy, the part that made frames late when the frame thread did
//! it. A [`NodeLoader`] runs a few threads that take nodes in the order asked and hand back their
//! colours; the frame thread uploads whatever is ready and never waits. Dropping the loader
//! cancels the jobs not started. Colours of nodes asked for and then no longer selected (the
//! camera moved on) stay ready until a new commit is shown (a growing store) or the loader is
//! dropped (a new colour mode): at most 4 bytes a sample of the nodes the views selected.

use crate::draw;
use crate::draw::lod::LodColor;
use mortar_core::octree::NodeId;
use mortar_io::store::{PayloadPlace, StoreLod};
use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{channel, Receiver, Sender};
use std::sync::{Arc, Mutex};

/// One node to colour.
struct Job {
    lod: Arc<StoreLod>,
    id: NodeId,
    place: PayloadPlace,
}

/// Colours of the nodes of one colour mode, computed by background threads.
pub struct NodeLoader {
    jobs: Option<Sender<Job>>,
    done: Receiver<(PayloadPlace, anyhow::Result<Vec<u32>>)>,
    /// Asked and not yet taken.
    asked: HashSet<PayloadPlace>,
    ready: HashMap<PayloadPlace, Vec<u32>>,
    cancel: Arc<AtomicBool>,
}

impl NodeLoader {
    /// A loader colouring by `color` over `range` on `threads` threads (at least one).
    pub fn new(color: LodColor, range: Option<[f64; 2]>, threads: usize) -> NodeLoader {
        let (jobs, rx) = channel::<Job>();
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
                    let Ok(job) = job else { return };
                    if cancel.load(Ordering::Relaxed) {
                        return;
                    }
                    let c = draw::lod::node_colors(&job.lod, job.id, color, range)
                        .map_err(anyhow::Error::from);
                    if tx.send((job.place, c)).is_err() {
                        return;
                    }
                }
            });
        }
        NodeLoader { jobs: Some(jobs), done, asked: HashSet::new(), ready: HashMap::new(), cancel }
    }

    /// The threads a loader takes on this machine: an eighth of the cores, 1 to 2 (beside a
    /// build, more take from its throughput).
    pub fn default_threads() -> usize {
        std::thread::available_parallelism().map_or(1, |n| (n.get() / 8).clamp(1, 2))
    }

    /// Takes the colours computed so far; the first error a thread met.
    pub fn collect(&mut self) -> anyhow::Result<()> {
        while let Ok((place, c)) = self.done.try_recv() {
            if self.asked.remove(&place) {
                self.ready.insert(place, c?);
            }
        }
        Ok(())
    }

    /// The colours of node `id` of `lod` (payload `place`) if they are ready (taken out of the
    /// loader); else asks for them once and returns `None`.
    pub fn take(
        &mut self,
        lod: &Arc<StoreLod>,
        id: NodeId,
        place: PayloadPlace,
    ) -> Option<Vec<u32>> {
        if let Some(c) = self.ready.remove(&place) {
            return Some(c);
        }
        self.ask(lod, id, place);
        None
    }

    /// Asks for the colours of node `id` of `lod` (payload `place`) unless they are ready or
    /// asked for already.
    pub fn ask(&mut self, lod: &Arc<StoreLod>, id: NodeId, place: PayloadPlace) {
        if !self.ready.contains_key(&place) && self.asked.insert(place) {
            if let Some(jobs) = &self.jobs {
                // The threads only end when this loader is dropped.
                let _ = jobs.send(Job { lod: lod.clone(), id, place });
            }
        }
    }

    /// Forgets ready colours of payloads `keep` rejects (nodes of commits no longer shown).
    pub fn retain(&mut self, keep: impl Fn(&PayloadPlace) -> bool) {
        self.ready.retain(|p, _| keep(p));
    }
}

impl Drop for NodeLoader {
    fn drop(&mut self) {
        self.cancel.store(true, Ordering::Relaxed);
        self.jobs = None;
    }
}
