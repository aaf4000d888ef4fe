//! Colour charts a holder may carry, and the colour spaces their reference
//! values are given in: CIE L\*a\*b\* under D50 (how chart makers publish
//! them) and linear sRGB (D65 white), the simulator's and the cameras'
//! working space. D50 and D65 are related by the Bradford chromatic
//! adaptation.

/// A chart patch: its maker's name and published reference value.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChartPatch {
    /// The maker's name for the patch (`dark skin`, `white 9.5`, …).
    pub name: &'static str,
    /// CIE L\*a\*b\* (D50, 2° observer).
    pub lab_d50: [f64; 3],
}

/// A chart rigd knows by name.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Chart {
    /// The name a profile gives (`colorchecker24`).
    pub name: &'static str,
    /// Rows of the patch grid.
    pub rows: usize,
    /// Columns of the patch grid.
    pub columns: usize,
    /// The patches row by row, from the top left (as the chart is read
    /// with its legend below).
    pub patches: &'static [ChartPatch],
}

/// The X-Rite (Calibrite) ColorChecker Classic, formulation from November
/// 2014 on: 4 rows of 6 patches, dark skin at the top left, black 2 at the
/// bottom right; X-Rite's published L\*a\*b\* (D50).
pub const COLORCHECKER24: Chart = Chart {
    name: "colorchecker24",
    rows: 4,
    columns: 6,
    patches: &[
        p("dark skin", 37.54, 14.37, 14.92),
        p("light skin", 64.66, 19.27, 17.50),
        p("blue sky", 49.32, -3.82, -22.54),
        p("foliage", 43.46, -12.74, 22.72),
        p("blue flower", 54.94, 9.61, -24.79),
        p("bluish green", 70.48, -32.26, -0.37),
        p("orange", 62.73, 35.83, 56.50),
        p("purplish blue", 39.43, 10.75, -45.17),
        p("moderate red", 50.57, 48.64, 16.67),
        p("purple", 30.10, 22.54, -20.87),
        p("yellow green", 71.77, -24.13, 58.19),
        p("orange yellow", 71.51, 18.24, 67.37),
        p("blue", 28.37, 15.42, -49.80),
        p("green", 54.38, -39.72, 32.27),
        p("red", 42.43, 51.05, 28.62),
        p("yellow", 81.80, 2.67, 80.41),
        p("magenta", 50.63, 51.28, -14.12),
        p("cyan", 49.57, -29.71, -28.32),
        p("white 9.5", 95.19, -1.03, 2.93),
        p("neutral 8", 81.29, -0.57, 0.44),
        p("neutral 6.5", 66.89, -0.75, -0.06),
        p("neutral 5", 50.76, -0.13, 0.14),
        p("neutral 3.5", 35.63, -0.46, -0.48),
        p("black 2", 20.64, 0.07, -0.46),
    ],
};

const fn p(name: &'static str, l: f64, a: f64, b: f64) -> ChartPatch {
    ChartPatch {
        name,
        lab_d50: [l, a, b],
    }
}

/// Every chart known by name.
pub const CHARTS: [Chart; 1] = [COLORCHECKER24];

/// The chart called `name`, if rigd knows it.
pub fn chart(name: &str) -> Option<&'static Chart> {
    CHARTS.iter().find(|c| c.name == name)
}

/// The D50 white (ICC), XYZ with Y = 1.
pub const D50: [f64; 3] = [0.964_22, 1.0, 0.825_21];

/// Bradford adaptation from D50 to D65.
const D50_TO_D65: [[f64; 3]; 3] = [
    [0.955_576_6, -0.023_039_3, 0.063_163_6],
    [-0.028_289_5, 1.009_941_6, 0.021_007_7],
    [0.012_298_2, -0.020_483_0, 1.329_909_8],
];

/// Bradford adaptation from D65 to D50.
const D65_TO_D50: [[f64; 3]; 3] = [
    [1.047_811_2, 0.022_886_6, -0.050_127_0],
    [0.029_542_4, 0.990_484_4, -0.017_049_1],
    [-0.009_234_5, 0.015_043_6, 0.752_131_6],
];

