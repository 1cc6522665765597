#!/usr/bin/env python3
"""Peer measurement for `mapless bench sim`: an F1TENTH-gym-style planar LiDAR on one core.

This file re-implements, for a side-by-side measurement, the method described in f1tenth_gym's
`gym/f110_gym/envs/laser_models.py` (github.com/f1tenth/f1tenth_gym, MIT licence). It mirrors
`get_dt`, `xy_2_rc` + `distance_transform`, `trace_ray`, `get_scan`, `ScanSimulator2D.set_map`
and `ScanSimulator2D.scan`, `check_ttc_jit`, and the per-beam side distances precomputed in
`base_classes.RaceCar.__init__`. It was written independently from a reading of that method;
no code was copied. Same data structures and per-ray work as the original:

- map: ROS map_server image flipped so that row index grows with y, binarised at 128 (0 =
  obstacle, 255 = free), then `scipy.ndimage.distance_transform_edt` times the resolution;
- beams: a 2000-entry sin/cos table over linspace(0, 2π) indexed by a float angle index that is
  advanced by a constant increment per beam and truncated to int (no per-beam trig);
- each ray: sphere tracing on the distance transform, eps = 1e-4 m, stop once past max range,
  result clamped to max range; a point outside the map reads the last cell, as there;
- every scan adds Gaussian noise with `numpy.random.Generator.normal` (σ = 0.1 m here, ours);
- the environment-collision check of a gym step: iTTC over the scan against the car's sides.

What one timed unit is, and why the comparison favours the peer: a gym step with one agent is
`RaceCar.update_pose` (dynamics + `ScanSimulator2D.scan`) then `RaceCar.update_scan`
(`check_ttc` + ray casting onto opponents, of which there are none). We time exactly the scan
(numba kernel called from Python, as the gym calls it), its noise, and the iTTC check: no
dynamics, no pose assembly, no observation dict, no reward, no resets. A mapless vehicle-step
does all of those (dynamics, footprint collision, reward, EQS, episode resets) on top of its
scan, so scans/s here is an upper bound on the peer's steps/s, i.e. a lower bound on the work
in one of our steps. Single core: NUMBA_NUM_THREADS=1, and nothing here is parallel.

Output: one JSON object per line, in `mapless bench sim --json`'s {bench, config, value, unit}
shape, for the same three presets (7 beams over 135°, 100 over 90°, 1080 over 270°, 12 m).
"""

import os

# Must be set before numba is imported; the shell runner sets them too.
for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import numba
import numpy as np
import scipy
from numba import njit
from scipy.ndimage import distance_transform_edt

# Our presets (sim/src/bench.rs SCAN_PRESETS) and our sensor (sim/src/config.rs SensorConfig).
PRESETS = [(7, 135.0), (100, 90.0), (1080, 270.0)]
MAX_RANGE_M = 12.0
NOISE_STD_M = 0.1
# f1tenth's ScanSimulator2D defaults.
THETA_DIS = 2000
EPS = 1e-4
# iTTC check: f1tenth's threshold; our car's footprint (0.55 m x 0.30 m) and top speed (0.5 m/s).
TTC_THRESH_S = 0.005
HALF_LENGTH_M, HALF_WIDTH_M = 0.275, 0.15
V_MAX_MPS = 0.5
METHOD = "f1tenth-style EDT ray marching (numba)"


# --- map loading -------------------------------------------------------------------------------

def read_map_yaml(path):
    """The flat `key: value` subset of YAML that map_server files use (no PyYAML needed)."""
    meta = {}
    for line in Path(path).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if ":" not in line:
            continue
        key, value = (s.strip() for s in line.split(":", 1))
        if value.startswith("["):
            meta[key] = [float(v) for v in value.strip("[]").split(",")]
        else:
            meta[key] = value
    return meta


def read_pgm(path):
    """A binary (P5) 8-bit PGM as a (height, width) uint8 array, row 0 = top of the image."""
    data = Path(path).read_bytes()
    fields, pos = [], 0
    while len(fields) < 4:  # magic, width, height, maxval; '#' starts a comment to end of line
        while data[pos:pos + 1].isspace():
            pos += 1
        if data[pos:pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end:end + 1].isspace():
            end += 1
        fields.append(data[pos:end])
        pos = end
    magic, width, height, maxval = fields[0], int(fields[1]), int(fields[2]), int(fields[3])
    if magic != b"P5" or maxval > 255:
        raise ValueError(f"{path}: only 8-bit binary PGM (P5) is supported")
    pos += 1  # the single whitespace byte after maxval
    return np.frombuffer(data, np.uint8, width * height, pos).reshape(height, width)


