//! Progressive recomputation of a precomputed volume, a bounded slab of z-slices per frame, so
//! that a frame never stalls on it. Generic on purpose: the frame loop uses it for V_PAO after a
//! transfer-function switch, and any other per-voxel precompute (an SH visibility volume) can
//! reuse the same two pieces: [`SlabScheduler`] (which slices this frame records) and
//! [`HostTask`] (host work on a worker thread, polled without blocking).

use std::ops::Range;
use std::thread::JoinHandle;

/// How many slices a slab holds so that it costs at most `budget` (in the caller's unit, e.g.
/// opacity samples) at `cost_per_slice` each: at least one slice, at most `total`, and a multiple
/// of 4 once it is 4 or more (the compute kernels run 4 slices deep per workgroup).
pub fn slab_slices(total: usize, cost_per_slice: f64, budget: f64) -> usize {
    let n = if cost_per_slice > 0.0 && budget.is_finite() {
        (budget / cost_per_slice)
            .floor()
            .max(1.0)
            .min(total.max(1) as f64) as usize
    } else {
        total.max(1)
    };
    if n >= 4 && n < total {
        n / 4 * 4
    } else {
        n
    }
}

/// Hands out consecutive z-ranges `[z0, z1)` of `slab` slices until `total` slices are covered.
#[derive(Clone, Debug, PartialEq)]
pub struct SlabScheduler {
    total: usize,
    slab: usize,
    next: usize,
    /// The cost of one slice when the slabs follow a budget ([`SlabScheduler::set_budget`]).
    cost_per_slice: Option<f64>,
    /// The fewest slices a slab holds whatever the budget ([`SlabScheduler::with_least_slab`]).
    least: usize,
}

impl SlabScheduler {
    pub fn new(total: usize, slab: usize) -> SlabScheduler {
        SlabScheduler {
            total,
            slab: slab.max(1),
            next: 0,
            cost_per_slice: None,
            least: 1,
        }
    }

    /// The same with slabs of at least `least` slices, however small the budget: a pass that
    /// must end within `total / least` slabs.
    pub fn with_least_slab(self, least: usize) -> SlabScheduler {
        let least = least.max(1);
        SlabScheduler {
            least,
            slab: self.slab.max(least),
            ..self
        }
    }

    /// A scheduler whose slabs cost at most `budget` each ([`slab_slices`]).
    pub fn with_budget(total: usize, cost_per_slice: f64, budget: f64) -> SlabScheduler {
        SlabScheduler {
            cost_per_slice: Some(cost_per_slice),
            ..Self::new(total, slab_slices(total, cost_per_slice, budget))
        }
    }

    /// Sizes the slabs still to come for a new `budget` (a scheduler made by
    /// [`SlabScheduler::with_budget`]; one of fixed slabs keeps them). The slices already handed
    /// out stay as they were: a slab's result does not depend on where the slabs split.
    pub fn set_budget(&mut self, budget: f64) {
        if let Some(cost) = self.cost_per_slice {
            self.slab = slab_slices(self.total, cost, budget).max(self.least);
        }
    }

    /// The next slab to record, or None once every slice was handed out.
    pub fn next_slab(&mut self) -> Option<Range<usize>> {
        (self.next < self.total).then(|| {
            let z0 = self.next;
            self.next = (z0 + self.slab).min(self.total);
            z0..self.next
        })
    }

    /// Slices handed out so far.
    pub fn done(&self) -> usize {
        self.next
    }

    pub fn total(&self) -> usize {
        self.total
    }

    pub fn slab(&self) -> usize {
        self.slab
    }

    /// Slabs (frames) a full pass takes.
    pub fn slab_count(&self) -> usize {
        self.total.div_ceil(self.slab)
    }

    /// Fraction of the slices handed out, 0..=1 (1 for an empty volume).
    pub fn fraction(&self) -> f32 {
        if self.total == 0 {
            1.0
        } else {
            self.next as f32 / self.total as f32
        }
    }

    pub fn is_finished(&self) -> bool {
        self.next >= self.total
    }
}

/// Host work running on its own thread; [`HostTask::poll`] takes its result once it is there
/// and never blocks. Dropping an unfinished task detaches the thread: it runs to its end and its
/// result is discarded (host memory only, so nothing else has to wait for it).
pub struct HostTask<T> {
    handle: Option<JoinHandle<T>>,
}

