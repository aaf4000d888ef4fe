//! What the exposure policy needs to see of a frame while the rig is still
//! capturing: how much of the sample it clipped. The sample is where the
//! rig's pose puts the holder's sample window in the frame; a white
//! marker that clips beside it costs no retake.

use rigd_core::camera::Camera;
use rigd_core::pixel_format::CLIPPED_LEVEL;
use rigd_core::Direction;

use crate::model::profile::Profile;
use crate::rig::hal::Frame;

/// The sample window's corners in a frame of camera `camera` seen from
/// `view`, pixels, as the rig's pose predicts them; None when the profile
/// cannot say (a camera without intrinsics, a holder that does not
/// resolve, a corner behind the camera).
pub fn sample_window(
    profile: &Profile,
    camera: &str,
    size: [u32; 2],
    view: Direction,
) -> Option<[[f64; 2]; 4]> {
    let geometry = crate::kinematics::camera::camera_geometry(profile, camera, size)?;
    let holder = profile.holder.holder().ok()?;
    let cam = Camera::new(
        view.to_vector(),
        size,
        Some(geometry.focal_px),
        geometry.distance_m,
        1.1 * holder.half,
    );
    let [hx, hy] = holder.sample_half;
    let corner = |x: f64, y: f64| cam.project([x, y, 0.0]);
    Some([
        corner(-hx, -hy)?,
        corner(hx, -hy)?,
        corner(hx, hy)?,
        corner(-hx, hy)?,
    ])
}

/// How far beyond the sample window a clipped pixel still reaches the
/// sample's texels, pixels: a Bayer demosaic reads up to 3 pixels around
/// (AHD), and the resampling one more. A window seen near grazing is only
/// a few pixels tall, so its edges matter.
pub const WINDOW_MARGIN_PX: f64 = 4.0;

/// The share of `window`'s pixels (the whole frame without one), taken
/// with a margin of [`WINDOW_MARGIN_PX`], whose value is clipped: at or
/// above [`CLIPPED_LEVEL`] of the frame's full scale. A window wholly off
/// the frame clips nothing.
pub fn clipped_share(frame: &Frame, window: Option<&[[f64; 2]; 4]>) -> f64 {
    let (w, h) = (frame.width as usize, frame.height as usize);
    if w == 0 || h == 0 || frame.pixels.len() != w * h {
        return 0.0;
    }
    let full = (1u32 << frame.bit_depth.clamp(1, 16)) - 1;
    let level = (CLIPPED_LEVEL as f64 * f64::from(full)).ceil() as u32;
    let clipped = |v: u16| u32::from(v) >= level;
    let Some(quad) = window else {
        let n = frame.pixels.iter().filter(|&&v| clipped(v)).count();
        return n as f64 / frame.pixels.len() as f64;
    };
    // The quadrilateral's bounding box, clamped to the frame.
    let xs = quad.map(|p| p[0] - WINDOW_MARGIN_PX);
    let ys = quad.map(|p| p[1] - WINDOW_MARGIN_PX);
    let xs_far = quad.map(|p| p[0] + WINDOW_MARGIN_PX);
    let ys_far = quad.map(|p| p[1] + WINDOW_MARGIN_PX);
    let lo = |v: [f64; 4], n: usize| {
        (v.iter()
            .copied()
            .fold(f64::INFINITY, f64::min)
            .floor()
            .max(0.0) as usize)
            .min(n)
    };
    let hi = |v: [f64; 4], n: usize| {
        (v.iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max)
            .ceil()
            .max(0.0) as usize)
            .min(n)
    };
    let (x0, x1, y0, y1) = (lo(xs, w), hi(xs_far, w), lo(ys, h), hi(ys_far, h));
    let margin = WINDOW_MARGIN_PX;
    let (mut inside, mut hit) = (0usize, 0usize);
    for y in y0..y1 {
        for x in x0..x1 {
            if near(quad, [x as f64 + 0.5, y as f64 + 0.5], margin) {
                inside += 1;
                if clipped(frame.pixels[y * w + x]) {
                    hit += 1;
                }
            }
        }
    }
    if inside == 0 {
        0.0
    } else {
        hit as f64 / inside as f64
    }
}

/// Whether point `p` lies inside the convex quadrilateral `quad` (either
/// winding, possibly degenerate) or within `margin` of its edges.
fn near(quad: &[[f64; 2]; 4], p: [f64; 2], margin: f64) -> bool {
    let side =
        |a: [f64; 2], b: [f64; 2]| (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]);
    let sides: [f64; 4] = std::array::from_fn(|i| side(quad[i], quad[(i + 1) % 4]));
    let inside = sides.iter().all(|&s| s >= 0.0) || sides.iter().all(|&s| s <= 0.0);
    inside || (0..4).any(|i| segment_distance(quad[i], quad[(i + 1) % 4], p) <= margin)
}

