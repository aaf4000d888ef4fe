//! Marker-based registration and rectification of rig frames onto the
//! frontal plane (seed 000 §3.2): find the holder plate's point markers in
//! a frame, estimate the plate→image homography, and resample the sample
//! region to a frontal "normtexture".
//!
//! # Conventions
//! - **Plate coordinates** are metres in the holder plane (z = 0), origin at
//!   the sample centre, `+x` right and `+y` up when seen from the front
//!   (θ = 0, φ = 0) — the sample frame of the simulator.
//! - **Pixel coordinates** are continuous, `x` right and `y` down; pixel
//!   `(i, j)` spans `[i, i+1) × [j, j+1)`, so its centre is `(i+0.5, j+0.5)`.
//! - **Homographies** are row-major 3×3 matrices mapping plate `(x, y, 1)`
//!   to pixel `(u w, v w, w)`; they are scaled to unit Frobenius norm with
//!   `w > 0` over the plate.
//! - **Textures** (output of [`rectify`]): row 0 is the `+y` edge of the
//!   region, column 0 its `−x` edge, i.e. the frontal view as the camera at
//!   θ = 0, φ = 0 sees it.
//!
//! # Pipeline
//! 1. [`detect_markers`]: for each marker whose position the rig predicts
//!    (from the commanded pose; tens of pixels off is fine), the bright blob
//!    nearest the prediction within a search radius. Candidate blobs come
//!    from connected components at a few global levels of the search window
//!    (so a bright sample nearby cannot mask a dimmer marker); each is then
//!    regrown from its peak at the *local* threshold midway between its
//!    surround's median (the dark plate) and its peak, and accepted only if
//!    it does not touch the window or image border, its area is within
//!    [`DetectOptions::min_area_px`]..[`DetectOptions::max_area_px`], it is
//!    not too elongated (second moments), fills its moment ellipse like a
//!    disc does, and is isolated (its surround is dark: a speck of a bright
//!    textured sample is not). The centre is the centroid of the blob
//!    dilated by one pixel, weighted by intensity above the local
//!    background, so partially covered edge pixels count by their coverage.
//!    Under perspective the centroid of a projected disc is not exactly the
//!    projection of its centre; for the holder's 6 mm discs at rig
//!    distances the difference is of the order of 0.01 px.
//! 2. [`detect_border_corners`] (optional, needs a homography good to
//!    about a pixel, e.g. from the point markers): the border lines'
//!    centrelines from cross profiles, fitted as straight image lines, and
//!    their 4 intersections as extra markers
//!    ([`MarkerLayout::with_border_corners`]).
//! 3. [`register`]: normalised DLT (Hartley) over all found markers by
//!    faer's SVD, Levenberg–Marquardt refinement of the reprojection error,
//!    and outlier rejection (see [`register`]); a typed [`RectifyError`]
//!    when fewer than 4 markers are usable, the set is degenerate, the
//!    residual stays too large, or the mapping folds over the plate.
//! 4. [`rectify`]: anisotropic area filtering through the homography's
//!    Jacobian (see [`Filter::Area`]), then [`roi_cut`] and [`quantise`].
//!
//! Every function validates its input and returns finite values; nothing on
//! an input-reachable path panics.

use rayon::prelude::*;

use crate::image_io::Image;

/// Size of a normtexture in the seed (1024²).
pub const NORMTEXTURE_SIZE: usize = 1024;
/// Size of the final textures after the ROI cut in the seed (256²).
pub const FINAL_TEXTURE_SIZE: usize = 256;
/// The seed's ROI: about 550 of 1024 texels, centred.
pub const SEED_ROI_FRACTION: f64 = 550.0 / 1024.0;
/// Largest output side accepted by [`rectify`] and [`roi_cut`].
pub const MAX_OUTPUT_SIDE: usize = 16384;

/// A 3×3 homography, row-major, plate metres → pixels.
pub type Homography = [[f64; 3]; 3];

#[derive(Debug, thiserror::Error)]
pub enum RectifyError {
    #[error(
        "only {found} of {total} markers found (at least 4 needed); missing markers {missing:?}"
    )]
    TooFewMarkers {
        found: usize,
        total: usize,
        missing: Vec<usize>,
    },
    #[error("the {found} markers found ({used:?}) are degenerate: no 4 of them are in general position (near-collinear)")]
    Degenerate { found: usize, used: Vec<usize> },
    #[error("markers inconsistent: worst residual {max_px:.2} px exceeds {limit_px:.2} px with {used} markers used ({found} found, rejected {rejected:?})")]
    Inconsistent {
        found: usize,
        used: usize,
        rejected: Vec<usize>,
        max_px: f64,
        limit_px: f64,
    },
    #[error("the homography from {found} markers folds over the plate (the plate reaches the camera's horizon)")]
    Folded { found: usize },
    #[error("SVD failed: {0}")]
    Svd(String),
    #[error("invalid input: {0}")]
    InvalidInput(String),
    #[error("{} of {total} frames could not be registered: {}", failures.len(), failures.iter().map(|(n, e)| format!("{n}: {e}")).collect::<Vec<_>>().join("; "))]
    Frames {
        total: usize,
        failures: Vec<(String, String)>,
    },
}

// ------------------------------------------------------------------ layout

/// Where the markers are on the plate.
#[derive(Debug, Clone, PartialEq)]
pub struct MarkerLayout {
    /// Marker centres, plate metres. Detections and residuals are indexed
    /// like this list.
    pub points: Vec<[f64; 2]>,
    /// Radius of a point marker, metres.
    pub radius_m: f64,
    /// Half the sample's size, metres, per axis.
    pub sample_half: [f64; 2],
}

impl MarkerLayout {
    /// The simulator's default holder: a 160 mm plate with 6 mm discs at
    /// `±71 mm` (corners and edge midpoints, in the order
    /// `(sx, sy)` for `sx` in −1, 0, 1 and `sy` in −1, 0, 1 without the
    /// centre) and a 100 × 100 mm sample.
    pub fn default_holder() -> MarkerLayout {
        MarkerLayout::square(0.160, 0.006, [0.05, 0.05])
    }

    /// A plate of side `plate_m` with discs of diameter `marker_m` at the
    /// corners and edge midpoints of the square at `±(plate/2 − 1.5 marker)`
    /// (the simulator's layout).
    pub fn square(plate_m: f64, marker_m: f64, sample_half: [f64; 2]) -> MarkerLayout {
        let c = plate_m / 2.0 - 1.5 * marker_m;
        let mut points = Vec::with_capacity(8);
        for sx in [-1.0, 0.0, 1.0] {
            for sy in [-1.0, 0.0, 1.0] {
                if sx != 0.0 || sy != 0.0 {
                    points.push([sx * c, sy * c]);
                }
            }
        }
        MarkerLayout {
            points,
            radius_m: marker_m / 2.0,
            sample_half,
        }
    }

    /// This layout with the border lines' corners (see
    /// [`BorderLines::corners`]) appended as markers 8..12, to register
    /// with point and border markers together.
    pub fn with_border_corners(&self, border: &BorderLines) -> MarkerLayout {
        let mut out = self.clone();
        out.points.extend(border.corners());
        out
    }

    /// The sample square, `±sample_half`.
    pub fn sample_region(&self) -> Region {
        Region::centred(self.sample_half)
    }
}

/// An axis-aligned rectangle on the plate, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Region {
    pub x_min: f64,
    pub x_max: f64,
    pub y_min: f64,
    pub y_max: f64,
}

impl Region {
    /// `[−half_x, half_x] × [−half_y, half_y]`.
    pub fn centred(half: [f64; 2]) -> Region {
        Region {
            x_min: -half[0],
            x_max: half[0],
            y_min: -half[1],
            y_max: half[1],
        }
    }

    fn is_valid(&self) -> bool {
        [self.x_min, self.x_max, self.y_min, self.y_max]
            .iter()
            .all(|v| v.is_finite())
            && self.x_max > self.x_min
            && self.y_max > self.y_min
    }
}

/// Projects a plate point through `h`; `None` if it maps to or behind the
/// camera's horizon (`w ≤ 0`) or is not finite.
pub fn project(h: &Homography, p: [f64; 2]) -> Option<[f64; 2]> {
    let w = h[2][0] * p[0] + h[2][1] * p[1] + h[2][2];
    if !above(w, 0.0) {
        return None;
    }
    let u = (h[0][0] * p[0] + h[0][1] * p[1] + h[0][2]) / w;
    let v = (h[1][0] * p[0] + h[1][1] * p[1] + h[1][2]) / w;
    (u.is_finite() && v.is_finite()).then_some([u, v])
}

/// Predicted marker positions from a predicted homography (e.g. from the
/// commanded pose): `None` where a marker maps behind the camera.
pub fn predict_markers(h: &Homography, layout: &MarkerLayout) -> Vec<Option<[f64; 2]>> {
    layout.points.iter().map(|&p| project(h, p)).collect()
}

// --------------------------------------------------------------- detection

