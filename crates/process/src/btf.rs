//! BTF compression by per-view-slot PCA (Sattler et al., §4.1) and reconstruction
//! at arbitrary light and view directions (§4.2, eq. 3 and 5).
//!
//! # Model
//!
//! For one view slot j, the normtextures N_ij under the measured lights
//! i = 1…n are vectors of `width · height · channels` values (texel-major,
//! row-major texels, channels interleaved: r₁₁ g₁₁ b₁₁ r₁₂ …, as X_ij in
//! Sattler et al.). The slot matrix has one column per light. Per value (row) the mean
//! over lights is removed and stored as the *mean texture* M_j; the centred
//! matrix is factored, U Σ Vᵀ, and the first C components are kept (through
//! the small Gram matrix or a thin SVD, whichever is cheaper for the shape:
//! [`PcaRoute`]):
//!
//! * eigen-textures B_kj = column k of U: unit L2 norm, mutually orthogonal;
//!   sign chosen so the entry of largest magnitude is positive;
//! * weights p_ikj = σ_k V_ik, i.e. the projection of the centred N_ij onto
//!   B_kj;
//!
//! so that N_ij ≈ M_j + Σ_k p_ikj B_kj. The mean texture is Sattler et al.'s B_0j
//! with γ_0j = 1 (eq. 4) and makes the kept subspace the affine one of §4.1.
//!
//! C is clamped to min(C, lights, values); components whose singular value is
//! below what rounding the input to f32 can produce (rank-deficient slots,
//! e.g. constant images or one light) are stored as zero eigen-textures with
//! zero weights, never NaN.
//!
//! All singular values are kept (not only C), so the RMS error of a rank-c
//! approximation for any c is known without reconstructing: it is
//! sqrt(Σ_{k>c} σ_k² / (values · lights)), exactly the RMS over the slot of
//! (original − rank-c reconstruction), up to f32 rounding of stored factors.
//!
//! # On-disk format (version 1)
//!
//! A directory holding:
//!
//! * `btf.json`, UTF-8 JSON:
//!   ```text
//!   {
//!     "format": "rigd-btf-pca",          // fixed
//!     "version": 1,
//!     "width": W, "height": H,
//!     "channels": 1 | 3,
//!     "components": C,                    // stored per slot, ≤ lights, ≤ W·H·channels
//!     "value_encoding": "f32le",          // the only encoding of version 1
//!     "light_directions": [{"theta_deg": θ, "phi_deg": φ}, …],  // light index order
//!     "view_directions":  [{"theta_deg": θ, "phi_deg": φ}, …],  // slot order
//!     "slots": [{"file": "slot_000.bin",
//!                "singular_values": [σ_1 ≥ σ_2 ≥ …]}, …]       // min(lights, W·H·channels) each
//!   }
//!   ```
//! * per view slot j, `slot_{j:03}.bin` (the name is listed in `btf.json`; a
//!   plain file name in the same directory): little-endian IEEE-754 f32, no
//!   header, in this order:
//!   1. the mean texture: W·H·channels values;
//!   2. C eigen-textures, component-major, each W·H·channels values;
//!   3. the weights: lights × C values, light-major (all C weights of light 0,
//!      then light 1, …).
//!
//!   The file size is therefore exactly 4 · (W·H·ch · (1 + C) + lights · C)
//!   bytes; readers reject any other size and non-finite values.
//!
//! Every file is written to a temporary name in the directory, synced and
//! renamed, and `btf.json` is written last, so a directory with a `btf.json`
//! is complete.

use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use faer::Mat;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::directions::{Direction, DirectionError, DirectionTable, Interpolation};

/// Value of `format` in `btf.json`.
pub const FORMAT_NAME: &str = "rigd-btf-pca";
/// Value of `version` in `btf.json` written by this module.
pub const FORMAT_VERSION: u32 = 1;
/// The header file of a stored BTF.
pub const HEADER_FILE: &str = "btf.json";
/// The only value encoding of format version 1.
pub const VALUE_ENCODING: &str = "f32le";
/// Largest component count the error report goes up to (Sattler et al. keep 16).
pub const MAX_REPORTED_COMPONENTS: usize = 32;

