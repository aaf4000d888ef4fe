//! A run's metadata and every frame it wrote, as the processing steps read them.

use std::path::{Path, PathBuf};

use rigd_process::image_io::Image;

use super::ProcessError;
use crate::rig::hal::decode_png;
use crate::store::{read_journal, read_meta, FrameEntry, RunMeta, JOURNAL_FILE};

/// A run's metadata and every frame it wrote, in capture order.
pub struct RunFrames {
    /// The run directory.
    pub root: PathBuf,
    /// What the run was asked for (`run.json`).
    pub meta: RunMeta,
    /// Every journaled frame, sorted by image index.
    pub entries: Vec<FrameEntry>,
}

impl RunFrames {
    /// Reads the run directory's metadata and journal.
    pub fn open(root: &Path) -> Result<RunFrames, ProcessError> {
        let meta = read_meta(root)?;
        let (mut entries, _) = read_journal(&root.join(JOURNAL_FILE))?;
        entries.sort_by_key(|e| e.index);
        Ok(RunFrames {
            root: root.to_path_buf(),
            meta,
            entries,
        })
    }

    /// One frame as linear values in [0, 1].
    pub fn image(&self, entry: &FrameEntry) -> Result<Image, ProcessError> {
        let path = self.root.join(&entry.file);
        let bytes = std::fs::read(&path).map_err(|e| ProcessError::Frame {
            path: path.clone(),
            message: e.to_string(),
        })?;
        let (w, h, pixels) = decode_png(&bytes).map_err(|message| ProcessError::Frame {
            path: path.clone(),
            message,
        })?;
        let full = ((1u32 << entry.bit_depth.clamp(1, 16)) - 1) as f32;
        let mut img = Image::new(w as usize, h as usize, 1);
        for (d, p) in img.data.iter_mut().zip(pixels) {
            *d = p as f32 / full;
        }
        Ok(img)
    }
}