/// A found marker.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detection {
    /// Intensity-weighted centroid, continuous pixel coordinates.
    pub centre_px: [f64; 2],
    /// Pixels above the local threshold.
    pub area_px: f64,
    /// Peak minus local background, in image units.
    pub contrast: f64,
    /// Ratio of the blob's principal axes (1 for a frontal disc).
    pub elongation: f64,
}

/// Acceptance limits for marker blobs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetectOptions {
    /// Smallest blob accepted, pixels.
    pub min_area_px: f64,
    /// Largest blob accepted, pixels. Set it from the predicted homography
    /// (a few times the predicted disc area) when the scale is known; the
    /// default suits a plate of up to ~1100 px.
    pub max_area_px: f64,
    /// Largest ratio of principal axes (a disc at θ = 80° has 5.8).
    pub max_elongation: f64,
    /// Least peak-minus-background, image units.
    pub min_contrast: f64,
    /// Largest mean brightness of the blob's surround (2 px out) above the
    /// window's dark level, as a fraction of the blob's contrast.
    pub max_surround: f64,
}

impl Default for DetectOptions {
    fn default() -> Self {
        DetectOptions {
            min_area_px: 3.0,
            max_area_px: 5000.0,
            max_elongation: 8.0,
            min_contrast: 0.02,
            max_surround: 0.3,
        }
    }
}

/// Global levels (fractions of the window's range above its dark level) at
/// which candidate blobs are looked for.
const LEVELS: [f32; 4] = [0.5, 0.3, 0.18, 0.1];

/// Finds, for each predicted marker position, the acceptable bright blob
/// nearest the prediction whose centre lies within `search_radius_px`; see
/// the module doc for the criteria. `None` where no prediction is given
/// or nothing acceptable is found.
pub fn detect_markers(
    image: &Image,
    predicted_px: &[Option<[f64; 2]>],
    search_radius_px: f64,
    opts: &DetectOptions,
) -> Result<Vec<Option<Detection>>, RectifyError> {
    check_image(image)?;
    if !(search_radius_px.is_finite() && search_radius_px > 0.0) {
        return Err(RectifyError::InvalidInput(format!(
            "search radius {search_radius_px} px"
        )));
    }
    let o = opts;
    if !(o.min_area_px.is_finite()
        && o.max_area_px.is_finite()
        && o.min_area_px >= 1.0
        && o.max_area_px >= o.min_area_px
        && o.max_elongation >= 1.0
        && o.min_contrast.is_finite()
        && o.max_surround.is_finite())
    {
        return Err(RectifyError::InvalidInput(format!(
            "detect options {opts:?}"
        )));
    }
    let grey = luminance(image);
    Ok(predicted_px
        .par_iter()
        .map(|p| {
            let p = (*p)?;
            if !(p[0].is_finite() && p[1].is_finite()) {
                return None;
            }
            detect_one(&grey, image.width, image.height, p, search_radius_px, opts)
        })
        .collect())
}

/// One grey value per pixel (Rec. 709 luminance for RGB, the mean for other
/// channel counts); non-finite samples read as 0.
fn luminance(image: &Image) -> Vec<f32> {
    let c = image.channels;
    image
        .data
        .par_chunks(c)
        .map(|px| {
            let v = if c == 3 {
                0.2126 * px[0] + 0.7152 * px[1] + 0.0722 * px[2]
            } else {
                px.iter().sum::<f32>() / c as f32
            };
            if v.is_finite() {
                v
            } else {
                0.0
            }
        })
        .collect()
}

struct Window {
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
    v: Vec<f32>,
    /// The window's dark level (10th percentile).
    dark: f32,
}

fn detect_one(
    grey: &[f32],
    width: usize,
    height: usize,
    pred: [f64; 2],
    radius: f64,
    opts: &DetectOptions,
) -> Option<Detection> {
    let margin = (opts.max_area_px * opts.max_elongation / std::f64::consts::PI).sqrt() + 3.0;
    let half = radius + margin;
    let lo_x = (pred[0] - half).floor().max(0.0);
    let lo_y = (pred[1] - half).floor().max(0.0);
    let hi_x = (pred[0] + half).ceil().min(width as f64);
    let hi_y = (pred[1] + half).ceil().min(height as f64);
    if !(hi_x - lo_x >= 3.0 && hi_y - lo_y >= 3.0) {
        return None;
    }
    let (x0, y0) = (lo_x as usize, lo_y as usize);
    let (w, h) = (hi_x as usize - x0, hi_y as usize - y0);
    let mut v = Vec::with_capacity(w * h);
    for y in y0..y0 + h {
        v.extend_from_slice(&grey[y * width + x0..y * width + x0 + w]);
    }
    let mut sorted = v.clone();
    let k = sorted.len() / 10;
    let (_, dark, _) = sorted.select_nth_unstable_by(k, f32::total_cmp);
    let dark = *dark;
    let bright = v.iter().copied().fold(f32::MIN, f32::max);
    if !above_or_eq(f64::from(bright - dark), opts.min_contrast) {
        return None;
    }
    let win = Window {
        x0,
        y0,
        w,
        h,
        v,
        dark,
    };
    let pred_local = [pred[0] - x0 as f64, pred[1] - y0 as f64];
    let mut tried_peaks = std::collections::HashSet::new();
    let mut best: Option<(f64, Detection)> = None;
    let mut label = vec![false; w * h];
    let mut stack = Vec::new();
    for level in LEVELS {
        let t = dark + level * (bright - dark);
        label.iter_mut().for_each(|l| *l = false);
        for start in 0..w * h {
            if label[start] || win.v[start] <= t {
                continue;
            }
            // Flood the component above the level, tracking its peak.
            let mut peak = start;
            label[start] = true;
            stack.push(start);
            while let Some(i) = stack.pop() {
                if win.v[i] > win.v[peak] {
                    peak = i;
                }
                for_neighbours(i, w, h, |j| {
                    if !label[j] && win.v[j] > t {
                        label[j] = true;
                        stack.push(j);
                    }
                });
            }
            if !tried_peaks.insert(peak) {
                continue;
            }
            if let Some(d) = analyse_blob(&win, peak, opts) {
                let c = [
                    d.centre_px[0] - win.x0 as f64,
                    d.centre_px[1] - win.y0 as f64,
                ];
                let dist = (c[0] - pred_local[0]).hypot(c[1] - pred_local[1]);
                if dist <= radius && best.as_ref().is_none_or(|(b, _)| dist < *b) {
                    best = Some((dist, d));
                }
            }
        }
    }
    best.map(|(_, d)| d)
}

/// Calls `f` with the window indices of the 8 neighbours of `i`.
fn for_neighbours(i: usize, w: usize, h: usize, mut f: impl FnMut(usize)) {
    let (x, y) = (i % w, i / w);
    for dy in -1i64..=1 {
        for dx in -1i64..=1 {
            if dx == 0 && dy == 0 {
                continue;
            }
            let (nx, ny) = (x as i64 + dx, y as i64 + dy);
            if nx >= 0 && ny >= 0 && (nx as usize) < w && (ny as usize) < h {
                f(ny as usize * w + nx as usize);
            }
        }
    }
}

struct Blob {
    pixels: Vec<usize>,
    touches_border: bool,
}

/// The 8-connected region above `threshold` around `seed`, or `None` when it
/// grows beyond `max_pixels`.
fn grow(win: &Window, seed: usize, threshold: f32, max_pixels: usize) -> Option<Blob> {
    let (w, h) = (win.w, win.h);
    // A mask, not a hash set: a window holds a few thousand pixels and a
    // textured frame sends hundreds of candidate peaks through here.
    let mut inside = vec![false; w * h];
    let mut pixels = vec![seed];
    inside[seed] = true;
    let mut touches_border = false;
    let mut k = 0;
    while k < pixels.len() {
        let i = pixels[k];
        k += 1;
        let (x, y) = (i % w, i / w);
        if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
            touches_border = true;
        }
        let mut overflow = false;
        for_neighbours(i, w, h, |j| {
            if win.v[j] > threshold && !inside[j] {
                inside[j] = true;
                pixels.push(j);
                if pixels.len() > max_pixels {
                    overflow = true;
                }
            }
        });
        if overflow {
            return None;
        }
    }
    Some(Blob {
        pixels,
        touches_border,
    })
}

/// Pixels at chessboard distance 1 (`ring1`) and 2 (`ring2`) from the blob.
fn rings(win: &Window, blob: &[usize]) -> (Vec<usize>, Vec<usize>) {
    const INSIDE: u8 = 1;
    const RING1: u8 = 2;
    const RING2: u8 = 3;
    let mut mark = vec![0u8; win.w * win.h];
    for &i in blob {
        mark[i] = INSIDE;
    }
    let mut r1 = Vec::new();
    for &i in blob {
        for_neighbours(i, win.w, win.h, |j| {
            if mark[j] == 0 {
                mark[j] = RING1;
                r1.push(j);
            }
        });
    }
    let mut r2 = Vec::new();
    for &i in &r1 {
        for_neighbours(i, win.w, win.h, |j| {
            if mark[j] == 0 {
                mark[j] = RING2;
                r2.push(j);
            }
        });
    }
    r1.sort_unstable();
    r2.sort_unstable();
    (r1, r2)
}

