//! PNG charts from `minflow::plot`: a loss-curve-like chart and a 2 x 3 panel figure decode
//! to the requested pixel size, are not blank and show every series colour (each panel its
//! own); empty series, single points, NaN/infinite values and all-non-positive data on a log
//! axis draw without panicking; bad requests and unwritable paths are errors naming the file.

use std::collections::HashSet;
use std::path::Path;

use minflow::plot::{self, series_colour, PlotError, Series};

/// A decoded 8-bit RGB image.
struct Image {
    width: u32,
    height: u32,
    rgb: Vec<u8>,
}

impl Image {
    fn read(path: &Path) -> Image {
        let file = std::fs::File::open(path).expect("open png");
        let mut reader = png::Decoder::new(file).read_info().expect("png header");
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).expect("png frame");
        assert_eq!(
            (info.color_type, info.bit_depth),
            (png::ColorType::Rgb, png::BitDepth::Eight)
        );
        buf.truncate(info.buffer_size());
        Image {
            width: info.width,
            height: info.height,
            rgb: buf,
        }
    }

    fn pixel(&self, x: u32, y: u32) -> (u8, u8, u8) {
        let i = 3 * (y as usize * self.width as usize + x as usize);
        (self.rgb[i], self.rgb[i + 1], self.rgb[i + 2])
    }

    /// Distinct colours inside the rectangle [x0, x1) x [y0, y1).
    fn colours_in(&self, (x0, x1): (u32, u32), (y0, y1): (u32, u32)) -> HashSet<(u8, u8, u8)> {
        (y0..y1)
            .flat_map(|y| (x0..x1).map(move |x| (x, y)))
            .map(|(x, y)| self.pixel(x, y))
            .collect()
    }

    /// Pixels of exactly `colour` inside the rectangle [x0, x1) x [y0, y1).
    fn count_in(&self, colour: (u8, u8, u8), (x0, x1): (u32, u32), (y0, y1): (u32, u32)) -> usize {
        (y0..y1)
            .flat_map(|y| (x0..x1).map(move |x| (x, y)))
            .filter(|&(x, y)| self.pixel(x, y) == colour)
            .count()
    }

    fn colours(&self) -> HashSet<(u8, u8, u8)> {
        self.colours_in((0, self.width), (0, self.height))
    }
}

/// Train and validation losses over 50 epochs, decaying from ~1 to ~1e-3.
fn loss_series() -> Vec<Series> {
    let curve = |scale: f64, rate: f64| {
        (0..50)
            .map(|e| (e as f64, scale * (-rate * e as f64).exp()))
            .collect()
    };
    vec![
        Series {
            name: "train".into(),
            points: curve(1.0, 0.14),
        },
        Series {
            name: "validation".into(),
            points: curve(1.3, 0.12),
        },
    ]
}

#[test]
fn loss_curve_has_requested_size_and_both_series_colours() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let path = dir.path().join("loss.png");
    plot::line_chart(
        &path,
        "Training loss",
        "epoch",
        "MSE",
        &loss_series(),
        true,
        (640, 400),
    )
    .expect("line_chart");
    let img = Image::read(&path);
    assert_eq!((img.width, img.height), (640, 400));
    let colours = img.colours();
    assert!(colours.len() > 3, "only {} colours", colours.len());
    for index in 0..2 {
        // A 2 px line over ~500 px of plot plus the legend swatch: well over 100 pixels.
        let n = img.count_in(series_colour(index), (0, 640), (0, 400));
        assert!(
            n > 100,
            "series {index}: {n} pixels of {:?}",
            series_colour(index)
        );
    }
}

#[test]
fn panels_2x3_have_requested_size_and_every_panel_is_drawn() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let path = dir.path().join("scenes.png");
    let panels: Vec<(String, Vec<Series>)> = (0..6)
        .map(|k| {
            let mse = |s: f64| {
                (0..40)
                    .map(|t| (t as f64, s * (1.0 + k as f64) * (1.0 + 0.1 * t as f64)))
                    .collect()
            };
            let series = vec![
                Series {
                    name: "minGRU".into(),
                    points: mse(1e-4),
                },
                Series {
                    name: "minLSTM".into(),
                    points: mse(2e-4),
                },
            ];
            (format!("scene {k}"), series)
        })
        .collect();
    let (pw, ph) = (320, 240);
    plot::panels(&path, &panels, "step", "MSE", true, 3, (pw, ph)).expect("panels");
    let img = Image::read(&path);
    assert_eq!((img.width, img.height), (3 * pw, 2 * ph));
    assert!(img.colours().len() > 3);
    for row in 0..2 {
        for col in 0..3 {
            let cell = ((col * pw, (col + 1) * pw), (row * ph, (row + 1) * ph));
            assert!(
                img.colours_in(cell.0, cell.1).len() > 3,
                "panel ({row}, {col}) is blank"
            );
            for index in 0..2 {
                let n = img.count_in(series_colour(index), cell.0, cell.1);
                assert!(n > 20, "panel ({row}, {col}) series {index}: {n} pixels");
            }
        }
    }
}

