//! Demosaicing of Bayer raw frames: from one sample per photosite, behind a
//! 2×2 colour filter tile, to red, green and blue at every pixel.
//!
//! [`bilinear`] is this module's own: a pixel keeps its own sample for its
//! own colour, and each other colour is the mean of that colour's samples
//! among its eight neighbours (green at a red site from its 4 edge
//! neighbours, blue at a red site from its 4 diagonals, red at a green site
//! from its 2 neighbours along the row or column). At the frame's border
//! the window is clipped, so fewer neighbours are averaged. It is exact on
//! smooth (locally linear) colour fields and needs no tuning; its cost is
//! colour fringes and aliasing at detail near the red and blue planes'
//! Nyquist limit.
//!
//! [`demosaic`] offers the better methods of the `demosaic` crate besides
//! it ([`Method`]); which one the colour steps use, [`DEFAULT_METHOD`], was
//! chosen by measuring them against the simulator's full-RGB truth (the
//! table and its command are in `docs/processing.md`, "Demosaicing,
//! measured").
//!
//! The steps that work on grey read a Bayer frame through [`luminance`]:
//! (R + 2G + B) / 4 of the bilinear pixel. That is the mean of a 2×2
//! tile's samples, so a neutral scene seen through a sensor with equal
//! channel responses reads exactly as a monochrome sensor would. No white
//! balance is applied there; `rigd process colour` measures one (see
//! [`crate::colour`]) for the RGB steps.

use rigd_core::pixel_format::Cfa;

/// A Bayer frame too small to hold one whole 2×2 tile.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("a {width}x{height} Bayer frame has no whole 2x2 colour filter tile")]
pub struct TooSmall {
    /// Frame width, pixels.
    pub width: usize,
    /// Frame height, pixels.
    pub height: usize,
}

/// A way to demosaic a Bayer frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Method {
    /// This module's [`bilinear`].
    Bilinear,
    /// Malvar, He and Cutler's gradient-corrected linear interpolation
    /// ("High-quality linear interpolation for demosaicing of
    /// Bayer-patterned color images", 2004): 5 × 5 kernels.
    MalvarHeCutler,
    /// Patterned pixel grouping: green along the smaller gradient, then red
    /// and blue from colour differences.
    PatternedPixelGrouping,
    /// Variable number of gradients: each pixel averages along the
    /// directions whose gradient is below a threshold.
    VariableNumberOfGradients,
    /// Adaptive homogeneity-directed: horizontal and vertical
    /// interpolations, kept per pixel where the result is more homogeneous
    /// in CIELAB.
    AdaptiveHomogeneityDirected,
}

impl Method {
    /// Every method, in the order the measurement table lists them.
    pub const ALL: [Method; 5] = [
        Method::Bilinear,
        Method::MalvarHeCutler,
        Method::PatternedPixelGrouping,
        Method::VariableNumberOfGradients,
        Method::AdaptiveHomogeneityDirected,
    ];

    /// The method's short name: `bilinear`, `mhc`, `ppg`, `vng`, `ahd`.
    pub fn name(self) -> &'static str {
        match self {
            Method::Bilinear => "bilinear",
            Method::MalvarHeCutler => "mhc",
            Method::PatternedPixelGrouping => "ppg",
            Method::VariableNumberOfGradients => "vng",
            Method::AdaptiveHomogeneityDirected => "ahd",
        }
    }

    /// How far from a pixel, in pixels along a row or column, the method
    /// reads photosites to fill it in: a clipped photosite makes every
    /// pixel within this distance a lower bound.
    pub fn reach(self) -> usize {
        match self {
            Method::Bilinear => 1,
            Method::MalvarHeCutler | Method::VariableNumberOfGradients => 2,
            // Red and blue from colour differences against green that was
            // itself interpolated two photosites out; AHD then picks per
            // pixel by its 3 × 3 neighbourhood.
            Method::PatternedPixelGrouping | Method::AdaptiveHomogeneityDirected => 3,
        }
    }

    fn of_crate(self) -> Option<demosaic::Algorithm> {
        match self {
            Method::Bilinear => None,
            Method::MalvarHeCutler => Some(demosaic::Algorithm::Mhc),
            Method::PatternedPixelGrouping => Some(demosaic::Algorithm::Ppg),
            Method::VariableNumberOfGradients => Some(demosaic::Algorithm::Vng),
            Method::AdaptiveHomogeneityDirected => Some(demosaic::Algorithm::Ahd),
        }
    }
}

