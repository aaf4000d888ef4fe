//! `rigd holder template`: the profile's holder plate drawn to scale, to
//! print and build it by (or to glue onto a plate): the plate in its grey,
//! the point markers as discs, the border lines, the sample window, the
//! colour patches and white areas, a 100 mm line to check the print's
//! scale, and in the margin the profile's and the holder's names.
//!
//! One drawing ([`Drawing`], page millimetres, y down) is written as SVG
//! (the `svg` crate; the document's user unit is the millimetre) or as PDF
//! (`printpdf`, with PDF's built-in Helvetica, so no font file is needed).

use std::path::Path;

use rigd_core::chart::{chart, linear_to_srgb};
use rigd_core::holder::{HolderError, HolderSpec, Polarity};

/// Blank margin around the plate on the page, mm: room for the names at
/// the top and the scale check line at the bottom, and for a printer's
/// unprintable edge.
pub const MARGIN_MM: f64 = 20.0;

/// Length of the scale check line, mm.
pub const CHECK_LINE_MM: f64 = 100.0;

/// The file formats a template is written in, chosen by the extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TemplateFormat {
    /// `.svg`: Scalable Vector Graphics in millimetre units.
    Svg,
    /// `.pdf`: one page of exactly the drawing's size.
    Pdf,
}

impl TemplateFormat {
    /// The format a file name's extension asks for (`.svg`, `.pdf`, any
    /// case); None for any other.
    pub fn of_path(path: &Path) -> Option<TemplateFormat> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        match ext.as_str() {
            "svg" => Some(TemplateFormat::Svg),
            "pdf" => Some(TemplateFormat::Pdf),
            _ => None,
        }
    }
}

/// Why a template could not be made or written.
#[derive(Debug, thiserror::Error)]
pub enum TemplateError {
    /// The profile's holder cannot work (the key and why).
    #[error("the profile's holder cannot be drawn: {0}")]
    Holder(#[from] HolderError),
    /// The output's extension is neither `.svg` nor `.pdf`.
    #[error("{0}: expected a file name ending in .svg or .pdf")]
    Format(String),
    /// The PDF writer failed.
    #[error("cannot make the PDF: {0}")]
    Pdf(String),
    /// Writing the file failed.
    #[error(transparent)]
    Write(#[from] rigd_core::atomic::WriteError),
}

/// An sRGB colour, each channel encoded, 0 to 1.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Srgb(pub [f64; 3]);

impl Srgb {
    /// The grey a print of diffuse reflectance `r` needs.
    pub fn grey(r: f64) -> Srgb {
        let v = linear_to_srgb(r);
        Srgb([v; 3])
    }

    /// The colour of a linear sRGB reflectance.
    pub fn of_linear(rgb: [f64; 3]) -> Srgb {
        Srgb(rgb.map(linear_to_srgb))
    }

    /// `#rrggbb`.
    pub fn hex(self) -> String {
        let [r, g, b] = self.0.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
        format!("#{r:02x}{g:02x}{b:02x}")
    }

    /// Black or white, whichever reads on this colour.
    fn ink(self) -> Srgb {
        let y = 0.2126 * self.0[0] + 0.7152 * self.0[1] + 0.0722 * self.0[2];
        if y < 0.5 {
            Srgb([1.0; 3])
        } else {
            Srgb([0.0; 3])
        }
    }
}

/// Where text sits relative to its point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Anchor {
    /// The point is the text's start.
    Start,
    /// The point is the text's middle.
    Middle,
}

/// What a shape is on the plate, kept in the SVG as its `class` so that
/// tools (and the tests) find the markers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// The plate's outline.
    Plate,
    /// A point marker.
    Marker,
    /// A border line.
    BorderLine,
    /// The sample window.
    Sample,
    /// A colour patch.
    Patch,
    /// A white reference area.
    White,
    /// The scale check line.
    CheckLine,
    /// A label.
    Label,
}

impl Role {
    fn class(self) -> &'static str {
        match self {
            Role::Plate => "plate",
            Role::Marker => "marker",
            Role::BorderLine => "border-line",
            Role::Sample => "sample-window",
            Role::Patch => "patch",
            Role::White => "white",
            Role::CheckLine => "check-line",
            Role::Label => "label",
        }
    }
}

