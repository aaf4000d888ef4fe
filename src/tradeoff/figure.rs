//! The trade-off figure: one panel per family, each with its own axes,
//! units and a title that asks the family's question; the Pareto frontier
//! drawn, dominated settings in grey, each row's standard error as an
//! error bar, the profile's default plan ringed, and the labels placed so
//! that none overlaps another or a marker.
//!
//! Axes, ticks and text are laid out by `plotters` (its SVG back end). The
//! point labels are placed here: plotters draws text where it is told, and
//! avoiding collisions is this module's job ([`place_labels`]). The layout
//! ([`Figure`]) is also what the dashboard needs to make the picture
//! interactive: every point's position in the SVG's own coordinates, its
//! row and its values.
//!
//! Only SVG is written: the dashboard and the docs show it as it is, and a
//! bitmap back end would need a font file to draw text.

use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use serde::Serialize;

use super::choice::frontier_by;
use super::{Report, Row, CAMERA_CHAIN_SUFFIX};

/// Width of one panel, SVG pixels.
const PANEL_W: u32 = 470;
/// Height of one panel, SVG pixels.
const PANEL_H: u32 = 310;
/// Height of the figure's title and legend above the panels.
const HEADER_H: u32 = 48;
/// Panels side by side.
const COLUMNS: usize = 2;
/// Font size of the point labels, CSS pixels.
const LABEL_PX: f64 = 11.0;
/// plotters' SVG back end writes a style's size divided by 1.24 as the
/// CSS font size; sizes given to it are multiplied by this.
const PLOTTERS_FONT: f64 = 1.24;
/// Radius of a point's marker.
const MARKER_R: i32 = 4;
/// A family's coverage "varies", and gets its own axis, when two settings
/// differ by more than this many percentage points.
const COVERAGE_VARIES_PCT: f64 = 0.5;

/// One family's panel: which rows, and how they are drawn.
struct PanelSpec {
    family: &'static str,
    title: &'static str,
    x_desc: &'static str,
    y_desc: &'static str,
    /// The cost axis' value of a row, in the axis' unit.
    x_of: fn(&Row) -> Option<f64>,
    /// The row's error in the axis' unit (relative errors as percent).
    y_scale: f64,
    /// The error the panel plots, and its standard error, before scaling.
    y_of: fn(&Row) -> Option<ErrorWithSpread>,
}

/// An error and its standard error, as a panel plots them.
type ErrorWithSpread = (f64, Option<f64>);

/// A row's own error and spread: what most panels plot.
fn own_error(r: &Row) -> Option<ErrorWithSpread> {
    Some((r.error?, r.spread))
}

const PANELS: [PanelSpec; 6] = [
    PanelSpec {
        family: "plans",
        title: "How many directions? Error vs capture time",
        x_desc: "physical capture time, h",
        y_desc: "held-out error, %",
        x_of: |r| r.physical_s.map(|s| s / 3600.0),
        y_scale: 100.0,
        y_of: own_error,
    },
    PanelSpec {
        family: "pca",
        title: "How many PCA components? Error vs size",
        x_desc: "compressed BTF, MB",
        y_desc: "held-out error, %",
        x_of: |r| r.bytes.map(|b| b as f64 / 1e6),
        y_scale: 100.0,
        y_of: own_error,
    },
    PanelSpec {
        family: "laser",
        title: "How many laser sources? Depth error vs scan time",
        x_desc: "physical scan time, min",
        y_desc: "depth error on common pixels, mm",
        x_of: |r| r.physical_s.map(|s| s / 60.0),
        y_scale: 1.0,
        y_of: own_error,
    },
    PanelSpec {
        family: "photometric stereo",
        title: "How many lights? Normal error vs capture time",
        x_desc: "physical capture time, min",
        y_desc: "mean normal error, °",
        x_of: |r| r.physical_s.map(|s| s / 60.0),
        y_scale: 1.0,
        y_of: own_error,
    },
    PanelSpec {
        family: "fidelity",
        title: "Which effects matter? Frame change vs render time",
        x_desc: "render time, s",
        y_desc: "frame change without it, %",
        x_of: |r| r.compute_s,
        y_scale: 100.0,
        y_of: own_error,
    },
    PanelSpec {
        family: super::exposure::FAMILY,
        title: "Which exposures? Error near the mirror vs capture time",
        x_desc: "physical capture time, h",
        y_desc: "held-out error within 10° of the mirror, %",
        x_of: |r| r.physical_s.map(|s| s / 3600.0),
        y_scale: 100.0,
        y_of: |r| r.near_mirror.map(|m| (m.error, m.spread)),
    },
];

