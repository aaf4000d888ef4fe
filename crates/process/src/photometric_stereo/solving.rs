//! Solving.

use super::*;

/// Solves a loaded dataset.
pub fn solve(dataset: &PsDataset, opts: &PsOptions) -> Result<PsResult, PsError> {
    if dataset.image_names.len() != dataset.images.len() {
        return Err(PsError::InvalidInput {
            origin: dataset.lights_origin.clone(),
            reason: format!(
                "{} image names for {} images",
                dataset.image_names.len(),
                dataset.images.len()
            ),
        });
    }
    solve_core(
        &dataset.images,
        &dataset.image_names,
        &dataset.lights,
        dataset.intensities.as_deref(),
        dataset.mask.as_deref(),
        &dataset.lights_origin,
        opts,
    )
}

/// Solves images already in memory (e.g. frames of a rigd run). `lights`
/// need not be unit length; `mask` is row-major, `true` = solve.
pub fn solve_images(
    images: &[Image],
    lights: &[[f64; 3]],
    mask: Option<&[bool]>,
    opts: &PsOptions,
) -> Result<PsResult, PsError> {
    let names: Vec<String> = (0..images.len()).map(|i| format!("image #{i}")).collect();
    solve_core(images, &names, lights, None, mask, "light directions", opts)
}

/// Per-pixel outcome before assembly.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum Status {
    Valid,
    Masked,
    Dark,
    Saturated,
    FacingAway,
}

#[derive(Clone, Copy)]
pub(super) struct PixelOut {
    pub(super) normal: [f64; 3],
    pub(super) albedo: [f32; 3],
    pub(super) status: Status,
    pub(super) residual: f64,
    pub(super) fallback: bool,
    pub(super) rejected: Rejections,
}

#[derive(Clone, Copy, Default)]
pub(super) struct Rejections {
    pub(super) shadow: u32,
    pub(super) specular: u32,
    pub(super) saturated: u32,
}

/// Everything a pixel solve needs that does not change between pixels.
pub(super) struct Solver<'a> {
    pub(super) images: &'a [Image],
    pub(super) lights: Vec<[f64; 3]>,
    /// 3×N: pseudo-inverse (or inverse for N = 3) of the light matrix.
    pub(super) pinv: Vec<[f64; 3]>,
    /// Per image, the reciprocal intensity of each channel.
    pub(super) inv_intensity: Vec<[f64; 3]>,
    pub(super) channels: usize,
    pub(super) opts: PsOptions<'a>,
}

/// Scratch buffers reused across the pixels of a row.
pub(super) struct Scratch {
    pub(super) raw: Vec<f64>,
    pub(super) corrected: Vec<f64>,
    pub(super) lum: Vec<f64>,
    pub(super) raw_lum: Vec<f64>,
    pub(super) raw_max: Vec<f32>,
    pub(super) used: Vec<bool>,
    pub(super) sort: Vec<f64>,
    pub(super) ranked: Vec<(f64, f64, usize)>,
}

