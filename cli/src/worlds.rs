//! `mapless worlds generate | show`: the procedural worlds of `mapless_sim::worlds` as files
//! and pictures.

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Subcommand;
use mapless_plots::{Canvas, contact_sheet_png, default_px_per_m};
use mapless_sim::worlds::{DRIVABLE_CELL_M, DRIVE_CLEARANCE_M, DrivableSpace, Family, Split, generate};
use mapless_sim::{Map, VehicleConfig};

#[derive(Subcommand)]
pub enum WorldsCmd {
    /// List the families of generated worlds.
    List,
    /// Write one generated world as a ROS map_server map (FAMILY-SEED.yaml + .pgm), a picture
    /// (.png) and, where it has one, its vector form (.vector.yaml, with the shaded regions).
    Generate {
        /// rooms, cave, hall, forest or field.
        #[arg(long)]
        family: String,
        #[arg(long)]
        seed: u64,
        /// Output folder.
        #[arg(long)]
        out: PathBuf,
        /// Metres per pixel of the ROS map.
        #[arg(long, default_value_t = 0.05)]
        resolution: f64,
    },
    /// Draw a contact sheet of a family: one small picture per seed.
    Show {
        #[arg(long)]
        family: String,
        /// Seeds A..B (B excluded).
        #[arg(long, default_value = "0..12", value_parser = parse_seeds)]
        seeds: Range<u64>,
        /// Pictures per row.
        #[arg(long, default_value_t = 4)]
        columns: usize,
        #[arg(long)]
        out: PathBuf,
    },
}

/// `A..B` as a range of seeds (B excluded, at most 100 seeds).
pub fn parse_seeds(s: &str) -> Result<Range<u64>, String> {
    let (a, b) = s.split_once("..").ok_or_else(|| format!("`{s}`: seeds are a range A..B, e.g. 0..12"))?;
    let (a, b) = (a.trim().parse::<u64>().map_err(|e| format!("`{a}`: {e}"))?, b.trim().parse::<u64>().map_err(|e| format!("`{b}`: {e}"))?);
    if b <= a || b - a > 100 {
        return Err(format!("`{s}`: need A < B and at most 100 seeds"));
    }
    Ok(a..b)
}

pub fn run(cmd: WorldsCmd) -> Result<()> {
    match cmd {
        WorldsCmd::List => {
            for f in Family::ALL {
                let (lo, hi) = f.size_range_m();
                println!("{:<7} {lo:>2.0}–{hi:<2.0} m  {}", f.name(), f.describe());
            }
            println!(
                "(name one anywhere a map is named as gen:FAMILY:SEED; training worlds are seeds below {}, held-out ones (what evaluations report) start there, validation ones (what a run judges itself by while training) at {})",
                Split::HeldOut.seed(0)?,
                Split::Validation.seed(0)?
            );
            Ok(())
        }
        WorldsCmd::Generate { family, seed, out, resolution } => generate_cmd(&family, seed, &out, resolution),
        WorldsCmd::Show { family, seeds, columns, out } => show(&family, seeds, columns, &out),
    }
}

/// One line on a world: size, obstacles, drivable share, and how much of it is dead ends the
/// default car (which cannot reverse) could drive into but not turn round in.
fn summary(map: &Map, space: &DrivableSpace, dead_share: f64) -> String {
    let things = if map.grid.is_some() { "grid".to_string() } else { format!("{} obstacles, {} shaded", map.obstacles.len(), map.shaded.len()) };
    format!(
        "{:.1} m × {:.1} m, {things}, {:.0} m² drivable ({:.0} %) in one piece, {:.1} % of it in dead ends too narrow to turn round in",
        map.bounds.width(),
        map.bounds.height(),
        space.area_m2(),
        100.0 * space.share(),
        100.0 * dead_share
    )
}

fn generate_cmd(family: &str, seed: u64, out: &Path, resolution: f64) -> Result<()> {
    let map = generate(Family::parse(family)?, seed)?;
    let yaml = map.write_ros(out, resolution)?;
    let png = out.join(format!("{}.png", map.name));
    let title = format!("{} — {:.1} m × {:.1} m", map.name, map.bounds.width(), map.bounds.height());
    let mut c = Canvas::map(&map, default_px_per_m(&map), &title)?;
    let space = DrivableSpace::of(&map, DRIVE_CLEARANCE_M, DRIVABLE_CELL_M);
    let line = summary(&map, &space, space.dead_end_share(&VehicleConfig::default()));
    c.footer(&line)?;
    c.save_png(&png)?;
    println!("wrote {} (+ .pgm) and {}", yaml.display(), png.display());
    if let Some(text) = map.to_vector_yaml() {
        let v = out.join(format!("{}.vector.yaml", map.name));
        std::fs::write(&v, text).with_context(|| format!("writing {}", v.display()))?;
        println!("wrote {} (vector form, with shaded regions)", v.display());
    }
    println!("{}: {line}", map.name);
    Ok(())
}

fn show(family: &str, seeds: Range<u64>, columns: usize, out: &Path) -> Result<()> {
    let f = Family::parse(family)?;
    if columns == 0 {
        bail!("--columns must be ≥ 1");
    }
    let mut tiles = Vec::new();
    let mut dead_sum = 0.0;
    for seed in seeds.clone() {
        let map = generate(f, seed)?;
        // Every world at the same scale, so their sizes compare.
        let mut c = Canvas::map(&map, 600.0 / 60.0, &format!("{} ({:.0} m)", map.name, map.bounds.width()))?;
        let space = DrivableSpace::of(&map, DRIVE_CLEARANCE_M, DRIVABLE_CELL_M);
        let dead = space.dead_end_share(&VehicleConfig::default());
        c.footer(&format!("{:.0} % drivable, {:.1} % of it dead ends", 100.0 * space.share(), 100.0 * dead))?;
        println!("{}: {}", map.name, summary(&map, &space, dead));
        dead_sum += dead;
        tiles.push(c);
    }
    println!("{f}: {:.2} % of the drivable space in dead ends on average (a dead end: a passage too narrow for the car to turn round in that leads nowhere)", 100.0 * dead_sum / tiles.len() as f64);
    let title = format!("{f} worlds, seeds {}..{} — {}", seeds.start, seeds.end, f.describe());
    contact_sheet_png(&tiles, columns, 0.5, &title, out)?;
    println!("wrote {} ({} worlds)", out.display(), tiles.len());
    Ok(())
}