/// A rectangle in SVG pixels: `[x0, y0, x1, y1]`.
pub type Rect = [f64; 4];

/// The figure: its SVG, and its layout (size, panels, every point drawn)
/// for the dashboard to make it interactive.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct Figure {
    /// The figure as SVG (what `tradeoff.svg` holds).
    pub svg: String,
    /// SVG width (the `viewBox` width), pixels.
    pub width: u32,
    /// SVG height, pixels.
    pub height: u32,
    /// The panels, one per family with points.
    pub panels: Vec<Panel>,
    /// Every point drawn, panel by panel.
    pub points: Vec<FigurePoint>,
}

/// One panel of the figure.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct Panel {
    /// The family (`plans`, `pca`, `laser`, `photometric stereo`, `fidelity`,
    /// `exposure`).
    pub family: String,
    /// Its title: the question it answers.
    pub title: String,
    /// The cost axis, with its unit.
    pub x_desc: String,
    /// The error axis, with its unit.
    pub y_desc: String,
    /// Whether the cost axis is logarithmic.
    pub log_x: bool,
    /// The plotting area, SVG pixels `[x0, y0, x1, y1]`.
    #[schema(value_type = Vec<f64>)]
    pub area: Rect,
}

/// One point of the figure, with what the dashboard shows and does.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct FigurePoint {
    /// Index of its panel in `panels`.
    pub panel: usize,
    /// Index of its row in the report's `rows`.
    pub row: usize,
    /// The row's setting.
    pub setting: String,
    /// Centre, SVG pixels.
    pub x: f64,
    /// Centre, SVG pixels.
    pub y: f64,
    /// The cost, in the panel's x unit.
    pub cost: f64,
    /// The error, in the panel's y unit.
    pub error: f64,
    /// One standard error, in the panel's y unit.
    pub spread: Option<f64>,
    /// On the family's Pareto frontier (nothing both cheaper and better).
    pub frontier: bool,
    /// The profile's default plan.
    pub marked: bool,
    /// Where its label is drawn; None when no free place was found (the
    /// value is still in the point's tooltip). `[x0, y0, x1, y1]`.
    #[schema(value_type = Option<Vec<f64>>)]
    pub label: Option<Rect>,
}

/// The frontier and dominated colours.
const GREY: RGBColor = RGBColor(170, 170, 170);
const COLOURS: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(255, 127, 14),
];

/// Whether `row` is the plan `marked` names (`grid12x8` names
/// `grid 12x8`).
fn is_marked(row: &Row, marked: Option<&str>) -> bool {
    let Some(m) = marked else { return false };
    row.family == "plans"
        && !row.setting.ends_with(CAMERA_CHAIN_SUFFIX)
        && (row.plan.as_deref() == Some(m) || row.setting.replace(' ', "") == m.replace(' ', ""))
}

/// A point's label text.
fn label_text(row: &Row, marked: bool) -> String {
    if marked {
        format!("{} (default)", row.setting)
    } else {
        row.setting.clone()
    }
}

/// Width of `text` in ems, on the generous side for common sans-serif
/// faces (DejaVu Sans is the widest of them), so that a box placed from
/// it holds the rendered text.
pub fn text_width_em(text: &str) -> f64 {
    text.chars()
        .map(|c| match c {
            'i' | 'l' | 'j' | '.' | ',' | ':' | ';' | '\'' | '|' | '!' => 0.32,
            ' ' | 'f' | 't' | 'r' | '(' | ')' | '°' | '-' | '/' => 0.45,
            'm' | 'w' | 'M' | 'W' | '%' => 1.0,
            c if c.is_ascii_uppercase() => 0.78,
            _ => 0.66,
        })
        .sum()
}

fn overlaps(a: &Rect, b: &Rect, gap: f64) -> bool {
    a[0] < b[2] + gap && b[0] < a[2] + gap && a[1] < b[3] + gap && b[1] < a[3] + gap
}

/// Whether the segment `a`–`b` crosses the rectangle (Liang–Barsky
/// clipping).
fn segment_hits(a: (f64, f64), b: (f64, f64), r: &Rect) -> bool {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [
        (-dx, a.0 - r[0]),
        (dx, r[2] - a.0),
        (-dy, a.1 - r[1]),
        (dy, r[3] - a.1),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return false;
            }
        } else {
            let t = q / p;
            if p < 0.0 {
                t0 = t0.max(t);
            } else {
                t1 = t1.min(t);
            }
            if t0 > t1 {
                return false;
            }
        }
    }
    true
}

