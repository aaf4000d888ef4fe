//! What the BTF viewer and `rigd process render` read from a processed run:
//! the compressed BTF (`RUN/processed/btf/`, from `rigd process btf`) or,
//! for a photometric-stereo run, its albedo and normals
//! (`RUN/processed/ps/`, from `rigd process photometric-stereo RUN`).

use std::path::{Path, PathBuf};

use rigd_process::btf::{BtfError, BtfHeader, CompressedBtf, TextureShape, HEADER_FILE};
use rigd_process::directions::{DirectionError, DirectionTable};
use rigd_process::mdf::{MdfTexture, MDF_TEXTURE_HEADER};
use rigd_process::mesh::{Mesh, MeshKind};
use rigd_process::npy::{self, NpyError};
use rigd_process::relight::{self, RelightError, RelightSettings, RgbImage};
use rigd_process::silhouette::{self, MesoSettings, SilhouetteError, SilhouetteReport};
use rigd_process::webgl::{self, BlobManifest, MdfManifest, PackError};
use serde::Serialize;

/// Material tiles per world unit on the viewer's meshes (two across the
/// flat sample).
pub const DEFAULT_DENSITY: f64 = 1.0;

/// Why the viewer or the reference renderer cannot show a run.
#[derive(Debug, thiserror::Error)]
pub enum ViewerError {
    /// The run holds neither a compressed BTF nor photometric-stereo maps.
    #[error(
        "{run} has no processed BTF ({btf}) and no photometric-stereo result ({ps}): run `rigd process rectify` then `rigd process btf`, or `rigd process photometric-stereo`"
    )]
    NotProcessed {
        /// The run directory.
        run: String,
        /// Where the BTF's header was looked for.
        btf: String,
        /// Where the photometric-stereo normals were looked for.
        ps: String,
    },
    /// Something only a BTF allows (the reference render) was asked of a
    /// photometric-stereo run.
    #[error("{what} needs a compressed BTF; {run} holds a photometric-stereo result only")]
    NeedsBtf {
        /// What needed the BTF, for the message.
        what: &'static str,
        /// The run directory.
        run: String,
    },
    /// The stored BTF cannot be read or is inconsistent.
    #[error(transparent)]
    Btf(#[from] BtfError),
    /// The BTF's light or view directions do not make a valid table.
    #[error(transparent)]
    Direction(#[from] DirectionError),
    /// A photometric-stereo `.npy` map cannot be read.
    #[error(transparent)]
    Npy(#[from] NpyError),
    /// The material cannot be packed into the viewer's blob.
    #[error(transparent)]
    Pack(#[from] PackError),
    /// The reference render failed.
    #[error(transparent)]
    Render(#[from] RelightError),
    /// Silhouettes or shadows from the MDF were asked of a run without an
    /// MDF texture.
    #[error(
        "{run} has no MDF texture ({dir}): capture a laser scan of the same sample (`rigd run --plan laser`), run `rigd process mdf LASER_RUN`, then `rigd process mdf-texture {run} --laser LASER_RUN`"
    )]
    NoMdf {
        /// The run directory.
        run: String,
        /// Where the MDF texture was looked for.
        dir: String,
    },
    /// The run's MDF texture cannot be read.
    #[error("the MDF texture: {0}")]
    Mdf(#[from] rigd_process::mdf::MdfError),
    /// The render with silhouettes or shadows refused.
    #[error(transparent)]
    Silhouette(#[from] SilhouetteError),
}

/// `btf` or `photometric-stereo` when the run holds what the viewer shows.
pub fn processed_kind(run: &Path) -> Option<&'static str> {
    if crate::store::processed::btf_dir(run)
        .join(HEADER_FILE)
        .is_file()
    {
        Some("btf")
    } else if crate::store::processed::ps_dir(run)
        .join("normals.npy")
        .is_file()
        && crate::store::processed::ps_dir(run)
            .join("albedo.npy")
            .is_file()
    {
        Some("photometric-stereo")
    } else {
        None
    }
}

/// What a processed run holds for relighting.
pub enum Material {
    /// The compressed BTF of `processed/btf/`.
    Btf(CompressedBtf),
    /// Albedo and normal maps of a photometric-stereo run.
    PhotometricStereo {
        /// The folder holding `albedo.npy` and `normals.npy`.
        dir: PathBuf,
    },
}

/// Opens what the run holds: the BTF if there is one, else the
/// photometric-stereo maps.
pub fn open(run: &Path) -> Result<Material, ViewerError> {
    let btf = crate::store::processed::btf_dir(run);
    if btf.join(HEADER_FILE).is_file() {
        return Ok(Material::Btf(CompressedBtf::read(&btf)?));
    }
    let ps = crate::store::processed::ps_dir(run);
    if ps.join("normals.npy").is_file() && ps.join("albedo.npy").is_file() {
        return Ok(Material::PhotometricStereo { dir: ps });
    }
    Err(ViewerError::NotProcessed {
        run: run.display().to_string(),
        btf: btf.join(HEADER_FILE).display().to_string(),
        ps: ps.join("normals.npy").display().to_string(),
    })
}

/// The header of the run's BTF and its tables, without the slot data.
fn btf_header(
    run: &Path,
) -> Result<Option<(BtfHeader, DirectionTable, DirectionTable)>, ViewerError> {
    let dir = crate::store::processed::btf_dir(run);
    if !dir.join(HEADER_FILE).is_file() {
        return Ok(None);
    }
    let header = BtfHeader::read(&dir)?;
    let lights = DirectionTable::new(header.light_directions.clone())?;
    let views = DirectionTable::new(header.view_directions.clone())?;
    Ok(Some((header, lights, views)))
}

/// The manifest of the viewer's blob; for a BTF from `btf.json` alone.
pub fn manifest(run: &Path, max_components: usize) -> Result<BlobManifest, ViewerError> {
    match btf_header(run)? {
        Some((header, lights, views)) => {
            let shape = TextureShape::new(header.width, header.height, header.channels)?;
            Ok(webgl::btf_manifest(
                shape,
                header.components,
                &lights,
                &views,
                max_components,
            ))
        }
        None => pack(run, max_components).map(|(manifest, _)| manifest),
    }
}

/// The viewer's blob and its manifest ([`rigd_process::webgl`]).
pub fn pack(run: &Path, max_components: usize) -> Result<(BlobManifest, Vec<u8>), ViewerError> {
    match open(run)? {
        Material::Btf(store) => Ok(webgl::pack_btf(&store, max_components)),
        Material::PhotometricStereo { dir } => {
            let albedo = npy::read_f32(&dir.join("albedo.npy"))?;
            let normals = npy::read_f32(&dir.join("normals.npy"))?;
            Ok(webgl::pack_photometric_stereo(
                &albedo.shape,
                &albedo.data,
                &normals.shape,
                &normals.data,
            )?)
        }
    }
}

/// A mesh as the viewer gets it: the geometry, and for a BTF run the
/// visibility of each measured light direction per vertex (vertex-major).
#[derive(Debug, Serialize)]
pub struct MeshView {
    /// The mesh's geometry, flattened into the JSON object.
    #[serde(flatten)]
    pub mesh: Mesh,
    /// Material tiles per world unit the mesh was built with.
    pub density: f64,
    /// Per vertex, then per measured light direction: 1 if the direction
    /// sees the sky from the vertex, 0 if hidden; empty for a
    /// photometric-stereo run.
    pub visibility: Vec<u8>,
    /// Light directions per vertex in `visibility` (0 without a BTF).
    pub visibility_directions: usize,
}

/// Builds the viewer's mesh of `kind` for a processed run, with the
/// visibility of the BTF's light directions.
pub fn mesh_view(run: &Path, kind: MeshKind, density: f64) -> Result<MeshView, ViewerError> {
    let mesh = Mesh::build(kind, density);
    let (visibility, visibility_directions) = match btf_header(run)? {
        Some((_, lights, _)) => (mesh.visibility(lights.directions()), lights.len()),
        None => {
            // Not a BTF: a photometric-stereo result, or the error saying
            // what is missing.
            open(run)?;
            (Vec::new(), 0)
        }
    };
    Ok(MeshView {
        mesh,
        density,
        visibility,
        visibility_directions,
    })
}

/// The run's MDF texture (`processed/mdf-texture/`).
pub fn mdf_texture(run: &Path) -> Result<MdfTexture, ViewerError> {
    let dir = crate::store::processed::mdf_texture_dir(run);
    if !dir.join(MDF_TEXTURE_HEADER).is_file() {
        return Err(ViewerError::NoMdf {
            run: run.display().to_string(),
            dir: dir.display().to_string(),
        });
    }
    Ok(MdfTexture::read(&dir)?)
}

/// The manifest of the viewer's MDF blob ([`webgl::pack_mdf`]).
pub fn mdf_manifest(run: &Path) -> Result<MdfManifest, ViewerError> {
    Ok(webgl::mdf_manifest(&mdf_texture(run)?))
}

/// The viewer's MDF blob.
pub fn mdf_pack(run: &Path) -> Result<Vec<u8>, ViewerError> {
    Ok(webgl::pack_mdf(&mdf_texture(run)?).1)
}

/// The reference render with the MDF's silhouettes and shadows as `meso`
/// asks ([`rigd_process::silhouette`]); with both off, [`relight_run`]'s
/// image and no report.
pub fn render_run(
    run: &Path,
    kind: MeshKind,
    settings: &RelightSettings,
    meso: &MesoSettings,
) -> Result<(RgbImage, Option<SilhouetteReport>), ViewerError> {
    if !meso.silhouettes && !meso.shadows {
        return Ok((relight_run(run, kind, meso.density, settings)?, None));
    }
    let Material::Btf(store) = open(run)? else {
        return Err(ViewerError::NeedsBtf {
            what: "the reference renderer",
            run: run.display().to_string(),
        });
    };
    let mdf = mdf_texture(run)?;
    let mesh = Mesh::build(kind, meso.density);
    let (image, report) = silhouette::render(&store, &mesh, &mdf, settings, meso)?;
    Ok((image, Some(report)))
}

/// The reference render of a BTF run (`rigd process render`).
pub fn relight_run(
    run: &Path,
    kind: MeshKind,
    density: f64,
    settings: &RelightSettings,
) -> Result<RgbImage, ViewerError> {
    let Material::Btf(store) = open(run)? else {
        return Err(ViewerError::NeedsBtf {
            what: "the reference renderer",
            run: run.display().to_string(),
        });
    };
    let mesh = Mesh::build(kind, density);
    Ok(relight::relight(&store, &mesh, settings)?)
}