/// Errors of BTF compression, reconstruction and the on-disk store.
#[derive(Debug, thiserror::Error)]
pub enum BtfError {
    /// A [`TextureShape`] with a zero side, a channel count other than 1 or 3,
    /// or too many values.
    #[error("texture shape {width}×{height}×{channels} is invalid: {why}")]
    Shape {
        /// Requested width, texels.
        width: usize,
        /// Requested height, texels.
        height: usize,
        /// Requested values per texel.
        channels: usize,
        /// Which rule the shape breaks.
        why: &'static str,
    },
    /// [`compress_slot`] was given no images.
    #[error("a view slot needs at least one image")]
    NoImages,
    /// Zero PCA components were requested.
    #[error("at least one PCA component is required")]
    NoComponents,
    /// An image's value count differs from `width · height · channels`.
    #[error("image {image} has {actual} values, expected {expected} (width · height · channels)")]
    ImageSize {
        /// Index of the image (its light) in the slot.
        image: usize,
        /// Values the texture shape needs.
        expected: usize,
        /// Values the image has.
        actual: usize,
    },
    /// An input image holds NaN or infinity.
    #[error("image {image} has a non-finite value at {value_index}")]
    NonFiniteValue {
        /// Index of the image (its light) in the slot.
        image: usize,
        /// Index of the first non-finite value in the image.
        value_index: usize,
    },
    /// faer's SVD or eigen-decomposition of a slot matrix did not converge.
    #[error("the factorisation of a view slot did not converge")]
    SvdNoConvergence,
    /// A light or view direction table is invalid, or a query direction is
    /// not finite.
    #[error(transparent)]
    Direction(#[from] DirectionError),
    /// A slot disagrees with the store's texture size, light count or component
    /// count, or its loader returned a different number of images than lights.
    #[error("view slot {slot}: {why}")]
    SlotMismatch {
        /// Index of the offending view slot.
        slot: usize,
        /// What does not match.
        why: String,
    },
    /// The number of slots differs from the number of view directions.
    #[error("{slots} slots for {views} view directions")]
    SlotCount {
        /// Slots given.
        slots: usize,
        /// View directions in the table.
        views: usize,
    },
    /// A light index is beyond the slot's measured lights.
    #[error("light index {light} out of range ({lights} lights)")]
    LightIndex {
        /// The requested light index.
        light: usize,
        /// Measured lights in the slot.
        lights: usize,
    },
    /// A view-slot index is beyond the store's slots.
    #[error("view slot {slot} out of range ({slots} slots)")]
    SlotIndex {
        /// The requested slot index.
        slot: usize,
        /// Slots in the store.
        slots: usize,
    },
    /// Creating the directory, or reading or writing a file of the store, failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or directory concerned.
        path: PathBuf,
        /// The underlying I/O error.
        source: io::Error,
    },
    /// `btf.json` or a slot file is malformed: bad JSON, an unknown format,
    /// version or encoding, inconsistent counts, a wrong file size or a
    /// non-finite value.
    #[error("{}: {why}", path.display())]
    Format {
        /// The file concerned.
        path: PathBuf,
        /// What is wrong with it.
        why: String,
    },
}

/// Size of one normtexture.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct TextureShape {
    width: usize,
    height: usize,
    channels: usize,
}

impl TextureShape {
    /// `channels` is 1 (grey) or 3 (RGB); the sizes must be positive.
    pub fn new(width: usize, height: usize, channels: usize) -> Result<Self, BtfError> {
        let invalid = |why| BtfError::Shape {
            width,
            height,
            channels,
            why,
        };
        if width == 0 || height == 0 {
            return Err(invalid("width and height must be positive"));
        }
        if channels != 1 && channels != 3 {
            return Err(invalid("channels must be 1 or 3"));
        }
        let values = width
            .checked_mul(height)
            .and_then(|t| t.checked_mul(channels))
            // Room for the byte size of a slot file as well.
            .and_then(|v| v.checked_mul(4));
        if values.is_none() {
            return Err(invalid("too many values"));
        }
        Ok(TextureShape {
            width,
            height,
            channels,
        })
    }

    /// Width, texels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height, texels (rows).
    pub fn height(&self) -> usize {
        self.height
    }

    /// Values per texel: 1 (grey) or 3 (RGB, interleaved).
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Texels per texture: width · height.
    pub fn texels(&self) -> usize {
        self.width * self.height
    }

    /// Values per texture: texels · channels.
    pub fn values(&self) -> usize {
        self.texels() * self.channels
    }
}

/// The component count actually stored for `requested` components: a slot of
/// `lights` images of `values` values has at most min(lights, values).
pub fn stored_components(requested: usize, lights: usize, values: usize) -> usize {
    requested.min(lights).min(values)
}

/// The PCA of one view slot. See the module documentation for the model.
#[derive(Debug, Clone, PartialEq)]
pub struct SlotPca {
    values: usize,
    lights: usize,
    components: usize,
    mean: Vec<f32>,
    /// `components` textures of `values` values, component-major.
    eigen_textures: Vec<f32>,
    /// `lights × components`, light-major.
    weights: Vec<f32>,
    /// All min(values, lights) singular values of the centred matrix,
    /// non-increasing.
    singular_values: Vec<f64>,
}

/// How one slot's PCA is computed; [`PcaRoute::for_shape`] picks the cheaper.
///
/// Both give the same factors up to rounding: the eigenvalues, the error
/// curve and every reconstruction agree (tested to 1e-9 relative on the
/// leading eigenvalues and to f32 storage on reconstructions).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PcaRoute {
    /// Eigen-decomposition of the small lights × lights Gram matrix XᵀX
    /// (accumulated in f64), then the eigen-textures as X v / σ: one pass of
    /// values · lights² / 2 multiply-adds, about four times fewer than the
    /// SVD's QR. Eigenvalues below what rounding in the Gram matrix can
    /// produce (about 1e-13 of the largest) are reported as 0.
    Gram,
    /// A thin SVD of the values × lights matrix: exact to the smallest
    /// singular value, for matrices that are not much taller than wide.
    ThinSvd,
}

impl PcaRoute {
    /// The Gram route for slots with at least twice as many values as lights
    /// (every real normtexture: 256² texels against 81 lights), the thin SVD
    /// otherwise (tiny textures, where both are instant).
    pub fn for_shape(values: usize, lights: usize) -> PcaRoute {
        if values >= 2 * lights {
            PcaRoute::Gram
        } else {
            PcaRoute::ThinSvd
        }
    }
}

