"""Why each warning of a run was highlighted right, wrong or not at all (`vcfusion explain-highlights`).

From a run folder with the camera fusing (its ``fusion`` table: one judged row per twin in view
and AR update, `vcfusion.metrics.highlights`): one row per warning episode (a run of AR updates
in which a warned twin has the same outcome and the same vehicle in its box, as the guidance
study counts them) with the twin, the drawn box, the vehicle inside it, its IoU with the twin's
visible box and a sentence saying why the episode is right, wrong, missed or unseen. Where the
run recorded its AR frames (``frames/NNNNNN.png``, scenario ``ar.video``), the frame in the middle
of each episode is copied with the judgement written under it.

Writes OUT/highlights.csv, OUT/highlights.md and OUT/frames/ (when the run has frames).
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.errors import InputError
from vcfusion.metrics.highlights import MIN_VISIBLE_PX, MIN_VISIBLE_SHARE, RIGHT_IOU, is_visible, warning_episodes

COLUMNS = ["episode", "twin", "outcome", "start_s", "end_s", "updates", "bridged", "level", "lc_prob_max",
           "box_vehicle_id",
           "gt_iou", "visible_px", "visible_share", "x1", "y1", "x2", "y2", "frame", "undrawn", "why"]


UNDRAWN_WHY = {"no_match": "no box was matched to its twin",
               "hidden": "a box was matched but not drawn: the twins in front of it hide its whole outline, or most "
                         "of it (fusion.fuse.MOSTLY_HIDDEN_SHARE), and the box's depth does not put it at the twin "
                         "(fusion.fuse.HIDDEN_DEPTH_CONFIRM_SIGMAS)",
               "small": "a box was matched but not drawn: the part of the twin's outline the twins in front "
                        "leave visible is under 50 px (fusion.fuse.MIN_DRAWN_VISIBLE_PX)",
               "too_large": "a box was matched but not drawn: it is too large for the twin's outline"}


def _unseen_words(visible_px: float, visible_share: float) -> str:
    """Why a vehicle is not visible, in words (vcfusion.metrics.highlights.is_visible)."""
    if visible_px == 0:
        return "not in the frame"
    if visible_px < MIN_VISIBLE_PX:
        return f"the box around its largest patch in the frame is {visible_px:.0f} px, < {MIN_VISIBLE_PX:g} px"
    return (f"its {visible_px:.0f} px visible box is {visible_share:.2f} of its outline, < {MIN_VISIBLE_SHARE:g}: "
            "a sliver beside what hides it")


def why(outcome: str, twin: str, shown: str, iou: float, visible_px: float, undrawn: str = "no_match",
        visible_share: float = 1.0) -> str:
    """The judgement of one AR update in words (the rules of vcfusion.metrics.highlights;
    `undrawn`: why nothing was drawn, vcfusion.fusion.fuse.undrawn_reason; `visible_share`: 1 for
    tables written before it was recorded, whose judgements did not use it)."""
    if outcome == "right":
        return (f"the box drawn for {twin} lies on {twin}: IoU {iou:.2f} with its visible box "
                f"(>= {RIGHT_IOU:g})")
    if outcome == "wrong":
        if not is_visible(visible_px, visible_share):
            return (f"a box is drawn for {twin}, whose vehicle the driver cannot see "
                    f"({_unseen_words(visible_px, visible_share)}); the box shows {shown or 'no vehicle'}")
        if shown == twin:
            return (f"the box drawn for {twin} covers only part of it or much around it: IoU {iou:.2f} with its "
                    f"visible box (< {RIGHT_IOU:g})")
        return (f"the box drawn for {twin} shows {shown or 'no vehicle'}: IoU {iou:.2f} with {twin}'s visible box "
                f"(< {RIGHT_IOU:g})")
    if outcome == "missed":
        return (f"{twin} is visible ({visible_px:.0f} px) and warned, but "
                f"{UNDRAWN_WHY.get(undrawn, UNDRAWN_WHY['no_match'])}: nothing drawn")
    return (f"{twin} is warned but not visible ({_unseen_words(visible_px, visible_share)}: hidden or too small); "
            "nothing drawn, not a miss")


def explain_episodes(fusion: pd.DataFrame, period_s: float) -> pd.DataFrame:
    """One row per warning episode of a judged ``fusion`` table (COLUMNS); the box, IoU and frame
    are the episode's middle update's."""
    from vcfusion.guidance import WARNING_LEVELS

    if "outcome" not in fusion:
        raise InputError("fusion table: no 'outcome' column (the judged highlight of each twin); expected a run "
                         "written by a version that judges highlights (vcfusion.metrics.highlights)")
    warned = fusion[fusion["level"].isin(WARNING_LEVELS)].sort_values("time", kind="stable").reset_index(drop=True)
    rows = []
    for episode in warning_episodes(warned, period_s):
        twin, outcome, shown = episode.twin, episode.outcome, episode.box_vehicle_id
        ep = warned.iloc[list(episode.rows)]
        mid = ep.iloc[len(ep) // 2]
        frame = int(mid["frame"]) if "frame" in ep and not pd.isna(mid["frame"]) else -1
        share = float(mid["visible_share"]) if "visible_share" in ep else 1.0
        rows.append({"twin": str(twin), "outcome": str(outcome), "start_s": float(ep["time"].iloc[0]),
                     "end_s": float(ep["time"].iloc[-1]), "updates": len(ep), "bridged": episode.bridged,
                     "level": "high" if (ep["level"] == "high").any() else "medium",
                     "lc_prob_max": float(ep["lc_prob"].max()), "box_vehicle_id": str(shown),
                     "gt_iou": float(mid["gt_iou"]), "visible_px": float(mid["visible_px"]), "visible_share": share,
                     "x1": float(mid["x1"]), "y1": float(mid["y1"]), "x2": float(mid["x2"]), "y2": float(mid["y2"]),
                     "frame": frame,
                     "undrawn": str(mid["undrawn"]) if "undrawn" in ep else "",
                     "why": why(str(outcome), str(twin), str(shown), float(mid["gt_iou"]), float(mid["visible_px"]),
                                str(mid["undrawn"]) if "undrawn" in ep and mid["undrawn"] else "no_match", share)
                      + (f"; {episode.bridged} update(s) without a box inside it, spanned by the driver's "
                         "warning hold (a flicker, no missed warning)" if episode.bridged else "")})
    out = pd.DataFrame(rows, columns=[c for c in COLUMNS if c != "episode"])
    out = out.sort_values(["start_s", "twin"]).reset_index(drop=True)
    out.insert(0, "episode", np.arange(len(out)))
    return out


def _caption(src: Path, dst: Path, row) -> None:
    """Copy of the frame with the episode's judgement written in a band under it."""
    import cv2

    image = cv2.imread(str(src))
    if image is None:
        shutil.copyfile(src, dst)
        return
    colour = {"right": (60, 160, 60), "wrong": (40, 40, 220), "missed": (0, 140, 255)}.get(row.outcome, (128, 128, 128))
    if not math.isnan(row.x1):  # the drawn box, outlined again in the judgement's colour
        cv2.rectangle(image, (int(round(row.x1)) - 2, int(round(row.y1)) - 2),
                      (int(round(row.x2)) + 2, int(round(row.y2)) + 2), colour, 1, cv2.LINE_AA)
    w = image.shape[1]
    words, lines, line = f"{row.start_s:.1f}-{row.end_s:.1f} s {row.outcome.upper()}: {row.why}".split(), [], ""
    for word in words:  # wrap to the image's width
        if len(line) + len(word) + 1 > max(20, w // 7):
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    lines.append(line)
    band = np.full((18 * len(lines) + 8, w, 3), 255, np.uint8)
    for k, text in enumerate(lines):
        cv2.putText(band, text, (4, 18 * (k + 1)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    cv2.imwrite(str(dst), np.vstack([image, band]))


def explain_run(folder: Path, out: Path) -> dict:
    """Explain the warning episodes of run folder `folder` into `out` (see the module doc)."""
    from vcfusion.runio import atomic_folder
    from vcfusion.studies.from_runs import load_run_folder

    folder = Path(folder)
    trip = load_run_folder(folder)
    sc = trip.run["scenario"]
    fusion = trip.run["tables"].get("fusion")
    if not sc.fusion.enabled or fusion is None:
        raise InputError(f"{folder}: the run did not fuse a camera (scenario fusion.enabled is false): its highlights "
                         "mark the cloud's twins themselves, with no box to explain; expected a run with the camera "
                         "and fusion on")
    episodes = explain_episodes(fusion, sc.v2c.period_s)
    frames_dir = folder / "frames"
    has_frames = frames_dir.is_dir()
    counts = episodes["outcome"].value_counts().to_dict()
    with atomic_folder(Path(out)) as tmp:
        tmp = Path(tmp)
        episodes.to_csv(tmp / "highlights.csv", index=False)
        if has_frames:
            (tmp / "frames").mkdir()
            for row in episodes.itertuples(index=False):
                src = frames_dir / f"{row.frame:06d}.png"
                if row.frame >= 0 and src.is_file():
                    _caption(src, tmp / "frames" / f"episode{row.episode:04d}_{row.twin}_{row.outcome}.png", row)
        head = (f"# Highlights of {folder.name} (scenario {sc.name}, seed {trip.seed}, {trip.driver_kind} driver, "
                f"arm {trip.arm})\n\n"
                f"Warning episodes: " + ", ".join(f"{counts.get(k, 0)} {k}" for k in ("right", "wrong", "missed", "unseen"))
                + f" (rules: vcfusion.metrics.highlights, IoU >= {RIGHT_IOU:g}, visible >= {MIN_VISIBLE_PX:g} px and >= "
                f"{MIN_VISIBLE_SHARE:g} of the outline).\n"
                + ("" if has_frames else "\nThe run recorded no AR frames (scenario ar.video false): no images.\n")
                + "\n| # | twin | outcome | time [s] | updates | box shows | IoU | visible px | share | why |\n"
                "|---|---|---|---|---|---|---|---|---|---|\n")
        body = "".join(f"| {r.episode} | {r.twin} | {r.outcome} | {r.start_s:.1f}-{r.end_s:.1f} | {r.updates} | "
                       f"{r.box_vehicle_id or '-'} | {r.gt_iou:.2f} | {r.visible_px:.0f} | {r.visible_share:.2f} | {r.why} |\n"
                       for r in episodes.itertuples(index=False))
        (tmp / "highlights.md").write_text(head + body)
    return {"episodes": episodes, "counts": counts, "frames": has_frames}
