//! Rectification while the capture runs: each frame's first pass (read,
//! markers, texture) as soon as the frame is journaled, kept in the same
//! store an interrupted `rectify` resumes from. The `rectify` step after
//! the capture then takes those frames from the store and runs only the
//! passes that need the whole run (black frames, the holder offset, the
//! pose fallbacks, the fills), so in a healthy run it reads each frame once,
//! during the capture.
//!
//! A frame's view slot and light index are its directions' order of first
//! appearance over the frames before it (in image index order, which is
//! the capture order), so only the journal's contiguous prefix is worked
//! on: a frame whose predecessors are not all journaled yet waits. Were a
//! frame's slot to change all the same (a frame that never comes), its
//! kept result no longer matches its key and `rectify` registers it again.
//!
//! A colour run calibrated on its own patches is corrected by what its most
//! frontal frames measure (`colour::calibrate_run`). Its frames wait until
//! no frame still to come can be among those, then the calibration is
//! measured once, kept in `colour.json` as `rectify` would keep it, and
//! every frame is registered in colour.

use std::path::{Path, PathBuf};

use rigd_core::holder::Holder;
use rigd_process::rectify::MarkerLayout;

use super::colour::ColourWhileCapturing;
use super::resume::FirstPassCache;
use super::run::{assign_slots, check_config, encoding_of, holder_layout};
use super::steps::Rectifier;
use super::{slot_of, FrameRegistration, NormtextureIndex, RectifyConfig};
use crate::postprocess::frames::RunFrames;
use crate::postprocess::ProcessError;
use rigd_core::geometry::Direction;

/// Where a [`RectifyStream`] stands after a call of
/// [`RectifyStream::catch_up`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StreamProgress {
    /// Frames of the run, from the journal's start, whose first pass is
    /// kept.
    pub done: usize,
    /// Frames journaled so far.
    pub journaled: usize,
    /// Frames this call registered (not found in the store).
    pub registered: usize,
}

/// The first passes of a capturing run, done a batch at a time.
pub struct RectifyStream {
    root: PathBuf,
    cfg: RectifyConfig,
    holder: Holder,
    layout: MarkerLayout,
    next: usize,
    /// Distinct light directions in the run's plan: a view slot is
    /// complete when it has that many textures.
    plan_lights: usize,
    /// The first-pass records of the frames before `next`, and the
    /// directions they were numbered against.
    recs: Vec<FrameRegistration>,
    lights: Vec<Direction>,
    views: Vec<Direction>,
    bit_depth: u8,
    /// Values per texel of the textures so far.
    channels: usize,
    /// The colour the textures are corrected by, once it is known.
    colour: ColourWhileCapturing,
}

impl RectifyStream {
    /// A stream over the run at `root`, registering with `cfg` (which must
    /// be the settings the `rectify` step will use, or nothing is reused).
    pub fn new(root: &Path, cfg: RectifyConfig) -> Result<RectifyStream, ProcessError> {
        check_config(&cfg)?;
        let meta = crate::store::read_meta(root)?;
        let cfg = cfg.for_run(&meta);
        let (holder, layout) = holder_layout(&meta)?;
        let mut plan_lights = Vec::new();
        for pair in &meta.plan.pairs {
            slot_of(&mut plan_lights, pair.light.canonical());
        }
        Ok(RectifyStream {
            root: root.to_path_buf(),
            cfg,
            holder,
            layout,
            next: 0,
            plan_lights: plan_lights.len(),
            recs: Vec::new(),
            lights: Vec::new(),
            views: Vec::new(),
            bit_depth: 8,
            channels: 1,
            colour: ColourWhileCapturing::default(),
        })
    }

    /// The view slots whose every light of the plan has a texture so far.
    /// The `rectify` step keeps these textures unless its later passes
    /// find a reason not to (a black or doubted frame), so a slot's
    /// compression can start now; `btf` checks that its inputs did not
    /// change.
    pub fn complete_slots(&self) -> Vec<usize> {
        let mut textured = vec![std::collections::BTreeSet::new(); self.views.len()];
        for r in self.recs.iter().filter(|r| r.file.is_some()) {
            if let Some(set) = textured.get_mut(r.view_slot) {
                set.insert(r.light_index);
            }
        }
        (0..self.views.len())
            .filter(|&s| self.plan_lights > 0 && textured[s].len() == self.plan_lights)
            .collect()
    }

    /// The index of the frames registered so far, as `rectify` would write
    /// it for them (without a summary): what `btf` reads a slot's textures
    /// through.
    pub fn partial_index(&self) -> NormtextureIndex {
        NormtextureIndex {
            size: self.cfg.final_size,
            encoding: encoding_of(self.cfg.bits).into(),
            bit_depth: self.bit_depth,
            lights: self.lights.clone(),
            views: self.views.clone(),
            frames: self.recs.clone(),
            summary: None,
            roi: Some(self.cfg.roi),
            channels: self.channels,
        }
    }

    /// Reads the journal and does the first pass of up to `max_frames`
    /// frames of its contiguous prefix that no earlier call did, in
    /// parallel on the current rayon pool. Frames the store already holds
    /// (a stream cut by a restart) are taken from it.
    pub fn catch_up(&mut self, max_frames: usize) -> Result<StreamProgress, ProcessError> {
        use rayon::prelude::*;
        let run = RunFrames::open(&self.root)?;
        let prefix = run
            .entries
            .iter()
            .enumerate()
            .take_while(|(position, e)| e.index == *position)
            .count();
        let end = prefix.min(self.next.saturating_add(max_frames));
        let mut progress = StreamProgress {
            done: self.next.min(prefix),
            journaled: run.entries.len(),
            registered: 0,
        };
        if end <= self.next {
            return Ok(progress);
        }
        // A run calibrated on its own patches waits for its most frontal
        // frames: registered before, its textures would not be `rectify`'s.
        let Some(colour) = self.colour.texture_colour(&run)? else {
            return Ok(progress);
        };
        let (lights, views, slots) = assign_slots(&run.entries[..end]);
        let out_dir = crate::store::processed::normtextures_dir(&self.root);
        crate::postprocess::create_dir(&out_dir)?;
        let rectifier = Rectifier {
            run: &run,
            cfg: &self.cfg,
            holder: self.holder.clone(),
            layout: self.layout.clone(),
            out_dir: out_dir.clone(),
            colour,
            lamp: None,
        }
        .with_lamp();
        self.channels = rectifier.channels();
        let store = FirstPassCache::new(&out_dir, &self.cfg, &rectifier);
        let done: Vec<(FrameRegistration, bool)> = (self.next..end)
            .into_par_iter()
            .map(|position| {
                let entry = &run.entries[position];
                let (view_slot, light_index) = slots[position];
                if let Some(kept) = store.load(entry, position, view_slot, light_index) {
                    return (kept.rec, false);
                }
                let f = rectifier.first_pass(position, view_slot, light_index);
                store.keep(entry, view_slot, light_index, &f);
                (f.rec, true)
            })
            .collect();
        progress.registered = done.iter().filter(|d| d.1).count();
        self.recs.extend(done.into_iter().map(|d| d.0));
        (self.lights, self.views) = (lights, views);
        self.bit_depth = run.entries.first().map_or(8, |e| e.bit_depth);
        self.next = end;
        progress.done = end;
        Ok(progress)
    }
}
