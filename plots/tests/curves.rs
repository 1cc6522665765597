//! Training-curve pictures: the PNG shows the bold moving-average line where the data is, the
//! goal lines, and text where it should be. (The moving average itself is tested in
//! `mapless_sim::stats`.)

use std::path::{Path, PathBuf};

use mapless_plots::PlotError;
use mapless_plots::curves::{AVERAGE_RGB, CurvePoint, CurveStyle, GOAL_RGB, HEIGHT_PX, NOTE_RGB, WIDTH_PX, training_curves_png};

fn out(name: &str) -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join("plot").join(name)
}

struct Decoded {
    width: u32,
    height: u32,
    rgba: Vec<u8>,
}

impl Decoded {
    fn open(path: &Path) -> Decoded {
        let img = image::open(path).unwrap().to_rgba8();
        Decoded { width: img.width(), height: img.height(), rgba: img.into_raw() }
    }

    fn rgb(&self, x: u32, y: u32) -> [u8; 3] {
        let i = ((y * self.width + x) * 4) as usize;
        [self.rgba[i], self.rgba[i + 1], self.rgba[i + 2]]
    }

    /// Pixels of (about) colour `rgb` in columns `xs`, rows `ys`, as (x, y).
    fn find(&self, rgb: [u8; 3], xs: std::ops::Range<u32>, ys: std::ops::Range<u32>) -> Vec<(u32, u32)> {
        let mut hits = Vec::new();
        for y in ys {
            for x in xs.clone() {
                let p = self.rgb(x, y);
                if p.iter().zip(rgb).all(|(a, b)| a.abs_diff(b) <= 3) {
                    hits.push((x, y));
                }
            }
        }
        hits
    }
}

// Layout (see curves.rs): plot areas span x 96..972; the return panel y 80..310 and the steps
// panel y 380..610, each with its caption and legend on the line above it, tick labels below
// and left of it, axis titles beyond those.
const PLOT_X: std::ops::Range<u32> = 97..971;
const RETURN_ROWS: std::ops::Range<u32> = 81..310;
const STEPS_ROWS: std::ops::Range<u32> = 381..610;

/// Dark text pixels (tick labels, captions, titles) in a region.
fn text_pixels(img: &Decoded, xs: std::ops::Range<u32>, ys: std::ops::Range<u32>) -> usize {
    ys.flat_map(|y| xs.clone().map(move |x| (x, y))).filter(|&(x, y)| img.rgb(x, y).iter().all(|&c| c < 90)).count()
}

/// A deterministic learning curve: return rises towards 330, steps towards 1000, with noise.
fn learning_curve(n: u64) -> Vec<CurvePoint> {
    let mut state = 12345u64;
    (1..=n)
        .map(|e| {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let noise = ((state >> 33) as f64 / (1u64 << 31) as f64) - 0.5; // −0.5 .. 0.5
            let progress = 1.0 - (-(e as f64) / (n as f64 / 4.0)).exp();
            let episode_return = -50.0 + 380.0 * progress + 120.0 * noise;
            let steps = (1000.0 * progress + 300.0 * noise).clamp(1.0, 1000.0) as u32;
            CurvePoint { episode: e, episode_return, steps }
        })
        .collect()
}

#[test]
fn window_zero_is_an_error_and_writes_nothing() {
    let path = out("window0.png");
    let _ = std::fs::remove_file(&path);
    let style = CurveStyle { window: 0, ..CurveStyle::default() };
    let err = training_curves_png(&learning_curve(10), &style, &path).unwrap_err();
    assert!(matches!(err, PlotError::Invalid { .. }), "{err}");
    assert!(!path.exists());
}

#[test]
fn default_style_is_matlabs_window_50() {
    let s = CurveStyle::default();
    assert_eq!(s.window, 50);
    assert!(s.title.is_empty() && s.footer.is_empty() && s.return_goal.is_none() && s.steps_goal.is_none());
}