/// What a label must keep clear of besides other labels.
#[derive(Debug, Clone, Default)]
pub struct Obstacles {
    /// Markers: centre and radius.
    pub markers: Vec<((f64, f64), f64)>,
    /// Drawn lines (the frontier), as segments.
    pub segments: Vec<Segment>,
}

/// Places one label of the given size per point, inside `bounds`, so that
/// no two labels overlap and no label covers a marker; a label crosses a
/// line only where no place clear of lines is left. Each label takes the
/// first free place of rings of candidates around its point (right, left,
/// above, below, the diagonals, and above or below flush with the point),
/// nearest ring first. Points earlier in the list choose first. None where
/// every candidate collides.
pub fn place_labels(
    points: &[(f64, f64)],
    sizes: &[(f64, f64)],
    bounds: Rect,
    obstacles: &Obstacles,
) -> Vec<Option<Rect>> {
    let markers: Vec<Rect> = obstacles
        .markers
        .iter()
        .map(|&((x, y), r)| [x - r, y - r, x + r, y + r])
        .collect();
    let mut placed: Vec<Rect> = Vec::new();
    let mut out = Vec::with_capacity(points.len());
    for (&(x, y), &(w, h)) in points.iter().zip(sizes) {
        // The point's own marker radius sets the first ring.
        let own_r = obstacles
            .markers
            .iter()
            .filter(|((mx, my), _)| *mx == x && *my == y)
            .map(|(_, r)| *r)
            .fold(0.0, f64::max);
        let candidates = |d: f64| {
            let r = own_r + d;
            let q = r * std::f64::consts::FRAC_1_SQRT_2;
            [
                (x + r, y - h / 2.0),
                (x - r - w, y - h / 2.0),
                (x - w / 2.0, y - r - h),
                (x - w / 2.0, y + r),
                (x + q, y - q - h),
                (x + q, y + q),
                (x - q - w, y - q - h),
                (x - q - w, y + q),
                (x - w + 4.0, y - r - h),
                (x - 4.0, y - r - h),
                (x - w + 4.0, y + r),
                (x - 4.0, y + r),
            ]
        };
        let fits = |rect: &Rect, clear_of_lines: bool| {
            rect[0] >= bounds[0]
                && rect[1] >= bounds[1]
                && rect[2] <= bounds[2]
                && rect[3] <= bounds[3]
                && !placed.iter().any(|p| overlaps(p, rect, 2.0))
                && !markers.iter().any(|m| overlaps(m, rect, 1.0))
                && (!clear_of_lines
                    || !obstacles
                        .segments
                        .iter()
                        .any(|&(a, b)| segment_hits(a, b, rect)))
        };
        let rings = [2.0, 8.0, 16.0, 28.0, 44.0, 64.0, 90.0];
        let chosen = [true, false].into_iter().find_map(|clear_of_lines| {
            rings.iter().find_map(|&d| {
                candidates(d)
                    .into_iter()
                    .map(|(x0, y0)| [x0, y0, x0 + w, y0 + h])
                    .find(|rect| fits(rect, clear_of_lines))
            })
        });
        if let Some(rect) = chosen {
            placed.push(rect);
        }
        out.push(chosen);
    }
    out
}

/// A row of a panel, before drawing.
struct Plotted {
    row: usize,
    cost: f64,
    error: f64,
    spread: Option<f64>,
    frontier: bool,
    marked: bool,
    /// A check of another row, not a setting of its own: drawn hollow,
    /// never on the frontier.
    check: bool,
    /// The share of the sample the setting measures, percent, where the
    /// family records it (laser, photometric stereo).
    coverage: Option<f64>,
}

/// The rows of `spec`'s family that can be drawn.
fn plotted(report: &Report, spec: &PanelSpec, marked: Option<&str>) -> Vec<Plotted> {
    let mut items: Vec<Plotted> = report
        .rows
        .iter()
        .enumerate()
        .filter(|(_, r)| r.family == spec.family)
        .filter_map(|(k, r)| {
            let cost = (spec.x_of)(r)?;
            let (error, spread) = (spec.y_of)(r)?;
            let error = error * spec.y_scale;
            (cost.is_finite() && cost > 0.0 && error.is_finite()).then(|| Plotted {
                row: k,
                cost,
                error,
                spread: spread.map(|s| s * spec.y_scale).filter(|s| s.is_finite()),
                frontier: false,
                marked: is_marked(r, marked),
                check: r.setting.ends_with(CAMERA_CHAIN_SUFFIX),
                coverage: r.coverage.map(|c| 100.0 * c).filter(|c| c.is_finite()),
            })
        })
        .collect();
    let candidates: Vec<usize> = (0..items.len()).filter(|&i| !items[i].check).collect();
    for i in frontier_by(&candidates, |&i| (items[i].cost, items[i].error)) {
        items[i].frontier = true;
    }
    items
}

