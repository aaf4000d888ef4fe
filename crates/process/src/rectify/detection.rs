//! Detection.

use super::*;

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
pub(super) const LEVELS: [f32; 4] = [0.5, 0.3, 0.18, 0.1];

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
    detect_markers_of_polarity(image, predicted_px, &[], search_radius_px, opts)
}

/// [`detect_markers`] for markers of either polarity: where `dark[i]` is
/// true, marker `i` is a disc darker than the plate around it, found as a
/// bright one in its search window with the values turned over. Markers
/// beyond `dark`'s length are light.
pub fn detect_markers_of_polarity(
    image: &Image,
    predicted_px: &[Option<[f64; 2]>],
    dark: &[bool],
    search_radius_px: f64,
    opts: &DetectOptions,
) -> Result<Vec<Option<Detection>>, RectifyError> {
    detect_markers_where(image, predicted_px, dark, search_radius_px, opts, |_, _| {
        true
    })
}

/// [`detect_markers_of_polarity`] taking, for marker `i`, the nearest
/// acceptable blob for which `belongs(i, centre_px)` holds: the caller
/// knows what else the image shows near the marker (a border line, the
/// next marker) and can refuse a blob that lies nearer to that.
pub fn detect_markers_where(
    image: &Image,
    predicted_px: &[Option<[f64; 2]>],
    dark: &[bool],
    search_radius_px: f64,
    opts: &DetectOptions,
    belongs: impl Fn(usize, [f64; 2]) -> bool + Sync,
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
        .enumerate()
        .map(|(i, p)| {
            let p = (*p)?;
            if !(p[0].is_finite() && p[1].is_finite()) {
                return None;
            }
            let polarity = if dark.get(i).copied().unwrap_or(false) {
                Polarity::Dark
            } else {
                Polarity::Light
            };
            detect_one(
                &grey,
                [image.width, image.height],
                p,
                search_radius_px,
                opts,
                polarity,
                &|c| belongs(i, c),
            )
        })
        .collect())
}

/// One grey value per pixel (Rec. 709 luminance for RGB, the mean for other
/// channel counts); non-finite samples read as 0.
pub(super) fn luminance(image: &Image) -> Vec<f32> {
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

pub(super) struct Window {
    pub(super) x0: usize,
    pub(super) y0: usize,
    pub(super) w: usize,
    pub(super) h: usize,
    pub(super) v: Vec<f32>,
    /// The window's dark level (10th percentile).
    pub(super) dark: f32,
    /// [`Window::plate_levels`], sorted out only when a blob needs them.
    plate: std::cell::OnceCell<[f32; 3]>,
}

impl Window {
    /// The window's 50th, 75th and 90th percentiles: the plate's level is
    /// one of them when the plate fills half, a quarter or a tenth of the
    /// window (the rest the floor past its edge, or shade).
    fn plate_levels(&self) -> [f32; 3] {
        *self.plate.get_or_init(|| {
            let mut sorted = self.v.clone();
            sorted.sort_unstable_by(f32::total_cmp);
            let at = |q: f64| sorted[((sorted.len() - 1) as f64 * q).round() as usize];
            [at(0.5), at(0.75), at(0.9)]
        })
    }
}

/// Whether a marker is lighter or darker than the plate around it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Polarity {
    Light,
    Dark,
}

pub(super) fn detect_one(
    grey: &[f32],
    [width, height]: [usize; 2],
    pred: [f64; 2],
    radius: f64,
    opts: &DetectOptions,
    polarity: Polarity,
    belongs: &dyn Fn([f64; 2]) -> bool,
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
    if polarity == Polarity::Dark {
        // A dark disc on a light plate is a light one on a dark plate once
        // the window's values are turned over.
        let top = v.iter().copied().fold(f32::MIN, f32::max);
        v.iter_mut().for_each(|x| *x = top - *x);
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
        plate: std::cell::OnceCell::new(),
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
                if dist <= radius
                    && best.as_ref().is_none_or(|(b, _)| dist < *b)
                    && belongs(d.centre_px)
                {
                    best = Some((dist, d));
                }
            }
        }
    }
    best.map(|(_, d)| d)
}