/// The method the colour steps demosaic with: the best by the measurement
/// in `docs/processing.md`, "Demosaicing, measured".
pub const DEFAULT_METHOD: Method = Method::AdaptiveHomogeneityDirected;

/// Pixels added on each side before the crate's methods run: their 5 × 5
/// windows then read the right colour at the frame's border, where the
/// crate would clamp onto a neighbour of another colour.
const PAD: usize = 2;

/// Demosaics a `width × height` mosaic (row by row) by `method`: red,
/// green and blue planes of the same size.
///
/// The mosaic is white-balanced first by its own channel means (grey
/// world) and the planes divided back afterwards, so the methods that
/// borrow detail across channels borrow it at equal gains, and the planes
/// stay in the camera's raw units as [`bilinear`]'s do.
pub fn demosaic(
    mosaic: &[f32],
    width: usize,
    height: usize,
    cfa: Cfa,
    method: Method,
) -> Result<[Vec<f32>; 3], TooSmall> {
    let Some(algorithm) = method.of_crate() else {
        return bilinear(mosaic, width, height, cfa);
    };
    if width < 2 || height < 2 || mosaic.len() != width * height {
        return Err(TooSmall { width, height });
    }
    let gains = grey_world_gains(mosaic, width, cfa);
    // The padded frame starts PAD (even) pixels early, so its tile is the
    // frame's own.
    let (pw, ph) = (width + 2 * PAD, height + 2 * PAD);
    let source = |i: usize, n: usize| -> usize {
        // The nearest pixel of the same colour inside the frame.
        let i = i as isize - PAD as isize;
        let n = n as isize;
        let inside = if i < 0 {
            i.rem_euclid(2)
        } else if i >= n {
            n - 2 + (i - n).rem_euclid(2)
        } else {
            i
        };
        inside as usize
    };
    let padded: Vec<f32> = (0..ph)
        .flat_map(|y| (0..pw).map(move |x| (x, y)))
        .map(|(x, y)| {
            let (sx, sy) = (source(x, width), source(y, height));
            mosaic[sy * width + sx] * gains[cfa.channel_at(sx, sy)]
        })
        .collect();
    let pattern = match cfa {
        Cfa::Rggb => demosaic::CfaPattern::bayer_rggb(),
        Cfa::Grbg => demosaic::CfaPattern::bayer_grbg(),
        Cfa::Gbrg => demosaic::CfaPattern::bayer_gbrg(),
        Cfa::Bggr => demosaic::CfaPattern::bayer_bggr(),
    };
    let mut out = vec![0.0f32; 3 * pw * ph];
    demosaic::demosaic(&padded, pw, ph, &pattern, algorithm, &mut out)
        .map_err(|_| TooSmall { width, height })?;
    let planes = [0, 1, 2].map(|c| {
        let plane = &out[c * pw * ph..(c + 1) * pw * ph];
        let gain = gains[c];
        (PAD..PAD + height)
            .flat_map(|y| plane[y * pw + PAD..y * pw + PAD + width].iter())
            .map(|v| v / gain)
            .collect::<Vec<f32>>()
    });
    Ok(planes)
}

/// Gains that bring each channel's mean to green's: 1 for a channel with
/// no light, so a dark frame passes through unchanged.
fn grey_world_gains(mosaic: &[f32], width: usize, cfa: Cfa) -> [f32; 3] {
    let mut sum = [0.0f64; 3];
    let mut count = [0usize; 3];
    for (i, v) in mosaic.iter().enumerate() {
        let c = cfa.channel_at(i % width, i / width);
        sum[c] += f64::from(*v);
        count[c] += 1;
    }
    let mean = [0, 1, 2].map(|c| sum[c] / count[c].max(1) as f64);
    [0, 1, 2].map(|c| {
        let g = mean[1] / mean[c];
        if g.is_finite() && g > 0.0 {
            g as f32
        } else {
            1.0
        }
    })
}

