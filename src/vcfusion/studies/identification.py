"""Target identification study (the paper's Fig. 4, extended with latency, GNSS noise, detectors).

For every (frame, visible target twin) and every method (the paper's RGB-only baseline, our
nearest-centre RGB-only heuristic ``baseline_centre``, paper fusion = Algorithm 2, joint matcher;
see matching.py), the box the method chose and its IoU with the target's visible box (the box
around its largest patch of pixels, ``gt_x1`` .. ``gt_y2``; 0 when the method chose none). Accuracy
at an IoU threshold is the fraction of target-frames whose chosen box has at least that IoU. A
target is a neighbour twin whose vehicle is visible in the frame: a visible box of at least
``min_gt_area_px`` (default: the one definition's ``MIN_VISIBLE_PX``) covering at least
``MIN_VISIBLE_SHARE`` of its outline (vcfusion.metrics.highlights, which also gives each row's
``outcome`` at its IoU rule, as the guidance study counts highlights). Each row also records how
many detected boxes contain the target's anchor (``n_anchor_boxes``: 0 = none, 1 = the easy case,
>= 2 = the ambiguous case of Fig. 3 that depth is meant to resolve) and the scenario's name, so a
study over several scenarios can be read per scenario and per case.

`run_identification_study` runs the scenario(s) for each seed and each V2C condition (latency, GNSS
noise) with a frame source (the renderer), runs every detector on the same frames, and writes:
- ``identification_rows.parquet``: one row per (scenario, seed, condition, detector, frame, target, method);
- ``identification_accuracy_iou.csv`` + ``identification_accuracy_iou.png``: accuracy vs IoU
  threshold 0.5..0.95 per method and detector, at zero latency and noise (Fig. 4);
- ``identification_latency_noise.csv`` + ``identification_latency_noise.png``: accuracy at IoU 0.7
  vs latency (noise 0) and vs GNSS noise (latency 0), per method and detector.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from vcfusion.fusion.depth_eval import DepthEvalParams
from vcfusion.fusion.fuse import METHODS, CameraFrame, FusionResult, fuse_frame
from vcfusion.fusion.matching import JointMatcher, JointMatcherParams
from vcfusion.metrics.highlights import MIN_VISIBLE_PX, judge_highlight
from vcfusion.runio import atomic_write

IOU_THRESHOLDS = np.round(np.arange(0.5, 0.951, 0.05), 2)
ROW_COLUMNS = ["scenario", "seed", "latency_s", "gnss_noise_m", "detector", "time", "vehicle_id", "method", "n_anchor_boxes", "matched", "iou",
               "outcome", "x1", "y1", "x2", "y2", "gt_x1", "gt_y1", "gt_x2", "gt_y2"]


def identification_rows(frame: CameraFrame, result: FusionResult, min_gt_area_px: float = MIN_VISIBLE_PX,
                        **context) -> list[dict]:
    """Rows for the visible targets of one frame (context: scenario, seed, latency_s, gnss_noise_m,
    detector), each method's box judged by the one definition of a right highlight
    (vcfusion.metrics.highlights: ``outcome`` at its IoU rule, ``iou`` for any other threshold)."""
    gt = np.asarray(frame.visible_boxes, dtype=float).reshape(-1, 4)  # what the judgement compares with
    gt_index = {vid: k for k, vid in enumerate(frame.gt_ids)}
    rows = []
    for i, vid in enumerate(result.twin_ids):
        k = gt_index.get(vid)
        if k is None:
            continue
        g = gt[k]
        for method, chosen in result.choice.items():
            j = int(chosen[i])
            box = (np.nan,) * 4 if j < 0 else tuple(float(v) for v in result.detections.boxes[j])
            judged = judge_highlight(vid, None if j < 0 else box, gt, frame.gt_ids, frame.gt_visible_share,
                                     min_visible_px=min_gt_area_px)
            if not judged.visible:  # not a target: the target's visibility, the same for every method
                break
            n_cand = -1 if result.n_anchor_boxes is None else int(result.n_anchor_boxes[i])
            rows.append({**context, "time": round(float(frame.time), 6), "vehicle_id": vid, "method": method,
                         "n_anchor_boxes": n_cand, "matched": j >= 0, "iou": judged.iou, "outcome": judged.outcome,
                         "x1": box[0], "y1": box[1], "x2": box[2], "y2": box[3],
                         "gt_x1": g[0], "gt_y1": g[1], "gt_x2": g[2], "gt_y2": g[3]})
    return rows


def accuracy_vs_iou(rows: pd.DataFrame, thresholds=IOU_THRESHOLDS, by=("detector", "method")) -> pd.DataFrame:
    """Accuracy (fraction of target-frames with IoU >= threshold) per group and threshold."""
    by = [c for c in by if c in rows.columns]
    out = []
    groups = rows.groupby(by, sort=True) if by else [((), rows)]
    for key, grp in groups:
        key = key if isinstance(key, tuple) else (key,)
        iou = grp["iou"].to_numpy()
        for t in thresholds:
            out.append({**dict(zip(by, key)), "iou_threshold": float(t), "accuracy": float((iou >= t - 1e-12).mean()),
                        "n": len(iou)})
    return pd.DataFrame(out)


def accuracy_at(rows: pd.DataFrame, threshold: float = 0.7,
                by=("detector", "latency_s", "gnss_noise_m", "method")) -> pd.DataFrame:
    by = [c for c in by if c in rows.columns]
    g = rows.assign(ok=rows["iou"] >= threshold - 1e-12).groupby(by, sort=True)
    return g["ok"].agg(accuracy="mean", n="size").reset_index()


def write_study_outputs(rows: pd.DataFrame, out_dir, threshold: float = 0.7) -> dict[str, Path]:
    """CSV tables and plots of a study's rows (each file written atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {}
    clean = rows[(rows["latency_s"] == 0) & (rows["gnss_noise_m"] == 0)] if "latency_s" in rows else rows
    curve = accuracy_vs_iou(clean)
    sweep = accuracy_at(rows, threshold)
    paths["rows"] = out_dir / "identification_rows.parquet"
    atomic_write(paths["rows"], lambda p: rows.to_parquet(p, index=False))
    paths["accuracy_iou"] = out_dir / "identification_accuracy_iou.csv"
    atomic_write(paths["accuracy_iou"], lambda p: curve.to_csv(p, index=False, float_format="%.4f"))
    paths["latency_noise"] = out_dir / "identification_latency_noise.csv"
    atomic_write(paths["latency_noise"], lambda p: sweep.to_csv(p, index=False, float_format="%.4f"))

    styles = {"baseline": ("tab:blue", "RGB only (paper's baseline)"),
              "baseline_centre": ("tab:purple", "RGB only, nearest centre (ours)"),
              "paper": ("tab:orange", "RGB + depth (Alg. 2)"), "joint": ("tab:green", "joint matcher")}
    detectors = sorted(curve["detector"].unique()) if len(curve) else []
    fig, ax = plt.subplots(figsize=(6, 4))
    for det, ls in zip(detectors, ("-", "--", ":", "-.")):
        for method in METHODS:
            sel = curve[(curve["detector"] == det) & (curve["method"] == method)]
            if len(sel):
                colour, label = styles[method]
                ax.plot(sel["iou_threshold"], 100 * sel["accuracy"], ls, marker="o", ms=3, color=colour,
                        label=f"{label} [{det}]")
    ax.set_xlabel("IoU threshold")
    ax.set_ylabel("identification accuracy (%)")
    n_targets = int(clean.groupby(["detector", "method"]).size().max()) if len(clean) else 0  # per detector
    scen = ", ".join(sorted(clean["scenario"].dropna().unique())) if "scenario" in clean else ""
    ax.set_title(f"Target identification (latency 0, noise 0; {n_targets} target-frames)"
                 + (f"\n{scen}" if scen else ""), fontsize=9)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:  # a study without curves draws empty axes, not an empty legend
        ax.legend(fontsize=7)
    fig.tight_layout()
    paths["accuracy_iou_plot"] = out_dir / "identification_accuracy_iou.png"
    atomic_write(paths["accuracy_iou_plot"], lambda p: fig.savefig(p, dpi=120, format="png"))
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, (xcol, fixed, xlabel) in zip(axes, (("latency_s", "gnss_noise_m", "V2C latency (s)"),
                                                ("gnss_noise_m", "latency_s", "GNSS noise std (m)"))):
        sub = sweep[sweep[fixed] == 0]
        for det, ls in zip(detectors, ("-", "--", ":", "-.")):
            for method in METHODS:
                sel = sub[(sub["detector"] == det) & (sub["method"] == method)].sort_values(xcol)
                if len(sel):
                    colour, label = styles[method]
                    ax.plot(sel[xcol], 100 * sel["accuracy"], ls, marker="o", ms=3, color=colour, label=f"{label} [{det}]")
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"accuracy at IoU {threshold} (%)")
    if axes[1].get_legend_handles_labels()[0]:
        axes[1].legend(fontsize=7)
    fig.tight_layout()
    paths["latency_noise_plot"] = out_dir / "identification_latency_noise.png"
    atomic_write(paths["latency_noise_plot"], lambda p: fig.savefig(p, dpi=120, format="png"))
    plt.close(fig)
    return paths


