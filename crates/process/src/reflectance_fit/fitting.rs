//! Fitting.

use super::*;

#[derive(Debug, Clone, Copy)]
pub(super) struct Bounds {
    pub(super) max_amplitude: f64,
    pub(super) max_exponent: f64,
}

pub(super) struct TexelPlan {
    pub(super) lobes: Vec<Lobe>,
    /// LM iterations spent refining the first lobes during initialisation.
    pub(super) iterations: usize,
    pub(super) fallback: Option<Fallback>,
    pub(super) bounds: Bounds,
}

/// Fallbacks and principal-direction initialisation for one texel.
pub(super) fn plan_texel(
    lights: &[[f64; 3]],
    values: &[f64],
    k: usize,
    opts: &FitOptions,
) -> TexelPlan {
    let peak = values.iter().fold(0.0f64, |acc, &v| acc.max(v));
    let bounds = Bounds {
        max_amplitude: (opts.max_amplitude_ratio * peak).min(MAX_AMPLITUDE),
        max_exponent: opts.max_exponent,
    };
    if peak <= 0.0 {
        return TexelPlan {
            lobes: Vec::new(),
            iterations: 0,
            fallback: Some(Fallback::Dark),
            bounds,
        };
    }
    let active = k.min(lights.len() / PARAMS_PER_LOBE);
    if active == 0 {
        let mut lobes = vec![Lobe::zero()];
        fit_amplitudes(lights, values, &mut lobes, &bounds);
        return TexelPlan {
            lobes,
            iterations: 0,
            fallback: Some(Fallback::DiffuseOnly),
            bounds,
        };
    }
    let (lobes, iterations) = principal_direction_lobes(lights, values, active, &bounds, opts);
    TexelPlan {
        lobes,
        iterations,
        fallback: (active < k).then_some(Fallback::ReducedLobes { active }),
        bounds,
    }
}

/// Lights within this angle of a residual peak take part in estimating
/// the peak's lobe (wide enough to reach the next ring of a 15° sampling).
pub(super) const NEIGHBOUR_COS: f64 = 0.906; // cos 25°