/// Compresses one view slot: `images[i]` is the normtexture under light i,
/// `shape.values()` f32 values each. Keeps min(`components`, lights, values)
/// components. Only this slot's matrix is in memory (in f64, plus the
/// factors), so slots can be streamed. The route is
/// [`PcaRoute::for_shape`]'s choice.
pub fn compress_slot(
    images: &[&[f32]],
    shape: TextureShape,
    components: usize,
) -> Result<SlotPca, BtfError> {
    compress_slot_by(
        PcaRoute::for_shape(shape.values(), images.len()),
        images,
        shape,
        components,
    )
}

/// [`compress_slot`] by a given route (to compare the two).
pub fn compress_slot_by(
    route: PcaRoute,
    images: &[&[f32]],
    shape: TextureShape,
    components: usize,
) -> Result<SlotPca, BtfError> {
    if images.is_empty() {
        return Err(BtfError::NoImages);
    }
    if components == 0 {
        return Err(BtfError::NoComponents);
    }
    let values = shape.values();
    let lights = images.len();
    for (image, data) in images.iter().enumerate() {
        if data.len() != values {
            return Err(BtfError::ImageSize {
                image,
                expected: values,
                actual: data.len(),
            });
        }
        if let Some(value_index) = data.iter().position(|v| !v.is_finite()) {
            return Err(BtfError::NonFiniteValue { image, value_index });
        }
    }

    let mut mean = vec![0.0f64; values];
    for data in images {
        for (m, &v) in mean.iter_mut().zip(data.iter()) {
            *m += f64::from(v);
        }
    }
    for m in &mut mean {
        *m /= lights as f64;
    }
    let stored = stored_components(components, lights, values);
    // Rounding the input to f32 perturbs the matrix by at most
    // ε/2 · ‖X‖_F (Frobenius), which bounds every singular value that rounding
    // alone can create: components below it carry no data and are zero-filled,
    // which also makes exactly rank-deficient slots deterministic.
    let data_norm = images
        .iter()
        .flat_map(|data| data.iter())
        .map(|&v| f64::from(v) * f64::from(v))
        .sum::<f64>()
        .sqrt();
    let negligible = 0.5 * f64::from(f32::EPSILON) * data_norm;
    let centred = |first_row: usize, rows: usize| {
        Mat::<f64>::from_fn(rows, lights, |row, col| {
            f64::from(images[col][first_row + row]) - mean[first_row + row]
        })
    };
    let factors = match route {
        PcaRoute::Gram => gram_factors(values, lights, stored, centred)?,
        PcaRoute::ThinSvd => svd_factors(&centred(0, values), stored)?,
    };

    let mut eigen_textures = vec![0.0f32; stored * values];
    let mut weights = vec![0.0f32; lights * stored];
    for (k, &sigma) in factors.singular_values.iter().enumerate().take(stored) {
        if sigma <= negligible || !sigma.is_finite() {
            continue;
        }
        let column = factors.textures.col(k);
        let sign = column
            .iter()
            .copied()
            .max_by(|a, b| a.abs().total_cmp(&b.abs()))
            .map_or(1.0, |x| if x < 0.0 { -1.0 } else { 1.0 });
        let texture = &mut eigen_textures[k * values..(k + 1) * values];
        for (out, &x) in texture.iter_mut().zip(column.iter()) {
            *out = (sign * x) as f32;
        }
        for (light, &x) in factors.light_vectors.col(k).iter().enumerate() {
            weights[light * stored + k] = (sign * sigma * x) as f32;
        }
    }

    Ok(SlotPca {
        values,
        lights,
        components: stored,
        mean: mean.into_iter().map(|m| m as f32).collect(),
        eigen_textures,
        weights,
        singular_values: factors.singular_values,
    })
}

/// A slot's leading factors: X ≈ Σ_k σ_k u_k v_kᵀ.
struct SlotFactors {
    /// All min(values, lights) singular values, non-increasing.
    singular_values: Vec<f64>,
    /// u_k, unit norm, for the first `stored` k (values × stored).
    textures: Mat<f64>,
    /// v_k, unit norm, for the first `stored` k (lights × stored).
    light_vectors: Mat<f64>,
}

/// Thin SVD of the centred slot matrix. faer reduces a tall matrix by QR
/// first, so the cost is O(values · lights²) with a constant of about 2.
fn svd_factors(centred: &Mat<f64>, stored: usize) -> Result<SlotFactors, BtfError> {
    let svd = centred.thin_svd().map_err(|_| BtfError::SvdNoConvergence)?;
    Ok(SlotFactors {
        singular_values: svd.S().column_vector().iter().copied().collect(),
        textures: svd.U().subcols(0, stored).to_owned(),
        light_vectors: svd.V().subcols(0, stored).to_owned(),
    })
}

/// Bytes [`compress_slot`] holds for one slot of `lights` images of
/// `values` values keeping `components` components by the Gram route, the
/// images included: the images in f32, the mean in f64, the eigen-textures
/// in f64 and f32, and one block of the centred matrix in f64. (The thin
/// SVD, for tiny textures only, holds the whole centred matrix instead.)
pub fn slot_memory_bytes(values: usize, lights: usize, components: usize) -> usize {
    let stored = stored_components(components, lights, values);
    values
        .saturating_mul(4 * lights + 12 * stored + 8)
        .saturating_add(GRAM_BLOCK_ROWS.min(values) * lights * 8)
}

