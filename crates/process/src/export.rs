//! Export of registered BTF textures in the layouts existing BTF tools read,
//! and the readers that bring them back:
//!
//! - **UTIA** (`Format::Utia`): a folder per view, `tv{θv:03}_pv{φv:03}/`,
//!   holding one 8-bit PNG per light named
//!   `tl{θl:03}_pl{φl:03}_tv{θv:03}_pv{φv:03}.png`;
//! - **UBO2003** (`Format::Ubo2003`): a zip of 8-bit JPEG images named
//!   `tl{ttt} pl{ppp} tv{ttt} pv{ppp}.jpg` (spaces, integer degrees), as the
//!   Bonn 2003 BTF database ships.
//!
//! Angles are rounded to whole degrees, as both formats name them; two
//! measured directions that round to the same name are an error rather
//! than a silent overwrite. Textures are grey or RGB (linear sRGB, the
//! channels interleaved), values in [0, 1]; RGB textures are written as
//! RGB PNGs and 3-channel JPEGs, as the Bonn database's are, and read back
//! as RGB.

use std::collections::BTreeSet;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use crate::directions::Direction;
use crate::image_io::{self, Image, PngDepth};

/// The export formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// UTIA layout: a folder per view holding one 8-bit PNG per light.
    Utia,
    /// Bonn 2003 (UBO2003) layout: a zip of 8-bit JPEGs.
    Ubo2003,
}

impl std::str::FromStr for Format {
    type Err = String;
    fn from_str(s: &str) -> Result<Format, String> {
        match s {
            "utia" => Ok(Format::Utia),
            "ubo2003" => Ok(Format::Ubo2003),
            _ => Err(format!("unknown format `{s}` (known: utia, ubo2003)")),
        }
    }
}

/// One texture and the directions it was measured under.
#[derive(Debug, Clone)]
pub struct Texture {
    /// Light direction the texture was measured under.
    pub light: Direction,
    /// View direction the texture was measured from.
    pub view: Direction,
    /// The texture: grey (1 channel) or RGB (3), values in [0, 1], at most
    /// 65535 pixels a side.
    pub image: Image,
}

/// Why exporting or importing textures failed.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// Creating, listing, reading or writing a file, folder or zip failed,
    /// or an image in it could not be encoded or decoded.
    #[error("{}: {message}", path.display())]
    Io {
        /// The file, folder or zip concerned.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// Two textures' directions round to the same file name in whole degrees.
    #[error("two textures would both be written as `{name}` (the format names a texture by its directions in whole degrees): {first}, and {second}")]
    NameClash {
        /// The shared file name.
        name: String,
        /// Light and view of the first texture with that name.
        first: String,
        /// Light and view of the second texture with that name.
        second: String,
    },
    /// On import, an image's name does not parse as `tl…pl…tv…pv…`.
    #[error("{}: `{name}` is not a name this format uses", path.display())]
    BadName {
        /// The PNG file, or the zip holding the entry.
        path: PathBuf,
        /// The name that did not parse.
        name: String,
    },
    /// A texture to export is neither grey nor RGB, or has a side of 0 or
    /// more than 65535
    /// pixels.
    #[error("texture for {what} is {width}x{height} with {channels} channels: expected grey or RGB, at most 65535 pixels a side")]
    BadTexture {
        /// The file name the texture would have had.
        what: String,
        /// Its width, pixels.
        width: usize,
        /// Its height, pixels.
        height: usize,
        /// Its channel count (only 1 can be exported).
        channels: usize,
    },
}

/// The largest file a UBO2003 zip may hold, bytes: a JPEG of the largest
/// texture with room to spare.
pub const MAX_ENTRY_BYTES: u64 = 256 << 20;