/// The distance from `p` to the segment from `a` to `b`.
fn segment_distance(a: [f64; 2], b: [f64; 2], p: [f64; 2]) -> f64 {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let length2 = dx * dx + dy * dy;
    let t = if length2 > 0.0 {
        (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / length2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (p[0] - a[0] - t * dx).hypot(p[1] - a[1] - t * dy)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(width: u32, height: u32, pixels: Vec<u16>) -> Frame {
        Frame {
            width,
            height,
            bit_depth: 12,
            pixels,
            device: None,
            original: None,
        }
    }

    #[test]
    fn only_the_sample_window_s_clipped_pixels_count() {
        // 30×30, the window the centre 4×4 (13 … 17) and its margin: 12×12
        // pixel centres, rounded corners left out.
        let window = [[13.0, 13.0], [17.0, 13.0], [17.0, 17.0], [13.0, 17.0]];
        let inside = (0..900)
            .filter(|i| near(&window, [(i % 30) as f64 + 0.5, (i / 30) as f64 + 0.5], 4.0))
            .count();
        assert!((4 * 4 + 4 * 4 * 4..=12 * 12).contains(&inside), "{inside}");
        // Two white markers far beside the sample cost nothing.
        let mut pixels = vec![100u16; 900];
        pixels[0] = 4095;
        pixels[899] = 4094;
        let f = frame(30, 30, pixels.clone());
        assert_eq!(clipped_share(&f, Some(&window)), 0.0);
        assert_eq!(clipped_share(&f, None), 2.0 / 900.0);
        // One inside counts, and so does one 2 pixels outside the edge,
        // which a demosaic reads into the sample's texels.
        pixels[15 * 30 + 15] = 4095;
        let f = frame(30, 30, pixels.clone());
        assert_eq!(clipped_share(&f, Some(&window)), 1.0 / inside as f64);
        pixels[15 * 30 + 19] = 4095;
        let f = frame(30, 30, pixels);
        assert_eq!(clipped_share(&f, Some(&window)), 2.0 / inside as f64);
        // Wound the other way round: the same window.
        let reversed = [[13.0, 13.0], [13.0, 17.0], [17.0, 17.0], [17.0, 13.0]];
        assert_eq!(clipped_share(&f, Some(&reversed)), 2.0 / inside as f64);
        // Below the level (99.5 % of 4095 is 4074.5): not clipped.
        let mut pixels = vec![4074u16; 100];
        pixels[55] = 4075;
        assert_eq!(clipped_share(&frame(10, 10, pixels), None), 0.01);
    }

    #[test]
    fn a_window_off_the_frame_clips_nothing_and_one_edge_on_still_reads_its_pixels() {
        let f = frame(4, 4, vec![4095; 16]);
        let off = [[20.0, 20.0], [22.0, 20.0], [22.0, 22.0], [20.0, 22.0]];
        assert_eq!(clipped_share(&f, Some(&off)), 0.0);
        // Seen edge-on (grazing), the sample is a line whose texels read
        // the pixels around it.
        let edge_on = [[0.0, 2.0], [4.0, 2.0], [4.0, 2.0], [0.0, 2.0]];
        assert_eq!(clipped_share(&f, Some(&edge_on)), 1.0);
        assert_eq!(clipped_share(&frame(0, 0, vec![]), None), 0.0);
    }

    #[test]
    fn the_bonn_rig_s_sample_window_sits_inside_a_frontal_frame() {
        let profile = Profile::load("bonn-gonioreflectometer").unwrap_or_else(|e| panic!("{e}"));
        let camera = profile.camera_names().remove(0);
        let quad = sample_window(&profile, &camera, [320, 240], Direction::new(0.0, 0.0))
            .expect("a window");
        for [x, y] in quad {
            assert!(
                (0.0..=320.0).contains(&x) && (0.0..=240.0).contains(&y),
                "{quad:?}"
            );
        }
        // A grazing view foreshortens it.
        let grazing = sample_window(&profile, &camera, [320, 240], Direction::new(80.0, 0.0))
            .expect("a window");
        let area = |q: [[f64; 2]; 4]| {
            0.5 * (0..4)
                .map(|i| q[i][0] * q[(i + 1) % 4][1] - q[(i + 1) % 4][0] * q[i][1])
                .sum::<f64>()
                .abs()
        };
        assert!(
            area(grazing) < 0.3 * area(quad),
            "{grazing:?} against {quad:?}"
        );
    }
}