# ---------------------------------------------------------------------------------------------
# the study runner


@dataclass(frozen=True)
class Condition:
    latency_s: float
    gnss_noise_m: float


def default_conditions(latencies=(0.0, 0.1, 0.2, 0.3, 0.5), noises=(0.0, 0.5, 1.0, 2.0)) -> list[Condition]:
    """Latency sweep at zero noise and noise sweep at zero latency (the clean run is shared)."""
    conds = [Condition(float(lat), 0.0) for lat in latencies]
    conds += [Condition(0.0, float(n)) for n in noises if n != 0.0]
    if Condition(0.0, 0.0) not in conds:
        conds.insert(0, Condition(0.0, 0.0))
    return conds


class _StudyHook:
    table = "identification"
    needs = ("neighbours",)  # its frames come from its own frame source, not the camera stage

    def __init__(self, frame_source, detectors: dict, seed: int, condition: Condition,
                 depth_params: DepthEvalParams, joint_params: JointMatcherParams, min_gt_area_px: float,
                 fallback_radius_px: float | None = None, scenario_name: str = "", refine: dict | None = None):
        self.frame_source = frame_source
        self.refine = refine or {}
        self.scenario_name = scenario_name
        self.detectors = detectors
        self.seed = seed
        self.condition = condition
        self.depth_params = depth_params
        self.joints = {name: JointMatcher(joint_params) for name in detectors}
        self.min_gt_area_px = min_gt_area_px
        self.fallback_radius_px = fallback_radius_px
        self.rngs = {name: np.random.default_rng([seed, k]) for k, name in enumerate(detectors)}
        self.rows: list[dict] = []
        self.depth_counts: dict = {}  # detector -> the depth step's counts

    def __call__(self, tick):
        if tick.neighbours is None or len(tick.neighbours) == 0:
            return None
        frame = self.frame_source(tick)
        if frame is None:
            return None
        for name, det in self.detectors.items():
            result = fuse_frame(frame, tick.neighbours, det, self.rngs[name], self.depth_params, self.joints[name],
                                fallback_radius_px=self.fallback_radius_px, refine=self.refine.get(name))
            mine = self.depth_counts.setdefault(name, {})
            for key, v in result.depth_counts.items():
                mine[key] = mine.get(key, 0) + v
            self.rows.extend(identification_rows(
                frame, result, self.min_gt_area_px, scenario=self.scenario_name, seed=self.seed, latency_s=self.condition.latency_s,
                gnss_noise_m=self.condition.gnss_noise_m, detector=name))
        return None  # the rows are collected here, not written into the run folder


