//! How many slots the Fill pass draws per frame ([`FillBudget`]): a fixed number, or the adaptive
//! budget of paper 000 §3.4.1 ([`AdaptiveBudget`], computed from [`ProbeTimings`] that a CPU
//! renderer measures with a wall clock and a GPU renderer with timestamp queries).

/// What the adaptive budget is computed from, measured in the frame being drawn: on the CPU with
/// a wall clock, on a GPU from timestamp queries (the hook for a GPU renderer: fill these from
/// the timestamps and call [`AdaptiveBudget::extra_points`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProbeTimings {
    /// Slots filled in the first, fixed step.
    pub probe_points: u64,
    /// Time the first step took, ms.
    pub probe_ms: f64,
    /// Time since the frame began, the first step included, ms.
    pub elapsed_ms: f64,
    /// Time expected after the fill (Prepare and what follows), ms: the last frame's.
    pub after_fill_ms: f64,
}

/// The adaptive fill budget of paper 000 §3.4.1: "we measure the time since the beginning of the
/// frame, and the time it took to render the first 1 million points. From this, we compute the
/// number of rendered points per millisecond, which we then multiply by the milliseconds we have
/// left to finish the frame."
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdaptiveBudget {
    /// The frame time to stay within, ms (16.6 for 60 frames per second).
    pub target_ms: f64,
    /// Slots filled first to measure the rate (the paper: 1 M points on a GPU).
    pub probe_points: u64,
    /// Share of `target_ms` planned for, for the estimate's error and work outside the passes
    /// (the paper suggests planning with about 10 of 16.6 ms on a GPU).
    pub usable: f64,
}

impl Default for AdaptiveBudget {
    fn default() -> Self {
        AdaptiveBudget { target_ms: 16.6, probe_points: 100_000, usable: 0.9 }
    }
}

impl AdaptiveBudget {
    /// Points to fill after the first step: the measured rate times the time left, 0 when no time
    /// is left, `u64::MAX` (fill everything) when the first step was too fast to measure.
    pub fn extra_points(&self, t: &ProbeTimings) -> u64 {
        let left = self.target_ms * self.usable - t.elapsed_ms - t.after_fill_ms;
        if t.probe_points == 0 || left.is_nan() || left <= 0.0 {
            return 0;
        }
        if t.probe_ms.is_nan() || t.probe_ms <= 0.0 {
            return u64::MAX;
        }
        let extra = t.probe_points as f64 / t.probe_ms * left;
        if extra >= u64::MAX as f64 {
            u64::MAX
        } else {
            extra as u64
        }
    }
}

/// How many slots the Fill pass draws per frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FillBudget {
    /// A fixed number of slots (at most the whole buffer).
    Fixed(u64),
    /// The adaptive budget of §3.4.1.
    Adaptive(AdaptiveBudget),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn adaptive_budget_fills_the_time_left() {
        let a = AdaptiveBudget { target_ms: 16.0, probe_points: 1_000_000, usable: 1.0 };
        // 1 M points in 2 ms, 4 ms into the frame, 2 ms expected after: 10 ms left at 0.5 M/ms.
        let t = ProbeTimings {
            probe_points: 1_000_000,
            probe_ms: 2.0,
            elapsed_ms: 4.0,
            after_fill_ms: 2.0,
        };
        assert_eq!(a.extra_points(&t), 5_000_000);
        // Twice as fast (e.g. half the points outside the frustum): twice the budget.
        assert_eq!(
            a.extra_points(&ProbeTimings { probe_ms: 1.0, elapsed_ms: 3.0, ..t }),
            11_000_000
        );
        // Planning with 10 of 16 ms (the paper's advice) leaves 4 ms.
        let careful = AdaptiveBudget { usable: 10.0 / 16.0, ..a };
        assert_eq!(careful.extra_points(&t), 2_000_000);
        // Over time already: nothing more; too fast to measure: everything; no probe: nothing.
        assert_eq!(a.extra_points(&ProbeTimings { elapsed_ms: 15.0, ..t }), 0);
        assert_eq!(a.extra_points(&ProbeTimings { elapsed_ms: f64::NAN, ..t }), 0);
        assert_eq!(a.extra_points(&ProbeTimings { probe_ms: 0.0, ..t }), u64::MAX);
        assert_eq!(a.extra_points(&ProbeTimings { probe_points: 0, ..t }), 0);
        // A closed loop against a synthetic machine (fixed cost per point, reprojection and
        // prepare costs): frames stay within the target and the budget settles where the fill
        // takes the time left.
        let (per_point_ms, reproject_ms, prepare_ms) = (2e-6, 1.0, 1.5);
        let a = AdaptiveBudget { target_ms: 16.6, probe_points: 100_000, usable: 0.9 };
        let mut after = 0.0;
        for frame in 0..5 {
            let probe_ms = a.probe_points as f64 * per_point_ms;
            let t = ProbeTimings {
                probe_points: a.probe_points,
                probe_ms,
                elapsed_ms: reproject_ms + probe_ms,
                after_fill_ms: after,
            };
            let extra = a.extra_points(&t);
            let total = reproject_ms + (a.probe_points + extra) as f64 * per_point_ms + prepare_ms;
            after = prepare_ms;
            if frame > 0 {
                assert!(
                    total <= 16.6 * 0.9 + 1e-6 && total > 16.6 * 0.9 - 1e-3,
                    "frame {frame}: {total} ms"
                );
                let fill = ((16.6 * 0.9 - reproject_ms - prepare_ms) / per_point_ms) as u64;
                assert!(
                    (a.probe_points + extra).abs_diff(fill) <= 1,
                    "frame {frame}: {} points, {fill} fit",
                    a.probe_points + extra
                );
            }
        }
    }
}
