//! The MDF in the sample's texture space, as the renderers read it
//! (`crate::silhouette` on the CPU, the viewer's shader on the GPU): one
//! square layer per measured view direction, texel rows and columns those
//! of the BTF's normtextures (row 0 the sample's `+y` edge), each texel the
//! distance in millimetres along the view ray from the mesostructure's top
//! plane down to the surface, [`NO_DEPTH`] where nothing was measured.
//!
//! Stored as `mdf.npy` (float32, shape `[views, size, size]`) and
//! `mdf.json` ([`MdfTextureHeader`]) in one folder.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::{MdfError, NO_DEPTH};
use crate::directions::{Direction, DirectionError, DirectionTable};
use crate::npy;

/// File of the depths in an MDF texture folder.
pub const MDF_TEXTURE_FILE: &str = "mdf.npy";
/// File of the header in an MDF texture folder.
pub const MDF_TEXTURE_HEADER: &str = "mdf.json";

/// What `mdf.json` says about `mdf.npy`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MdfTextureHeader {
    /// Side of every layer, texels.
    pub size: usize,
    /// The view direction of each layer, sample frame (the BTF's local
    /// frame: φ = 0 along the texture's columns, θ = 0 the normal).
    pub views: Vec<Direction>,
    /// Side of the square of sample one texture tile covers, mm.
    pub tile_mm: f64,
    /// Height of the top plane the depths start from, over the turntable, mm.
    pub top_mm: f64,
    /// Share of each layer's texels holding a measurement.
    pub coverage: Vec<f64>,
    /// Where the depths came from (the laser run), for people.
    pub source: String,
}

/// An MDF in texture space; see the module doc.
#[derive(Debug, Clone)]
pub struct MdfTexture {
    header: MdfTextureHeader,
    views: DirectionTable,
    depth_mm: Vec<f32>,
}

/// Refuses what is not a usable texture, with the reason.
fn invalid(what: String) -> MdfError {
    MdfError::InvalidInput(what)
}

impl MdfTexture {
    /// Checks the header against the depths: `views · size²` finite values,
    /// each a depth ≥ 0 or [`NO_DEPTH`]; a positive tile; a valid view
    /// table.
    pub fn new(header: MdfTextureHeader, depth_mm: Vec<f32>) -> Result<MdfTexture, MdfError> {
        let n = header.size;
        if n == 0 || n > 8192 {
            return Err(invalid(format!("MDF texture side {n}: expected 1 … 8192")));
        }
        if depth_mm.len() != header.views.len() * n * n {
            return Err(invalid(format!(
                "MDF texture of {} views × {n}² texels holds {} values",
                header.views.len(),
                depth_mm.len()
            )));
        }
        if !(header.tile_mm.is_finite() && header.tile_mm > 0.0 && header.top_mm.is_finite()) {
            return Err(invalid(format!(
                "MDF texture tile {} mm, top {} mm: expected a positive tile and a finite top",
                header.tile_mm, header.top_mm
            )));
        }
        if let Some(bad) = depth_mm
            .iter()
            .find(|&&d| !(d.is_finite() && (d >= 0.0 || d == NO_DEPTH)))
        {
            return Err(invalid(format!(
                "MDF texture value {bad}: expected a depth ≥ 0 mm or −1"
            )));
        }
        let views = DirectionTable::new(header.views.clone())
            .map_err(|e| invalid(format!("MDF texture views: {e}")))?;
        Ok(MdfTexture {
            header,
            views,
            depth_mm,
        })
    }

    /// The header.
    pub fn header(&self) -> &MdfTextureHeader {
        &self.header
    }

    /// The view table the offsets interpolate over.
    pub fn views(&self) -> &DirectionTable {
        &self.views
    }

    /// Every texel, layer-major, then rows, then columns, mm.
    pub fn depth_mm(&self) -> &[f32] {
        &self.depth_mm
    }

    /// The depth of texel (x, y) of layer `view`, mm, or [`NO_DEPTH`].
    pub fn texel(&self, view: usize, x: usize, y: usize) -> f32 {
        let n = self.header.size;
        self.depth_mm
            .get((view * n + y) * n + x)
            .copied()
            .unwrap_or(NO_DEPTH)
    }

    /// The offset in millimetres at texture coordinate `(s, r)` (tiles, as
    /// the mesh gives them) for the local direction `local` (unit, pointing
    /// away from the surface): the view table's interpolation entries, the
    /// nearest texel `(⌊fract(s)·N⌋, ⌊fract(−r)·N⌋)` of each, the weighted
    /// mean over those holding a measurement, and 0 when none does (no
    /// measurement counts as the surface at the mesh).
    pub fn offset_mm(&self, s: f64, r: f64, local: [f64; 3]) -> Result<f64, DirectionError> {
        let n = self.header.size;
        let texel_of = |c: f64| (((c - c.floor()) * n as f64).floor() as usize).min(n - 1);
        let (x, y) = (texel_of(s), texel_of(-r));
        let entries = self
            .views
            .interpolate(crate::relight::local_angles(local))?;
        let (mut sum, mut weight) = (0.0, 0.0);
        for &(view, w) in entries.entries() {
            let d = self.texel(view, x, y);
            if d >= 0.0 {
                sum += w * f64::from(d);
                weight += w;
            }
        }
        Ok(if weight > 0.0 { sum / weight } else { 0.0 })
    }

