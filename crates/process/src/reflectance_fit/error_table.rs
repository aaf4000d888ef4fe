//! Error table (Meseth et al. Table 1).

use super::*;

/// A row label of the error table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum FitMethod {
    /// The 6-coefficient biquadratic PTM of Malzbender et al.
    Ptm,
    /// Meseth et al.'s eq. 1 with this many lobes.
    Lobes(usize),
}

impl fmt::Display for FitMethod {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FitMethod::Ptm => write!(f, "PTM"),
            FitMethod::Lobes(k) => write!(f, "non-linear K={k}"),
        }
    }
}

/// One row of Meseth et al. Table 1 for one view slot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ErrorRow {
    /// Which model the row is for.
    pub method: FitMethod,
    /// Mean over texels and lights of |model − value|, input units: the
    /// paper's "average luminance difference between data and model" (the
    /// paper does not define it further; we read "average difference" as
    /// the mean absolute difference).
    pub mean_abs_error: f64,
    /// RMS over texels and lights of model − value, input units.
    pub rms_error: f64,
    /// Wall time of the whole slot fit on the rayon pool.
    pub fit_time: Duration,
    /// Texels whose LM converged (all of them for PTM).
    pub converged_texels: usize,
}

/// Meseth et al. Table 1 for one view slot: one row per method.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ErrorTable {
    /// Texels in the slot.
    pub texels: usize,
    /// Lights (values) per texel.
    pub lights: usize,
    /// Threads of the rayon pool the fits ran on.
    pub threads: usize,
    /// PTM first, then one row per lobe count asked for, in that order.
    pub rows: Vec<ErrorRow>,
}

impl fmt::Display for ErrorTable {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "{} texels x {} lights, {} threads",
            self.texels, self.lights, self.threads
        )?;
        writeln!(
            f,
            "{:<16} {:>12} {:>12} {:>12} {:>10}",
            "method", "mean |err|", "rms err", "fit time ms", "converged"
        )?;
        for row in &self.rows {
            writeln!(
                f,
                "{:<16} {:>12.6} {:>12.6} {:>12.1} {:>10}",
                row.method.to_string(),
                row.mean_abs_error,
                row.rms_error,
                row.fit_time.as_secs_f64() * 1e3,
                row.converged_texels
            )?;
        }
        Ok(())
    }
}

/// Fits a view slot with PTM and with each `k` in `ks` and tabulates the
/// average luminance errors and fit times (Meseth et al. Table 1; its
/// "Lafortune (2 lobes)" column fits one model to all views and is not a
/// per-slot method, so it has no row here).
pub fn error_table(
    lights: &[[f64; 3]],
    values: &[f32],
    ks: &[usize],
    opts: &FitOptions,
) -> Result<ErrorTable, FitError> {
    let unit = unit_lights(lights)?;
    check_slot_values(values, unit.len())?;
    let texels = values.len() / unit.len();
    let mut rows = Vec::with_capacity(ks.len() + 1);
    let start = Instant::now();
    let ptm = fit_ptm_slot(&unit, values)?;
    rows.push(ErrorRow {
        method: FitMethod::Ptm,
        mean_abs_error: ptm.mean_abs_error(),
        rms_error: ptm.rms_error(),
        fit_time: start.elapsed(),
        converged_texels: texels,
    });
    for &k in ks {
        let start = Instant::now();
        let fit = fit_slot(&unit, values, k, opts)?;
        rows.push(ErrorRow {
            method: FitMethod::Lobes(k),
            mean_abs_error: fit.mean_abs_error(),
            rms_error: fit.rms_error(),
            fit_time: start.elapsed(),
            converged_texels: fit.converged_texels(),
        });
    }
    Ok(ErrorTable {
        texels,
        lights: unit.len(),
        threads: rayon::current_num_threads(),
        rows,
    })
}