impl<T: Send + 'static> HostTask<T> {
    /// Starts `work` on a new thread; fails only when the OS refuses a thread.
    pub fn spawn(
        name: &str,
        work: impl FnOnce() -> T + Send + 'static,
    ) -> std::io::Result<HostTask<T>> {
        let handle = std::thread::Builder::new().name(name.into()).spawn(work)?;
        Ok(HostTask {
            handle: Some(handle),
        })
    }

    /// The result once the work finished (Err(message) if it panicked), else None. After it
    /// returned Some, the task is spent and returns None.
    pub fn poll(&mut self) -> Option<Result<T, String>> {
        if !self.handle.as_ref()?.is_finished() {
            return None;
        }
        self.wait()
    }

    /// Waits for the result (for callers that cannot go on without it, e.g. tests).
    pub fn wait(&mut self) -> Option<Result<T, String>> {
        let h = self.handle.take()?;
        Some(h.join().map_err(|e| {
            e.downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| e.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "worker thread panicked".into())
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_new_budget_resizes_the_slabs_still_to_come() {
        let mut s = SlabScheduler::with_budget(32, 10.0, 45.0);
        assert_eq!(s.next_slab(), Some(0..4));
        s.set_budget(85.0);
        assert_eq!(s.next_slab(), Some(4..12));
        s.set_budget(1.0);
        assert_eq!(s.next_slab(), Some(12..13));
        // fixed slabs stay fixed
        let mut f = SlabScheduler::new(1, 1);
        f.set_budget(1e9);
        assert_eq!(f.slab(), 1);
    }

    #[test]
    fn a_least_slab_holds_whatever_the_budget() {
        // 72 slices within 8 slabs: 9 at least, though the budget asks for 1 (and rounding to
        // multiples of 4 would give 8, nine slabs).
        let mut s = SlabScheduler::with_budget(72, 10.0, 10.0).with_least_slab(72usize.div_ceil(8));
        assert_eq!(s.slab(), 9);
        s.set_budget(0.0);
        assert_eq!(s.slab_count(), 8);
        s.set_budget(200.0);
        assert_eq!(s.slab(), 20, "a larger budget still counts");
    }

    #[test]
    fn slabs_cover_the_volume_once_within_budget() {
        // 32 slices at 10 each, 45 per frame: 4 slices (a multiple of 4), 8 slabs.
        let mut s = SlabScheduler::with_budget(32, 10.0, 45.0);
        assert_eq!((s.slab(), s.slab_count()), (4, 8));
        let mut seen = Vec::new();
        let mut fractions = Vec::new();
        while let Some(r) = s.next_slab() {
            seen.extend(r);
            fractions.push(s.fraction());
        }
        assert_eq!(seen, (0..32).collect::<Vec<_>>());
        assert_eq!(fractions.len(), 8);
        assert!(fractions.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(*fractions.last().unwrap(), 1.0);
        assert!(s.is_finished() && s.next_slab().is_none());

        // Uneven: 10 slices, 3 per slab: 3+3+3+1.
        let mut s = SlabScheduler::new(10, 3);
        let slabs: Vec<_> = std::iter::from_fn(|| s.next_slab()).collect();
        assert_eq!(slabs, [0..3, 3..6, 6..9, 9..10]);
    }

    #[test]
    fn slab_size_is_clamped() {
        assert_eq!(slab_slices(100, 1e9, 1.0), 1, "at least one slice");
        assert_eq!(slab_slices(10, 1.0, 1e9), 10, "at most the whole volume");
        assert_eq!(
            slab_slices(10, 1.0, 7.0),
            4,
            "rounded down to a multiple of 4"
        );
        assert_eq!(slab_slices(10, 1.0, 3.0), 3);
        assert_eq!(slab_slices(10, 0.0, 3.0), 10, "free slices: all at once");
        assert_eq!(SlabScheduler::new(0, 4).fraction(), 1.0);
    }

    #[test]
    fn host_task_hands_over_its_result_once() {
        let mut t = HostTask::spawn("test", || 6 * 7).unwrap();
        let r = loop {
            if let Some(r) = t.poll() {
                break r;
            }
            std::thread::yield_now();
        };
        assert_eq!(r, Ok(42));
        assert!(t.poll().is_none());
        let mut p: HostTask<i32> = HostTask::spawn("test-panic", || panic!("boom")).unwrap();
        assert_eq!(p.wait(), Some(Err("boom".into())));
    }
}
