"""Benchmark of the road frame's per-tick conversions (`python -m vcfusion.traffic.bench`).

Prints the median time of one call for N points (default 100, about the twins of a dense tick)
on the straight road (today's `Road` and the frame of the same network) and on the curved and
on-ramp networks: world -> (s, d), world -> (s, d, lane) in one pass, and (s, d) -> world.
Points lie on the road, spread over its length and lanes. Run on a quiet machine.
"""

from __future__ import annotations

import argparse

import numpy as np

from vcfusion.bench import median_us
from vcfusion.resources import networks_dir
from vcfusion.traffic.network import read_road
from vcfusion.traffic.roadframe import RoadFrame

CASES = (("highway", None), ("curved", None), ("onramp", ("main_in", "accel", "main_out")))


def run_bench(n_points: int = 100, repeats: int = 3000) -> str:
    rng = np.random.default_rng(0)
    lines = [f"road frame, one call for {n_points} points (median of {repeats}, microseconds)"]
    road = read_road(networks_dir() / "highway.net.xml")
    s = rng.uniform(0.0, road.length_m, n_points)
    x, y = road.to_world(s, rng.uniform(0.0, road.width_m, n_points))
    t_road = median_us(lambda: road.to_road_frame(x, y), repeats)
    t_road_lane = median_us(lambda: road.locate(x, y), repeats)
    lines.append(f"  Road (straight, closed form) to_frame {t_road:7.1f}   +lane {t_road_lane:7.1f}")
    for name, route in CASES:
        frame = RoadFrame.from_net(networks_dir() / f"{name}.net.xml", route)
        s = rng.uniform(0.0, frame.length_m, n_points)
        track = rng.integers(1 if name == "onramp" else 0, frame.num_tracks, n_points)
        x, y = frame.to_world(s, frame.lane_centre_d(track, s))
        t_frame = median_us(lambda: frame.to_frame(x, y), repeats)
        t_locate = median_us(lambda: frame.locate(x, y), repeats)
        sd = frame.to_frame(x, y)
        t_world = median_us(lambda: frame.to_world(*sd), repeats)
        lines.append(f"  RoadFrame {name:<17} to_frame {t_frame:7.1f}   +lane {t_locate:7.1f}   "
                     f"to_world {t_world:7.1f}   ({len(frame._P) - 1} segments)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3000)
    args = parser.parse_args(argv)
    print(run_bench(args.points, args.repeats))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