/// Whether a cost axis from `lo` to `hi` reads better logarithmic.
fn wants_log(lo: f64, hi: f64) -> bool {
    hi / lo > 8.0
}

/// Tick text: short, with as many digits as the size needs.
fn tick(v: f64) -> String {
    let a = v.abs();
    if a == 0.0 {
        "0".into()
    } else if a >= 10.0 {
        format!("{v:.0}")
    } else if a >= 1.0 {
        format!("{v:.1}").trim_end_matches(".0").to_string()
    } else if a >= 0.1 {
        format!("{v:.2}").trim_end_matches('0').to_string()
    } else {
        format!("{v:.3}").trim_end_matches('0').to_string()
    }
}

/// The figure of `report`, with `marked` (a plan name, the profile's
/// default) ringed.
pub fn figure(report: &Report, marked: Option<&str>) -> Figure {
    let panels: Vec<(&PanelSpec, Vec<Plotted>)> = PANELS
        .iter()
        .map(|spec| (spec, plotted(report, spec, marked)))
        .filter(|(_, items)| !items.is_empty())
        .collect();
    let rows_of_panels = panels.len().div_ceil(COLUMNS).max(1);
    let width = PANEL_W * COLUMNS as u32;
    let height = HEADER_H + PANEL_H * rows_of_panels as u32;
    let mut buffer = String::new();
    let mut figure = Figure {
        svg: String::new(),
        width,
        height,
        panels: Vec::new(),
        points: Vec::new(),
    };
    // The SVG back end writes into a String and does not fail; if a draw
    // did, the figure drawn so far is kept and the failure logged.
    if let Err(e) = draw(report, &panels, &mut buffer, &mut figure) {
        tracing::warn!("the trade-off figure is incomplete: {e}");
    }
    figure.svg = buffer;
    figure
}

type DrawResult = Result<(), Box<dyn std::error::Error>>;