fn median_f32(mut v: Vec<f32>) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    let k = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(k, f32::total_cmp);
    Some(*m)
}

fn analyse_blob(win: &Window, peak: usize, opts: &DetectOptions) -> Option<Detection> {
    let pv = win.v[peak];
    let max_pixels = opts.max_area_px.min(1e9) as usize;
    // Threshold midway between the background and the peak: first with the
    // window's dark level, then with the blob's own surround.
    let mut bg = win.dark;
    let mut blob = grow(win, peak, bg + 0.5 * (pv - bg), max_pixels)?;
    let (_, ring2) = rings(win, &blob.pixels);
    bg = median_f32(ring2.iter().map(|&i| win.v[i]).collect())?;
    if !above(f64::from(pv), f64::from(bg)) {
        return None;
    }
    blob = grow(win, peak, bg + 0.5 * (pv - bg), max_pixels)?;
    if blob.touches_border {
        return None;
    }
    let n = blob.pixels.len();
    if (n as f64) < opts.min_area_px || (n as f64) > opts.max_area_px {
        return None;
    }
    let (ring1, ring2) = rings(win, &blob.pixels);
    if ring2.is_empty() {
        return None;
    }
    bg = median_f32(ring2.iter().map(|&i| win.v[i]).collect())?;
    let contrast = f64::from(pv - bg);
    if !above_or_eq(contrast, opts.min_contrast) {
        return None;
    }
    let surround_mean =
        ring2.iter().map(|&i| f64::from(win.v[i])).sum::<f64>() / ring2.len() as f64;
    let full = f64::from(pv - win.dark);
    if full <= 0.0 || (surround_mean - f64::from(win.dark)) > opts.max_surround * full {
        return None;
    }
    // Shape from the binary region's second moments (+1/12 per axis for the
    // pixel's own extent).
    let w = win.w;
    let nf = n as f64;
    let (mut sx, mut sy) = (0.0, 0.0);
    for &i in &blob.pixels {
        sx += (i % w) as f64;
        sy += (i / w) as f64;
    }
    let (mx, my) = (sx / nf, sy / nf);
    let (mut cxx, mut cyy, mut cxy) = (1.0 / 12.0, 1.0 / 12.0, 0.0);
    for &i in &blob.pixels {
        let (dx, dy) = ((i % w) as f64 - mx, (i / w) as f64 - my);
        cxx += dx * dx / nf;
        cyy += dy * dy / nf;
        cxy += dx * dy / nf;
    }
    let tr = cxx + cyy;
    let disc = ((cxx - cyy).powi(2) / 4.0 + cxy * cxy).sqrt();
    let (l1, l2) = (tr / 2.0 + disc, tr / 2.0 - disc);
    if !above(l2, 0.0) {
        return None;
    }
    let elongation = (l1 / l2).sqrt();
    let fill = nf / (4.0 * std::f64::consts::PI * (l1 * l2).sqrt());
    if elongation > opts.max_elongation || !(0.6..=1.4).contains(&fill) {
        return None;
    }
    // Intensity-weighted centroid over the blob and its first ring.
    let (mut sw, mut swx, mut swy) = (0.0, 0.0, 0.0);
    for &i in blob.pixels.iter().chain(&ring1) {
        let wt = f64::from(win.v[i] - bg).max(0.0);
        sw += wt;
        swx += wt * ((i % w) as f64 + 0.5);
        swy += wt * ((i / w) as f64 + 0.5);
    }
    if !above(sw, 0.0) {
        return None;
    }
    let centre = [swx / sw + win.x0 as f64, swy / sw + win.y0 as f64];
    (centre[0].is_finite() && centre[1].is_finite()).then_some(Detection {
        centre_px: centre,
        area_px: nf,
        contrast,
        elongation,
    })
}

// ------------------------------------------------------------ border lines

/// The white border lines around the sample: centrelines at `x = ±offset[0]`
/// and `y = ±offset[1]` (plate metres), each `2 × half_width_m` wide,
/// running to the square's corners.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BorderLines {
    pub offset: [f64; 2],
    pub half_width_m: f64,
}

impl BorderLines {
    /// The simulator's default: 2 mm lines 5 mm outside a 100 × 100 mm
    /// sample.
    pub fn default_holder() -> BorderLines {
        BorderLines {
            offset: [0.055, 0.055],
            half_width_m: 0.001,
        }
    }

    /// Where the centrelines cross, in the simulator's order
    /// `(−,−), (+,−), (+,+), (−,+)`.
    pub fn corners(&self) -> [[f64; 2]; 4] {
        let [ox, oy] = self.offset;
        [[-ox, -oy], [ox, -oy], [ox, oy], [-ox, oy]]
    }
}

/// Profiles taken across each border line.
const LINE_PROFILES: usize = 48;
/// Samples per profile.
const PROFILE_SAMPLES: usize = 64;
/// Fewest accepted profiles for a line to be fitted.
const MIN_LINE_PROFILES: usize = 10;

/// Locates the border lines' corners (see [`BorderLines::corners`]) given a
/// homography that is already good to about a pixel (e.g. from
/// [`register`] on the point markers). Each line is measured by
/// 48 cross profiles between its ends (4 mm clear of the
/// corners), each spanning `±(half_width + 1.5 mm)` on the plate so it
/// stays clear of the sample 5 mm inside: the line's centre on a profile is
/// the intensity-weighted centroid (above the profile's background, per
/// image length) of the contiguous bright run around its peak; profiles
/// whose run is flat, too wide, or touches the profile's ends (hidden,
/// out of the frame, a bright sample) are dropped. A straight line is
/// fitted through the centres by total least squares, dropping centres
/// farther than `max(0.5 px, 3 × 1.4826 × MAD)`; the corners are the
/// intersections of adjacent lines (`None` when a line has fewer than
/// 10 usable profiles). The detections can be appended to the
/// point markers with [`MarkerLayout::with_border_corners`].
pub fn detect_border_corners(
    image: &Image,
    homography: &Homography,
    border: &BorderLines,
    opts: &DetectOptions,
) -> Result<Vec<Option<Detection>>, RectifyError> {
    check_image(image)?;
    if homography.iter().flatten().any(|v| !v.is_finite())
        || !border.offset.iter().all(|v| v.is_finite() && *v > 0.0)
        || !(border.half_width_m.is_finite() && border.half_width_m > 0.0)
    {
        return Err(RectifyError::InvalidInput(format!(
            "border lines {border:?} or homography"
        )));
    }
    let [ox, oy] = border.offset;
    // Lines as (point on centreline at parameter t, along, across) with
    // t ∈ [−len, len]: bottom, right, top, left.
    // Bottom, right, top, left.
    let line = |centre, along, across, len| LineSpec {
        centre,
        along,
        across,
        len,
    };
    let lines = [
        line([0.0, -oy], [1.0, 0.0], [0.0, 1.0], ox),
        line([ox, 0.0], [0.0, 1.0], [1.0, 0.0], oy),
        line([0.0, oy], [1.0, 0.0], [0.0, 1.0], ox),
        line([-ox, 0.0], [0.0, 1.0], [1.0, 0.0], oy),
    ];
    let grey = Image {
        width: image.width,
        height: image.height,
        channels: 1,
        data: luminance(image),
    };
    let fitted: Vec<Option<FittedLine>> = lines
        .par_iter()
        .map(|spec| fit_border_line(&grey, homography, spec, border, opts))
        .collect();
    // Corner k is where line k meets line k−1 (bottom/left, bottom/right,
    // top/right, top/left).
    let pairs = [(0usize, 3usize), (0, 1), (2, 1), (2, 3)];
    Ok(pairs
        .iter()
        .map(|&(a, b)| {
            let FittedLine {
                a: a1,
                b: b1,
                c: c1,
                used: n1,
                contrast: k1,
            } = fitted[a]?;
            let FittedLine {
                a: a2,
                b: b2,
                c: c2,
                used: n2,
                contrast: k2,
            } = fitted[b]?;
            let det = a1 * b2 - a2 * b1;
            if !above(det.abs(), 1e-6) {
                return None;
            }
            let x = (b1 * c2 - b2 * c1) / det;
            let y = (a2 * c1 - a1 * c2) / det;
            (x.is_finite() && y.is_finite()).then_some(Detection {
                centre_px: [x, y],
                area_px: (n1 + n2) as f64,
                contrast: k1.min(k2),
                elongation: 1.0,
            })
        })
        .collect())
}

/// A border line's centreline on the plate: `centre + t along` for
/// `t ∈ [−len, len]`, with `across` its unit normal.
struct LineSpec {
    centre: [f64; 2],
    along: [f64; 2],
    across: [f64; 2],
    len: f64,
}

