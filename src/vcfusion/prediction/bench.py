"""Benchmark of the cloud lane-change predictor: one tick for N twins (`vcfusion bench-predict`).

Prints the median time per tick of each step (features, model, smoothing) and of the whole
process model, plus torch inference of the same model on the same batch for comparison, for
the shipped default model and the other shipped kind (the MLP and the GRU sequence model).
Run: `vcfusion bench-predict --twins 100` or `python -m vcfusion.prediction.bench`.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np

from vcfusion.bench import median_us
from vcfusion.records import TwinStates
from vcfusion.traffic.network import Road


def _twins(n_twins: int, road: Road, rng: np.random.Generator, time: float = 0.0) -> TwinStates:
    lane = rng.integers(0, 3, n_twins).astype(np.int16)
    s = rng.uniform(0, 2000, n_twins)
    x, y = road.to_world(s, (lane + 0.5) * road.lane_width_m)
    return TwinStates(time=time, ids=tuple(f"veh{i:04d}" for i in range(n_twins)), measured_time=np.zeros(n_twins),
                      x=x, y=y, z=np.zeros(n_twins), heading=np.zeros(n_twins), speed=rng.uniform(0, 30, n_twins),
                      accel=rng.normal(0, 1, n_twins), lane=lane, length=np.full(n_twins, 4.6),
                      width=np.full(n_twins, 1.8), height=np.full(n_twins, 1.5), outputs={})


def bench_model(path, n_twins: int = 100, repeats: int = 2000) -> list[str]:
    """Median times of one tick of the process model with the model file `path` (MLP or GRU)."""
    from vcfusion.prediction.cloud import LaneChangePredictor
    from vcfusion.prediction.model import load_model

    road = Road("hw", (0.0, 0.0), (2000.0, 0.0), 3, 3.5, 25.0)
    model = load_model(path)
    twins = _twins(n_twins, road, np.random.default_rng(0))
    predictor = LaneChangePredictor(model, road, 0.1)
    predictor(twins)  # warm-up, fills the per-twin memory
    gru = model.kind == "gru"
    members = None
    flags = {"extras": gru, "availability": predictor.availability, "lateral": predictor.lateral,
             "sway": predictor.sway}  # the model's inputs
    features = predictor.extractor.from_twins(twins, **flags)
    if gru:
        ticks = iter(range(1, 10**9))  # each call one tick later: the per-twin states are carried, never reset
        prob = predictor.sequence(twins.ids, twins.time, features)
        step = lambda: predictor.sequence(twins.ids, 0.1 * next(ticks), features)  # noqa: E731
        members = getattr(model, "members", None)  # an ensemble of GRUs (vcfusion.prediction.ensemble)
        size = (f"GRU ensemble of {len(members)}, hidden {'/'.join(str(m.hidden) for m in members)}" if members
                else f"GRU, hidden {model.hidden}")
    else:
        prob = model.predict_proba(features)
        step = lambda: model.predict_proba(features)  # noqa: E731
        size = f"MLP, hidden {model.weights[0][0].shape[0]}"
    raw = (prob > predictor.threshold).astype(np.int8)
    t_features = median_us(lambda: predictor.extractor.from_twins(twins, **flags), repeats)
    t_model = median_us(step, repeats)
    t_smooth = median_us(lambda: predictor.smoother(twins.ids, raw), repeats)
    # one snapshot per tick, each 0.1 s later (built beforehand: the timing is the predictor's)
    snapshots = iter([dataclasses.replace(twins, time=0.1 * k) for k in range(10**5, 10**5 + 2 * repeats + 100)])
    t_total = median_us(lambda: predictor(next(snapshots)), repeats)
    lines = [f"lane-change predictor, {n_twins} twins per tick, median of {repeats} ticks "
             f"(model {Path(path).name}: {size}, {len(model.feature_names)} inputs):",
             f"  features (compiled)     {t_features:8.1f} us",
             f"  {'GRU step, NumPy f32' if gru else 'MLP, NumPy float32':22s}  {t_model:8.1f} us"
             + ("  (one step per twin, states carried" + (", each member's, probabilities averaged)"
                                                            if members else ")") if gru else ""),
             f"  smoothing ({predictor.smoother.method:12s}) {t_smooth:5.1f} us",
             f"  whole process model     {t_total:8.1f} us per tick"]
    if members:  # an ensemble has no single torch module to compare with
        return lines
    try:
        import torch

        torch.set_num_threads(1)
        if gru:
            cell, head = model.to_torch()
            xt = torch.from_numpy(((features - model.mean) / model.std).astype(np.float32))
            ht = torch.zeros(n_twins, model.hidden)

            def torch_infer():
                with torch.inference_mode():
                    torch.sigmoid(head(cell(xt, ht)))
        else:
            module = model.to_torch().eval()
            xt = torch.from_numpy(((features - model.mean) / model.std).astype(np.float32))

            def torch_infer():
                with torch.inference_mode():
                    torch.sigmoid(module(xt))

        lines.append(f"  {'GRU' if gru else 'MLP'}, torch (1 thread)   {median_us(torch_infer, repeats):8.1f} us  "
                     "(for comparison)")
    except ImportError:
        pass
    return lines


def run_bench(n_twins: int = 100, repeats: int = 2000, models=None) -> str:
    """The shipped default model first, then every other model shipped in vcfusion/assets, then
    the model files `models`."""
    from vcfusion.prediction.model import SHIPPED_MODEL_NAMES, default_model_path

    default = default_model_path()
    paths = [default] + [default.with_name(n) for n in SHIPPED_MODEL_NAMES
                         if n != default.name and default.with_name(n).is_file()] + [Path(m) for m in models or ()]
    lines = []
    for k, path in enumerate(paths):
        lines += bench_model(path, n_twins, repeats)
        if k == 0:
            lines[-len(lines)] += "  [default]"
    return "\n".join(lines)


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 100
    print(run_bench(n))