pub(super) fn solve_core(
    images: &[Image],
    names: &[String],
    lights: &[[f64; 3]],
    intensities: Option<&[[f64; 3]]>,
    mask: Option<&[bool]>,
    lights_origin: &str,
    opts: &PsOptions,
) -> Result<PsResult, PsError> {
    check_images(images, names)?;
    let invalid = |reason: String| PsError::InvalidInput {
        origin: lights_origin.to_string(),
        reason,
    };
    if lights.len() != images.len() {
        return Err(invalid(format!(
            "{} light directions for {} images",
            lights.len(),
            images.len()
        )));
    }
    if lights.len() < 3 {
        return Err(PsError::TooFewLights {
            origin: lights_origin.to_string(),
            count: lights.len(),
        });
    }
    let mut unit = Vec::with_capacity(lights.len());
    for (i, l) in lights.iter().enumerate() {
        let norm = dot(*l, *l).sqrt();
        if !(norm.is_finite() && norm > 0.0) {
            return Err(invalid(format!(
                "light {} ({}) is zero or not finite",
                i + 1,
                names[i]
            )));
        }
        unit.push([l[0] / norm, l[1] / norm, l[2] / norm]);
    }
    let (width, height, channels) = (images[0].width, images[0].height, images[0].channels);
    if let Some(m) = mask {
        if m.len() != width * height {
            return Err(PsError::MaskMismatch {
                mask: "mask".into(),
                expected: format!("{} pixels", width * height),
                found: format!("{} values", m.len()),
            });
        }
    }
    let inv_intensity = match intensities {
        Some(table) => {
            if table.len() != images.len() {
                return Err(invalid(format!(
                    "{} intensities for {} images",
                    table.len(),
                    images.len()
                )));
            }
            let mut inv = Vec::with_capacity(table.len());
            for (i, t) in table.iter().enumerate() {
                if t.iter().any(|&v| !(v.is_finite() && v > 0.0)) {
                    return Err(invalid(format!(
                        "intensity of {} is not positive",
                        names[i]
                    )));
                }
                inv.push(if channels == 1 {
                    [1.0 / dot(*t, LUMA); 3]
                } else {
                    [1.0 / t[0], 1.0 / t[1], 1.0 / t[2]]
                });
            }
            inv
        }
        None => vec![[1.0; 3]; images.len()],
    };

    let (condition, pinv) = light_matrix_inverse(&unit, lights_origin)?;
    if condition.is_nan() || condition > opts.max_condition {
        return Err(PsError::IllConditioned {
            origin: lights_origin.to_string(),
            condition,
            max: opts.max_condition,
        });
    }

    let solver = Solver {
        images,
        lights: unit,
        pinv,
        inv_intensity,
        channels,
        opts: *opts,
    };
    let rows_done = AtomicUsize::new(0);
    let rows: Vec<Vec<PixelOut>> = (0..height)
        .into_par_iter()
        .map(|y| {
            let mut scratch = Scratch::new(images.len(), channels);
            let row = (0..width)
                .map(|x| {
                    let index = y * width + x;
                    let enabled = mask.is_none_or(|m| m[index]);
                    solver.pixel(index, enabled, &mut scratch)
                })
                .collect();
            let done = rows_done.fetch_add(1, Ordering::Relaxed) + 1;
            if let Some(progress) = opts.progress {
                progress(done, height);
            }
            row
        })
        .collect();

    let n_pixels = width * height;
    let albedo_channels = channels;
    let mut result = PsResult {
        width,
        height,
        normals: Vec::with_capacity(n_pixels),
        albedo: Vec::with_capacity(n_pixels * albedo_channels),
        albedo_channels,
        p: Vec::with_capacity(n_pixels),
        q: Vec::with_capacity(n_pixels),
        height_map: Vec::new(),
        valid: Vec::with_capacity(n_pixels),
        report: PsReport {
            robust: opts.robust,
            width,
            height,
            channels,
            images: names.to_vec(),
            lights: solver.lights.clone(),
            intensities: intensities.map(<[_]>::to_vec),
            condition_number: condition,
            mean_residual: 0.0,
            pixels_total: n_pixels,
            pixels_valid: 0,
            pixels_masked: 0,
            pixels_dark: 0,
            pixels_saturated: 0,
            pixels_facing_away: 0,
            pixels_fallback: 0,
            samples_rejected_shadow: 0,
            samples_rejected_specular: 0,
            samples_rejected_saturated: 0,
        },
    };
    let mut residual_sum = 0.0;
    for px in rows.iter().flatten() {
        let report = &mut result.report;
        match px.status {
            Status::Valid => {
                report.pixels_valid += 1;
                residual_sum += px.residual;
            }
            Status::Masked => report.pixels_masked += 1,
            Status::Dark => report.pixels_dark += 1,
            Status::Saturated => report.pixels_saturated += 1,
            Status::FacingAway => report.pixels_facing_away += 1,
        }
        report.pixels_fallback += usize::from(px.fallback);
        report.samples_rejected_shadow += u64::from(px.rejected.shadow);
        report.samples_rejected_specular += u64::from(px.rejected.specular);
        report.samples_rejected_saturated += u64::from(px.rejected.saturated);
        let n = px.normal;
        let nz = n[2].max(MIN_NZ);
        result.normals.push([n[0] as f32, n[1] as f32, n[2] as f32]);
        result.p.push((-n[0] / nz) as f32);
        result.q.push((-n[1] / nz) as f32);
        result
            .albedo
            .extend_from_slice(&px.albedo[..albedo_channels]);
        result.valid.push(px.status == Status::Valid);
    }
    if result.report.pixels_valid > 0 {
        result.report.mean_residual = residual_sum / result.report.pixels_valid as f64;
    }
    result.height_map = integrate_frankot_chellappa(&result.p, &result.q, width, height)?;
    Ok(result)
}