/// Rows of the centred matrix the Gram route holds at once: 4096 × 81
/// lights in f64 is 2.6 MB, which stays in cache while it is multiplied.
const GRAM_BLOCK_ROWS: usize = 4096;

/// The Gram route: G = XᵀX (lights × lights, f64), G = V Λ Vᵀ, σ = √λ and
/// u = X v / σ. X is never held whole: `centred(first, rows)` makes a block
/// of its rows, G and X v are accumulated block by block. The products run
/// on the calling thread (callers parallelise over slots; faer's own
/// threads, nested in a busy pool, were ten times slower here).
///
/// Squaring X squares its condition number: eigenvalues below what
/// rounding in G and its eigensolver can produce, 16 · lights · ε_f64 ·
/// λ_max (σ below 5.4e-7 σ_max at 81 lights), are reported as 0. What that
/// drops from the error report is below 5e-6 of the slot's RMS, far under
/// the 8-bit quantisation of a normtexture (1e-3).
fn gram_factors(
    values: usize,
    lights: usize,
    stored: usize,
    centred: impl Fn(usize, usize) -> Mat<f64>,
) -> Result<SlotFactors, BtfError> {
    use faer::linalg::matmul::matmul;
    use faer::{Accum, Par};
    let blocks = || {
        (0..values)
            .step_by(GRAM_BLOCK_ROWS)
            .map(move |first| (first, GRAM_BLOCK_ROWS.min(values - first)))
    };
    let mut gram = Mat::<f64>::zeros(lights, lights);
    for (first, rows) in blocks() {
        let block = centred(first, rows);
        matmul(
            gram.as_mut(),
            Accum::Add,
            block.transpose(),
            block.as_ref(),
            1.0,
            Par::Seq,
        );
    }
    let eigen = gram
        .self_adjoint_eigen(faer::Side::Lower)
        .map_err(|_| BtfError::SvdNoConvergence)?;
    // faer sorts eigenvalues non-decreasing; the PCA wants them largest first.
    let lambda: Vec<f64> = eigen.S().column_vector().iter().rev().copied().collect();
    let largest = lambda.first().copied().unwrap_or(0.0).max(0.0);
    let floor = 16.0 * lights as f64 * f64::EPSILON * largest;
    let singular_values: Vec<f64> = lambda
        .iter()
        .map(|&l| if l > floor { l.sqrt() } else { 0.0 })
        .collect();
    let light_vectors = Mat::<f64>::from_fn(lights, stored, |light, k| {
        eigen.U()[(light, lights - 1 - k)]
    });
    let mut textures = Mat::<f64>::zeros(values, stored);
    for (first, rows) in blocks() {
        let block = centred(first, rows);
        matmul(
            textures.as_mut().subrows_mut(first, rows),
            Accum::Replace,
            block.as_ref(),
            light_vectors.as_ref(),
            1.0,
            Par::Seq,
        );
    }
    for (k, &sigma) in singular_values.iter().enumerate().take(stored) {
        let scale = if sigma > 0.0 { sigma.recip() } else { 0.0 };
        for x in textures.col_mut(k).iter_mut() {
            *x *= scale;
        }
    }
    Ok(SlotFactors {
        singular_values,
        textures,
        light_vectors,
    })
}

impl SlotPca {
    /// Values per texture (width · height · channels).
    pub fn values(&self) -> usize {
        self.values
    }

    /// Number of measured lights (images) the slot was compressed from.
    pub fn lights(&self) -> usize {
        self.lights
    }

    /// Stored components C.
    pub fn components(&self) -> usize {
        self.components
    }

    /// The mean texture M_j: per value, the mean over lights; `values()`
    /// values, texel-major with channels interleaved.
    pub fn mean(&self) -> &[f32] {
        &self.mean
    }

    /// Eigen-texture k (0-based), unit norm (or zero if rank-deficient).
    pub fn eigen_texture(&self, k: usize) -> Option<&[f32]> {
        (k < self.components).then(|| &self.eigen_textures[k * self.values..(k + 1) * self.values])
    }

    /// The C weights p_ik of light i.
    pub fn light_weights(&self, light: usize) -> Option<&[f32]> {
        (light < self.lights)
            .then(|| &self.weights[light * self.components..(light + 1) * self.components])
    }

    /// All singular values of the centred slot matrix, non-increasing.
    pub fn singular_values(&self) -> &[f64] {
        &self.singular_values
    }

    /// Eigenvalues of the PCA (σ², unnormalised scatter), non-increasing:
    /// the decay curve of Sattler et al. Fig. 7.
    pub fn eigenvalues(&self) -> Vec<f64> {
        self.singular_values.iter().map(|s| s * s).collect()
    }

    /// RMS over all values and lights of original − rank-`components`
    /// reconstruction, from the discarded singular values. `components` may
    /// exceed the stored C (the report shows what more would buy); beyond the
    /// rank it is 0.
    pub fn rms_error(&self, components: usize) -> f64 {
        let discarded: f64 = self
            .singular_values
            .iter()
            .skip(components)
            .map(|s| s * s)
            .sum();
        (discarded / (self.values as f64 * self.lights as f64)).sqrt()
    }

    /// `rms_error(c)` for c = 1 … min(`max_components`, number of singular values).
    pub fn rms_error_curve(&self, max_components: usize) -> Vec<f64> {
        let top = max_components.min(self.singular_values.len());
        (1..=top).map(|c| self.rms_error(c)).collect()
    }