/// Bilinear demosaicing of a `width × height` mosaic (row by row): red,
/// green and blue planes of the same size.
pub fn bilinear(
    mosaic: &[f32],
    width: usize,
    height: usize,
    cfa: Cfa,
) -> Result<[Vec<f32>; 3], TooSmall> {
    if width < 2 || height < 2 || mosaic.len() != width * height {
        return Err(TooSmall { width, height });
    }
    let mut planes = [
        vec![0.0f32; width * height],
        vec![0.0f32; width * height],
        vec![0.0f32; width * height],
    ];
    for y in 0..height {
        for x in 0..width {
            let own = cfa.channel_at(x, y);
            let mut sum = [0.0f32; 3];
            let mut count = [0u32; 3];
            for ny in y.saturating_sub(1)..=(y + 1).min(height - 1) {
                for nx in x.saturating_sub(1)..=(x + 1).min(width - 1) {
                    if (nx, ny) == (x, y) {
                        continue;
                    }
                    let c = cfa.channel_at(nx, ny);
                    sum[c] += mosaic[ny * width + nx];
                    count[c] += 1;
                }
            }
            let i = y * width + x;
            for (c, plane) in planes.iter_mut().enumerate() {
                plane[i] = if c == own {
                    mosaic[i]
                } else if count[c] > 0 {
                    sum[c] / count[c] as f32
                } else {
                    // Unreachable on frames of at least 2×2: every 3×3
                    // window (clipped) holds a whole tile's colours.
                    0.0
                };
            }
        }
    }
    Ok(planes)
}

