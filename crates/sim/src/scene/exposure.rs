//! The pixel loop of a frame. Each pixel is one camera ray, shaded
//! ([`super::shade`]) and read out by the sensor ([`super::sensor`]) in the
//! same pass, so no frame-sized linear buffer is written and read back.
//! Pixels whose rays cannot meet the plate or the relief are not traced
//! ([`super::coverage`]). The render threads take bands of rows; a band is
//! rendered tile by tile, so the texels a tile reads stay in cache whatever
//! way the view turns the sample, and each tile row as a [`Run`] of pixels
//! shaded stage by stage.

use rayon::prelude::*;
use rigd_core::geometry::scale;

use super::coverage::Coverage;
use super::effects::{Effect, EffectPlan};
use super::rays::{RayFan, Row};
use super::sensor::max_code;
use super::shade::{direct, Frame, Incidence, Primary, Shadow, Surface};
use super::shot::{camera, Shot, WHITE_LEVEL};
use super::Scene;

/// Rows a render thread takes at a time.
pub(crate) const BAND_ROWS: usize = 8;

/// Columns of a tile: a band is rendered tile by tile, each tile row by
/// row, so neighbouring rays' texel reads share cache lines and pages.
const TILE_COLUMNS: usize = 64;

/// One frame's set-up, shared by every pixel: the camera, the shading
/// context, the exposure and which pixels can be lit.
pub(crate) struct Exposure<'a> {
    width: usize,
    height: usize,
    rays: RayFan,
    frame: Frame<'a>,
    /// Digital numbers per unit of reflectance factor.
    gain: f64,
    /// The vignetting's strength, when live.
    vignette: Option<f64>,
    /// Pixels outside the coverage are 0 without tracing them.
    coverage: Coverage,
    /// Points that land on the floor beyond the plate are 0 without
    /// shading them.
    skip_off_holder: bool,
    /// A colour camera's filter array: each pixel records its channel.
    cfa: Option<rigd_core::Cfa>,
}

