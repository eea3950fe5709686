//! A frame budget: the headset (and, when asked, the window) holds a target frame time by
//! lengthening the ray caster's step, within bounds, past the longest step by foveating
//! ([`crate::render::Foveation`]), and past that by lowering the render scale (each eye drawn
//! into a smaller part of its image, which the compositor or the window's blit enlarges), from
//! the measured GPU times of the frames before. The ray cast is nearly all of a frame and costs
//! about 1 / step, and about scale² per eye; the AO is never touched (its volumes are
//! data-space and shared by every view, so they stay exact). The knobs come back in the
//! opposite order: the scale first, then foveation, then the step.

/// The headset's frame budget by default: 90 Hz.
pub const HEADSET_FRAME_MS: f64 = 1000.0 / 90.0;

/// The longest step the budget takes, as a multiple of the configured one.
pub const MAX_STEP_FACTOR: f64 = 3.0;
/// Step factors are multiples of this (a new step rebuilds the pre-integration table and the
/// empty bricks, so it should not change on every frame).
const QUANTUM: f64 = 0.125;
/// Frame times within this share of the target leave the step alone.
const DEADBAND: f64 = 0.1;
/// What foveation is taken to save on the ray cast, for turning it off again: the frame must
/// fit with the ray cast this many times longer (`bench frame` measured 2.4x with the default
/// rings on the phantom; 2 errs on the side of leaving it on).
const FOVEATION_GAIN: f64 = 2.0;
/// The lowest render scale the budget takes (a quarter of the rays).
pub const MIN_RENDER_SCALE: f64 = 0.5;
/// Render scales are multiples of this.
const SCALE_QUANTUM: f64 = 1.0 / 16.0;

/// The controller: a step factor in [1, MAX_STEP_FACTOR] following the frame times,
/// foveation once the longest step is not enough, and a render scale in [MIN_RENDER_SCALE, 1]
/// once foveation is not enough either.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameBudget {
    pub target_ms: f64,
    factor: f64,
    foveate: bool,
    scale: f64,
}

impl FrameBudget {
    pub fn new(target_ms: f64) -> FrameBudget {
        FrameBudget {
            target_ms,
            factor: 1.0,
            foveate: false,
            scale: 1.0,
        }
    }

    /// Whether the frames to come are foveated: on once a frame is over budget at the longest
    /// step, off again once one at the configured step would fit without it (it is taken to
    /// have saved `FOVEATION_GAIN`), so that it does not flicker on and off.
    pub fn foveate(&self) -> bool {
        self.foveate
    }

    /// The ray step as a multiple of the configured one.
    pub fn step_factor(&self) -> f64 {
        self.factor
    }

    /// Each eye's drawn size as a fraction of its image's, per axis.
    pub fn render_scale(&self) -> f64 {
        self.scale
    }

    /// Takes one frame's GPU times, the ray cast and everything else, and returns the step
    /// factor for the frames to come: the one at which the ray cast fits the room the rest
    /// leaves (at least a tenth of the target), approached halfway (in ratio) per frame, and
    /// only when the frame is more than `DEADBAND` off. Past the longest step and foveation the
    /// render scale moves instead, the same way (the ray cast costs about scale²), and while
    /// it is below 1 nothing else moves.
    pub fn observe(&mut self, ray_ms: f64, other_ms: f64) -> f64 {
        if !(ray_ms > 0.0 && other_ms >= 0.0 && self.target_ms > 0.0) {
            return self.factor;
        }
        let frame = ray_ms + other_ms;
        let off = frame / self.target_ms;
        let room = (self.target_ms - other_ms).max(0.1 * self.target_ms);
        let ratio = ray_ms / room;
        let over = off > 1.0 + DEADBAND;
        if self.scale < 1.0 || (self.foveate && self.factor >= MAX_STEP_FACTOR && over) {
            if !(1.0 - DEADBAND..=1.0 + DEADBAND).contains(&off) {
                let next = self.scale * ratio.powf(-0.25);
                self.scale = quantized(next, self.scale, SCALE_QUANTUM, MIN_RENDER_SCALE, 1.0);
            }
            return self.factor;
        }
        if !self.foveate && self.factor >= MAX_STEP_FACTOR && over {
            self.foveate = true;
        } else if self.foveate
            && self.factor <= 1.0
            && (ray_ms * FOVEATION_GAIN + other_ms) < (1.0 - DEADBAND) * self.target_ms
        {
            self.foveate = false;
        }
        if (1.0 - DEADBAND..=1.0 + DEADBAND).contains(&off) {
            return self.factor;
        }
        let next = self.factor * ratio.sqrt();
        self.factor = quantized(next, self.factor, QUANTUM, 1.0, MAX_STEP_FACTOR);
        self.factor
    }
}