#[test]
fn empty_single_point_and_non_finite_data_draw_without_panicking() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let named = |name: &str, points: Vec<(f64, f64)>| Series {
        name: name.into(),
        points,
    };
    let cases: Vec<(&str, Vec<Series>, bool)> = vec![
        ("no_series", vec![], false),
        ("no_series_log", vec![], true),
        (
            "empty_series",
            vec![named("empty", vec![]), named("", vec![])],
            true,
        ),
        ("single_point", vec![named("one", vec![(3.0, 0.5)])], false),
        (
            "single_point_log",
            vec![named("one", vec![(3.0, 0.5)])],
            true,
        ),
        (
            "nan",
            vec![named(
                "nan",
                vec![
                    (f64::NAN, 1.0),
                    (1.0, f64::NAN),
                    (2.0, 2.0),
                    (3.0, f64::INFINITY),
                    (4.0, 1.0),
                ],
            )],
            false,
        ),
        (
            "all_nan",
            vec![named("nan", vec![(f64::NAN, f64::NAN); 5])],
            true,
        ),
        (
            "non_positive_log",
            vec![named("zero", vec![(0.0, 0.0), (1.0, -1.0)])],
            true,
        ),
        (
            "flat",
            vec![named("flat", vec![(0.0, 2.0), (1.0, 2.0), (2.0, 2.0)])],
            false,
        ),
        (
            "huge",
            vec![named(
                "huge",
                vec![(0.0, 1e308), (1.0, -1e308), (2.0, 1.0), (3.0, 1e-310)],
            )],
            true,
        ),
    ];
    for (name, series, log_y) in &cases {
        let path = dir.path().join(format!("{name}.png"));
        plot::line_chart(&path, name, "x", "y", series, *log_y, (300, 200))
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        let img = Image::read(&path);
        assert_eq!((img.width, img.height), (300, 200), "{name}");
        assert!(img.colours().len() > 3, "{name}: axes and text missing");
    }
    // The single point is drawn as a dot in the series colour.
    let img = Image::read(&dir.path().join("single_point.png"));
    assert!(img.count_in(series_colour(0), (0, 300), (0, 200)) > 5);

    // Panels with nothing to draw, fewer panels than cells, and the smallest size.
    let path = dir.path().join("empty_panels.png");
    let panels = vec![
        ("a".to_string(), vec![]),
        ("b".to_string(), vec![named("nan", vec![(f64::NAN, 0.0)])]),
    ];
    plot::panels(
        &path,
        &panels,
        "x",
        "y",
        true,
        3,
        (plot::MIN_SIDE, plot::MIN_SIDE),
    )
    .expect("empty panels");
    let img = Image::read(&path);
    assert_eq!(
        (img.width, img.height),
        (3 * plot::MIN_SIDE, plot::MIN_SIDE)
    );
}

#[test]
fn bad_requests_and_unwritable_paths_are_errors_naming_the_file() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let path = dir.path().join("bad.png");
    let series = loss_series();
    let invalid = [
        plot::line_chart(&path, "t", "x", "y", &series, false, (0, 100)),
        plot::line_chart(
            &path,
            "t",
            "x",
            "y",
            &series,
            false,
            (200, plot::MAX_SIDE + 1),
        ),
        plot::panels(&path, &[], "x", "y", false, 2, (200, 200)),
        plot::panels(
            &path,
            &[("a".into(), series.clone())],
            "x",
            "y",
            false,
            0,
            (200, 200),
        ),
        plot::panels(
            &path,
            &[("a".into(), series.clone())],
            "x",
            "y",
            false,
            100,
            (200, 200),
        ),
    ];
    for result in invalid {
        let err = result.expect_err("invalid request accepted");
        assert!(matches!(err, PlotError::InvalidRequest { .. }), "{err}");
        assert!(err.to_string().contains("bad.png"), "{err}");
    }
    assert!(!path.exists());

    let missing = dir.path().join("no_such_dir").join("loss.png");
    let err = plot::line_chart(&missing, "t", "x", "y", &series, true, (200, 200))
        .expect_err("wrote into a missing folder");
    assert!(matches!(err, PlotError::Write { .. }), "{err}");
    assert!(err.to_string().contains("no_such_dir"), "{err}");
}