#[test]
fn learning_curve_picture_shows_the_rising_average_in_both_panels() {
    // A folder of its own: the other tests write their pictures beside each other at once.
    let path = out("learning-curve/curves.png");
    let style = CurveStyle {
        title: "env1 SAC — order-50 moving average".into(),
        return_goal: Some(320.0),
        steps_goal: Some(990.0),
        footer: "synthetic learning curve, 600 episodes".into(),
        ..CurveStyle::default()
    };
    training_curves_png(&learning_curve(600), &style, &path).unwrap();
    let left: Vec<_> = std::fs::read_dir(path.parent().unwrap()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(left, ["curves.png"], "temp file renamed away");
    let img = Decoded::open(&path);
    assert_eq!((img.width, img.height), (WIDTH_PX, HEIGHT_PX));
    assert_eq!((img.width, img.height), (1000, 700));

    for (name, rows) in [("return", RETURN_ROWS), ("steps", STEPS_ROWS)] {
        let hits = img.find(AVERAGE_RGB, PLOT_X, rows.clone());
        assert!(hits.len() > 500, "{name} panel: bold average line drawn ({} pixels)", hits.len());
        // Curve rises: the line sits lower in the picture (larger y) early than late.
        let mean_y = |xs: std::ops::Range<u32>| {
            let ys: Vec<f64> = hits.iter().filter(|(x, _)| xs.contains(x)).map(|&(_, y)| y as f64).collect();
            assert!(!ys.is_empty(), "{name}: average drawn in columns {xs:?}");
            ys.iter().sum::<f64>() / ys.len() as f64
        };
        let (early, late) = (mean_y(100..160), mean_y(880..960));
        assert!(early > late + 50.0, "{name}: average rises from y {early} to y {late}");
        // The dashed goal line crosses the panel.
        let goal = img.find(GOAL_RGB, PLOT_X, rows);
        assert!(goal.len() > 200, "{name}: goal line drawn ({} pixels)", goal.len());
    }
    // The goal labels ("goal ≥ 320") in red above the right end of each goal line.
    for (name, rows) in [("return", RETURN_ROWS), ("steps", STEPS_ROWS)] {
        let line = img.find(GOAL_RGB, 100..800, rows.clone());
        let line_y = line.iter().map(|&(_, y)| y).min().unwrap();
        // Anti-aliased text: red-dominated pixels, not only the exact colour.
        let label = (rows.start..line_y - 2).flat_map(|y| (860..971).map(move |x| (x, y))).filter(|&(x, y)| {
            let [r, g, b] = img.rgb(x, y);
            r > 150 && g < 150 && b < 150 && r > g + 60
        });
        let n = label.count();
        assert!(n > 40, "{name}: goal label ({n} pixels)");
    }
    // Axes: tick labels left of and below both panels, axis titles, the title and captions.
    for (name, rows) in [("return", RETURN_ROWS), ("steps", STEPS_ROWS)] {
        assert!(text_pixels(&img, 40..92, rows.clone()) > 60, "{name}: y tick labels");
        assert!(text_pixels(&img, PLOT_X, rows.end + 6..rows.end + 24) > 60, "{name}: x tick labels");
        assert!(text_pixels(&img, 8..30, rows.clone()) > 20, "{name}: y axis title");
        assert!(text_pixels(&img, 96..300, rows.start - 26..rows.start - 2) > 60, "{name}: caption");
    }
    assert!(text_pixels(&img, 480..600, 640..660) > 20, "x axis title");
    assert!(text_pixels(&img, 20..400, 10..40) > 100, "title");
    // Outside the plot areas (left margin below the title) the picture is white.
    assert_eq!(img.rgb(5, 200), [255, 255, 255]);
}

#[test]
fn non_finite_points_do_not_panic() {
    let mut pts = learning_curve(100);
    pts[10].episode_return = f64::NAN;
    pts[11].episode_return = f64::INFINITY;
    pts[50].episode_return = f64::NEG_INFINITY;
    let path = out("nan.png");
    training_curves_png(&pts, &CurveStyle { return_goal: Some(f64::NAN), ..CurveStyle::default() }, &path).unwrap();
    let img = Decoded::open(&path);
    assert_eq!((img.width, img.height), (1000, 700));
    assert!(!img.find(AVERAGE_RGB, PLOT_X, RETURN_ROWS).is_empty());
    // All returns non-finite, and the many-points path too.
    let all_nan: Vec<CurvePoint> = (1..=3000).map(|e| CurvePoint { episode: e, episode_return: f64::NAN, steps: 5 }).collect();
    training_curves_png(&all_nan, &CurveStyle::default(), &out("all-nan.png")).unwrap();
    let img = Decoded::open(&out("all-nan.png"));
    assert!(img.find(AVERAGE_RGB, PLOT_X, RETURN_ROWS).is_empty(), "no average line where no value is finite");
    assert!(!img.find(NOTE_RGB, 400..700, 180..210).is_empty(), "'no finite values' in the return panel");
    assert!(img.find(AVERAGE_RGB, PLOT_X, STEPS_ROWS).len() > 500, "steps are still drawn");
    // Extreme finite values.
    let extreme = [CurvePoint { episode: 1, episode_return: f64::MAX, steps: 0 }, CurvePoint { episode: 2, episode_return: -f64::MAX, steps: u32::MAX }];
    training_curves_png(&extreme, &CurveStyle::default(), &out("extreme.png")).unwrap();
}

#[test]
fn empty_input_draws_empty_axes() {
    let path = out("empty.png");
    let style = CurveStyle { title: "no data".into(), return_goal: Some(320.0), ..CurveStyle::default() };
    training_curves_png(&[], &style, &path).unwrap();
    let img = Decoded::open(&path);
    assert_eq!((img.width, img.height), (1000, 700));
    // Only the legend swatch (above the plot area) carries the average colour.
    assert!(img.find(AVERAGE_RGB, PLOT_X, RETURN_ROWS).is_empty(), "no data line");
    assert!(!img.find(AVERAGE_RGB, 700..971, 50..80).is_empty(), "legend swatch");
    // "no episodes yet" in grey in the middle of each panel.
    assert!(!img.find(NOTE_RGB, 400..700, 180..210).is_empty(), "message in the return panel");
    assert!(!img.find(NOTE_RGB, 400..700, 480..510).is_empty(), "message in the steps panel");
    // Axes with tick labels even without data.
    assert!(text_pixels(&img, 40..92, RETURN_ROWS) > 60 && text_pixels(&img, PLOT_X, 316..334) > 60);
    // A single episode works too: its dot is drawn.
    training_curves_png(&[CurvePoint { episode: 1, episode_return: 3.0, steps: 7 }], &CurveStyle::default(), &out("one.png")).unwrap();
    let img = Decoded::open(&out("one.png"));
    let bluish = |(x, y): (u32, u32)| {
        let p = img.rgb(x, y);
        p[2] > 200 && u16::from(p[2]) > u16::from(p[0]) + 20
    };
    assert!(PLOT_X.flat_map(|x| RETURN_ROWS.map(move |y| (x, y))).any(bluish), "the one episode's dot");
    assert!(img.find(AVERAGE_RGB, 960..975, RETURN_ROWS).len() >= 4, "its average, a dot on the axis' end");
}

#[test]
fn a_hundred_thousand_episodes_are_downsampled() {
    let pts = learning_curve(100_000);
    let path = out("long.png");
    let t = std::time::Instant::now();
    training_curves_png(&pts, &CurveStyle { title: "100000 episodes".into(), ..CurveStyle::default() }, &path).unwrap();
    eprintln!("100k episodes drawn in {:?}", t.elapsed());
    let img = Decoded::open(&path);
    for rows in [RETURN_ROWS, STEPS_ROWS] {
        assert!(img.find(AVERAGE_RGB, PLOT_X, rows).len() > 500);
    }
    // The raw envelope covers the panel: light-blue-ish pixels across most columns.
    let bluish = |x: u32, y: u32| {
        let p = img.rgb(x, y);
        p[2] > 200 && p[0] < 215 && p[2] > p[0] + 20
    };
    let covered = PLOT_X.filter(|&x| RETURN_ROWS.clone().any(|y| bluish(x, y))).count();
    assert!(covered > 800, "raw values drawn across the width ({covered} columns)");
}
