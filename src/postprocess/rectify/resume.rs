//! The first pass's result per frame, kept while `rectify` runs, so a run
//! of the step that is cut short (a killed daemon, a crash, Ctrl-C)
//! resumes without registering again the frames it had done. Removed when
//! the step completes.
//!
//! An entry is used only when it was made with the same settings, for
//! the same frame file (its SHA-256), slot and rigd version, and its
//! texture is still on disk at the size it was written with. The later
//! steps rewrite every texture they change, so a texture they had changed
//! before the cut is either rewritten again or fails that check and is
//! registered again. Entries are written without fsync: after a power
//! cut a torn entry fails to parse and the frame is simply redone.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::steps::FirstPass;
use super::{FrameRegistration, RectifyConfig};
use crate::store::FrameEntry;

/// The folder of `processed/normtextures/` the entries are kept in.
pub(super) const FIRST_PASS_DIR: &str = "first-pass";

#[derive(Serialize, Deserialize)]
struct Entry {
    key: String,
    rec: FrameRegistration,
    markers: Option<rigd_process::rectify::Homography>,
    pose: Option<rigd_process::rectify::Homography>,
    unusable: bool,
    p99: f32,
    texture_bytes: Option<u64>,
}

/// The kept first-pass results of one run of `rectify`.
pub(super) struct FirstPassCache {
    dir: PathBuf,
    out_dir: PathBuf,
    settings: String,
}

impl FirstPassCache {
    /// The store in `out_dir` (the normtextures folder) for `cfg`, and the
    /// colour calibration and lamp reference the textures are corrected by.
    pub(super) fn new(
        out_dir: &Path,
        cfg: &RectifyConfig,
        rectifier: &super::steps::Rectifier<'_>,
    ) -> FirstPassCache {
        let (colour, lamp) = (
            rectifier.colour.as_ref(),
            rectifier.lamp.as_ref().map(|(_, reference)| reference),
        );
        FirstPassCache {
            dir: out_dir.join(FIRST_PASS_DIR),
            out_dir: out_dir.to_path_buf(),
            settings: format!("{} {cfg:?} {colour:?} {lamp:?}", env!("CARGO_PKG_VERSION")),
        }
    }

    fn key(&self, entry: &FrameEntry, view_slot: usize, light_index: usize) -> String {
        format!(
            "{} {} {view_slot} {light_index}",
            self.settings, entry.sha256
        )
    }

    fn path(&self, entry: &FrameEntry) -> PathBuf {
        self.dir.join(format!("{:06}.json", entry.index))
    }

    fn texture_bytes(&self, rec: &FrameRegistration) -> Option<u64> {
        let file = rec.file.as_ref()?;
        std::fs::metadata(self.out_dir.join(file))
            .ok()
            .map(|m| m.len())
    }

    /// The kept result for the frame at `position`, if it is still good.
    pub(super) fn load(
        &self,
        entry: &FrameEntry,
        position: usize,
        view_slot: usize,
        light_index: usize,
    ) -> Option<FirstPass> {
        let bytes = std::fs::read(self.path(entry)).ok()?;
        let kept: Entry = serde_json::from_slice(&bytes).ok()?;
        if kept.key != self.key(entry, view_slot, light_index)
            || kept.texture_bytes != self.texture_bytes(&kept.rec)
        {
            return None;
        }
        Some(FirstPass {
            position,
            rec: kept.rec,
            markers: kept.markers,
            pose: kept.pose,
            unusable: kept.unusable,
            p99: kept.p99,
        })
    }

    /// Keeps a frame's result (best effort: a failure only costs the
    /// frame's registration on a resume).
    pub(super) fn keep(
        &self,
        entry: &FrameEntry,
        view_slot: usize,
        light_index: usize,
        f: &FirstPass,
    ) {
        let kept = Entry {
            key: self.key(entry, view_slot, light_index),
            rec: f.rec.clone(),
            markers: f.markers,
            pose: f.pose,
            unusable: f.unusable,
            p99: f.p99,
            texture_bytes: self.texture_bytes(&f.rec),
        };
        let Ok(json) = serde_json::to_vec(&kept) else {
            return;
        };
        let path = self.path(entry);
        let written = std::fs::create_dir_all(&self.dir).and_then(|()| {
            rigd_core::atomic::write_unsynced(&path, &json).map_err(std::io::Error::from)
        });
        if let Err(e) = written {
            tracing::debug!("{}: {e}", path.display());
        }
    }

    /// Removes the store once the step has written its index.
    pub(super) fn remove(&self) {
        if let Err(e) = std::fs::remove_dir_all(&self.dir) {
            if e.kind() != std::io::ErrorKind::NotFound {
                tracing::warn!("{}: {e}", self.dir.display());
            }
        }
    }
}
