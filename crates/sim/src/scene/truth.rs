//! Ground truth from a scene, for judging what the post-processing
//! recovers: the reflectance a perfect rig would measure at any texel for
//! any (light, view), the true height and normals, the mesostructure
//! distance function (Wang et al., §3), and where the markers are in a frame.
//!
//! BTF texels are points (x, y) of the holder plane z = 0, the plane the
//! markers register frames to (Sattler et al., §3.2): a texel shows what the ray
//! through (x, y, 0) from the view direction meets first. The MDF's texels
//! lie on a reference plane at the top of the relief (Wang et al., §3: "a
//! reference surface that lies above the top of mesostructure details").

use super::effects::{Effect, EffectSwitches};
use rigd_core::geometry::{add, normalize, scale};

use super::shade::Frame;
use super::shot::Shot;
use super::{Marker, Scene};

impl Scene {
    /// The apparent reflectance factor at texel (x, y) of the holder plane
    /// for a directional light and an orthographic view: the BTF value, with
    /// parallax, masking, shadows and the lobe as the scene renders them
    /// (1 = white Lambertian, frontally lit). `effects` switches as in a
    /// frame; sensor effects never apply.
    pub fn true_btf(
        &self,
        x: f64,
        y: f64,
        light: [f64; 3],
        view: [f64; 3],
        effects: EffectSwitches,
    ) -> f64 {
        self.true_btf_through(x, y, light, view, effects, None)
    }

    /// [`Scene::true_btf`] in one channel of linear sRGB (0 red, 1 green,
    /// 2 blue): what a perfect colour camera, colour-corrected, records.
    /// The grey BTF is its luminance.
    pub fn true_btf_channel(
        &self,
        x: f64,
        y: f64,
        light: [f64; 3],
        view: [f64; 3],
        channel: usize,
    ) -> f64 {
        let filter = &super::colour::SRGB_CHANNELS[channel.min(2)];
        self.true_btf_through(x, y, light, view, Default::default(), Some(filter))
    }

    fn true_btf_through(
        &self,
        x: f64,
        y: f64,
        light: [f64; 3],
        view: [f64; 3],
        effects: EffectSwitches,
        filter: Option<&[f64; 3]>,
    ) -> f64 {
        let v = normalize(view);
        let mut fx = effects;
        fx.forbid.insert(Effect::Noise);
        fx.forbid.insert(Effect::Vignetting);
        let shot = Shot {
            light,
            view: v,
            effects: fx,
            ..Shot::default()
        };
        let mut frame = Frame::new(self, &shot);
        frame.colour = filter.is_some();
        if v[2] <= 1e-9 {
            return 0.0;
        }
        // Back along the ray through (x, y, 0) to above the relief.
        let above = add(
            [x, y, 0.0],
            scale(v, (self.reference_height() + 1e-6) / v[2]),
        );
        match frame.intersect(above, scale(v, -1.0)) {
            Some(p) => frame.shade(p, v, filter),
            None => 0.0,
        }
    }

    /// The true surface height at (x, y), metres above the holder.
    pub fn true_height(&self, x: f64, y: f64) -> f64 {
        self.height(x, y)
    }

    /// The true unit normal at (x, y).
    pub fn true_normal(&self, x: f64, y: f64) -> [f64; 3] {
        self.normal(x, y)
    }

    /// The mesostructure distance D(x, y, v): how far along -v from the
    /// reference-plane point (x, y) the ray first meets the surface, metres.
    /// `None` for a view at or below the horizon.
    pub fn true_mdf(&self, x: f64, y: f64, view: [f64; 3]) -> Option<f64> {
        let v = normalize(view);
        if v[2] <= 1e-9 {
            return None;
        }
        let shot = Shot {
            view: v,
            ..Shot::default()
        };
        let frame = Frame::new(self, &shot);
        let start = [x, y, self.reference_height()];
        let p = frame.intersect(add(start, scale(v, 1e-9)), scale(v, -1.0))?;
        let d = [p[0] - start[0], p[1] - start[1], p[2] - start[2]];
        Some((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt())
    }

    /// The surface point pixel (i, j) of this shot's frame sees, with the
    /// relief always marched (whatever the shot's switches), or None if the
    /// ray misses everything.
    pub fn true_surface_point(&self, shot: &Shot, i: usize, j: usize) -> Option<[f64; 3]> {
        let mut s = *shot;
        s.effects.forbid.remove(Effect::Relief);
        let frame = Frame::new(self, &s);
        let (o, d) = super::shot::camera(self, &s).ray(i, j);
        frame.intersect(o, d)
    }

    /// Where every marker lands in the frame this shot takes, in pixels
    /// (x right, y down, pixel i spanning [i, i+1)); `None` behind the camera.
    pub fn true_markers(&self, shot: &Shot) -> Vec<(Marker, Option<[f64; 2]>)> {
        self.marker_pixels(shot)
    }
}
