//! A profile's cameras and lamps as optics: how far each stands from the
//! sample, and a camera's focal length in pixels of the frames it delivers.

use std::collections::BTreeMap;

use crate::model::profile::{Profile, RigGeometry};

/// Where a profile's camera stands and how it images, for frames of a
/// given size: what the simulator renders with and the rectification
/// predicts marker positions with.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraGeometry {
    /// The sensor's focal length scaled to the simulated frame's width.
    pub focal_px: f64,
    /// Distance from the sample centre, metres (None: unknown).
    pub distance_m: Option<f64>,
    /// Bits per sample of the sensor.
    pub bit_depth: u8,
    /// The distance of the profile's first lamp (None: a directional light).
    pub lamp_distance_m: Option<f64>,
}

/// A camera's geometry for frames of `size`; None if it is not a camera
/// with intrinsics.
pub fn camera_geometry(profile: &Profile, camera: &str, size: [u32; 2]) -> Option<CameraGeometry> {
    let i = profile.devices.get(camera)?.as_camera()?.intrinsics;
    Some(CameraGeometry {
        focal_px: i.focal_px * profile.sim.zoom * f64::from(size[0])
            / f64::from(i.resolution[0].max(1)),
        distance_m: camera_distance(profile, camera),
        bit_depth: i.bit_depth,
        lamp_distance_m: lamp_distances(profile).into_values().next(),
    })
}

/// How far a camera stands from the sample centre.
pub fn camera_distance(profile: &Profile, camera: &str) -> Option<f64> {
    let own = profile.devices.get(camera).and_then(|d| d.distance_m());
    own.or(match &profile.rig {
        RigGeometry::Gonioreflectometer { rail_radius_m, .. } => Some(*rail_radius_m),
        _ => None,
    })
}

/// How far each lamp stands from the sample centre.
pub fn lamp_distances(profile: &Profile) -> BTreeMap<String, f64> {
    profile
        .lamp_names()
        .into_iter()
        .filter_map(|lamp| {
            let own = profile.devices.get(&lamp).and_then(|d| d.distance_m());
            let d = own.or(match &profile.rig {
                RigGeometry::Gonioreflectometer {
                    lamp_distance_m, ..
                } => Some(*lamp_distance_m),
                RigGeometry::TurntableArcs { arc_radius_m, .. } => Some(*arc_radius_m),
                RigGeometry::FixedLamps { .. } => None,
            })?;
            Some((lamp, d))
        })
        .collect()
}
