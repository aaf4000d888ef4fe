//! A processed run in the form the browser viewer uploads to WebGL2 without
//! conversion: one binary blob plus a JSON manifest saying where
//! each part lies.
//!
//! # BTF (`kind: "btf"`)
//!
//! * `textures`: little-endian IEEE-754 half floats (`f16le`), one layer per
//!   (slot, k): layer `slot · (components + 1) + k`, k = 0 the slot's mean
//!   texture, k ≥ 1 its eigen-texture k. A layer is `height` rows from the
//!   sample's +y edge down, each `width` texels of `channels` interleaved
//!   values: what `texImage3D(TEXTURE_2D_ARRAY, 0, R16F | RGB16F, width,
//!   height, layers, 0, RED | RGB, HALF_FLOAT, …)` takes. Eigen-textures are
//!   scaled to a largest magnitude of 1 (half floats keep 11 significant bits
//!   there, where a unit-norm texture of 256² × 3 values would sit near the
//!   half-float subnormals); the scale moves into the weights.
//! * `weights`: little-endian f32 (`f32le`), `slots × lights × components`,
//!   slot-major, then light, then component: `p_isk · peak_sk`, so
//!   `value = M_s + Σ_k (Σ_i τ_i w_isk) B'_sk` with the stored B' is
//!   Sattler et al.'s eq. 3 unchanged.
//! * `light_table` and `view_table`: the measured directions, their rings
//!   (θ, pole, members as (φ, index) sorted by φ) for the shader's eq. 3 and
//!   5 interpolation, and each direction's solid angle for environment
//!   lighting (Sattler et al. eq. 10).
//!
//! # Photometric stereo (`kind: "photometric-stereo"`)
//!
//! `textures` holds two RGB `f16le` layers: the albedo (grey repeated) and
//! the unit normals (x right, y up, z towards the camera).
//!
//! Sections start on 4-byte boundaries so a `Float32Array` can view them.

use serde::Serialize;

use crate::btf::{CompressedBtf, TextureShape};
use crate::directions::{Direction, DirectionTable, RingLayout};
use crate::mdf::{MdfTexture, NO_DEPTH};

/// The format version the viewer checks.
pub const PACK_VERSION: u32 = 1;

/// Where one part of the blob lies.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Section {
    /// Start, bytes from the beginning of the blob (a multiple of 4).
    pub offset: usize,
    /// Length, bytes.
    pub bytes: usize,
    /// Value encoding: `f16le` (half floats) or `f32le`.
    pub encoding: &'static str,
}

/// A direction table as the viewer's shader reads it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TableLayout {
    /// The measured directions, in index order.
    pub directions: Vec<Direction>,
    /// Rings of equal θ, ascending, for the eq. 3 and 5 interpolation.
    pub rings: Vec<RingLayout>,
    /// Solid angle each direction stands for, steradians (summing to 2π).
    pub solid_angle_sr: Vec<f64>,
}

impl TableLayout {
    fn of(table: &DirectionTable) -> TableLayout {
        TableLayout {
            directions: table.directions().to_vec(),
            rings: table.ring_layout(),
            solid_angle_sr: table.solid_angles(),
        }
    }
}

/// The JSON manifest of a blob: what it holds and where; see the module
/// doc.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BlobManifest {
    /// Format version, [`PACK_VERSION`].
    pub version: u32,
    /// `btf` or `photometric-stereo`.
    pub kind: &'static str,
    /// Texture width, texels.
    pub width: usize,
    /// Texture height, texels (rows).
    pub height: usize,
    /// Values per texel in a layer: 1 or 3 (always 3 for photometric
    /// stereo).
    pub channels: usize,
    /// Components per slot in this blob (the stored ones, or fewer when asked).
    pub components: usize,
    /// Texture layers: slots × (components + 1) for a BTF, 2 for photometric
    /// stereo.
    pub layers: usize,
    /// The half-float texture layers.
    pub textures: Section,
    /// The BTF's f32 weights; `None` for photometric stereo.
    pub weights: Option<Section>,
    /// The BTF's light directions; `None` for photometric stereo.
    pub light_table: Option<TableLayout>,
    /// The BTF's view directions, one per slot; `None` for photometric
    /// stereo.
    pub view_table: Option<TableLayout>,
    /// Total blob size.
    pub bytes: usize,
}

/// The manifest of an MDF texture's blob ([`pack_mdf`]): one little-endian
/// f32 layer per view, `size` rows of `size` texels, rows as the BTF's
/// layers, millimetres along the view ray below the top plane, −1 = no
/// measurement: what `texImage3D(TEXTURE_2D_ARRAY, 0, R32F, size, size,
/// views, 0, RED, FLOAT, …)` takes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MdfManifest {
    /// Format version, [`PACK_VERSION`].
    pub version: u32,
    /// Side of every layer, texels.
    pub size: usize,
    /// Layers, one per view direction.
    pub views: usize,
    /// The view directions and their rings, for the same interpolation as
    /// the BTF's view slots.
    pub view_table: TableLayout,
    /// Side of the sample square one texture tile covers, mm: a depth in
    /// world units is `mm / (tile_mm · density)`.
    pub tile_mm: f64,
    /// Height of the top plane over the turntable, mm (for people).
    pub top_mm: f64,
    /// The value of a texel without a measurement.
    pub no_measurement: f32,
    /// The depths.
    pub depth: Section,
}