/// Initial lobes from principal directions (Meseth et al., §4.2: "detecting
/// principal directions with a high-pass filter").
///
/// Lobe 1 is the low-pass part: its axis is the value-weighted mean light
/// direction (first moment of the reflected energy; unlike the dominant
/// eigenvector of the second moment it has no sign ambiguity) and its
/// exponent comes from the weighted mean cosine, `E[cos] = (n+1)/(n+2)` for
/// a `cos^n` lobe under lights spread evenly over the hemisphere. The lobes
/// so far are then refined by LM, and the next lobe sits at the peak of the
/// high-pass residual (data minus those lobes): its axis is the peak light
/// or the residual-weighted mean of the peak's neighbours, its exponent the
/// neighbours' falloff or one of a ladder, whichever fits best with
/// non-negative least-squares amplitudes. Returns the lobes and the LM
/// iterations spent.
pub(super) fn principal_direction_lobes(
    lights: &[[f64; 3]],
    values: &[f64],
    count: usize,
    bounds: &Bounds,
    opts: &FitOptions,
) -> (Vec<Lobe>, usize) {
    let broad_limit = bounds.max_exponent.min(1.0e3);
    let mut total = 0.0;
    let mut moment = [0.0; 3];
    for (light, &v) in lights.iter().zip(values) {
        let w = v.max(0.0);
        total += w;
        moment = add_scaled(moment, *light, w);
    }
    let axis = normalized(moment).unwrap_or([0.0, 0.0, 1.0]);
    let mean_cos = lights
        .iter()
        .zip(values)
        .map(|(l, &v)| v.max(0.0) * dot(axis, *l).max(0.0))
        .sum::<f64>()
        / total;
    let exponent = clamp_exponent((2.0 * mean_cos - 1.0) / (1.0 - mean_cos), broad_limit);
    let mut lobes = vec![Lobe {
        axis,
        amplitude: 0.0,
        exponent,
    }];
    fit_amplitudes(lights, values, &mut lobes, bounds);

    // Each stage's lobes are fitted before the next peak is sought, so the
    // high-pass residual is measured against the best low-pass model, not
    // against the moment estimate (whose misfit at grazing lights would
    // otherwise outshine a specular peak).
    let stage_opts = FitOptions {
        max_iterations: opts.max_iterations / 2,
        ..*opts
    };
    let mut iterations = 0;
    while lobes.len() < count {
        iterations += levenberg_marquardt(lights, values, &mut lobes, bounds, &stage_opts).0;
        let residual: Vec<f64> = lights
            .iter()
            .zip(values)
            .map(|(l, v)| v - lobes.iter().map(|lobe| lobe.evaluate(*l)).sum::<f64>())
            .collect();
        let (peak_index, peak) =
            residual
                .iter()
                .copied()
                .enumerate()
                .fold((0, f64::NEG_INFINITY), |best, (i, r)| {
                    if r > best.1 {
                        (i, r)
                    } else {
                        best
                    }
                });
        let scale = values.iter().fold(0.0f64, |acc, v| acc.max(v.abs()));
        if peak <= 1e-9 * scale {
            // Nothing left to explain: an idle lobe LM may still pick up.
            lobes.push(Lobe {
                axis: lobes[0].axis,
                amplitude: 0.0,
                exponent: MIN_EXPONENT,
            });
            continue;
        }
        let peak_light = lights[peak_index];
        let mut weighted = [0.0; 3];
        for (light, &r) in lights.iter().zip(&residual) {
            if r > 0.0 && dot(*light, peak_light) >= NEIGHBOUR_COS {
                weighted = add_scaled(weighted, *light, r);
            }
        }
        let axis = normalized(weighted).unwrap_or(peak_light);
        // Geometric mean of the exponents implied by each neighbour's
        // falloff r_j / r_peak = cos(angle)^n.
        let mut log_sum = 0.0;
        let mut count_estimates = 0usize;
        let mut nearest_cos = -1.0f64;
        for (j, (light, &r)) in lights.iter().zip(&residual).enumerate() {
            let c = dot(*light, peak_light);
            if j == peak_index || c >= 1.0 - 1e-12 {
                continue;
            }
            nearest_cos = nearest_cos.max(c);
            if c >= NEIGHBOUR_COS && r > 0.0 && r < peak {
                let n = (r / peak).ln() / c.ln();
                if n.is_finite() && n > 0.0 {
                    log_sum += n.ln();
                    count_estimates += 1;
                }
            }
        }
        // Sharper than a lobe that is down to 1 % at the nearest light, a
        // lobe sees one light only; LM cannot widen it again (its gradient
        // in n vanishes), so the start is never sharper than that.
        let sharpest = if nearest_cos > 0.0 {
            100f64.ln() / -nearest_cos.ln()
        } else {
            MIN_EXPONENT
        };
        let mut exponents = vec![sharpest];
        if count_estimates > 0 {
            exponents.push((log_sum / count_estimates as f64).exp().min(sharpest));
        }
        // The falloff estimate is fooled when the low-pass misfit around the
        // peak is as large as the peak itself: also try a fixed ladder and
        // keep whichever (axis, exponent) fits best after the amplitudes.
        exponents.extend(EXPONENT_LADDER.iter().filter(|&&n| n < sharpest));
        let mut best: Option<(f64, Vec<Lobe>)> = None;
        for candidate_axis in [axis, peak_light] {
            for &exponent in &exponents {
                let mut candidate = lobes.clone();
                candidate.push(Lobe {
                    axis: candidate_axis,
                    amplitude: 0.0,
                    exponent: clamp_exponent(exponent, bounds.max_exponent),
                });
                fit_amplitudes(lights, values, &mut candidate, bounds);
                let cost = cost_of(lights, values, &candidate);
                if best.as_ref().is_none_or(|(best_cost, _)| cost < *best_cost) {
                    best = Some((cost, candidate));
                }
            }
        }
        if let Some((_, candidate)) = best {
            lobes = candidate;
        }
    }
    (lobes, iterations)
}

/// Exponents tried for each new lobe of the initialisation.
pub(super) const EXPONENT_LADDER: [f64; 6] = [2.0, 5.0, 10.0, 20.0, 50.0, 100.0];

/// Non-negative least squares for the amplitudes with axes and exponents
/// fixed, by cyclic coordinate descent (a convex problem of ≤ MAX_LOBES
/// unknowns).
pub(super) fn fit_amplitudes(
    lights: &[[f64; 3]],
    values: &[f64],
    lobes: &mut [Lobe],
    bounds: &Bounds,
) {
    let k = lobes.len();
    let shapes: Vec<Vec<f64>> = lobes
        .iter()
        .map(|lobe| {
            lights
                .iter()
                .map(|l| power(dot(lobe.axis, *l), lobe.exponent))
                .collect()
        })
        .collect();
    let mut gram = vec![0.0; k * k];
    let mut rhs = vec![0.0; k];
    for i in 0..k {
        rhs[i] = shapes[i].iter().zip(values).map(|(s, v)| s * v).sum();
        for j in 0..k {
            gram[i * k + j] = shapes[i].iter().zip(&shapes[j]).map(|(a, b)| a * b).sum();
        }
    }
    for lobe in lobes.iter_mut() {
        lobe.amplitude = 0.0;
    }
    for _ in 0..100 {
        let mut change = 0.0f64;
        for i in 0..k {
            if gram[i * k + i] <= 0.0 {
                continue;
            }
            let others: f64 = (0..k)
                .filter(|&j| j != i)
                .map(|j| gram[i * k + j] * lobes[j].amplitude)
                .sum();
            let updated = ((rhs[i] - others) / gram[i * k + i]).clamp(0.0, bounds.max_amplitude);
            if updated.is_finite() {
                change = change.max((updated - lobes[i].amplitude).abs());
                lobes[i].amplitude = updated;
            }
        }
        if change <= 1e-14 * bounds.max_amplitude {
            break;
        }
    }
}