/// One thing drawn, page millimetres from the top left corner, y down.
#[derive(Debug, Clone, PartialEq)]
pub enum Shape {
    /// A rectangle: top left corner, width and height; filled and/or
    /// outlined (with a dash length, mm, for a dashed outline).
    Rect {
        /// What it is.
        role: Role,
        /// Top left corner.
        at: [f64; 2],
        /// Width and height.
        size: [f64; 2],
        /// Fill colour, if filled.
        fill: Option<Srgb>,
        /// Outline colour and width, if outlined.
        stroke: Option<(Srgb, f64)>,
        /// Dash length of the outline; None: solid.
        dash: Option<f64>,
    },
    /// A filled disc.
    Disc {
        /// What it is.
        role: Role,
        /// Its index among the holder's markers, for a marker.
        index: Option<usize>,
        /// Centre.
        centre: [f64; 2],
        /// Radius.
        radius: f64,
        /// Fill colour.
        fill: Srgb,
    },
    /// A straight line.
    Line {
        /// What it is.
        role: Role,
        /// One end.
        from: [f64; 2],
        /// The other end.
        to: [f64; 2],
        /// Colour and width.
        stroke: (Srgb, f64),
    },
    /// One line of text; `at` is on its baseline.
    Text {
        /// Where: on the baseline, at the start or the middle.
        at: [f64; 2],
        /// Height of the type (its em), mm.
        size: f64,
        /// How the text sits on `at`.
        anchor: Anchor,
        /// Colour.
        fill: Srgb,
        /// The text.
        text: String,
    },
}

/// The whole page: its size and what is on it, in drawing order.
#[derive(Debug, Clone, PartialEq)]
pub struct Drawing {
    /// Page width and height, mm.
    pub page_mm: [f64; 2],
    /// The plate's centre (the sample centre) on the page, mm from the top
    /// left corner.
    pub centre_mm: [f64; 2],
    /// The shapes, back to front.
    pub shapes: Vec<Shape>,
    /// A title for the document's metadata.
    pub title: String,
}

/// Width of the type's average character, as a fraction of its size
/// (Helvetica's lower case): what text is fitted by.
const CHAR_WIDTH: f64 = 0.52;

