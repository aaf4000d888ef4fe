//! [`rectify_run`]: every frame of a run through the steps of
//! [`super::steps`], in the order that lets the fallbacks learn from the
//! frames the markers registered.

use super::resume::FirstPassCache;
use super::steps::*;
use super::*;

/// Registers every frame of a run and resamples the sample square to a
/// frontal texture, then writes the textures and
/// `processed/normtextures/index.json`. It never gives up on the dataset
/// for a few bad frames:
/// - a frame is registered by its holder markers where they are found
///   (`markers`);
/// - otherwise from the rig's achieved pose through the camera model,
///   corrected by the holder's offset that the marker-registered frames
///   measure (`pose`), and shifted onto a marker-registered frame of the
///   same view slot by the sample's texture where that finds a clear match
///   (`pose+texture`);
/// - a frame that is lost, damaged (its file fails the SHA-256 its journal
///   line recorded: flagged `damaged`), black or saturated is filled from
///   its view slot's nearest lights (`interpolated`).
///
/// Each frame records its method and an error estimate. The call fails
/// only when a whole view slot has no usable frame, naming it and why
/// (after every other texture and the index are written).
pub fn rectify_run(
    run: &RunFrames,
    cfg: &RectifyConfig,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<NormtextureIndex, ProcessError> {
    use rayon::prelude::*;
    use rigd_process::rectify as rect;
    check_config(cfg)?;
    let cfg = &cfg.for_run(&run.meta);
    let (holder, layout) = holder_layout(&run.meta)?;
    let out_dir = crate::store::processed::normtextures_dir(&run.root);
    crate::postprocess::create_dir(&out_dir)?;
    let region = layout.sample_region();
    let rectifier = Rectifier {
        run,
        cfg,
        holder,
        layout,
        out_dir: out_dir.clone(),
        colour: super::colour::texture_colour(run, true)?,
        lamp: None,
    }
    .with_lamp();
    let (lights, views, slots) = assign_slots(&run.entries);
    let done = std::sync::atomic::AtomicUsize::new(0);
    let total = run.entries.len();
    let tick = || {
        let n = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        progress(n.min(total), total);
    };
    let bit_depth = run.entries.first().map_or(8, |e| e.bit_depth);

    // 1. Markers, where they are found; frames an interrupted run of this
    // step had done come from its store.
    let store = FirstPassCache::new(&out_dir, cfg, &rectifier);
    let resumed = std::sync::atomic::AtomicUsize::new(0);
    let mut first: Vec<FirstPass> = slots
        .par_iter()
        .enumerate()
        .map(|(position, &(view_slot, light_index))| {
            let entry = &run.entries[position];
            let f = match store.load(entry, position, view_slot, light_index) {
                Some(f) => {
                    resumed.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    f
                }
                None => {
                    let f = rectifier.first_pass(position, view_slot, light_index);
                    store.keep(entry, view_slot, light_index, &f);
                    f
                }
            };
            // Progress follows this pass, which reads every frame; the
            // fallbacks after it are a few frames in a healthy run.
            tick();
            f
        })
        .collect();

    // 2. Black frames, against their slot's nearest lights.
    let black: Vec<(usize, f32)> = (0..first.len())
        .filter(|&i| !first[i].unusable && first[i].p99 < BLACK_P99)
        .filter_map(|i| {
            let own = lights[first[i].rec.light_index].to_vector();
            let mut near: Vec<(f64, f32)> = first
                .iter()
                .enumerate()
                .filter(|(j, f)| {
                    *j != i && f.rec.view_slot == first[i].rec.view_slot && !f.unusable
                })
                .map(|(_, f)| {
                    let l = lights[f.rec.light_index].to_vector();
                    (-(own[0] * l[0] + own[1] * l[1] + own[2] * l[2]), f.p99)
                })
                .collect();
            near.sort_by(|a, b| a.0.total_cmp(&b.0));
            let reference = near
                .iter()
                .take(2)
                .map(|n| n.1)
                .fold(f32::INFINITY, f32::min);
            let p99 = first[i].p99;
            let black =
                p99 < BLACK_FLOOR || (reference.is_finite() && p99 < BLACK_RATIO * reference);
            black.then_some((i, reference))
        })
        .collect();
    for (i, reference) in black {
        let f = &mut first[i];
        f.unusable = true;
        f.markers = None;
        if let Some(stale) = f.rec.file.take() {
            // Its markers were found in the dark; the fill replaces it, or
            // nothing does.
            let _ = std::fs::remove_file(out_dir.join(stale));
        }
        f.rec.method = None;
        f.rec.error_px = None;
        f.rec.problem = Some(if reference.is_finite() {
            format!(
                "black: its 99th percentile is {:.2} % of full scale, its slot's nearest lights reach {:.2} %",
                100.0 * f.p99,
                100.0 * reference
            )
        } else {
            format!(
                "black: its 99th percentile is {:.2} % of full scale",
                100.0 * f.p99
            )
        });
    }

    // 3. The holder's offset from the pose model, measured where both
    // exist; marker fits too few to reveal an outlier that land far from
    // the calibrated pose are not trusted, and the offset is fitted again
    // without them.
    let pairs_of = |first: &[FirstPass]| -> Vec<(usize, rect::Homography, rect::Homography)> {
        first
            .iter()
            .enumerate()
            .filter_map(|(i, f)| Some((i, f.pose?, f.markers?)))
            .collect()
    };
    let fit = |pairs: &[(usize, rect::Homography, rect::Homography)]| {
        let hs: Vec<(rect::Homography, rect::Homography)> =
            pairs.iter().map(|(_, p, m)| (*p, *m)).collect();
        rect::fit_plate_offset(&hs, region).unwrap_or([0.0, 0.0])
    };
    // First from the fits that could reject an outlier, if there are any.
    let all_pairs = pairs_of(&first);
    let trusted: Vec<_> = all_pairs
        .iter()
        .filter(|(i, _, _)| first[*i].rec.markers_used >= rigd_process::rectify::MIN_FOR_REJECTION)
        .cloned()
        .collect();
    let first_offset = fit(if trusted.is_empty() {
        &all_pairs
    } else {
        &trusted
    });
    let disagreements: Vec<(usize, f64)> = all_pairs
        .iter()
        .filter_map(|(i, p, m)| {
            Some((
                *i,
                rect::disagreement_px(&rect::shift_plate(p, first_offset), m, region)?,
            ))
        })
        .collect();
    let median_disagreement = spread(
        &disagreements
            .iter()
            .filter(|(i, _)| trusted.is_empty() || trusted.iter().any(|t| t.0 == *i))
            .map(|d| d.1)
            .collect::<Vec<_>>(),
    )
    .map_or(0.0, |s| s[0]);
    let doubt = MARKER_DOUBT_PX.max(MARKER_DOUBT_FACTOR * median_disagreement);
    for &(i, d) in &disagreements {
        let f = &mut first[i];
        if d > doubt && f.rec.markers_used < rigd_process::rectify::MIN_FOR_REJECTION {
            f.markers = None;
            f.rec.method = None;
            f.rec.error_px = None;
            if let Some(doubted) = f.rec.file.take() {
                // The pose's texture replaces it, or the fill does.
                let _ = std::fs::remove_file(out_dir.join(doubted));
            }
            f.rec.problem = Some(format!(
                "the markers' fit lands {d:.1} px from the calibrated pose at the sample, and {} markers cannot reveal an outlier",
                f.rec.markers_used
            ));
        }
    }
    let pairs = pairs_of(&first);
    let offset = fit(&pairs);
    let both: Vec<(&rect::Homography, &rect::Homography)> =
        pairs.iter().map(|(_, p, m)| (p, m)).collect();
    let p95_against_markers = |shift: [f64; 2]| {
        let d: Vec<f64> = both
            .iter()
            .filter_map(|(p, m)| rect::disagreement_px(&rect::shift_plate(p, shift), m, region))
            .collect();
        spread(&d).map(|s| s[1])
    };
    let pose_error_px = p95_against_markers(offset);
    let uncalibrated_pose_error_px = p95_against_markers([0.0, 0.0]);

    // 4. The marker-registered frame each frame's texture is aligned to:
    // the one of its view slot with the nearest light, whose shading is
    // most alike (under lights far apart a relief's bright flanks swap
    // sides, and the correlation would lock on to that).
    let reference_of = |i: usize| -> Option<usize> {
        let own = lights[first[i].rec.light_index].to_vector();
        (0..first.len())
            .filter(|&j| j != i && first[j].markers.is_some())
            .filter(|&j| first[j].rec.view_slot == first[i].rec.view_slot)
            .map(|j| {
                let l = lights[first[j].rec.light_index].to_vector();
                (own[0] * l[0] + own[1] * l[1] + own[2] * l[2], j)
            })
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .filter(|(cos, _)| *cos >= MAX_REFERENCE_LIGHT_DEG.to_radians().cos())
            .map(|(_, j)| j)
    };
    let needs_pose: Vec<usize> = (0..first.len())
        .filter(|&i| first[i].markers.is_none() && !first[i].unusable)
        .collect();
    // The texture refinement's own error, measured on marker-registered
    // frames spread over the run.
    let checks: Vec<usize> = {
        let candidates: Vec<usize> = (0..first.len())
            .filter(|&i| first[i].markers.is_some() && first[i].pose.is_some())
            .collect();
        let step = (candidates.len() / TEXTURE_CHECKS).max(1);
        candidates
            .into_iter()
            .step_by(step)
            .take(TEXTURE_CHECKS)
            .collect()
    };
    let refine = |i: usize, image: &Image| {
        let reference = reference_of(i).and_then(|r| rectifier.reference_texture(&first[r]));
        let pose = first[i].pose.unwrap_or([[0.0; 3]; 3]);
        rectifier.pose_registration(image, &pose, offset, reference.as_ref())
    };
    let texture_errors: Vec<f64> = checks
        .par_iter()
        .filter_map(|&i| {
            let f = &first[i];
            let images = rectifier.frame_images(&run.entries[i]).ok()?;
            let (h, method) = refine(i, images.texture_grey());
            (method == RegistrationMethod::PoseTexture)
                .then(|| rect::disagreement_px(&h, f.markers.as_ref()?, region))
                .flatten()
        })
        .collect();
    let pose_texture_error_px = spread(&texture_errors).map(|s| s[1]);
    // The run's own frames say whether the texture helps: only if it lands
    // nearer the markers than the calibrated pose does.
    let texture_helps = matches!(
        (pose_texture_error_px, pose_error_px),
        (Some(t), Some(p)) if t < p
    );
    let refine = |i: usize, image: &Image| {
        if texture_helps {
            refine(i, image)
        } else {
            let pose = first[i].pose.unwrap_or([[0.0; 3]; 3]);
            (rect::shift_plate(&pose, offset), RegistrationMethod::Pose)
        }
    };

    // 5. The rest from their pose.
    let pose_results: Vec<(usize, FrameRegistration, bool)> = needs_pose
        .par_iter()
        .map(|&i| {
            let f = &first[i];
            let mut rec = f.rec.clone();
            let mut usable = false;
            let entry = &run.entries[i];
            match rectifier.frame_images(entry) {
                Err(e) => rec.problem = Some(format!("lost: {e}")),
                Ok(images) => {
                    let (h, method) = refine(i, images.texture_grey());
                    match rectifier.write_texture(&mut rec, &images, &h, entry.bit_depth) {
                        Ok(()) => {
                            rec.method = Some(method);
                            rec.error_px = match method {
                                RegistrationMethod::PoseTexture => pose_texture_error_px,
                                _ => pose_error_px,
                            };
                            usable = true;
                        }
                        Err(e) => rec.problem = Some(e),
                    }
                }
            }
            (i, rec, usable)
        })
        .collect();
    for (i, rec, usable) in pose_results {
        first[i].rec = rec;
        first[i].unusable = !usable;
    }

    // 6. Unusable frames from their slot's nearest usable lights.
    let mut frames: Vec<FrameRegistration> = first.into_iter().map(|f| f.rec).collect();
    let index_so_far = NormtextureIndex {
        size: cfg.final_size,
        encoding: encoding_of(cfg.bits).into(),
        bit_depth,
        lights: lights.clone(),
        views: views.clone(),
        frames: frames.clone(),
        summary: None,
        roi: Some(cfg.roi),
        channels: rectifier.channels(),
    };
    type Filled = Result<(Option<String>, Vec<usize>), String>;
    let fills: Vec<(usize, Filled)> = (0..frames.len())
        .into_par_iter()
        .filter(|&i| frames[i].file.is_none())
        .map(|i| {
            let mut rec = frames[i].clone();
            let result = fill_from_neighbours(&rectifier, &index_so_far, &mut rec, &lights)
                .map(|from| (rec.file, from));
            (i, result)
        })
        .collect();
    let mut failed_slots: std::collections::BTreeMap<usize, Vec<String>> = Default::default();
    for (i, result) in fills {
        let rec = &mut frames[i];
        match result {
            Ok((file, from)) => {
                rec.file = file;
                rec.method = Some(RegistrationMethod::Interpolated);
                rec.interpolated_from = from;
                rec.coverage = None;
            }
            Err(e) => {
                rec.error = Some(format!(
                    "{}; {e}",
                    rec.problem.clone().unwrap_or_else(|| "unusable".into())
                ));
                failed_slots.entry(rec.view_slot).or_default().push(format!(
                    "frame {}: {}",
                    rec.index,
                    rec.problem.as_deref().unwrap_or("unusable")
                ));
            }
        }
    }

    let mut by_method: std::collections::BTreeMap<String, usize> = Default::default();
    for f in &frames {
        if let Some(m) = f.method {
            *by_method.entry(m.name().to_string()).or_default() += 1;
        }
    }
    let marker_rms: Vec<f64> = frames
        .iter()
        .filter(|f| f.method == Some(RegistrationMethod::Markers))
        .filter_map(|f| f.rms_px)
        .collect();
    let damaged: Vec<usize> = frames
        .iter()
        .filter(|f| f.damaged)
        .map(|f| f.index)
        .collect();
    let mut clipped: Vec<&FrameRegistration> =
        frames.iter().filter(|f| f.clipped_texels > 0).collect();
    clipped.sort_by(|a, b| {
        b.clipped_share
            .unwrap_or(0.0)
            .total_cmp(&a.clipped_share.unwrap_or(0.0))
    });
    let most_clipped = clipped
        .iter()
        .take(super::CLIPPED_LISTED)
        .filter_map(|f| {
            Some(super::ClippedFrame {
                index: f.index,
                share: f.clipped_share.unwrap_or(0.0),
                light: *index_so_far.lights.get(f.light_index)?,
                view: *index_so_far.views.get(f.view_slot)?,
            })
        })
        .collect();
    let summary = RegistrationSummary {
        frames_clipped: clipped.len(),
        clipped_texels: clipped.iter().map(|f| f.clipped_texels).sum(),
        most_clipped,
        frames_by_method: by_method,
        frames_without_texture: frames.iter().filter(|f| f.file.is_none()).count(),
        frames_damaged: damaged.len(),
        damaged,
        marker_rms_px: spread(&marker_rms),
        holder_offset_mm: (!pairs.is_empty()).then(|| offset.map(|v| v * 1e3)),
        uncalibrated_pose_error_px,
        pose_error_px,
        pose_texture_error_px,
        pose_texture_checked: texture_errors.len(),
        resumed_frames: resumed.into_inner(),
    };
    let index = NormtextureIndex {
        frames,
        summary: Some(summary),
        ..index_so_far
    };
    let path = out_dir.join(NORMTEXTURE_INDEX);
    let mut json =
        serde_json::to_vec_pretty(&index).map_err(|e| ProcessError::Invalid(e.to_string()))?;
    json.push(b'\n');
    crate::store::write_atomic(&path, &json)?;
    store.remove();
    write_lamp_figure(run, &index)?;
    if !failed_slots.is_empty() {
        let described: Vec<String> = failed_slots
            .iter()
            .take(5)
            .map(|(slot, why)| {
                let v = index.views[*slot];
                format!(
                    "view slot {slot} (θ {:.1}°, φ {:.1}°): no usable frame ({}{})",
                    v.theta_deg,
                    v.phi_deg,
                    why.iter().take(2).cloned().collect::<Vec<_>>().join("; "),
                    if why.len() > 2 { "; …" } else { "" }
                )
            })
            .collect();
        return Err(ProcessError::Invalid(format!(
            "{} of {} view slots have no usable frame (listed in {}): {}{}",
            failed_slots.len(),
            index.views.len(),
            path.display(),
            described.join("; "),
            if failed_slots.len() > 5 { "; …" } else { "" }
        )));
    }
    Ok(index)
}

/// `processed/lamp-level.svg`, the lamp's level over the capture, when
/// the holder's white areas measured it in any frame.
fn write_lamp_figure(run: &RunFrames, index: &NormtextureIndex) -> Result<(), ProcessError> {
    let by_index: std::collections::HashMap<usize, f64> =
        run.entries.iter().map(|e| (e.index, e.t_s)).collect();
    let points: Vec<(f64, f64)> = index
        .frames
        .iter()
        .filter_map(|f| Some((*by_index.get(&f.index)?, f.lamp_level?)))
        .collect();
    if points.is_empty() {
        return Ok(());
    }
    let svg = super::lamp::figure(&points).map_err(ProcessError::Invalid)?;
    let path = crate::store::processed::processed_dir(&run.root).join(super::lamp::LAMP_FIGURE);
    Ok(crate::store::write_atomic(&path, svg.as_bytes())?)
}

/// Checks the sizes of a rectification before any frame is read.
pub(super) fn check_config(cfg: &RectifyConfig) -> Result<(), ProcessError> {
    cfg.check().map_err(ProcessError::Invalid)
}

/// The run's holder and the layout of its point markers around the sample.
pub(super) fn holder_layout(
    meta: &crate::store::RunMeta,
) -> Result<
    (
        rigd_core::holder::Holder,
        rigd_process::rectify::MarkerLayout,
    ),
    ProcessError,
> {
    let (holder, _) = holder_of(meta)?;
    let layout = super::marker_layout(&holder);
    Ok((holder, layout))
}

/// The run's light and view directions in order of first appearance, and
/// each entry's (view slot, light index). A frame's slot depends only on
/// the frames before it, so the slots of a journal's prefix are those the
/// whole run gives them: what lets [`super::RectifyStream`] work ahead.
pub(super) fn assign_slots(
    entries: &[crate::store::FrameEntry],
) -> (Vec<Direction>, Vec<Direction>, Vec<(usize, usize)>) {
    let (mut lights, mut views) = (Vec::new(), Vec::new());
    let slots = entries
        .iter()
        .map(|e| {
            (
                slot_of(&mut views, e.view.canonical()),
                slot_of(&mut lights, e.light.canonical()),
            )
        })
        .collect();
    (lights, views, slots)
}

/// The index's `encoding` of textures stored as `bits`.
pub(super) fn encoding_of(bits: TextureBits) -> &'static str {
    match bits {
        TextureBits::Float => "npy-f32",
        TextureBits::Half => "npy-f16",
        TextureBits::Top8 | TextureBits::Shift(_) => "png8",
    }
}