    /// The reconstruction of measured light `light` with all stored components.
    pub fn reconstruct_measured(&self, light: usize) -> Result<Vec<f32>, BtfError> {
        self.reconstruct_measured_truncated(light, self.components)
    }

    /// The reconstruction of measured light `light` with the first
    /// min(`components`, C) components.
    pub fn reconstruct_measured_truncated(
        &self,
        light: usize,
        components: usize,
    ) -> Result<Vec<f32>, BtfError> {
        let mut acc = vec![0.0f64; self.values];
        self.accumulate(&[(light, 1.0)], 1.0, components, &mut acc)?;
        Ok(acc.into_iter().map(|v| v as f32).collect())
    }

    /// The texture under an interpolated light (eq. 3): blended weights
    /// γ_k = Σ_m τ_m p_{i_m,k}, then M + Σ_k γ_k B_k.
    pub fn reconstruct_blend(&self, light_weights: &Interpolation) -> Result<Vec<f32>, BtfError> {
        let mut acc = vec![0.0f64; self.values];
        self.accumulate(light_weights.entries(), 1.0, self.components, &mut acc)?;
        Ok(acc.into_iter().map(|v| v as f32).collect())
    }

    /// acc += scale · (Σ_m τ_m · M + Σ_{k<components} γ_k B_k).
    fn accumulate(
        &self,
        light_weights: &[(usize, f64)],
        scale: f64,
        components: usize,
        acc: &mut [f64],
    ) -> Result<(), BtfError> {
        let components = components.min(self.components);
        let mut gamma = vec![0.0f64; components];
        let mut tau_total = 0.0;
        for &(light, tau) in light_weights {
            let p = self.light_weights(light).ok_or(BtfError::LightIndex {
                light,
                lights: self.lights,
            })?;
            tau_total += tau;
            for (g, &pk) in gamma.iter_mut().zip(p) {
                *g += tau * f64::from(pk);
            }
        }
        let mean_scale = scale * tau_total;
        for (a, &m) in acc.iter_mut().zip(&self.mean) {
            *a += mean_scale * f64::from(m);
        }
        for (k, &g) in gamma.iter().enumerate() {
            if g == 0.0 {
                continue;
            }
            let g = scale * g;
            let texture = &self.eigen_textures[k * self.values..(k + 1) * self.values];
            for (a, &b) in acc.iter_mut().zip(texture) {
                *a += g * f64::from(b);
            }
        }
        Ok(())
    }
}

/// Eigenvalue decay and error curve of one view slot.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SlotReport {
    /// Index of the view slot.
    pub slot: usize,
    /// The slot's measured view direction.
    pub view: Direction,
    /// σ², non-increasing, all of them.
    pub eigenvalues: Vec<f64>,
    /// RMS error of the mean texture alone (C = 0).
    pub rms_mean_only: f64,
    /// `rms_by_components[c - 1]` is the RMS error with c components,
    /// c = 1 … min(32, rank bound).
    pub rms_by_components: Vec<f64>,
}

/// A compressed BTF: one [`SlotPca`] per view direction.
#[derive(Debug, Clone, PartialEq)]
pub struct CompressedBtf {
    shape: TextureShape,
    components: usize,
    lights: DirectionTable,
    views: DirectionTable,
    slots: Vec<SlotPca>,
}

impl CompressedBtf {
    /// Assembles slots compressed with [`compress_slot`]; `slots[j]` belongs
    /// to view direction j and must cover every light of `lights`.
    pub fn new(
        shape: TextureShape,
        lights: DirectionTable,
        views: DirectionTable,
        slots: Vec<SlotPca>,
    ) -> Result<Self, BtfError> {
        if slots.len() != views.len() {
            return Err(BtfError::SlotCount {
                slots: slots.len(),
                views: views.len(),
            });
        }
        let components = slots.first().map_or(0, |s| s.components);
        for (slot, pca) in slots.iter().enumerate() {
            check_slot(slot, pca, shape, lights.len(), components)?;
        }
        Ok(CompressedBtf {
            shape,
            components,
            lights,
            views,
            slots,
        })
    }

    /// Compresses every view slot, in parallel over slots with rayon.
    /// `load_slot(j)` returns the images of slot j in light order. Memory is
    /// one slot per rayon worker; for one slot at a time use
    /// [`compress_to_dir`] or [`compress_slot`] with a [`BtfWriter`].
    pub fn compress<F>(
        shape: TextureShape,
        lights: DirectionTable,
        views: DirectionTable,
        components: usize,
        load_slot: F,
    ) -> Result<Self, BtfError>
    where
        F: Fn(usize) -> Result<Vec<Vec<f32>>, BtfError> + Sync,
    {
        let light_count = lights.len();
        let slots = (0..views.len())
            .into_par_iter()
            .map(|slot| load_and_compress(slot, &load_slot, shape, light_count, components))
            .collect::<Result<Vec<_>, _>>()?;
        CompressedBtf::new(shape, lights, views, slots)
    }

    /// Size of every texture in the store.
    pub fn shape(&self) -> TextureShape {
        self.shape
    }

    /// Stored components per slot.
    pub fn components(&self) -> usize {
        self.components
    }

    /// The measured light directions, in light-index order.
    pub fn lights(&self) -> &DirectionTable {
        &self.lights
    }

