//! Ray marching through the relief: conservative steps bounded by the
//! steepest slope until the ray is below the surface, then bisection.
//!
//! A step is one long chain of dependent operations (a division, a floor,
//! a texel read, the bilinear blend, another division), so one ray at a
//! time leaves the processor waiting. A [`March`] is a ray's march as a
//! state that advances one height probe at a time, and [`Marcher::run`]
//! advances many side by side: the rays of neighbouring pixels, the
//! shadow rays of their points, the bounce rays of one point. Every ray
//! still takes exactly the steps it would alone.

use rigd_core::geometry::{add, scale};

use super::surface::Sampler;
use super::Relief;

/// Marches run side by side at most; longer batches run in groups.
const LANES: usize = 64;

/// Bisection steps once a ray has gone below the surface.
const BISECTIONS: u8 = 12;

/// One ray's march over `[ta, tb]`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct March {
    o: [f64; 3],
    d: [f64; 3],
    ta: f64,
    tb: f64,
    /// A shadow (or bounce) ray: any crossing will do, and it gives up once
    /// above the relief's top.
    shadow: bool,
    /// How fast the gap can close per unit of t, and the smallest step;
    /// worked out at the first step, since a ray whose first probe decides
    /// it never needs them (and they cost a `hypot`).
    pace: Option<Pace>,
    t: f64,
    t_prev: f64,
    phase: Phase,
}

/// The step size's bounds for one ray direction.
#[derive(Debug, Clone, Copy)]
struct Pace {
    rate: f64,
    min_step: f64,
}

impl Pace {
    fn of(relief_texel: f64, max_slope: f64, d: [f64; 3]) -> Pace {
        let horizontal = d[0].hypot(d[1]);
        Pace {
            rate: d[2].abs() + max_slope * horizontal,
            min_step: 0.35 * relief_texel / horizontal.max(d[2].abs()).max(1e-6),
        }
    }
}

#[derive(Debug, Clone, Copy)]
enum Phase {
    Stepping,
    /// Narrowing `[lo, hi]`, `left` probes to go.
    Bisecting {
        lo: f64,
        hi: f64,
        left: u8,
    },
    /// Where the ray went below the surface, if it did.
    Done(Option<f64>),
}

impl March {
    /// The march of the ray `o + t d` over `[ta, tb]`.
    pub(crate) fn new(o: [f64; 3], d: [f64; 3], ta: f64, tb: f64, shadow: bool) -> March {
        March {
            o,
            d,
            ta,
            tb,
            shadow,
            pace: None,
            t: ta,
            t_prev: ta,
            phase: Phase::Stepping,
        }
    }

    /// A march that is already over, without a hit: fills unused slots.
    pub(crate) fn finished() -> March {
        March {
            o: [0.0; 3],
            d: [0.0; 3],
            ta: 0.0,
            tb: 0.0,
            shadow: false,
            pace: None,
            t: 0.0,
            t_prev: 0.0,
            phase: Phase::Done(None),
        }
    }

    /// The ray's origin and direction.
    pub(crate) fn ray(&self) -> ([f64; 3], [f64; 3]) {
        (self.o, self.d)
    }

    /// The first t where the ray is below the surface (for a shadow ray,
    /// any such t), once the march is done.
    pub(crate) fn hit(&self) -> Option<f64> {
        match self.phase {
            Phase::Done(t) => t,
            _ => None,
        }
    }

    fn is_done(&self) -> bool {
        matches!(self.phase, Phase::Done(_))
    }

    /// The t whose height the march needs next.
    #[inline(always)]
    fn probe(&self) -> f64 {
        match self.phase {
            Phase::Bisecting { lo, hi, .. } => 0.5 * (lo + hi),
            _ => self.t,
        }
    }

    /// One step, given the gap between the ray and the surface at
    /// [`March::probe`].
    #[inline(always)]
    fn advance(&mut self, gap: f64, relief: &Relief) {
        match self.phase {
            Phase::Stepping => {
                let t = self.t;
                if gap <= 0.0 {
                    self.phase = if t == self.ta {
                        Phase::Done(Some(t))
                    } else {
                        Phase::Bisecting {
                            lo: self.t_prev,
                            hi: t,
                            left: BISECTIONS,
                        }
                    };
                } else if t >= self.tb || (self.shadow && self.o[2] + t * self.d[2] > relief.top) {
                    self.phase = Phase::Done(None);
                } else {
                    let pace = *self.pace.get_or_insert_with(|| {
                        Pace::of(relief.height.texel, relief.max_slope, self.d)
                    });
                    self.t_prev = t;
                    self.t = (t + (gap / pace.rate).max(pace.min_step)).min(self.tb);
                }
            }
            Phase::Bisecting { lo, hi, left } => {
                let mid = 0.5 * (lo + hi);
                let (lo, hi) = if gap > 0.0 { (mid, hi) } else { (lo, mid) };
                self.phase = if left <= 1 {
                    Phase::Done(Some(hi))
                } else {
                    Phase::Bisecting {
                        lo,
                        hi,
                        left: left - 1,
                    }
                };
            }
            Phase::Done(_) => {}
        }
    }
}

/// Marches rays through one relief on a sample of half-sides `half`.
#[derive(Clone, Copy)]
pub(crate) struct Marcher<'a> {
    relief: &'a Relief,
    height: Sampler<'a>,
    half: [f64; 2],
}

impl<'a> Marcher<'a> {
    pub(crate) fn new(relief: &'a Relief, half: [f64; 2]) -> Marcher<'a> {
        Marcher {
            relief,
            height: relief.height.sampler(),
            half,
        }
    }

    /// Height of the ray above the surface at `t`: the relief's height on
    /// the sample, 0 beyond it (as `Scene::height` reads it).
    #[inline(always)]
    fn gap(&self, m: &March, t: f64) -> f64 {
        let p = add(m.o, scale(m.d, t));
        let on_sample = p[0].abs() <= self.half[0] && p[1].abs() <= self.half[1];
        p[2] - if on_sample {
            self.height.sample(p[0], p[1])
        } else {
            0.0
        }
    }

    /// Runs every march to its end, side by side.
    pub(crate) fn run(&self, marches: &mut [March]) {
        self.run_in(marches, |m| Some(m));
    }

    /// Runs to its end, side by side, the march each item holds (`march`
    /// finds it; items without one are left alone), in place.
    pub(crate) fn run_in<T>(&self, items: &mut [T], march: impl Fn(&mut T) -> Option<&mut March>) {
        for group in items.chunks_mut(LANES) {
            // Indices of the marches still going, compacted each round.
            let mut active = [0u8; LANES];
            let mut count = 0;
            for (k, item) in group.iter_mut().enumerate() {
                if march(item).is_some_and(|m| !m.is_done()) {
                    active[count] = k as u8;
                    count += 1;
                }
            }
            while count > 0 {
                let mut still = 0;
                for a in 0..count {
                    let k = active[a] as usize;
                    if let Some(m) = march(&mut group[k]) {
                        let g = self.gap(m, m.probe());
                        m.advance(g, self.relief);
                        if !m.is_done() {
                            active[still] = k as u8;
                            still += 1;
                        }
                    }
                }
                count = still;
            }
        }
    }

    /// Runs one march to its end.
    pub(crate) fn one(&self, mut m: March) -> Option<f64> {
        while !m.is_done() {
            let g = self.gap(&m, m.probe());
            m.advance(g, self.relief);
        }
        m.hit()
    }
}
