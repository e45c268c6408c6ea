"""False alarms cut off by a track's end (censored), the judged (censoring-aware) rate and its decision
choice, and decision settings written into a model file
(`vcfusion set-decision`), on hand-made streams and a tiny GRU."""

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vcfusion.commands import main
from vcfusion.prediction.cloud import LaneChangePredictor
from vcfusion.prediction.decision_curve import (censored_alarm_outcomes, choose_threshold, threshold_curve,
                                                weak_judged_bounds)
from vcfusion.prediction.events import event_scores, false_alarm_rate, judged_ticks, track_bounds
from vcfusion.prediction.features import SEQUENCE_INPUT_SETS
from vcfusion.prediction.model import load_model
from vcfusion.prediction.sequence import SequenceModel, save_sequence_model
from vcfusion.prediction.train import choose_default, tune_decisions
from vcfusion.prediction.transfer import bootstrap
from vcfusion.traffic.network import Road


def _stream(tracks: dict[str, float]) -> pd.DataFrame:
    """One seed; each vehicle observed from 0 s to its given last time, every 0.1 s."""
    frames = [pd.DataFrame({"seed": 0, "vehicle_id": vid, "time": np.round(np.arange(0.0, last + 1e-9, 0.1), 1)})
              for vid, last in tracks.items()]
    return pd.concat(frames, ignore_index=True)


def _on(stream: pd.DataFrame, vid: str, a: float, b: float) -> np.ndarray:
    t = stream["time"].to_numpy()
    return ((stream["vehicle_id"].to_numpy() == vid) & (t >= a - 1e-9) & (t <= b + 1e-9)).astype(np.int8)


def test_false_alarms_whose_confirming_window_passes_the_track_end_are_counted_apart():
    # "short": an 8 s track with an alarm at 3-4 s (window to 14 s: censored);
    # "long": 40 s, an alarm at 5-6 s (window to 16 s, observed: a plain false alarm) and one at
    # 20-21 s before its change ending at 25 s (a hit, neither false nor censored)
    stream = _stream({"long": 40.0, "short": 8.0})
    events = pd.DataFrame({"seed": [0], "event_id": [1], "vehicle_id": ["long"], "end": [25.0], "mid": [23.0]})
    dec = _on(stream, "short", 3.0, 4.0) | _on(stream, "long", 5.0, 6.0) | _on(stream, "long", 20.0, 21.0)
    fa, censored = {}, {}
    summary, per_event = event_scores(stream, dec, events, 0.1, 10.0, track_bounds(stream), fa, censored)
    assert summary["alarms"] == 3 and summary["false_alarms"] == 2 and summary["false_alarms_censored"] == 1
    assert fa == {(0, "long"): 1, (0, "short"): 1} and censored == {(0, "short"): 1}
    assert bool(per_event["predicted"].iloc[0])
    # with a 3 s horizon the short track's window (to 7 s) is observed: not censored (and the alarm
    # 4 s before the change is now false too)
    summary3, _ = event_scores(stream, dec, events, 0.1, 3.0, track_bounds(stream))
    assert summary3["false_alarms_censored"] == 0 and summary3["false_alarms"] == 3


def test_bootstrap_gives_the_censored_share_of_the_false_alarms():
    table = pd.DataFrame({"lane_changes": [1, 0], "predicted": [1, 0], "before_mid": [1, 0], "advance_sum_s": [3.0, 0.0],
                          "false_alarms": [1, 3], "false_alarms_censored": [0, 3], "hours": [1.0, 1.0],
                          "judged_hours": [0.5, 0.0]})
    got = bootstrap(table, n_boot=500, seed=0)
    assert got["censored_false_alarms_share"]["value"] == pytest.approx(0.75)
    # judged: the one uncensored false alarm over the 0.5 h where a window fits; the headline rate stays 4 / 2 h
    assert got["false_alarms_judged_per_veh_h"]["value"] == pytest.approx(2.0)
    assert got["false_alarms_per_veh_h"]["value"] == pytest.approx(2.0)
    # resamples of the second vehicle alone have no judged exposure (undefined, left out); all others give 2
    assert got["false_alarms_judged_per_veh_h"]["low"] == got["false_alarms_judged_per_veh_h"]["high"] == 2.0
    assert got["censored_false_alarms_share"]["low"] == 0.0 and got["censored_false_alarms_share"]["high"] == 1.0