fn draw(
    report: &Report,
    panels: &[(&PanelSpec, Vec<Plotted>)],
    buffer: &mut String,
    figure: &mut Figure,
) -> DrawResult {
    let root = SVGBackend::with_string(buffer, (figure.width, figure.height)).into_drawing_area();
    root.fill(&WHITE)?;
    let (header, body) = root.split_vertically(HEADER_H);
    header.draw(&Text::new(
        format!(
            "{} on {}: what accuracy costs",
            report.scene, report.profile
        ),
        (12, 8),
        ("sans-serif", 15.0 * PLOTTERS_FONT).into_font(),
    ))?;
    legend(&header)?;
    // A family with rows but nothing to draw (the laser scan that hardly
    // sees a sample) is named, not silently left out.
    let omitted: Vec<&str> = PANELS
        .iter()
        .map(|spec| spec.family)
        .filter(|f| report.rows.iter().any(|r| r.family == *f))
        .filter(|f| !panels.iter().any(|(spec, _)| spec.family == *f))
        .collect();
    if !omitted.is_empty() {
        header.draw(&Text::new(
            format!(
                "no errors to draw: {} (see the table's detail)",
                omitted.join(", ")
            ),
            (figure.width as i32 - 12, 10),
            ("sans-serif", 11.0 * PLOTTERS_FONT)
                .into_font()
                .color(&BLACK)
                .pos(Pos::new(HPos::Right, VPos::Top)),
        ))?;
    }
    if panels.is_empty() {
        header.draw(&Text::new(
            "no row has both a cost and an error",
            (12, 30),
            ("sans-serif", 11.0 * PLOTTERS_FONT).into_font(),
        ))?;
        root.present()?;
        return Ok(());
    }
    let rows_of_panels = panels.len().div_ceil(COLUMNS);
    let areas = body.split_evenly((rows_of_panels, COLUMNS));
    let mut labels: Vec<(String, Rect, RGBColor, (f64, f64))> = Vec::new();
    for (p, ((spec, items), area)) in panels.iter().zip(areas.iter()).enumerate() {
        let colour = COLOURS[p % COLOURS.len()];
        let lo = items.iter().map(|i| i.cost).fold(f64::INFINITY, f64::min);
        let hi = items.iter().map(|i| i.cost).fold(0.0, f64::max);
        let top = items
            .iter()
            .map(|i| i.error + i.spread.unwrap_or(0.0))
            .fold(0.0, f64::max);
        let y_range = 0.0..(top * 1.2).max(1e-9);
        let log_x = wants_log(lo, hi);
        let drawn = if log_x {
            panel(
                area,
                spec,
                (lo / 1.6..hi * 1.6).log_scale(),
                y_range,
                items,
                colour,
            )?
        } else {
            let pad = ((hi - lo) * 0.15).max(hi * 0.1);
            panel(
                area,
                spec,
                (lo - pad).max(0.0)..hi + pad,
                y_range,
                items,
                colour,
            )?
        };
        let PanelDrawn {
            area: bounds,
            centres,
            error_bars,
            coverage,
        } = drawn;
        figure.panels.push(Panel {
            family: spec.family.to_string(),
            title: spec.title.to_string(),
            x_desc: spec.x_desc.to_string(),
            y_desc: spec.y_desc.to_string(),
            log_x,
            area: bounds,
        });
        // Frontier and marked points choose their label's place first.
        let mut order: Vec<usize> = (0..items.len()).collect();
        order.sort_by_key(|&i| (!items[i].marked, !items[i].frontier, i));
        let texts: Vec<String> = order
            .iter()
            .map(|&i| label_text(&report.rows[items[i].row], items[i].marked))
            .collect();
        let sizes: Vec<(f64, f64)> = texts
            .iter()
            .map(|t| (text_width_em(t) * LABEL_PX, 1.25 * LABEL_PX))
            .collect();
        let at: Vec<(f64, f64)> = order.iter().map(|&i| centres[i]).collect();
        let mut front: Vec<usize> = (0..items.len()).filter(|&i| items[i].frontier).collect();
        front.sort_by(|&a, &b| items[a].cost.total_cmp(&items[b].cost));
        let obstacles = Obstacles {
            markers: items
                .iter()
                .zip(&centres)
                .map(|(item, &c)| {
                    let r = if item.marked {
                        MARKER_R + 6
                    } else {
                        MARKER_R + 1
                    };
                    (c, f64::from(r))
                })
                .chain(coverage.iter().map(|&c| (c, f64::from(MARKER_R) + 1.0)))
                .collect(),
            segments: front
                .windows(2)
                .map(|w| (centres[w[0]], centres[w[1]]))
                .chain(error_bars.iter().flatten().copied())
                .chain(coverage.windows(2).map(|w| (w[0], w[1])))
                .collect(),
        };
        let placed = place_labels(&at, &sizes, bounds, &obstacles);
        let mut label_of = vec![None; items.len()];
        for ((&i, rect), text) in order.iter().zip(placed).zip(texts) {
            label_of[i] = rect;
            if let Some(rect) = rect {
                let c = if items[i].frontier || items[i].marked {
                    colour
                } else {
                    RGBColor(120, 120, 120)
                };
                labels.push((text, rect, c, centres[i]));
            }
        }
        for (i, item) in items.iter().enumerate() {
            figure.points.push(FigurePoint {
                panel: p,
                row: item.row,
                setting: report.rows[item.row].setting.clone(),
                x: centres[i].0,
                y: centres[i].1,
                cost: item.cost,
                error: item.error,
                spread: item.spread,
                frontier: item.frontier,
                marked: item.marked,
                label: label_of[i],
            });
        }
    }
    for (text, rect, colour, (px, py)) in labels {
        // A label set off from its point gets a leader line.
        let near_x = px.clamp(rect[0], rect[2]);
        let near_y = py.clamp(rect[1], rect[3]);
        if (near_x - px).hypot(near_y - py) > f64::from(MARKER_R) + 8.0 {
            root.draw(&PathElement::new(
                vec![
                    (px.round() as i32, py.round() as i32),
                    (near_x.round() as i32, near_y.round() as i32),
                ],
                GREY.stroke_width(1),
            ))?;
        }
        // The glyphs' box starts ~0.17 em above the text's top anchor.
        let y = rect[1] + 0.2 * LABEL_PX;
        root.draw(&Text::new(
            text,
            (rect[0].round() as i32, y.round() as i32),
            ("sans-serif", LABEL_PX * PLOTTERS_FONT)
                .into_font()
                .color(&colour)
                .pos(Pos::new(HPos::Left, VPos::Top)),
        ))?;
    }
    root.present()?;
    Ok(())
}

