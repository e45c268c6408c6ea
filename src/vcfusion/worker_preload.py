"""Imported by the worker fork server (see vcfusion.workers), and only there: importing it loads
the run code and the compiled per-tick kernels (from numba's cache), so forked workers start warm.
It starts no SUMO simulation and no thread."""

import numpy as np

import vcfusion.run  # noqa: F401  (the run code and everything it imports)
from vcfusion.cloud.twins import TwinStore
from vcfusion.driver.perception import DriverView, visible_vehicles
from vcfusion.fusion.fuse import warm_depth_kernels
from vcfusion.guidance import GuidancePolicy
from vcfusion.prediction.features import FeatureExtractor
from vcfusion.prediction.smoothing import StreamingSmoother
from vcfusion.records import GnssReports
from vcfusion.scenario import V2CConfig
from vcfusion.traffic.network import Road

# One tiny call per kernel and argument type the tick loop uses loads its machine code.
_road = Road("warm-up", (0.0, 0.0), (100.0, 0.0), 2, 3.5, 25.0)
_ones = np.ones(2)
FeatureExtractor(_road, 0.1)(("a", "b"), np.array([10.0, 30.0]), np.array([0, 1], dtype=np.int16), _ones, _ones, _ones)
for _method in ("none", "aggressive", "conservative"):
    StreamingSmoother(_method, 2, 2)(("a", "b"), np.array([0, 1], dtype=np.int8))
_store = TwinStore(V2CConfig(), _road)
_store.ingest(GnssReports(measured_time=np.zeros(2), ids=("a", "b"), x=_ones, y=_ones, z=_ones, heading=_ones,
                          speed=_ones, accel=_ones, length=_ones, width=_ones, height=_ones))
_pos = np.array([10.0, 30.0])
visible_vehicles(_pos, _ones, _ones, _ones, _ones, 0, GuidancePolicy.on_road(_road, 0, 0.3, 0.6, 150.0),
                 DriverView())
warm_depth_kernels()  # the depth step's (vcfusion.fusion.box_refine, vcfusion.fusion.fuse)