impl Scratch {
    pub(super) fn new(n: usize, channels: usize) -> Self {
        Scratch {
            raw: vec![0.0; n * channels],
            corrected: vec![0.0; n * channels],
            lum: vec![0.0; n],
            raw_lum: vec![0.0; n],
            raw_max: vec![0.0; n],
            used: vec![false; n],
            sort: Vec::with_capacity(n),
            ranked: Vec::with_capacity(n),
        }
    }
}

pub(super) const INVALID_NORMAL: [f64; 3] = [0.0, 0.0, 1.0];

impl Solver<'_> {
    pub(super) fn invalid(status: Status) -> PixelOut {
        PixelOut {
            normal: INVALID_NORMAL,
            albedo: [0.0; 3],
            status,
            residual: 0.0,
            fallback: false,
            rejected: Rejections::default(),
        }
    }

    pub(super) fn pixel(&self, index: usize, enabled: bool, s: &mut Scratch) -> PixelOut {
        if !enabled {
            return Self::invalid(Status::Masked);
        }
        let ch = self.channels;
        let n = self.lights.len();
        for (i, image) in self.images.iter().enumerate() {
            let mut raw_max = 0.0f32;
            for c in 0..ch {
                let v = image.data[index * ch + c];
                let v = if v.is_finite() { v } else { 0.0 };
                raw_max = raw_max.max(v);
                s.raw[i * ch + c] = f64::from(v);
                s.corrected[i * ch + c] = f64::from(v) * self.inv_intensity[i][c];
            }
            s.raw_max[i] = raw_max;
            if ch == 1 {
                s.lum[i] = s.corrected[i];
                s.raw_lum[i] = s.raw[i];
            } else {
                s.lum[i] = dot(
                    [
                        s.corrected[3 * i],
                        s.corrected[3 * i + 1],
                        s.corrected[3 * i + 2],
                    ],
                    LUMA,
                );
                s.raw_lum[i] = dot([s.raw[3 * i], s.raw[3 * i + 1], s.raw[3 * i + 2]], LUMA);
            }
        }
        if s.raw_max.iter().all(|&v| v <= 0.0) {
            return Self::invalid(Status::Dark);
        }
        if s.raw_max.iter().all(|&v| v >= self.opts.saturation_level) {
            return Self::invalid(Status::Saturated);
        }

        let mut rejected = Rejections::default();
        let mut fallback = false;
        let robust = if self.opts.robust {
            self.robust_fit(s, &mut rejected)
        } else {
            None
        };
        let t = match robust {
            Some(t) => t,
            None => {
                fallback = self.opts.robust;
                rejected = Rejections::default();
                s.used.iter_mut().for_each(|u| *u = true);
                let mut t = [0.0; 3];
                for (row, lum) in self.pinv.iter().zip(&s.lum) {
                    for k in 0..3 {
                        t[k] += row[k] * lum;
                    }
                }
                t
            }
        };
        let rho = dot(t, t).sqrt();
        if !(rho > 1e-12 && rho.is_finite()) {
            return Self::invalid(Status::Dark);
        }
        if t[2] <= 0.0 {
            return Self::invalid(Status::FacingAway);
        }
        let normal = [t[0] / rho, t[1] / rho, t[2] / rho];

        let (mut ss, mut res2, mut used) = (0.0, 0.0, 0usize);
        let mut sc = [0.0f64; 3];
        for i in (0..n).filter(|&i| s.used[i]) {
            let shading = dot(self.lights[i], normal);
            ss += shading * shading;
            for (c, acc) in sc.iter_mut().enumerate().take(ch) {
                *acc += shading * s.corrected[i * ch + c];
            }
            let r = s.lum[i] - rho * shading;
            res2 += r * r;
            used += 1;
        }
        let mut albedo = [0.0f32; 3];
        if ss > 0.0 {
            for c in 0..ch {
                albedo[c] = (sc[c] / ss).max(0.0) as f32;
            }
        }
        PixelOut {
            normal,
            albedo,
            status: Status::Valid,
            residual: (res2 / used.max(1) as f64).sqrt(),
            fallback,
            rejected,
        }
    }

    /// Robust fit (module doc); `None` means "use the plain solution".
    /// Leaves the chosen samples in `s.used`.
    pub(super) fn robust_fit(
        &self,
        s: &mut Scratch,
        rejected: &mut Rejections,
    ) -> Option<[f64; 3]> {
        let n = self.lights.len();
        let opts = &self.opts;
        for use_relative in [true, false] {
            let mut r = Rejections::default();
            for i in 0..n {
                s.used[i] = s.raw_max[i] < opts.saturation_level;
                r.saturated += u32::from(!s.used[i]);
            }
            s.sort.clear();
            s.sort
                .extend((0..n).filter(|&i| s.used[i]).map(|i| s.lum[i]));
            let median = median(&mut s.sort);
            for i in 0..n {
                let dark = s.raw_lum[i] <= opts.dark_absolute
                    || (use_relative && s.lum[i] < opts.dark_relative * median);
                if s.used[i] && dark {
                    s.used[i] = false;
                    r.shadow += 1;
                }
            }
            let count = s.used.iter().filter(|&&u| u).count();
            if count < 3 || self.subset_condition(&s.used, None) > opts.max_pixel_condition {
                continue;
            }
            let t = self.refit_loop(s, &mut r)?;
            *rejected = r;
            return Some(t);
        }
        None
    }

    pub(super) fn refit_loop(&self, s: &mut Scratch, r: &mut Rejections) -> Option<[f64; 3]> {
        let n = self.lights.len();
        let opts = &self.opts;
        loop {
            let mut gram = [[0.0; 3]; 3];
            let mut rhs = [0.0; 3];
            let mut count = 0;
            for i in (0..n).filter(|&i| s.used[i]) {
                let l = self.lights[i];
                add_outer(&mut gram, l, 1.0);
                for k in 0..3 {
                    rhs[k] += l[k] * s.lum[i];
                }
                count += 1;
            }
            let inverse = invert3(&gram)?;
            let t = mat_vec(&inverse, rhs);
            if count <= 3 {
                return Some(t);
            }
            s.sort.clear();
            s.ranked.clear();
            for i in (0..n).filter(|&i| s.used[i]) {
                let l = self.lights[i];
                let residual = s.lum[i] - dot(l, t);
                let leverage = dot(l, mat_vec(&inverse, l));
                let studentised = residual / (1.0 - leverage).max(1e-12).sqrt();
                s.sort.push(residual.abs());
                s.ranked.push((studentised, s.lum[i], i));
            }
            let scale = (opts.residual_sigmas * 1.4826 * median(&mut s.sort))
                .max(opts.residual_tolerance * dot(t, t).sqrt());
            let largest = s.ranked.iter().map(|e| e.0.abs()).fold(0.0, f64::max);
            let tie = 1e-9 * largest;
            // Largest |studentised residual| first; near-ties to the brighter sample.
            // Comparators must be total orders (sort may panic otherwise), so
            // the near-tie group is re-sorted separately rather than with a
            // tolerance inside one comparator.
            s.ranked.sort_by(|a, b| b.0.abs().total_cmp(&a.0.abs()));
            let tied = s
                .ranked
                .iter()
                .take_while(|e| e.0.abs() >= largest - tie)
                .count();
            s.ranked[..tied].sort_by(|a, b| b.1.total_cmp(&a.1));
            let mut removed = false;
            for k in 0..s.ranked.len() {
                let (studentised, _, i) = s.ranked[k];
                if studentised.abs() <= scale {
                    break;
                }
                if self.subset_condition(&s.used, Some(i)) <= opts.max_pixel_condition {
                    s.used[i] = false;
                    if studentised > 0.0 {
                        r.specular += 1;
                    } else {
                        r.shadow += 1;
                    }
                    removed = true;
                    break;
                }
            }
            if !removed {
                return Some(t);
            }
        }
    }

    /// Condition number of the used lights, optionally without `skip`.
    pub(super) fn subset_condition(&self, used: &[bool], skip: Option<usize>) -> f64 {
        let mut gram = [[0.0; 3]; 3];
        let mut count = 0;
        for (i, l) in self.lights.iter().enumerate() {
            if used[i] && skip != Some(i) {
                add_outer(&mut gram, *l, 1.0);
                count += 1;
            }
        }
        if count < 3 {
            return f64::INFINITY;
        }
        let eig = symmetric_eigenvalues(gram);
        let (min, max) = eig.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &e| {
            (lo.min(e), hi.max(e))
        });
        if min <= 0.0 {
            f64::INFINITY
        } else {
            (max / min).sqrt()
        }
    }
}