pub(super) fn fit_checked(
    lights: &[[f64; 3]],
    values: &[f32],
    k: usize,
    opts: &FitOptions,
) -> TexelFit {
    let values: Vec<f64> = values.iter().map(|&v| f64::from(v)).collect();
    let plan = plan_texel(lights, &values, k, opts);
    let mut lobes = plan.lobes;
    let initial_rms_error = errors64(lights, &values, &lobes).0;
    let (iterations, converged) = match plan.fallback {
        Some(Fallback::Dark) | Some(Fallback::DiffuseOnly) => (0, true),
        _ => levenberg_marquardt(lights, &values, &mut lobes, &plan.bounds, opts),
    };
    let iterations = iterations + plan.iterations;
    let (rms_error, mean_abs_error) = errors64(lights, &values, &lobes);
    let active_lobes = lobes.len();
    TexelFit {
        model: LobeModel {
            lobes: padded(lobes, k),
        },
        rms_error,
        mean_abs_error,
        initial_rms_error,
        iterations,
        converged,
        active_lobes,
        fallback: plan.fallback,
    }
}

/// Minimises `½ Σ (model − value)²` over all lobe parameters. Damping
/// follows Marquardt (scaled by diag JᵀJ) with Nielsen's update; only
/// steps that lower the cost are taken, so the result is never worse than
/// the start. Axes move on the sphere: each step is expressed in the
/// tangent basis of the current axis, which is re-centred after every
/// accepted step, so the poles need no special case.
pub(super) fn levenberg_marquardt(
    lights: &[[f64; 3]],
    values: &[f64],
    lobes: &mut Vec<Lobe>,
    bounds: &Bounds,
    opts: &FitOptions,
) -> (usize, bool) {
    let m = lights.len();
    let p = lobes.len() * PARAMS_PER_LOBE;
    let scale = values.iter().fold(0.0f64, |acc, v| acc.max(v.abs()));
    // The values are f32 (relative precision 6e-8): once the RMS residual is
    // a few f32 ulps of the largest value, further steps only fit rounding.
    let cost_floor = 0.5 * m as f64 * (4.0 * f64::from(f32::EPSILON) * scale).powi(2);
    let mut jac = vec![0.0; m * p];
    let mut residual = vec![0.0; m];
    let mut normal = vec![0.0; p * p];
    let mut gradient = vec![0.0; p];
    let mut system = vec![0.0; p * p];
    let mut step = vec![0.0; p];

    let mut cost = linearise(lights, values, lobes, &mut jac, &mut residual);
    normal_equations(&jac, &residual, p, &mut normal, &mut gradient);
    let max_diag = (0..p).map(|i| normal[i * p + i]).fold(0.0f64, f64::max);
    let mut damping = opts.initial_damping * if max_diag > 0.0 { max_diag } else { 1.0 };
    let mut growth = 2.0;

    for iteration in 1..=opts.max_iterations {
        if cost <= cost_floor {
            return (iteration - 1, true);
        }
        let max_diag = (0..p).map(|i| normal[i * p + i]).fold(0.0f64, f64::max);
        let diag_floor = 1e-12 * max_diag + f64::MIN_POSITIVE;
        system.copy_from_slice(&normal);
        for i in 0..p {
            system[i * p + i] += damping * normal[i * p + i].max(diag_floor);
            step[i] = -gradient[i];
        }
        pin_active_bounds(lobes, &gradient, bounds, &mut system, &mut step);
        if !cholesky_solve(&mut system, p, &mut step) {
            damping *= growth;
            growth *= 2.0;
            continue;
        }
        // Predicted decrease of the linear model: ½ δᵀ(λDδ − g).
        let predicted: f64 = (0..p)
            .map(|i| {
                0.5 * step[i]
                    * (damping * normal[i * p + i].max(diag_floor) * step[i] - gradient[i])
            })
            .sum();
        let trial: Vec<Lobe> = lobes
            .iter()
            .zip(step.chunks_exact(PARAMS_PER_LOBE))
            .map(|(lobe, s)| lobe.retract(s, bounds))
            .collect();
        let trial_cost = cost_of(lights, values, &trial);
        let actual = cost - trial_cost;
        if actual > 0.0 && trial_cost.is_finite() {
            let gain = if predicted > 0.0 {
                actual / predicted
            } else {
                1.0
            };
            damping *= (1.0 - (2.0 * gain - 1.0).powi(3)).max(1.0 / 3.0);
            growth = 2.0;
            let moved = largest_move(&step, scale);
            *lobes = trial;
            let previous = cost;
            cost = linearise(lights, values, lobes, &mut jac, &mut residual);
            normal_equations(&jac, &residual, p, &mut normal, &mut gradient);
            let small_decrease = actual <= opts.cost_tolerance * previous
                && predicted <= opts.cost_tolerance * previous;
            if small_decrease || moved <= opts.step_tolerance {
                return (iteration, true);
            }
        } else {
            damping *= growth;
            growth *= 2.0;
            // Damping this large means no step lowers the cost at f64
            // precision: a (possibly bound-constrained) minimum.
            if damping > 1e16 * (max_diag + f64::MIN_POSITIVE) || !damping.is_finite() {
                return (iteration, true);
            }
        }
    }
    (opts.max_iterations, false)
}

