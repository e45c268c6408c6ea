"""The vehicle-to-cloud (V2C) uplink: GNSS error, latency, jitter and loss.

Every V2C period each vehicle measures its state and sends a report stamped with the
measurement time. A report arrives after `latency + jitter` (jitter: a zero-mean Gaussian
with std `jitter_s`, the total clipped at 0), or never, with probability `loss_probability`.
GNSS error is an independent zero-mean Gaussian of std `gnss_noise_std_m` on each horizontal
axis of the antenna position. Times are kept as integer microseconds so that "arrived by t"
is exact.
"""

from __future__ import annotations

import numpy as np

from vcfusion.records import GnssReports, VehicleStates, add_gnss_error, gnss_antenna_points
from vcfusion.scenario import V2CConfig

_US = 1_000_000


def to_us(t: float | np.ndarray) -> np.ndarray:
    # rint: np.round's rounding (half to even) without its dispatch, on the per-tick path
    return np.rint(np.asarray(t, dtype=float) * _US).astype(np.int64)


class V2CChannel:
    def __init__(self, config: V2CConfig, rng: np.random.Generator):
        self.config = config
        self.rng = rng
        self._in_flight: list[tuple[np.ndarray, GnssReports]] = []  # (arrival_us, reports)
        self.sent = 0
        self.lost = 0

    def measure(self, states: VehicleStates) -> GnssReports:
        """GNSS reports of all vehicles at states.time (error applied)."""
        n = len(states)
        antenna = add_gnss_error(gnss_antenna_points(states.x, states.y, states.z, states.height),
                                 self.config.gnss_noise_std_m, self.rng)
        return GnssReports(
            measured_time=np.full(n, states.time),
            ids=states.ids,
            x=antenna[:, 0], y=antenna[:, 1], z=antenna[:, 2],
            heading=states.heading.copy(), speed=states.speed.copy(), accel=states.accel.copy(),
            length=states.length, width=states.width, height=states.height,
        )

    def send(self, reports: GnssReports) -> None:
        n = len(reports)
        if n == 0:
            return
        cfg = self.config
        self.sent += n
        # the common ideal channel (no loss, no jitter) skips the per-report draws
        keep = self.rng.random(n) >= cfg.loss_probability if cfg.loss_probability > 0 else None
        delay = cfg.latency_s
        if cfg.jitter_s > 0:
            delay = np.maximum(np.full(n, delay) + self.rng.normal(0.0, cfg.jitter_s, size=n), 0.0)
        arrival = to_us(reports.measured_time + delay)
        if keep is None or keep.all():
            self._in_flight.append((arrival, reports))
            return
        self.lost += int(n - keep.sum())
        if keep.any():
            idx = np.flatnonzero(keep)
            self._in_flight.append((arrival[idx], reports.select(idx)))

    def deliver(self, now: float) -> list[GnssReports]:
        """Reports that have arrived by `now`, in sending order."""
        # to_us of a scalar without the array calls: the same product of doubles, and Python's
        # round() of a float is np.rint's (the nearest integer, half to even)
        now_us = round(float(now) * _US)
        arrived, still = [], []
        for arrival, batch in self._in_flight:
            done = arrival <= now_us
            if done.all():
                arrived.append(batch)
            elif done.any():
                arrived.append(batch.select(np.flatnonzero(done)))
                rest = np.flatnonzero(~done)
                still.append((arrival[rest], batch.select(rest)))
            else:
                still.append((arrival, batch))
        self._in_flight = still
        return arrived
