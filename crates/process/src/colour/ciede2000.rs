//! The CIEDE2000 colour difference (CIE 142-2001), as Sharma, Wu & Dalal
//! spell it out in "The CIEDE2000 color-difference formula: implementation
//! notes, supplementary test data, and mathematical observations" (Color
//! Research & Application 30(1), 2005), with the parametric factors
//! kL = kC = kH = 1 (reference conditions).
//!
//! Unlike ΔE*ab it weighs lightness, chroma and hue differences as an
//! observer does: a difference near neutral counts more than the same
//! Euclidean distance among saturated colours, and blues get the rotation
//! term. A ΔE2000 of about 1 is a just-noticeable difference side by side.

/// 25⁷, the chroma at which the a\* rescaling G and the rotation's R_C are
/// half their extremes.
const POW25_7: f64 = 6_103_515_625.0;

/// The hue angle of (a, b) in degrees, in [0, 360); 0 for a neutral.
fn hue_degrees(a: f64, b: f64) -> f64 {
    if a == 0.0 && b == 0.0 {
        return 0.0;
    }
    b.atan2(a).to_degrees().rem_euclid(360.0)
}

/// CIEDE2000 colour difference ΔE00 between two CIE L\*a\*b\* colours (any
/// white, the same for both). Symmetric; 0 for equal colours; NaN in, NaN
/// out.
pub fn delta_e2000(lab1: [f64; 3], lab2: [f64; 3]) -> f64 {
    let [l1, a1, b1] = lab1;
    let [l2, a2, b2] = lab2;
    // a* rescaled so that near-neutral colours' hue differences are not
    // overweighted (step 1 of Sharma et al.).
    let c_mean = (a1.hypot(b1) + a2.hypot(b2)) / 2.0;
    let c7 = c_mean.powi(7);
    let g = 0.5 * (1.0 - (c7 / (c7 + POW25_7)).sqrt());
    let (a1p, a2p) = ((1.0 + g) * a1, (1.0 + g) * a2);
    let (c1p, c2p) = (a1p.hypot(b1), a2p.hypot(b2));
    let (h1p, h2p) = (hue_degrees(a1p, b1), hue_degrees(a2p, b2));

    // Differences (step 2): the hue difference the short way round the
    // circle, none when either colour is neutral.
    let dl = l2 - l1;
    let dc = c2p - c1p;
    let neutral = c1p * c2p == 0.0;
    let dh_angle = if neutral {
        0.0
    } else {
        let d = h2p - h1p;
        if d > 180.0 {
            d - 360.0
        } else if d < -180.0 {
            d + 360.0
        } else {
            d
        }
    };
    let dh = 2.0 * (c1p * c2p).sqrt() * (dh_angle.to_radians() / 2.0).sin();

    // Weights (step 3): the mean hue also the short way round; with a
    // neutral it is the other colour's hue (their sum).
    let l_mean = (l1 + l2) / 2.0;
    let cp_mean = (c1p + c2p) / 2.0;
    let h_mean = if neutral {
        h1p + h2p
    } else if (h1p - h2p).abs() <= 180.0 {
        (h1p + h2p) / 2.0
    } else if h1p + h2p < 360.0 {
        (h1p + h2p + 360.0) / 2.0
    } else {
        (h1p + h2p - 360.0) / 2.0
    };
    let cos_deg = |d: f64| d.to_radians().cos();
    let t = 1.0 - 0.17 * cos_deg(h_mean - 30.0)
        + 0.24 * cos_deg(2.0 * h_mean)
        + 0.32 * cos_deg(3.0 * h_mean + 6.0)
        - 0.20 * cos_deg(4.0 * h_mean - 63.0);
    let d_theta = 30.0 * (-((h_mean - 275.0) / 25.0).powi(2)).exp();
    let cp7 = cp_mean.powi(7);
    let r_c = 2.0 * (cp7 / (cp7 + POW25_7)).sqrt();
    let l50 = (l_mean - 50.0).powi(2);
    let s_l = 1.0 + 0.015 * l50 / (20.0 + l50).sqrt();
    let s_c = 1.0 + 0.045 * cp_mean;
    let s_h = 1.0 + 0.015 * cp_mean * t;
    let r_t = -(2.0 * d_theta).to_radians().sin() * r_c;

    let (el, ec, eh) = (dl / s_l, dc / s_c, dh / s_h);
    let sum = el * el + ec * ec + eh * eh + r_t * ec * eh;
    // Rounding can take an exact 0 a hair below; NaN stays NaN.
    if sum < 0.0 {
        0.0
    } else {
        sum.sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Table 1 of Sharma, Wu & Dalal (2005): all 34 pairs and their ΔE00
    /// to 4 decimals. Pairs 7-16 cross hue 0°/360° or sit at a\* ≈ 0 (the
    /// mean-hue and hue-difference wrap-arounds), 17-24 a grey against
    /// colours, 25-34 come from the CIE's own test set.
    const SHARMA: [([f64; 3], [f64; 3], f64); 34] = [
        ([50.0, 2.6772, -79.7751], [50.0, 0.0, -82.7485], 2.0425),
        ([50.0, 3.1571, -77.2803], [50.0, 0.0, -82.7485], 2.8615),
        ([50.0, 2.8361, -74.0200], [50.0, 0.0, -82.7485], 3.4412),
        ([50.0, -1.3802, -84.2814], [50.0, 0.0, -82.7485], 1.0000),
        ([50.0, -1.1848, -84.8006], [50.0, 0.0, -82.7485], 1.0000),
        ([50.0, -0.9009, -85.5211], [50.0, 0.0, -82.7485], 1.0000),
        ([50.0, 0.0, 0.0], [50.0, -1.0, 2.0], 2.3669),
        ([50.0, -1.0, 2.0], [50.0, 0.0, 0.0], 2.3669),
        ([50.0, 2.4900, -0.0010], [50.0, -2.4900, 0.0009], 7.1792),
        ([50.0, 2.4900, -0.0010], [50.0, -2.4900, 0.0010], 7.1792),
        ([50.0, 2.4900, -0.0010], [50.0, -2.4900, 0.0011], 7.2195),
        ([50.0, 2.4900, -0.0010], [50.0, -2.4900, 0.0012], 7.2195),
        ([50.0, -0.0010, 2.4900], [50.0, 0.0009, -2.4900], 4.8045),
        ([50.0, -0.0010, 2.4900], [50.0, 0.0010, -2.4900], 4.8045),
        ([50.0, -0.0010, 2.4900], [50.0, 0.0011, -2.4900], 4.7461),
        ([50.0, 2.5000, 0.0], [50.0, 0.0, -2.5000], 4.3065),
        ([50.0, 2.5000, 0.0], [73.0, 25.0, -18.0], 27.1492),
        ([50.0, 2.5000, 0.0], [61.0, -5.0, 29.0], 22.8977),
        ([50.0, 2.5000, 0.0], [56.0, -27.0, -3.0], 31.9030),
        ([50.0, 2.5000, 0.0], [58.0, 24.0, 15.0], 19.4535),
        ([50.0, 2.5000, 0.0], [50.0, 3.1736, 0.5854], 1.0000),
        ([50.0, 2.5000, 0.0], [50.0, 3.2972, 0.0], 1.0000),
        ([50.0, 2.5000, 0.0], [50.0, 1.8634, 0.5757], 1.0000),
        ([50.0, 2.5000, 0.0], [50.0, 3.2592, 0.3350], 1.0000),
        (
            [60.2574, -34.0099, 36.2677],
            [60.4626, -34.1751, 39.4387],
            1.2644,
        ),
        (
            [63.0109, -31.0961, -5.8663],
            [62.8187, -29.7946, -4.0864],
            1.2630,
        ),
        (
            [61.2901, 3.7196, -5.3901],
            [61.4292, 2.2480, -4.9620],
            1.8731,
        ),
        (
            [35.0831, -44.1164, 3.7933],
            [35.0232, -40.0716, 1.5901],
            1.8645,
        ),
        (
            [22.7233, 20.0904, -46.6940],
            [23.0331, 14.9730, -42.5619],
            2.0373,
        ),
        (
            [36.4612, 47.8580, 18.3852],
            [36.2715, 50.5065, 21.2231],
            1.4146,
        ),
        (
            [90.8027, -2.0831, 1.4410],
            [91.1528, -1.6435, 0.0447],
            1.4441,
        ),
        (
            [90.9257, -0.5406, -0.9208],
            [88.6381, -0.8985, -0.7239],
            1.5381,
        ),
        (
            [6.7747, -0.2908, -2.4247],
            [5.8714, -0.0985, -2.2286],
            0.6377,
        ),
        (
            [2.0776, 0.0795, -1.1350],
            [0.9033, -0.0636, -0.5514],
            0.9082,
        ),
    ];

    #[test]
    fn sharma_wu_dalal_s_pairs_to_four_decimals() {
        for (i, (lab1, lab2, want)) in SHARMA.iter().enumerate() {
            for (x, y) in [(lab1, lab2), (lab2, lab1)] {
                let got = delta_e2000(*x, *y);
                assert!(
                    (got - want).abs() < 5e-5,
                    "pair {}: {x:?} {y:?} gives {got:.6}, published {want}",
                    i + 1
                );
            }
        }
    }

    #[test]
    fn equal_colours_and_neutrals_are_well_defined() {
        assert_eq!(delta_e2000([42.0, -3.0, 17.0], [42.0, -3.0, 17.0]), 0.0);
        // Both neutral: no hue, no division by zero.
        let d = delta_e2000([50.0, 0.0, 0.0], [60.0, 0.0, 0.0]);
        assert!(d.is_finite() && d > 0.0);
        assert!(delta_e2000([f64::NAN, 0.0, 0.0], [50.0, 0.0, 0.0]).is_nan());
    }
}
