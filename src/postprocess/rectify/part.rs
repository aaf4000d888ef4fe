//! The first pass of a range of a run's frames, kept in the store that
//! `rectify` resumes from: one task of a cluster's job array
//! ([`crate::postprocess::parts`]). The `rectify` step that follows takes
//! these frames from the store and runs only the passes that need the
//! whole run, so the result is the one a single machine gives.

use std::ops::Range;

use super::resume::FirstPassCache;
use super::run::{assign_slots, check_config, holder_layout};
use super::steps::Rectifier;
use super::RectifyConfig;
use crate::postprocess::frames::RunFrames;
use crate::postprocess::ProcessError;

/// Does the first pass of the frames at `positions` (in the journal's
/// order) that the store does not hold yet, in parallel on the current
/// rayon pool, calling `progress(done, total)` per frame. Returns how many
/// it registered (the others were kept already).
pub fn first_pass_range(
    run: &RunFrames,
    cfg: &RectifyConfig,
    positions: Range<usize>,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<usize, ProcessError> {
    use rayon::prelude::*;
    check_config(cfg)?;
    if positions.end > run.entries.len() {
        return Err(ProcessError::Invalid(format!(
            "frames {}..{}: the run has {}",
            positions.start,
            positions.end,
            run.entries.len()
        )));
    }
    let (holder, layout) = holder_layout(&run.meta)?;
    let out_dir = crate::store::processed::normtextures_dir(&run.root);
    crate::postprocess::create_dir(&out_dir)?;
    // Slots depend on every frame before: number them over the whole run.
    let (_, _, slots) = assign_slots(&run.entries);
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
    let store = FirstPassCache::new(&out_dir, cfg, &rectifier);
    let total = positions.len();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let registered: usize = positions
        .into_par_iter()
        .map(|position| {
            let entry = &run.entries[position];
            let (view_slot, light_index) = slots[position];
            let new = store
                .load(entry, position, view_slot, light_index)
                .is_none();
            if new {
                let f = rectifier.first_pass(position, view_slot, light_index);
                store.keep(entry, view_slot, light_index, &f);
            }
            let n = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
            progress(n, total);
            usize::from(new)
        })
        .sum();
    Ok(registered)
}
