"""Training of the lane-change GRU (vcfusion.prediction.sequence) on one or several datasets.

- Data: every vehicle's every-tick samples of the training seeds, as segments
  (:func:`vcfusion.prediction.sequence.segment_bounds`), the GRU run over each from a zero state.
- Loss: binary cross-entropy on the Fig. 5 windows (window_label 1 / 0, as the MLP) plus the
  ticks outside the windows that are not within 2 tau + tau_g of a lane change (negatives the
  paper's windows never show, like the MLP's `--background-negatives`), those weighted so that
  they count `background_negatives` times the window samples; positives weighted to balance
  all negatives. The gap ticks (tau .. tau + tau_g before a change) are not scored, as in Fig. 5.
- Truncated backpropagation through time: segments are processed in chunks of `bptt_ticks`
  ticks; the hidden state is carried from one chunk to the next (so the model sees the whole
  history) and gradients flow back over one chunk (bptt_ticks x 0.1 s).
- Adam, gradient clipping, early stopping on the validation seeds' loss (best epoch kept);
  then Platt calibration and the decision settings on the validation stream, as the MLP
  (:func:`vcfusion.prediction.train.tune_decisions`) but with a false-alarm budget of
  `false_alarm_budget` (1.5 per vehicle-hour: the 2 / veh-h target less a margin for the
  difference between the validation stream and unseen traffic).
- Seeded and single-threaded by default: the same command gives the same weights.
"""

from __future__ import annotations

import copy
import dataclasses
import time as wallclock
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.prediction.dataset import DatasetError
from vcfusion.prediction.model import feature_scaling, fit_platt
from vcfusion.prediction.sequence import DEFAULT_RESET_GAP_TICKS, SequenceModel, save_sequence_model, segment_bounds


@dataclass(frozen=True)
class SequenceConfig:
    hidden: int = 48
    epochs: int = 8
    patience: int = 3
    batch_segments: int = 16
    bptt_ticks: int = 100  # 10 s at the V2C period
    learning_rate: float = 1e-3  # the CLI default, with which the shipped GRU was trained
    weight_decay: float = 1e-5
    seed: int = 0
    background_negatives: float = 3.0
    threads: int = 1
    reset_gap_ticks: int = DEFAULT_RESET_GAP_TICKS
    horizon_s: float = 10.0
    # Validation false-alarm budget of the decision settings: the target is <= 2 per vehicle-hour
    # on traffic never tuned on, and a threshold tuned to exactly 2 on validation lands on either
    # side of 2 elsewhere (validation is a sample, and families differ), so tune with a 25 % margin.
    false_alarm_budget: float = 1.5
    # Inputs: the name of one of features.SEQUENCE_INPUT_SETS: base | availability (with the
    # availability flags) | lateral (flags and lateral motion).
    inputs: str = "base"
    # Early-warning weighting of the positive window: a positive tick t seconds before the change's
    # end weighs 1 + early_weight * t / tau before the positives are balanced against the negatives
    # (0: all positives alike, the shipped recipe; 2: the earliest weigh 3 times the latest). The
    # early positives are the ones the advance depends on (docs/components/real-data.md, "What
    # limits the advance").
    early_weight: float = 0.0
    # Fine-tuning: start from this GRU file's weights and input standardisation (its inputs, its
    # hidden size) instead of a random initialisation; None = from scratch.
    init: str | None = None