/// Draws `spec`'s plate for the profile named `profile`: checked first,
/// a holder that cannot work is refused naming its key. The page is the
/// plate plus [`MARGIN_MM`] on every side (wider only if the plate is
/// narrower than the check line).
pub fn drawing(profile: &str, spec: &HolderSpec) -> Result<Drawing, HolderError> {
    let holder = spec.holder()?;
    let mm = |m: f64| m * 1e3;
    let plate = mm(2.0 * holder.half);
    let page = [
        plate.max(CHECK_LINE_MM) + 2.0 * MARGIN_MM,
        plate + 2.0 * MARGIN_MM,
    ];
    let centre = [page[0] / 2.0, MARGIN_MM + plate / 2.0];
    // Plate metres (+y up) to page millimetres (+y down).
    let at = |p: [f64; 2]| [centre[0] + mm(p[0]), centre[1] - mm(p[1])];
    let black = Srgb([0.0; 3]);
    let plate_grey = Srgb::grey(holder.colour);
    let on_plate = plate_grey.ink();
    let mut shapes = vec![Shape::Rect {
        role: Role::Plate,
        at: at([-holder.half, holder.half]),
        size: [plate, plate],
        fill: Some(plate_grey),
        stroke: Some((black, 0.2)),
        dash: None,
    }];
    // Border lines: a frame of four lines around the sample window.
    if holder.has_border_lines() {
        let [ox, oy] = holder.line_offset;
        let w = mm(2.0 * holder.line_half_width);
        let grey = Srgb::grey(holder.marker_colour);
        let h = holder.line_half_width;
        let lines = [
            ([-ox - h, oy], [ox + h, oy]),
            ([-ox - h, -oy], [ox + h, -oy]),
            ([-ox, oy + h], [-ox, -oy - h]),
            ([ox, oy + h], [ox, -oy - h]),
        ];
        for (a, b) in lines {
            shapes.push(Shape::Line {
                role: Role::BorderLine,
                from: at(a),
                to: at(b),
                stroke: (grey, w),
            });
        }
    }
    // The sample window, dashed, with its size.
    let [sx, sy] = holder.sample_half;
    shapes.push(Shape::Rect {
        role: Role::Sample,
        at: at([-sx, sy]),
        size: [mm(2.0 * sx), mm(2.0 * sy)],
        fill: None,
        stroke: Some((on_plate, 0.3)),
        dash: Some(2.0),
    });
    let sample_label = format!(
        "sample {} × {} mm",
        trim_mm(spec.sample_mm[0]),
        trim_mm(spec.sample_mm[1])
    );
    let label_size = fit_type(&sample_label, mm(2.0 * sx) * 0.8, 4.0);
    shapes.push(Shape::Text {
        at: at([0.0, 0.0]),
        size: label_size,
        anchor: Anchor::Middle,
        fill: on_plate,
        text: sample_label,
    });
    // The patches: the standard row and the chart's filled with their
    // colour, the lab's own outlined; each named in small type.
    let standard = if spec.colour_patches {
        rigd_core::holder::COLOUR_PATCHES.len()
    } else {
        0
    };
    let charted = spec
        .chart
        .as_ref()
        .and_then(|c| chart(&c.name))
        .map_or(0, |c| c.patches.len());
    for (k, p) in holder.patches.iter().enumerate() {
        let filled = k < standard + charted;
        let side = mm(2.0 * p.half);
        let colour = Srgb::of_linear(p.rgb);
        shapes.push(Shape::Rect {
            role: Role::Patch,
            at: at([p.centre[0] - p.half, p.centre[1] + p.half]),
            size: [side, side],
            fill: filled.then_some(colour),
            stroke: Some((if filled { black } else { on_plate }, 0.2)),
            dash: None,
        });
        let size = fit_type(&p.name, side * 0.9, 2.0);
        let c = at(p.centre);
        shapes.push(Shape::Text {
            at: [c[0], c[1] + 0.35 * size],
            size,
            anchor: Anchor::Middle,
            fill: if filled { colour.ink() } else { on_plate },
            text: p.name.clone(),
        });
    }
    for w in &holder.whites {
        let size = [mm(2.0 * w.half[0]), mm(2.0 * w.half[1])];
        shapes.push(Shape::Rect {
            role: Role::White,
            at: at([w.centre[0] - w.half[0], w.centre[1] + w.half[1]]),
            size,
            fill: Some(Srgb::grey(w.reflectance)),
            stroke: Some((black, 0.2)),
            dash: None,
        });
        let text = format!("white {:.2}", w.reflectance);
        let type_size = fit_type(&text, size[0] * 0.9, 2.0);
        let c = at(w.centre);
        shapes.push(Shape::Text {
            at: [c[0], c[1] + 0.35 * type_size],
            size: type_size,
            anchor: Anchor::Middle,
            fill: Srgb::grey(w.reflectance).ink(),
            text,
        });
    }
    // The point markers last: nothing may cover them.
    for (i, p) in holder.points.iter().enumerate() {
        let r = match p.polarity {
            Polarity::Light => holder.marker_colour,
            Polarity::Dark => holder.dark_marker_colour,
        };
        shapes.push(Shape::Disc {
            role: Role::Marker,
            index: Some(i),
            centre: at(p.position),
            radius: mm(p.radius),
            fill: Srgb::grey(r),
        });
    }
    // The margin: names and how to print at the top, the check line at
    // the bottom.
    let left = (page[0] - plate) / 2.0;
    shapes.push(Shape::Text {
        at: [left, MARGIN_MM * 0.4],
        size: 4.0,
        anchor: Anchor::Start,
        fill: black,
        text: format!("profile {profile} · holder {}", holder.name),
    });
    shapes.push(Shape::Text {
        at: [left, MARGIN_MM * 0.75],
        size: 3.5,
        anchor: Anchor::Start,
        fill: black,
        text: "print at 100 % (no scaling)".into(),
    });
    let y = page[1] - MARGIN_MM * 0.55;
    let x0 = (page[0] - CHECK_LINE_MM) / 2.0;
    let x1 = x0 + CHECK_LINE_MM;
    let rule = (black, 0.3);
    shapes.push(Shape::Line {
        role: Role::CheckLine,
        from: [x0, y],
        to: [x1, y],
        stroke: rule,
    });
    for x in [x0, x1] {
        shapes.push(Shape::Line {
            role: Role::CheckLine,
            from: [x, y - 2.5],
            to: [x, y + 2.5],
            stroke: rule,
        });
    }
    shapes.push(Shape::Text {
        at: [page[0] / 2.0, y + 6.5],
        size: 3.5,
        anchor: Anchor::Middle,
        fill: black,
        text: format!("{CHECK_LINE_MM:.0} mm: measure this after printing"),
    });
    Ok(Drawing {
        page_mm: page,
        centre_mm: centre,
        shapes,
        title: format!("holder {} of profile {profile}", holder.name),
    })
}