fn io_err(path: &Path, e: impl std::fmt::Display) -> ExportError {
    ExportError::Io {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// Whole degrees for a file name: θ in 0 ..= 90, φ in 0 ..= 359 (the pole's
/// φ is written as 0).
fn degrees(d: Direction) -> (u32, u32) {
    let theta = d.theta_deg.round().clamp(0.0, 90.0) as u32;
    let phi = if theta == 0 {
        0
    } else {
        (d.phi_deg.rem_euclid(360.0).round() as u32) % 360
    };
    (theta, phi)
}

fn utia_view_dir(v: Direction) -> String {
    let (t, p) = degrees(v);
    format!("tv{t:03}_pv{p:03}")
}

fn utia_name(l: Direction, v: Direction) -> String {
    let ((tl, pl), (tv, pv)) = (degrees(l), degrees(v));
    format!("tl{tl:03}_pl{pl:03}_tv{tv:03}_pv{pv:03}.png")
}

fn ubo_name(l: Direction, v: Direction) -> String {
    let ((tl, pl), (tv, pv)) = (degrees(l), degrees(v));
    format!("tl{tl:03} pl{pl:03} tv{tv:03} pv{pv:03}.jpg")
}

/// Parses `tl…pl…tv…pv…` names of either format (separators `_` or ` `).
fn parse_name(stem: &str) -> Option<(Direction, Direction)> {
    let parts: Vec<&str> = stem.split(['_', ' ']).collect();
    let [tl, pl, tv, pv] = parts[..] else {
        return None;
    };
    let num = |s: &str, prefix: &str| s.strip_prefix(prefix)?.parse::<u32>().ok().map(f64::from);
    Some((
        Direction::new(num(tl, "tl")?, num(pl, "pl")?),
        Direction::new(num(tv, "tv")?, num(pv, "pv")?),
    ))
}

/// A texture's light and view in words, to a thousandth of a degree.
fn directions(t: &Texture) -> String {
    format!(
        "light θ {:.3}° φ {:.3}°, view θ {:.3}° φ {:.3}°",
        t.light.theta_deg, t.light.phi_deg, t.view.theta_deg, t.view.phi_deg
    )
}

fn check_names<'a>(
    textures: &'a [Texture],
    name: impl Fn(&Texture) -> String,
) -> Result<(), ExportError> {
    let mut seen: std::collections::BTreeMap<String, &'a Texture> = Default::default();
    for t in textures {
        let n = name(t);
        if let Some(first) = seen.get(&n) {
            return Err(ExportError::NameClash {
                name: n,
                first: directions(first),
                second: directions(t),
            });
        }
        let img = &t.image;
        if !(img.channels == 1 || img.channels == 3)
            || img.width > 65535
            || img.height > 65535
            || img.width == 0
            || img.height == 0
        {
            return Err(ExportError::BadTexture {
                what: n,
                width: img.width,
                height: img.height,
                channels: img.channels,
            });
        }
        seen.insert(n, t);
    }
    Ok(())
}

fn codes8(image: &Image) -> Vec<u8> {
    image
        .data
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect()
}

/// Writes the textures to `out` in `format`; returns the files written.
/// UBO2003 JPEGs use `jpeg_quality` (1 ..= 100).
pub fn write(
    textures: &[Texture],
    format: Format,
    out: &Path,
    jpeg_quality: u8,
) -> Result<usize, ExportError> {
    match format {
        Format::Utia => {
            check_names(textures, |t| {
                format!("{}/{}", utia_view_dir(t.view), utia_name(t.light, t.view))
            })?;
            for t in textures {
                let dir = out.join(utia_view_dir(t.view));
                std::fs::create_dir_all(&dir).map_err(|e| io_err(&dir, e))?;
                image_io::write_png(
                    &dir.join(utia_name(t.light, t.view)),
                    &t.image,
                    PngDepth::Eight,
                )
                .map_err(|e| io_err(&dir, e))?;
            }
            Ok(textures.len())
        }
        Format::Ubo2003 => {
            check_names(textures, |t| ubo_name(t.light, t.view))?;
            if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
                std::fs::create_dir_all(parent).map_err(|e| io_err(parent, e))?;
            }
            let options = zip::write::SimpleFileOptions::default()
                .compression_method(zip::CompressionMethod::Stored);
            rigd_core::atomic::write_with(out, |file| {
                let mut zip = zip::ZipWriter::new(file);
                for t in textures {
                    let name = ubo_name(t.light, t.view);
                    let mut jpeg = Vec::new();
                    jpeg_encoder::Encoder::new(&mut jpeg, jpeg_quality.clamp(1, 100))
                        .encode(
                            &codes8(&t.image),
                            t.image.width as u16,
                            t.image.height as u16,
                            if t.image.channels == 3 {
                                jpeg_encoder::ColorType::Rgb
                            } else {
                                jpeg_encoder::ColorType::Luma
                            },
                        )
                        .map_err(|e| std::io::Error::other(format!("{name}: {e}")))?;
                    zip.start_file(name.as_str(), options)
                        .map_err(std::io::Error::other)?;
                    zip.write_all(&jpeg)?;
                }
                zip.finish().map_err(std::io::Error::other)?;
                Ok(())
            })
            .map_err(|e| io_err(out, e))?;
            Ok(textures.len())
        }
    }
}