/// The manifest of `texture`'s blob, without packing it.
pub fn mdf_manifest(texture: &MdfTexture) -> MdfManifest {
    let header = texture.header();
    MdfManifest {
        version: PACK_VERSION,
        size: header.size,
        views: header.views.len(),
        view_table: TableLayout::of(texture.views()),
        tile_mm: header.tile_mm,
        top_mm: header.top_mm,
        no_measurement: NO_DEPTH,
        depth: Section {
            offset: 0,
            bytes: 4 * texture.depth_mm().len(),
            encoding: "f32le",
        },
    }
}

/// The viewer's blob of an MDF texture and its manifest.
pub fn pack_mdf(texture: &MdfTexture) -> (MdfManifest, Vec<u8>) {
    let mut out = Vec::with_capacity(4 * texture.depth_mm().len());
    for v in texture.depth_mm() {
        out.extend(v.to_le_bytes());
    }
    (mdf_manifest(texture), out)
}

fn push_f16(out: &mut Vec<u8>, values: impl Iterator<Item = f32>) {
    for v in values {
        out.extend(half::f16::from_f32(v).to_le_bytes());
    }
}

fn align4(out: &mut Vec<u8>) {
    out.resize(out.len().next_multiple_of(4), 0);
}

/// The manifest of a BTF's blob from what `btf.json` holds (no slot data
/// is read), keeping at most `max_components` per slot.
pub fn btf_manifest(
    shape: TextureShape,
    stored_components: usize,
    lights: &DirectionTable,
    views: &DirectionTable,
    max_components: usize,
) -> BlobManifest {
    let components = stored_components.min(max_components);
    let layers = views.len() * (components + 1);
    let texture_bytes = 2 * layers * shape.values();
    let weights_offset = texture_bytes.next_multiple_of(4);
    let weights_bytes = 4 * views.len() * lights.len() * components;
    BlobManifest {
        version: PACK_VERSION,
        kind: "btf",
        width: shape.width(),
        height: shape.height(),
        channels: shape.channels(),
        components,
        layers,
        textures: Section {
            offset: 0,
            bytes: texture_bytes,
            encoding: "f16le",
        },
        weights: Some(Section {
            offset: weights_offset,
            bytes: weights_bytes,
            encoding: "f32le",
        }),
        light_table: Some(TableLayout::of(lights)),
        view_table: Some(TableLayout::of(views)),
        bytes: weights_offset + weights_bytes,
    }
}

/// Packs `store`, keeping at most `max_components` per slot.
pub fn pack_btf(store: &CompressedBtf, max_components: usize) -> (BlobManifest, Vec<u8>) {
    let manifest = btf_manifest(
        store.shape(),
        store.components(),
        store.lights(),
        store.views(),
        max_components,
    );
    let components = manifest.components;
    let mut data = Vec::with_capacity(manifest.bytes);
    let mut peaks = Vec::with_capacity(store.slots().len() * components);
    for pca in store.slots() {
        push_f16(&mut data, pca.mean().iter().copied());
        for k in 0..components {
            let texture = pca.eigen_texture(k).unwrap_or(&[]);
            let peak = texture.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let scale = if peak > 0.0 { 1.0 / peak } else { 0.0 };
            push_f16(&mut data, texture.iter().map(|v| v * scale));
            peaks.push(peak);
        }
    }
    align4(&mut data);
    for (slot, pca) in store.slots().iter().enumerate() {
        for light in 0..store.lights().len() {
            let w = pca.light_weights(light).unwrap_or(&[]);
            for k in 0..components {
                let scaled = w.get(k).copied().unwrap_or(0.0) * peaks[slot * components + k];
                data.extend(scaled.to_le_bytes());
            }
        }
    }
    debug_assert_eq!(data.len(), manifest.bytes);
    (manifest, data)
}

/// Why a photometric-stereo result could not be packed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PackError {
    /// The albedo and normals arrays' shapes or lengths do not fit together.
    #[error(
        "albedo has shape {albedo:?} and normals {normals:?}: expected H×W (or H×W×C) and H×W×3"
    )]
    Shapes {
        /// Shape of the albedo array.
        albedo: Vec<usize>,
        /// Shape of the normals array.
        normals: Vec<usize>,
    },
}

