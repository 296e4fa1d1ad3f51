//! PNG line charts: [`line_chart`] draws named (x, y) series into one chart, [`panels`] draws
//! a grid of such charts with one title each. Inputs are plain `f64` pairs in whatever units
//! the caller plots (e.g. x = epoch, y = loss; x = step, y = MSE in domain units squared) and
//! sizes in pixels; the output is an 8-bit RGB PNG file, written whatever the file name's
//! extension. Text uses DejaVu Sans embedded in the binary (no system font libraries), so
//! charts look the same on every machine. Used by `minflow train` for the loss curve and by
//! `minflow eval` for per-scene MSE curves.
//!
//! [`draw_text`] writes labels onto RGB images (`minflow eval`'s particle renders).
//!
//! Non-finite points, points beyond ±1e300 and, on a log y axis, points with y <= 0 (or below
//! 1e-300) are skipped; a chart with nothing left to draw still gets its axes, on a default
//! range. Every failure is one [`PlotError`] that names the file.
//!
//! Files: `chart.rs` draws one chart on one drawing area, `range.rs` picks the drawable
//! points and the axis ranges, `ticks.rs` the tick values and labels.

mod chart;
mod range;
mod ticks;

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use plotters::backend::{BitMapBackend, RGBPixel};
use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};

use chart::ChartSpec;

// DejaVu Sans 2.37 (Bitstream Vera license + public-domain DejaVu changes: free to redistribute).
const FONT_TTF: &[u8] = include_bytes!("DejaVuSans.ttf");
/// Font family name the charts ask plotters for; [`FONT_TTF`] is registered under it.
const FONT_FAMILY: &str = "sans-serif";

/// Smallest accepted image side in pixels (whole image for [`line_chart`], one panel for
/// [`panels`]); below it the axes and labels have no room.
pub const MIN_SIDE: u32 = 120;
/// Largest accepted side of the whole image in pixels.
pub const MAX_SIDE: u32 = 16_384;

/// Series colours (RGB), in order: series `i` is drawn in `PALETTE[i % PALETTE.len()]`.
/// The Tableau 10 colours: distinct from each other and from the black/grey of the axes.
pub const PALETTE: [(u8, u8, u8); 10] = [
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
];

/// One named line: (x, y) points, drawn in the order given.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Series {
    /// Legend entry; an empty name leaves the series out of the legend.
    pub name: String,
    /// The points, (x, y).
    pub points: Vec<(f64, f64)>,
}

/// Every way drawing a chart can fail; each names the PNG file.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The request cannot be drawn: a size out of range, no panels, zero columns.
    #[error("{path}: cannot plot: {reason}")]
    InvalidRequest {
        /// PNG file.
        path: PathBuf,
        /// What is wrong with the request.
        reason: String,
    },
    /// The embedded font was rejected by the font loader.
    #[error("{path}: the embedded font DejaVuSans.ttf could not be loaded")]
    Font {
        /// PNG file.
        path: PathBuf,
    },
    /// plotters failed while drawing into the in-memory image.
    #[error("{path}: drawing the chart: {message}")]
    Draw {
        /// PNG file.
        path: PathBuf,
        /// The library's error, as text.
        message: String,
    },
    /// Creating, encoding or writing the PNG file failed.
    #[error("{path}: writing the PNG: {source}")]
    Write {
        /// PNG file.
        path: PathBuf,
        /// The OS or encoder error.
        #[source]
        source: std::io::Error,
    },
}

/// Colour of series `index`: [`PALETTE`], cycled.
pub fn series_colour(index: usize) -> (u8, u8, u8) {
    PALETTE[index % PALETTE.len()]
}

/// Line chart of `series` into a PNG of `size` = (width, height) pixels at `path`, with
/// `title`, axis labels, a legend of the named series (in the corner with the fewest points)
/// and one [`PALETTE`] colour per series; a series of one point is drawn as a dot.
/// `log_y` draws a log10 y axis and skips points with y <= 0.
pub fn line_chart(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series],
    log_y: bool,
    size: (u32, u32),
) -> Result<(), PlotError> {
    check_side(path, "width", size.0)?;
    check_side(path, "height", size.1)?;
    let spec = ChartSpec {
        title,
        x_label,
        y_label,
        series,
        log_y,
    };
    render(path, size, |root| chart::draw(root, &spec))
}

