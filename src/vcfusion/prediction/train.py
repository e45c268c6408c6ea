"""Training of the lane-change MLP (and the logistic-regression baseline) on a dataset.

- Data: the Fig. 5 window samples (window_label >= 0) of the training seeds; optionally
  `background_negatives` x as many extra negatives drawn from ticks outside the windows that
  are not within tau + tau_g of a lane change (the paper's windows never show the model a
  vehicle that does not change lanes; this option does).
- Inputs standardised with the training mean/std; the class balance is handled by weighting
  positives by n_negative / n_positive in the loss.
- Adam, mini-batches, early stopping on the validation seeds' window loss (best epoch kept).
- Seeded (torch, NumPy) and single-threaded by default, so a run is reproducible.
- Afterwards the output is calibrated (Platt scaling on the validation seeds' every-tick
  stream, so `lc_prob` is P(lane change ends within tau) there) and the run-time decision settings (probability threshold, tau_a, tau_c) are chosen
  on the validation seeds' every-tick stream (see :func:`tune_decisions`) and stored in the file.
"""

from __future__ import annotations

import time as wallclock
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.prediction.dataset import DatasetError, DatasetInfo, load_dataset, load_samples
from vcfusion.prediction.events import event_scores, judged_ticks, smooth_stream, smoothing_bounds, track_bounds
from vcfusion.prediction.events import false_alarm_rate as rate_of
from vcfusion.prediction.model import LaneChangeModel, build_torch_mlp, feature_scaling, fit_platt, save_model

# Run-time settings searched on the validation stream. Thresholds are calibrated probabilities
# of a lane change ending within tau (the stream's base rate is ~11%), on a 0.01 grid.
THRESHOLDS = tuple(float(t) for t in np.round(np.arange(0.05, 0.995, 0.01), 2)) + (0.995, 0.998, 0.999)
# Algorithm 3 holds a positive for tau_a more ticks; at most tau: a positive means "the change
# ends within tau s", so holding it longer would flag vehicles whose predicted change is over.
TAU_A_TICKS = (0, 10, 20, 30, 40, 50)
TAU_C_TICKS = (5, 10, 20, 30)
MAX_FALSE_ALARMS_PER_VH = 2.0


@dataclass(frozen=True)
class TrainConfig:
    hidden: int = 64
    epochs: int = 60
    patience: int = 8
    batch_size: int = 512
    learning_rate: float = 1e-3
    weight_decay: float = 1e-5
    seed: int = 0
    background_negatives: float = 0.0
    threads: int = 1
    kind: str = "mlp"  # mlp | logistic
    privileged: bool = False  # also SUMO's lane-change state (the ceiling; needs a --privileged dataset)
    horizon_s: float = 10.0


def training_rows(info: DatasetInfo, split: str, background: float, rng: np.random.Generator) -> pd.DataFrame:
    df = load_samples(info, split)
    windows = df[df["window_label"] >= 0]
    if background > 0:
        far = df[(df["window_label"] < 0) & ~(df["time_to_lc"] <= 2 * info.tau + info.tau_g)]
        n = min(len(far), int(round(background * len(windows))))
        far = far.iloc[np.sort(rng.choice(len(far), size=n, replace=False))].assign(window_label=0)
        windows = pd.concat([windows, far], ignore_index=True)
    return windows


def _fit_torch(x_tr, y_tr, x_va, y_va, cfg: TrainConfig, n_features: int, progress: bool = False):
    import torch

    torch.manual_seed(cfg.seed)
    torch.set_num_threads(max(1, cfg.threads))
    if cfg.kind == "mlp":
        module = build_torch_mlp(n_features, cfg.hidden)
    else:
        module = torch.nn.Sequential(torch.nn.Linear(n_features, 1))
    n_pos = max(1.0, float(y_tr.sum()))
    pos_weight = torch.tensor([(len(y_tr) - n_pos) / n_pos], dtype=torch.float32)
    loss_fn = torch.nn.BCEWithLogitsLoss(pos_weight=pos_weight)
    opt = torch.optim.Adam(module.parameters(), lr=cfg.learning_rate, weight_decay=cfg.weight_decay)
    xt, yt = torch.from_numpy(x_tr), torch.from_numpy(y_tr)
    xv, yv = torch.from_numpy(x_va), torch.from_numpy(y_va)
    gen = torch.Generator().manual_seed(cfg.seed)
    best, best_state, best_epoch, stale = np.inf, None, 0, 0
    history = []
    from tqdm import tqdm

    bar = tqdm(range(cfg.epochs), desc=f"train {cfg.kind}", unit="epoch", disable=not progress, leave=False)
    for epoch in bar:
        module.train()
        perm = torch.randperm(len(xt), generator=gen)
        for k in range(0, len(xt), cfg.batch_size):
            idx = perm[k:k + cfg.batch_size]
            opt.zero_grad()
            loss = loss_fn(module(xt[idx])[:, 0], yt[idx])
            loss.backward()
            opt.step()
        module.eval()
        with torch.no_grad():
            val = float(loss_fn(module(xv)[:, 0], yv))
        history.append(val)
        bar.set_postfix(val_loss=f"{val:.4f}")
        if val < best - 1e-5:
            best, best_epoch, stale = val, epoch, 0
            best_state = {k: v.clone() for k, v in module.state_dict().items()}
        else:
            stale += 1
            if stale >= cfg.patience:
                break
    module.load_state_dict(best_state)
    layers = [m for m in module if isinstance(m, torch.nn.Linear)]
    weights = [(l.weight.detach().numpy().copy(), l.bias.detach().numpy().copy()) for l in layers]
    return weights, {"best_epoch": best_epoch, "epochs_run": len(history), "best_val_loss": best}