/// XYZ (D65) to linear sRGB.
const XYZ_TO_SRGB: [[f64; 3]; 3] = [
    [3.240_454_2, -1.537_138_5, -0.498_531_4],
    [-0.969_266_0, 1.876_010_8, 0.041_556_0],
    [0.055_643_4, -0.204_025_9, 1.057_225_2],
];

/// Linear sRGB to XYZ (D65).
const SRGB_TO_XYZ: [[f64; 3]; 3] = [
    [0.412_456_4, 0.357_576_1, 0.180_437_5],
    [0.212_672_9, 0.715_152_2, 0.072_175_0],
    [0.019_333_9, 0.119_192_0, 0.950_304_1],
];

fn mul(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|r| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2])
}

/// CIE L\*a\*b\* to XYZ relative to `white`.
pub fn lab_to_xyz(lab: [f64; 3], white: [f64; 3]) -> [f64; 3] {
    const E: f64 = 6.0 / 29.0;
    let fy = (lab[0] + 16.0) / 116.0;
    let f = [fy + lab[1] / 500.0, fy, fy - lab[2] / 200.0];
    let inv = |t: f64| {
        if t > E {
            t * t * t
        } else {
            3.0 * E * E * (t - 4.0 / 29.0)
        }
    };
    [0, 1, 2].map(|k| white[k] * inv(f[k]))
}

/// XYZ relative to `white` to CIE L\*a\*b\*.
pub fn xyz_to_lab(xyz: [f64; 3], white: [f64; 3]) -> [f64; 3] {
    const E: f64 = 6.0 / 29.0;
    let f = |t: f64| {
        if t > E * E * E {
            t.cbrt()
        } else {
            t / (3.0 * E * E) + 4.0 / 29.0
        }
    };
    let [fx, fy, fz] = [0, 1, 2].map(|k| f(xyz[k] / white[k]));
    [116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)]
}

/// L\*a\*b\* (D50) to linear sRGB (D65 white, Bradford-adapted); a colour
/// outside the sRGB gamut comes out below 0 or above 1 in some channel.
pub fn lab_d50_to_linear_srgb(lab: [f64; 3]) -> [f64; 3] {
    mul(&XYZ_TO_SRGB, mul(&D50_TO_D65, lab_to_xyz(lab, D50)))
}

/// Linear sRGB (D65 white) to L\*a\*b\* (D50, Bradford-adapted).
pub fn linear_srgb_to_lab_d50(rgb: [f64; 3]) -> [f64; 3] {
    xyz_to_lab(mul(&D65_TO_D50, mul(&SRGB_TO_XYZ, rgb)), D50)
}