impl<'a> Exposure<'a> {
    pub(crate) fn new(scene: &'a Scene, shot: &Shot) -> Exposure<'a> {
        let (width, height) = (shot.width.max(1) as usize, shot.height.max(1) as usize);
        // The lamp's level scales what it lights; a laser frame has no lamp.
        let lamp = if shot.laser.is_none() {
            shot.lamp_level.max(0.0)
        } else {
            1.0
        };
        let gain = WHITE_LEVEL
            * max_code(shot)
            * shot.relative_exposure.max(0.0)
            * shot.gain.max(0.0)
            * lamp;
        let camera = camera(scene, shot);
        let rays = RayFan::new(camera);
        let frame = Frame::new(scene, shot);
        let vignette = frame
            .plan
            .has(Effect::Vignetting)
            .then_some(scene.sensor.vignetting);
        // A black point times a finite gain and vignetting stays 0.
        let skip_off_holder = frame.black_off_holder() && gain.is_finite();
        let coverage = if skip_off_holder {
            Coverage::new(
                rays.camera(),
                [width, height],
                scene.holder.half,
                scene.sample_half,
                frame.relief_top(),
            )
        } else {
            Coverage::full(width, height)
        };
        Exposure {
            width,
            height,
            rays,
            frame,
            gain,
            vignette,
            coverage,
            skip_off_holder,
            cfa: shot.cfa,
        }
    }

    /// Pixels in the frame.
    pub(crate) fn pixels(&self) -> usize {
        self.width * self.height
    }

    /// The effects the frame renders.
    pub(crate) fn plan(&self) -> &EffectPlan {
        &self.frame.plan
    }

    /// Whether `p` lies beyond the holder plate, where the albedo is 0.
    #[inline]
    fn off_holder(&self, p: [f64; 3]) -> bool {
        let half = self.frame.scene.holder.half;
        (p[0].abs() > half || p[1].abs() > half) && !self.frame.scene.on_sample(p[0], p[1])
    }

    /// Fills `out` (row-major, top row first) with `read_out(linear
    /// values, index of the first, out)` for every run of pixels, bands of
    /// rows in parallel.
    pub(crate) fn fill<T: Send>(
        &self,
        out: &mut [T],
        read_out: impl Fn(&[f32], u64, &mut [T]) + Sync,
    ) {
        let w = self.width;
        let band_len = w * BAND_ROWS;
        let fill_band = |scratch: &mut Scratch, (band_index, band): (usize, &mut [T])| {
            let Scratch { run, linear } = scratch;
            let first_row = band_index * BAND_ROWS;
            for tile_start in (0..w).step_by(TILE_COLUMNS) {
                let tile_end = (tile_start + TILE_COLUMNS).min(w);
                for (r, row) in band.chunks_mut(w).enumerate() {
                    let j = first_row + r;
                    let (lit_start, lit_end) = self.coverage.span(j);
                    let columns = tile_start.max(lit_start)..tile_end.min(lit_end);
                    run.shade(self, j, columns);
                    let tile = &mut linear[..tile_end - tile_start];
                    tile.fill(0.0);
                    let shaded = run.first.saturating_sub(tile_start);
                    if let Some(dst) = tile.get_mut(shaded..shaded + run.len) {
                        dst.copy_from_slice(&run.value[..run.len]);
                    }
                    let first_index = (j * w + tile_start) as u64;
                    if let Some(out) = row.get_mut(tile_start..tile_end) {
                        read_out(tile, first_index, out);
                    }
                }
            }
        };
        if out.len() <= band_len {
            // One band: handing it to other threads costs more than it saves.
            fill_band(&mut Scratch::default(), (0, out));
        } else {
            out.par_chunks_mut(band_len)
                .enumerate()
                .for_each_init(Scratch::default, fill_band);
        }
    }
}

/// What a render thread reuses from band to band.
struct Scratch {
    run: Box<Run>,
    /// One tile row's linear values.
    linear: [f32; TILE_COLUMNS],
}

impl Default for Scratch {
    fn default() -> Scratch {
        Scratch {
            run: Box::default(),
            linear: [0.0; TILE_COLUMNS],
        }
    }
}

/// A run of neighbouring pixels of one row, shaded stage by stage: the
/// rays and where they meet the surface (relief marches side by side),
/// what the surface is at each hit, the lamp as seen from each and its
/// shadow rays (side by side), then the rest of the shading. Every pixel's
/// arithmetic is what [`Frame::shade`] does, in the same order; staging
/// only lets the long dependent chains of neighbouring pixels (square
/// roots, divisions, texel reads, march steps) overlap instead of queueing
/// one behind the other.
struct Run {
    /// The run's first column.
    first: usize,
    /// Pixels in the run.
    len: usize,
    /// Each pixel's ray.
    origin: [[f64; 3]; TILE_COLUMNS],
    dir: [[f64; 3]; TILE_COLUMNS],
    /// Where each ray meets the surface, once marched.
    primary: [Primary; TILE_COLUMNS],
    /// Where each ray meets the surface.
    point: [[f64; 3]; TILE_COLUMNS],
    /// Whether the pixel needs shading: its ray hits, and not bare floor
    /// beyond the plate.
    lit: [bool; TILE_COLUMNS],
    surface: [Surface; TILE_COLUMNS],
    incidence: [Incidence; TILE_COLUMNS],
    /// Shadow rays, when the frame marches them.
    shadow: [Shadow; TILE_COLUMNS],
    /// The lamp's visibility at each hit.
    visibility: [f64; TILE_COLUMNS],
    /// The linear values, in digital numbers.
    value: [f32; TILE_COLUMNS],
}

impl Default for Run {
    fn default() -> Run {
        Run {
            first: 0,
            len: 0,
            origin: [[0.0; 3]; TILE_COLUMNS],
            dir: [[0.0; 3]; TILE_COLUMNS],
            primary: [Primary::Miss; TILE_COLUMNS],
            point: [[0.0; 3]; TILE_COLUMNS],
            lit: [false; TILE_COLUMNS],
            surface: [Surface::default(); TILE_COLUMNS],
            incidence: [Incidence::default(); TILE_COLUMNS],
            shadow: [Shadow::Known(1.0); TILE_COLUMNS],
            visibility: [1.0; TILE_COLUMNS],
            value: [0.0; TILE_COLUMNS],
        }
    }
}

impl Run {
    /// Shades pixels `columns` (at most [`TILE_COLUMNS`]) of row `j` into
    /// `value`.
    fn shade(&mut self, exposure: &Exposure, j: usize, columns: std::ops::Range<usize>) {
        self.first = columns.start;
        self.len = columns.len().min(TILE_COLUMNS);
        let row = exposure.rays.row(j);
        self.trace(exposure, &row);
        self.light(&exposure.frame);
        self.expose(exposure, j, &row);
    }

