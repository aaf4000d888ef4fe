//! Demosaicing of Bayer raw frames: from one sample per photosite, behind a
//! 2×2 colour filter tile, to red, green and blue at every pixel.
//!
//! The method is bilinear: a pixel keeps its own sample for its own colour,
//! and each other colour is the mean of that colour's samples among its
//! eight neighbours (green at a red site from its 4 edge neighbours, blue
//! at a red site from its 4 diagonals, red at a green site from its 2
//! neighbours along the row or column). At the frame's border the window
//! is clipped, so fewer neighbours are averaged. It is exact on smooth
//! (locally linear) colour fields and needs no tuning. Its known cost is
//! colour fringes at sharp edges, about one pixel wide. Rectification
//! resamples every frame into texture space anyway, which low-passes
//! the result further.
//!
//! The steps that work on grey read a Bayer frame through [`luminance`]:
//! (R + 2G + B) / 4 of the demosaiced pixel. That is the mean of a 2×2
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