/// `next` as a multiple of `quantum` within [lo, hi], rounded away from `now` so that a wanted
/// move is at least one quantum.
fn quantized(next: f64, now: f64, quantum: f64, lo: f64, hi: f64) -> f64 {
    let q = next.clamp(lo, hi) / quantum;
    let q = if next > now { q.ceil() } else { q.floor() };
    (q * quantum).clamp(lo, hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A simulated GPU: the ray cast costs `ray_at_1 / factor`, half that foveated, times the
    /// render scale squared, the rest `other`; returns the factors chosen frame by frame.
    fn run(b: &mut FrameBudget, ray_at_1: f64, other: f64, frames: usize) -> Vec<f64> {
        (0..frames)
            .map(|_| {
                let (f, s) = (b.step_factor(), b.render_scale());
                let fov = if b.foveate() { 0.5 } else { 1.0 };
                b.observe(ray_at_1 / f * fov * s * s, other)
            })
            .collect()
    }

    #[test]
    fn past_foveation_the_render_scale_drops_and_comes_back_first() {
        let mut b = FrameBudget::new(10.0);
        // 80 ms at the configured step: x3 and foveated give 13.3 ms of ray cast, 14.3 with
        // the rest; the scale settles where the frame fits.
        run(&mut b, 80.0, 1.0, 40);
        let s = b.render_scale();
        let frame = 80.0 / MAX_STEP_FACTOR * 0.5 * s * s + 1.0;
        assert!(b.foveate() && b.step_factor() == MAX_STEP_FACTOR, "{b:?}");
        assert!(
            s < 1.0 && (frame - b.target_ms).abs() <= 0.15 * b.target_ms,
            "{b:?}: {frame} ms"
        );
        // A load no scale meets: the lowest, no lower.
        run(&mut b, 1000.0, 1.0, 30);
        assert_eq!(b.render_scale(), MIN_RENDER_SCALE);
        // The load drops: the scale returns to 1 while the step and foveation hold, then the
        // others follow; every scale is a quantum multiple within the bounds.
        let mut seen = Vec::new();
        for _ in 0..60 {
            run(&mut b, 5.0, 1.0, 1);
            seen.push((b.render_scale(), b.foveate(), b.step_factor()));
        }
        let back = seen
            .iter()
            .position(|x| x.0 == 1.0)
            .expect("the scale came back");
        assert!(
            seen[..back]
                .iter()
                .all(|&(s, f, x)| f && x == MAX_STEP_FACTOR && (s / SCALE_QUANTUM).fract() == 0.0),
            "{seen:?}"
        );
        assert!(seen[back..].iter().all(|x| x.0 == 1.0), "{seen:?}");
        assert_eq!(*seen.last().unwrap(), (1.0, false, 1.0), "{seen:?}");
    }

    #[test]
    fn past_the_longest_step_it_foveates_and_stops_once_the_load_drops() {
        let mut b = FrameBudget::new(10.0);
        // 20 ms at the configured step: the step alone fits, no foveation.
        run(&mut b, 20.0, 1.0, 30);
        assert!(!b.foveate(), "{b:?}");
        // 40 ms: 3x is not enough (14.3 ms); foveated, the step shortens again to fit.
        let f = run(&mut b, 40.0, 1.0, 40);
        assert!(b.foveate(), "{b:?}");
        let (last, frame) = (*f.last().unwrap(), 0.5 * 40.0 / f.last().unwrap() + 1.0);
        assert!(
            last < MAX_STEP_FACTOR && frame <= 1.15 * b.target_ms,
            "x{last}: {frame} ms"
        );
        assert!(f[30..].iter().all(|&x| x == last), "it keeps moving: {f:?}");
        // A load it meets at the configured step without foveation: off again, and it stays off.
        let f = run(&mut b, 6.0, 1.0, 40);
        assert!(!b.foveate() && *f.last().unwrap() == 1.0, "{b:?} {f:?}");
        // In between (foveated it fits at x1, without it not even at x1.2): it stays foveated
        // rather than flickering.
        let mut b = FrameBudget::new(10.0);
        run(&mut b, 60.0, 1.0, 30);
        let f = run(&mut b, 11.0, 1.0, 40);
        assert!(b.foveate(), "{b:?} {f:?}");
    }

    #[test]
    fn the_step_settles_where_the_frame_fits_and_returns_when_the_load_drops() {
        let mut b = FrameBudget::new(1000.0 / 90.0);
        // 20 ms of ray cast at the configured step and 2 ms of AO: about 2.2x fits 11.1 ms.
        let f = run(&mut b, 20.0, 2.0, 30);
        let last = *f.last().unwrap();
        let frame = 20.0 / last + 2.0;
        assert!(
            (frame - b.target_ms).abs() <= 0.15 * b.target_ms,
            "settled at x{last}: {frame} ms"
        );
        assert!(f[20..].iter().all(|&x| x == last), "it keeps moving: {f:?}");
        assert!(f[0] > 1.0 && f[0] < last, "it moves gradually: {f:?}");
        // A load it cannot meet: the longest step, no further.
        let f = run(&mut b, 200.0, 2.0, 20);
        assert_eq!(*f.last().unwrap(), MAX_STEP_FACTOR);
        // The load drops: back to the configured step.
        let f = run(&mut b, 5.0, 1.0, 30);
        assert_eq!(*f.last().unwrap(), 1.0);
        // Every factor is a quantum multiple within the bounds.
        assert!(f
            .iter()
            .all(|&x| (1.0..=MAX_STEP_FACTOR).contains(&x) && (x / QUANTUM).fract() == 0.0));
    }

    #[test]
    fn a_frame_within_the_deadband_or_without_times_changes_nothing() {
        let mut b = FrameBudget::new(10.0);
        assert_eq!(b.observe(9.5, 0.0), 1.0);
        assert_eq!(b.observe(0.0, 3.0), 1.0);
        assert_eq!(b.observe(f64::NAN, 3.0), 1.0);
        assert!(b.observe(30.0, 0.0) > 1.0);
    }
}