/// Reads textures written in `format` (by [`write`] or by the databases
/// these formats come from), sorted by view then light.
pub fn read(format: Format, path: &Path) -> Result<Vec<Texture>, ExportError> {
    let mut out = Vec::new();
    match format {
        Format::Utia => {
            let mut files = BTreeSet::new();
            for view in std::fs::read_dir(path).map_err(|e| io_err(path, e))? {
                let view = view.map_err(|e| io_err(path, e))?.path();
                if !view.is_dir() {
                    continue;
                }
                for f in std::fs::read_dir(&view).map_err(|e| io_err(&view, e))? {
                    let f = f.map_err(|e| io_err(&view, e))?.path();
                    if f.extension().is_some_and(|e| e == "png") {
                        files.insert(f);
                    }
                }
            }
            for f in files {
                let stem = f
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default();
                let (light, view) = parse_name(&stem).ok_or_else(|| ExportError::BadName {
                    path: f.clone(),
                    name: stem.clone(),
                })?;
                let image = image_io::load_png(&f).map_err(|e| io_err(&f, e))?;
                out.push(Texture { light, view, image });
            }
        }
        Format::Ubo2003 => {
            let file = std::fs::File::open(path).map_err(|e| io_err(path, e))?;
            let mut zip =
                zip::ZipArchive::new(std::io::BufReader::new(file)).map_err(|e| io_err(path, e))?;
            for i in 0..zip.len() {
                let mut entry = zip.by_index(i).map_err(|e| io_err(path, e))?;
                let name = entry.name().to_string();
                let Some(stem) = name.rsplit('/').next().and_then(|n| n.strip_suffix(".jpg"))
                else {
                    continue;
                };
                let (light, view) = parse_name(stem).ok_or_else(|| ExportError::BadName {
                    path: path.to_path_buf(),
                    name: name.clone(),
                })?;
                // A deflated entry can claim anything and inflate without
                // end: read no more than a texture can be.
                let too_big = || {
                    io_err(
                        path,
                        format!(
                            "{name}: more than {MAX_ENTRY_BYTES} bytes, larger than any texture"
                        ),
                    )
                };
                if entry.size() > MAX_ENTRY_BYTES {
                    return Err(too_big());
                }
                let mut bytes = Vec::new();
                (&mut entry)
                    .take(MAX_ENTRY_BYTES + 1)
                    .read_to_end(&mut bytes)
                    .map_err(|e| io_err(path, format!("{name}: {e}")))?;
                if bytes.len() as u64 > MAX_ENTRY_BYTES {
                    return Err(too_big());
                }
                let image =
                    decode_jpeg(&bytes).map_err(|m| io_err(path, format!("{name}: {m}")))?;
                out.push(Texture { light, view, image });
            }
        }
    }
    out.sort_by(|a, b| {
        let key = |t: &Texture| (degrees(t.view), degrees(t.light));
        key(a).cmp(&key(b))
    });
    Ok(out)
}

/// A JPEG as an image in [0, 1]: grey for a one-component JPEG, RGB for a
/// colour one.
fn decode_jpeg(bytes: &[u8]) -> Result<Image, String> {
    let jpeg = crate::image_io::decode_jpeg(bytes)?;
    let mut image = Image::new(jpeg.width, jpeg.height, jpeg.channels);
    for (d, p) in image.data.iter_mut().zip(jpeg.samples) {
        *d = f32::from(p) / 255.0;
    }
    Ok(image)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_follow_each_format() {
        let (l, v) = (Direction::new(17.0, 345.0), Direction::new(85.0, 0.4));
        assert_eq!(utia_name(l, v), "tl017_pl345_tv085_pv000.png");
        assert_eq!(ubo_name(l, v), "tl017 pl345 tv085 pv000.jpg");
        // The pole has no azimuth; 359.6° wraps to 0.
        assert_eq!(degrees(Direction::new(0.0, 123.0)), (0, 0));
        assert_eq!(degrees(Direction::new(30.0, 359.6)), (30, 0));
        assert_eq!(
            parse_name("tl017 pl345 tv085 pv000").map(|(l, _)| l.theta_deg),
            Some(17.0)
        );
        assert!(parse_name("tl17_pl345").is_none());
    }

    #[test]
    fn a_name_clash_says_what_collides_in_words() {
        let t = |theta: f64| Texture {
            light: Direction::new(theta, 0.0),
            view: Direction::new(20.0, 90.0),
            image: Image::new(2, 2, 1),
        };
        let clash = check_names(&[t(30.0), t(29.999999999999996)], |t| {
            utia_name(t.light, t.view)
        })
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
        assert!(!clash.contains("Direction"), "{clash}");
        assert!(
            clash.contains("tl030_pl000_tv020_pv090.png")
                && clash.contains("light θ 30.000° φ 0.000°, view θ 20.000° φ 90.000°"),
            "{clash}"
        );
    }
}