/// Condition number of the N×3 light matrix and its (pseudo-)inverse as N
/// rows of 3 (row `i` holds column `i` of the 3×N inverse).
pub(super) fn light_matrix_inverse(
    lights: &[[f64; 3]],
    origin: &str,
) -> Result<(f64, Vec<[f64; 3]>), PsError> {
    let matrix = faer::Mat::<f64>::from_fn(lights.len(), 3, |i, j| lights[i][j]);
    let svd_err = |e: faer::linalg::svd::SvdError| PsError::Svd {
        origin: origin.to_string(),
        reason: format!("{e:?}"),
    };
    let svd = matrix.thin_svd().map_err(svd_err)?;
    let sigma = svd.S().column_vector();
    let (max, min) = (sigma[0], sigma[2]);
    let condition = if min > 0.0 { max / min } else { f64::INFINITY };
    if !condition.is_finite() {
        return Ok((f64::INFINITY, Vec::new()));
    }
    let pinv: Vec<[f64; 3]> = if lights.len() == 3 {
        let m = [lights[0], lights[1], lights[2]];
        let Some(inv) = invert3(&m) else {
            return Ok((f64::INFINITY, Vec::new()));
        };
        (0..3).map(|i| [inv[0][i], inv[1][i], inv[2][i]]).collect()
    } else {
        let p = svd.pseudoinverse();
        (0..lights.len())
            .map(|i| [p[(0, i)], p[(1, i)], p[(2, i)]])
            .collect()
    };
    Ok((condition, pinv))
}