/// Packs a photometric-stereo result: `albedo` H×W or H×W×C, `normals`
/// H×W×3 (shapes as in the `.npy` files).
pub fn pack_photometric_stereo(
    albedo_shape: &[usize],
    albedo: &[f32],
    normals_shape: &[usize],
    normals: &[f32],
) -> Result<(BlobManifest, Vec<u8>), PackError> {
    let bad = || PackError::Shapes {
        albedo: albedo_shape.to_vec(),
        normals: normals_shape.to_vec(),
    };
    let (h, w) = match normals_shape {
        [h, w, 3] => (*h, *w),
        _ => return Err(bad()),
    };
    let albedo_channels = match albedo_shape {
        [ah, aw] if (*ah, *aw) == (h, w) => 1,
        [ah, aw, c] if (*ah, *aw) == (h, w) && *c >= 1 => *c,
        _ => return Err(bad()),
    };
    if albedo.len() != h * w * albedo_channels || normals.len() != h * w * 3 {
        return Err(bad());
    }
    let mut data = Vec::with_capacity(2 * 6 * h * w);
    push_f16(
        &mut data,
        (0..h * w).flat_map(|t| {
            (0..3).map(move |c| albedo[t * albedo_channels + c.min(albedo_channels - 1)])
        }),
    );
    push_f16(&mut data, normals.iter().copied());
    let manifest = BlobManifest {
        version: PACK_VERSION,
        kind: "photometric-stereo",
        width: w,
        height: h,
        channels: 3,
        components: 0,
        layers: 2,
        textures: Section {
            offset: 0,
            bytes: 2 * 6 * h * w,
            encoding: "f16le",
        },
        weights: None,
        light_table: None,
        view_table: None,
        bytes: data.len(),
    };
    Ok((manifest, data))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::btf::{compress_slot, TextureShape};
    use crate::directions::h1;

    fn store() -> CompressedBtf {
        let shape = TextureShape::new(4, 3, 3).unwrap();
        let lights = DirectionTable::new(h1()).unwrap();
        let views = DirectionTable::new(vec![Direction::new(0.0, 0.0), Direction::new(40.0, 90.0)])
            .unwrap();
        let slots = (0..2)
            .map(|slot| {
                let images: Vec<Vec<f32>> = lights
                    .directions()
                    .iter()
                    .enumerate()
                    .map(|(i, l)| {
                        (0..36)
                            .map(|v| {
                                (0.3 + 0.2 * l.theta_deg.to_radians().cos()
                                    + 0.01 * (v * (i + slot) % 7) as f64)
                                    as f32
                            })
                            .collect()
                    })
                    .collect();
                let refs: Vec<&[f32]> = images.iter().map(Vec::as_slice).collect();
                compress_slot(&refs, shape, 5).unwrap()
            })
            .collect();
        CompressedBtf::new(shape, lights, views, slots).unwrap()
    }

    fn f16_at(data: &[u8], index: usize) -> f32 {
        half::f16::from_le_bytes([data[2 * index], data[2 * index + 1]]).to_f32()
    }

    #[test]
    fn the_blob_reconstructs_what_the_store_does() {
        let store = store();
        let (m, data) = pack_btf(&store, 3);
        assert_eq!(m.components, 3);
        assert_eq!(m.layers, 2 * 4);
        assert_eq!(m.bytes, data.len());
        let weights = m.weights.as_ref().unwrap();
        assert_eq!(weights.offset % 4, 0);
        assert_eq!(weights.bytes, 4 * 2 * 81 * 3);
        let values = 36;
        // Evaluate light 17 of slot 1 with 3 components from the blob.
        let (slot, light) = (1, 17);
        let weight = |k: usize| {
            let at = weights.offset + 4 * ((slot * 81 + light) * 3 + k);
            f32::from_le_bytes([data[at], data[at + 1], data[at + 2], data[at + 3]])
        };
        let pca = &store.slots()[slot];
        let want = pca.reconstruct_measured_truncated(light, 3).unwrap();
        for (v, &wanted) in want.iter().enumerate().take(values) {
            let mut got = f16_at(&data, (slot * 4) * values + v);
            for k in 0..3 {
                got += weight(k) * f16_at(&data, (slot * 4 + 1 + k) * values + v);
            }
            assert!((got - wanted).abs() < 2e-3, "value {v}: {got} vs {wanted}");
        }
        let rings = &m.light_table.as_ref().unwrap().rings;
        assert!(rings[0].pole);
    }

    #[test]
    fn photometric_stereo_maps_pack_and_bad_shapes_are_named() {
        let albedo = vec![0.5f32; 6];
        let normals: Vec<f32> = (0..6).flat_map(|_| [0.0, 0.0, 1.0]).collect();
        let (m, data) = pack_photometric_stereo(&[2, 3], &albedo, &[2, 3, 3], &normals).unwrap();
        assert_eq!((m.width, m.height, m.layers), (3, 2, 2));
        assert_eq!(f16_at(&data, 0), 0.5);
        assert_eq!(f16_at(&data, 18 + 2), 1.0);
        let err = pack_photometric_stereo(&[3, 3], &albedo, &[2, 3, 3], &normals).unwrap_err();
        assert!(err.to_string().contains("[3, 3]"), "{err}");
    }
}
