//! Merge.

use super::*;

/// Unsigned volume of the tetrahedron `a, b, c, d`.
pub fn tetrahedron_volume(a: [f64; 3], b: [f64; 3], c: [f64; 3], d: [f64; 3]) -> f64 {
    let v = dot(sub(b, a), cross(sub(c, a), sub(d, a))).abs() / 6.0;
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

/// Wang et al.'s merge weight of a scan (§3.2, after the error analysis of
/// [2]): the volume of the tetrahedron formed by the laser source position,
/// the camera location, and two points on the laser line passing through
/// the turntable centre. The laser strip on the turntable is orthogonal to
/// the scan direction (§3.1), which is the source's horizontal direction,
/// so the line through the centre runs along `unit(ẑ × source)`; the two
/// points are `±half_length` along it (any fixed length: only ratios of
/// weights matter). The volume vanishes when the camera lies in that laser
/// plane (triangulation ill-conditioned).
pub fn wang_source_weight(
    source: [f64; 3],
    camera_centre: [f64; 3],
    half_length: f64,
) -> Result<f64, MdfError> {
    if !(finite3(source) && finite3(camera_centre) && half_length.is_finite() && half_length > 0.0)
    {
        return Err(MdfError::InvalidInput(format!(
            "source {source:?}, camera {camera_centre:?}, half length {half_length}"
        )));
    }
    let u = unit(cross([0.0, 0.0, 1.0], source)).ok_or_else(|| {
        MdfError::InvalidInput(format!(
            "source {source:?} is above the turntable centre: no scan direction"
        ))
    })?;
    Ok(tetrahedron_volume(
        source,
        camera_centre,
        scale(u, half_length),
        scale(u, -half_length),
    ))
}

/// Merges the displacement images of several laser source positions with
/// Wang et al.'s tetrahedron weights ([`wang_source_weight`] with
/// `half_length` metres); see [`merge_weighted`].
pub fn merge(
    displacements: &[DisplacementImage],
    source_positions: &[[f64; 3]],
    camera: &PinholeCamera,
    half_length: f64,
    use_pixel_confidence: bool,
) -> Result<DisplacementImage, MdfError> {
    camera.validate()?;
    if displacements.len() != source_positions.len() {
        return Err(MdfError::SourceCount {
            count: displacements.len(),
            sources: source_positions.len(),
        });
    }
    let weights: Vec<f64> = source_positions
        .iter()
        .map(|&s| wang_source_weight(s, camera.centre, half_length))
        .collect::<Result<_, _>>()?;
    merge_weighted(displacements, &weights, use_pixel_confidence)
}

/// `D_v(x,y) = Σ w_i D_{v,l_i}(x,y) / Σ w_i` over the scans with
/// `D_{v,l_i}(x,y) ≠ −1` (Wang et al., §3.2). With `use_pixel_confidence` each
/// term's weight is `w_i` times the pixel's [`space_time`] confidence
/// (Wang et al.'s formula is `false`). A pixel with no valid scan, or whose
/// weights sum to 0, stays −1. The output weight is the sum of the weights
/// used.
pub fn merge_weighted(
    displacements: &[DisplacementImage],
    weights: &[f64],
    use_pixel_confidence: bool,
) -> Result<DisplacementImage, MdfError> {
    if displacements.len() != weights.len() {
        return Err(MdfError::SourceCount {
            count: displacements.len(),
            sources: weights.len(),
        });
    }
    let first = displacements
        .first()
        .ok_or_else(|| MdfError::InvalidInput("no displacement images to merge".into()))?;
    let size = (first.width, first.height);
    for (i, d) in displacements.iter().enumerate() {
        d.check(i, size)?;
    }
    if let Some(w) = weights.iter().find(|w| !(w.is_finite() && **w >= 0.0)) {
        return Err(MdfError::InvalidInput(format!("scan weight {w}")));
    }
    let n = size.0 * size.1;
    let (depth, weight): (Vec<f32>, Vec<f32>) = (0..n)
        .into_par_iter()
        .map(|p| {
            let (mut sw, mut swd) = (0.0f64, 0.0f64);
            for (d, &wi) in displacements.iter().zip(weights) {
                let v = d.depth[p];
                if !(v >= 0.0 && v.is_finite()) {
                    continue;
                }
                let c = if use_pixel_confidence {
                    f64::from(d.weight[p]).max(0.0)
                } else {
                    1.0
                };
                let wt = wi * c;
                if wt.is_finite() {
                    sw += wt;
                    swd += wt * f64::from(v);
                }
            }
            if sw > 0.0 && (swd / sw).is_finite() {
                ((swd / sw) as f32, sw as f32)
            } else {
                (NO_DEPTH, 0.0)
            }
        })
        .unzip();
    Ok(DisplacementImage {
        width: size.0,
        height: size.1,
        depth,
        weight,
    })
}