/// A line `a x + b y + c = 0` in the image (unit normal), the profiles
/// used and their median contrast.
#[derive(Clone, Copy)]
struct FittedLine {
    a: f64,
    b: f64,
    c: f64,
    used: usize,
    contrast: f64,
}

/// Fits one border line in the image; see [`detect_border_corners`].
fn fit_border_line(
    grey: &Image,
    h: &Homography,
    spec: &LineSpec,
    border: &BorderLines,
    opts: &DetectOptions,
) -> Option<FittedLine> {
    let LineSpec {
        centre,
        along,
        across,
        len,
    } = *spec;
    let clear = 0.004;
    let span = border.half_width_m + 0.0015;
    let mut points = Vec::new();
    let mut contrasts = Vec::new();
    let mut acc = [0.0f64];
    for k in 0..LINE_PROFILES {
        let t = -len + clear + (k as f64 + 0.5) / LINE_PROFILES as f64 * 2.0 * (len - clear);
        let base = [centre[0] + t * along[0], centre[1] + t * along[1]];
        let mut prof = Vec::with_capacity(PROFILE_SAMPLES);
        let mut outside = false;
        for i in 0..PROFILE_SAMPLES {
            let s = -span + (i as f64 + 0.5) / PROFILE_SAMPLES as f64 * 2.0 * span;
            let p = [base[0] + s * across[0], base[1] + s * across[1]];
            let Some(q) = project(h, p) else {
                outside = true;
                break;
            };
            acc[0] = 0.0;
            if !sample_bilinear(grey, q[0], q[1], &mut acc) {
                outside = true;
                break;
            }
            prof.push((q, acc[0]));
        }
        if outside {
            continue;
        }
        let Some(point) = profile_centre(&prof, opts) else {
            continue;
        };
        points.push(point.0);
        contrasts.push(point.1);
    }
    // Total least squares with MAD-based rejection.
    let mut keep: Vec<usize> = (0..points.len()).collect();
    let mut line = None;
    for _ in 0..4 {
        if keep.len() < MIN_LINE_PROFILES {
            return None;
        }
        let n = keep.len() as f64;
        let mx = keep.iter().map(|&i| points[i][0]).sum::<f64>() / n;
        let my = keep.iter().map(|&i| points[i][1]).sum::<f64>() / n;
        let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
        for &i in &keep {
            let (dx, dy) = (points[i][0] - mx, points[i][1] - my);
            sxx += dx * dx;
            syy += dy * dy;
            sxy += dx * dy;
        }
        // Normal = eigenvector of the smaller eigenvalue of the scatter.
        let angle = 0.5 * (2.0 * sxy).atan2(sxx - syy);
        let (a, b) = (-angle.sin(), angle.cos());
        let c = -(a * mx + b * my);
        let dist: Vec<f64> = keep
            .iter()
            .map(|&i| (a * points[i][0] + b * points[i][1] + c).abs())
            .collect();
        let mad = median_f64(&dist);
        let limit = (3.0 * 1.4826 * mad).max(0.5);
        let next: Vec<usize> = keep
            .iter()
            .zip(&dist)
            .filter_map(|(&i, &d)| (d <= limit).then_some(i))
            .collect();
        line = Some((a, b, c));
        if next.len() == keep.len() {
            break;
        }
        keep = next;
    }
    let (a, b, c) = line?;
    if keep.len() < MIN_LINE_PROFILES || ![a, b, c].iter().all(|v| v.is_finite()) {
        return None;
    }
    Some(FittedLine {
        a,
        b,
        c,
        used: keep.len(),
        contrast: median_f64(&contrasts),
    })
}

/// Centre (image point) and contrast of the bright run around a profile's
/// peak; `None` when implausible (see [`detect_border_corners`]).
fn profile_centre(prof: &[([f64; 2], f64)], opts: &DetectOptions) -> Option<([f64; 2], f64)> {
    let n = prof.len();
    if n < 8 {
        return None;
    }
    let mut values: Vec<f64> = prof.iter().map(|p| p.1).collect();
    let peak_i = (0..n).max_by(|&i, &j| values[i].total_cmp(&values[j]))?;
    let peak = values[peak_i];
    // Background: median of the outer quarter on each side.
    let q = n / 4;
    let mut ends: Vec<f64> = values[..q]
        .iter()
        .chain(&values[n - q..])
        .copied()
        .collect();
    ends.sort_unstable_by(f64::total_cmp);
    let bg = ends[ends.len() / 2];
    let contrast = peak - bg;
    if !above_or_eq(contrast, opts.min_contrast) {
        return None;
    }
    let half = bg + 0.5 * contrast;
    let (mut lo, mut hi) = (peak_i, peak_i);
    while lo > 0 && values[lo - 1] > half {
        lo -= 1;
    }
    while hi + 1 < n && values[hi + 1] > half {
        hi += 1;
    }
    // The run must sit inside the profile with background on both sides.
    if lo < q / 2 || hi + q / 2 >= n || hi - lo + 1 > n / 2 {
        return None;
    }
    // Centroid over the run widened by its half-width on each side, per
    // image length.
    let pad = (hi - lo).div_ceil(2) + 1;
    let (a, b) = (lo.saturating_sub(pad), (hi + pad).min(n - 1));
    let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for i in a..=b {
        let prev = prof[i.saturating_sub(1)].0;
        let next = prof[(i + 1).min(n - 1)].0;
        let dl = 0.5 * (next[0] - prev[0]).hypot(next[1] - prev[1]);
        let w = (values[i] - bg).max(0.0) * dl;
        sw += w;
        sx += w * prof[i].0[0];
        sy += w * prof[i].0[1];
    }
    values.clear();
    (above(sw, 0.0)).then(|| ([sx / sw, sy / sw], contrast))
}

// ------------------------------------------------------------ registration

/// Options of [`register`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RegisterOptions {
    /// A marker is an outlier candidate when its residual exceeds
    /// `max(outlier_px, outlier_median_factor × median residual)`.
    pub outlier_px: f64,
    pub outlier_median_factor: f64,
    /// After rejection, a worst residual above this fails the frame.
    pub max_residual_px: f64,
    /// Refine the DLT estimate by Levenberg–Marquardt on the reprojection
    /// error.
    pub refine: bool,
}

impl Default for RegisterOptions {
    fn default() -> Self {
        RegisterOptions {
            outlier_px: 2.0,
            outlier_median_factor: 3.0,
            max_residual_px: 3.0,
            refine: true,
        }
    }
}

/// A frame's plate→image mapping and how well the markers agree with it.
#[derive(Debug, Clone, PartialEq)]
pub struct Registration {
    /// Plate metres → pixels; see the module doc.
    pub homography: Homography,
    /// Per layout marker: reprojection residual in pixels under the final
    /// homography (rejected markers included), `None` if not found.
    pub residuals_px: Vec<Option<f64>>,
    /// RMS and maximum residual over the markers used.
    pub rms_px: f64,
    pub max_px: f64,
    /// Markers found, and used in the final fit.
    pub found: usize,
    pub used: usize,
    /// Layout indices of the markers rejected as outliers.
    pub rejected: Vec<usize>,
}

/// Fewest markers at which an outlier can be identified: with 5 points
/// every 4-subset fits exactly, so a bad one can be detected (large
/// residual) but not told apart; from 6 on, leave-one-out separates it.
const MIN_FOR_REJECTION: usize = 6;