    /// Where each pixel's ray meets the surface, relief marches side by
    /// side, and whether the pixel needs shading.
    fn trace(&mut self, exposure: &Exposure, row: &Row) {
        let (n, frame) = (self.len, &exposure.frame);
        exposure
            .rays
            .rays(self.first, row, &mut self.origin[..n], &mut self.dir[..n]);
        if frame.marches_relief() {
            for k in 0..n {
                self.primary[k] = frame.primary(self.origin[k], self.dir[k]);
            }
            frame.march_primaries(&mut self.primary[..n]);
            for k in 0..n {
                self.hit(exposure, k, self.primary[k].point());
            }
        } else {
            for k in 0..n {
                let point = frame.primary(self.origin[k], self.dir[k]).point();
                self.hit(exposure, k, point);
            }
        }
    }

    /// Records where pixel `k`'s ray meets the surface, and whether the
    /// pixel needs shading.
    #[inline]
    fn hit(&mut self, exposure: &Exposure, k: usize, point: Option<[f64; 3]>) {
        match point {
            Some(p) => {
                self.point[k] = p;
                self.lit[k] = !(exposure.skip_off_holder && exposure.off_holder(p));
            }
            None => self.lit[k] = false,
        }
    }

    /// What the surface is at each hit, the lamp as seen from there and
    /// its visibility, shadow rays marched side by side.
    fn light(&mut self, frame: &Frame) {
        let n = self.len;
        for k in 0..n {
            if self.lit[k] {
                self.surface[k] = frame.surface(self.point[k]);
            }
        }
        let Some(lamp) = &frame.lamp else {
            return;
        };
        for k in 0..n {
            self.incidence[k] = lamp.incidence(self.point[k], self.surface[k].normal);
        }
        if frame.marches_shadows() {
            for k in 0..n {
                let (p, normal) = (self.point[k], self.surface[k].normal);
                self.shadow[k] = if self.lit[k] {
                    frame.shadow(p, normal, &self.incidence[k])
                } else {
                    Shadow::Known(1.0)
                };
            }
            frame.resolve(&mut self.shadow[..n]);
            for k in 0..n {
                self.visibility[k] = self.shadow[k].visibility();
            }
        } else {
            for k in 0..n {
                let (p, normal) = (self.point[k], self.surface[k].normal);
                self.visibility[k] = if self.lit[k] {
                    frame.shadow(p, normal, &self.incidence[k]).visibility()
                } else {
                    1.0
                };
            }
        }
    }

    /// The rest of the shading, the gain and the vignetting: each pixel's
    /// linear value.
    fn expose(&mut self, exposure: &Exposure, j: usize, row: &Row) {
        let frame = &exposure.frame;
        for k in 0..self.len {
            self.value[k] = if self.lit[k] {
                let lit = frame.lamp.map(|_| {
                    let inc = self.incidence[k];
                    (inc, direct(&inc, self.visibility[k]))
                });
                let to_eye = scale(self.dir[k], -1.0);
                let filter = exposure.cfa.map(|cfa| {
                    frame
                        .scene
                        .response
                        .filter(cfa.channel_at(self.first + k, j))
                });
                let radiance = frame.shade_from(
                    self.point[k],
                    to_eye,
                    &self.surface[k],
                    lit.as_ref(),
                    filter,
                );
                let mut v = radiance * exposure.gain;
                if let Some(s) = exposure.vignette {
                    v *= exposure.rays.vignetting(self.first + k, row, s);
                }
                v as f32
            } else {
                0.0
            };
        }
    }
}