def loss_weights(stream: pd.DataFrame, tau: float, tau_g: float, background: float,
                 early_weight: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(target, weight) per row: windows weight 1 (positives re-weighted to balance), far
    negatives weighted to total `background` x the window rows, gap ticks weight 0; with
    early_weight > 0 a positive weighs 1 + early_weight x time to the end / tau before the balancing."""
    window = stream["window_label"].to_numpy()
    ttl = stream["time_to_lc"].to_numpy(dtype=float)
    target = (window == 1).astype(np.float32)
    in_window = window >= 0
    with np.errstate(invalid="ignore"):
        far = (window < 0) & ~(ttl <= 2 * tau + tau_g)
    weight = in_window.astype(np.float64)
    if early_weight > 0:
        pos = target == 1
        weight[pos] = 1.0 + early_weight * np.clip(ttl[pos], 0.0, tau) / tau
    if far.any() and background > 0:
        weight[far] = background * in_window.sum() / far.sum()
    neg_total = weight[target == 0].sum()
    pos_total = weight[target == 1].sum()
    if pos_total > 0:
        weight[target == 1] *= neg_total / pos_total
    return target, weight.astype(np.float32)


class _Batches:
    """Segments grouped into padded batches of similar length (longest first), for TBPTT."""

    def __init__(self, x: np.ndarray, target: np.ndarray, weight: np.ndarray, bounds, batch: int):
        self.x, self.target, self.weight = x, target, weight
        lengths = np.array([b - a for a, b in bounds])
        order = np.argsort(-lengths, kind="stable")
        self.groups = [[bounds[i] for i in order[k:k + batch]] for k in range(0, len(order), batch)]

    def tensors(self, group):
        import torch

        t_max = max(b - a for a, b in group)
        xb = np.zeros((len(group), t_max, self.x.shape[1]), dtype=np.float32)
        yb = np.zeros((len(group), t_max), dtype=np.float32)
        wb = np.zeros((len(group), t_max), dtype=np.float32)
        for i, (a, b) in enumerate(group):
            xb[i, :b - a], yb[i, :b - a], wb[i, :b - a] = self.x[a:b], self.target[a:b], self.weight[a:b]
        return torch.from_numpy(xb), torch.from_numpy(yb), torch.from_numpy(wb)


def _fit(train: _Batches, val: _Batches, n_inputs: int, cfg: SequenceConfig, progress: bool, init=None):
    import torch
    from tqdm import tqdm

    torch.manual_seed(cfg.seed)
    torch.set_num_threads(max(1, cfg.threads))
    hidden = cfg.hidden if init is None else init.hidden
    gru = torch.nn.GRU(n_inputs, hidden, batch_first=True)
    head = torch.nn.Linear(hidden, 1)
    if init is not None:  # fine-tuning: the pretrained weights
        with torch.no_grad():
            for p, a in ((gru.weight_ih_l0, init.w_ih), (gru.weight_hh_l0, init.w_hh), (gru.bias_ih_l0, init.b_ih),
                         (gru.bias_hh_l0, init.b_hh), (head.weight, init.w_out), (head.bias, init.b_out)):
                p.copy_(torch.from_numpy(np.array(a, dtype=np.float32)))
    params = list(gru.parameters()) + list(head.parameters())
    opt = torch.optim.Adam(params, lr=cfg.learning_rate, weight_decay=cfg.weight_decay)
    rng = np.random.default_rng(cfg.seed)

    def run(batches: _Batches, group, learn: bool) -> tuple[float, float]:
        xb, yb, wb = batches.tensors(group)
        h = None
        total, weight = 0.0, 0.0
        for c in range(0, xb.shape[1], cfg.bptt_ticks):
            w = wb[:, c:c + cfg.bptt_ticks]
            out, h = gru(xb[:, c:c + cfg.bptt_ticks], h)
            z = head(out)[..., 0]
            loss = torch.nn.functional.binary_cross_entropy_with_logits(z, yb[:, c:c + cfg.bptt_ticks], weight=w,
                                                                        reduction="sum")
            if learn and float(w.sum()) > 0:
                opt.zero_grad()
                (loss / w.sum()).backward()
                torch.nn.utils.clip_grad_norm_(params, 1.0)
                opt.step()
            h = h.detach()  # truncation: the state goes on, its gradient stops here
            total += float(loss.detach())
            weight += float(w.sum())
        return total, weight

    best, best_state, best_epoch, stale, history = np.inf, None, 0, 0, []
    bar = tqdm(range(cfg.epochs), desc="train gru", unit="epoch", disable=not progress, leave=False)
    for epoch in bar:
        gru.train()
        for k in rng.permutation(len(train.groups)):
            run(train, train.groups[k], learn=True)
        gru.eval()
        with torch.no_grad():
            sums = [run(val, g, learn=False) for g in val.groups]
        val_loss = sum(s for s, _ in sums) / max(1e-9, sum(w for _, w in sums))
        history.append(val_loss)
        bar.set_postfix(val_loss=f"{val_loss:.4f}")
        if val_loss < best - 1e-5:
            best, best_epoch, stale = val_loss, epoch, 0
            best_state = ({k: v.clone() for k, v in gru.state_dict().items()},
                          {k: v.clone() for k, v in head.state_dict().items()})
        else:
            stale += 1
            if stale >= cfg.patience:
                break
    gru.load_state_dict(best_state[0])
    head.load_state_dict(best_state[1])
    arrays = {"w_ih": gru.weight_ih_l0, "w_hh": gru.weight_hh_l0, "b_ih": gru.bias_ih_l0, "b_hh": gru.bias_hh_l0,
              "w_out": head.weight, "b_out": head.bias}
    arrays = {k: v.detach().numpy().copy() for k, v in arrays.items()}
    return arrays, {"best_epoch": best_epoch, "epochs_run": len(history), "best_val_loss": best,
                    "val_loss_history": history}


def train_sequence_model(datasets: list[Path], out: Path, cfg: SequenceConfig, progress: bool = True) -> str:
    """Train the GRU on the train seeds of `datasets`, calibrate and tune on their validation
    seeds, save the model file; returns a report."""
    from vcfusion.prediction.features import SEQUENCE_INPUT_SETS, stored_columns, with_derived_columns
    from vcfusion.prediction.train import (choose_default, combined_stream, load_datasets, require_both_labels,
                                           tune_decisions, tuning_report)

    started = wallclock.perf_counter()
    infos = load_datasets(datasets)
    init = _init_model(cfg.init) if cfg.init else None
    names = list(init.feature_names if init is not None
                 else SEQUENCE_INPUT_SETS[cfg.inputs])
    tau, tau_g, period = infos[0].tau, infos[0].tau_g, infos[0].period_s
    if init is not None and (init.tau, init.tau_g, init.period_s) != (tau, tau_g, period):
        raise DatasetError(f"{cfg.init}: tau / tau_g / V2C period {init.tau, init.tau_g, init.period_s} differ from "
                           f"the datasets' {tau, tau_g, period}; fine-tune on datasets of the same labels")
    columns = ["seed", "vehicle_id", "time", "window_label", "time_to_lc", "stream_label", *stored_columns(names)]
    tr, _ = combined_stream(infos, "train", columns)
    va, va_events = combined_stream(infos, "validation", columns)
    with_derived_columns(tr, names, period)
    with_derived_columns(va, names, period)
    require_both_labels((tr["window_label"] == 1).to_numpy(), "train")
    require_both_labels((va["window_label"] == 1).to_numpy(), "validation")
    x_tr = tr[names].to_numpy(np.float32)
    # a fine-tuned model keeps the pretrained standardisation (its weights were learnt on it)
    mean, std = (init.mean, init.std) if init is not None else feature_scaling(x_tr)
    norm = lambda a: ((a - mean) / std).astype(np.float32)  # noqa: E731
    y_tr, w_tr = loss_weights(tr, tau, tau_g, cfg.background_negatives, cfg.early_weight)
    y_va, w_va = loss_weights(va, tau, tau_g, cfg.background_negatives, cfg.early_weight)
    b_tr = segment_bounds(tr, period, cfg.reset_gap_ticks)
    b_va = segment_bounds(va, period, cfg.reset_gap_ticks)
    arrays, fit = _fit(_Batches(norm(x_tr), y_tr, w_tr, b_tr, cfg.batch_segments),
                       _Batches(norm(va[names].to_numpy(np.float32)), y_va, w_va, b_va, cfg.batch_segments),
                       len(names), cfg, progress, init)
    del x_tr
    model = SequenceModel(tuple(names), mean, std, **arrays, tau=tau, tau_g=tau_g, period_s=period,
                          reset_gap_ticks=cfg.reset_gap_ticks)
    logits = model.sequence_logits(va[names].to_numpy(np.float32), b_va)
    model.calibration = fit_platt(logits, va["stream_label"].to_numpy() == 1)
    prob = model.calibrated(logits)
    tuned = tune_decisions(prob, va, va_events, period, cfg.horizon_s, model.conservative_threshold,
                           cfg.false_alarm_budget)
    default = choose_default(tuned, cfg.false_alarm_budget)
    model.smoothing = default
    model.thresholds = {m: float(t["threshold"]) for m, t in tuned.items()}
    model.threshold = model.thresholds[default]
    model.tau_a_ticks = int(tuned["aggressive"]["tau_ticks"])
    model.tau_c_ticks = int(tuned["conservative"]["tau_ticks"])
    model.info = {
        "kind": "gru", "datasets": [str(Path(d).absolute()) for d in datasets],
        "init": str(Path(cfg.init).absolute()) if cfg.init else None,
        "scenarios": [i.meta.get("scenario") for i in infos], "config": asdict(cfg), "fit": fit,
        "train_rows": int(len(tr)), "train_segments": len(b_tr), "splits": [i.splits for i in infos],
        "tuning": tuned, "calibration": list(model.calibration),
    }
    save_sequence_model(model, out)
    start = f", fine-tuned from {cfg.init}" if cfg.init else ""
    lines = [f"trained gru (hidden {model.hidden}{start}) on {len(b_tr)} segments / {len(tr)} ticks of "
             f"{sum(len(i.splits['train']) for i in infos)} seeds of {len(infos)} datasets in "
             f"{wallclock.perf_counter() - started:.1f} s: best epoch {fit['best_epoch'] + 1} of {fit['epochs_run']}, "
             f"validation loss {fit['best_val_loss']:.4f}"]
    return "\n".join(lines + tuning_report(tuned, default, out))


def check_sequence_columns(infos, names=None) -> None:
    """The sequence model's extra inputs (and those of `names`, a model's input list) must be in the
    samples (datasets built before they existed are brought up to date with `vcfusion dataset ...
    --refeature`; an imported recording: import it again)."""
    import pyarrow.parquet as pq

    from vcfusion.prediction.features import SEQUENCE_EXTRA_NAMES, stored_columns

    needed = [*SEQUENCE_EXTRA_NAMES, *[n for n in stored_columns(names or ()) if n not in SEQUENCE_EXTRA_NAMES]]
    for info in infos:
        for seed in info.seeds("all"):
            f = info.samples_file(seed)
            missing = [n for n in needed if n not in pq.read_schema(f).names]
            if missing:
                raise DatasetError(f"{f}: missing columns {missing} (the sequence model's inputs); bring the dataset up "
                                   "to date with `vcfusion dataset SCENARIO --seeds ... --out DIR --refeature`")


def _init_model(path) -> SequenceModel:
    """The GRU a fine-tuning starts from (a ModelFileError for anything else)."""
    from vcfusion.prediction.model import ModelFileError, load_model

    from vcfusion.prediction.ensemble import EnsembleModel

    model = load_model(path)
    if model.kind != "gru":
        raise ModelFileError(f"{path}: --init: expected a GRU file (`vcfusion train --kind gru`), got an MLP")
    if isinstance(model, EnsembleModel):
        raise ModelFileError(f"{path}: --init: an ensemble of {len(model.members)} GRUs; fine-tune from one GRU "
                             "file and ensemble the results (`vcfusion ensemble-models`)")
    return model


def retune_decisions(model_path: Path, datasets: list[Path], out: Path, false_alarm_budget: float,
                     horizon_s: float = 10.0, false_alarm_rate: str = "all") -> str:
    """Re-calibrate (Platt) and re-tune the decision settings of a model file on the validation
    seeds of `datasets` (the target kind's validation data: a real recording's validation part),
    weights unchanged; writes the new file, returns a report. `false_alarm_rate`: the rate the
    budget bounds, "all" or "judged" (censoring-aware; :func:`vcfusion.prediction.train.tune_decisions`)."""
    from vcfusion.prediction.features import stored_columns, with_derived_columns
    from vcfusion.prediction.model import fit_platt, load_model, save_model_file
    from vcfusion.prediction.train import choose_default, combined_stream, load_datasets, tune_decisions, tuning_report

    model = copy.deepcopy(load_model(model_path))
    infos = load_datasets(datasets)
    names = list(model.feature_names)
    columns = ["seed", "vehicle_id", "time", "stream_label", *stored_columns(names)]
    va, va_events = combined_stream(infos, "validation", columns)
    with_derived_columns(va, names, model.period_s)
    if model.kind == "gru":
        logits = model.sequence_logits(va[names].to_numpy(np.float32),
                                       segment_bounds(va, model.period_s, model.reset_gap_ticks))
    else:
        logits = model.logits(va[names].to_numpy(np.float32))
    model.calibration = fit_platt(logits, va["stream_label"].to_numpy() == 1)
    if model.kind == "gru":
        prob = model.calibrated(logits)
    else:
        prob = model.predict_proba(va[names].to_numpy(np.float32))
    tuned = tune_decisions(prob, va, va_events, model.period_s, horizon_s, model.conservative_threshold,
                           false_alarm_budget, false_alarm_rate)
    default = choose_default(tuned, false_alarm_budget, false_alarm_rate)
    model.smoothing = default
    model.thresholds = {m: float(t["threshold"]) for m, t in tuned.items()}
    model.threshold = model.thresholds[default]
    model.tau_a_ticks = int(tuned["aggressive"]["tau_ticks"])
    model.tau_c_ticks = int(tuned["conservative"]["tau_ticks"])
    model.info = {**model.info, "retuned": {"from": Path(model_path).name, "datasets": [Path(d).name for d in datasets],
                                            "false_alarm_budget": false_alarm_budget,
                                            "false_alarm_rate": false_alarm_rate, "tuning": tuned,
                                            "calibration": list(model.calibration)}}
    save_model_file(model, out)
    head = (f"re-tuned {model_path} on the validation seeds of {len(infos)} datasets ({len(va_events)} lane changes, "
            f"{len(va) * model.period_s / 3600:.2f} vehicle-hours), false-alarm budget {false_alarm_budget:g} / veh-h "
            f"({false_alarm_rate})")
    return "\n".join([head] + tuning_report(tuned, default, out, false_alarm_rate))


def set_decision(model_path: Path, out: Path, smoothing: str, threshold: float, tau_ticks: int,
                 reason: str) -> str:
    """Write `model_path` with the decision settings given (weights and calibration unchanged): the
    smoothing made default, its probability threshold and its window (tau_a or tau_c ticks). For a
    decision chosen outside the model's own validation tuning, e.g. on the cross-fitted validation
    streams of a small recording (docs: components/real-data.md, "False alarms on real data");
    `reason` is recorded in the file's info (`decision_set`) with the settings it replaced."""
    from vcfusion.prediction.model import load_model, save_model_file
    from vcfusion.prediction.smoothing import _METHODS

    if smoothing not in _METHODS:
        raise ValueError(f"smoothing: expected one of {', '.join(_METHODS)}, got {smoothing!r}")
    if not 0.0 < threshold < 1.0:
        raise ValueError(f"threshold: expected a probability in (0, 1), got {threshold}")
    if int(tau_ticks) != tau_ticks or tau_ticks < 0:
        raise ValueError(f"tau ticks: expected a whole number >= 0, got {tau_ticks}")
    if not reason.strip():
        raise ValueError("reason: expected a note saying where the settings were chosen")
    model = copy.deepcopy(load_model(model_path))
    before = {"smoothing": model.smoothing, "thresholds": dict(model.thresholds), "threshold": model.threshold,
              "tau_a_ticks": model.tau_a_ticks, "tau_c_ticks": model.tau_c_ticks}
    model.smoothing = smoothing
    model.thresholds = {**model.thresholds, smoothing: float(threshold)}
    model.threshold = float(threshold)
    if smoothing == "aggressive":
        model.tau_a_ticks = int(tau_ticks)
    elif smoothing == "conservative":
        model.tau_c_ticks = int(tau_ticks)
    model.info = {**model.info, "decision_set": {"from": Path(model_path).name, "smoothing": smoothing,
                                                 "threshold": float(threshold), "tau_ticks": int(tau_ticks),
                                                 "reason": reason, "replaced": before}}
    save_model_file(model, out)
    return (f"{out}: {smoothing}, threshold {threshold:g}, tau {int(tau_ticks)} ticks "
            f"(was {before['smoothing']}, threshold {before['thresholds'].get(before['smoothing'], before['threshold']):g}); "
            f"weights and calibration of {model_path}")


def extend_inputs(model: SequenceModel, names, mean, std) -> SequenceModel:
    """A copy of the GRU `model` whose inputs are `names` (its own inputs first, in order, then new
    ones), the new inputs standardised with `mean` / `std` (one per new input) and given zero input
    weights: its probabilities are the model's until it is fine-tuned (`vcfusion train --init`)."""
    names = tuple(names)
    own = tuple(model.feature_names)
    if names[:len(own)] != own or len(names) == len(own):
        raise ValueError(f"inputs {list(names[len(own):]) or 'none'}: expected the model's {len(own)} inputs "
                         "first, in order, then at least one new one")
    mean, std = np.asarray(mean, dtype=float), np.asarray(std, dtype=float)
    extra = len(names) - len(own)
    if mean.shape != (extra,) or std.shape != (extra,) or not (std > 0).all():
        raise ValueError(f"mean / std: expected {extra} values each, std > 0")
    return dataclasses.replace(copy.deepcopy(model), feature_names=names, mean=np.r_[model.mean, mean],
                               std=np.r_[model.std, std],
                               w_ih=np.hstack([model.w_ih, np.zeros((model.w_ih.shape[0], extra), np.float32)]))
