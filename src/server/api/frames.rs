//! Frame routes: the raw PNG, and an 8-bit downscaled preview. The run id
//! must name a known run and the index must be a plain integer below the
//! run's image count; the path is built from those, never from raw input.

use axum::http::header;
use axum::response::{IntoResponse, Response};

use axum::extract::State;

use super::AppState;
use crate::rig::hal::decode_png;
use crate::server::error::{ApiError, ApiPath, ErrorBody};
use crate::server::supervisor::Daemon;
use crate::store::frame_file;

/// Longest side of a preview, pixels.
pub const PREVIEW_MAX: u32 = 256;

fn parse_index(s: &str) -> Result<usize, ApiError> {
    if s.is_empty() || s.len() > 9 || !s.bytes().all(|b| b.is_ascii_digit()) {
        return Err(ApiError::bad_request(
            "the frame index must be a non-negative integer (digits only)",
        ));
    }
    s.parse()
        .map_err(|_| ApiError::bad_request("the frame index must be a non-negative integer"))
}

async fn read_frame(d: &Daemon, id: &str, index: &str) -> Result<Vec<u8>, ApiError> {
    let index = parse_index(index)?;
    let root = d
        .run_root(id)
        .ok_or_else(|| ApiError::not_found("no such run"))?;
    let total = d.view(id).map_or(0, |v| v.steps_total);
    if index >= total {
        return Err(ApiError::not_found(format!(
            "frame {index}: the run has {total} images"
        )));
    }
    match tokio::fs::read(root.join(frame_file(index))).await {
        Ok(b) => Ok(b),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(ApiError::not_found(format!(
            "frame {index} is not taken yet"
        ))),
        Err(e) => Err(ApiError::internal(e.to_string())),
    }
}

fn png(bytes: Vec<u8>) -> Response {
    (
        [
            (header::CONTENT_TYPE, "image/png"),
            (header::CACHE_CONTROL, "max-age=3600"),
        ],
        bytes,
    )
        .into_response()
}

/// Image `index` of run `id` as stored: the frame's PNG, raw sensor values.
/// 400 when `index` is not a plain integer; 404 for an unknown run, an
/// index past the run's image count, or a frame not taken yet.
pub async fn raw(d: &Daemon, id: &str, index: &str) -> Result<Response, ApiError> {
    read_frame(d, id, index).await.map(png)
}

/// Image `index` of run `id` as an 8-bit PNG, box-filtered to at most
/// [`PREVIEW_MAX`] pixels on its longer side and stretched to its own
/// brightest pixel; the errors of [`raw`].
pub async fn preview(d: &Daemon, id: &str, index: &str) -> Result<Response, ApiError> {
    let bytes = read_frame(d, id, index).await?;
    let out = tokio::task::spawn_blocking(move || make_preview(&bytes, PREVIEW_MAX))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?
        .map_err(ApiError::internal)?;
    Ok(png(out))
}

/// Box-filters a frame down to at most `max` px on its longer side and
/// stretches it to 8 bits by the frame's own maximum.
pub fn make_preview(png_bytes: &[u8], max: u32) -> Result<Vec<u8>, String> {
    let (w, h, px) = decode_png(png_bytes)?;
    if w == 0 || h == 0 || px.len() < (w as usize) * (h as usize) {
        return Err("frame with no pixels".into());
    }
    let scale = (w.max(h) as f64 / max as f64).max(1.0);
    let ow = ((w as f64 / scale).round() as u32).clamp(1, max);
    let oh = ((h as f64 / scale).round() as u32).clamp(1, max);
    let mut sums = vec![0f64; (ow * oh) as usize];
    let mut counts = vec![0u32; (ow * oh) as usize];
    for y in 0..h {
        let oy = ((y as u64 * oh as u64) / h as u64) as u32;
        for x in 0..w {
            let ox = ((x as u64 * ow as u64) / w as u64) as u32;
            let o = (oy * ow + ox) as usize;
            sums[o] += px[(y * w + x) as usize] as f64;
            counts[o] += 1;
        }
    }
    let avg: Vec<f64> = sums
        .iter()
        .zip(&counts)
        .map(|(s, &c)| if c > 0 { s / c as f64 } else { 0.0 })
        .collect();
    let peak = avg.iter().cloned().fold(0.0, f64::max).max(1.0);
    let data: Vec<u8> = avg
        .iter()
        .map(|v| ((v / peak) * 255.0).round().clamp(0.0, 255.0) as u8)
        .collect();
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, ow, oh);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        let mut wr = enc.write_header().map_err(|e| e.to_string())?;
        wr.write_image_data(&data).map_err(|e| e.to_string())?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn indices_are_digits_only() {
        assert_eq!(parse_index("0").ok(), Some(0));
        assert_eq!(parse_index("000012").ok(), Some(12));
        for bad in [
            "",
            "-1",
            "1.5",
            "..",
            "1e3",
            "0x10",
            "1234567890",
            "%2e%2e",
            " 1",
        ] {
            assert!(parse_index(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn preview_downscales_to_8_bit() {
        let frame = crate::rig::hal::Frame {
            width: 600,
            height: 300,
            bit_depth: 12,
            pixels: (0..600 * 300).map(|i| (i % 4096) as u16).collect(),
            device: None,
        };
        let png16 = crate::rig::hal::encode_png(&frame).expect("encode");
        let out = make_preview(&png16, 256).expect("preview");
        let dec = png::Decoder::new(&out[..]);
        let reader = dec.read_info().expect("png");
        let info = reader.info();
        assert_eq!((info.width, info.height), (256, 128));
        assert_eq!(info.bit_depth, png::BitDepth::Eight);
    }
}

/// The raw frame: a greyscale PNG holding the sensor values (16-bit for >8-bit cameras).
#[utoipa::path(get, path = "/api/v1/runs/{id}/frames/{index}", tag = "runs",
    params(("id" = String, Path, description = "Run id"), ("index" = u64, Path, description = "Image index")),
    responses((status = 200, description = "The frame", content_type = "image/png", body = Vec<u8>),
              (status = 400, description = "Index not a non-negative integer", body = ErrorBody),
              (status = 404, description = "No such run or frame not taken", body = ErrorBody)))]
pub async fn frame_raw(
    State(d): State<AppState>,
    ApiPath((id, index)): ApiPath<(String, String)>,
) -> Result<Response, ApiError> {
    super::frames::raw(&d, &id, &index).await
}

/// An 8-bit preview PNG of a frame, downscaled to at most 256 px on its longer side
/// and stretched to the frame's own maximum.
#[utoipa::path(get, path = "/api/v1/runs/{id}/frames/{index}/preview", tag = "runs",
    params(("id" = String, Path, description = "Run id"), ("index" = u64, Path, description = "Image index")),
    responses((status = 200, description = "The preview", content_type = "image/png", body = Vec<u8>),
              (status = 400, description = "Index not a non-negative integer", body = ErrorBody),
              (status = 404, description = "No such run or frame not taken", body = ErrorBody)))]
pub async fn frame_preview(
    State(d): State<AppState>,
    ApiPath((id, index)): ApiPath<(String, String)>,
) -> Result<Response, ApiError> {
    super::frames::preview(&d, &id, &index).await
}