/// Calls `f` with the window indices of the 8 neighbours of `i`.
pub(super) fn for_neighbours(i: usize, w: usize, h: usize, mut f: impl FnMut(usize)) {
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

pub(super) struct Blob {
    pub(super) pixels: Vec<usize>,
    pub(super) touches_border: bool,
}

thread_local! {
    /// A window-sized mask per thread, all false between uses: a
    /// textured frame sends hundreds of candidate peaks through [`grow`]
    /// and [`rings`], and clearing a fresh window-sized mask for each was
    /// a visible share of a large frame's registration.
    static MASK: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Runs `f` with a zeroed mask of `len` entries; `f` returns the indices
/// it set, which are zeroed again afterwards.
fn with_mask<T>(len: usize, f: impl FnOnce(&mut [u8]) -> (T, Vec<usize>)) -> T {
    MASK.with(|m| {
        let mut mask = m.borrow_mut();
        if mask.len() < len {
            mask.resize(len, 0);
        }
        let (out, touched) = f(&mut mask[..len]);
        for i in touched {
            mask[i] = 0;
        }
        out
    })
}

/// The 8-connected region above `threshold` around `seed`, or `None` when it
/// grows beyond `max_pixels`.
pub(super) fn grow(win: &Window, seed: usize, threshold: f32, max_pixels: usize) -> Option<Blob> {
    let (w, h) = (win.w, win.h);
    with_mask(w * h, |inside| {
        let mut pixels = vec![seed];
        inside[seed] = 1;
        let mut touches_border = false;
        let mut overflow = false;
        let mut k = 0;
        while k < pixels.len() && !overflow {
            let i = pixels[k];
            k += 1;
            let (x, y) = (i % w, i / w);
            if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                touches_border = true;
            }
            for_neighbours(i, w, h, |j| {
                if win.v[j] > threshold && inside[j] == 0 {
                    inside[j] = 1;
                    pixels.push(j);
                    if pixels.len() > max_pixels {
                        overflow = true;
                    }
                }
            });
        }
        let blob = (!overflow).then(|| Blob {
            pixels: pixels.clone(),
            touches_border,
        });
        (blob, pixels)
    })
}

/// Pixels at chessboard distance 1 (`ring1`) and 2 (`ring2`) from the blob.
pub(super) fn rings(win: &Window, blob: &[usize]) -> (Vec<usize>, Vec<usize>) {
    const INSIDE: u8 = 1;
    const RING1: u8 = 2;
    const RING2: u8 = 3;
    with_mask(win.w * win.h, |mark| {
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
        let touched = blob.iter().chain(&r1).chain(&r2).copied().collect();
        ((r1, r2), touched)
    })
}

pub(super) fn median_f32(mut v: Vec<f32>) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    let k = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(k, f32::total_cmp);
    Some(*m)
}

/// Largest spread (90th minus 10th percentile) of a blob's surround, as a
/// fraction of its contrast, for the surround to count as a uniform
/// plate: a marker on a mid-grey plate is isolated although its surround
/// is far above the window's dark level (the floor past the plate's
/// edge); a speck of a textured sample's surround is not uniform.
const UNIFORM_SURROUND: f64 = 0.25;

/// How a blob is told from a bright speck of something larger.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Isolation {
    /// Its surround is near the window's dark level: a light marker on a
    /// dark plate.
    DarkSurround,
    /// Its surround is uniform: a light marker on a plate of any grey.
    UniformSurround,
}