/// Grey from demosaiced planes: (R + 2G + B) / 4 per pixel.
pub fn luminance(rgb: &[Vec<f32>; 3]) -> Vec<f32> {
    rgb[0]
        .iter()
        .zip(&rgb[1])
        .zip(&rgb[2])
        .map(|((r, g), b)| 0.25 * r + 0.5 * g + 0.25 * b)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const ALL: [Cfa; 4] = [Cfa::Rggb, Cfa::Grbg, Cfa::Gbrg, Cfa::Bggr];

    /// The mosaic a sensor behind `cfa` records of a scene whose colour at
    /// (x, y) is `scene(x, y)`.
    fn record(cfa: Cfa, w: usize, h: usize, scene: impl Fn(usize, usize) -> [f32; 3]) -> Vec<f32> {
        (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| scene(x, y)[cfa.channel_at(x, y)])
            .collect()
    }

    #[test]
    fn every_tile_has_one_red_two_greens_and_one_blue() {
        for cfa in ALL {
            let mut n = [0; 3];
            for (x, y) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                n[cfa.channel_at(x, y)] += 1;
            }
            assert_eq!(n, [1, 2, 1], "{cfa:?}");
        }
        assert_eq!(Cfa::Rggb.channel_at(0, 0), 0);
        assert_eq!(Cfa::Bggr.channel_at(0, 0), 2);
        // The tile repeats.
        assert_eq!(Cfa::Grbg.channel_at(5, 4), Cfa::Grbg.channel_at(1, 0));
    }

    #[test]
    fn a_uniform_colour_comes_back_everywhere_on_every_tile_and_border() {
        for cfa in ALL {
            for (w, h) in [(2, 2), (3, 2), (5, 7), (8, 6)] {
                let colour = [0.8, 0.3, 0.1];
                let m = record(cfa, w, h, |_, _| colour);
                let rgb = bilinear(&m, w, h, cfa).expect("demosaic");
                for (c, plane) in rgb.iter().enumerate() {
                    assert!(
                        plane.iter().all(|v| (v - colour[c]).abs() < 1e-6),
                        "{cfa:?} {w}x{h} channel {c}: {plane:?}"
                    );
                }
                let grey = luminance(&rgb);
                let want = 0.25 * 0.8 + 0.5 * 0.3 + 0.25 * 0.1;
                assert!(grey.iter().all(|v| (v - want).abs() < 1e-6));
            }
        }
    }

    #[test]
    fn a_linear_ramp_is_exact_away_from_the_border() {
        // Bilinear interpolation reproduces a linear field inside.
        let scene = |x: usize, y: usize| {
            let (x, y) = (x as f32, y as f32);
            [
                0.1 * x + 0.02 * y,
                0.05 * x - 0.03 * y + 1.0,
                0.2 - 0.01 * x + 0.04 * y,
            ]
        };
        for cfa in ALL {
            let (w, h) = (9, 8);
            let rgb = bilinear(&record(cfa, w, h, scene), w, h, cfa).expect("demosaic");
            for y in 1..h - 1 {
                for x in 1..w - 1 {
                    let want = scene(x, y);
                    for c in 0..3 {
                        let got = rgb[c][y * w + x];
                        assert!(
                            (got - want[c]).abs() < 1e-5,
                            "{cfa:?} ({x},{y}) c{c}: {got} vs {}",
                            want[c]
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn every_method_keeps_a_uniform_colour_on_every_tile_and_border() {
        for method in Method::ALL {
            for cfa in ALL {
                for (w, h) in [(2, 2), (3, 2), (5, 7), (8, 6), (16, 9)] {
                    let colour = [0.8, 0.3, 0.1];
                    let m = record(cfa, w, h, |_, _| colour);
                    let rgb = demosaic(&m, w, h, cfa, method).expect("demosaic");
                    for (c, plane) in rgb.iter().enumerate() {
                        assert_eq!(plane.len(), w * h);
                        assert!(
                            plane.iter().all(|v| (v - colour[c]).abs() < 1e-5),
                            "{method:?} {cfa:?} {w}x{h} channel {c}: {plane:?}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn every_method_follows_a_ramp_up_to_the_border() {
        // The padding gives the border its own colour's samples: a smooth
        // field stays close to the truth there too.
        let scene = |x: usize, y: usize| {
            let (x, y) = (x as f32, y as f32);
            [0.2 + 0.01 * x, 0.3 + 0.005 * y, 0.1 + 0.004 * (x + y)]
        };
        for method in Method::ALL {
            for cfa in ALL {
                let (w, h) = (12, 10);
                let rgb = demosaic(&record(cfa, w, h, scene), w, h, cfa, method).expect("demosaic");
                for y in 0..h {
                    for x in 0..w {
                        let want = scene(x, y);
                        for c in 0..3 {
                            let got = rgb[c][y * w + x];
                            assert!(
                                (got - want[c]).abs() < 0.03,
                                "{method:?} {cfa:?} ({x},{y}) c{c}: {got} vs {}",
                                want[c]
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn a_dark_frame_and_a_channel_without_light_stay_finite() {
        for method in Method::ALL {
            let dark = demosaic(&[0.0; 64], 8, 8, Cfa::Rggb, method).expect("demosaic");
            assert!(dark.iter().flatten().all(|v| *v == 0.0), "{method:?}");
            let red_only = record(Cfa::Rggb, 8, 8, |_, _| [0.5, 0.0, 0.0]);
            let rgb = demosaic(&red_only, 8, 8, Cfa::Rggb, method).expect("demosaic");
            assert!(rgb.iter().flatten().all(|v| v.is_finite()), "{method:?}");
        }
    }

    #[test]
    fn frames_without_a_whole_tile_are_refused_by_every_method() {
        for method in Method::ALL {
            assert_eq!(
                demosaic(&[0.0; 3], 3, 1, Cfa::Rggb, method),
                Err(TooSmall {
                    width: 3,
                    height: 1
                })
            );
            assert!(demosaic(&[0.0; 5], 2, 2, Cfa::Rggb, method).is_err());
            assert!(demosaic(&[], 0, 0, Cfa::Rggb, method).is_err());
        }
    }

    #[test]
    fn frames_without_a_whole_tile_are_refused() {
        assert_eq!(
            bilinear(&[0.0; 3], 3, 1, Cfa::Rggb),
            Err(TooSmall {
                width: 3,
                height: 1
            })
        );
        assert!(
            bilinear(&[0.0; 5], 2, 2, Cfa::Rggb).is_err(),
            "wrong length"
        );
        assert!(bilinear(&[], 0, 0, Cfa::Rggb).is_err());
    }
}