def _tiny_gru(threshold=0.3) -> SequenceModel:
    names = SEQUENCE_INPUT_SETS["lateral"]
    rng = np.random.default_rng(0)
    f, h = len(names), 4
    return SequenceModel(tuple(names), np.zeros(f), np.full(f, 10.0), rng.normal(0, 0.5, (3 * h, f)),
                         rng.normal(0, 0.5, (3 * h, h)), np.zeros(3 * h), np.zeros(3 * h), rng.normal(0, 1.0, (1, h)),
                         np.array([0.0]), tau=5.0, tau_g=2.0, period_s=0.1, threshold=threshold,
                         thresholds={"aggressive": threshold, "conservative": 0.6}, smoothing="aggressive",
                         tau_a_ticks=10, tau_c_ticks=5, calibration=(0.8, -0.2))


def test_set_decision_writes_the_settings_and_the_reason_and_keeps_the_weights(tmp_path):
    src = tmp_path / "gru.npz"
    save_sequence_model(_tiny_gru(), src)
    out = tmp_path / "gru-set.npz"
    assert main(["set-decision", str(src), "--out", str(out), "--smoothing", "aggressive", "--threshold", "0.43",
                 "--tau-ticks", "50", "--reason", "cross-fitted validation streams"]) == 0
    before, after = load_model(src), load_model(out)
    assert (after.smoothing, after.threshold_for("aggressive"), after.tau_a_ticks) == ("aggressive", 0.43, 50)
    assert after.threshold_for("conservative") == 0.6 and after.tau_c_ticks == 5  # the other smoothing unchanged
    assert after.calibration == before.calibration
    assert np.array_equal(after.w_ih, before.w_ih) and np.array_equal(after.w_out, before.w_out)
    note = after.info["decision_set"]
    assert note["reason"] == "cross-fitted validation streams" and note["replaced"]["thresholds"]["aggressive"] == 0.3
    # the cloud's predictor decides with the written settings
    pred = LaneChangePredictor(after, Road("hw", (0.0, 0.0), (2000.0, 0.0), 3, 3.5, 25.0), 0.1)
    assert pred.threshold == 0.43 and pred.smoother.tau_a == 50
    # conservative: the window goes to tau_c
    cons = tmp_path / "gru-cons.npz"
    assert main(["set-decision", str(src), "--out", str(cons), "--smoothing", "conservative", "--threshold", "0.5",
                 "--tau-ticks", "20", "--reason", "r"]) == 0
    c = load_model(cons)
    assert (c.smoothing, c.threshold_for("conservative"), c.tau_c_ticks, c.tau_a_ticks) == ("conservative", 0.5, 20, 10)


@pytest.mark.parametrize("args", [["--threshold", "1.5", "--reason", "r"], ["--threshold", "0.4", "--reason", " "],
                                  ["--threshold", "0.4", "--tau-ticks", "-1", "--reason", "r"]])
def test_set_decision_refuses_bad_settings_and_writes_nothing(tmp_path, args, capsys):
    src = tmp_path / "gru.npz"
    save_sequence_model(_tiny_gru(), src)
    out = tmp_path / "x.npz"
    assert main(["set-decision", str(src), "--out", str(out), "--smoothing", "aggressive", *args]) == 2
    assert not out.exists()
    err = capsys.readouterr().err
    assert any(word in err for word in ("threshold", "reason", "tau ticks"))


def test_set_decision_does_not_replace_a_file_unasked(tmp_path):
    src = tmp_path / "gru.npz"
    save_sequence_model(_tiny_gru(), src)
    out = tmp_path / "exists.npz"
    out.write_bytes(b"keep")
    args = ["set-decision", str(src), "--out", str(out), "--smoothing", "none", "--threshold", "0.5", "--reason", "r"]
    assert main(args) == 2 and out.read_bytes() == b"keep"
    assert main(args + ["--force"]) == 0 and load_model(out).smoothing == "none"
    assert json.loads(json.dumps(load_model(out).info["decision_set"]))["from"] == Path(src).name


# ---------------------------------------------------------------- the judged (censoring-aware) rate