/// Estimates the homography from the detections (indexed like
/// `layout.points`).
///
/// Outlier rejection (for ≤ 8 markers exhaustive leave-one-out is cheaper
/// and more reliable than RANSAC or dropping the worst residual of a fit
/// the outlier has already pulled): while at least 6 markers are used, fit
/// every subset that leaves one marker out, take the subset whose worst
/// residual is smallest, and reject the left-out marker if its residual
/// under that subset's fit exceeds `max(outlier_px, outlier_median_factor ×
/// median residual of the subset)`; otherwise stop. If the worst residual
/// of the final fit exceeds `max_residual_px` the frame fails with
/// [`RectifyError::Inconsistent`] (with 4 markers the fit is exact and
/// cannot reveal an outlier; with 5 it can reveal but not locate one).
pub fn register(
    layout: &MarkerLayout,
    detections: &[Option<Detection>],
    opts: &RegisterOptions,
) -> Result<Registration, RectifyError> {
    if detections.len() != layout.points.len() {
        return Err(RectifyError::InvalidInput(format!(
            "{} detections for {} markers",
            detections.len(),
            layout.points.len()
        )));
    }
    if layout
        .points
        .iter()
        .flatten()
        .chain(&layout.sample_half)
        .any(|v| !v.is_finite())
    {
        return Err(RectifyError::InvalidInput("non-finite layout".into()));
    }
    let found_idx: Vec<usize> = detections
        .iter()
        .enumerate()
        .filter_map(|(i, d)| d.map(|_| i))
        .collect();
    let found = found_idx.len();
    let total = layout.points.len();
    if found < 4 {
        return Err(RectifyError::TooFewMarkers {
            found,
            total,
            missing: (0..total).filter(|i| !found_idx.contains(i)).collect(),
        });
    }
    let plate =
        |set: &[usize]| -> Vec<[f64; 2]> { set.iter().map(|&i| layout.points[i]).collect() };
    let pix = |set: &[usize]| -> Vec<[f64; 2]> {
        set.iter()
            .filter_map(|&i| detections[i].map(|d| d.centre_px))
            .collect()
    };
    if !general_position(&plate(&found_idx)) {
        return Err(RectifyError::Degenerate {
            found,
            used: found_idx,
        });
    }
    let fit_set = |set: &[usize]| -> Result<(Homography, Vec<f64>), RectifyError> {
        let (p, q) = (plate(set), pix(set));
        let h = fit_homography(&p, &q, opts.refine)?;
        let r = residuals(&h, &p, &q);
        Ok((h, r))
    };
    let mut used = found_idx.clone();
    let mut rejected = Vec::new();
    let (mut h, mut res) = fit_set(&used)?;
    while used.len() >= MIN_FOR_REJECTION {
        // The most self-consistent leave-one-out subset …
        let mut best: Option<(f64, usize, Homography, Vec<f64>)> = None;
        for k in 0..used.len() {
            let subset: Vec<usize> = used
                .iter()
                .enumerate()
                .filter_map(|(j, &m)| (j != k).then_some(m))
                .collect();
            if !general_position(&plate(&subset)) {
                continue;
            }
            let Ok((hk, rk)) = fit_set(&subset) else {
                continue;
            };
            let score = rk.iter().copied().fold(0.0, f64::max);
            if best.as_ref().is_none_or(|b| score < b.0) {
                best = Some((score, k, hk, rk));
            }
        }
        let Some((_, k, hk, rk)) = best else { break };
        // … and whether the marker it leaves out disagrees with it.
        let m = used[k];
        let left_out = residuals(&hk, &[layout.points[m]], &pix(&[m]))
            .first()
            .copied()
            .unwrap_or(f64::INFINITY);
        let threshold = opts
            .outlier_px
            .max(opts.outlier_median_factor * median_f64(&rk));
        if left_out <= threshold {
            break;
        }
        rejected.push(used.remove(k));
        h = hk;
        res = rk;
    }
    let max_px = res.iter().copied().fold(0.0, f64::max);
    let rms_px = (res.iter().map(|r| r * r).sum::<f64>() / res.len() as f64).sqrt();
    rejected.sort_unstable();
    // Fold check: w must stay clearly positive over the plate's region of
    // interest (sample corners and markers); w is affine so the corners of
    // the bounding box suffice.
    let [hx, hy] = layout.sample_half;
    let (mut x0, mut x1, mut y0, mut y1) = (-hx, hx, -hy, hy);
    for p in &layout.points {
        x0 = x0.min(p[0]);
        x1 = x1.max(p[0]);
        y0 = y0.min(p[1]);
        y1 = y1.max(p[1]);
    }
    let ws: Vec<f64> = [[x0, y0], [x1, y0], [x0, y1], [x1, y1]]
        .iter()
        .map(|p| h[2][0] * p[0] + h[2][1] * p[1] + h[2][2])
        .collect();
    let (wmin, wmax) = ws
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &w| {
            (a.min(w), b.max(w))
        });
    if !above(wmin, 0.02 * wmax) {
        return Err(RectifyError::Folded { found });
    }
    if !above_or_eq(opts.max_residual_px, max_px) {
        return Err(RectifyError::Inconsistent {
            found,
            used: used.len(),
            rejected,
            max_px,
            limit_px: opts.max_residual_px,
        });
    }
    let residuals_px = (0..total)
        .map(|i| {
            let d = detections[i]?;
            let q = project(&h, layout.points[i])?;
            Some((q[0] - d.centre_px[0]).hypot(q[1] - d.centre_px[1]))
        })
        .collect();
    Ok(Registration {
        homography: h,
        residuals_px,
        rms_px,
        max_px,
        found,
        used: used.len(),
        rejected,
    })
}

/// Turns per-frame registration results into one error naming every frame
/// that failed (with its reason), or `Ok` when all succeeded.
pub fn require_all<'a, I>(frames: I) -> Result<(), RectifyError>
where
    I: IntoIterator<Item = (&'a str, &'a Result<Registration, RectifyError>)>,
{
    let mut total = 0;
    let mut failures = Vec::new();
    for (name, r) in frames {
        total += 1;
        if let Err(e) = r {
            failures.push((name.to_string(), e.to_string()));
        }
    }
    if failures.is_empty() {
        Ok(())
    } else {
        Err(RectifyError::Frames { total, failures })
    }
}

/// `a > b`, false when either is NaN (spelt as a function so the negation
/// `!above(a, b)` reads as "not clearly above", NaN included).
fn above(a: f64, b: f64) -> bool {
    a > b
}

/// `a >= b`, false when either is NaN.
fn above_or_eq(a: f64, b: f64) -> bool {
    a >= b
}

fn median_f64(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_unstable_by(f64::total_cmp);
    match s.len() {
        0 => 0.0,
        n if n % 2 == 1 => s[n / 2],
        n => 0.5 * (s[n / 2 - 1] + s[n / 2]),
    }
}

fn residuals(h: &Homography, plate: &[[f64; 2]], pix: &[[f64; 2]]) -> Vec<f64> {
    plate
        .iter()
        .zip(pix)
        .map(|(&p, q)| match project(h, p) {
            Some(r) => (r[0] - q[0]).hypot(r[1] - q[1]),
            None => f64::INFINITY,
        })
        .collect()
}

/// Whether some 4 of the points have no 3 (nearly) collinear.
fn general_position(points: &[[f64; 2]]) -> bool {
    let n = points.len();
    if n < 4 {
        return false;
    }
    let scale = points
        .iter()
        .flat_map(|p| points.iter().map(move |q| (p[0] - q[0]).hypot(p[1] - q[1])))
        .fold(0.0, f64::max);
    if !above(scale, 0.0) {
        return false;
    }
    // |cross| / scale² is twice a triangle's area in units of the spread.
    let non_collinear = |a: [f64; 2], b: [f64; 2], c: [f64; 2]| {
        let cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
        cross.abs() / (scale * scale) > 1e-3
    };
    for a in 0..n {
        for b in a + 1..n {
            for c in b + 1..n {
                if !non_collinear(points[a], points[b], points[c]) {
                    continue;
                }
                for d in c + 1..n {
                    let (pa, pb, pc, pd) = (points[a], points[b], points[c], points[d]);
                    if non_collinear(pa, pb, pd)
                        && non_collinear(pa, pc, pd)
                        && non_collinear(pb, pc, pd)
                    {
                        return true;
                    }
                }
            }
        }
    }
    false
}