/// The legend under the title: what a filled, grey, hollow and ringed
/// point means.
fn legend(header: &DrawingArea<SVGBackend, Shift>) -> DrawResult {
    let font = ("sans-serif", 11.0 * PLOTTERS_FONT).into_font();
    let y = 34;
    let mut x = 16;
    header.draw(&Circle::new((x, y), MARKER_R, COLOURS[0].filled()))?;
    header.draw(&Text::new(
        "on the frontier (nothing both cheaper and better)",
        (x + 8, y - 6),
        font.clone(),
    ))?;
    x += 300;
    header.draw(&Circle::new((x, y), MARKER_R, GREY.filled()))?;
    header.draw(&Text::new("dominated", (x + 8, y - 6), font.clone()))?;
    x += 80;
    header.draw(&Circle::new((x, y), MARKER_R, COLOURS[0].stroke_width(1)))?;
    header.draw(&Text::new("check row", (x + 8, y - 6), font.clone()))?;
    x += 80;
    header.draw(&Circle::new((x, y), MARKER_R + 4, BLACK.stroke_width(2)))?;
    header.draw(&Text::new(
        "profile's default",
        (x + 12, y - 6),
        font.clone(),
    ))?;
    x += 130;
    header.draw(&PathElement::new(
        vec![(x, y - 6), (x, y + 6)],
        BLACK.stroke_width(1),
    ))?;
    header.draw(&Text::new("±1 standard error", (x + 6, y - 6), font))?;
    Ok(())
}

/// A segment between two points, SVG pixels.
type Segment = ((f64, f64), (f64, f64));

/// A drawn panel: its plotting area, each point's centre and error bar,
/// and the coverage markers.
struct PanelDrawn {
    area: Rect,
    centres: Vec<(f64, f64)>,
    error_bars: Vec<Option<Segment>>,
    /// The coverage markers on the right-hand axis, cheapest first.
    coverage: Vec<(f64, f64)>,
}