/// Projected LM: a parameter sitting on a bound whose descent direction
/// points out of the box is held fixed for this solve, so the clamp cannot
/// swallow the whole step (the other parameters still move).
pub(super) fn pin_active_bounds(
    lobes: &[Lobe],
    gradient: &[f64],
    bounds: &Bounds,
    system: &mut [f64],
    rhs: &mut [f64],
) {
    let p = rhs.len();
    for (index, lobe) in lobes.iter().enumerate() {
        let amplitude = index * PARAMS_PER_LOBE;
        let exponent = amplitude + 3;
        let pin_amplitude = (lobe.amplitude <= 0.0 && gradient[amplitude] > 0.0)
            || (lobe.amplitude >= bounds.max_amplitude && gradient[amplitude] < 0.0);
        let pin_exponent = (lobe.exponent <= MIN_EXPONENT && gradient[exponent] > 0.0)
            || (lobe.exponent >= bounds.max_exponent && gradient[exponent] < 0.0);
        for (pinned, i) in [(pin_amplitude, amplitude), (pin_exponent, exponent)] {
            if pinned {
                for j in 0..p {
                    system[i * p + j] = 0.0;
                    system[j * p + i] = 0.0;
                }
                system[i * p + i] = 1.0;
                rhs[i] = 0.0;
            }
        }
    }
}

/// Largest parameter change of a step: amplitudes relative to the data
/// scale, angles and `ln n` as they are.
pub(super) fn largest_move(step: &[f64], scale: f64) -> f64 {
    step.chunks_exact(PARAMS_PER_LOBE)
        .map(|s| {
            let amplitude = if scale > 0.0 {
                s[0].abs() / scale
            } else {
                s[0].abs()
            };
            amplitude.max(s[1].abs()).max(s[2].abs()).max(s[3].abs())
        })
        .fold(0.0, f64::max)
}

/// Fills the Jacobian (row-major lights × params) and residuals
/// (model − value); returns the cost ½ Σ r².
pub(super) fn linearise(
    lights: &[[f64; 3]],
    values: &[f64],
    lobes: &[Lobe],
    jac: &mut [f64],
    residual: &mut [f64],
) -> f64 {
    let p = lobes.len() * PARAMS_PER_LOBE;
    let bases: Vec<_> = lobes.iter().map(|l| tangent_basis(l.axis)).collect();
    let mut cost = 0.0;
    for (j, (light, value)) in lights.iter().zip(values).enumerate() {
        let model = lobes_jacobian_row(lobes, &bases, *light, &mut jac[j * p..(j + 1) * p]);
        let r = model - value;
        residual[j] = r;
        cost += 0.5 * r * r;
    }
    cost
}

