//! Output.

use super::*;

/// 8-bit codes of the depths (Wang et al. store MDFs quantised to 8 bits):
/// `round(clamp(depth / max_depth, 0, 1) · 254)`; 255 ([`NO_DEPTH_CODE`])
/// for −1 (any negative or non-finite depth).
pub fn quantise_depth(d: &DisplacementImage, max_depth: f64) -> Result<Vec<u8>, MdfError> {
    if !(max_depth.is_finite() && max_depth > 0.0) {
        return Err(MdfError::InvalidInput(format!("max depth {max_depth}")));
    }
    Ok(d.depth
        .iter()
        .map(|&v| {
            if !(v >= 0.0 && v.is_finite()) {
                NO_DEPTH_CODE
            } else {
                let q = (f64::from(v) / max_depth).clamp(0.0, 1.0) * f64::from(MAX_DEPTH_CODE);
                q.round() as u8
            }
        })
        .collect())
}

/// Inverse of [`quantise_depth`]: code 255 → −1.
pub fn dequantise_depth(codes: &[u8], max_depth: f64) -> Vec<f32> {
    codes
        .iter()
        .map(|&c| {
            if c == NO_DEPTH_CODE {
                NO_DEPTH
            } else {
                (f64::from(c) / f64::from(MAX_DEPTH_CODE) * max_depth) as f32
            }
        })
        .collect()
}

/// Writes a displacement image as `float32` `.npy` of shape `(H, W)`
/// (metres, −1 = none) to `npy_path` and its [`quantise_depth`] codes as
/// an 8-bit grey PNG to `png_path` (both atomically).
pub fn write_displacement(
    d: &DisplacementImage,
    npy_path: &Path,
    png_path: &Path,
    max_depth: f64,
) -> Result<(), MdfError> {
    d.check(0, (d.width, d.height))?;
    write_f32(npy_path, &[d.height, d.width], &d.depth)?;
    let codes = quantise_depth(d, max_depth)?;
    let image = Image {
        width: d.width,
        height: d.height,
        channels: 1,
        data: codes.iter().map(|&c| f32::from(c) / 255.0).collect(),
    };
    write_png(png_path, &image, PngDepth::Eight)?;
    Ok(())
}
