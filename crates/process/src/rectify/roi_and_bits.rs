//! ROI and bits.

use super::*;

/// A rectangle of texels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Roi {
    /// Column of the left edge, texels.
    pub x: usize,
    /// Row of the top edge, texels.
    pub y: usize,
    /// Width, texels.
    pub width: usize,
    /// Height, texels.
    pub height: usize,
}

impl Roi {
    /// The centred square covering `fraction` of the smaller side of a
    /// `width × height` texture (e.g. [`SATTLER_ROI_FRACTION`]).
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

/// Linear edge blending (Sattler et al., §3.2: "linear edgeblending is applied,
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
pub(super) fn resample_weights(n_in: usize, n_out: usize) -> Vec<Vec<(usize, f64)>> {
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
    /// the central 8 bits (bits 2..=9) as in Sattler et al.: codes ≥ 1020
    /// saturate to 255 (never wrap); `shift: 4` keeps the top 8 bits.
    Bits8 {
        /// Low bits dropped from the sensor code before clipping to 255 (2: the
        /// central 8 of 12 bits).
        shift: u8,
    },
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
