//! Frame routes: the frame as stored (rigd's PNG, or the camera's own file:
//! DNG, raw, JPEG), and an 8-bit downscaled preview. The run id
//! must name a known run and the index must be a plain integer below the
//! run's image count; the path is built from those, never from raw input.

use axum::http::header;
use axum::response::{IntoResponse, Response};

use axum::extract::State;

use super::AppState;
use crate::rig::camera_file::{self, FileFormat};
use crate::rig::hal::decode_png;
use crate::server::error::{ApiError, ApiPath, ErrorBody};
use crate::server::supervisor::Daemon;
use crate::store::frame_file_with;

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

/// A stored frame's bytes and the extension it is stored with.
struct StoredFrame {
    bytes: Vec<u8>,
    extension: &'static str,
}

async fn read_frame(d: &Daemon, id: &str, index: &str) -> Result<StoredFrame, ApiError> {
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
    // The name comes from the index and a fixed list of extensions only.
    for extension in std::iter::once("png").chain(camera_file::EXTENSIONS) {
        match super::read_served(root.join(frame_file_with(index, extension))).await {
            Ok(bytes) => return Ok(StoredFrame { bytes, extension }),
            Err(e) if e.io_kind() == Some(std::io::ErrorKind::NotFound) => {}
            Err(e) => return Err(ApiError::internal(e.to_string())),
        }
    }
    Err(ApiError::not_found(format!(
        "frame {index} is not taken yet"
    )))
}

fn png(bytes: Vec<u8>) -> Response {
    image(bytes, "image/png")
}

fn image(bytes: Vec<u8>, content_type: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CACHE_CONTROL, "max-age=3600"),
        ],
        bytes,
    )
        .into_response()
}

/// The MIME type of a frame stored with `extension`.
fn mime_of(extension: &str) -> &'static str {
    match extension {
        "png" => "image/png",
        "dng" => FileFormat::Dng.mime(),
        "jpg" => FileFormat::Jpeg.mime(),
        "tif" => FileFormat::Tiff.mime(),
        _ => "application/octet-stream",
    }
}

/// Image `index` of run `id` as stored: rigd's PNG of raw sensor values,
/// or the camera's own file (DNG, vendor raw, TIFF, JPEG) byte for byte.
/// 400 when `index` is not a plain integer; 404 for an unknown run, an
/// index past the run's image count, or a frame not taken yet.
pub async fn raw(d: &Daemon, id: &str, index: &str) -> Result<Response, ApiError> {
    let frame = read_frame(d, id, index).await?;
    Ok(image(frame.bytes, mime_of(frame.extension)))
}

/// Image `index` of run `id` as an 8-bit PNG, box-filtered to at most
/// [`PREVIEW_MAX`] pixels on its longer side and stretched to its own
/// brightest pixel; the errors of [`raw`].
pub async fn preview(d: &Daemon, id: &str, index: &str) -> Result<Response, ApiError> {
    let bytes = read_frame(d, id, index).await?.bytes;
    let out = tokio::task::spawn_blocking(move || make_preview(&bytes, PREVIEW_MAX))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?
        .map_err(ApiError::internal)?;
    Ok(png(out))
}

/// A stored frame's values for a preview: a PNG's samples, a camera file's
/// light (a mosaic as it is, RGB as the mean of its channels).
fn preview_values(bytes: &[u8]) -> Result<(u32, u32, Vec<f64>), String> {
    if crate::rig::hal::is_png(bytes) {
        let (w, h, px) = decode_png(bytes)?;
        return Ok((w, h, px.into_iter().map(f64::from).collect()));
    }
    let img = camera_file::decode(bytes).map_err(|e| e.to_string())?;
    let linear = img.linear();
    let values = linear
        .chunks_exact(img.channels.max(1))
        .map(|c| c.iter().map(|&v| f64::from(v)).sum::<f64>() / c.len() as f64)
        .collect();
    Ok((img.width, img.height, values))
}

/// Box-filters a stored frame (PNG or camera file) down to at most `max`
/// px on its longer side and stretches it to 8 bits by the frame's own
/// maximum.
pub fn make_preview(frame_bytes: &[u8], max: u32) -> Result<Vec<u8>, String> {
    let (w, h, px) = preview_values(frame_bytes)?;
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
            sums[o] += px[(y * w + x) as usize];
            counts[o] += 1;
        }
    }
    let avg: Vec<f64> = sums
        .iter()
        .zip(&counts)
        .map(|(s, &c)| if c > 0 { s / c as f64 } else { 0.0 })
        .collect();
    let peak = avg.iter().cloned().fold(0.0, f64::max);
    let peak = if peak > 0.0 { peak } else { 1.0 };
    // One PNG writer for every image rigd renders (rigd_process::image_io).
    let image = rigd_process::image_io::Image {
        width: ow as usize,
        height: oh as usize,
        channels: 1,
        data: avg.iter().map(|v| (v / peak) as f32).collect(),
    };
    rigd_process::image_io::encode_png(
        &image,
        rigd_process::image_io::PngDepth::Eight,
        std::path::Path::new("preview.png"),
    )
    .map_err(|e| e.to_string())
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
            original: None,
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

/// The frame as stored: a greyscale PNG holding the sensor values (16-bit for >8-bit cameras),
/// or the camera's own file byte for byte (`image/x-adobe-dng`, `image/jpeg`, `image/tiff`,
/// vendor raw as `application/octet-stream`).
#[utoipa::path(get, path = "/api/v1/runs/{id}/frames/{index}", tag = "runs",
    params(("id" = String, Path, description = "Run id"), ("index" = u64, Path, description = "Image index")),
    responses((status = 200, description = "The frame as stored", content(
                  (Vec<u8> = "image/png"), (Vec<u8> = "image/x-adobe-dng"), (Vec<u8> = "image/jpeg"),
                  (Vec<u8> = "image/tiff"), (Vec<u8> = "application/octet-stream"))),
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