/// A length in mm without needless decimals (`100`, `62.5`).
fn trim_mm(v: f64) -> String {
    let s = format!("{v:.2}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

/// The type size at which `text` fits `width` mm, at most `max`.
fn fit_type(text: &str, width: f64, max: f64) -> f64 {
    let chars = text.chars().count().max(1) as f64;
    (width / (CHAR_WIDTH * chars)).min(max)
}

/// Shortest decimal that keeps 1 µm: what the SVG's numbers are written as.
fn num(v: f64) -> f64 {
    (v * 1e4).round() / 1e4
}

impl Drawing {
    /// The drawing as an SVG document: width and height in mm, the user
    /// unit a millimetre (`viewBox` = the page), each shape's role as its
    /// `class` and each marker's index as `data-index`.
    pub fn svg(&self) -> String {
        use svg::node::element::{Circle, Line, Rectangle, Text, Title};
        let [w, h] = self.page_mm;
        let mut doc = svg::Document::new()
            .set("width", format!("{}mm", num(w)))
            .set("height", format!("{}mm", num(h)))
            .set("viewBox", (0.0, 0.0, num(w), num(h)))
            .add(Title::new(self.title.clone()))
            // The page itself is white: a viewer's background may not be.
            .add(
                Rectangle::new()
                    .set("width", num(w))
                    .set("height", num(h))
                    .set("fill", "#ffffff"),
            );
        for shape in &self.shapes {
            doc = match shape {
                Shape::Rect {
                    role,
                    at,
                    size,
                    fill,
                    stroke,
                    dash,
                } => {
                    let mut r = Rectangle::new()
                        .set("class", role.class())
                        .set("x", num(at[0]))
                        .set("y", num(at[1]))
                        .set("width", num(size[0]))
                        .set("height", num(size[1]))
                        .set("fill", fill.map_or("none".to_string(), Srgb::hex));
                    if let Some((colour, width)) = stroke {
                        r = r
                            .set("stroke", colour.hex())
                            .set("stroke-width", num(*width));
                    }
                    if let Some(d) = dash {
                        r = r.set("stroke-dasharray", format!("{} {}", num(*d), num(*d)));
                    }
                    doc.add(r)
                }
                Shape::Disc {
                    role,
                    index,
                    centre,
                    radius,
                    fill,
                } => {
                    let mut c = Circle::new()
                        .set("class", role.class())
                        .set("cx", num(centre[0]))
                        .set("cy", num(centre[1]))
                        .set("r", num(*radius))
                        .set("fill", fill.hex());
                    if let Some(i) = index {
                        c = c.set("data-index", *i);
                    }
                    doc.add(c)
                }
                Shape::Line {
                    role,
                    from,
                    to,
                    stroke,
                } => doc.add(
                    Line::new()
                        .set("class", role.class())
                        .set("x1", num(from[0]))
                        .set("y1", num(from[1]))
                        .set("x2", num(to[0]))
                        .set("y2", num(to[1]))
                        .set("stroke", stroke.0.hex())
                        .set("stroke-width", num(stroke.1)),
                ),
                Shape::Text {
                    at,
                    size,
                    anchor,
                    fill,
                    text,
                } => doc.add(
                    Text::new(text.clone())
                        .set("class", Role::Label.class())
                        .set("x", num(at[0]))
                        .set("y", num(at[1]))
                        .set("font-size", num(*size))
                        .set("font-family", "Helvetica, Arial, sans-serif")
                        .set(
                            "text-anchor",
                            match anchor {
                                Anchor::Start => "start",
                                Anchor::Middle => "middle",
                            },
                        )
                        .set("fill", fill.hex()),
                ),
            };
        }
        format!("{doc}\n")
    }

    /// The drawing as a one-page PDF of exactly the page's size.
    pub fn pdf(&self) -> Result<Vec<u8>, TemplateError> {
        use printpdf::path::{PaintMode, WindingOrder};
        use printpdf::{
            calculate_points_for_circle, BuiltinFont, Color, Line, LineDashPattern, Mm,
            PdfDocument, Point, Polygon, Pt, Rgb,
        };
        let [w, h] = self.page_mm;
        let (doc, page, layer) =
            PdfDocument::new(&self.title, Mm(w as f32), Mm(h as f32), "template");
        let layer = doc.get_page(page).get_layer(layer);
        let font = doc
            .add_builtin_font(BuiltinFont::Helvetica)
            .map_err(|e| TemplateError::Pdf(e.to_string()))?;
        // Page millimetres (y down) to PDF points (y up).
        let pt = |p: [f64; 2]| Point::new(Mm(p[0] as f32), Mm((h - p[1]) as f32));
        let colour =
            |c: Srgb| Color::Rgb(Rgb::new(c.0[0] as f32, c.0[1] as f32, c.0[2] as f32, None));
        let points_per_mm = 72.0 / 25.4;
        let solid = LineDashPattern::default();
        for shape in &self.shapes {
            match shape {
                Shape::Rect {
                    at,
                    size,
                    fill,
                    stroke,
                    dash,
                    ..
                } => {
                    let corners = [
                        *at,
                        [at[0] + size[0], at[1]],
                        [at[0] + size[0], at[1] + size[1]],
                        [at[0], at[1] + size[1]],
                    ];
                    let ring: Vec<(Point, bool)> =
                        corners.iter().map(|&c| (pt(c), false)).collect();
                    if let Some(f) = fill {
                        layer.set_fill_color(colour(*f));
                        layer.add_polygon(Polygon {
                            rings: vec![ring.clone()],
                            mode: PaintMode::Fill,
                            winding_order: WindingOrder::NonZero,
                        });
                    }
                    if let Some((c, width)) = stroke {
                        layer.set_outline_color(colour(*c));
                        layer.set_outline_thickness((width * points_per_mm) as f32);
                        layer.set_line_dash_pattern(match dash {
                            Some(d) => {
                                let d = (d * points_per_mm).round().max(1.0) as i64;
                                LineDashPattern {
                                    dash_1: Some(d),
                                    gap_1: Some(d),
                                    ..LineDashPattern::default()
                                }
                            }
                            None => solid,
                        });
                        layer.add_line(Line {
                            points: ring,
                            is_closed: true,
                        });
                        layer.set_line_dash_pattern(solid);
                    }
                }
                Shape::Disc {
                    centre,
                    radius,
                    fill,
                    ..
                } => {
                    let c = pt(*centre);
                    layer.set_fill_color(colour(*fill));
                    layer.add_polygon(Polygon {
                        rings: vec![calculate_points_for_circle(
                            Pt::from(Mm(*radius as f32)),
                            c.x,
                            c.y,
                        )],
                        mode: PaintMode::Fill,
                        winding_order: WindingOrder::NonZero,
                    });
                }
                Shape::Line {
                    from, to, stroke, ..
                } => {
                    layer.set_outline_color(colour(stroke.0));
                    layer.set_outline_thickness((stroke.1 * points_per_mm) as f32);
                    layer.add_line(Line {
                        points: vec![(pt(*from), false), (pt(*to), false)],
                        is_closed: false,
                    });
                }
                Shape::Text {
                    at,
                    size,
                    anchor,
                    fill,
                    text,
                } => {
                    // PDF places text by its start: a middle is estimated
                    // from the type's average width.
                    let x = match anchor {
                        Anchor::Start => at[0],
                        Anchor::Middle => {
                            at[0] - 0.5 * CHAR_WIDTH * size * text.chars().count() as f64
                        }
                    };
                    let p = pt([x, at[1]]);
                    layer.set_fill_color(colour(*fill));
                    layer.use_text(
                        text.as_str(),
                        (size * points_per_mm) as f32,
                        Mm::from(p.x),
                        Mm::from(p.y),
                        &font,
                    );
                }
            }
        }
        doc.save_to_bytes()
            .map_err(|e| TemplateError::Pdf(e.to_string()))
    }
}

/// Draws the holder of `spec` for the profile named `profile` and writes
/// it to `out` in the format its extension names, atomically: the file is
/// whole or not there. Returns the drawing.
pub fn write_template(
    profile: &str,
    spec: &HolderSpec,
    out: &Path,
) -> Result<Drawing, TemplateError> {
    let format = TemplateFormat::of_path(out)
        .ok_or_else(|| TemplateError::Format(out.display().to_string()))?;
    let drawing = drawing(profile, spec)?;
    let bytes = match format {
        TemplateFormat::Svg => drawing.svg().into_bytes(),
        TemplateFormat::Pdf => drawing.pdf()?,
    };
    rigd_core::atomic::write(out, &bytes)?;
    Ok(drawing)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_format_is_the_extension_and_nothing_else() {
        assert_eq!(
            TemplateFormat::of_path(Path::new("a/plate.SVG")),
            Some(TemplateFormat::Svg)
        );
        assert_eq!(
            TemplateFormat::of_path(Path::new("plate.pdf")),
            Some(TemplateFormat::Pdf)
        );
        for bad in ["plate.png", "plate", "plate.svg.txt", ".pdf"] {
            assert_eq!(TemplateFormat::of_path(Path::new(bad)), None, "{bad}");
        }
    }

    #[test]
    fn the_standard_plate_is_drawn_to_scale_with_every_marker() {
        let spec = HolderSpec::default();
        let d = drawing("bonn", &spec).expect("the standard plate");
        assert_eq!(d.page_mm, [200.0, 200.0]);
        let holder = spec.holder().expect("holder");
        let discs: Vec<[f64; 2]> = d
            .shapes
            .iter()
            .filter_map(|s| match s {
                Shape::Disc { centre, .. } => Some(*centre),
                _ => None,
            })
            .collect();
        assert_eq!(discs.len(), holder.points.len());
        for (c, p) in discs.iter().zip(&holder.points) {
            assert!((c[0] - d.centre_mm[0] - p.position[0] * 1e3).abs() < 1e-9);
            assert!((d.centre_mm[1] - c[1] - p.position[1] * 1e3).abs() < 1e-9);
        }
        let texts: Vec<&str> = d
            .shapes
            .iter()
            .filter_map(|s| match s {
                Shape::Text { text, .. } => Some(text.as_str()),
                _ => None,
            })
            .collect();
        for want in [
            "sample 100 × 100 mm",
            "100 mm: measure this after printing",
            "print at 100 % (no scaling)",
            "profile bonn · holder standard",
        ] {
            assert!(texts.contains(&want), "{want} in {texts:?}");
        }
    }

    #[test]
    fn grey_is_the_printed_reflectance() {
        assert_eq!(Srgb::grey(0.0).hex(), "#000000");
        assert_eq!(Srgb::grey(1.0).hex(), "#ffffff");
        // 18 % grey prints as sRGB 118.
        assert_eq!(Srgb::grey(0.18).hex(), "#767676");
        assert_eq!(trim_mm(100.0), "100");
        assert_eq!(trim_mm(62.5), "62.5");
    }
}