def run_identification_study(scenarios, seeds, frame_source_factory, detectors: dict, out_dir,
                             conditions: list[Condition] | None = None, depth_params=DepthEvalParams(),
                             joint_params: JointMatcherParams = JointMatcherParams(), min_gt_area_px: float = MIN_VISIBLE_PX,
                             fallback_radius_px: float | None = None, progress: bool = True,
                             refine: dict | None = None) -> pd.DataFrame:
    """Run every (scenario, seed, condition), collect the rows, write the outputs; returns the rows.

    ``scenarios``: one Scenario or a list of them (each run with every seed; their names must differ).
    ``frame_source_factory(scenario, seed)`` gives the frame source of a run (the renderer);
    ``detectors`` maps a name to a detector (e.g. {'oracle': OracleDetector(), 'cnn': TorchDetector(...)});
    ``refine`` maps a detector's name to its depth-guided box refinement (absent: boxes as detected).
    """
    from vcfusion.cosim import CoSimulation
    from vcfusion.driver.idm import IdmController

    conditions = conditions or default_conditions()
    scenarios = list(scenarios) if isinstance(scenarios, (list, tuple)) else [scenarios]
    names = [sc.name for sc in scenarios]
    if len(set(names)) != len(names):
        raise ValueError(f"scenarios: expected distinct scenario names, got {names}")
    rows: list[dict] = []
    depth_counts: dict = {}
    jobs = [(scenario, seed, c) for scenario in scenarios for seed in seeds for c in conditions]
    for scenario, seed, cond in tqdm(jobs, desc="identification study", unit="run", disable=not progress):
        sc = scenario.model_copy(update={"v2c": scenario.v2c.model_copy(
            update={"latency_s": cond.latency_s, "gnss_noise_std_m": cond.gnss_noise_m})})
        # a new joint matcher per run and detector: its position filter holds per-run state
        hook = _StudyHook(frame_source_factory(sc, seed), detectors, seed, cond, depth_params, joint_params,
                          min_gt_area_px, fallback_radius_px, scenario.name, refine)
        CoSimulation(sc, seed, controller=IdmController.for_scenario(sc), hooks=[hook]).run()
        rows.extend(hook.rows)
        for name, counts in hook.depth_counts.items():
            mine = depth_counts.setdefault(name, {})
            for key, v in counts.items():
                mine[key] = mine.get(key, 0) + v
    frame = pd.DataFrame(rows, columns=ROW_COLUMNS)
    # what the depth step could not decide, per detector (boxes kept as detected, failed road fits)
    frame.attrs["depth_counts"] = depth_counts
    write_study_outputs(frame, out_dir)
    return frame