pub(super) fn add_outer(m: &mut [[f64; 3]; 3], v: [f64; 3], w: f64) {
    for r in 0..3 {
        for c in 0..3 {
            m[r][c] += w * v[r] * v[c];
        }
    }
}

pub(super) fn mat_vec(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [dot(m[0], v), dot(m[1], v), dot(m[2], v)]
}

/// Inverse by cofactors; `None` if singular.
pub(super) fn invert3(m: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let c = |r: usize, k: usize| {
        let (r1, r2) = ((r + 1) % 3, (r + 2) % 3);
        let (k1, k2) = ((k + 1) % 3, (k + 2) % 3);
        m[r1][k1] * m[r2][k2] - m[r1][k2] * m[r2][k1]
    };
    let det = m[0][0] * c(0, 0) + m[0][1] * c(0, 1) + m[0][2] * c(0, 2);
    if !(det.abs() > f64::MIN_POSITIVE && det.is_finite()) {
        return None;
    }
    let mut inv = [[0.0; 3]; 3];
    for (r, row) in inv.iter_mut().enumerate() {
        for (k, v) in row.iter_mut().enumerate() {
            *v = c(k, r) / det;
        }
    }
    Some(inv)
}

/// Eigenvalues of a symmetric 3×3 matrix by cyclic Jacobi rotations.
pub(super) fn symmetric_eigenvalues(mut a: [[f64; 3]; 3]) -> [f64; 3] {
    for _ in 0..50 {
        let off = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
        let diag = a[0][0] * a[0][0] + a[1][1] * a[1][1] + a[2][2] * a[2][2];
        if off <= 1e-30 * diag || off == 0.0 {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for row in a.iter_mut() {
                let (kp, kq) = (row[p], row[q]);
                row[p] = c * kp - s * kq;
                row[q] = s * kp + c * kq;
            }
            let (row_p, row_q) = (a[p], a[q]);
            a[p] = std::array::from_fn(|k| c * row_p[k] - s * row_q[k]);
            a[q] = std::array::from_fn(|k| s * row_p[k] + c * row_q[k]);
        }
    }
    [a[0][0], a[1][1], a[2][2]]
}

/// Median of `values` (reordered in place); 0 when empty.
pub(super) fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    values.sort_by(f64::total_cmp);
    let mid = values.len() / 2;
    if values.len() % 2 == 1 {
        values[mid]
    } else {
        0.5 * (values[mid - 1] + values[mid])
    }
}
