//! Divergence detection beyond a non-finite loss (docs/runs.md). A run has diverged when its
//! running loss (exponential average, weight 0.1 per step) either
//! - **never learned**: `GRACE` steps after the last warm-up ends it has never been below 95% of
//!   its value at step `SETTLE` (a healthy run has fallen far below it by then: `tiny`, 300 steps:
//!   0.18 -> 0.04), or
//! - **blew up**: stayed above `BLOWUP` × its best value for `PATIENCE` consecutive steps.
//!
//! Both are far outside what a healthy run shows (batch noise moves the running loss by tens
//! of percent, not by 3×), so a false alarm would need a run that is not learning anyway.

/// Steps before the running loss is taken as the reference.
pub const SETTLE: u64 = 10;
/// Steps after warm-up within which the loss must have fallen below 95% of the reference.
pub const GRACE: u64 = 200;
/// Running loss over its best value that counts as a blow-up.
pub const BLOWUP: f64 = 3.0;
/// Consecutive blown-up steps before the run is stopped.
pub const PATIENCE: u64 = 100;

/// Feeds on every step's loss; [`Guard::step`] says why the run diverged, if it has.
pub struct Guard {
    /// Step from which "never learned" is checked (`u64::MAX`: not checked).
    check_from: u64,
    /// Step at which the running loss becomes the reference (`SETTLE` steps into the guard).
    settle_at: u64,
    ema: Option<f64>,
    reference: Option<f64>,
    best: f64,
    above: u64,
}

impl Guard {
    /// `warmup`: the longest learning-rate warm-up of the run's parameter groups; `start`: the
    /// step the run starts from (0, or a resumed checkpoint's). A resumed run starts a fresh
    /// guard (its history is not in the checkpoint). "Never learned" is a test of a run's start:
    /// it is checked only if the run resumes before a fresh run would have been checked, from a
    /// reference taken `SETTLE` steps after the resume. Later, a converged run's loss no longer
    /// falls 5 % in 200 steps, and checking it would stop a healthy run (it did: a run resumed at
    /// step 3,682 of 10,000 was stopped as "not learning" 200 steps later).
    pub fn new(warmup: u64, start: u64) -> Guard {
        let fresh_check = warmup.max(SETTLE) + GRACE;
        Guard {
            check_from: if start < fresh_check {
                fresh_check
            } else {
                u64::MAX
            },
            settle_at: start + SETTLE,
            ema: None,
            reference: None,
            best: f64::INFINITY,
            above: 0,
        }
    }

    /// After step `k` (steps done) with loss `loss`: `Some(reason)` when the run has diverged.
    pub fn step(&mut self, k: u64, loss: f64) -> Option<String> {
        let e = self.ema.map_or(loss, |e| 0.9 * e + 0.1 * loss);
        self.ema = Some(e);
        if self.reference.is_none() && k >= self.settle_at {
            self.reference = Some(e);
            self.check_from = self.check_from.max(k.saturating_add(GRACE));
        }
        self.best = self.best.min(e);
        if let Some(r) = self.reference {
            if k >= self.check_from && self.best >= 0.95 * r {
                return Some(format!(
                    "the running loss has not fallen in {} steps ({r:.4} then, at best {:.4} since): the run is not learning (a learning rate far too high?)",
                    k - self.settle_at,
                    self.best
                ));
            }
        }
        self.above = if e > BLOWUP * self.best {
            self.above + 1
        } else {
            0
        };
        (self.above >= PATIENCE).then(|| {
            format!(
                "the running loss has been above {BLOWUP}× its best ({:.4}) for {PATIENCE} steps (now {e:.4}): the run blew up (a learning rate too high?)",
                self.best
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_falling_loss_is_healthy_and_a_flat_or_exploding_one_is_not() {
        // Healthy: falls from 0.2 to 0.02 with ±30% batch noise.
        let mut g = Guard::new(0, 0);
        for k in 1..=2000u64 {
            let noise = if k % 3 == 0 { 1.3 } else { 0.85 };
            let loss = (0.2 * (-(k as f64) / 150.0).exp()).max(0.02) * noise;
            assert_eq!(g.step(k, loss), None, "step {k}");
        }
        // Never learns: flat at the initial loss.
        let mut g = Guard::new(0, 0);
        let hit = (1..=1000u64).find_map(|k| g.step(k, 0.4).map(|r| (k, r)));
        let (k, r) = hit.expect("a flat loss is caught");
        assert_eq!(k, SETTLE + GRACE);
        assert!(r.contains("not learning"), "{r}");
        // With a warm-up of 500 steps, the same is caught only after it.
        let mut g = Guard::new(500, 0);
        let k = (1..=2000u64).find(|&k| g.step(k, 0.4).is_some()).unwrap();
        assert_eq!(k, 500 + GRACE);
        // Learns, then blows up to 10× its best.
        let mut g = Guard::new(0, 0);
        let mut caught = None;
        for k in 1..=2000u64 {
            let loss = if k < 400 { 0.2 / k as f64 } else { 0.3 };
            if let Some(r) = g.step(k, loss) {
                caught = Some((k, r));
                break;
            }
        }
        let (k, r) = caught.expect("a blow-up is caught");
        assert!((400..400 + PATIENCE + 30).contains(&k), "caught at {k}");
        assert!(r.contains("blew up"), "{r}");
    }

    #[test]
    fn a_resumed_run_is_checked_for_learning_only_near_its_start() {
        // Converged, resumed late: a flat loss (with batch noise) is healthy, however long.
        let mut g = Guard::new(0, 3682);
        for k in 3683..=10_000u64 {
            let loss = if k % 3 == 0 { 0.033 } else { 0.027 };
            assert_eq!(g.step(k, loss), None, "step {k}");
        }
        // Resumed before a fresh run's check: a flat loss is still caught, GRACE steps after
        // the reference taken SETTLE steps into the resumed run.
        let mut g = Guard::new(0, 50);
        let k = (51..=2000u64).find(|&k| g.step(k, 0.4).is_some()).unwrap();
        assert_eq!(k, 50 + SETTLE + GRACE);
        // A blow-up after a late resume is caught.
        let mut g = Guard::new(0, 5000);
        let k = (5001..=8000u64)
            .find(|&k| g.step(k, if k < 5300 { 0.03 } else { 0.3 }).is_some())
            .unwrap();
        assert!((5300..5300 + PATIENCE + 30).contains(&k), "caught at {k}");
    }
}
