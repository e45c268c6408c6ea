"""How CommonRoad's censored false alarms might have turned out, estimated on NGSIM's long tracks
(docs/components/real-data.md, "Censoring-aware false-alarm rates"): on the cross-fitted streams of a
finished `tools/real_alarms_cv.py` work folder, at each threshold (aggressive smoothing, tau_a
ticks), each NGSIM alarm run is cut as CommonRoad's censored alarms are cut by their tracks' ends
(`vcfusion.prediction.decision_curve.censored_alarm_outcomes`), and the full NGSIM track says
whether the censored-like alarm was true or false.

    python tools/censored_alarm_check.py CV_WORK_DIR [--thresholds 0.31 0.38 0.53] [--tau-ticks 50]

Run from the repository root (it reads splits/); a minute on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_alarms_cv import out_of_fold  # noqa: E402

from vcfusion.prediction.decision_curve import censored_alarm_outcomes  # noqa: E402
from vcfusion.prediction.events import smooth_stream, smoothing_bounds  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("work", help="a finished tools/real_alarms_cv.py work folder (ft_cv*.npz, fold datasets)")
    p.add_argument("--thresholds", type=float, nargs="+", default=[0.31, 0.38, 0.53])
    p.add_argument("--tau-ticks", type=int, default=50)
    a = p.parse_args()
    stream, events = out_of_fold(Path(a.work))
    prob, stretches = stream["prob"].to_numpy(), smoothing_bounds(stream)
    print("| threshold | CommonRoad censored false alarms (median span observed after the start) | NGSIM runs | "
          "censored-like (run, span) pairs: false | distinct runs: false |")
    print("|---|---|---|---|---|")
    for thr in a.thresholds:
        dec = smooth_stream(stretches, (prob > thr).astype(np.int8), "aggressive", a.tau_ticks, a.tau_ticks)
        r = censored_alarm_outcomes(stream, dec, events, 10.0, short="cr", long="ngsim")
        share = lambda n, k: f"{k} of {n} ({k / n:.0%})" if n else "-"  # noqa: E731
        print(f"| {thr:.2f} | {r['short_censored_false_alarms']} ({r['short_span_median_s']:.1f} s) | {r['long_runs']} | "
              f"{share(r['pairs'], r['pairs_false'])} | {share(r['runs'], r['runs_false'])} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