/// Draws one panel and returns where its points went, SVG pixels. Where
/// the family's coverage varies (a setting that measures less of the
/// sample), it gets its own axis on the right, 0–100 %.
fn panel<X>(
    area: &DrawingArea<SVGBackend, Shift>,
    spec: &PanelSpec,
    x_range: X,
    y_range: std::ops::Range<f64>,
    items: &[Plotted],
    colour: RGBColor,
) -> Result<PanelDrawn, Box<dyn std::error::Error>>
where
    X: AsRangedCoord<Value = f64> + Clone,
    X::CoordDescType: ValueFormatter<f64>,
{
    let coverage: Vec<(f64, f64)> = {
        let mut c: Vec<(f64, f64)> = items
            .iter()
            .filter_map(|i| Some((i.cost, i.coverage?)))
            .collect();
        c.sort_by(|a, b| a.0.total_cmp(&b.0));
        c
    };
    let varies = coverage.len() > 1
        && coverage
            .iter()
            .any(|c| (c.1 - coverage[0].1).abs() > COVERAGE_VARIES_PCT);
    let mut chart = ChartBuilder::on(area)
        .caption(spec.title, ("sans-serif", 13.0 * PLOTTERS_FONT).into_font())
        .margin(10)
        .x_label_area_size(38)
        .y_label_area_size(52)
        .right_y_label_area_size(if varies { 46 } else { 0 })
        .build_cartesian_2d(x_range.clone(), y_range)?
        .set_secondary_coord(x_range, 0.0..105.0);
    chart
        .configure_mesh()
        .x_desc(spec.x_desc)
        .y_desc(spec.y_desc)
        .x_labels(6)
        .y_labels(6)
        .x_label_formatter(&|v| tick(*v))
        .y_label_formatter(&|v| tick(*v))
        .label_style(("sans-serif", 10.0 * PLOTTERS_FONT).into_font())
        .axis_desc_style(("sans-serif", 11.0 * PLOTTERS_FONT).into_font())
        .light_line_style(RGBColor(240, 240, 240))
        .bold_line_style(RGBColor(225, 225, 225))
        .draw()?;
    let mut coverage_px = Vec::new();
    if varies {
        chart
            .configure_secondary_axes()
            .y_desc("coverage of the sample, % (×)")
            .y_labels(6)
            .y_label_formatter(&|v| tick(*v))
            .label_style(("sans-serif", 10.0 * PLOTTERS_FONT).into_font())
            .axis_desc_style(("sans-serif", 11.0 * PLOTTERS_FONT).into_font())
            .draw()?;
        let faint = colour.mix(0.45);
        chart.draw_secondary_series(LineSeries::new(
            coverage.iter().copied(),
            faint.stroke_width(1),
        ))?;
        chart.draw_secondary_series(
            coverage
                .iter()
                .map(|&c| Cross::new(c, MARKER_R, faint.stroke_width(2))),
        )?;
        for c in &coverage {
            let (x, y) = chart.borrow_secondary().backend_coord(c);
            coverage_px.push((f64::from(x), f64::from(y)));
        }
    }
    let (xs, ys) = chart.plotting_area().get_pixel_range();
    let bounds = [
        f64::from(xs.start),
        f64::from(ys.start),
        f64::from(xs.end),
        f64::from(ys.end),
    ];
    // The frontier, cheapest first.
    let mut front: Vec<&Plotted> = items.iter().filter(|i| i.frontier).collect();
    front.sort_by(|a, b| a.cost.total_cmp(&b.cost));
    chart.draw_series(LineSeries::new(
        front.iter().map(|i| (i.cost, i.error)),
        colour.stroke_width(2),
    ))?;
    let mut centres = Vec::with_capacity(items.len());
    let mut bars = Vec::with_capacity(items.len());
    for item in items {
        let c = if item.frontier { colour } else { GREY };
        let pixel = |y: f64| {
            let (px, py) = chart.backend_coord(&(item.cost, y));
            (f64::from(px), f64::from(py))
        };
        bars.push(
            item.spread
                .map(|s| (pixel((item.error - s).max(0.0)), pixel(item.error + s))),
        );
        if let Some(s) = item.spread {
            chart.draw_series(std::iter::once(ErrorBar::new_vertical(
                item.cost,
                (item.error - s).max(0.0),
                item.error,
                item.error + s,
                c.stroke_width(1),
                6,
            )))?;
        }
        let style = if item.check {
            c.stroke_width(2)
        } else {
            c.filled()
        };
        chart.draw_series(std::iter::once(Circle::new(
            (item.cost, item.error),
            MARKER_R,
            style,
        )))?;
        if item.marked {
            chart.draw_series(std::iter::once(Circle::new(
                (item.cost, item.error),
                MARKER_R + 4,
                BLACK.stroke_width(2),
            )))?;
        }
        let (x, y) = chart.backend_coord(&(item.cost, item.error));
        centres.push((f64::from(x), f64::from(y)));
    }
    Ok(PanelDrawn {
        area: bounds,
        centres,
        error_bars: bars,
        coverage: coverage_px,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn row(family: &str, setting: &str, t: f64, e: f64) -> Row {
        Row {
            family: family.into(),
            setting: setting.into(),
            physical_s: Some(t),
            bytes: Some((t * 1000.0) as u64),
            error: Some(e),
            spread: Some(e * 0.05),
            unit: "relative".into(),
            ..Row::default()
        }
    }

    fn report(rows: Vec<Row>) -> Report {
        Report {
            profile: "bonn-gonioreflectometer".into(),
            scene: "corduroy".into(),
            texture: 8,
            held_out: 24,
            components: 8,
            method: vec![],
            summary: vec![],
            rows,
        }
    }

    #[test]
    fn one_panel_per_family_with_its_frontier_and_the_default_ringed() {
        let r = report(vec![
            row("plans", "h2", 34_000.0, 0.10),
            row("plans", "h1", 35_000.0, 0.12),
            row("plans", "h2, 3 rings", 2_100.0, 0.57),
            row("plans", "h2, 3 rings, camera chain", 2_100.0, 0.50),
            row("pca", "C = 2", 2.0, 0.3),
            row("pca", "C = 8", 8.0, 0.2),
        ]);
        let f = figure(&r, Some("h1"));
        assert_eq!(f.panels.len(), 2);
        assert_eq!(f.panels[0].family, "plans");
        assert_eq!(f.panels[1].family, "pca");
        let by = |s: &str| f.points.iter().find(|p| p.setting == s).expect(s);
        assert!(by("h2").frontier && by("h2, 3 rings").frontier);
        // h1 is slower and worse than h2: dominated, and the default.
        assert!(!by("h1").frontier && by("h1").marked);
        // The camera-chain row checks another; it is never on the frontier.
        assert!(!by("h2, 3 rings, camera chain").frontier);
        // The error axis is percent; the spread rides along.
        assert!((by("h2").error - 10.0).abs() < 1e-9);
        assert!((by("h2").spread.unwrap() - 0.5).abs() < 1e-9);
        let svg = f.svg;
        assert!(svg.contains("How many directions?") && svg.contains("h1 (default)"));
        assert!(svg.contains("viewBox"));
    }

    #[test]
    fn a_segment_hits_the_rectangles_it_crosses_only() {
        let r = [10.0, 10.0, 20.0, 20.0];
        assert!(segment_hits((0.0, 15.0), (30.0, 15.0), &r));
        assert!(segment_hits((12.0, 12.0), (13.0, 13.0), &r));
        assert!(!segment_hits((0.0, 0.0), (30.0, 5.0), &r));
        assert!(!segment_hits((0.0, 30.0), (9.0, 0.0), &r));
        // Vertical and horizontal segments beside it.
        assert!(!segment_hits((25.0, 0.0), (25.0, 30.0), &r));
        assert!(segment_hits((15.0, 0.0), (15.0, 30.0), &r));
    }

    #[test]
    fn coverage_gets_its_own_axis_only_where_it_varies() {
        let laser = |n: usize, e: f64, cov: f64| Row {
            coverage: Some(cov),
            unit: "mm".into(),
            ..row("laser", &format!("{n} sources"), 60.0 * n as f64, e)
        };
        let varies = figure(
            &report(vec![laser(1, 0.13, 0.22), laser(26, 0.07, 0.98)]),
            None,
        );
        assert!(varies.svg.contains("coverage of the sample"));
        let same = figure(
            &report(vec![laser(1, 0.13, 1.0), laser(26, 0.07, 1.0)]),
            None,
        );
        assert!(!same.svg.contains("coverage of the sample"));
    }

    #[test]
    fn a_report_with_nothing_to_draw_says_so() {
        let svg = figure(&report(vec![]), None).svg;
        assert!(svg.contains("no row has both a cost and an error"));
        // A family whose rows have no error is named.
        let mut laser = row("laser", "1 source", 60.0, 0.1);
        laser.error = None;
        let f = figure(&report(vec![row("plans", "h2", 3600.0, 0.1), laser]), None);
        assert_eq!(f.panels.len(), 1);
        assert!(f.svg.contains("no errors to draw: laser"), "{}", f.svg);
    }

    #[test]
    fn labels_of_a_crowded_panel_do_not_overlap() {
        // Eight plans with nearly the same time and error: the worst case.
        let rows: Vec<Row> = (0..8)
            .map(|k| row("plans", &format!("plan {k}"), 3600.0 + k as f64, 0.2))
            .collect();
        let f = figure(&report(rows), None);
        let boxes: Vec<Rect> = f.points.iter().filter_map(|p| p.label).collect();
        assert!(boxes.len() >= 6, "only {} of 8 labels placed", boxes.len());
        for (i, a) in boxes.iter().enumerate() {
            for b in &boxes[i + 1..] {
                assert!(!overlaps(a, b, 0.0), "{a:?} and {b:?}");
            }
        }
    }

    proptest! {
        #[test]
        fn placed_labels_never_overlap_and_stay_inside(
            pts in proptest::collection::vec((0.0f64..400.0, 0.0f64..260.0, 20.0f64..120.0), 1..14)
        ) {
            let bounds = [0.0, 0.0, 400.0, 260.0];
            let points: Vec<(f64, f64)> = pts.iter().map(|p| (p.0, p.1)).collect();
            let sizes: Vec<(f64, f64)> = pts.iter().map(|p| (p.2, 14.0)).collect();
            let obstacles = Obstacles {
                markers: points.iter().map(|&p| (p, 5.0)).collect(),
                segments: points.windows(2).map(|w| (w[0], w[1])).collect(),
            };
            let placed = place_labels(&points, &sizes, bounds, &obstacles);
            let boxes: Vec<Rect> = placed.into_iter().flatten().collect();
            for (i, a) in boxes.iter().enumerate() {
                prop_assert!(a[0] >= 0.0 && a[1] >= 0.0 && a[2] <= 400.0 && a[3] <= 260.0);
                for b in &boxes[i + 1..] {
                    prop_assert!(!overlaps(a, b, 0.0));
                }
                for &(x, y) in &points {
                    prop_assert!(!overlaps(a, &[x - 5.0, y - 5.0, x + 5.0, y + 5.0], 0.0));
                }
            }
        }
    }
}
