//! `rigd frame decode`: what rigd makes of a camera's file (DNG, vendor
//! raw, TIFF, JPEG): the camera, the sensor's layout and levels, the
//! exposure, and with `--out` the raw values, the facts and a preview.
//! The file is decoded in the decoder child, as every file from outside is.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use serde::Serialize;

use rigd::rig::camera_file::{self, CameraImage, Encoding, Facts};
use rigd_process::demosaic::DEFAULT_METHOD;
use rigd_process::image_io::{write_png, Image, PngDepth};

use super::exit::bad_input;

/// The `rigd frame` commands.
#[derive(Subcommand)]
pub enum FrameCmd {
    /// Decode a camera file and print what it holds: make and model,
    /// dimensions and active area, the colour filter pattern, black and
    /// white levels, exposure and ISO. With --out, also write raw.npy (the
    /// active area's values, uint16), frame.json (these facts) and
    /// preview.png (white-balanced, demosaiced, sRGB). A file rigd cannot
    /// decode exits 2 naming its format and what is missing.
    Decode(DecodeArgs),
}

/// `rigd frame decode`'s arguments.
#[derive(Args)]
pub struct DecodeArgs {
    /// The camera file (DNG, NEF, CR2, CR3, ARW, RAF, ORF, RW2, PEF, …,
    /// TIFF or JPEG).
    file: PathBuf,
    /// Write raw.npy, frame.json and preview.png into this folder (made if
    /// missing).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print the facts as JSON (frame.json's content) instead of lines.
    #[arg(long)]
    json: bool,
}

/// Runs a `rigd frame` command.
pub fn run(cmd: FrameCmd) -> Result<ExitCode> {
    match cmd {
        FrameCmd::Decode(args) => decode(args)?,
    }
    Ok(ExitCode::SUCCESS)
}

/// What `frame.json` and `--json` say of a file.
#[derive(Serialize)]
struct FrameReport {
    file: String,
    /// The format by its usual name (`DNG`, `NEF`, `JPEG`).
    format: String,
    /// Width and height of the decoded image (a raw file's active area).
    width: u32,
    height: u32,
    /// Samples per pixel: 1 (a mosaic or grey) or 3 (RGB).
    channels: usize,
    /// Mean black and white level, in sample values.
    black: f32,
    white: f32,
    /// Whether samples are linear (raw) or sRGB-encoded (rendered).
    encoding: &'static str,
    #[serde(flatten)]
    facts: Facts,
}

fn report(file: &Path, img: &CameraImage) -> FrameReport {
    FrameReport {
        file: file.display().to_string(),
        format: img.format.name().to_string(),
        width: img.width,
        height: img.height,
        channels: img.channels,
        black: img.black,
        white: img.white,
        encoding: match img.encoding {
            Encoding::Linear => "linear",
            Encoding::Srgb => "srgb",
        },
        facts: img.facts.clone(),
    }
}

fn lines(r: &FrameReport) -> Vec<String> {
    let f = &r.facts;
    let levels = |v: &[f32]| {
        v.iter()
            .map(|x| format!("{x}"))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let camera = format!("{} {}", f.make, f.model);
    let mut out = vec![
        format!("file          {}", r.file),
        format!("format        {}", r.format),
        format!(
            "camera        {}",
            if camera.trim().is_empty() {
                "(not named)"
            } else {
                camera.trim()
            }
        ),
        format!(
            "size          {} x {} ({} channel{})",
            r.width,
            r.height,
            r.channels,
            if r.channels == 1 { "" } else { "s" }
        ),
        format!(
            "sensor        {} x {}, active area {} x {} at ({}, {})",
            f.full_size[0],
            f.full_size[1],
            f.active_area[2],
            f.active_area[3],
            f.active_area[0],
            f.active_area[1]
        ),
        format!(
            "cfa           {}",
            f.cfa_pattern.as_deref().unwrap_or("none")
        ),
        format!("bits          {}", f.bits_per_sample),
    ];
    if f.black_levels.is_empty() {
        out.push(format!(
            "levels        black {}, white {}",
            r.black, r.white
        ));
    } else {
        out.push(format!(
            "levels        black {}, white {}",
            levels(&f.black_levels),
            levels(&f.white_levels)
        ));
    }
    let mut exposure = Vec::new();
    if let Some(t) = f.exposure_s {
        exposure.push(if t > 0.0 && t < 0.5 {
            format!("1/{} s", (1.0 / t).round())
        } else {
            format!("{t} s")
        });
    }
    if let Some(iso) = f.iso {
        exposure.push(format!("ISO {iso}"));
    }
    if let Some(n) = f.f_number {
        exposure.push(format!("f/{n:.1}"));
    }
    if let Some(mm) = f.focal_length_mm {
        exposure.push(format!("{mm:.0} mm"));
    }
    out.push(format!(
        "exposure      {}",
        if exposure.is_empty() {
            "(not recorded)".to_string()
        } else {
            exposure.join(", ")
        }
    ));
    if let Some(wb) = &f.white_balance {
        out.push(format!("white balance {}", levels(wb)));
    }
    out
}

fn decode(args: DecodeArgs) -> Result<()> {
    let name = args.file.display().to_string();
    let bytes = rigd_core::read::read_bounded(&args.file, rigd_core::read::IMAGE_LIMIT)
        .map_err(|e| bad_input(format!("cannot read {e}")))?;
    let img = match camera_file::decode(&bytes) {
        Ok(img) => img,
        Err(e) if e.is_the_file_s() => return Err(bad_input(format!("{name}: {e}"))),
        Err(e) => return Err(anyhow::Error::new(e).context(name)),
    };
    let report = report(&args.file, &img);
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        for line in lines(&report) {
            println!("{line}");
        }
    }
    if let Some(dir) = &args.out {
        write_outputs(dir, &img, &report)?;
        if !args.json {
            println!("-> {}", dir.display());
        }
    }
    Ok(())
}

