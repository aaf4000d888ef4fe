//! Loading.

use super::*;

/// Reads the light table, image list, images, intensities and mask.
pub fn load_inputs(inputs: &PsInputs) -> Result<PsDataset, PsError> {
    let lights = read_table(&inputs.lights_file, &[3], true)?;
    let (paths, listing) = match &inputs.names_file {
        Some(names) => (read_names(names, &inputs.images_dir)?, names.clone()),
        None => (
            list_pngs(&inputs.images_dir, inputs.mask_file.as_deref())?,
            inputs.images_dir.clone(),
        ),
    };
    let images_origin = listing.display().to_string();
    if lights.len() != paths.len() {
        return Err(PsError::CountMismatch {
            path: inputs.lights_file.clone(),
            what: "light directions",
            found: lights.len(),
            expected: paths.len(),
            images: images_origin,
        });
    }
    let intensities = match &inputs.intensities_file {
        Some(file) => {
            let table = read_table(file, &[1, 3], false)?;
            if table.len() != paths.len() {
                return Err(PsError::CountMismatch {
                    path: file.clone(),
                    what: "intensities",
                    found: table.len(),
                    expected: paths.len(),
                    images: images_origin,
                });
            }
            Some(table)
        }
        None => None,
    };
    let images: Vec<Image> = paths
        .par_iter()
        .map(|p| image_io::load_png(p))
        .collect::<Result<_, _>>()?;
    let image_names: Vec<String> = paths.iter().map(|p| p.display().to_string()).collect();
    check_images(&images, &image_names)?;
    let mask = match &inputs.mask_file {
        Some(file) => {
            let m = image_io::load_png(file)?;
            let first = &images[0];
            if (m.width, m.height) != (first.width, first.height) {
                return Err(PsError::MaskMismatch {
                    mask: file.display().to_string(),
                    expected: format!("{}x{}", first.width, first.height),
                    found: format!("{}x{}", m.width, m.height),
                });
            }
            Some(
                m.data
                    .chunks(m.channels)
                    .map(|px| px.iter().any(|&v| v > 0.0))
                    .collect(),
            )
        }
        None => None,
    };
    Ok(PsDataset {
        image_names,
        images,
        lights,
        intensities,
        mask,
        lights_origin: inputs.lights_file.display().to_string(),
    })
}

pub(super) fn read_text(path: &Path) -> Result<String, PsError> {
    std::fs::read_to_string(path)
        .map(|text| rigd_core::read::strip_bom(&text).to_owned())
        .map_err(|source| PsError::Read {
            path: path.to_path_buf(),
            source,
        })
}

/// Non-blank, non-comment lines with their 1-based line numbers.
pub(super) fn content_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().filter_map(|(i, line)| {
        let line = line.split('#').next().unwrap_or("").trim();
        (!line.is_empty()).then_some((i + 1, line))
    })
}

/// Reads one vector per line with one of `arities` components. Lights
/// (`directions`) must be non-zero and are normalised; intensities must be
/// positive. A single intensity applies to all three channels.
pub(super) fn read_table(
    path: &Path,
    arities: &[usize],
    directions: bool,
) -> Result<Vec<[f64; 3]>, PsError> {
    let text = read_text(path)?;
    let parse_err = |line: usize, reason: String| PsError::Parse {
        path: path.to_path_buf(),
        line,
        reason,
    };
    let expected = if directions {
        "`x y z`"
    } else {
        "`r g b` or a single intensity"
    };
    let mut rows = Vec::new();
    for (line_no, line) in content_lines(&text) {
        let fields: Vec<&str> = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|f| !f.is_empty())
            .collect();
        if !arities.contains(&fields.len()) {
            return Err(parse_err(
                line_no,
                format!("expected {expected}, found {} values", fields.len()),
            ));
        }
        let mut values = Vec::with_capacity(3);
        for f in &fields {
            let v: f64 = f
                .parse()
                .map_err(|_| parse_err(line_no, format!("'{f}' is not a number")))?;
            if !v.is_finite() {
                return Err(parse_err(line_no, format!("'{f}' is not finite")));
            }
            values.push(v);
        }
        let v = if values.len() == 1 {
            [values[0]; 3]
        } else {
            [values[0], values[1], values[2]]
        };
        if directions {
            let norm = dot(v, v).sqrt();
            if !(norm > 0.0 && norm.is_finite()) {
                return Err(parse_err(line_no, "light direction has zero length".into()));
            }
            rows.push([v[0] / norm, v[1] / norm, v[2] / norm]);
        } else {
            if v.iter().any(|&x| x <= 0.0) {
                return Err(parse_err(line_no, "intensities must be positive".into()));
            }
            rows.push(v);
        }
    }
    Ok(rows)
}

pub(super) fn read_names(names_file: &Path, dir: &Path) -> Result<Vec<PathBuf>, PsError> {
    let text = read_text(names_file)?;
    let names: Vec<PathBuf> = content_lines(&text)
        .map(|(_, name)| dir.join(name))
        .collect();
    if names.is_empty() {
        return Err(PsError::NoImages {
            path: names_file.to_path_buf(),
        });
    }
    Ok(names)
}

pub(super) fn list_pngs(dir: &Path, exclude: Option<&Path>) -> Result<Vec<PathBuf>, PsError> {
    let read_err = |source| PsError::Read {
        path: dir.to_path_buf(),
        source,
    };
    // The mask may live next to the images; it is not one of them.
    let exclude = exclude.and_then(|p| p.canonicalize().ok());
    let mut paths = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(read_err)? {
        let path = entry.map_err(read_err)?.path();
        let is_png = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("png"));
        if is_png && path.is_file() && (exclude.is_none() || path.canonicalize().ok() != exclude) {
            paths.push(path);
        }
    }
    paths.sort_by(|a, b| a.file_name().cmp(&b.file_name()));
    if paths.is_empty() {
        return Err(PsError::NoImages {
            path: dir.to_path_buf(),
        });
    }
    Ok(paths)
}

pub(super) fn describe(image: &Image) -> String {
    let kind = match image.channels {
        1 => "grey",
        3 => "RGB",
        _ => "?",
    };
    format!("{}x{} {kind}", image.width, image.height)
}

pub(super) fn check_images(images: &[Image], names: &[String]) -> Result<(), PsError> {
    let Some(first) = images.first() else {
        return Err(PsError::InvalidInput {
            origin: "images".into(),
            reason: "no images".into(),
        });
    };
    for (image, name) in images.iter().zip(names) {
        let consistent = image.channels == first.channels
            && image.width == first.width
            && image.height == first.height;
        if !consistent {
            return Err(PsError::ImageMismatch {
                image: name.clone(),
                expected: describe(first),
                found: describe(image),
            });
        }
        if !(image.channels == 1 || image.channels == 3)
            || image.data.len() != image.width * image.height * image.channels
        {
            return Err(PsError::InvalidInput {
                origin: name.clone(),
                reason: format!(
                    "{} samples for {} channels of {}x{} (expected 1 or 3 channels)",
                    image.data.len(),
                    image.channels,
                    image.width,
                    image.height
                ),
            });
        }
        if image.width == 0 || image.height == 0 {
            return Err(PsError::InvalidInput {
                origin: name.clone(),
                reason: "empty image".into(),
            });
        }
    }
    Ok(())
}
