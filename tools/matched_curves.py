"""Two or more decision curves of `tools/real_alarms_cv.py` (curve.csv: the cross-fitted streams'
lane changes predicted, mean advance and false-alarm rates against the threshold) compared at
matched recall and at matched false alarms (docs/components/real-data.md, "Lateral speed over the
vehicle's own sway").

    python tools/matched_curves.py "NAME=WORK_DIR/curve.csv" ... [--shares 63/94,70/94] \
        [--rates all:1.7,all:5,judged:3.4] [--out FILE.md] [--agreement]

At each share: for each curve the threshold predicting at least that share of the pooled changes
(--recording: of one recording's) with the fewest false alarms, once for the headline rate and
once for the judged rate. At each rate:budget: the threshold predicting most changes within that
rate. Prints a Markdown table (and writes it to --out).

--agreement: instead, how far the curves lie apart (e.g. one model fine-tuned with several seeds):
for each pair, over the thresholds both hold, the mean and largest absolute difference of the
pooled lane changes predicted (count) and of the headline false alarms / veh-h, then the mean
over the pairs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from vcfusion.prediction.decision_curve import at_pooled_rate, at_share

RATE_NAME = {"all": "headline", "judged": "judged"}


def _cells(row: pd.Series | None) -> dict:
    if row is None:
        return {"threshold": "-", "predicted": "none reaches it"}
    return {"threshold": f"{row['threshold']:.2f}",
            "predicted": f"{100 * row['all_predicted']:.1f} %",
            "mean advance": f"{row['all_advance_s']:.2f} s",
            "false alarms / veh-h": f"{row['all_fa_per_veh_h']:.1f}",
            "judged / veh-h": f"{row['all_fa_judged_per_veh_h']:.1f}",
            "NGSIM": f"{100 * row['ngsim_predicted']:.0f} % / {row['ngsim_advance_s']:.2f} s / "
                     f"{row['ngsim_fa_per_veh_h']:.1f} (judged {row['ngsim_fa_judged_per_veh_h']:.1f})",
            "CommonRoad": f"{100 * row['cr_predicted']:.0f} % / {row['cr_advance_s']:.2f} s / "
                          f"{row['cr_fa_per_veh_h']:.1f} ({int(row['cr_fa_censored'])} of {int(row['cr_fa'])} "
                          "censored)"}


def agreement(curves: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """Per pair of curves, over the thresholds both hold: mean and largest |difference| of the share of
    pooled lane changes predicted (percentage points) and of the headline false alarms / veh-h; with
    more than one pair, a last row of the means over the pairs."""
    rows = []
    names = list(curves)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            m = curves[a].merge(curves[b], on="threshold", suffixes=("_a", "_b"))
            dp = (m["all_predicted_a"] - m["all_predicted_b"]).abs()
            dfa = (m["all_fa_per_veh_h_a"] - m["all_fa_per_veh_h_b"]).abs()
            rows.append({"pair": f"{a} / {b}", "thresholds": len(m),
                         "predicted: mean abs. difference (points)": 100 * dp.mean(),
                         "predicted: largest (points)": 100 * dp.max(),
                         "false alarms / veh-h: mean abs. difference": dfa.mean(),
                         "false alarms / veh-h: largest": dfa.max()})
    table = pd.DataFrame(rows)
    if len(table) > 1:
        table = pd.concat([table, table.drop(columns=["pair"]).mean().to_frame().T.assign(
            pair=f"mean over {len(rows)} pairs")], ignore_index=True)
    return table


def _markdown(table: pd.DataFrame, formats: dict[str, str] | None = None) -> str:
    """A Markdown table; float cells as ``formats[column]`` (default two decimals)."""
    formats = formats or {}
    cell = lambda column, v: format(v, formats.get(column, ".2f")) if isinstance(v, float) else str(v)  # noqa: E731
    lines = ["| " + " | ".join(table.columns) + " |", "|" + "---|" * len(table.columns)]
    return "\n".join(lines + ["| " + " | ".join(cell(c, v) for c, v in zip(table.columns, r)) + " |"
                                for r in table.itertuples(index=False)])


def _fraction(text: str) -> float:
    """0.67 or 63/94."""
    num, sep, den = text.partition("/")
    return float(num) / float(den) if sep else float(text)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("curves", nargs="+", help="NAME=curve.csv")
    p.add_argument("--shares", default="63/94,70/94",
                   help="pooled shares of lane changes predicted to match (0.67 or 63/94)")
    p.add_argument("--rates", default="all:1.7,judged:3.4", help="RATE:BUDGET pairs (rate all or judged) to match")
    p.add_argument("--recording", default="all",
                   help="match on this recording's share and rates (a curve.csv prefix: ngsim, cr), default pooled")
    p.add_argument("--out", type=Path)
    p.add_argument("--agreement", action="store_true",
                   help="how far the curves lie apart, pair by pair (mean and largest differences over the thresholds)")
    a = p.parse_args()
    curves = {}
    for item in a.curves:
        name, sep, path = item.partition("=")
        if not sep:
            p.error(f"{item!r}: expected NAME=curve.csv")
        if name in curves:
            p.error(f"{name!r}: given twice (each curve needs its own name)")
        curves[name] = pd.read_csv(path)
    if a.agreement:
        if len(curves) < 2:
            p.error("--agreement: expected at least two curves")
        text = _markdown(agreement(curves), {"thresholds": ".0f"})
        print(text)
        if a.out:
            a.out.write_text(text + "\n")
        return 0
    rows = []
    for share in (_fraction(x) for x in a.shares.split(",") if x):
        for rate in ("all", "judged"):
            for name, curve in curves.items():
                rows.append({"matched": f"{a.recording} share >= {100 * share:.1f} %, fewest {RATE_NAME[rate]} false alarms",
                             "model": name, **_cells(at_share(curve, share, rate, a.recording))})
    for item in (x for x in a.rates.split(",") if x):
        rate, _, budget = item.partition(":")
        for name, curve in curves.items():
            rows.append({"matched": f"{a.recording} {RATE_NAME[rate]} false alarms <= {float(budget):g} / veh-h, most changes",
                         "model": name, **_cells(at_pooled_rate(curve, float(budget), rate, a.recording))})
    text = _markdown(pd.DataFrame(rows).fillna(""))
    print(text)
    if a.out:
        a.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