class DistanceMap:
    """The map as f1tenth's `set_map` prepares it: flipped, binarised, distance-transformed."""

    def __init__(self, yaml_path):
        meta = read_map_yaml(yaml_path)
        image = read_pgm(Path(yaml_path).parent / meta["image"])
        # Flip so that row r covers y in [origin_y + r*res, origin_y + (r+1)*res).
        img = image[::-1].astype(np.float64)
        img[img <= 128.0] = 0.0
        img[img > 128.0] = 255.0
        self.resolution = float(meta["resolution"])
        self.origin_x, self.origin_y, yaw = meta["origin"][:3]
        self.origin_c, self.origin_s = math.cos(yaw), math.sin(yaw)
        self.height, self.width = img.shape
        # Distance (m) from each free cell to the nearest obstacle cell; 0 on obstacles.
        self.dt = self.resolution * distance_transform_edt(img)


# --- the ray caster (numba) ----------------------------------------------------------------------

@njit(cache=False)
def clearance_at(x, y, orig_x, orig_y, orig_c, orig_s, height, width, resolution, dt):
    """Distance-transform value of the cell holding world point (x, y)."""
    # World frame -> map frame (undo the origin's translation and yaw).
    dx, dy = x - orig_x, y - orig_y
    mx = dx * orig_c + dy * orig_s
    my = -dx * orig_s + dy * orig_c
    if mx < 0.0 or my < 0.0 or mx >= width * resolution or my >= height * resolution:
        # Off the map the original indexes (-1, -1), i.e. the last cell; keep that behaviour.
        return dt[height - 1, width - 1]
    return dt[int(my / resolution), int(mx / resolution)]


@njit(cache=False)
def march_ray(x, y, theta_index, sines, cosines, eps, orig_x, orig_y, orig_c, orig_s,
              height, width, resolution, dt, max_range):
    """Range along one beam by sphere tracing: jump by the clearance until it drops below eps."""
    k = int(theta_index)
    dir_s, dir_c = sines[k], cosines[k]
    step = clearance_at(x, y, orig_x, orig_y, orig_c, orig_s, height, width, resolution, dt)
    travelled = step
    while step > eps and travelled <= max_range:
        x += step * dir_c
        y += step * dir_s
        step = clearance_at(x, y, orig_x, orig_y, orig_c, orig_s, height, width, resolution, dt)
        travelled += step
    return min(travelled, max_range)


@njit(cache=False)
def scan_ranges(pose, theta_dis, fov, num_beams, theta_index_increment, sines, cosines, eps,
                orig_x, orig_y, orig_c, orig_s, height, width, resolution, dt, max_range):
    """All beams of one scan, first beam at heading - fov/2, in the table's index space."""
    ranges = np.empty(num_beams)
    theta_index = np.fmod(theta_dis * (pose[2] - fov / 2.0) / (2.0 * np.pi), theta_dis)
    while theta_index < 0.0:
        theta_index += theta_dis
    for i in range(num_beams):
        ranges[i] = march_ray(pose[0], pose[1], theta_index, sines, cosines, eps, orig_x, orig_y,
                              orig_c, orig_s, height, width, resolution, dt, max_range)
        theta_index += theta_index_increment
        while theta_index >= theta_dis:
            theta_index -= theta_dis
    return ranges


@njit(cache=False)
def ittc_collision(ranges, vel, beam_cosines, side_distances, ttc_thresh):
    """True if some beam's time to reach the car's outline is in [0, ttc_thresh)."""
    if vel == 0.0:
        return False
    for i in range(ranges.shape[0]):
        ttc = (ranges[i] - side_distances[i]) / (vel * beam_cosines[i])
        if 0.0 <= ttc < ttc_thresh:
            return True
    return False


