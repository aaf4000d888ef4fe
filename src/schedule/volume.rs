//! How much raw sensor data a schedule produces: every image at its
//! camera's resolution and bit depth, before the store's compression.
//! Labs size disks and transfers by it (one Bonn H2 is 6561 frames of a
//! 3032 × 2008 sensor), and `plan show`, `/plans` and the trade-off report
//! all quote it.

use serde::Serialize;

use super::Schedule;
use crate::model::exposure::ExposurePolicy;
use crate::model::profile::Profile;

/// The raw data of a schedule.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct DataVolume {
    /// Raw sensor bytes of all images: one byte a pixel at 8 bits, two
    /// above.
    pub raw_bytes: u64,
    /// The largest single image, bytes.
    pub largest_image_bytes: u64,
}

/// Bytes of one image from `camera`: its resolution at one byte a pixel up
/// to 8 bits, two above; 0 for a camera without intrinsics.
pub fn image_bytes(profile: &Profile, camera: &str) -> u64 {
    profile
        .devices
        .get(camera)
        .and_then(|d| d.intrinsics())
        .map_or(0, |i| {
            let pixels = u64::from(i.resolution[0]) * u64::from(i.resolution[1]);
            if i.bit_depth > 8 {
                2 * pixels
            } else {
                pixels
            }
        })
}

/// The raw data `schedule` produces on `profile`'s cameras under an
/// exposure policy: a `brackets` run stores every exposure of every image
/// (a laser sweep's frames take one); an `auto` run is counted as if
/// nothing clipped.
pub fn data_volume(profile: &Profile, schedule: &Schedule, policy: &ExposurePolicy) -> DataVolume {
    let mut volume = DataVolume {
        raw_bytes: 0,
        largest_image_bytes: 0,
    };
    let series = policy.first_exposures(0.0).len() as u64;
    for img in &schedule.images {
        let bytes = image_bytes(profile, &img.camera);
        let exposures = if schedule.triggers[img.trigger].sweep.is_some() {
            1
        } else {
            series
        };
        volume.raw_bytes += bytes * exposures;
        volume.largest_image_bytes = volume.largest_image_bytes.max(bytes);
    }
    volume
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_h2_on_the_bonn_rig_is_6561_sixteen_bit_frames() {
        let profile = Profile::load("bonn-gonioreflectometer").expect("embedded profile");
        let solver = crate::kinematics::Solver::new(&profile).expect("solver");
        let offer = super::super::rig_offer(&profile, &solver);
        let plan = crate::plan::resolve("h2", &offer).expect("h2");
        let schedule = super::super::build(&profile, &solver, &plan);
        let v = data_volume(&profile, &schedule, &ExposurePolicy::default());
        let camera = &schedule.images[0].camera;
        let intr = profile.devices[camera].intrinsics().expect("intrinsics");
        let frame = u64::from(intr.resolution[0]) * u64::from(intr.resolution[1]) * 2;
        assert!(intr.bit_depth > 8);
        assert_eq!(v.largest_image_bytes, frame);
        assert_eq!(v.raw_bytes, 6561 * frame);
        // Brackets store every exposure; `auto` is counted as if nothing
        // clipped.
        let brackets: ExposurePolicy = "brackets:0.25,0.0625,0.015625".parse().expect("policy");
        let v = data_volume(&profile, &schedule, &brackets);
        assert_eq!(v.raw_bytes, 3 * 6561 * frame);
        assert_eq!(v.largest_image_bytes, frame);
        let auto: ExposurePolicy = "auto".parse().expect("policy");
        assert_eq!(
            data_volume(&profile, &schedule, &auto).raw_bytes,
            6561 * frame
        );
    }
}
