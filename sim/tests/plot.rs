//! Training-curve pictures: the moving average is MATLAB's trailing average, and the PNG shows
//! the bold average line where the data is.

use std::path::{Path, PathBuf};

use mapless_sim::SimError;
use mapless_sim::plot::{AVERAGE_RGB, CurvePoint, CurveStyle, GOAL_RGB, HEIGHT_PX, WIDTH_PX, moving_average, training_curves_png};

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
        let mut dec = png::Decoder::new(std::fs::File::open(path).unwrap());
        dec.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
        let mut reader = dec.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!(info.color_type, png::ColorType::Rgba, "tiny-skia writes RGBA");
        buf.truncate(info.buffer_size());
        Decoded { width: info.width, height: info.height, rgba: buf }
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

// Layout (see plot.rs): plot areas span x 92..972; the return panel y 68..303 and the steps
// panel y 362..597, each with its title and legend in the 22 px above it.
const PLOT_X: std::ops::Range<u32> = 93..971;
const RETURN_ROWS: std::ops::Range<u32> = 66..306;
const STEPS_ROWS: std::ops::Range<u32> = 360..600;

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

fn close(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x.is_nan() && y.is_nan()) || (x - y).abs() < 1e-9)
}

#[test]
fn moving_average_matches_hand_computed_values() {
    let v = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
    // Warm-up: 1, (1+2)/2, then full windows (1+2+3)/3, (2+3+4)/3 …
    assert!(close(&moving_average(&v, 3), &[1.0, 1.5, 2.0, 3.0, 4.0, 5.0]));
    assert!(close(&moving_average(&v, 1), &v), "window 1 is the values themselves");
    assert!(close(&moving_average(&v, 10), &[1.0, 1.5, 2.0, 2.5, 3.0, 3.5]), "window longer than the data: running mean");
    assert!(close(&moving_average(&[10.0, 0.0, 20.0, -10.0], 2), &[10.0, 5.0, 10.0, 5.0]));
    assert!(moving_average(&[], 50).is_empty());
    // Non-finite values are skipped; a window without finite values gives NaN.
    assert!(close(&moving_average(&[1.0, f64::NAN, 3.0, 5.0], 2), &[1.0, 1.0, 3.0, 4.0]));
    assert!(close(&moving_average(&[f64::NAN, f64::INFINITY, 2.0], 2), &[f64::NAN, f64::NAN, 2.0]));
}

#[test]
fn moving_average_of_a_long_series_does_not_drift() {
    let v: Vec<f64> = (0..100_000).map(|i| 1e6 + ((i * 7919) % 1000) as f64 * 0.001).collect();
    let w = 50;
    let fast = moving_average(&v, w);
    for i in [0usize, 1, 48, 49, 50, 12_345, 99_998, 99_999] {
        let lo = (i + 1).saturating_sub(w);
        let direct = v[lo..=i].iter().sum::<f64>() / (i + 1 - lo) as f64;
        assert!((fast[i] - direct).abs() < 1e-6, "entry {i}: {} vs {direct}", fast[i]);
    }
}

#[test]
fn window_zero_is_an_error_and_writes_nothing() {
    let path = out("window0.png");
    let _ = std::fs::remove_file(&path);
    let style = CurveStyle { window: 0, ..CurveStyle::default() };
    let err = training_curves_png(&learning_curve(10), &style, &path).unwrap_err();
    assert!(matches!(err, SimError::InvalidConfig(_)), "{err}");
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
    let path = out("curves.png");
    let style = CurveStyle {
        title: "env1 SAC — order-50 moving average".into(),
        return_goal: Some(320.0),
        steps_goal: Some(990.0),
        footer: "synthetic learning curve, 600 episodes".into(),
        ..CurveStyle::default()
    };
    training_curves_png(&learning_curve(600), &style, &path).unwrap();
    assert!(!path.with_extension("png.tmp").exists(), "temp file renamed away");
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
    assert!(img.find(AVERAGE_RGB, PLOT_X, RETURN_ROWS).len() < 100, "no average line where no value is finite (legend swatch only)");
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
    assert!(img.find(AVERAGE_RGB, PLOT_X, 70..300).is_empty(), "no data line");
    // "no episodes yet" in grey in the middle of each panel.
    assert!(!img.find([120, 120, 120], 400..700, 170..200).is_empty(), "message in the return panel");
    assert!(!img.find([120, 120, 120], 400..700, 465..495).is_empty(), "message in the steps panel");
    // A single episode works too.
    training_curves_png(&[CurvePoint { episode: 1, episode_return: 3.0, steps: 7 }], &CurveStyle::default(), &out("one.png")).unwrap();
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