fn write_outputs(dir: &Path, img: &CameraImage, report: &FrameReport) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot make {}", dir.display()))?;
    let (w, h) = (u64::from(img.width), u64::from(img.height));
    let shape: Vec<u64> = if img.channels == 1 {
        vec![h, w]
    } else {
        vec![h, w, img.channels as u64]
    };
    let mut npy = Vec::with_capacity(img.samples.len() * 2 + 128);
    {
        use npyz::WriterBuilder;
        let mut writer = npyz::WriteOptions::new()
            .default_dtype()
            .shape(&shape)
            .writer(&mut npy)
            .begin_nd()?;
        writer.extend(img.samples.iter().copied())?;
        writer.finish()?;
    }
    let write = |file: &str, bytes: &[u8]| -> Result<()> {
        let path = dir.join(file);
        rigd_core::atomic::write(&path, bytes)
            .map_err(|e| e.error)
            .with_context(|| format!("cannot write {}", path.display()))
    };
    write("raw.npy", &npy)?;
    let mut json = serde_json::to_vec_pretty(report)?;
    json.push(b'\n');
    write("frame.json", &json)?;
    let preview = preview(img).map_err(|e| bad_input(format!("{}: {e}", report.file)))?;
    write_png(&dir.join("preview.png"), &preview, PngDepth::Eight)?;
    Ok(())
}

/// The image as a person would see it: a mosaic white-balanced by the
/// camera's as-shot multipliers, demosaiced as processing does
/// ([`DEFAULT_METHOD`]), turned to linear sRGB by the camera's colour
/// matrix and sRGB encoded; a rendered file as it is.
fn preview(img: &CameraImage) -> Result<Image, String> {
    let (w, h) = (img.width as usize, img.height as usize);
    let linear = img.linear();
    if img.encoding == Encoding::Srgb {
        let data = img
            .samples
            .iter()
            .map(|&s| f32::from(s) / img.white.max(1.0))
            .collect();
        return Ok(Image {
            width: w,
            height: h,
            channels: img.channels,
            data,
        });
    }
    let encode = |v: f32| rigd_core::chart::linear_to_srgb(f64::from(v)) as f32;
    let Some(cfa) = img.cfa else {
        return Ok(Image {
            width: w,
            height: h,
            channels: img.channels,
            data: linear.into_iter().map(encode).collect(),
        });
    };
    // As-shot multipliers relative to green; none recorded, none applied.
    let wb = img
        .facts
        .white_balance
        .as_ref()
        .filter(|wb| wb.len() >= 3 && wb[1] > 0.0 && wb.iter().take(3).all(|m| *m > 0.0))
        .map(|wb| [wb[0] / wb[1], 1.0, wb[2] / wb[1]])
        .unwrap_or([1.0; 3]);
    let balanced: Vec<f32> = linear
        .iter()
        .enumerate()
        .map(|(i, v)| v * wb[cfa.channel_at(i % w, i / w)])
        .collect();
    let planes = rigd_process::demosaic::demosaic(&balanced, w, h, cfa, DEFAULT_METHOD)
        .map_err(|e| e.to_string())?;
    let matrix = img
        .facts
        .xyz_to_camera
        .as_ref()
        .filter(|m| m.len() == 9)
        .and_then(|m| {
            let m = [0, 1, 2].map(|r| [0, 1, 2].map(|c| f64::from(m[3 * r + c])));
            rigd_core::chart::camera_to_linear_srgb(m)
        });
    let mut data = Vec::with_capacity(w * h * 3);
    let [r, g, b] = &planes;
    for ((r, g), b) in r.iter().zip(g).zip(b) {
        let cam = [r, g, b].map(|v| f64::from(*v));
        let rgb = match matrix {
            Some(m) => [0, 1, 2].map(|r| (0..3).map(|k| m[r][k] * cam[k]).sum::<f64>()),
            None => cam,
        };
        data.extend(rgb.map(|v| rigd_core::chart::linear_to_srgb(v) as f32));
    }
    Ok(Image {
        width: w,
        height: h,
        channels: 3,
        data,
    })
}