/// A linear sRGB value (reflectance, 0 to 1) as its sRGB-encoded value
/// (IEC 61966-2-1), what a printer or a screen is given; clamped to [0, 1].
pub fn linear_to_srgb(v: f64) -> f64 {
    let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
    if v >= 1.0 {
        // The curve's end is exactly white, not a rounding short of it.
        1.0
    } else if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// The matrix from a camera's white-balanced RGB to linear sRGB, from its
/// XYZ (D65) to camera matrix (a raw file's ColorMatrix), as raw converters
/// build it: sRGB to camera through XYZ, each row scaled so that white
/// stays white, then inverted. None when it cannot be inverted.
pub fn camera_to_linear_srgb(xyz_to_camera: [[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let mut srgb_to_camera = [[0.0; 3]; 3];
    for (r, row) in srgb_to_camera.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = (0..3)
                .map(|k| xyz_to_camera[r][k] * SRGB_TO_XYZ[k][c])
                .sum();
        }
        let sum: f64 = row.iter().sum();
        if sum.abs() < 1e-12 || !sum.is_finite() {
            return None;
        }
        for v in row.iter_mut() {
            *v /= sum;
        }
    }
    invert3(&srgb_to_camera)
}

/// The inverse of a 3×3 matrix by its adjugate; None when singular.
fn invert3(m: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let cof =
        |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    let adj = [
        [cof(1, 2, 1, 2), -cof(0, 2, 1, 2), cof(0, 1, 1, 2)],
        [-cof(1, 2, 0, 2), cof(0, 2, 0, 2), -cof(0, 1, 0, 2)],
        [cof(1, 2, 0, 1), -cof(0, 2, 0, 1), cof(0, 1, 0, 1)],
    ];
    let det = m[0][0] * adj[0][0] + m[0][1] * adj[1][0] + m[0][2] * adj[2][0];
    if det.abs() < 1e-12 || !det.is_finite() {
        return None;
    }
    Some(adj.map(|row| row.map(|v| v / det)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_srgb_camera_s_matrix_is_the_identity() {
        // A camera whose channels are the sRGB primaries: its ColorMatrix
        // is XYZ to linear sRGB.
        let m = camera_to_linear_srgb(XYZ_TO_SRGB).expect("invertible");
        for (r, row) in m.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                let want = if r == c { 1.0 } else { 0.0 };
                assert!((v - want).abs() < 1e-3, "{m:?}");
            }
        }
        assert_eq!(camera_to_linear_srgb([[0.0; 3]; 3]), None);
    }

    #[test]
    fn srgb_encoding_meets_its_published_points() {
        assert_eq!(linear_to_srgb(0.0), 0.0);
        assert!((linear_to_srgb(1.0) - 1.0).abs() < 1e-12);
        // 18 % grey is sRGB 117.6/255; the linear toe's end meets the curve.
        assert!((linear_to_srgb(0.18) * 255.0 - 117.63).abs() < 0.05);
        assert!((linear_to_srgb(0.003_130_8) - 0.040_45).abs() < 1e-5);
        assert_eq!(linear_to_srgb(-1.0), 0.0);
        assert_eq!(linear_to_srgb(2.0), 1.0);
    }

    #[test]
    fn lab_and_linear_srgb_round_trip() {
        for patch in COLORCHECKER24.patches {
            let back = linear_srgb_to_lab_d50(lab_d50_to_linear_srgb(patch.lab_d50));
            for k in 0..3 {
                assert!(
                    (back[k] - patch.lab_d50[k]).abs() < 1e-3,
                    "{patch:?}: {back:?}"
                );
            }
        }
    }

    #[test]
    fn the_d50_white_is_srgb_white() {
        let rgb = lab_d50_to_linear_srgb([100.0, 0.0, 0.0]);
        for v in rgb {
            assert!((v - 1.0).abs() < 2e-3, "{rgb:?}");
        }
    }

    /// colour-science's `ColorChecker24 - After November 2014` (X-Rite's
    /// L\*a\*b\* as xyY under the ICC D50 white, x 0.3457, y 0.3585): the
    /// table above converted back must land within X-Rite's rounding.
    #[test]
    fn the_table_is_colour_science_s_after_november_2014_data() {
        let xyy = [
            ("dark skin", [0.437_488, 0.378_489, 0.098_324]),
            ("blue sky", [0.276_138, 0.298_342, 0.178_552]),
            ("bluish green", [0.286_402, 0.389_675, 0.414_355]),
            ("red", [0.562_883, 0.335_536, 0.127_801]),
            ("yellow", [0.467_778, 0.475_996, 0.599_298]),
            ("cyan", [0.209_120, 0.302_615, 0.180_610]),
            ("white 9.5", [0.348_912, 0.364_174, 0.880_690]),
            ("black 2", [0.343_764, 0.356_019, 0.031_513]),
        ];
        for (name, [x, y, big_y]) in xyy {
            let xyz = [x * big_y / y, big_y, (1.0 - x - y) * big_y / y];
            let lab = xyz_to_lab(xyz, D50);
            let patch = COLORCHECKER24
                .patches
                .iter()
                .find(|p| p.name == name)
                .expect("a ColorChecker patch");
            for k in 0..3 {
                assert!(
                    (lab[k] - patch.lab_d50[k]).abs() < 0.05,
                    "{name}: {lab:?} from colour-science, {:?} here",
                    patch.lab_d50
                );
            }
        }
    }

    #[test]
    fn the_chart_reads_as_its_maker_lays_it_out() {
        let c = chart("colorchecker24").expect("known");
        assert_eq!(c.patches.len(), c.rows * c.columns);
        assert_eq!(c.patches[0].name, "dark skin");
        assert_eq!(c.patches[5].name, "bluish green");
        assert_eq!(c.patches[18].name, "white 9.5");
        assert_eq!(c.patches[23].name, "black 2");
        assert!(chart("colorchecker140").is_none());
    }
}