    /// The measured view directions, one per slot, in slot order.
    pub fn views(&self) -> &DirectionTable {
        &self.views
    }

    /// The per-view-slot PCAs, in slot order.
    pub fn slots(&self) -> &[SlotPca] {
        &self.slots
    }

    /// The texture for an arbitrary light and view (eq. 5): the four nearest
    /// view slots, each reconstructed under the bilinearly interpolated light
    /// (eq. 3), blended with the view weights. Errors only on non-finite
    /// directions; out-of-range θ is clamped (see [`crate::directions`]).
    pub fn reconstruct(&self, light: Direction, view: Direction) -> Result<Vec<f32>, BtfError> {
        let view_weights = self.views.interpolate(view)?;
        let light_weights = self.lights.interpolate(light)?;
        let mut acc = vec![0.0f64; self.shape.values()];
        for &(slot, omega) in view_weights.entries() {
            let pca = self.slot_checked(slot)?;
            pca.accumulate(light_weights.entries(), omega, pca.components, &mut acc)?;
        }
        Ok(acc.into_iter().map(|v| v as f32).collect())
    }

    /// The stored reconstruction of measured light `light` in view slot `slot`.
    pub fn reconstruct_measured(&self, slot: usize, light: usize) -> Result<Vec<f32>, BtfError> {
        self.slot_checked(slot)?.reconstruct_measured(light)
    }

    /// Eigenvalue decay and RMS error for C = 1 … `max_components` (clamped to
    /// each slot's rank bound) per slot; see [`MAX_REPORTED_COMPONENTS`].
    pub fn error_report(&self, max_components: usize) -> Vec<SlotReport> {
        self.slots
            .iter()
            .zip(self.views.directions())
            .enumerate()
            .map(|(slot, (pca, &view))| SlotReport {
                slot,
                view,
                eigenvalues: pca.eigenvalues(),
                rms_mean_only: pca.rms_error(0),
                rms_by_components: pca.rms_error_curve(max_components),
            })
            .collect()
    }

    /// Writes the store to `dir` (created if missing) in the format of the
    /// module documentation.
    pub fn write(&self, dir: &Path) -> Result<(), BtfError> {
        let mut writer =
            BtfWriter::create(dir, self.shape, &self.lights, &self.views, self.components)?;
        for (slot, pca) in self.slots.iter().enumerate() {
            writer.write_slot(slot, pca)?;
        }
        writer.finish()
    }

    /// Reads a store written by [`CompressedBtf::write`] or [`BtfWriter`].
    pub fn read(dir: &Path) -> Result<Self, BtfError> {
        let header = BtfHeader::read(dir)?;
        let slots = (0..header.slots.len())
            .map(|slot| header.read_slot(dir, slot))
            .collect::<Result<Vec<_>, _>>()?;
        let shape = header.shape(&dir.join(HEADER_FILE))?;
        let lights = DirectionTable::new(header.light_directions)?;
        let views = DirectionTable::new(header.view_directions)?;
        CompressedBtf::new(shape, lights, views, slots)
    }

    fn slot_checked(&self, slot: usize) -> Result<&SlotPca, BtfError> {
        self.slots.get(slot).ok_or(BtfError::SlotIndex {
            slot,
            slots: self.slots.len(),
        })
    }
}

fn load_and_compress<F>(
    slot: usize,
    load_slot: &F,
    shape: TextureShape,
    light_count: usize,
    components: usize,
) -> Result<SlotPca, BtfError>
where
    F: Fn(usize) -> Result<Vec<Vec<f32>>, BtfError>,
{
    let images = load_slot(slot)?;
    if images.len() != light_count {
        return Err(BtfError::SlotMismatch {
            slot,
            why: format!("{} images for {light_count} lights", images.len()),
        });
    }
    let views: Vec<&[f32]> = images.iter().map(Vec::as_slice).collect();
    compress_slot(&views, shape, components)
}

/// Compresses slot after slot straight to `dir`, holding one slot in memory
/// (faer still parallelises inside each SVD).
pub fn compress_to_dir<F>(
    dir: &Path,
    shape: TextureShape,
    lights: &DirectionTable,
    views: &DirectionTable,
    components: usize,
    load_slot: F,
) -> Result<(), BtfError>
where
    F: Fn(usize) -> Result<Vec<Vec<f32>>, BtfError>,
{
    let mut writer = BtfWriter::create(dir, shape, lights, views, components)?;
    for slot in 0..views.len() {
        let pca = load_and_compress(slot, &load_slot, shape, lights.len(), components)?;
        writer.write_slot(slot, &pca)?;
    }
    writer.finish()
}

fn check_slot(
    slot: usize,
    pca: &SlotPca,
    shape: TextureShape,
    lights: usize,
    components: usize,
) -> Result<(), BtfError> {
    let mismatch = |why: String| Err(BtfError::SlotMismatch { slot, why });
    if pca.values != shape.values() {
        return mismatch(format!(
            "{} values per texture, expected {}",
            pca.values,
            shape.values()
        ));
    }
    if pca.lights != lights {
        return mismatch(format!("{} lights, expected {lights}", pca.lights));
    }
    if pca.components != components {
        return mismatch(format!(
            "{} components, expected {components}",
            pca.components
        ));
    }
    Ok(())
}