def test_judged_rate_leaves_a_censored_alarm_out_of_both_count_and_exposure():
    # "long" (0-40 s): a false alarm at 5-6 s (judged) and one at 29-30 s (its window ends at 40 s,
    # the last tick: judged too); "mid" (0-20 s): a false alarm at 15-16 s, in its last 10 s
    # (censored); "short" (0-8 s): a false alarm at 3-4 s (censored; the track adds no exposure)
    stream = _stream({"long": 40.0, "mid": 20.0, "short": 8.0})
    events = pd.DataFrame(columns=["seed", "event_id", "vehicle_id", "end", "mid"])
    dec = (_on(stream, "long", 5.0, 6.0) | _on(stream, "long", 29.0, 30.0) | _on(stream, "mid", 15.0, 16.0)
           | _on(stream, "short", 3.0, 4.0))
    summary, _ = event_scores(stream, dec, events, 0.1, 10.0, track_bounds(stream))
    assert summary["false_alarms"] == 4 and summary["false_alarms_censored"] == 2
    assert summary["false_alarms_judged"] == 2
    # exposure: long 0..30 s (301 ticks), mid 0..10 s (101 ticks), short none
    assert summary["judged_vehicle_hours"] == pytest.approx((301 + 101) * 0.1 / 3600)
    assert summary["false_alarms_judged_per_vehicle_hour"] == pytest.approx(2 / ((301 + 101) * 0.1 / 3600))
    # the headline rate is unchanged: every false alarm over every tick
    assert summary["false_alarms_per_vehicle_hour"] == pytest.approx(4 / (len(stream) * 0.1 / 3600))
    assert false_alarm_rate(summary, "judged") == summary["false_alarms_judged_per_vehicle_hour"]
    assert false_alarm_rate(summary, "all") == summary["false_alarms_per_vehicle_hour"]
    with pytest.raises(ValueError, match="judged"):
        false_alarm_rate(summary, "uncensored")
    # moved one tick later the long track's second alarm is censored and leaves the count
    late = dec.copy()
    late[_on(stream, "long", 30.1, 30.1) == 1] = 1
    s2, _ = event_scores(stream, late, events, 0.1, 10.0, track_bounds(stream))
    assert s2["false_alarms_judged"] == 1 and s2["false_alarms"] == 4
    assert s2["judged_vehicle_hours"] == summary["judged_vehicle_hours"]


def test_judged_rate_is_undefined_without_exposure():
    stream = _stream({"short": 8.0})
    events = pd.DataFrame(columns=["seed", "event_id", "vehicle_id", "end", "mid"])
    summary, _ = event_scores(stream, _on(stream, "short", 1.0, 2.0), events, 0.1, 10.0, track_bounds(stream))
    assert summary["judged_vehicle_hours"] == 0.0 and np.isnan(summary["false_alarms_judged_per_vehicle_hour"])
    assert judged_ticks(np.arange(0.0, 8.05, 0.1), 10.0) == 0
    assert judged_ticks(np.round(np.arange(0.0, 12.05, 0.1), 1), 10.0) == 21  # 0.0 .. 2.0 s


def _tuning_case() -> tuple[pd.DataFrame, pd.DataFrame, np.ndarray]:
    """Two 60 s tracks, each with a change ending at 40 s: "a" rises to 0.9 before it, "b" only to
    0.4; five 8 s tracks at 0.4 for a second (alarms that no window confirms: all censored)."""
    stream = _stream({"a": 60.0, "b": 60.0, **{f"s{i}": 8.0 for i in range(5)}})
    events = pd.DataFrame({"seed": [0, 0], "event_id": [1, 2], "vehicle_id": ["a", "b"], "end": [40.0, 40.0],
                           "mid": [38.0, 38.0]})
    prob = np.full(len(stream), 0.05)
    prob[_on(stream, "a", 36.0, 39.0) == 1] = 0.9
    prob[_on(stream, "b", 36.0, 39.0) == 1] = 0.4
    for i in range(5):
        prob[_on(stream, f"s{i}", 2.0, 3.0) == 1] = 0.4
    return stream, events, prob


def test_tuning_with_the_judged_rate_is_not_held_back_by_censored_alarms():
    stream, events, prob = _tuning_case()
    headline = tune_decisions(prob, stream, events, 0.1, 10.0, max_false_alarms=5.0)
    judged = tune_decisions(prob, stream, events, 0.1, 10.0, max_false_alarms=5.0, false_alarm_rate="judged")
    # the headline rate counts the five censored alarms (5 in 160 s): the threshold must rise above 0.4
    # and the weak change is lost; the judged rate has none to count and keeps both changes
    assert headline["aggressive"]["threshold"] >= 0.4 and headline["aggressive"]["validation"]["predicted_share"] == 0.5
    assert judged["aggressive"]["threshold"] < 0.4 and judged["aggressive"]["validation"]["predicted_share"] == 1.0
    assert judged["aggressive"]["validation"]["false_alarms_censored"] == 5
    assert choose_default(judged, 5.0, "judged") == "aggressive"


def test_tuning_with_the_judged_rate_needs_judged_exposure():
    stream = _stream({f"s{i}": 8.0 for i in range(3)})
    events = pd.DataFrame(columns=["seed", "event_id", "vehicle_id", "end", "mid"])
    with pytest.raises(ValueError, match="confirming window"):
        tune_decisions(np.full(len(stream), 0.5), stream, events, 0.1, 10.0, false_alarm_rate="judged")


