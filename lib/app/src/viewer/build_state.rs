//! What the window knows of a build it previews ([`BuildState`]): progress, commits, the end.

use super::content::*;
use mortar_io::store::BuildProgress;
use std::sync::mpsc::{Receiver, TryRecvError};
use std::time::Instant;

/// The preview's build, as the window sees it.
pub(super) struct BuildState {
    pub(super) progress: Receiver<BuildProgress>,
    pub(super) latest: BuildProgress,
    pub(super) start: Instant,
    /// Points and time of an earlier report, for the rate.
    pub(super) rate_from: (u64, Instant),
    pub(super) rate: f64,
    pub(super) done: bool,
    /// Seconds the build took, once done.
    pub(super) seconds: Option<f64>,
    /// The store's last commit was loaded after the build ended.
    pub(super) final_loaded: bool,
    /// The build failed.
    pub(super) failed: bool,
}

impl BuildState {
    pub(super) fn new(progress: Receiver<BuildProgress>) -> BuildState {
        let now = Instant::now();
        BuildState {
            progress,
            latest: BuildProgress::default(),
            start: now,
            rate_from: (0, now),
            rate: 0.0,
            done: false,
            seconds: None,
            final_loaded: false,
            failed: false,
        }
    }

    /// Takes every report that arrived (keeping the newest); whether the commit count changed.
    pub(super) fn poll(&mut self) -> bool {
        let commits = self.latest.commits;
        loop {
            match self.progress.try_recv() {
                Ok(p) => self.latest = p,
                Err(TryRecvError::Empty) => break,
                // The build's end (and whether it succeeded) comes as `Wake::Done`.
                Err(TryRecvError::Disconnected) => break,
            }
        }
        let dt = self.rate_from.1.elapsed().as_secs_f64();
        if dt >= 1.0 {
            self.rate = (self.latest.points - self.rate_from.0) as f64 / dt;
            self.rate_from = (self.latest.points, Instant::now());
        }
        self.latest.commits != commits
    }

    pub(super) fn status(&self) -> String {
        let p = &self.latest;
        match self.seconds {
            Some(s) => format!("built {} points in {s:.1} s", group_digits(p.points)),
            None => format!(
                "building {} of {} ({:.0}%) {:.1} M pts/s",
                group_digits(p.points),
                group_digits(p.total),
                100.0 * p.points as f64 / p.total.max(1) as f64,
                self.rate / 1e6
            ),
        }
    }
}