/// One slot's entry in `btf.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SlotEntry {
    /// Name of the slot's `.bin` file, a plain file name in the store's
    /// directory.
    pub file: String,
    /// All singular values of the slot's centred matrix, non-increasing:
    /// min(lights, W·H·channels) of them.
    pub singular_values: Vec<f64>,
}

/// The contents of `btf.json`; see the module documentation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BtfHeader {
    /// Format name, always [`FORMAT_NAME`].
    pub format: String,
    /// Format version; this module reads and writes [`FORMAT_VERSION`].
    pub version: u32,
    /// Texture width, texels.
    pub width: usize,
    /// Texture height, texels.
    pub height: usize,
    /// Values per texel: 1 (grey) or 3 (RGB).
    pub channels: usize,
    /// Components C stored per slot.
    pub components: usize,
    /// Encoding of the slot files' values, [`VALUE_ENCODING`]
    /// (little-endian f32).
    pub value_encoding: String,
    /// Measured light directions, in light-index order.
    pub light_directions: Vec<Direction>,
    /// Measured view directions, in slot order.
    pub view_directions: Vec<Direction>,
    /// One entry per view slot, in slot order.
    pub slots: Vec<SlotEntry>,
}

impl BtfHeader {
    /// Reads and validates `dir/btf.json` (not the slot files).
    pub fn read(dir: &Path) -> Result<Self, BtfError> {
        let path = dir.join(HEADER_FILE);
        let text = fs::read_to_string(&path).map_err(|source| BtfError::Io {
            path: path.clone(),
            source,
        })?;
        let header: BtfHeader = serde_json::from_str(&text).map_err(|e| BtfError::Format {
            path: path.clone(),
            why: e.to_string(),
        })?;
        header.validate(&path)?;
        Ok(header)
    }

    fn shape(&self, path: &Path) -> Result<TextureShape, BtfError> {
        TextureShape::new(self.width, self.height, self.channels).map_err(|e| BtfError::Format {
            path: path.to_path_buf(),
            why: e.to_string(),
        })
    }

    fn validate(&self, path: &Path) -> Result<(), BtfError> {
        let bad = |why: String| {
            Err(BtfError::Format {
                path: path.to_path_buf(),
                why,
            })
        };
        if self.format != FORMAT_NAME {
            return bad(format!(
                "format `{}`, expected `{FORMAT_NAME}`",
                self.format
            ));
        }
        if self.version != FORMAT_VERSION {
            return bad(format!(
                "version {}, this reader knows {FORMAT_VERSION}",
                self.version
            ));
        }
        if self.value_encoding != VALUE_ENCODING {
            return bad(format!(
                "value encoding `{}`, expected `{VALUE_ENCODING}`",
                self.value_encoding
            ));
        }
        let shape = self.shape(path)?;
        let lights = self.light_directions.len();
        if let Err(e) = DirectionTable::new(self.light_directions.clone()) {
            return bad(format!("light directions: {e}"));
        }
        if let Err(e) = DirectionTable::new(self.view_directions.clone()) {
            return bad(format!("view directions: {e}"));
        }
        if self.components == 0
            || self.components != stored_components(self.components, lights, shape.values())
        {
            return bad(format!(
                "{} components for {lights} lights of {} values",
                self.components,
                shape.values()
            ));
        }
        if self.slots.len() != self.view_directions.len() {
            return bad(format!(
                "{} slots for {} view directions",
                self.slots.len(),
                self.view_directions.len()
            ));
        }
        let rank_bound = lights.min(shape.values());
        for (slot, entry) in self.slots.iter().enumerate() {
            if !is_plain_file_name(&entry.file) {
                return bad(format!(
                    "slot {slot}: file `{}` is not a plain file name",
                    entry.file
                ));
            }
            if entry.singular_values.len() != rank_bound
                || entry
                    .singular_values
                    .iter()
                    .any(|s| !s.is_finite() || *s < 0.0)
            {
                return bad(format!(
                    "slot {slot}: expected {rank_bound} finite non-negative singular values"
                ));
            }
        }
        Ok(())
    }

    /// Reads the PCA of view slot `slot` from its file in `dir`.
    pub fn read_slot(&self, dir: &Path, slot: usize) -> Result<SlotPca, BtfError> {
        let entry = self.slots.get(slot).ok_or(BtfError::SlotIndex {
            slot,
            slots: self.slots.len(),
        })?;
        let path = dir.join(&entry.file);
        let bad = |why: String| BtfError::Format {
            path: path.clone(),
            why,
        };
        let shape = self.shape(&dir.join(HEADER_FILE))?;
        let (values, lights, components) =
            (shape.values(), self.light_directions.len(), self.components);
        let expected_floats = values
            .checked_mul(components + 1)
            .and_then(|v| v.checked_add(lights.checked_mul(components)?))
            .ok_or_else(|| bad("slot size overflows".into()))?;
        let bytes = fs::read(&path).map_err(|source| BtfError::Io {
            path: path.clone(),
            source,
        })?;
        if Some(bytes.len()) != expected_floats.checked_mul(4) {
            return Err(bad(format!(
                "{} bytes, expected {expected_floats} f32 values ({values} per texture, {components} components, {lights} lights)",
                bytes.len()
            )));
        }
        SlotPca::from_le_bytes(
            &bytes,
            [values, lights, components],
            entry.singular_values.clone(),
        )
        .map_err(bad)
    }
}

