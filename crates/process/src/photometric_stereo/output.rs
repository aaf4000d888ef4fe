//! Output.

use super::*;

/// Writes the arrays, renderings and `report.json` into `out_dir` (created
/// if missing), each atomically; returns the written paths.
pub fn write_outputs(result: &PsResult, out_dir: &Path) -> Result<Vec<PathBuf>, PsError> {
    std::fs::create_dir_all(out_dir).map_err(|source| PsError::CreateDir {
        path: out_dir.to_path_buf(),
        source,
    })?;
    let (w, h) = (result.width, result.height);
    let mut written = Vec::new();
    let mut npy_out = |name: &str, shape: &[usize], data: &[f32]| -> Result<(), PsError> {
        let path = out_dir.join(name);
        npy::write_f32(&path, shape, data)?;
        written.push(path);
        Ok(())
    };
    let normals_flat: Vec<f32> = result.normals.iter().flatten().copied().collect();
    npy_out("normals.npy", &[h, w, 3], &normals_flat)?;
    if result.albedo_channels == 1 {
        npy_out("albedo.npy", &[h, w], &result.albedo)?;
    } else {
        npy_out(
            "albedo.npy",
            &[h, w, result.albedo_channels],
            &result.albedo,
        )?;
    }
    npy_out("height.npy", &[h, w], &result.height_map)?;
    npy_out("p.npy", &[h, w], &result.p)?;
    npy_out("q.npy", &[h, w], &result.q)?;

    let mut png_out = |name: &str, image: Image, depth: PngDepth| -> Result<(), PsError> {
        let path = out_dir.join(name);
        image_io::write_png(&path, &image, depth)?;
        written.push(path);
        Ok(())
    };
    png_out(
        "normals.png",
        Image {
            width: w,
            height: h,
            channels: 3,
            data: normals_flat.iter().map(|v| 0.5 * (v + 1.0)).collect(),
        },
        PngDepth::Eight,
    )?;
    // Albedo above 1 (possible after intensity division) is scaled down to fit.
    let albedo_max = result.albedo.iter().copied().fold(0.0f32, f32::max);
    let albedo_scale = if albedo_max > 1.0 {
        1.0 / albedo_max
    } else {
        1.0
    };
    png_out(
        "albedo.png",
        Image {
            width: w,
            height: h,
            channels: result.albedo_channels,
            data: result.albedo.iter().map(|v| v * albedo_scale).collect(),
        },
        PngDepth::Sixteen,
    )?;
    let (lo, hi) = result
        .height_map
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    let span = hi - lo;
    png_out(
        "height.png",
        Image {
            width: w,
            height: h,
            channels: 1,
            data: result
                .height_map
                .iter()
                .map(|&v| if span > 0.0 { (v - lo) / span } else { 0.5 })
                .collect(),
        },
        PngDepth::Sixteen,
    )?;

    let path = out_dir.join("report.json");
    rigd_core::atomic::write(&path, report_json(&result.report).as_bytes()).map_err(|e| {
        PsError::Write {
            path: path.clone(),
            source: e.error,
        }
    })?;
    written.push(path);
    Ok(written)
}

pub(super) fn json_string(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for ch in s.chars() {
        match ch {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if (c as u32) < 0x20 => out.push_str(&format!("\\u{:04x}", c as u32)),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

pub(super) fn json_number(v: f64) -> String {
    if v.is_finite() {
        format!("{v:?}")
    } else {
        "null".into()
    }
}

pub(super) fn json_vec3(v: &[f64; 3]) -> String {
    format!(
        "[{}, {}, {}]",
        json_number(v[0]),
        json_number(v[1]),
        json_number(v[2])
    )
}

/// `report.json`: hand-written to keep the crate free of a JSON dependency.
pub(super) fn report_json(r: &PsReport) -> String {
    let images: Vec<String> = r
        .images
        .iter()
        .enumerate()
        .map(|(i, name)| {
            let intensity = r
                .intensities
                .as_ref()
                .and_then(|t| t.get(i))
                .map_or_else(|| "null".to_string(), json_vec3);
            format!(
                "    {{\"name\": {}, \"light\": {}, \"intensity\": {intensity}}}",
                json_string(name),
                r.lights
                    .get(i)
                    .map_or_else(|| "null".to_string(), json_vec3)
            )
        })
        .collect();
    format!(
        "{{\n  \"method\": \"photometric-stereo\",\n  \"mode\": \"{mode}\",\n  \
         \"frame\": \"x right (column), y up (row decreasing), z towards the camera\",\n  \
         \"width\": {w},\n  \"height\": {h},\n  \"channels\": {c},\n  \
         \"lights_used\": {nl},\n  \"condition_number\": {cond},\n  \"mean_residual\": {res},\n  \
         \"pixels_total\": {pt},\n  \"pixels_valid\": {pv},\n  \"pixels_masked\": {pm},\n  \
         \"pixels_dark\": {pd},\n  \"pixels_saturated\": {ps},\n  \"pixels_facing_away\": {pf},\n  \
         \"pixels_fallback\": {pfb},\n  \"samples_rejected_shadow\": {rs},\n  \
         \"samples_rejected_specular\": {rsp},\n  \"samples_rejected_saturated\": {rsat},\n  \
         \"images\": [\n{images}\n  ]\n}}\n",
        mode = if r.robust { "robust" } else { "plain" },
        w = r.width,
        h = r.height,
        c = r.channels,
        nl = r.lights.len(),
        cond = json_number(r.condition_number),
        res = json_number(r.mean_residual),
        pt = r.pixels_total,
        pv = r.pixels_valid,
        pm = r.pixels_masked,
        pd = r.pixels_dark,
        ps = r.pixels_saturated,
        pf = r.pixels_facing_away,
        pfb = r.pixels_fallback,
        rs = r.samples_rejected_shadow,
        rsp = r.samples_rejected_specular,
        rsat = r.samples_rejected_saturated,
        images = images.join(",\n"),
    )
}
