//! Error statistics of a result against a ground truth, pixel by pixel:
//! what the simulator's truth (`truth`, cargo feature `sim`) fills in and
//! the reports (`mdf`, `rigd tradeoff`) summarise.

use serde::{Deserialize, Serialize};

/// Side of the tiles [`tile_spread`] groups pixels by.
pub const SPREAD_TILE: usize = 16;

/// The standard error of a per-pixel mean, with neighbouring pixels not
/// taken as independent: the pixels (index in an image `width` wide,
/// value) are grouped into [`SPREAD_TILE`]² tiles, and the error is the
/// standard deviation of the tile means over the square root of their
/// count. Pixel-level standard errors would be far too small: a
/// relief's errors come in patches. NaN with fewer than two tiles.
pub fn tile_spread(width: usize, pixels: impl Iterator<Item = (usize, f64)>) -> f64 {
    let mut tiles: std::collections::BTreeMap<(usize, usize), (f64, usize)> = Default::default();
    for (k, v) in pixels {
        let (i, j) = (k % width.max(1), k / width.max(1));
        let t = tiles.entry((i / SPREAD_TILE, j / SPREAD_TILE)).or_default();
        t.0 += v;
        t.1 += 1;
    }
    let means: Vec<f64> = tiles.values().map(|(s, n)| s / *n as f64).collect();
    let n = means.len();
    if n < 2 {
        return f64::NAN;
    }
    let mean = means.iter().sum::<f64>() / n as f64;
    let var = means.iter().map(|m| (m - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    (var / n as f64).sqrt()
}

/// One pixel of a result image (a displacement, a normal) against the
/// truth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PixelError {
    /// The pixel's true surface point is not on the sample.
    OffSample,
    /// On the sample, with no measurement.
    Unmeasured,
    /// On the sample: the error (mm of displacement, degrees of normal).
    Measured(f64),
}

/// A result image's error, pixel by pixel, row-major.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PixelErrors {
    /// Image width, pixels.
    pub width: usize,
    /// One entry per pixel.
    pub pixels: Vec<PixelError>,
}

/// Statistics of per-pixel errors, in their unit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorStats {
    /// Measured pixels the statistics are over.
    pub pixels: usize,
    /// Their share of the sample pixels considered.
    pub coverage: f64,
    /// Mean error; NaN without a pixel.
    pub mean: f64,
    /// Median error; NaN without a pixel.
    pub median: f64,
    /// 95th percentile; NaN without a pixel.
    pub p95: f64,
    /// Standard error of `mean` over tiles ([`tile_spread`]).
    pub spread: f64,
}

impl From<ErrorStats> for DepthError {
    fn from(s: ErrorStats) -> DepthError {
        DepthError {
            pixels: s.pixels,
            coverage: s.coverage,
            mean_mm: s.mean,
            median_mm: s.median,
            p95_mm: s.p95,
            spread_mm: s.spread,
        }
    }
}

impl PixelErrors {
    /// The depth summary over all sample pixels ([`PixelErrors::stats`]).
    pub fn summary(&self) -> DepthError {
        self.stats(|_| true).into()
    }

    /// The statistics over the sample's pixels that `keep` (by pixel
    /// index) admits: coverage is the measured share of the kept sample
    /// pixels.
    pub fn stats(&self, keep: impl Fn(usize) -> bool) -> ErrorStats {
        let mut errors = Vec::new();
        let mut at = Vec::new();
        let mut sample_pixels = 0usize;
        for (k, p) in self.pixels.iter().enumerate() {
            if *p == PixelError::OffSample || !keep(k) {
                continue;
            }
            sample_pixels += 1;
            if let PixelError::Measured(e) = *p {
                errors.push(e);
                at.push(k);
            }
        }
        let spread = tile_spread(self.width, at.into_iter().zip(errors.iter().copied()));
        errors.sort_by(f64::total_cmp);
        let pick = |q: f64| {
            errors
                .get(((errors.len() as f64 - 1.0) * q).round() as usize)
                .copied()
                .unwrap_or(f64::NAN)
        };
        ErrorStats {
            pixels: errors.len(),
            coverage: errors.len() as f64 / sample_pixels.max(1) as f64,
            mean: if errors.is_empty() {
                f64::NAN
            } else {
                errors.iter().sum::<f64>() / errors.len() as f64
            },
            median: pick(0.5),
            p95: pick(0.95),
            spread,
        }
    }

    /// The sample's pixels (measured or not).
    pub fn sample_pixels(&self) -> usize {
        self.pixels
            .iter()
            .filter(|p| **p != PixelError::OffSample)
            .count()
    }

    /// Whether pixel `k` is on the sample and measured.
    pub fn measured(&self, k: usize) -> bool {
        matches!(self.pixels.get(k), Some(PixelError::Measured(_)))
    }
}

/// Depth error against the scene's true MDF, millimetres.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct DepthError {
    /// Sample pixels with a measurement, over which the error is taken.
    pub pixels: usize,
    /// Share of the sample's pixels with a measurement.
    pub coverage: f64,
    /// Mean absolute error of the displacement, mm.
    pub mean_mm: f64,
    /// Median absolute error, mm.
    pub median_mm: f64,
    /// 95th percentile of the absolute error, mm.
    pub p95_mm: f64,
    /// Standard error of `mean_mm` over 16 × 16-pixel tiles
    /// ([`tile_spread`]); NaN with fewer than two tiles.
    pub spread_mm: f64,
}