impl SlotPca {
    /// The slot as a slot file stores it: the mean, the eigen-textures and
    /// the light weights, f32 little-endian.
    pub fn to_le_bytes(&self) -> Vec<u8> {
        [&self.mean, &self.eigen_textures, &self.weights]
            .into_iter()
            .flat_map(|part| part.iter().flat_map(|v| v.to_le_bytes()))
            .collect()
    }

    /// A slot from [`SlotPca::to_le_bytes`]'s layout, for `[values, lights,
    /// components]`, with its singular values; `Err` says what does not fit.
    pub fn from_le_bytes(
        bytes: &[u8],
        [values, lights, components]: [usize; 3],
        singular_values: Vec<f64>,
    ) -> Result<SlotPca, String> {
        let expected = values
            .checked_mul(components + 1)
            .and_then(|v| v.checked_add(lights.checked_mul(components)?))
            .and_then(|v| v.checked_mul(4));
        if expected != Some(bytes.len()) {
            return Err(format!(
                "{} bytes, expected 4 per f32 value ({values} per texture, {components} components, {lights} lights)",
                bytes.len()
            ));
        }
        let floats: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        if let Some(at) = floats.iter().position(|v| !v.is_finite()) {
            return Err(format!("value {at} is not finite"));
        }
        let (mean, rest) = floats.split_at(values);
        let (eigen_textures, weights) = rest.split_at(values * components);
        Ok(SlotPca {
            values,
            lights,
            components,
            mean: mean.to_vec(),
            eigen_textures: eigen_textures.to_vec(),
            weights: weights.to_vec(),
            singular_values,
        })
    }
}

fn is_plain_file_name(name: &str) -> bool {
    !name.is_empty()
        && name != "."
        && name != ".."
        && !name.contains(['/', '\\'])
        && Path::new(name).file_name() == Some(std::ffi::OsStr::new(name))
}

/// File name of view slot `slot`.
pub fn slot_file_name(slot: usize) -> String {
    format!("slot_{slot:03}.bin")
}

/// Writes a store slot by slot, so a caller compressing in a stream keeps one
/// slot in memory. `btf.json` is written by [`BtfWriter::finish`], last.
#[derive(Debug)]
pub struct BtfWriter {
    dir: PathBuf,
    shape: TextureShape,
    lights: usize,
    header: BtfHeader,
    written: Vec<bool>,
}

impl BtfWriter {
    /// Prepares `dir` (created if missing). `components` is the requested C;
    /// it is clamped like [`compress_slot`] does.
    pub fn create(
        dir: &Path,
        shape: TextureShape,
        lights: &DirectionTable,
        views: &DirectionTable,
        components: usize,
    ) -> Result<Self, BtfError> {
        if components == 0 {
            return Err(BtfError::NoComponents);
        }
        fs::create_dir_all(dir).map_err(|source| BtfError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        let header = BtfHeader {
            format: FORMAT_NAME.into(),
            version: FORMAT_VERSION,
            width: shape.width,
            height: shape.height,
            channels: shape.channels,
            components: stored_components(components, lights.len(), shape.values()),
            value_encoding: VALUE_ENCODING.into(),
            light_directions: lights.directions().to_vec(),
            view_directions: views.directions().to_vec(),
            slots: (0..views.len())
                .map(|slot| SlotEntry {
                    file: slot_file_name(slot),
                    singular_values: Vec::new(),
                })
                .collect(),
        };
        Ok(BtfWriter {
            dir: dir.to_path_buf(),
            shape,
            lights: lights.len(),
            written: vec![false; views.len()],
            header,
        })
    }

    /// Writes `slot_{slot:03}.bin` atomically.
    pub fn write_slot(&mut self, slot: usize, pca: &SlotPca) -> Result<(), BtfError> {
        let slots = self.header.slots.len();
        let entry = self
            .header
            .slots
            .get_mut(slot)
            .ok_or(BtfError::SlotIndex { slot, slots })?;
        check_slot(slot, pca, self.shape, self.lights, self.header.components)?;
        let path = self.dir.join(&entry.file);
        write_atomically(&path, |out| {
            for part in [&pca.mean, &pca.eigen_textures, &pca.weights] {
                for value in part.iter() {
                    out.write_all(&value.to_le_bytes())?;
                }
            }
            Ok(())
        })?;
        entry.singular_values = pca.singular_values.clone();
        self.written[slot] = true;
        Ok(())
    }

    /// Writes `btf.json`; fails if a slot was never written.
    pub fn finish(self) -> Result<(), BtfError> {
        if let Some(slot) = self.written.iter().position(|w| !w) {
            return Err(BtfError::SlotMismatch {
                slot,
                why: "never written".into(),
            });
        }
        let path = self.dir.join(HEADER_FILE);
        let json = serde_json::to_vec_pretty(&self.header).map_err(|e| BtfError::Format {
            path: path.clone(),
            why: e.to_string(),
        })?;
        write_atomically(&path, |out| out.write_all(&json))
    }
}

/// Writes `path` whole or not at all ([`crate::atomic`]).
fn write_atomically(
    path: &Path,
    fill: impl FnOnce(&mut io::BufWriter<&fs::File>) -> io::Result<()>,
) -> Result<(), BtfError> {
    rigd_core::atomic::write_with(path, fill).map_err(|e| BtfError::Io {
        path: path.to_path_buf(),
        source: e.error,
    })
}