    /// [`MdfTexture::offset_mm`] in world units of a mesh whose material
    /// has `density` tiles per unit.
    pub fn offset(
        &self,
        s: f64,
        r: f64,
        local: [f64; 3],
        density: f64,
    ) -> Result<f64, DirectionError> {
        Ok(self.offset_mm(s, r, local)? / (self.header.tile_mm * density))
    }

    /// Writes `mdf.npy` and `mdf.json` into `dir` (created).
    pub fn write(&self, dir: &Path) -> Result<(), MdfError> {
        std::fs::create_dir_all(dir)
            .map_err(|e| invalid(format!("cannot create {}: {e}", dir.display())))?;
        let n = self.header.size;
        npy::write_f32(
            &dir.join(MDF_TEXTURE_FILE),
            &[self.header.views.len(), n, n],
            &self.depth_mm,
        )?;
        let json = serde_json::to_vec_pretty(&self.header)
            .map_err(|e| invalid(format!("MDF texture header: {e}")))?;
        let path = dir.join(MDF_TEXTURE_HEADER);
        rigd_core::atomic::write(&path, &json)
            .map_err(|e| invalid(format!("cannot write {}: {e}", path.display())))
    }

    /// Reads what [`MdfTexture::write`] wrote.
    pub fn read(dir: &Path) -> Result<MdfTexture, MdfError> {
        let path = dir.join(MDF_TEXTURE_HEADER);
        let bytes = std::fs::read(&path)
            .map_err(|e| invalid(format!("cannot read {}: {e}", path.display())))?;
        let header: MdfTextureHeader = serde_json::from_slice(&bytes)
            .map_err(|e| invalid(format!("{}: {e}", path.display())))?;
        let depth = npy::read_f32(&dir.join(MDF_TEXTURE_FILE))?;
        let n = header.size;
        if depth.shape != [header.views.len(), n, n] {
            return Err(invalid(format!(
                "{}: shape {:?}, the header says [{}, {n}, {n}]",
                dir.join(MDF_TEXTURE_FILE).display(),
                depth.shape,
                header.views.len()
            )));
        }
        MdfTexture::new(header, depth.data)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn texture(depths: Vec<f32>, views: Vec<Direction>, size: usize) -> MdfTexture {
        let coverage = vec![1.0; views.len()];
        MdfTexture::new(
            MdfTextureHeader {
                size,
                views,
                tile_mm: 50.0,
                top_mm: 5.0,
                coverage,
                source: "test".into(),
            },
            depths,
        )
        .unwrap()
    }

    #[test]
    fn offsets_take_the_nearest_texel_wrap_and_skip_missing_views() {
        // Two views, 2×2 texels: the pole and a grazing ring member.
        let views = vec![Direction::new(0.0, 0.0), Direction::new(80.0, 0.0)];
        let t = texture(
            vec![1.0, 2.0, 3.0, 4.0, 10.0, NO_DEPTH, 30.0, 40.0],
            views,
            2,
        );
        // Overhead: layer 0. (s, r) = (0.25, −0.25) is texel (0, 0);
        // s = 1.75 wraps to column 1; r = 0.25 → t = −0.25 → row 1.
        assert_eq!(t.offset_mm(0.25, -0.25, [0.0, 0.0, 1.0]).unwrap(), 1.0);
        assert_eq!(t.offset_mm(1.75, -0.25, [0.0, 0.0, 1.0]).unwrap(), 2.0);
        assert_eq!(t.offset_mm(0.25, 0.25, [0.0, 0.0, 1.0]).unwrap(), 3.0);
        // Grazing (clamped to the outer ring), texel (1, 0) missing there:
        // no measurement anywhere counts as 0 only when every entry lacks it.
        let grazing = [1.0, 0.0, 0.0];
        assert_eq!(t.offset_mm(0.25, -0.25, grazing).unwrap(), 10.0);
        assert_eq!(t.offset_mm(0.75, -0.25, grazing).unwrap(), 0.0);
        // World units: 50 mm tiles at 2 tiles per unit.
        let w = t.offset(0.25, -0.25, grazing, 2.0).unwrap();
        assert!((w - 0.1).abs() < 1e-12);
        // A non-finite direction is an error, not a NaN.
        assert!(t.offset_mm(0.0, 0.0, [f64::NAN, 0.0, 1.0]).is_err());
    }

    #[test]
    fn bad_textures_are_refused_and_a_written_one_reads_back() {
        let views = vec![Direction::new(0.0, 0.0)];
        let header = |size| MdfTextureHeader {
            size,
            views: views.clone(),
            tile_mm: 50.0,
            top_mm: 5.0,
            coverage: vec![1.0],
            source: "test".into(),
        };
        assert!(MdfTexture::new(header(2), vec![0.0; 3]).is_err());
        assert!(MdfTexture::new(header(1), vec![-0.5]).is_err());
        assert!(MdfTexture::new(header(1), vec![f32::NAN]).is_err());
        let dir = tempfile::tempdir().unwrap();
        let t = MdfTexture::new(header(2), vec![0.0, 1.5, NO_DEPTH, 2.0]).unwrap();
        t.write(dir.path()).unwrap();
        let back = MdfTexture::read(dir.path()).unwrap();
        assert_eq!(back.header(), t.header());
        assert_eq!(back.depth_mm(), t.depth_mm());
    }
}