def stream_with_events(info: DatasetInfo, split: str, columns: list[str] | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The every-tick samples of a split sorted by (seed, vehicle, time), and its lane-change events."""
    from vcfusion.prediction.labels import event_end_times

    stream = load_samples(info, split, columns=columns)
    stream = stream.sort_values(["seed", "vehicle_id", "time"], kind="stable").reset_index(drop=True)
    frames = []
    for seed in info.seeds(split):
        ev = pd.read_parquet(info.run_folder(seed) / "lane_changes.parquet")
        if len(ev):
            half = float(info.meta.get("lanechange_end_after_mid_s", 1.5))
            frames.append(pd.DataFrame({"seed": seed, "event_id": ev["event_id"].to_numpy(),
                                        "vehicle_id": ev["vehicle_id"].astype(str).to_numpy(),
                                        "end": event_end_times(ev, half), "mid": ev["mid_time"].to_numpy(),
                                        "reason": ev["reason"].to_numpy()}))
    events = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(
        columns=["seed", "event_id", "vehicle_id", "end", "mid", "reason"])
    return stream, events


SEED_STRIDE = 1_000_000  # when datasets are mixed, dataset k's seeds become k * SEED_STRIDE + seed


def load_datasets(datasets: list[Path]) -> list[DatasetInfo]:
    """The dataset folders a model is trained on (several = scenario families mixed). They must
    share the labels (tau, tau_g), the V2C period and the features, and each have train and
    validation seeds."""
    from vcfusion.prediction.features import FEATURE_NAMES

    if not datasets:
        raise DatasetError("expected at least one dataset folder")
    infos = [load_dataset(d) for d in datasets]
    for d, info in zip(datasets, infos):
        if tuple(info.feature_names) != FEATURE_NAMES:
            raise DatasetError(f"{d}: built with other features than this version computes; bring it up to date "
                               "with `vcfusion dataset ... --refeature`")
        for split in ("train", "validation"):
            if not info.splits.get(split):
                raise DatasetError(f"{d}: split {split!r} is empty (build the dataset from at least 3 seeds)")
        first = infos[0]
        for key in ("tau", "tau_g", "period_s"):
            if getattr(info, key) != getattr(first, key):
                raise DatasetError(f"{d}: {key} = {getattr(info, key)}, but {datasets[0]} has {getattr(first, key)}; "
                                   "datasets trained on together need the same labels and V2C period")
    if len({Path(d).resolve() for d in datasets}) != len(datasets):
        raise DatasetError("the same dataset folder is given twice")
    return infos


def require_both_labels(labels: np.ndarray, split: str, hint: str = "") -> None:
    """DatasetError unless the split's training rows hold positive and negative windows: fitting,
    early stopping and calibration need both (a split without a lane change crashed the training)."""
    positive = int(np.count_nonzero(labels))
    if positive == 0 or positive == len(labels):
        raise DatasetError(f"split {split!r}: {positive} positive and {len(labels) - positive} negative windows in "
                           "the datasets given; training needs both (a lane change in its seeds): build the "
                           f"dataset from more or longer runs{hint}")


def combined_stream(infos: list[DatasetInfo], split: str, columns: list[str] | None = None
                    ) -> tuple[pd.DataFrame, pd.DataFrame]:
    """:func:`stream_with_events` of several datasets, one after the other, with the seeds of
    dataset k moved to k * SEED_STRIDE + seed so that tracks and events never collide."""
    streams, events = [], []
    for k, info in enumerate(infos):
        if not info.seeds(split):
            continue
        stream, ev = stream_with_events(info, split, columns)
        stream["seed"] = stream["seed"].astype(np.int64) + k * SEED_STRIDE
        ev["seed"] = ev["seed"].astype(np.int64) + k * SEED_STRIDE
        streams.append(stream)
        events.append(ev)
    if not streams:
        raise DatasetError(f"split {split!r} is empty in every dataset given")
    return pd.concat(streams, ignore_index=True), pd.concat(events, ignore_index=True)


def tune_decisions(prob: np.ndarray, stream: pd.DataFrame, events: pd.DataFrame, period_s: float,
                   horizon_s: float, conservative_threshold: float = 0.5,
                   max_false_alarms: float = MAX_FALSE_ALARMS_PER_VH, false_alarm_rate: str = "all") -> dict:
    """Pick threshold / tau_a / tau_c on a validation stream.

    `false_alarm_rate`: the rate bounded by `max_false_alarms`, "all" (every false alarm over all
    vehicle-hours) or "judged" (the uncensored false alarms over the exposure where a confirming
    window fits in the track; :mod:`vcfusion.prediction.events`); a stream without judged exposure
    cannot bound the judged rate (ValueError).

    For each smoothing and each tau, the lowest threshold of THRESHOLDS with at most
    `max_false_alarms` false alarms per vehicle-hour, found by bisection. That assumes false
    alarms fall as the threshold rises. Raising it only removes positive decisions, but it can
    split one alarm in two, so on one vehicle the count can rise; over a validation stream of
    thousands of vehicles the curve is close to monotone, and a full scan of the grid would cost
    ~15x the evaluations. Then, over the taus, the setting predicting the most lane changes (ties:
    larger mean advance). If no setting meets the bound, the one with the fewest false alarms.
    The default smoothing is then picked by :func:`choose_default`.
    """
    best: dict = {}
    bounds, stretches = track_bounds(stream), smoothing_bounds(stream)
    rate = lambda summary: rate_of(summary, false_alarm_rate)  # noqa: E731
    if false_alarm_rate == "judged":
        times = stream["time"].to_numpy(dtype=float)
        if not sum(judged_ticks(times[a:b], horizon_s) for a, b in bounds):
            raise ValueError(f"judged false-alarm rate: no validation track is longer than the {horizon_s:g} s "
                             f"confirming window, so no false alarm can be judged")
    for method, taus in (("none", (0,)), ("aggressive", TAU_A_TICKS), ("conservative", TAU_C_TICKS)):
        candidates = []
        for tau in taus:
            cache: dict[int, dict] = {}

            def score(i: int) -> dict:
                if i not in cache:
                    raw = (prob > THRESHOLDS[i]).astype(np.int8)
                    dec = smooth_stream(stretches, raw, method, tau_a=tau, tau_c=tau,
                                        threshold=conservative_threshold)
                    cache[i] = event_scores(stream, dec, events, period_s, horizon_s, bounds)[0]
                return cache[i]

            ok = lambda i: rate(score(i)) <= max_false_alarms  # noqa: E731
            lo, hi = 0, len(THRESHOLDS) - 1
            if ok(lo):
                hi = lo
            elif ok(hi):
                while hi - lo > 1:  # invariant: not ok(lo), ok(hi)
                    mid = (lo + hi) // 2
                    if ok(mid):
                        hi = mid
                    else:
                        lo = mid
            candidates += [(THRESHOLDS[i], tau, summary) for i, summary in cache.items()]
        ok_c = [c for c in candidates if rate(c[2]) <= max_false_alarms]
        if ok_c:
            thr, tau, summary = max(ok_c, key=lambda c: (c[2]["predicted_share"], c[2]["advance_final_mean_s"]))
        else:
            thr, tau, summary = min(candidates, key=lambda c: (rate(c[2]), -c[2]["predicted_share"]))
        best[method] = {"threshold": thr, "tau_ticks": tau, "validation": summary}
    return best


def choose_default(tuned: dict, max_false_alarms: float = MAX_FALSE_ALARMS_PER_VH, false_alarm_rate: str = "all") -> str:
    """The smoothing a model file makes default: among the variants that meet the false-alarm bound
    on validation, the one predicting most lane changes; if none meets it, the one with the fewest
    false alarms. Ties go to the aggressive variant (the paper's choice). `false_alarm_rate`: as
    :func:`tune_decisions`."""
    order = ("aggressive", "conservative", "none")
    rate = lambda m: rate_of(tuned[m]["validation"], false_alarm_rate)  # noqa: E731
    ok = [m for m in order if rate(m) <= max_false_alarms]
    if ok:
        return max(ok, key=lambda m: (tuned[m]["validation"]["predicted_share"], -order.index(m)))
    return min(order, key=lambda m: (rate(m), order.index(m)))


def train_model(datasets: Path | list[Path], out: Path, cfg: TrainConfig, progress: bool = True) -> str:
    """Train on the train seeds of one or several datasets (scenario families mixed), tune the
    decision settings on their validation seeds, save the model file; returns a report."""
    started = wallclock.perf_counter()
    datasets = [datasets] if isinstance(datasets, (str, Path)) else list(datasets)
    infos = load_datasets(datasets)
    info = infos[0]
    rng = np.random.default_rng(cfg.seed)
    names = list(info.feature_names)
    if cfg.privileged:
        for d, i in zip(datasets, infos):
            if not i.meta.get("privileged_names"):
                raise DatasetError(f"{d}: --privileged needs SUMO's lane-change state in the samples; build the "
                                   f"dataset with `vcfusion dataset ... --privileged`")
        names += list(info.meta["privileged_names"])
    tr = pd.concat([training_rows(i, "train", cfg.background_negatives, rng) for i in infos], ignore_index=True)
    va = pd.concat([training_rows(i, "validation", cfg.background_negatives, rng) for i in infos], ignore_index=True)
    x_tr = tr[names].to_numpy(np.float32)
    y_tr = (tr["window_label"] == 1).to_numpy(np.float32)
    y_va = (va["window_label"] == 1).to_numpy(np.float32)
    require_both_labels(y_tr, "train")
    require_both_labels(y_va, "validation")
    mean, std = feature_scaling(x_tr)
    x_va = ((va[names].to_numpy(np.float32) - mean) / std).astype(np.float32)
    weights, fit = _fit_torch(((x_tr - mean) / std).astype(np.float32), y_tr, x_va, y_va, cfg, len(names), progress)
    model = LaneChangeModel(tuple(names), mean, std, weights, tau=info.tau, tau_g=info.tau_g, period_s=info.period_s)
    stream, events = combined_stream(infos, "validation", columns=["seed", "vehicle_id", "time", "stream_label",
                                                                   *names])
    x_stream = stream[names].to_numpy(np.float32)
    model.calibration = fit_platt(model.logits(x_stream), stream["stream_label"].to_numpy() == 1)
    prob = model.predict_proba(x_stream)
    tuned = tune_decisions(prob, stream, events, info.period_s, cfg.horizon_s, model.conservative_threshold)
    default = choose_default(tuned)
    model.smoothing = default
    model.thresholds = {m: float(t["threshold"]) for m, t in tuned.items()}
    model.threshold = model.thresholds[default]
    model.tau_a_ticks = int(tuned["aggressive"]["tau_ticks"])
    model.tau_c_ticks = int(tuned["conservative"]["tau_ticks"])
    model.info = {
        "dataset": str(Path(datasets[0]).absolute()), "scenario": info.meta.get("scenario"), "kind": cfg.kind,
        "datasets": [str(Path(d).absolute()) for d in datasets], "scenarios": [i.meta.get("scenario") for i in infos],
        "config": asdict(cfg), "fit": fit, "train_samples": int(len(tr)), "train_positives": int(y_tr.sum()),
        "splits": info.splits if len(infos) == 1 else [i.splits for i in infos], "tuning": tuned, "calibration": list(model.calibration),
        "command": f"vcfusion train {' '.join(map(str, datasets))} --out {out.name} --hidden {cfg.hidden} --epochs {cfg.epochs} "
                   f"--patience {cfg.patience} --seed {cfg.seed} --background-negatives {cfg.background_negatives} "
                   f"--learning-rate {cfg.learning_rate} --weight-decay {cfg.weight_decay}"
                   + (" --privileged" if cfg.privileged else ""),
    }
    save_model(model, out)
    lines = [f"trained {cfg.kind} on {len(tr)} samples ({int(y_tr.sum())} positive) of "
             f"{sum(len(i.splits['train']) for i in infos)} seeds of {len(infos)} dataset(s) in {wallclock.perf_counter() - started:.1f} s: best epoch {fit['best_epoch'] + 1} of "
             f"{fit['epochs_run']}, validation loss {fit['best_val_loss']:.4f}"]
    return "\n".join(lines + tuning_report(tuned, default, out))


def tuning_report(tuned: dict, default: str, out: Path, false_alarm_rate: str = "all") -> list[str]:
    """The validation figures of each smoothing method, as printed after training (MLP and GRU alike);
    with `false_alarm_rate` "judged" also the judged (censoring-aware) rate."""
    lines = []
    for method, t in tuned.items():
        v = t["validation"]
        judged = (f" (judged {v['false_alarms_judged_per_vehicle_hour']:.2f} over "
                  f"{v['judged_vehicle_hours']:.2f} veh-h)" if false_alarm_rate == "judged" else "")
        lines.append(f"  {method:12s} threshold {t['threshold']:.2f} tau {t['tau_ticks']:2d} ticks: "
                     f"{100 * v['predicted_share']:.1f}% predicted, mean advance {v['advance_final_mean_s']:.2f} s, "
                     f"{v['false_alarms_per_vehicle_hour']:.2f} false alarms/veh-h{judged} (validation)")
    lines.append(f"  default smoothing: {default}; model file: {out}")
    return lines
