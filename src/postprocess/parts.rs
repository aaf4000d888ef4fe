//! A processing step's work in parts that need nothing from each other,
//! the way the data splits: `rectify` in chunks of frames, `btf` and `fit`
//! in groups of view slots, `mdf` per view. Each part keeps its result
//! where the step itself finds it (the first-pass store, `btf-ahead/`,
//! `fit-ahead/`, `mdf-ahead/`), so the step run after the parts only joins
//! them and gives the files a single machine gives. `photometric-stereo`,
//! one view solved in one pass, is one part: the whole step.

use std::ops::Range;
use std::path::Path;

use super::pipeline::{ProcessOptions, ProcessStep, StepProgress};
use super::ProcessError;

/// How much work a part gets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PartSizes {
    /// Frames per part of `rectify`.
    pub frames: usize,
    /// View slots per part of `btf` and `fit`.
    pub slots: usize,
}

/// How a step splits for a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Split {
    /// `units` units of work (frames or view slots) in `parts` parts; the
    /// step run afterwards joins them.
    Units {
        /// Frames (`rectify`), view slots (`btf`, `fit`) or views (`mdf`).
        units: usize,
        /// Parts, each a contiguous range of units.
        parts: usize,
    },
    /// The step runs whole, as one part; nothing is left to join.
    Whole,
}

impl Split {
    /// The number of parts.
    pub fn parts(self) -> usize {
        match self {
            Split::Units { parts, .. } => parts,
            Split::Whole => 1,
        }
    }
}

/// How `step` splits for the run at `root`: frames in chunks of
/// `sizes.frames` for `rectify`, view slots in groups of `sizes.slots` for
/// `btf` and `fit` (read from the run's normtexture index, so `rectify`
/// must have run), one view per part of `mdf`, and `photometric-stereo`
/// whole.
pub fn split(
    root: &Path,
    step: ProcessStep,
    opts: &ProcessOptions,
    sizes: PartSizes,
) -> Result<Split, ProcessError> {
    let units = match step {
        ProcessStep::Rectify => super::frames::RunFrames::open(root)?.entries.len(),
        ProcessStep::Btf | ProcessStep::Fit => {
            super::rectify::NormtextureIndex::read(root)?.views.len()
        }
        ProcessStep::Mdf => {
            let run = super::frames::RunFrames::open(root)?;
            super::mdf::mdf_view_count(&run, &opts.mdf.config())?
        }
        ProcessStep::PhotometricStereo => return Ok(Split::Whole),
    };
    let per_part = match step {
        ProcessStep::Rectify => sizes.frames.max(1),
        ProcessStep::Mdf => 1,
        _ => sizes.slots.max(1),
    };
    if units == 0 {
        return Err(ProcessError::Invalid(format!(
            "{}: the run has nothing to process",
            step.name()
        )));
    }
    Ok(Split::Units {
        units,
        parts: units.div_ceil(per_part),
    })
}

/// The units of part `part` of `parts` over `units`: contiguous ranges
/// whose sizes differ by at most one, covering every unit once.
pub fn part_range(units: usize, parts: usize, part: usize) -> Range<usize> {
    let parts = parts.max(1);
    let start = units * part / parts;
    let end = units * (part + 1) / parts;
    start.min(units)..end.min(units)
}

/// Runs part `part` of `step` as split by `split` on the run at `root`;
/// returns a one-line summary. A [`Split::Whole`] part is the step itself
/// ([`super::pipeline::run_step`]).
pub fn run_part(
    root: &Path,
    step: ProcessStep,
    opts: &ProcessOptions,
    split: Split,
    part: usize,
    progress: StepProgress<'_>,
) -> Result<String, ProcessError> {
    let Split::Units { units, parts } = split else {
        if part != 0 {
            return Err(ProcessError::Invalid(format!(
                "{} runs whole: part {part} does not exist",
                step.name()
            )));
        }
        return super::pipeline::run_step(root, step, opts, progress);
    };
    if part >= parts {
        return Err(ProcessError::Invalid(format!(
            "part {part} of {parts}: expected 0 … {}",
            parts - 1
        )));
    }
    let range = part_range(units, parts, part);
    let what = format!("{} {}..{}", step.name(), range.start, range.end);
    let done = match step {
        ProcessStep::Rectify => {
            let cfg = opts.rectify.config().map_err(ProcessError::Invalid)?;
            let run = super::frames::RunFrames::open(root)?;
            let n = super::rectify::first_pass_range(&run, &cfg, range.clone(), progress)?;
            format!("{n} of {} frames registered", range.len())
        }
        ProcessStep::Btf => {
            let n = super::btf::compress_slots_part(
                root,
                range.clone(),
                opts.btf.components,
                progress,
            )?;
            format!("{n} of {} view slots compressed", range.len())
        }
        ProcessStep::Fit => {
            let n = super::fit::fit_slots_part(root, range.clone(), opts.fit.lobes, progress)?;
            format!("{n} of {} view slots fitted", range.len())
        }
        ProcessStep::Mdf => {
            let run = super::frames::RunFrames::open(root)?;
            super::mdf::mdf_views_part(&run, &opts.mdf.config(), range.clone(), progress)?;
            format!("{} views merged", range.len())
        }
        ProcessStep::PhotometricStereo => {
            return Err(ProcessError::Invalid(format!(
                "{} does not split into parts",
                step.name()
            )))
        }
    };
    Ok(format!("{what}: {done}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn parts_cover_every_unit_once_in_order(units in 1usize..5000, parts in 1usize..300) {
            let parts = parts.min(units);
            let mut next = 0;
            for part in 0..parts {
                let r = part_range(units, parts, part);
                prop_assert_eq!(r.start, next);
                prop_assert!(!r.is_empty());
                prop_assert!(r.len() <= units.div_ceil(parts));
                next = r.end;
            }
            prop_assert_eq!(next, units);
        }
    }

    #[test]
    fn a_whole_step_is_one_part() {
        assert_eq!(Split::Whole.parts(), 1);
        assert_eq!(
            Split::Units {
                units: 10,
                parts: 4
            }
            .parts(),
            4
        );
        assert_eq!(part_range(10, 4, 3), 7..10);
    }
}