/// Hartley normalisation: translate the centroid to 0, scale the mean
/// distance to √2. Returns the 3×3 transform.
fn normaliser(points: &[[f64; 2]]) -> Option<[[f64; 3]; 3]> {
    let n = points.len() as f64;
    let cx = points.iter().map(|p| p[0]).sum::<f64>() / n;
    let cy = points.iter().map(|p| p[1]).sum::<f64>() / n;
    let mean = points
        .iter()
        .map(|p| (p[0] - cx).hypot(p[1] - cy))
        .sum::<f64>()
        / n;
    if !(mean > 0.0 && mean.is_finite()) {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean;
    Some([[s, 0.0, -s * cx], [0.0, s, -s * cy], [0.0, 0.0, 1.0]])
}

fn apply(t: &[[f64; 3]; 3], p: [f64; 2]) -> [f64; 2] {
    // Normalisers are affine.
    [
        t[0][0] * p[0] + t[0][1] * p[1] + t[0][2],
        t[1][0] * p[0] + t[1][1] * p[1] + t[1][2],
    ]
}

fn mul3(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut m = [[0.0; 3]; 3];
    for (i, row) in m.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    m
}

/// Inverse of an affine normaliser `[[s,0,tx],[0,s,ty],[0,0,1]]`.
fn inverse_normaliser(t: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let s = t[0][0];
    [
        [1.0 / s, 0.0, -t[0][2] / s],
        [0.0, 1.0 / s, -t[1][2] / s],
        [0.0, 0.0, 1.0],
    ]
}

/// Least-squares homography from ≥ 4 correspondences plate → pixels:
/// normalised DLT (SVD of the 2N×9 system with faer) and, with `refine`,
/// Levenberg–Marquardt on the reprojection error. Scaled to unit Frobenius
/// norm with `w > 0` at the points' centroid.
pub fn fit_homography(
    plate: &[[f64; 2]],
    pixels: &[[f64; 2]],
    refine: bool,
) -> Result<Homography, RectifyError> {
    let n = plate.len();
    if n != pixels.len() {
        return Err(RectifyError::InvalidInput(format!(
            "{n} plate points for {} pixel points",
            pixels.len()
        )));
    }
    if n < 4 {
        return Err(RectifyError::TooFewMarkers {
            found: n,
            total: n,
            missing: Vec::new(),
        });
    }
    if plate.iter().chain(pixels).flatten().any(|v| !v.is_finite()) {
        return Err(RectifyError::InvalidInput("non-finite point".into()));
    }
    if !general_position(plate) || !general_position(pixels) {
        return Err(RectifyError::Degenerate {
            found: n,
            used: (0..n).collect(),
        });
    }
    let degenerate = || RectifyError::Degenerate {
        found: n,
        used: (0..n).collect(),
    };
    let tp = normaliser(plate).ok_or_else(degenerate)?;
    let ti = normaliser(pixels).ok_or_else(degenerate)?;
    let p: Vec<[f64; 2]> = plate.iter().map(|&q| apply(&tp, q)).collect();
    let q: Vec<[f64; 2]> = pixels.iter().map(|&x| apply(&ti, x)).collect();
    // Rows padded with zeros to ≥ 9 so the thin SVD's V is 9×9.
    let rows = (2 * n).max(9);
    let a = faer::Mat::<f64>::from_fn(rows, 9, |r, c| {
        let k = r / 2;
        if k >= n {
            return 0.0;
        }
        let ([x, y], [u, v]) = (p[k], q[k]);
        let row = if r % 2 == 0 {
            [0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v]
        } else {
            [x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y, -u]
        };
        row[c]
    });
    let svd = a
        .thin_svd()
        .map_err(|e| RectifyError::Svd(format!("{e:?}")))?;
    let sigma = svd.S().column_vector();
    if !above(sigma[7], 1e-9 * sigma[0]) {
        return Err(degenerate());
    }
    let v = svd.V();
    let mut hn = [[0.0; 3]; 3];
    for (k, item) in hn.iter_mut().flatten().enumerate() {
        *item = v[(k, 8)];
    }
    if refine {
        if let Some(r) = refine_lm(&hn, &p, &q) {
            hn = r;
        }
    }
    let h = mul3(&mul3(&inverse_normaliser(&ti), &hn), &tp);
    normalise_h(h, plate).ok_or_else(degenerate)
}

/// Unit Frobenius norm, sign such that `w > 0` at the centroid of `points`.
fn normalise_h(h: Homography, points: &[[f64; 2]]) -> Option<Homography> {
    let norm = h.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
    if !(norm > 0.0 && norm.is_finite()) {
        return None;
    }
    let n = points.len() as f64;
    let cx = points.iter().map(|p| p[0]).sum::<f64>() / n;
    let cy = points.iter().map(|p| p[1]).sum::<f64>() / n;
    let w = h[2][0] * cx + h[2][1] * cy + h[2][2];
    let s = if w < 0.0 { -1.0 / norm } else { 1.0 / norm };
    let mut out = h;
    out.iter_mut().flatten().for_each(|v| *v *= s);
    Some(out)
}

/// Levenberg–Marquardt on the (normalised) reprojection error with
/// `h22 = 1`; `None` when that parameterisation is unsuitable or nothing
/// improved.
fn refine_lm(h0: &Homography, p: &[[f64; 2]], q: &[[f64; 2]]) -> Option<Homography> {
    let norm = h0.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
    if !above(h0[2][2].abs(), 1e-6 * norm) {
        return None;
    }
    let mut x = [0.0; 8];
    for (k, v) in x.iter_mut().enumerate() {
        *v = h0[k / 3][k % 3] / h0[2][2];
    }
    let cost = |x: &[f64; 8]| -> f64 {
        p.iter()
            .zip(q)
            .map(|(&[a, b], &[u, v])| {
                let w = x[6] * a + x[7] * b + 1.0;
                let eu = (x[0] * a + x[1] * b + x[2]) / w - u;
                let ev = (x[3] * a + x[4] * b + x[5]) / w - v;
                eu * eu + ev * ev
            })
            .sum()
    };
    let mut c = cost(&x);
    if !c.is_finite() {
        return None;
    }
    let mut lambda = 1e-3;
    for _ in 0..50 {
        let mut jtj = [[0.0; 8]; 8];
        let mut jtr = [0.0; 8];
        for (&[a, b], &[u, v]) in p.iter().zip(q) {
            let w = x[6] * a + x[7] * b + 1.0;
            let pu = (x[0] * a + x[1] * b + x[2]) / w;
            let pv = (x[3] * a + x[4] * b + x[5]) / w;
            let ju = [
                a / w,
                b / w,
                1.0 / w,
                0.0,
                0.0,
                0.0,
                -pu * a / w,
                -pu * b / w,
            ];
            let jv = [
                0.0,
                0.0,
                0.0,
                a / w,
                b / w,
                1.0 / w,
                -pv * a / w,
                -pv * b / w,
            ];
            for (jrow, r) in [(ju, pu - u), (jv, pv - v)] {
                for i in 0..8 {
                    jtr[i] += jrow[i] * r;
                    for k in 0..8 {
                        jtj[i][k] += jrow[i] * jrow[k];
                    }
                }
            }
        }
        let mut improved = false;
        for _ in 0..10 {
            let mut m = jtj;
            for (i, row) in m.iter_mut().enumerate() {
                row[i] += lambda * (jtj[i][i] + 1e-12);
            }
            let rhs = jtr.map(|v| -v);
            let Some(d) = solve8(m, rhs) else {
                lambda *= 10.0;
                continue;
            };
            let mut xn = x;
            for i in 0..8 {
                xn[i] += d[i];
            }
            let cn = cost(&xn);
            if cn.is_finite() && cn < c {
                let gain = c - cn;
                x = xn;
                c = cn;
                lambda = (lambda / 10.0).max(1e-12);
                improved = gain > 1e-15 * (1.0 + c);
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    let mut h = [[0.0; 3]; 3];
    for k in 0..8 {
        h[k / 3][k % 3] = x[k];
    }
    h[2][2] = 1.0;
    Some(h)
}

/// Gaussian elimination with partial pivoting.
fn solve8(mut m: [[f64; 8]; 8], mut b: [f64; 8]) -> Option<[f64; 8]> {
    for col in 0..8 {
        let piv = (col..8).max_by(|&i, &j| m[i][col].abs().total_cmp(&m[j][col].abs()))?;
        if !above(m[piv][col].abs(), 1e-300) {
            return None;
        }
        m.swap(col, piv);
        b.swap(col, piv);
        for r in col + 1..8 {
            let f = m[r][col] / m[col][col];
            let pivot_row = m[col];
            for (x, p) in m[r].iter_mut().zip(pivot_row).skip(col) {
                *x -= f * p;
            }
            b[r] -= f * b[col];
        }
    }
    let mut x = [0.0; 8];
    for r in (0..8).rev() {
        let s: f64 = (r + 1..8).map(|k| m[r][k] * x[k]).sum();
        x[r] = (b[r] - s) / m[r][r];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

// ---------------------------------------------------------- rectification

/// How an output texel is computed from the frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Filter {
    /// The input pixel containing the texel centre's projection (for
    /// comparison; aliases when minifying, blocky when magnifying).
    Nearest,
    /// One bilinear lookup at the texel centre's projection.
    Bilinear,
    /// Anisotropic area filter: the texel's footprint in the frame is the
    /// parallelogram spanned by the columns of the Jacobian of the
    /// texel→pixel map; the texel is the mean of `k_c × k_r` bilinear
    /// lookups spread evenly over the texel (mapped exactly through the
    /// homography), with `k = ceil(footprint length in pixels)` per texel
    /// axis, capped at [`RectifyOptions::max_taps`]. Minification averages
    /// over the footprint (no aliasing); magnification is one bilinear tap
    /// (smooth).
    Area,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RectifyOptions {
    pub filter: Filter,
    /// Cap on taps per texel axis for [`Filter::Area`].
    pub max_taps: usize,
}

impl Default for RectifyOptions {
    fn default() -> Self {
        RectifyOptions {
            filter: Filter::Area,
            max_taps: 16,
        }
    }
}

/// A frontal texture and how much of it the frame covered.
#[derive(Debug, Clone, PartialEq)]
pub struct Rectified {
    pub texture: Image,
    /// Mean over texels of the fraction of their taps that fell inside the
    /// frame (1 = fully covered). Uncovered taps are left out of a texel's
    /// mean; a texel with none is 0.
    pub coverage: f64,
}

/// Resamples `region` of the plate, seen in `image` through `homography`
/// (plate metres → pixels, e.g. [`Registration::homography`]), to a
/// frontal texture of `size = [width, height]` texels; row 0 is the `+y`
/// edge of the region, column 0 the `−x` edge. Channels as the input.
pub fn rectify(
    image: &Image,
    homography: &Homography,
    region: Region,
    size: [usize; 2],
    opts: &RectifyOptions,
) -> Result<Rectified, RectifyError> {
    check_image(image)?;
    let [ow, oh] = size;
    if ow == 0 || oh == 0 || ow > MAX_OUTPUT_SIDE || oh > MAX_OUTPUT_SIDE {
        return Err(RectifyError::InvalidInput(format!(
            "output size {ow}x{oh} (1..={MAX_OUTPUT_SIDE} per side)"
        )));
    }
    if !region.is_valid() {
        return Err(RectifyError::InvalidInput(format!("region {region:?}")));
    }
    if homography.iter().flatten().any(|v| !v.is_finite()) {
        return Err(RectifyError::InvalidInput("non-finite homography".into()));
    }
    if opts.max_taps == 0 || opts.max_taps > 256 {
        return Err(RectifyError::InvalidInput(format!(
            "max_taps {} (1..=256)",
            opts.max_taps
        )));
    }
    let h = homography;
    let ch = image.channels;
    let dx = (region.x_max - region.x_min) / ow as f64;
    let dy = (region.y_max - region.y_min) / oh as f64;
    let mut texture = Image::new(ow, oh, ch);
    let covered: f64 = texture
        .data
        .par_chunks_mut(ow * ch)
        .enumerate()
        .map(|(r, row)| {
            let mut acc = vec![0.0f64; ch];
            let mut row_cover = 0.0;
            for c in 0..ow {
                // Texel centre and its plate-space axes.
                let x = region.x_min + (c as f64 + 0.5) * dx;
                let y = region.y_max - (r as f64 + 0.5) * dy;
                let (kc, kr) = match opts.filter {
                    Filter::Nearest | Filter::Bilinear => (1, 1),
                    Filter::Area => match jacobian(h, x, y) {
                        Some(j) => {
                            let col = |v: f64| {
                                if v.is_finite() {
                                    (v.ceil() as usize).clamp(1, opts.max_taps)
                                } else {
                                    opts.max_taps
                                }
                            };
                            (
                                col((j[0][0] * dx).hypot(j[1][0] * dx)),
                                col((j[0][1] * dy).hypot(j[1][1] * dy)),
                            )
                        }
                        None => (1, 1),
                    },
                };
                acc.iter_mut().for_each(|a| *a = 0.0);
                let mut hits = 0usize;
                for b in 0..kr {
                    let ty = y - ((b as f64 + 0.5) / kr as f64 - 0.5) * dy;
                    for a in 0..kc {
                        let tx = x + ((a as f64 + 0.5) / kc as f64 - 0.5) * dx;
                        let Some([u, v]) = project(h, [tx, ty]) else {
                            continue;
                        };
                        let ok = match opts.filter {
                            Filter::Nearest => sample_nearest(image, u, v, &mut acc),
                            _ => sample_bilinear(image, u, v, &mut acc),
                        };
                        hits += usize::from(ok);
                    }
                }
                let taps = (kc * kr) as f64;
                if hits > 0 {
                    for (k, a) in acc.iter().enumerate() {
                        let val = (a / hits as f64) as f32;
                        row[c * ch + k] = if val.is_finite() { val } else { 0.0 };
                    }
                }
                row_cover += hits as f64 / taps;
            }
            row_cover
        })
        .sum();
    Ok(Rectified {
        texture,
        coverage: covered / (ow * oh) as f64,
    })
}

/// ∂(u, v)/∂(x, y) of the homography at a plate point.
fn jacobian(h: &Homography, x: f64, y: f64) -> Option<[[f64; 2]; 2]> {
    let w = h[2][0] * x + h[2][1] * y + h[2][2];
    if !above(w, 0.0) {
        return None;
    }
    let u = (h[0][0] * x + h[0][1] * y + h[0][2]) / w;
    let v = (h[1][0] * x + h[1][1] * y + h[1][2]) / w;
    Some([
        [(h[0][0] - u * h[2][0]) / w, (h[0][1] - u * h[2][1]) / w],
        [(h[1][0] - v * h[2][0]) / w, (h[1][1] - v * h[2][1]) / w],
    ])
}

fn sanitise(v: f32) -> f64 {
    if v.is_finite() {
        f64::from(v)
    } else {
        0.0
    }
}

/// Adds the pixel containing `(u, v)` to `acc`; false when outside.
fn sample_nearest(image: &Image, u: f64, v: f64, acc: &mut [f64]) -> bool {
    if !(u >= 0.0 && v >= 0.0 && u < image.width as f64 && v < image.height as f64) {
        return false;
    }
    let (x, y) = (u as usize, v as usize);
    let base = (y * image.width + x) * image.channels;
    for (k, a) in acc.iter_mut().enumerate() {
        *a += sanitise(image.data[base + k]);
    }
    true
}

/// Adds the bilinear interpolation of the pixel centres around `(u, v)` to
/// `acc` (clamped to the edge within the image); false when outside.
fn sample_bilinear(image: &Image, u: f64, v: f64, acc: &mut [f64]) -> bool {
    let (w, h) = (image.width, image.height);
    if !(u >= 0.0 && v >= 0.0 && u <= w as f64 && v <= h as f64) {
        return false;
    }
    let fx = (u - 0.5).clamp(0.0, (w - 1) as f64);
    let fy = (v - 0.5).clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (ax, ay) = (fx - x0 as f64, fy - y0 as f64);
    let ch = image.channels;
    let at = |x: usize, y: usize, k: usize| sanitise(image.data[(y * w + x) * ch + k]);
    for (k, a) in acc.iter_mut().enumerate() {
        let top = at(x0, y0, k) * (1.0 - ax) + at(x1, y0, k) * ax;
        let bottom = at(x0, y1, k) * (1.0 - ax) + at(x1, y1, k) * ax;
        *a += top * (1.0 - ay) + bottom * ay;
    }
    true
}

fn check_image(image: &Image) -> Result<(), RectifyError> {
    if image.width == 0
        || image.height == 0
        || image.channels == 0
        || image
            .width
            .checked_mul(image.height)
            .and_then(|n| n.checked_mul(image.channels))
            != Some(image.data.len())
    {
        return Err(RectifyError::InvalidInput(format!(
            "image {}x{}x{} with {} samples",
            image.width,
            image.height,
            image.channels,
            image.data.len()
        )));
    }
    Ok(())
}

// ---------------------------------------------------------- ROI and bits

/// A rectangle of texels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Roi {
    pub x: usize,
    pub y: usize,
    pub width: usize,
    pub height: usize,
}

impl Roi {
    /// The centred square covering `fraction` of the smaller side of a
    /// `width × height` texture (e.g. [`SEED_ROI_FRACTION`]).
    pub fn centred(width: usize, height: usize, fraction: f64) -> Roi {
        let f = if fraction.is_finite() {
            fraction.clamp(0.0, 1.0)
        } else {
            1.0
        };
        let side = ((width.min(height) as f64 * f).round() as usize).max(1);
        Roi {
            x: width.saturating_sub(side) / 2,
            y: height.saturating_sub(side) / 2,
            width: side.min(width),
            height: side.min(height),
        }
    }
}

/// Cuts `roi` out of `texture` and resizes it to `size = [width, height]`:
/// separable exact area averaging (box over each output texel's span with
/// fractional overlaps) when shrinking an axis, linear interpolation of
/// texel centres when enlarging it.
pub fn roi_cut(texture: &Image, roi: Roi, size: [usize; 2]) -> Result<Image, RectifyError> {
    check_image(texture)?;
    let [ow, oh] = size;
    if ow == 0 || oh == 0 || ow > MAX_OUTPUT_SIDE || oh > MAX_OUTPUT_SIDE {
        return Err(RectifyError::InvalidInput(format!(
            "output size {ow}x{oh} (1..={MAX_OUTPUT_SIDE} per side)"
        )));
    }
    if roi.width == 0
        || roi.height == 0
        || roi
            .x
            .checked_add(roi.width)
            .is_none_or(|e| e > texture.width)
        || roi
            .y
            .checked_add(roi.height)
            .is_none_or(|e| e > texture.height)
    {
        return Err(RectifyError::InvalidInput(format!(
            "ROI {roi:?} outside a {}x{} texture",
            texture.width, texture.height
        )));
    }
    let wx = resample_weights(roi.width, ow);
    let wy = resample_weights(roi.height, oh);
    let ch = texture.channels;
    // Horizontal pass over the ROI's rows, then vertical.
    let mut tmp = vec![0.0f64; roi.height * ow * ch];
    tmp.par_chunks_mut(ow * ch)
        .enumerate()
        .for_each(|(r, row)| {
            let src = (roi.y + r) * texture.width;
            for (o, taps) in wx.iter().enumerate() {
                for &(i, wt) in taps {
                    let base = (src + roi.x + i) * ch;
                    for k in 0..ch {
                        row[o * ch + k] += wt * sanitise(texture.data[base + k]);
                    }
                }
            }
        });
    let mut out = Image::new(ow, oh, ch);
    out.data
        .par_chunks_mut(ow * ch)
        .enumerate()
        .for_each(|(o, row)| {
            for &(i, wt) in &wy[o] {
                let src = &tmp[i * ow * ch..(i + 1) * ow * ch];
                for (d, s) in row.iter_mut().zip(src) {
                    *d += (wt * s) as f32;
                }
            }
            for d in row.iter_mut() {
                if !d.is_finite() {
                    *d = 0.0;
                }
            }
        });
    Ok(out)
}

/// Linear edge blending (seed 000 §3.2: "linear edgeblending is applied,
/// which reduces the usual tiling artifacts"): an `(n + band)`-square
/// texture becomes an `n`-square one that tiles without seams. Along each
/// axis, texel `x < band` mixes texel `x` (weight `(x + ½)/band`) with texel
/// `x + n` (the rest), so where one tile's texel `n − 1` meets the next
/// tile's texel 0 the values are those of neighbouring input texels `n − 1`
/// and (almost) `n`. `band = 0` returns the texture unchanged.
pub fn edge_blend(texture: &Image, band: usize) -> Result<Image, RectifyError> {
    check_image(texture)?;
    if band == 0 {
        return Ok(texture.clone());
    }
    let (w, h, ch) = (texture.width, texture.height, texture.channels);
    if w != h || band >= w.saturating_sub(band) {
        return Err(RectifyError::InvalidInput(format!(
            "edge blend of {band} texels on a {w}x{h} texture (square, band < side − band)"
        )));
    }
    let n = w - band;
    let weight = |x: usize| (x as f64 + 0.5) / band as f64;
    // Columns first, into an n × (n + band) image, then rows.
    let mut cols = vec![0.0f32; h * n * ch];
    for y in 0..h {
        for x in 0..n {
            for c in 0..ch {
                let at = |xx: usize| f64::from(texture.data[(y * w + xx) * ch + c]);
                let v = if x < band {
                    weight(x) * at(x) + (1.0 - weight(x)) * at(x + n)
                } else {
                    at(x)
                };
                cols[(y * n + x) * ch + c] = v as f32;
            }
        }
    }
    let mut out = Image::new(n, n, ch);
    for y in 0..n {
        for x in 0..n {
            for c in 0..ch {
                let at = |yy: usize| f64::from(cols[(yy * n + x) * ch + c]);
                let v = if y < band {
                    weight(y) * at(y) + (1.0 - weight(y)) * at(y + n)
                } else {
                    at(y)
                };
                out.data[(y * n + x) * ch + c] = v as f32;
            }
        }
    }
    Ok(out)
}

/// Per output index, the input indices and weights (summing to 1).
fn resample_weights(n_in: usize, n_out: usize) -> Vec<Vec<(usize, f64)>> {
    let s = n_in as f64 / n_out as f64;
    (0..n_out)
        .map(|o| {
            if s >= 1.0 {
                let (a, b) = (o as f64 * s, (o + 1) as f64 * s);
                let first = a.floor() as usize;
                let last = (b.ceil() as usize).min(n_in);
                (first..last)
                    .filter_map(|i| {
                        let overlap = (b.min(i as f64 + 1.0) - a.max(i as f64)).max(0.0);
                        (overlap > 0.0).then_some((i, overlap / s))
                    })
                    .collect()
            } else {
                let c = ((o as f64 + 0.5) * s - 0.5).clamp(0.0, (n_in - 1) as f64);
                let i0 = c.floor() as usize;
                let i1 = (i0 + 1).min(n_in - 1);
                let f = c - i0 as f64;
                if i1 == i0 || f == 0.0 {
                    vec![(i0, 1.0)]
                } else {
                    vec![(i0, 1.0 - f), (i1, f)]
                }
            }
        })
        .collect()
}

/// What to keep of a texture's values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quantisation {
    /// Keep the linear `f32` values unchanged (the caller may store them as
    /// 16-bit floats, whose 11-bit mantissa holds a 12-bit sensor's codes
    /// near full scale to within half a code).
    Float,
    /// 8 bits of the sensor code: `code = round(value × (2^bit_depth − 1))`,
    /// then `min(code >> shift, 255)`. For a 12-bit sensor `shift: 2` keeps
    /// the central 8 bits (bits 2..=9) as in the seed: codes ≥ 1020
    /// saturate to 255 (never wrap); `shift: 4` keeps the top 8 bits.
    Bits8 { shift: u8 },
}

/// Applies `q` to a texture whose values are linear in `[0, 1]` of a
/// `bit_depth`-bit sensor. `Bits8` returns 8-bit codes as `code / 255`, so
/// writing the result with
/// [`write_png`](crate::image_io::write_png)`(…, PngDepth::Eight)` stores
/// exactly the codes ([`codes8`] reads them back). Values outside `[0, 1]`
/// are clamped and non-finite ones read as 0.
pub fn quantise(texture: &Image, bit_depth: u8, q: Quantisation) -> Result<Image, RectifyError> {
    check_image(texture)?;
    if !(1..=16).contains(&bit_depth) {
        return Err(RectifyError::InvalidInput(format!(
            "bit depth {bit_depth} (1..=16)"
        )));
    }
    match q {
        Quantisation::Float => Ok(texture.clone()),
        Quantisation::Bits8 { shift } => {
            if shift >= bit_depth {
                return Err(RectifyError::InvalidInput(format!(
                    "shift {shift} leaves no bits of a {bit_depth}-bit value"
                )));
            }
            let full = f64::from((1u32 << bit_depth) - 1);
            let data = texture
                .data
                .par_iter()
                .map(|&v| {
                    let v = if v.is_finite() {
                        f64::from(v).clamp(0.0, 1.0)
                    } else {
                        0.0
                    };
                    let code = (v * full).round() as u32;
                    f32::from((code >> shift).min(255) as u8) / 255.0
                })
                .collect();
            Ok(Image {
                width: texture.width,
                height: texture.height,
                channels: texture.channels,
                data,
            })
        }
    }
}

/// The 8-bit codes of a [`Quantisation::Bits8`] result.
pub fn codes8(texture: &Image) -> Vec<u8> {
    texture
        .data
        .iter()
        .map(|&v| {
            let v = if v.is_finite() {
                v.clamp(0.0, 1.0)
            } else {
                0.0
            };
            (v * 255.0).round() as u8
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resample_weights_sum_to_one() {
        for (n_in, n_out) in [(1024, 256), (550, 256), (10, 4), (2, 7), (5, 5)] {
            for taps in resample_weights(n_in, n_out) {
                let s: f64 = taps.iter().map(|t| t.1).sum();
                assert!((s - 1.0).abs() < 1e-12, "{n_in}->{n_out}: {s}");
                assert!(taps.iter().all(|&(i, w)| i < n_in && w > 0.0));
            }
        }
    }

    #[test]
    fn general_position_needs_four_points_without_collinear_triples() {
        let square = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
        assert!(general_position(&square));
        assert!(!general_position(&square[..3]));
        let line_plus_one = [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.0, 1.0]];
        assert!(!general_position(&line_plus_one));
        let mut more = line_plus_one.to_vec();
        more.push([2.0, 1.0]);
        assert!(general_position(&more));
    }

    #[test]
    fn solve8_solves_and_refuses_singular_systems() {
        let mut m = [[0.0; 8]; 8];
        for (i, row) in m.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = 1.0 / (1.0 + i as f64 + j as f64) + if i == j { 1.0 } else { 0.0 };
            }
        }
        let x: [f64; 8] = std::array::from_fn(|i| i as f64 - 3.5);
        let b: [f64; 8] = std::array::from_fn(|i| (0..8).map(|j| m[i][j] * x[j]).sum());
        let got = solve8(m, b).unwrap();
        for (g, w) in got.iter().zip(x) {
            assert!((g - w).abs() < 1e-9);
        }
        assert!(solve8([[0.0; 8]; 8], b).is_none());
    }

    #[test]
    fn disc_centroid_is_subpixel_accurate() {
        // A supersampled disc of radius 5 px at sub-pixel offsets.
        for (cx, cy) in [(30.0, 30.0), (30.3, 29.7), (31.77, 28.21)] {
            let (w, h) = (64, 60);
            let mut img = Image::new(w, h, 1);
            for y in 0..h {
                for x in 0..w {
                    let mut s = 0.0;
                    for a in 0..8 {
                        for b in 0..8 {
                            let px = x as f64 + (a as f64 + 0.5) / 8.0;
                            let py = y as f64 + (b as f64 + 0.5) / 8.0;
                            if (px - cx).hypot(py - cy) <= 5.0 {
                                s += 1.0;
                            }
                        }
                    }
                    img.set(x, y, 0, (0.05 + 0.7 * s / 64.0) as f32);
                }
            }
            let found = detect_markers(
                &img,
                &[Some([cx + 6.0, cy - 4.0])],
                10.0,
                &DetectOptions::default(),
            )
            .unwrap();
            let d = found[0].unwrap();
            let e = (d.centre_px[0] - cx).hypot(d.centre_px[1] - cy);
            assert!(e < 0.02, "({cx}, {cy}): {:?} error {e}", d.centre_px);
            assert!(
                (d.area_px - 78.5).abs() < 8.0 && d.elongation < 1.1,
                "{d:?}"
            );
        }
    }
}
