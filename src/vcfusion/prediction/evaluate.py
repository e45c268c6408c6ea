"""`vcfusion evaluate`: frame- and event-level scores of a model and two baselines on test seeds.

Predictors (all fitted on the training seeds, decision settings tuned on the validation
seeds, scored on the test seeds — three disjoint sets of runs):
- the model file given (the MLP, or the GRU sequence model run along each vehicle's track);
- logistic regression (one linear layer, same inputs, standardisation, class weighting and
  early stopping as the MLP);
- a gap/speed threshold rule: positive when the own-lane leader is slower by more than dv
  and closer than g while an adjacent lane offers a longer leader gap, or a stopped vehicle
  is ahead in the own lane closer than b (dv, g, b grid-searched on the training windows).
Variants: original (threshold only), aggressive (Algorithm 3), conservative (Algorithm 4).
Frame level: accuracy, precision, recall, F1, ROC AUC on the test window samples (Fig. 5, the
paper's balanced set) and on the full every-tick stream. Scores for ROC AUC: the probability
(original), its running max over tau_a + 1 ticks (aggressive), the running mean of the raw
decisions over tau_c + 1 ticks (conservative), matching how each variant decides.
Event level: see vcfusion.prediction.events.

`split`: train / validation / test, or all (every seed: for an imported recording, every vehicle).
Baselines need train and validation seeds; a dataset without them (a short recording) is scored
with the model alone, and the report says so. A model trained with SUMO's state
(`vcfusion train --privileged`) is scored as the ceiling, and on a `--privileged` dataset the rule
"SUMO wants to change lanes" joins the baselines (vcfusion.prediction.privileged).
Outputs: report.md, evaluation.png, metrics.csv (one row per predictor x variant), settings.json
and evaluation.json (:func:`evaluation_summary`).
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import rankdata

from vcfusion.prediction.dataset import DatasetError, load_dataset
from vcfusion.prediction.events import event_scores, smooth_stream, smoothing_bounds, track_bounds
from vcfusion.prediction.features import (SEQUENCE_EXTRA_NAMES, SEQUENCE_INPUT_SETS, stored_columns,
                                          with_derived_columns)
from vcfusion.prediction.model import LaneChangeModel, feature_scaling, load_model, model_feature_names, model_kind
from vcfusion.prediction.train_sequence import check_sequence_columns
from vcfusion.prediction.privileged import SumoWantsRule
from vcfusion.prediction.train import (TrainConfig, _fit_torch, require_both_labels, stream_with_events,
                                      training_rows, tune_decisions)
from vcfusion.runio import atomic_write

VARIANTS = ("original", "aggressive", "conservative")
_METHOD = {"original": "none", "aggressive": "aggressive", "conservative": "conservative"}


def roc_auc(y: np.ndarray, score: np.ndarray) -> float:
    y = np.asarray(y).astype(bool)
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    ranks = rankdata(score)  # ties get their mean rank: the Mann-Whitney form of the AUC
    return float((ranks[y].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def frame_metrics(y: np.ndarray, decision: np.ndarray, score: np.ndarray) -> dict:
    y = np.asarray(y).astype(bool)
    d = np.asarray(decision).astype(bool)
    tp, fp = int((y & d).sum()), int((~y & d).sum())
    fn, tn = int((y & ~d).sum()), int((~y & ~d).sum())
    precision = tp / (tp + fp) if tp + fp else float("nan")
    recall = tp / (tp + fn) if tp + fn else float("nan")
    # undefined, not 0, where there is nothing to score (no sample; no positive window for F1):
    # a split without a lane change read "accuracy 0.0, F1 0.0"
    f1 = float("nan") if tp + fn == 0 else (2 * precision * recall / (precision + recall) if tp else 0.0)
    accuracy = (tp + tn) / len(y) if len(y) else float("nan")
    return {"accuracy": accuracy, "precision": precision, "recall": recall, "f1": f1, "roc_auc": roc_auc(y, score)}


def _running(bounds, values: np.ndarray, window: int, how: str) -> np.ndarray:
    out = np.empty(len(values), dtype=float)
    for a, b in bounds:
        v = pd.Series(values[a:b].astype(float))
        r = v.rolling(window, min_periods=1)
        out[a:b] = (r.max() if how == "max" else r.sum() / window).to_numpy()
    return out


class RuleBaseline:
    """Gap/speed threshold rule (see module docstring); predict_proba returns 0/1."""

    GRID_DV = (0.5, 1.0, 2.0, 4.0)
    GRID_GAP = (10.0, 20.0, 40.0, 80.0)
    GRID_BLOCK = (0.0, 50.0, 100.0, 200.0)

    def __init__(self, names: list[str], dv=1.0, gap=20.0, block=100.0):
        self.col = {n: i for i, n in enumerate(names)}
        self.dv, self.gap, self.block = dv, gap, block

    def predict_proba(self, x: np.ndarray) -> np.ndarray:
        c = self.col
        own_gap = x[:, c["gap_lead_own"]]
        slow_leader = (x[:, c["dv_lead_own"]] < -self.dv) & (own_gap < self.gap)
        better_left = (x[:, c["left_lane_exists"]] > 0) & (x[:, c["gap_lead_left"]] > own_gap)
        better_right = (x[:, c["right_lane_exists"]] > 0) & (x[:, c["gap_lead_right"]] > own_gap)
        blocked = x[:, c["stopped_ahead_own"]] < self.block
        return ((slow_leader & (better_left | better_right)) | blocked).astype(np.float32)

    def fit(self, x: np.ndarray, y: np.ndarray) -> "RuleBaseline":
        best = (-1.0, None)
        for dv, gap, block in itertools.product(self.GRID_DV, self.GRID_GAP, self.GRID_BLOCK):
            self.dv, self.gap, self.block = dv, gap, block
            f1 = frame_metrics(y, self.predict_proba(x) > 0.5, self.predict_proba(x))["f1"]
            if f1 > best[0]:
                best = (f1, (dv, gap, block))
        self.dv, self.gap, self.block = best[1]
        return self


def _fmt(v: float, pct: bool = False) -> str:
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return "n/a"
    return f"{100 * v:.1f}%" if pct else f"{v:.3f}" if abs(v) < 10 else f"{v:.1f}"


def evaluate(model_path: Path, dataset: Path, out: Path | None = None, split: str = "test",
             horizon_s: float = 10.0, seed: int = 0, baselines: bool = True) -> Path:
    info = load_dataset(dataset)
    names = list(info.feature_names)  # what the cloud can observe: the baselines' inputs
    privileged = list(info.meta.get("privileged_names", []))  # SUMO's state, in a --privileged dataset
    # a ceiling model (`vcfusion train --privileged`) also takes the privileged columns
    ceiling = bool(privileged) and set(privileged) <= set(model_feature_names(model_path))
    if model_kind(model_path) == "gru":  # the sequence model also reads the extra sample columns
        file_names = tuple(model_feature_names(model_path))
        model_names = (list(file_names) if file_names in SEQUENCE_INPUT_SETS.values()
                       else names + list(SEQUENCE_EXTRA_NAMES))
        check_sequence_columns([info], model_names)
    else:
        model_names = names + privileged if ceiling else names
    model = load_model(model_path, expected_features=model_names)
    model_label = {"gru": "GRU"}.get(model.kind, "MLP + SUMO state (privileged)" if ceiling else "MLP")
    if getattr(model, "members", None):  # vcfusion.prediction.ensemble
        model_label = f"GRU ensemble of {len(model.members)}"
    if not info.seeds(split):
        raise DatasetError(f"{dataset}: split {split!r} is empty")
    out = Path(out) if out else Path(dataset) / f"eval-{Path(model_path).stem}"

    # Baselines, fitted on the dataset's training seeds and tuned on its validation seeds (an
    # imported recording too short for those splits is scored with the model alone).
    predictors: dict = {model_label: (model, model_names)}
    rule = None
    fitted = baselines and bool(info.splits.get("train")) and bool(info.splits.get("validation"))
    if fitted:
        rng = np.random.default_rng(seed)
        bg = float(model.info.get("config", {}).get("background_negatives", 0.0))
        tr = training_rows(info, "train", bg, rng)
        va = training_rows(info, "validation", bg, rng)
        x_tr, y_tr = tr[names].to_numpy(np.float32), (tr["window_label"] == 1).to_numpy(np.float32)
        for fitted_on, rows in (("train", tr), ("validation", va)):  # not `split`: the one scored
            require_both_labels((rows["window_label"] == 1).to_numpy(), fitted_on,
                                " (or score the model alone: --no-baselines)")
        mean, std = feature_scaling(x_tr)
        norm = lambda a: ((a - mean) / std).astype(np.float32)  # noqa: E731
        w, _ = _fit_torch(norm(x_tr), y_tr, norm(va[names].to_numpy(np.float32)),
                          (va["window_label"] == 1).to_numpy(np.float32), TrainConfig(kind="logistic", seed=seed),
                          len(names))
        logistic = LaneChangeModel(tuple(names), mean, std, w, tau=info.tau, tau_g=info.tau_g, period_s=info.period_s)
        rule = RuleBaseline(names).fit(x_tr, y_tr)
        predictors |= {"logistic regression": (logistic, names), "gap/speed rule": (rule, names)}
        if privileged:  # the ceiling's simplest form: flag a vehicle while SUMO wants to change lanes
            predictors["SUMO wants to change (privileged)"] = (SumoWantsRule(privileged), privileged)
        val_stream, val_events = stream_with_events(info, "validation",
                                                    columns=["seed", "vehicle_id", "time", *names, *privileged])
    baselines = {"fitted": fitted,
                 "scored_on_their_training_seeds": fitted and split in ("train", "all"),
                 "note": ("logistic regression and gap/speed rule fitted on the train seeds, tuned on the "
                          "validation seeds" if fitted else
                          "no baselines: --no-baselines" if not baselines else
                          "no baselines: the dataset has no train and validation seeds (fewer than 3 seeds)")}
    stream, events = stream_with_events(info, split, columns=["seed", "vehicle_id", "time", "window_label",
                                                               "stream_label", *dict.fromkeys(stored_columns(
                                                                   [*names, *privileged, *model_names]))])
    with_derived_columns(stream, model_names, info.period_s)
    bounds, stretches = track_bounds(stream), smoothing_bounds(stream)
    in_window = stream["window_label"].to_numpy() >= 0
    y_window = stream["window_label"].to_numpy()[in_window] == 1
    y_stream = stream["stream_label"].to_numpy() == 1

    rows, per_event_all, settings = [], {}, {}
    for pname, (pred, inputs) in predictors.items():
        if pred is model:
            tuned = {"none": {"threshold": model.threshold_for("none"), "tau_ticks": 0},
                     "aggressive": {"threshold": model.threshold_for("aggressive"), "tau_ticks": model.tau_a_ticks},
                     "conservative": {"threshold": model.threshold_for("conservative"),
                                      "tau_ticks": model.tau_c_ticks}}
        else:
            tuned = tune_decisions(pred.predict_proba(val_stream[inputs].to_numpy(np.float32)), val_stream,
                                   val_events, info.period_s, horizon_s)
        # the model may carry state along each track (the GRU): it scores the sorted stream itself
        prob = (model.stream_proba(stream, inputs) if pred is model
                else pred.predict_proba(stream[inputs].to_numpy(np.float32)))
        settings[pname] = {k: {"threshold": v["threshold"], "tau_ticks": v["tau_ticks"]} for k, v in tuned.items()}
        for variant in VARIANTS:
            t = tuned[_METHOD[variant]]
            raw = (prob > t["threshold"]).astype(np.int8)
            dec = smooth_stream(stretches, raw, _METHOD[variant], tau_a=t["tau_ticks"], tau_c=t["tau_ticks"],
                                threshold=model.conservative_threshold)
            if variant == "original":
                score = prob
            elif variant == "aggressive":
                score = _running(stretches, prob, t["tau_ticks"] + 1, "max")
            else:
                score = _running(stretches, raw, t["tau_ticks"] + 1, "mean")
            fw = frame_metrics(y_window, dec[in_window], score[in_window])
            fs = frame_metrics(y_stream, dec, score)
            ev, per_event = event_scores(stream, dec, events, info.period_s, horizon_s, bounds)
            per_event_all[(pname, variant)] = per_event
            rows.append({"predictor": pname, "variant": variant, "threshold": t["threshold"],
                         "tau_ticks": t["tau_ticks"], **{f"window_{k}": v for k, v in fw.items()},
                         **{f"stream_{k}": v for k, v in fs.items()}, **ev})
    table = pd.DataFrame(rows)
    out.mkdir(parents=True, exist_ok=True)  # only now: a bad input leaves nothing behind
    table.to_csv(out / "metrics.csv", index=False)
    default = (model_label, {"none": "original"}.get(model.smoothing, model.smoothing))
    _plot(table, per_event_all, default, out / "evaluation.png")
    report = _report(table, info, split, model_path, model, horizon_s, default, rule, events, per_event_all[default],
                     baselines)
    (out / "report.md").write_text(report)
    (out / "settings.json").write_text(json.dumps(settings, indent=2) + "\n")
    summary = evaluation_summary(table, info, split, model_path, horizon_s, default, stream, events,
                                 per_event_all[default], baselines)
    text = json.dumps(summary, indent=2, allow_nan=False) + "\n"
    atomic_write(out / EVALUATION_JSON, lambda tmp: tmp.write_text(text))
    return out / "report.md"


EVALUATION_JSON = "evaluation.json"
# metrics.csv column -> evaluation.json key (shares as fractions, rates per vehicle-hour)
_JSON_KEYS = {"predicted_share": "predicted", "predicted_before_mid_share": "predicted_before_mid",
              "false_alarms_per_vehicle_hour": "false_alarms_per_veh_h"}


def _plain(value):
    """JSON-safe scalar: NaN / inf -> None, NumPy scalars -> Python."""
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def evaluation_summary(table: pd.DataFrame, info, split: str, model_path, horizon_s: float, default,
                       stream: pd.DataFrame, events: pd.DataFrame, per_event: pd.DataFrame, baselines: dict) -> dict:
    """The machine-readable form of the report (`evaluation.json`): `default` is the model's own
    variant, `variants` every predictor x variant row, with the same keys; `predicted` and
    `predicted_before_mid` are fractions of the lane changes (null when there are none)."""
    rows = [{_JSON_KEYS.get(k, k): _plain(v) for k, v in r.items()} for r in table.to_dict("records")]
    chosen = next(r for r in rows if (r["predictor"], r["variant"]) == default)
    by_reason = per_event.merge(events[["seed", "event_id", "reason"]], on=["seed", "event_id"], how="left")
    by_reason["reason"] = by_reason["reason"].fillna("").str.split("|").str[0]
    reasons = [{"reason": reason, "lane_changes": int(len(g)), "predicted": _plain(g["predicted"].mean()),
                "advance_final_mean_s": _plain(g.loc[g["predicted"], "advance_final_s"].mean())}
               for reason, g in by_reason.groupby("reason")]
    return {
        "model": str(model_path), "dataset": str(info.root), "source": info.meta.get("scenario"),
        "split": split, "seeds": [int(s) for s in info.seeds(split)],
        "vehicles": int(stream[["seed", "vehicle_id"]].drop_duplicates().shape[0]),
        "lane_changes": int(len(events)), "vehicle_hours": _plain(len(stream) * info.period_s / 3600.0),
        "tau_s": info.tau, "tau_g_s": info.tau_g, "horizon_s": horizon_s,
        "baselines": baselines, "default": chosen, "variants": rows, "default_by_reason": reasons,
    }


def _report(table, info, split, model_path, model, horizon_s, default, rule, events, per_event, baselines) -> str:
    seeds = info.seeds(split)
    lines = [f"# Lane-change prediction: evaluation of `{Path(model_path).name}`", "",
             f"Dataset `{info.root}` ({info.meta.get('scenario')}), {split} split: {len(seeds)} seeds "
             f"({seeds[0]}..{seeds[-1]}), {len(events)} lane changes. tau = {info.tau} s, tau_g = {info.tau_g} s; "
             f"event horizon {horizon_s} s. Default variant: {default[0]} {default[1]}.", "",
             "## Event level (every-tick stream)", "",
             "| predictor | variant | thr | tau ticks | predicted | before mid | adv. final mean / median (s) "
             "| adv. first mean / median (s) | false alarms / veh-h |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in table.itertuples(index=False):
        lines.append(f"| {r.predictor} | {r.variant} | {r.threshold:.2f} | {r.tau_ticks} | {_fmt(r.predicted_share, True)} "
                     f"| {_fmt(r.predicted_before_mid_share, True)} | {_fmt(r.advance_final_mean_s)} / "
                     f"{_fmt(r.advance_final_median_s)} | {_fmt(r.advance_first_mean_s)} / {_fmt(r.advance_first_median_s)} "
                     f"| {r.false_alarms_per_vehicle_hour:.2f} ({r.false_alarms} in {r.vehicle_hours:.1f} h) |")
    for title, prefix in (("Frame level, Fig. 5 window samples (balanced)", "window"),
                          ("Frame level, every tick (unbalanced)", "stream")):
        lines += ["", f"## {title}", "", "| predictor | variant | accuracy | precision | recall | F1 | ROC AUC |",
                  "|---|---|---|---|---|---|---|"]
        for r in table.to_dict("records"):
            lines.append(f"| {r['predictor']} | {r['variant']} | " + " | ".join(
                _fmt(r[f"{prefix}_{k}"]) for k in ("accuracy", "precision", "recall", "f1", "roc_auc")) + " |")
    by_reason = per_event.merge(events[["seed", "event_id", "reason"]], on=["seed", "event_id"], how="left")
    by_reason["reason"] = by_reason["reason"].str.split("|").str[0]
    lines += ["", f"## {default[0]} {default[1]} by lane-change reason", "",
              "| reason | lane changes | predicted | mean advance final (s) |", "|---|---|---|---|"]
    for reason, g in by_reason.groupby("reason"):
        lines.append(f"| {reason} | {len(g)} | {_fmt(g['predicted'].mean(), True)} | "
                     f"{_fmt(g.loc[g['predicted'], 'advance_final_s'].mean())} |")
    if rule is not None:
        lines += ["", f"Rule baseline thresholds (fitted on training windows): dv = {rule.dv} m/s, gap = {rule.gap} m, "
                  f"blocked = {rule.block} m."]
    lines += ["", f"Baselines: {baselines['note']}."]
    if baselines["scored_on_their_training_seeds"]:
        lines.append(f"Split {split!r} holds the train seeds: the baselines are partly scored on the seeds they were "
                     "fitted on.")
    lines += ["", "![evaluation](evaluation.png)", ""]
    return "\n".join(lines)


def _plot(table: pd.DataFrame, per_event: dict, default, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    labels = [f"{r.predictor}\n{r.variant}" for r in table.itertuples()]
    pos = np.arange(len(table))
    axes[0].bar(pos, 100 * table["predicted_share"], color="tab:blue")
    axes[0].set_ylabel("lane changes predicted (%)")
    axes[0].set_xticks(pos, labels, rotation=90, fontsize=7)
    ax2 = axes[1]
    ax2.bar(pos, table["false_alarms_per_vehicle_hour"], color="tab:red")
    ax2.set_ylabel("false alarms per vehicle-hour")
    ax2.set_xticks(pos, labels, rotation=90, fontsize=7)
    ev = per_event[default]
    adv = ev.loc[ev["predicted"], "advance_final_s"]
    axes[2].hist(adv, bins=np.arange(0, max(12.0, float(adv.max()) + 0.5 if len(adv) else 12.0), 0.5), color="tab:green")
    axes[2].set_xlabel("advance before lane-change end (s), final positive run")
    axes[2].set_ylabel("lane changes")
    axes[2].set_title(f"{default[0]} {default[1]}")
    fig.tight_layout()
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110))
    finally:
        plt.close(fig)