class EdtLidar:
    """Counterpart of f1tenth's ScanSimulator2D (+ RaceCar's iTTC tables) for one preset."""

    def __init__(self, dmap, num_beams, fov_rad, std_dev, max_range, seed):
        self.map = dmap
        self.num_beams = num_beams
        self.fov = fov_rad
        self.std_dev = std_dev
        self.max_range = max_range
        self.theta_dis = THETA_DIS
        self.eps = EPS
        angle_increment = fov_rad / (num_beams - 1)
        self.theta_index_increment = THETA_DIS * angle_increment / (2.0 * np.pi)
        # Like the original: num points over [0, 2π] inclusive, indexed as if spaced 2π/num.
        table = np.linspace(0.0, 2.0 * np.pi, num=THETA_DIS)
        self.sines, self.cosines = np.sin(table), np.cos(table)
        self.rng = np.random.default_rng(seed)
        # iTTC tables, per beam angle relative to the heading: cos, and the distance from the
        # sensor (car centre) to the car's rectangular outline along the beam.
        angles = -fov_rad / 2.0 + angle_increment * np.arange(num_beams)
        self.beam_cosines = np.cos(angles)
        with np.errstate(divide="ignore"):
            self.side_distances = np.minimum(HALF_WIDTH_M / np.abs(np.sin(angles)),
                                             HALF_LENGTH_M / np.abs(np.cos(angles)))

    def scan(self, pose):
        """One noisy scan, called per step from Python exactly as the gym calls it."""
        m = self.map
        ranges = scan_ranges(pose, self.theta_dis, self.fov, self.num_beams,
                             self.theta_index_increment, self.sines, self.cosines, self.eps,
                             m.origin_x, m.origin_y, m.origin_c, m.origin_s, m.height, m.width,
                             m.resolution, m.dt, self.max_range)
        return ranges + self.rng.normal(0.0, self.std_dev, size=self.num_beams)

    def in_collision(self, ranges, vel):
        return ittc_collision(ranges, vel, self.beam_cosines, self.side_distances, TTC_THRESH_S)


# --- measurement ---------------------------------------------------------------------------------

def random_free_poses(dmap, count, clearance_m, seed):
    """Poses (x, y, heading) at cell centres with at least `clearance_m` to any obstacle."""
    rng = np.random.default_rng(seed)
    rows, cols = np.nonzero(dmap.dt >= clearance_m)
    if rows.size == 0:
        raise SystemExit(f"no free cell with {clearance_m} m clearance")
    pick = rng.integers(0, rows.size, size=count)
    mx = (cols[pick] + 0.5) * dmap.resolution
    my = (rows[pick] + 0.5) * dmap.resolution
    x = dmap.origin_x + mx * dmap.origin_c - my * dmap.origin_s
    y = dmap.origin_y + mx * dmap.origin_s + my * dmap.origin_c
    heading = rng.uniform(0.0, 2.0 * np.pi, size=count)
    # One contiguous array per pose, so the timed loop does no slicing.
    return [np.array(p) for p in np.stack([x, y, heading], axis=1)], rng.uniform(0.0, V_MAX_MPS, count)


def measure(lidar, poses, speeds, seconds):
    """Scans (+ noise + iTTC) per second, cycling through the poses for about `seconds`."""
    n, i, done = len(poses), 0, 0
    start = time.perf_counter()
    deadline = start + seconds
    while True:
        for _ in range(32):  # read the clock every few scans only
            ranges = lidar.scan(poses[i])
            lidar.in_collision(ranges, speeds[i])
            i = i + 1 if i + 1 < n else 0
        done += 32
        now = time.perf_counter()
        if now >= deadline:
            return done, now - start


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map-yaml", required=True, help="ROS map_server YAML (e.g. from `mapless maps rasterize`)")
    ap.add_argument("--map-name", help="name for the JSON config (default: the YAML's stem)")
    ap.add_argument("--seconds", type=float, default=3.0, help="timed seconds per preset (ours: 3)")
    ap.add_argument("--poses", type=int, default=4096, help="precomputed random free poses")
    ap.add_argument("--clearance", type=float, default=0.35, help="min obstacle distance of a pose (m)")
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()

    print(f"# python {platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}, "
          f"numba {numba.__version__}, NUMBA_NUM_THREADS={numba.config.NUMBA_NUM_THREADS}", file=sys.stderr)
    name = args.map_name or Path(args.map_yaml).stem
    dmap = DistanceMap(args.map_yaml)
    poses, speeds = random_free_poses(dmap, args.poses, args.clearance, args.seed)

    for beams, fov_deg in PRESETS:
        lidar = EdtLidar(dmap, beams, math.radians(fov_deg), NOISE_STD_M, MAX_RANGE_M, args.seed)
        # Warm-up outside the timing: JIT compile (first preset) and touch every pose once.
        for pose, vel in zip(poses, speeds):
            lidar.in_collision(lidar.scan(pose), vel)
        scans, seconds = measure(lidar, poses, speeds, args.seconds)
        print(json.dumps({
            "bench": "peer.f1tenth_scan_per_s",
            "config": {"map": name, "beams": beams, "fov_deg": round(fov_deg), "method": METHOD,
                       "threads": 1, "seconds": seconds},
            "value": round(scans / seconds),
            "unit": "scans/s",
        }), flush=True)


if __name__ == "__main__":
    main()
