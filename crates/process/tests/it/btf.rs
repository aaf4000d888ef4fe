//! BTF compression, storage and direction interpolation on analytic data.

use std::path::Path;

use proptest::prelude::*;
use rigd_process::btf::{
    compress_slot, compress_slot_by, compress_to_dir, BtfError, BtfHeader, BtfWriter,
    CompressedBtf, PcaRoute, SlotPca, TextureShape, HEADER_FILE, MAX_REPORTED_COMPONENTS,
};
use rigd_process::directions::{
    h1, h2, ring_directions, Direction, DirectionError, DirectionTable, Interpolation,
};

// ---------------------------------------------------------------- helpers

/// Deterministic pseudo-random numbers in [0, 1) (no rand dependency).
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / (1u64 << 24) as f32
    }

    fn texture(&mut self, values: usize) -> Vec<f32> {
        (0..values).map(|_| self.next()).collect()
    }
}

fn refs(images: &[Vec<f32>]) -> Vec<&[f32]> {
    images.iter().map(Vec::as_slice).collect()
}

fn rms(a: &[f32], b: &[f32]) -> f64 {
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
        .sum();
    (sum / a.len() as f64).sqrt()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// RMS over every light of the explicit reconstruction with `c` components.
fn explicit_rms(pca: &SlotPca, images: &[Vec<f32>], c: usize) -> f64 {
    let mut sum = 0.0;
    for (light, image) in images.iter().enumerate() {
        let rebuilt = pca.reconstruct_measured_truncated(light, c).unwrap();
        sum += rms(&rebuilt, image).powi(2);
    }
    (sum / images.len() as f64).sqrt()
}

fn all_finite(pca: &SlotPca) -> bool {
    pca.mean().iter().all(|v| v.is_finite())
        && (0..pca.components())
            .all(|k| pca.eigen_texture(k).unwrap().iter().all(|v| v.is_finite()))
        && (0..pca.lights()).all(|i| pca.light_weights(i).unwrap().iter().all(|v| v.is_finite()))
        && pca.singular_values().iter().all(|s| s.is_finite())
}

/// Smooth analytic BTF value: texel pattern times functions of the light and
/// view unit vectors (a few cosine lobes), positive and of order 1.
fn analytic_value(texel: usize, channel: usize, light: Direction, view: Direction) -> f32 {
    let l = light.to_vector();
    let v = view.to_vector();
    let x = texel as f64;
    let albedo = 0.5 + 0.3 * (0.7 * x + channel as f64).sin();
    let relief = 0.2 * (1.3 * x).cos();
    let half = [l[0] + v[0], l[1] + v[1], l[2] + v[2]];
    let half_norm = (half[0] * half[0] + half[1] * half[1] + half[2] * half[2]).sqrt();
    let specular = (half[2] / half_norm).powi(4);
    (albedo * l[2] + relief * l[0] * v[2] + 0.3 * specular * (1.0 + 0.5 * x.cos())) as f32
}

fn analytic_image(shape: TextureShape, light: Direction, view: Direction) -> Vec<f32> {
    let mut out = Vec::with_capacity(shape.values());
    for texel in 0..shape.texels() {
        for channel in 0..shape.channels() {
            out.push(analytic_value(texel, channel, light, view));
        }
    }
    out
}

fn analytic_slot(shape: TextureShape, lights: &DirectionTable, view: Direction) -> Vec<Vec<f32>> {
    lights
        .directions()
        .iter()
        .map(|&light| analytic_image(shape, light, view))
        .collect()
}

fn sum_of_weights(w: &Interpolation) -> f64 {
    w.entries().iter().map(|e| e.1).sum()
}

fn index_of(table: &DirectionTable, theta: f64, phi: f64) -> usize {
    table
        .directions()
        .iter()
        .position(|d| (d.theta_deg - theta).abs() < 1e-9 && (d.phi_deg - phi).abs() < 1e-9)
        .unwrap()
}

// ------------------------------------------------------ interpolation cases

#[test]
fn pole_query_is_the_same_for_every_phi_and_lands_on_the_pole_sample() {
    for table in [
        DirectionTable::new(h1()).unwrap(),
        DirectionTable::new(h2()).unwrap(),
    ] {
        let pole = index_of(&table, 0.0, 0.0);
        let reference = table.interpolate(Direction::new(0.0, 0.0)).unwrap();
        assert_eq!(reference.entries(), &[(pole, 1.0)]);
        for phi in [0.0, 37.0, 90.0, 179.9, 271.3, 359.999, -45.0, 1234.5] {
            assert_eq!(
                table.interpolate(Direction::new(0.0, phi)).unwrap(),
                reference
            );
        }
    }
}

#[test]
fn near_the_pole_the_single_pole_sample_takes_the_whole_ring_weight() {
    let table = DirectionTable::new(h2()).unwrap();
    let pole = index_of(&table, 0.0, 0.0);
    // θ = 5 is a third of the way to the 15° ring: pole weight 2/3 whatever φ.
    for phi in [0.0, 10.0, 200.0, 359.0] {
        let w = table.interpolate(Direction::new(5.0, phi)).unwrap();
        assert!((w.weight_of(pole) - 2.0 / 3.0).abs() < 1e-12, "φ = {phi}");
        assert!(w.entries().len() <= 3);
        assert!((sum_of_weights(&w) - 1.0).abs() < 1e-12);
    }
}

#[test]
fn a_pole_ring_with_many_phi_labels_is_still_phi_independent() {
    // grid12-like table with an elevation of 0: twelve labels of the pole.
    let table = DirectionTable::new(ring_directions(&[0.0, 30.0], &[12, 12])).unwrap();
    let a = table.interpolate(Direction::new(0.0, 0.0)).unwrap();
    let b = table.interpolate(Direction::new(0.0, 77.0)).unwrap();
    assert_eq!(a, b);
    assert!(a.entries().iter().all(|e| (e.1 - 1.0 / 12.0).abs() < 1e-12));
}

#[test]
fn phi_wrap_around_is_continuous() {
    let table = DirectionTable::new(h2()).unwrap();
    for theta in [15.0, 22.0, 45.0, 52.5, 75.0, 80.0] {
        let before = table.interpolate(Direction::new(theta, 359.999)).unwrap();
        let after = table.interpolate(Direction::new(theta, 0.001)).unwrap();
        let indices: Vec<usize> = before
            .entries()
            .iter()
            .chain(after.entries())
            .map(|e| e.0)
            .collect();
        for i in indices {
            let (a, b) = (before.weight_of(i), after.weight_of(i));
            assert!((a - b).abs() < 1e-3, "θ = {theta}, index {i}: {a} vs {b}");
        }
    }
    // φ = 359 on the 75° ring (Δφ = 15) lies between 345° and 0°.
    let w = table.interpolate(Direction::new(75.0, 359.0)).unwrap();
    let (at_345, at_0) = (index_of(&table, 75.0, 345.0), index_of(&table, 75.0, 0.0));
    assert!((w.weight_of(at_345) - 1.0 / 15.0).abs() < 1e-12);
    assert!((w.weight_of(at_0) - 14.0 / 15.0).abs() < 1e-12);
}

#[test]
fn grazing_queries_clamp_to_the_outermost_ring() {
    let table = DirectionTable::new(h2()).unwrap(); // outermost ring 75°, 24 samples
    for theta in [85.0, 89.9, 90.0] {
        let w = table.interpolate(Direction::new(theta, 7.5)).unwrap();
        let (at_0, at_15) = (index_of(&table, 75.0, 0.0), index_of(&table, 75.0, 15.0));
        assert_eq!(w.entries().len(), 2, "θ = {theta}");
        assert!((w.weight_of(at_0) - 0.5).abs() < 1e-12);
        assert!((w.weight_of(at_15) - 0.5).abs() < 1e-12);
    }
    let h1_table = DirectionTable::new(h1()).unwrap(); // outermost ring 85°
    let w = h1_table.interpolate(Direction::new(89.9, 30.0)).unwrap();
    assert_eq!(w.entries(), &[(index_of(&h1_table, 85.0, 30.0), 1.0)]);
}

#[test]
fn exact_hits_give_weight_one() {
    for table in [
        DirectionTable::new(h1()).unwrap(),
        DirectionTable::new(h2()).unwrap(),
    ] {
        for (index, &d) in table.directions().iter().enumerate() {
            let w = table.interpolate(d).unwrap();
            assert!((w.weight_of(index) - 1.0).abs() < 1e-9, "{d:?}: {w:?}");
        }
    }
}

#[test]
fn tables_without_ring_structure_still_interpolate() {
    let table = DirectionTable::new(vec![
        Direction::new(10.0, 40.0),
        Direction::new(33.0, 200.0),
        Direction::new(33.0, 250.0),
        Direction::new(71.0, 5.0),
    ])
    .unwrap();
    assert_eq!(table.rings().len(), 3);
    for query in [
        Direction::new(0.0, 0.0),
        Direction::new(20.0, 300.0),
        Direction::new(50.0, 100.0),
        Direction::new(89.0, 359.0),
    ] {
        let w = table.interpolate(query).unwrap();
        assert!((sum_of_weights(&w) - 1.0).abs() < 1e-12);
        assert!(w.entries().iter().all(|e| e.1 > 0.0));
    }
    // θ between the single-sample rings 10° and 33°: linear in θ.
    let w = table.interpolate(Direction::new(21.5, 225.0)).unwrap();
    assert!((w.weight_of(0) - 0.5).abs() < 1e-12);
    assert!((w.weight_of(1) - 0.25).abs() < 1e-12);
    assert!((w.weight_of(2) - 0.25).abs() < 1e-12);
}

#[test]
fn invalid_tables_and_queries_are_typed_errors() {
    assert_eq!(DirectionTable::new(Vec::new()), Err(DirectionError::Empty));
    assert!(matches!(
        DirectionTable::new(vec![Direction::new(f64::NAN, 0.0)]),
        Err(DirectionError::NonFinite { index: 0, .. })
    ));
    let table = DirectionTable::new(h1()).unwrap();
    assert!(matches!(
        table.interpolate(Direction::new(10.0, f64::NAN)),
        Err(DirectionError::NonFiniteQuery { .. })
    ));
}

/// A ring-structured table: rings at increasing θ (first above 0) with at
/// least two samples each, arbitrary φ offsets and spacings.
fn ring_table() -> impl Strategy<Value = Vec<Direction>> {
    prop::collection::vec(
        (
            1.0f64..20.0,
            prop::collection::vec(1.0f64..90.0, 2..8),
            0.0f64..360.0,
        ),
        1..6,
    )
    .prop_map(|rings| {
        let mut out = Vec::new();
        let mut theta = 0.0;
        for (step, gaps, offset) in rings {
            theta += step;
            if theta > 90.0 {
                break;
            }
            let total: f64 = gaps.iter().sum();
            let mut phi = offset;
            for gap in gaps {
                out.push(Direction::new(theta, phi % 360.0));
                // Gaps scaled to fill less than the full circle.
                phi += 340.0 * gap / total;
            }
        }
        if out.is_empty() {
            out.push(Direction::new(10.0, 0.0));
        }
        out
    })
}

proptest! {
    #[test]
    fn weights_are_finite_non_negative_and_sum_to_one(
        table in ring_table(),
        theta in -10.0f64..100.0,
        phi in -720.0f64..720.0,
    ) {
        let table = DirectionTable::new(table).unwrap();
        let w = table.interpolate(Direction::new(theta, phi)).unwrap();
        prop_assert!(!w.entries().is_empty());
        prop_assert!(w.entries().iter().all(|e| e.1.is_finite() && e.1 > 0.0 && e.0 < table.len()));
        prop_assert!((sum_of_weights(&w) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn scattered_tables_give_normalised_weights(
        dirs in prop::collection::vec((0.0f64..=90.0, 0.0f64..360.0), 1..30),
        theta in 0.0f64..=90.0,
        phi in 0.0f64..360.0,
    ) {
        let dirs: Vec<Direction> = dirs.into_iter().map(|(t, p)| Direction::new(t, p)).collect();
        // Random tables may repeat a direction; that is a typed error, not a panic.
        if let Ok(table) = DirectionTable::new(dirs) {
            let w = table.interpolate(Direction::new(theta, phi)).unwrap();
            prop_assert!(w.entries().iter().all(|e| e.1.is_finite() && e.1 > 0.0));
            prop_assert!((sum_of_weights(&w) - 1.0).abs() < 1e-12);
        }
    }

    /// f(θ, φ) = a + bθ + cφ is reproduced exactly between rings, as long as
    /// φ lies between the first and last sample of both bracketing rings.
    #[test]
    fn linear_functions_are_reproduced_away_from_the_wrap(
        dirs in ring_table(),
        a in -5.0f64..5.0,
        b in -1.0f64..1.0,
        c in -1.0f64..1.0,
        u in 0.0f64..1.0,
        v in 0.0f64..1.0,
        w in 0.0f64..1.0,
    ) {
        let table = DirectionTable::new(dirs).unwrap();
        let rings = table.rings();
        prop_assume!(rings.len() >= 2);
        let ring_index = ((u * (rings.len() - 1) as f64) as usize).min(rings.len() - 2);
        let (lo, hi) = (rings[ring_index].0, rings[ring_index + 1].0);
        let theta = lo + (hi - lo) * w;
        // φ range covered without wrapping on both rings.
        let phis_on = |ring_theta: f64| -> Vec<f64> {
            table.directions().iter()
                .filter(|d| (d.theta_deg - ring_theta).abs() < 1e-9)
                .map(|d| d.phi_deg.rem_euclid(360.0))
                .collect()
        };
        let (p_lo, p_hi) = (phis_on(lo), phis_on(hi));
        let min_of = |p: &[f64]| p.iter().copied().fold(f64::INFINITY, f64::min);
        let max_of = |p: &[f64]| p.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let start = min_of(&p_lo).max(min_of(&p_hi));
        let end = max_of(&p_lo).min(max_of(&p_hi));
        prop_assume!(end > start);
        let phi = start + (end - start) * v;
        let f = |d: Direction| a + b * d.theta_deg + c * d.phi_deg.rem_euclid(360.0);
        let weights = table.interpolate(Direction::new(theta, phi)).unwrap();
        let interpolated: f64 = weights.entries().iter().map(|&(i, wi)| wi * f(table.directions()[i])).sum();
        let expected = a + b * theta + c * phi;
        prop_assert!((interpolated - expected).abs() < 1e-9 * (1.0 + expected.abs() + 360.0),
            "θ {theta} φ {phi}: {interpolated} vs {expected}");
    }
}

// ------------------------------------------------------------ compression

#[test]
fn rank_two_btf_is_exact_with_two_components_and_not_with_one() {
    let shape = TextureShape::new(16, 12, 3).unwrap();
    let lights = DirectionTable::new(h2()).unwrap();
    let mut rng = Lcg(7);
    let a = rng.texture(shape.values());
    let b = rng.texture(shape.values());
    // texel = A(x)·f(light) + B(x)·g(light), f and g affinely independent.
    let images: Vec<Vec<f32>> = lights
        .directions()
        .iter()
        .map(|d| {
            let l = d.to_vector();
            let (f, g) = (l[2], 0.5 * l[0] + 0.2 * l[1] * l[1]);
            a.iter()
                .zip(&b)
                .map(|(&ax, &bx)| ax * f as f32 + bx * g as f32)
                .collect()
        })
        .collect();
    for requested in [1, 2, 16] {
        let pca = compress_slot(&refs(&images), shape, requested).unwrap();
        let explicit = explicit_rms(&pca, &images, requested);
        let scale = rms(&images[0], &vec![0.0; shape.values()]);
        if requested == 1 {
            assert!(explicit > 1e-2 * scale, "C = 1 should not fit: {explicit}");
            assert!(pca.rms_error(1) > 1e-2 * scale);
        } else {
            assert!(explicit < 1e-5 * scale, "C = {requested}: {explicit}");
            assert!(pca.rms_error(2) < 1e-6 * scale);
        }
    }
}

#[test]
fn rms_from_singular_values_matches_explicit_reconstruction() {
    let shape = TextureShape::new(12, 10, 3).unwrap();
    let lights = DirectionTable::new(h1()).unwrap();
    let view = Direction::new(30.0, 60.0);
    // Smooth part plus noise: a spread-out spectrum.
    let mut rng = Lcg(99);
    let images: Vec<Vec<f32>> = analytic_slot(shape, &lights, view)
        .into_iter()
        .map(|img| img.into_iter().map(|v| v + 0.05 * rng.next()).collect())
        .collect();
    let pca = compress_slot(&refs(&images), shape, 24).unwrap();
    assert_eq!(pca.components(), 24);
    let curve = pca.rms_error_curve(MAX_REPORTED_COMPONENTS);
    assert_eq!(curve.len(), 32);
    assert!(curve.windows(2).all(|w| w[1] <= w[0]));
    for c in [0, 1, 2, 3, 5, 8, 16, 24] {
        let explicit = explicit_rms(&pca, &images, c);
        let predicted = pca.rms_error(c);
        assert!(
            (explicit - predicted).abs() <= 1e-4 * predicted + 1e-6,
            "C = {c}: explicit {explicit}, from σ {predicted}"
        );
    }
    let eigenvalues = pca.eigenvalues();
    assert_eq!(eigenvalues.len(), 81);
    assert!(eigenvalues.windows(2).all(|w| w[1] <= w[0]));
}

#[test]
fn eigen_textures_are_orthonormal_and_weights_are_projections() {
    let shape = TextureShape::new(8, 8, 1).unwrap();
    let lights = DirectionTable::new(h2()).unwrap();
    let images = analytic_slot(shape, &lights, Direction::new(45.0, 100.0));
    // Three texel patterns (albedo, relief, specular modulation): rank 3.
    let pca = compress_slot(&refs(&images), shape, 4).unwrap();
    assert!(pca.eigen_texture(3).unwrap().iter().all(|&v| v == 0.0));
    for j in 0..3 {
        for k in 0..3 {
            let dot: f64 = pca
                .eigen_texture(j)
                .unwrap()
                .iter()
                .zip(pca.eigen_texture(k).unwrap())
                .map(|(x, y)| f64::from(*x) * f64::from(*y))
                .sum();
            let expected = if j == k { 1.0 } else { 0.0 };
            assert!((dot - expected).abs() < 1e-5, "⟨B{j}, B{k}⟩ = {dot}");
        }
    }
    let light = 40;
    let centred: Vec<f64> = images[light]
        .iter()
        .zip(pca.mean())
        .map(|(x, m)| f64::from(*x) - f64::from(*m))
        .collect();
    for k in 0..3 {
        let projection: f64 = centred
            .iter()
            .zip(pca.eigen_texture(k).unwrap())
            .map(|(x, b)| x * f64::from(*b))
            .sum();
        let stored = f64::from(pca.light_weights(light).unwrap()[k]);
        assert!((projection - stored).abs() < 1e-4 * (1.0 + stored.abs()));
    }
}

#[test]
fn rank_deficient_slots_are_finite_and_clamped() {
    let shape = TextureShape::new(5, 4, 3).unwrap();
    // Constant images: the centred matrix is zero.
    let constant = vec![vec![0.5f32; shape.values()]; 9];
    let pca = compress_slot(&refs(&constant), shape, 16).unwrap();
    assert_eq!(pca.components(), 9);
    assert!(all_finite(&pca));
    assert!(pca.singular_values().iter().all(|&s| s == 0.0));
    assert_eq!(pca.reconstruct_measured(3).unwrap(), constant[3]);
    assert_eq!(pca.rms_error_curve(32), vec![0.0; 9]);

    // Identical non-constant images.
    let mut rng = Lcg(3);
    let image = rng.texture(shape.values());
    let same = vec![image.clone(); 6];
    let pca = compress_slot(&refs(&same), shape, 16).unwrap();
    assert!(all_finite(&pca));
    assert!(max_abs_diff(&pca.reconstruct_measured(5).unwrap(), &image) < 1e-6);

    // A single light.
    let pca = compress_slot(&[image.as_slice()], shape, 16).unwrap();
    assert_eq!(pca.components(), 1);
    assert!(all_finite(&pca));
    assert!(max_abs_diff(&pca.reconstruct_measured(0).unwrap(), &image) < 1e-6);

    // Rank 1 after centring with C larger than the rank: extra components zero.
    let scaled: Vec<Vec<f32>> = (0..5)
        .map(|i| image.iter().map(|v| v * (1.0 + i as f32)).collect())
        .collect();
    let pca = compress_slot(&refs(&scaled), shape, 16).unwrap();
    assert_eq!(pca.components(), 5);
    assert!(all_finite(&pca));
    for k in 1..5 {
        assert!(pca.eigen_texture(k).unwrap().iter().all(|&v| v == 0.0));
    }
    assert!(explicit_rms(&pca, &scaled, 1) < 1e-5);

    // Fewer values than lights: C clamps to the texture size.
    let tiny = TextureShape::new(1, 1, 1).unwrap();
    let pixels: Vec<Vec<f32>> = (0..7).map(|i| vec![i as f32]).collect();
    let pca = compress_slot(&refs(&pixels), tiny, 16).unwrap();
    assert_eq!(pca.components(), 1);
    assert!(all_finite(&pca));
    assert!(explicit_rms(&pca, &pixels, 1) < 1e-5);
}

#[test]
fn the_gram_route_agrees_with_the_thin_svd() {
    // A realistic tall slot (values ≫ lights): a smooth BTF plus 8-bit-sized
    // noise, so the spectrum decays over the whole range the report covers.
    let shape = TextureShape::new(24, 20, 1).unwrap();
    let lights = DirectionTable::new(h1()).unwrap();
    assert_eq!(
        PcaRoute::for_shape(shape.values(), lights.len()),
        PcaRoute::Gram
    );
    assert_eq!(PcaRoute::for_shape(100, 81), PcaRoute::ThinSvd);
    let mut rng = Lcg(11);
    let images: Vec<Vec<f32>> = analytic_slot(shape, &lights, Direction::new(40.0, 300.0))
        .into_iter()
        .map(|img| img.into_iter().map(|v| v + 0.004 * rng.next()).collect())
        .collect();
    let gram = compress_slot_by(PcaRoute::Gram, &refs(&images), shape, 16).unwrap();
    let svd = compress_slot_by(PcaRoute::ThinSvd, &refs(&images), shape, 16).unwrap();
    let (lg, ls) = (gram.eigenvalues(), svd.eigenvalues());
    assert_eq!(lg.len(), ls.len());
    for k in 0..16 {
        let relative = (lg[k] - ls[k]).abs() / ls[k];
        assert!(
            relative < 1e-9,
            "λ{k}: Gram {} against SVD {}",
            lg[k],
            ls[k]
        );
    }
    let (cg, cs) = (gram.rms_error_curve(32), svd.rms_error_curve(32));
    for (c, (g, s)) in cg.iter().zip(&cs).enumerate() {
        assert!(
            (g - s).abs() <= 1e-6 * s + 1e-9,
            "C = {}: {g} against {s}",
            c + 1
        );
    }
    for light in 0..lights.len() {
        let (a, b) = (
            gram.reconstruct_measured(light).unwrap(),
            svd.reconstruct_measured(light).unwrap(),
        );
        assert!(max_abs_diff(&a, &b) < 1e-5, "light {light}");
    }
    // The Gram route's reconstruction error is what its singular values say.
    for c in [1, 4, 16] {
        let explicit = explicit_rms(&gram, &images, c);
        assert!((explicit - gram.rms_error(c)).abs() <= 1e-4 * explicit + 1e-7);
    }
}

#[test]
fn the_viewer_reference_render_is_the_same_by_either_route() {
    use rigd_process::mesh::{Mesh, MeshKind};
    use rigd_process::relight::{relight, RelightSettings};
    let shape = TextureShape::new(8, 8, 3).unwrap();
    let lights = DirectionTable::new(h1()).unwrap();
    let views = DirectionTable::new(h1()).unwrap();
    let store_by = |route: PcaRoute| {
        let mut rng = Lcg(21);
        let slots = views
            .directions()
            .iter()
            .map(|&view| {
                let images: Vec<Vec<f32>> = analytic_slot(shape, &lights, view)
                    .into_iter()
                    .map(|img| img.into_iter().map(|v| v + 0.004 * rng.next()).collect())
                    .collect();
                compress_slot_by(route, &refs(&images), shape, 8).unwrap()
            })
            .collect();
        CompressedBtf::new(shape, lights.clone(), views.clone(), slots).unwrap()
    };
    let (gram, svd) = (store_by(PcaRoute::Gram), store_by(PcaRoute::ThinSvd));
    for (kind, light, view) in [
        (
            MeshKind::Flat,
            Direction::new(40.0, 30.0),
            Direction::new(35.0, 270.0),
        ),
        (
            MeshKind::Cylinder,
            Direction::new(85.0, 100.0),
            Direction::new(40.0, 250.0),
        ),
        (
            MeshKind::Cloth,
            Direction::new(45.0, 359.9),
            Direction::new(0.0, 123.0),
        ),
    ] {
        let mesh = Mesh::build(kind, 1.0);
        let settings = RelightSettings {
            width: 96,
            height: 96,
            light,
            view,
            ..RelightSettings::default()
        };
        let (a, b) = (
            relight(&gram, &mesh, &settings).unwrap(),
            relight(&svd, &mesh, &settings).unwrap(),
        );
        assert_eq!(a.covered, b.covered);
        let largest = a
            .pixels
            .iter()
            .zip(&b.pixels)
            .map(|(x, y)| x.abs_diff(*y))
            .max()
            .unwrap_or(0);
        // Reconstructions agree to 1e-5, so an 8-bit pixel moves at most by
        // one level where the value sits on a rounding boundary.
        assert!(largest <= 1, "{kind:?}: pixels differ by {largest} levels");
    }
}

#[test]
fn both_routes_handle_rank_deficient_slots() {
    let shape = TextureShape::new(8, 8, 1).unwrap();
    let mut rng = Lcg(5);
    let image = rng.texture(shape.values());
    let constant = vec![vec![0.25f32; shape.values()]; 7];
    let scaled: Vec<Vec<f32>> = (0..7)
        .map(|i| image.iter().map(|v| v * (1.0 + i as f32)).collect())
        .collect();
    for route in [PcaRoute::Gram, PcaRoute::ThinSvd] {
        let pca = compress_slot_by(route, &refs(&constant), shape, 4).unwrap();
        assert!(all_finite(&pca), "{route:?}");
        assert!(pca.singular_values().iter().all(|&s| s == 0.0), "{route:?}");
        assert_eq!(pca.reconstruct_measured(2).unwrap(), constant[2]);

        let pca = compress_slot_by(route, &refs(&scaled), shape, 4).unwrap();
        assert!(all_finite(&pca), "{route:?}");
        for k in 1..4 {
            let zero = pca.eigen_texture(k).unwrap().iter().all(|&v| v == 0.0);
            assert!(zero, "{route:?}: component {k} of a rank-1 slot");
        }
        assert!(explicit_rms(&pca, &scaled, 1) < 1e-5, "{route:?}");
    }
}

#[test]
fn bad_slot_input_is_a_typed_error() {
    let shape = TextureShape::new(2, 2, 3).unwrap();
    let good = vec![0.0f32; 12];
    let mut bad = good.clone();
    bad[7] = f32::NAN;
    assert!(matches!(
        compress_slot(&[&good, &bad], shape, 2),
        Err(BtfError::NonFiniteValue {
            image: 1,
            value_index: 7
        })
    ));
    assert!(matches!(
        compress_slot(&[&good, &good[..11]], shape, 2),
        Err(BtfError::ImageSize {
            image: 1,
            expected: 12,
            actual: 11
        })
    ));
    assert!(matches!(
        compress_slot(&[], shape, 2),
        Err(BtfError::NoImages)
    ));
    assert!(matches!(
        compress_slot(&[&good], shape, 0),
        Err(BtfError::NoComponents)
    ));
    assert!(matches!(
        TextureShape::new(2, 2, 4),
        Err(BtfError::Shape { .. })
    ));
}

fn small_analytic_store(shape: TextureShape, components: usize) -> (CompressedBtf, DirectionTable) {
    let lights = DirectionTable::new(h2()).unwrap();
    let views =
        DirectionTable::new(ring_directions(&[0.0, 20.0, 40.0, 60.0], &[1, 6, 8, 10])).unwrap();
    let store = CompressedBtf::compress(shape, lights.clone(), views.clone(), components, |slot| {
        Ok(analytic_slot(shape, &lights, views.directions()[slot]))
    })
    .unwrap();
    (store, views)
}

#[test]
fn measured_directions_reconstruct_their_stored_texture() {
    let shape = TextureShape::new(6, 5, 3).unwrap();
    let (store, views) = small_analytic_store(shape, 16);
    for (slot, light) in [(0, 0), (3, 17), (24, 80)] {
        let view = views.directions()[slot];
        let light_dir = store.lights().directions()[light];
        let via_directions = store.reconstruct(light_dir, view).unwrap();
        let measured = store.reconstruct_measured(slot, light).unwrap();
        assert!(max_abs_diff(&via_directions, &measured) < 1e-5);
        let original = analytic_image(shape, light_dir, view);
        assert!(max_abs_diff(&measured, &original) < 1e-3);
    }
}

#[test]
fn held_out_directions_interpolate_with_bounded_error() {
    let shape = TextureShape::new(6, 5, 3).unwrap();
    let (store, _) = small_analytic_store(shape, 16);
    let held_out = [
        (Direction::new(22.5, 37.0), Direction::new(10.0, 0.0)),
        (Direction::new(52.0, 200.0), Direction::new(30.0, 100.0)),
        (Direction::new(38.0, 359.0), Direction::new(50.0, 355.0)),
        (Direction::new(7.0, 123.0), Direction::new(45.0, 222.0)),
        (Direction::new(67.0, 181.0), Direction::new(5.0, 300.0)),
    ];
    let mut worst_interpolated = 0.0f32;
    let mut worst_nearest = 0.0f32;
    for (light, view) in held_out {
        let truth = analytic_image(shape, light, view);
        let interpolated = store.reconstruct(light, view).unwrap();
        let error = max_abs_diff(&interpolated, &truth);
        assert!(
            error < 0.05,
            "light {light:?} view {view:?}: max error {error}"
        );
        worst_interpolated = worst_interpolated.max(error);
        // The nearest measured pair, for comparison: interpolation must help.
        let slot = store.views().nearest(view).unwrap();
        let index = store.lights().nearest(light).unwrap();
        let nearest = store.reconstruct_measured(slot, index).unwrap();
        worst_nearest = worst_nearest.max(max_abs_diff(&nearest, &truth));
    }
    assert!(
        worst_interpolated < 0.5 * worst_nearest,
        "interpolated {worst_interpolated} vs nearest {worst_nearest}"
    );
}

#[test]
fn error_report_covers_every_slot_up_to_32_components() {
    let shape = TextureShape::new(6, 5, 3).unwrap();
    let (store, views) = small_analytic_store(shape, 16);
    let report = store.error_report(MAX_REPORTED_COMPONENTS);
    assert_eq!(report.len(), views.len());
    for entry in &report {
        assert_eq!(entry.rms_by_components.len(), 32);
        assert_eq!(entry.eigenvalues.len(), 81);
        assert!(entry.rms_mean_only >= entry.rms_by_components[0]);
        assert!(entry.rms_by_components.windows(2).all(|w| w[1] <= w[0]));
    }
}

// ---------------------------------------------------------------- storage

fn assert_same_store(a: &CompressedBtf, b: &CompressedBtf) {
    assert_eq!(a.shape(), b.shape());
    assert_eq!(a.components(), b.components());
    for (x, y) in [(a.lights(), b.lights()), (a.views(), b.views())] {
        assert_eq!(x.len(), y.len());
        for (p, q) in x.directions().iter().zip(y.directions()) {
            assert!((p.theta_deg - q.theta_deg).abs() < 1e-12);
            assert!((p.phi_deg - q.phi_deg).abs() < 1e-12);
        }
    }
    for (p, q) in a.slots().iter().zip(b.slots()) {
        assert_eq!(p.mean(), q.mean());
        for k in 0..p.components() {
            assert_eq!(p.eigen_texture(k), q.eigen_texture(k));
        }
        for i in 0..p.lights() {
            assert_eq!(p.light_weights(i), q.light_weights(i));
        }
        assert_eq!(p.singular_values().len(), q.singular_values().len());
        for (s, t) in p.singular_values().iter().zip(q.singular_values()) {
            assert!((s - t).abs() <= 1e-15 * s.abs().max(1.0));
        }
    }
}

fn file_names(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

#[test]
fn store_round_trips_and_leaves_no_temporary_files() {
    let shape = TextureShape::new(4, 3, 3).unwrap();
    let (store, _) = small_analytic_store(shape, 5);
    let dir = tempfile::tempdir().unwrap();
    let target = dir.path().join("btf");
    store.write(&target).unwrap();
    let names = file_names(&target);
    assert_eq!(names.len(), store.slots().len() + 1);
    assert!(names.contains(&HEADER_FILE.to_string()));
    assert!(names.contains(&"slot_024.bin".to_string()));
    let back = CompressedBtf::read(&target).unwrap();
    assert_same_store(&store, &back);
    // Byte size as documented: 4 · (values · (1 + C) + lights · C).
    let size = std::fs::metadata(target.join("slot_000.bin"))
        .unwrap()
        .len();
    assert_eq!(size, 4 * (36 * 6 + 81 * 5));
}

#[test]
fn streamed_compression_matches_the_in_memory_store() {
    let shape = TextureShape::new(4, 3, 1).unwrap();
    let (store, views) = small_analytic_store(shape, 3);
    let dir = tempfile::tempdir().unwrap();
    compress_to_dir(dir.path(), shape, store.lights(), &views, 3, |slot| {
        Ok(analytic_slot(
            shape,
            store.lights(),
            views.directions()[slot],
        ))
    })
    .unwrap();
    assert_same_store(&store, &CompressedBtf::read(dir.path()).unwrap());
}

#[test]
fn read_errors_name_the_file() {
    let shape = TextureShape::new(3, 2, 1).unwrap();
    let (store, _) = small_analytic_store(shape, 2);
    let dir = tempfile::tempdir().unwrap();

    match CompressedBtf::read(dir.path()) {
        Err(BtfError::Io { path, .. }) => assert!(path.ends_with(HEADER_FILE)),
        other => panic!("missing header: {other:?}"),
    }

    store.write(dir.path()).unwrap();
    let slot_path = dir.path().join("slot_002.bin");
    let bytes = std::fs::read(&slot_path).unwrap();
    std::fs::write(&slot_path, &bytes[..bytes.len() - 4]).unwrap();
    match CompressedBtf::read(dir.path()) {
        Err(e @ BtfError::Format { .. }) => assert!(e.to_string().contains("slot_002.bin"), "{e}"),
        other => panic!("truncated slot: {other:?}"),
    }
    let mut nan = bytes.clone();
    nan[0..4].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&slot_path, &nan).unwrap();
    assert!(matches!(
        CompressedBtf::read(dir.path()),
        Err(BtfError::Format { .. })
    ));
    std::fs::write(&slot_path, &bytes).unwrap();
    assert!(CompressedBtf::read(dir.path()).is_ok());

    let header_path = dir.path().join(HEADER_FILE);
    let mut header: BtfHeader =
        serde_json::from_str(&std::fs::read_to_string(&header_path).unwrap()).unwrap();
    header.slots[1].file = "../escape.bin".into();
    std::fs::write(&header_path, serde_json::to_string(&header).unwrap()).unwrap();
    match CompressedBtf::read(dir.path()) {
        Err(e @ BtfError::Format { .. }) => assert!(e.to_string().contains(HEADER_FILE), "{e}"),
        other => panic!("escaping file name: {other:?}"),
    }
    std::fs::write(&header_path, "{ not json").unwrap();
    assert!(matches!(
        CompressedBtf::read(dir.path()),
        Err(BtfError::Format { .. })
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(12))]
    #[test]
    fn random_stores_round_trip(
        width in 1usize..4,
        height in 1usize..4,
        rgb in any::<bool>(),
        light_count in 1usize..9,
        view_count in 1usize..4,
        components in 1usize..6,
        seed in any::<u64>(),
    ) {
        let shape = TextureShape::new(width, height, if rgb { 3 } else { 1 }).unwrap();
        let lights = DirectionTable::new(ring_directions(&[40.0], &[light_count])).unwrap();
        let views = DirectionTable::new(ring_directions(&[0.0, 50.0], &[1, view_count])).unwrap();
        let store = CompressedBtf::compress(shape, lights.clone(), views.clone(), components, |slot| {
            let mut rng = Lcg(seed ^ (slot as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            Ok((0..light_count).map(|_| rng.texture(shape.values())).collect())
        }).unwrap();
        let dir = tempfile::tempdir().unwrap();
        store.write(dir.path()).unwrap();
        let back = CompressedBtf::read(dir.path()).unwrap();
        assert_same_store(&store, &back);
        prop_assert_eq!(back.components(), components.min(light_count).min(shape.values()));
    }
}

#[test]
fn view_at_the_pole_reconstructs_the_same_texture_for_any_phi() {
    let shape = TextureShape::new(4, 3, 3).unwrap();
    let (store, _) = small_analytic_store(shape, 8);
    let light = Direction::new(33.0, 71.0);
    let reference = store.reconstruct(light, Direction::new(0.0, 0.0)).unwrap();
    for phi in [45.0, 180.0, 359.9] {
        let other = store.reconstruct(light, Direction::new(0.0, phi)).unwrap();
        assert_eq!(other, reference);
    }
    assert!(matches!(
        store.reconstruct(light, Direction::new(f64::NAN, 0.0)),
        Err(BtfError::Direction(DirectionError::NonFiniteQuery { .. }))
    ));
}

#[test]
fn mismatched_slots_and_unfinished_writers_are_errors() {
    let shape = TextureShape::new(2, 2, 1).unwrap();
    let lights = DirectionTable::new(h2()).unwrap();
    let views = DirectionTable::new(ring_directions(&[0.0, 30.0], &[1, 2])).unwrap();
    let short = CompressedBtf::compress(shape, lights.clone(), views.clone(), 2, |_| {
        Ok(vec![vec![0.0; 4]; 80])
    });
    assert!(matches!(short, Err(BtfError::SlotMismatch { .. })));

    let dir = tempfile::tempdir().unwrap();
    let mut writer = BtfWriter::create(dir.path(), shape, &lights, &views, 2).unwrap();
    let images = vec![vec![1.0f32; 4]; 81];
    let pca = compress_slot(&refs(&images), shape, 2).unwrap();
    writer.write_slot(0, &pca).unwrap();
    assert!(matches!(
        writer.write_slot(3, &pca),
        Err(BtfError::SlotIndex { slot: 3, .. })
    ));
    assert!(matches!(
        writer.finish(),
        Err(BtfError::SlotMismatch { slot: 1, .. })
    ));
    assert!(!dir.path().join(HEADER_FILE).exists());
}