/// Grid of line charts into one PNG at `path`: `panels` are (title, series) in row-major
/// order, `cols` per row, each panel `panel_size` = (width, height) pixels, so the image is
/// `cols * width` x `ceil(panels.len() / cols) * height`; cells past the last panel stay white.
/// Axis labels, `log_y` and colours as in [`line_chart`].
pub fn panels(
    path: &Path,
    panels: &[(String, Vec<Series>)],
    x_label: &str,
    y_label: &str,
    log_y: bool,
    cols: usize,
    panel_size: (u32, u32),
) -> Result<(), PlotError> {
    let invalid = |reason: String| PlotError::InvalidRequest {
        path: path.to_path_buf(),
        reason,
    };
    if panels.is_empty() {
        return Err(invalid("no panels to draw".into()));
    }
    if cols == 0 {
        return Err(invalid("zero columns".into()));
    }
    check_side(path, "panel width", panel_size.0)?;
    check_side(path, "panel height", panel_size.1)?;
    let rows = panels.len().div_ceil(cols);
    let total = |n: usize, side: u32, what: &str| {
        u32::try_from(n)
            .ok()
            .and_then(|n| n.checked_mul(side))
            .filter(|&t| t <= MAX_SIDE)
            .ok_or_else(|| invalid(format!("{n} {what} of {side} px exceed {MAX_SIDE} px")))
    };
    let size = (
        total(cols, panel_size.0, "columns")?,
        total(rows, panel_size.1, "rows")?,
    );
    render(path, size, |root| {
        for (area, (title, series)) in root.split_evenly((rows, cols)).iter().zip(panels) {
            let spec = ChartSpec {
                title,
                x_label,
                y_label,
                series,
                log_y,
            };
            chart::draw(area, &spec)?;
        }
        Ok(())
    })
}

/// Writes `text` onto an 8-bit RGB image buffer of `size` = (width, height) pixels with its
/// top-left corner at `pos` (pixels), in the embedded font, `px` pixels high, in `colour`
/// (RGB). Text past the edges is clipped. Used by `minflow eval`'s particle renders.
pub fn draw_text(
    pixels: &mut [u8],
    size: (u32, u32),
    text: &str,
    pos: (i32, i32),
    px: f64,
    colour: (u8, u8, u8),
) -> Result<(), String> {
    if !font_registered() {
        return Err("the embedded font DejaVuSans.ttf could not be loaded".into());
    }
    let backend = BitMapBackend::<RGBPixel>::with_buffer_and_format(pixels, size)
        .map_err(|e| e.to_string())?;
    let root = backend.into_drawing_area();
    let colour = RGBColor(colour.0, colour.1, colour.2);
    let style = TextStyle::from((FONT_FAMILY, px).into_font()).color(&colour);
    root.draw_text(text, &style, pos)
        .map_err(|e| e.to_string())?;
    root.present().map_err(|e| e.to_string())
}

/// The in-memory drawing area every chart is drawn on.
type Root<'a> = DrawingArea<BitMapBackend<'a, RGBPixel>, plotters::coord::Shift>;

/// Draws with `draw` on a white `size` image and writes it as a PNG to `path`.
fn render(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&Root<'_>) -> Result<(), String>,
) -> Result<(), PlotError> {
    if !font_registered() {
        return Err(PlotError::Font {
            path: path.to_path_buf(),
        });
    }
    let drawing = |message: String| PlotError::Draw {
        path: path.to_path_buf(),
        message,
    };
    // Sides are checked against MAX_SIDE, so this neither overflows nor allocates > 1 GiB.
    let mut pixels = vec![255u8; size.0 as usize * size.1 as usize * 3];
    {
        let backend = BitMapBackend::<RGBPixel>::with_buffer_and_format(&mut pixels, size)
            .map_err(|e| drawing(e.to_string()))?;
        let root = backend.into_drawing_area();
        root.fill(&WHITE).map_err(|e| drawing(e.to_string()))?;
        draw(&root).map_err(drawing)?;
        root.present().map_err(|e| drawing(e.to_string()))?;
    }
    write_png(path, size, &pixels).map_err(|source| PlotError::Write {
        path: path.to_path_buf(),
        source,
    })
}

/// Encodes 8-bit RGB `pixels` of `size` as a PNG file at `path`.
fn write_png(path: &Path, size: (u32, u32), pixels: &[u8]) -> std::io::Result<()> {
    let mut encoder = png::Encoder::new(BufWriter::new(File::create(path)?), size.0, size.1);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().map_err(io_error)?;
    writer.write_image_data(pixels).map_err(io_error)?;
    writer.finish().map_err(io_error)
}

/// An encoder error as the I/O error it wraps, or as an I/O error of kind `Other`.
fn io_error(e: png::EncodingError) -> std::io::Error {
    match e {
        png::EncodingError::IoError(e) => e,
        other => std::io::Error::other(other),
    }
}

/// Rejects a side outside [`MIN_SIDE`]..=[`MAX_SIDE`].
fn check_side(path: &Path, what: &str, side: u32) -> Result<(), PlotError> {
    if (MIN_SIDE..=MAX_SIDE).contains(&side) {
        return Ok(());
    }
    Err(PlotError::InvalidRequest {
        path: path.to_path_buf(),
        reason: format!("{what} {side} px is outside {MIN_SIDE}..={MAX_SIDE} px"),
    })
}

/// Registers [`FONT_TTF`] as [`FONT_FAMILY`] once per process; false if it was rejected.
fn font_registered() -> bool {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    *REGISTERED.get_or_init(|| register_font(FONT_FAMILY, FontStyle::Normal, FONT_TTF).is_ok())
}
