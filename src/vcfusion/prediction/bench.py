"""Benchmark of the cloud lane-change predictor: one tick for N twins (`vcfusion bench-predict`).

Prints the median time per tick of each step (features, MLP, smoothing) and of the whole
process model, plus torch inference of the same MLP on the same batch for comparison.
Run: `vcfusion bench-predict --twins 100` or `python -m vcfusion.prediction.bench`.
"""

from __future__ import annotations

import sys

import numpy as np

from vcfusion.bench import median_us
from vcfusion.records import TwinStates
from vcfusion.traffic.network import Road


def run_bench(n_twins: int = 100, repeats: int = 2000) -> str:
    from vcfusion.prediction.cloud import LaneChangePredictor
    from vcfusion.prediction.model import default_model_path, load_model

    road = Road("hw", (0.0, 0.0), (2000.0, 0.0), 3, 3.5, 25.0)
    model = load_model(default_model_path())
    rng = np.random.default_rng(0)
    lane = rng.integers(0, 3, n_twins).astype(np.int16)
    s = rng.uniform(0, 2000, n_twins)
    x, y = road.to_world(s, (lane + 0.5) * road.lane_width_m)
    twins = TwinStates(time=0.0, ids=tuple(f"veh{i:04d}" for i in range(n_twins)), measured_time=np.zeros(n_twins),
                       x=x, y=y, z=np.zeros(n_twins), heading=np.zeros(n_twins), speed=rng.uniform(0, 30, n_twins),
                       accel=rng.normal(0, 1, n_twins), lane=lane, length=np.full(n_twins, 4.6),
                       width=np.full(n_twins, 1.8), height=np.full(n_twins, 1.5), outputs={})
    predictor = LaneChangePredictor(model, road, 0.1)
    predictor(twins)  # warm-up, fills the per-twin memory
    features = predictor.extractor.from_twins(twins)
    prob = model.predict_proba(features)
    raw = (prob > predictor.threshold).astype(np.int8)
    t_features = median_us(lambda: predictor.extractor.from_twins(twins), repeats)
    t_mlp = median_us(lambda: model.predict_proba(features), repeats)
    t_smooth = median_us(lambda: predictor.smoother(twins.ids, raw), repeats)
    t_total = median_us(lambda: predictor(twins), repeats)
    lines = [f"lane-change predictor, {n_twins} twins per tick, median of {repeats} ticks "
             f"(model {default_model_path().name}, {len(model.feature_names)} features, "
             f"hidden {model.weights[0][0].shape[0]}):",
             f"  features (compiled)     {t_features:8.1f} us",
             f"  MLP, NumPy float32      {t_mlp:8.1f} us",
             f"  smoothing ({predictor.smoother.method:12s}) {t_smooth:5.1f} us",
             f"  whole process model     {t_total:8.1f} us per tick"]
    try:
        import torch

        torch.set_num_threads(1)
        module = model.to_torch().eval()
        xt = torch.from_numpy(((features - model.mean) / model.std).astype(np.float32))

        def torch_infer():
            with torch.inference_mode():
                torch.sigmoid(module(xt))

        lines.append(f"  MLP, torch (1 thread)   {median_us(torch_infer, repeats):8.1f} us  (for comparison)")
    except ImportError:
        pass
    return "\n".join(lines)


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 100
    print(run_bench(n))