def summary_lines(rows: pd.DataFrame, threshold: float = 0.7) -> list[str]:
    """Human-readable figures: accuracy at the threshold per condition, detector and method (all
    scenarios together); then, at zero latency and noise, per scenario and per anchor case (how many
    boxes contain the anchor: 0, 1, >= 2)."""
    def fmt(grp):
        return "  ".join(f"{r.method} {100 * r.accuracy:5.1f}%" for r in grp.itertuples())

    acc = accuracy_at(rows, threshold)
    lines = []
    for (det, lat, noise), grp in acc.groupby(["detector", "latency_s", "gnss_noise_m"]):
        lines.append(f"{det:>8} latency {lat:.2f} s noise {noise:.1f} m (n={int(grp['n'].iloc[0])}): {fmt(grp)}")
    clean = rows[(rows["latency_s"] == 0) & (rows["gnss_noise_m"] == 0)] if "latency_s" in rows else rows
    if "scenario" in clean and clean["scenario"].nunique() > 1:
        for (det, scen), grp in accuracy_at(clean, threshold, by=("detector", "scenario", "method")).groupby(
                ["detector", "scenario"]):
            lines.append(f"{det:>8} clean, scenario {scen} (n={int(grp['n'].iloc[0])}): {fmt(grp)}")
    if "n_anchor_boxes" in clean and len(clean):
        case = clean.assign(anchor_case=clean["n_anchor_boxes"].clip(upper=2).map({0: "0", 1: "1", 2: ">=2"}))
        case = case[case["n_anchor_boxes"] >= 0]
        for (det, c), grp in accuracy_at(case, threshold, by=("detector", "anchor_case", "method")).groupby(
                ["detector", "anchor_case"]):
            lines.append(f"{det:>8} clean, anchor in {c:>3} boxes (n={int(grp['n'].iloc[0])}): {fmt(grp)}")
    return lines