def test_per_recording_choice_bounds_the_rate_named():
    stream, events, prob = _tuning_case()
    stream = stream.assign(prob=prob, source=np.where(stream["vehicle_id"].str.startswith("s"), "short", "long"))
    curve = threshold_curve(stream, events, (0.3, 0.5), 10, 0.1, 10.0)
    assert curve["short_fa_censored"].tolist() == [5, 0] and curve["short_judged_veh_h"].tolist() == [0.0, 0.0]
    assert curve["long_fa_judged_per_veh_h"].tolist() == [0.0, 0.0]
    assert choose_threshold(curve, 5.0, ["long", "short"])["threshold"] == 0.5
    # the judged rate of a recording with no judged exposure cannot be bounded: an error, not a pass
    with pytest.raises(ValueError, match="short: no judged exposure"):
        choose_threshold(curve, 5.0, ["long", "short"], "judged")
    chosen = choose_threshold(curve, 5.0, ["long"], "judged")
    assert chosen["threshold"] == 0.3
    # 100 s of judged exposure on "long" is under 1 / 5 h: a single judged false alarm would break the budget
    assert chosen["long_judged_veh_h"] == pytest.approx(2 * 501 * 0.1 / 3600)
    notes = weak_judged_bounds(chosen, 5.0, ["long", "short"])
    assert len(notes) == 2 and notes[1].startswith("short: judged exposure 0.000") and "5 censored" in notes[1]
    assert weak_judged_bounds(chosen, 100.0, ["long"]) == []  # 1 / 100 h = 36 s < 100.2 s
    assert choose_threshold(curve.iloc[[0]], 5.0, ["long", "short"]) is None  # 5 alarms in 40 s


def test_censored_alarm_outcomes_cut_long_tracks_as_short_ones_are_cut():
    # short track "c" (0-8 s): a false alarm at 5-6 s, censored, observed 3 s after its start.
    # long track "L" (0-60 s): a run at 10-11 s before a change ending at 20 s (cut at 13 s:
    # unconfirmed there, true in full); a run at 30-31 s with no change (cut: unconfirmed, false);
    # a run at 44-45 s before a change ending at 46 s (confirmed within the cut); a run at 55-56 s
    # (its full window passes the track's end: left out)
    stream = _stream({"L": 60.0, "c": 8.0})
    stream["source"] = np.where(stream["vehicle_id"] == "c", "short", "long")
    events = pd.DataFrame({"seed": [0, 0], "event_id": [1, 2], "vehicle_id": ["L", "L"], "end": [20.0, 46.0],
                           "mid": [18.0, 45.0]})
    dec = (_on(stream, "c", 5.0, 6.0) | _on(stream, "L", 10.0, 11.0) | _on(stream, "L", 30.0, 31.0)
           | _on(stream, "L", 44.0, 45.0) | _on(stream, "L", 55.0, 56.0))
    got = censored_alarm_outcomes(stream, dec, events, 10.0, short="short", long="long")
    assert got["short_censored_false_alarms"] == 1 and got["short_span_median_s"] == pytest.approx(3.0)
    assert got["long_runs"] == 4
    assert (got["pairs"], got["pairs_false"], got["runs"], got["runs_false"]) == (2, 1, 2, 1)


def test_two_curves_compared_at_matched_share_and_matched_rate():
    from vcfusion.prediction.decision_curve import at_pooled_rate, at_share

    curve = pd.DataFrame({"threshold": [0.3, 0.4, 0.5, 0.6],
                          "all_predicted": [0.80, 0.75, 0.75, 0.60],
                          "all_advance_s": [3.5, 3.0, 3.2, 2.5],
                          "all_fa_per_veh_h": [9.0, 4.0, 4.0, 1.0],
                          "all_fa_judged_per_veh_h": [2.0, 3.0, 1.0, 0.5]})
    # at least 75 %: the fewest headline alarms (a tie: the longer advance), the fewest judged ones
    assert at_share(curve, 0.75)["threshold"] == 0.5
    assert at_share(curve, 0.75, "judged")["threshold"] == 0.5
    assert at_share(curve, 0.79, "judged")["threshold"] == 0.3
    assert at_share(curve, 0.9) is None
    # within 4 alarms / veh-h: most changes (a tie: the longer advance); within 0.9 none
    assert at_pooled_rate(curve, 4.0)["threshold"] == 0.5
    assert at_pooled_rate(curve, 2.5, "judged")["threshold"] == 0.3
    assert at_pooled_rate(curve, 0.9) is None
    with pytest.raises(ValueError, match="false-alarm rate"):
        at_share(curve, 0.5, "censored")
    # one recording's columns instead of the pooled ones
    rec = curve.rename(columns=lambda c: c.replace("all_", "ngsim_")).assign(all_predicted=0.0)
    assert at_share(rec, 0.75, recording="ngsim")["threshold"] == 0.5 and at_share(rec, 0.75) is None
    assert at_pooled_rate(rec, 2.5, "judged", recording="ngsim")["threshold"] == 0.3