/// `∂s/∂ρ = cos^n`, `∂s/∂u = ρ n cos^{n-1} (e₁·l)`, `∂s/∂v` likewise with
/// e₂, `∂s/∂ln n = ρ cos^n · n ln cos`; 0 where `cos ≤ 0`. All bounded:
/// `cos^{n-1} ≤ 1` as `n ≥ 1`, and `|x eˣ| ≤ 1/e` for `x = n ln cos ≤ 0`.
/// `bases` holds each lobe's [`tangent_basis`]. Returns the model value.
pub(super) fn lobes_jacobian_row(
    lobes: &[Lobe],
    bases: &[([f64; 3], [f64; 3])],
    light: [f64; 3],
    row: &mut [f64],
) -> f64 {
    let mut model = 0.0;
    for ((lobe, (e1, e2)), out) in lobes
        .iter()
        .zip(bases)
        .zip(row.chunks_exact_mut(PARAMS_PER_LOBE))
    {
        let c = dot(lobe.axis, light).min(1.0);
        if c <= 0.0 {
            out.fill(0.0);
            continue;
        }
        let n = lobe.exponent;
        let ln_c = c.ln();
        let shape = (n * ln_c).exp();
        // cos^{n-1} = cos^n / cos, at most 1 for n ≥ 1 (saves an exp).
        let slope = lobe.amplitude * n * (shape / c).min(1.0);
        model += lobe.amplitude * shape;
        out[0] = shape;
        out[1] = slope * dot(*e1, light);
        out[2] = slope * dot(*e2, light);
        out[3] = lobe.amplitude * shape * n * ln_c;
    }
    model
}

pub(super) fn normal_equations(
    jac: &[f64],
    residual: &[f64],
    p: usize,
    normal: &mut [f64],
    gradient: &mut [f64],
) {
    normal.fill(0.0);
    gradient.fill(0.0);
    for (row, r) in jac.chunks_exact(p).zip(residual) {
        for i in 0..p {
            gradient[i] += row[i] * r;
            for j in 0..=i {
                normal[i * p + j] += row[i] * row[j];
            }
        }
    }
    for i in 0..p {
        for j in 0..i {
            normal[j * p + i] = normal[i * p + j];
        }
    }
}

/// Solves `a x = b` in place for symmetric positive definite `a` (p × p,
/// row-major); false if `a` is not numerically positive definite.
pub(super) fn cholesky_solve(a: &mut [f64], p: usize, b: &mut [f64]) -> bool {
    for j in 0..p {
        let mut d = a[j * p + j];
        for k in 0..j {
            d -= a[j * p + k] * a[j * p + k];
        }
        if !(d > 0.0 && d.is_finite()) {
            return false;
        }
        let d = d.sqrt();
        a[j * p + j] = d;
        for i in j + 1..p {
            let mut s = a[i * p + j];
            for k in 0..j {
                s -= a[i * p + k] * a[j * p + k];
            }
            a[i * p + j] = s / d;
        }
    }
    for i in 0..p {
        let mut s = b[i];
        for k in 0..i {
            s -= a[i * p + k] * b[k];
        }
        b[i] = s / a[i * p + i];
    }
    for i in (0..p).rev() {
        let mut s = b[i];
        for k in i + 1..p {
            s -= a[k * p + i] * b[k];
        }
        b[i] = s / a[i * p + i];
    }
    b.iter().all(|x| x.is_finite())
}

pub(super) fn cost_of(lights: &[[f64; 3]], values: &[f64], lobes: &[Lobe]) -> f64 {
    lights
        .iter()
        .zip(values)
        .map(|(l, v)| {
            let r = lobes.iter().map(|lobe| lobe.evaluate(*l)).sum::<f64>() - v;
            0.5 * r * r
        })
        .sum()
}

/// (RMS, mean absolute) error of lobes against f64 values.
pub(super) fn errors64(lights: &[[f64; 3]], values: &[f64], lobes: &[Lobe]) -> (f64, f64) {
    let mut sum_sq = 0.0;
    let mut sum_abs = 0.0;
    for (l, v) in lights.iter().zip(values) {
        let r = lobes.iter().map(|lobe| lobe.evaluate(*l)).sum::<f64>() - v;
        sum_sq += r * r;
        sum_abs += r.abs();
    }
    let m = lights.len().max(1) as f64;
    ((sum_sq / m).sqrt(), sum_abs / m)
}

/// (RMS, mean absolute) error of any model against f32 values.
pub(super) fn errors(
    lights: &[[f64; 3]],
    values: &[f32],
    model: impl Fn([f64; 3]) -> f64,
) -> (f64, f64) {
    let mut sum_sq = 0.0;
    let mut sum_abs = 0.0;
    for (l, &v) in lights.iter().zip(values) {
        let r = model(*l) - f64::from(v);
        sum_sq += r * r;
        sum_abs += r.abs();
    }
    let m = lights.len().max(1) as f64;
    ((sum_sq / m).sqrt(), sum_abs / m)
}