pub(super) fn analyse_blob(win: &Window, peak: usize, opts: &DetectOptions) -> Option<Detection> {
    analyse_blob_as(win, peak, opts, win.dark, Isolation::DarkSurround).or_else(|| {
        // On a plate brighter than the window's darkest part, the first
        // threshold (midway from the dark level) floods the plate: grow
        // from the plate's level instead, whichever share of the window
        // the plate covers.
        win.plate_levels()
            .iter()
            .filter(|&&level| level > win.dark && level < win.v[peak])
            .find_map(|&level| analyse_blob_as(win, peak, opts, level, Isolation::UniformSurround))
    })
}

fn analyse_blob_as(
    win: &Window,
    peak: usize,
    opts: &DetectOptions,
    first_level: f32,
    isolation: Isolation,
) -> Option<Detection> {
    let pv = win.v[peak];
    let max_pixels = opts.max_area_px.min(1e9) as usize;
    // Threshold midway between the background and the peak: first with
    // `first_level`, then with the blob's own surround.
    let mut bg = first_level;
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
    let isolated = match isolation {
        Isolation::DarkSurround => {
            let surround_mean =
                ring2.iter().map(|&i| f64::from(win.v[i])).sum::<f64>() / ring2.len() as f64;
            let full = f64::from(pv - win.dark);
            full > 0.0 && (surround_mean - f64::from(win.dark)) <= opts.max_surround * full
        }
        Isolation::UniformSurround => {
            let mut ring: Vec<f32> = ring2.iter().map(|&i| win.v[i]).collect();
            ring.sort_by(f32::total_cmp);
            let at = |q: f64| f64::from(ring[((ring.len() - 1) as f64 * q).round() as usize]);
            at(0.9) - at(0.1) <= UNIFORM_SURROUND * contrast
        }
    };
    if !isolated {
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A mid-grey plate (0.5) whose left edge gives onto a black floor,
    /// with a light disc 15 px from that edge, a dark disc, and beside the
    /// floor a patch of noisy texture holding a bright speck.
    fn grey_plate() -> Image {
        let (w, h) = (200, 200);
        let mut img = Image::new(w, h, 1);
        let mut seed = 7u64;
        let mut noise = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as f32 / (1u64 << 31) as f32
        };
        for y in 0..h {
            for x in 0..w {
                let (fx, fy) = (x as f64 + 0.5, y as f64 + 0.5);
                let disc = |cx: f64, cy: f64| (fx - cx).hypot(fy - cy) <= 5.0;
                img.data[y * w + x] = if x < 40 {
                    0.0
                } else if disc(55.0, 60.0) {
                    0.95
                } else if disc(150.0, 60.0) {
                    0.02
                } else if y >= 120 && (40..100).contains(&x) {
                    if (54..56).contains(&x) && (159..161).contains(&y) {
                        0.95
                    } else {
                        0.3 + 0.4 * noise()
                    }
                } else {
                    0.5
                };
            }
        }
        img
    }

    #[test]
    fn markers_of_either_polarity_are_found_on_a_grey_plate_and_a_speck_is_not() {
        let img = grey_plate();
        let predicted = [Some([55.0, 60.0]), Some([150.0, 60.0]), Some([55.0, 160.0])];
        let found = detect_markers_of_polarity(
            &img,
            &predicted,
            &[false, true, false],
            12.0,
            &DetectOptions {
                max_area_px: 400.0,
                ..Default::default()
            },
        )
        .expect("valid input");
        for (k, want) in [(0, [55.0, 60.0]), (1, [150.0, 60.0])] {
            let d = found[k].unwrap_or_else(|| panic!("marker {k} not found"));
            let err = (d.centre_px[0] - want[0]).hypot(d.centre_px[1] - want[1]);
            assert!(err < 0.1, "marker {k} at {:?}", d.centre_px);
        }
        assert!(found[2].is_none(), "a speck of texture: {:?}", found[2]);
        // Taken as light, the dark disc is not found.
        let light =
            detect_markers(&img, &predicted[1..2], 12.0, &Default::default()).expect("valid input");
        assert!(light[0].is_none(), "{:?}", light[0]);
    }
}
