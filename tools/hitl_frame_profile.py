"""Where a paced drive's display loop spends each frame period: a drive of `accident_ar` at real
speed (vision beside the loop, headless, the keyboard idle) with the loop's parts timed.

    PYOPENGL_PLATFORM=osmesa PYTHONPATH=src python tools/hitl_frame_profile.py [--max-time 17.6] [--json OUT]
        [--full-gc-at 10.0]

Every part below is wrapped with a timer that records its own wall and CPU time (its children's
taken out): SUMO steps, the truth read, each tick stage (camera render, the hand-over to the vision
worker, metrics, ...), the display's render, the overlay carried to the frame, compose, the
window's blit and flip, the scoring of the drawn boxes, the vision result read, the pacing sleep,
and Python's garbage collections (gc.callbacks). The time of each part is attributed to the
display frame period it falls in (from one due display frame's step to the next). Printed: per
part, the median and 99th percentile per frame period and its share of the frames that overran the
33.3 ms budget (loop work above the frame period), the dropped frames and how many of them were
due at a V2C tick (0.1 s), the loop's CPU per simulated second, then the 15 worst frame periods
part by part and the collections over 1 ms inside the drive. `--full-gc-at T` makes one full
collection at simulated time T (what one costs inside a drive).
A measuring tool: its wrappers add a few microseconds per call.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


class Timeline:
    def __init__(self):
        self.events: list[tuple[str, float, float, float]] = []  # (part, start wall, self wall, self cpu)
        self._stack: list[list[float]] = []  # [child wall, child cpu] of the open parts
        self._gc_start: tuple[float, float] | None = None
        self.samples: list[tuple[float, float, int]] = []  # (wall, process CPU, involuntary switches) per SUMO step

    def sample(self):
        self.samples.append((time.perf_counter(), time.process_time(),
                             resource.getrusage(resource.RUSAGE_THREAD).ru_nivcsw))

    def wrap(self, name: str, fn):
        tl = self

        def timed(*args, **kwargs):
            tl._stack.append([0.0, 0.0])
            w0, c0 = time.perf_counter(), time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                w1, c1 = time.perf_counter(), time.thread_time()
                child_w, child_c = tl._stack.pop()
                w, c = w1 - w0, c1 - c0
                tl.events.append((name, w0, w - child_w, c - child_c))
                if tl._stack:
                    tl._stack[-1][0] += w
                    tl._stack[-1][1] += c
        timed.__wrapped__ = fn
        return timed

    def gc_callback(self, phase, info):
        if phase == "start":
            self._gc_start = (time.perf_counter(), time.thread_time())
        elif self._gc_start is not None:
            w0, c0 = self._gc_start
            w, c = time.perf_counter() - w0, time.thread_time() - c0
            self.events.append((f"gc{info['generation']}", w0, w, c))
            if self._stack:  # the part the collection interrupted does not own its time
                self._stack[-1][0] += w
                self._stack[-1][1] += c
            self._gc_start = None


def patch(tl: Timeline, full_gc_at: float | None = None):
    import vcfusion.hitl.driver as drv
    from vcfusion.hitl.display import Window
    from vcfusion.hitl.pipeline import PipelinedFusionHook, VisionPipeline
    from vcfusion.render.hook import CameraHook
    from vcfusion.render.renderer import EgoCameraRenderer
    from vcfusion.traffic.session import SumoSession

    SumoSession.step = tl.wrap("sumo_step", SumoSession.step)
    SumoSession.states = tl.wrap("truth_read", SumoSession.states)
    SumoSession.place_ego = tl.wrap("place_ego", SumoSession.place_ego)
    EgoCameraRenderer.render = tl.wrap("render", EgoCameraRenderer.render)
    CameraHook.__call__ = tl.wrap("camera_stage", CameraHook.__call__)
    VisionPipeline.submit = tl.wrap("vision_submit", VisionPipeline.submit)
    VisionPipeline.poll = tl.wrap("vision_poll", VisionPipeline.poll)
    PipelinedFusionHook.__call__ = tl.wrap("fusion_stage", PipelinedFusionHook.__call__)
    Window.show = tl.wrap("blit_flip", Window.show)
    drv.compose = tl.wrap("compose", drv.compose)
    drv.HumanDriver._drawn = tl.wrap("overlay_carry", drv.HumanDriver._drawn)
    drv.HumanDriver._log_drawn = tl.wrap("score_drawn", drv.HumanDriver._log_drawn)
    stepped = tl.wrap("driver_step", drv.HumanDriver.step)

    forced = []

    def step(self, st):
        tl.sample()
        if full_gc_at is not None and not forced and st.time >= full_gc_at:
            forced.append(st.time)
            gc.collect()  # a full collection falling inside the drive: what it costs there
        return stepped(self, st)
    drv.HumanDriver.step = step

    class Clock:  # the driver's pacing sleep, timed
        perf_counter = staticmethod(time.perf_counter)
        thread_time = staticmethod(time.thread_time)
        sleep = staticmethod(tl.wrap("pacing_sleep", time.sleep))
    drv.wallclock = Clock
    return drv


def hook_stages(tl: Timeline):
    """Every other tick stage of the run (metrics, guidance, ...), by class."""
    import vcfusion.run as run

    original = run.build_cosimulation

    def build(*args, **kwargs):
        cosim = original(*args, **kwargs)
        for hook in cosim.hooks:
            cls = type(hook)
            if not hasattr(cls.__call__, "__wrapped__"):
                cls.__call__ = tl.wrap(f"stage_{hook.table}", cls.__call__)
        return cosim
    run.build_cosimulation = build


def thread_cpu(pid: int) -> dict:
    """CPU seconds of each thread of a process by thread name (summed over threads of one name),
    with the process's nice value."""
    out: dict[str, float] = {}
    tick = os.sysconf("SC_CLK_TCK")
    for task in Path(f"/proc/{pid}/task").iterdir():
        stat = (task / "stat").read_text()
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2:].split()
        out[name] = round(out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / tick, 2)
    return {"nice": os.getpriority(os.PRIO_PROCESS, pid), "threads": out}


def analyse(tl: Timeline, frames, wall0: float, budget_ms: float, tick_s: float = 0.1) -> dict:
    due = np.asarray(frames["wall_s"], float) + wall0  # when each due frame was shown or dropped
    shown = np.asarray(frames["shown"], bool)
    ev = sorted(tl.events, key=lambda e: e[1])
    parts = sorted({e[0] for e in ev})
    wall = defaultdict(lambda: np.zeros(len(due)))
    cpu = defaultdict(lambda: np.zeros(len(due)))
    for name, start, w, c in ev:
        k = int(np.searchsorted(due, start))  # the frame period it falls in (ends at frame k)
        if k < len(due):
            wall[name][k] += w
            cpu[name][k] += c
    work = sum(wall[p] for p in parts if p != "pacing_sleep")
    work_cpu = sum(cpu[p] for p in parts if p != "pacing_sleep")
    over = work > budget_ms / 1e3
    smp = np.array(tl.samples)
    at = np.clip(np.searchsorted(smp[:, 0], due), 0, len(smp) - 1)  # the step after the one that drew / dropped each frame
    proc_cpu = np.diff(np.concatenate([[smp[at[0], 1]], smp[at, 1]]))
    nivcsw = np.diff(np.concatenate([[smp[at[0], 2]], smp[at, 2]]))
    out = {"frames_due": int(len(due)), "dropped": int((~shown).sum()),
           "work_ms_p50": round(1e3 * float(np.median(work)), 2),
           "work_ms_p95": round(1e3 * float(np.percentile(work, 95)), 2),
           "work_ms_p99": round(1e3 * float(np.percentile(work, 99)), 2),
           "cpu_ms_p50": round(1e3 * float(np.median(work_cpu)), 2),
           "cpu_ms_p99": round(1e3 * float(np.percentile(work_cpu, 99)), 2),
           "process_cpu_ms_p50": round(1e3 * float(np.median(proc_cpu)), 2),
           "process_cpu_ms_p99": round(1e3 * float(np.percentile(proc_cpu, 99)), 2),
           "involuntary_switches_per_frame": round(float(nivcsw.mean()), 2),
           "overrun_frames": int(over.sum()), "parts": {}}
    sim = np.asarray(frames["sim_time"], float)
    at_tick = np.isclose(sim / tick_s, np.round(sim / tick_s), atol=1e-6)
    out |= {"frames_at_ticks": int(at_tick.sum()), "dropped_at_ticks": int((~shown & at_tick).sum())}
    for p in parts:
        w = wall[p]
        out["parts"][p] = {"calls": sum(1 for e in ev if e[0] == p),
                           "ms_p50": round(1e3 * float(np.median(w)), 2), "ms_p99": round(1e3 * float(np.percentile(w, 99)), 2),
                           "ms_max": round(1e3 * float(w.max()), 2),
                           "cpu_ms_p50": round(1e3 * float(np.median(cpu[p])), 2),
                           "cpu_ms_p99": round(1e3 * float(np.percentile(cpu[p], 99)), 2),
                           "share_of_overrun_work_pct": round(100 * float(w[over].sum() / max(work[over].sum(), 1e-9)), 1)}
    out["gc"] = [{"gen": name[2:], "frame": int(np.searchsorted(due, start)), "ms": round(1e3 * w, 2),
                  "cpu_ms": round(1e3 * c, 2)} for name, start, w, c in ev if name.startswith("gc") and w > 1e-3]
    out["gc_pauses"] = {g: {"count": sum(1 for e in ev if e[0] == f"gc{g}"),
                            "ms_total": round(1e3 * sum(e[2] for e in ev if e[0] == f"gc{g}"), 1)} for g in "012"}
    out["per_frame"] = {"sim_time": list(map(float, frames["sim_time"])), "shown": shown.tolist(),
                        "work_ms": (1e3 * work).round(2).tolist(), "cpu_ms": (1e3 * work_cpu).round(2).tolist(),
                        "process_cpu_ms": (1e3 * proc_cpu).round(2).tolist(),
                        "render_cpu_ms": (1e3 * cpu["render"]).round(2).tolist()}
    worst = np.argsort(-work)[:15]
    out["worst"] = [{"frame": int(k), "sim_time": float(frames["sim_time"][k]), "shown": bool(shown[k]),
                     "work_ms": round(1e3 * float(work[k]), 1), "cpu_ms": round(1e3 * float(work_cpu[k]), 1),
                     "proc_cpu_ms": round(1e3 * float(proc_cpu[k]), 1), "nivcsw": int(nivcsw[k]),
                     **{p: round(1e3 * float(wall[p][k]), 1) for p in parts if wall[p][k] > 5e-4}} for k in worst]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-time", type=float, default=60.0, help="simulated s (the trip ends at ~17.6 s)")
    ap.add_argument("--json", type=Path, help="write the analysis here")
    ap.add_argument("--full-gc-at", type=float, help="make one full garbage collection at this simulated time, s "
                    "(what one costs inside a drive)")
    args = ap.parse_args(argv)

    from vcfusion.hitl.drive import drive
    from vcfusion.scenario import load_scenario

    tl = Timeline()
    drv = patch(tl, args.full_gc_at)
    hook_stages(tl)
    captured = {}
    original_finish = drv.HumanDriver.finish

    def finish(self, tables, summary):
        captured["frames"], captured["wall0"] = self.frame_rows, self._wall0
        captured["threads"] = {"loop": thread_cpu(os.getpid()),
                               "worker": thread_cpu(self.vision.worker_pid) if self.vision is not None else None}
        return original_finish(self, tables, summary)
    drv.HumanDriver.finish = finish
    gc.callbacks.append(tl.gc_callback)
    sc = load_scenario(ROOT / "scenarios" / "accident_ar.yaml")
    sc = sc.model_copy(update={"simulation": sc.simulation.model_copy(update={"max_time_s": args.max_time}),
                               "ar": sc.ar.model_copy(update={"video": False})})
    result = drive(sc, 0, input_spec="keyboard", guidance_on=True, speed=1.0, out_dir=None, headless=True,
                   display_fps=30.0, start_screen_s=0.0, vision_pipeline=True)
    gc.callbacks.remove(tl.gc_callback)
    out = analyse(tl, captured["frames"], captured["wall0"], 1e3 / 30.0, sc.v2c.period_s)
    rt = result.summary["realtime"]
    out["realtime"] = {k: rt.get(k) for k in ("display_fps_median", "dropped_frames", "max_lag_s", "ar_age_ms_median",
                                              "vision_ticks_dropped", "vision_latency_ms_median")}
    print(json.dumps({k: v for k, v in out.items() if k not in ("parts", "worst", "gc", "per_frame")}))
    print("dropped at", [round(t, 2) for t, sh in zip(captured["frames"]["sim_time"], captured["frames"]["shown"]) if not sh])
    print("threads:", captured.get("threads"))
    print(f"{'part':16s} {'calls':>6s} {'p50':>7s} {'p99':>7s} {'max':>7s} {'cpu50':>7s} {'cpu99':>7s} {'overrun%':>8s}")
    for p, s in sorted(out["parts"].items(), key=lambda kv: -kv[1]["share_of_overrun_work_pct"]):
        print(f"{p:16s} {s['calls']:6d} {s['ms_p50']:7.2f} {s['ms_p99']:7.2f} {s['ms_max']:7.2f} "
              f"{s['cpu_ms_p50']:7.2f} {s['cpu_ms_p99']:7.2f} {s['share_of_overrun_work_pct']:8.1f}")
    for w in out["worst"]:
        print(w)
    print("gc pauses:", out["gc_pauses"])
    print("gc over 1 ms inside the drive:", [g for g in out["gc"] if 0 < g["frame"] < out["frames_due"]])
    pf = out["per_frame"]
    t = np.asarray(pf["sim_time"])
    print("per simulated second: loop thread CPU ms / process CPU ms per frame period (mean), dropped")
    for sec in range(int(t.max()) + 1):
        m = (t >= sec) & (t < sec + 1)
        if m.any() and sec > 0:
            print(f"  {sec:3d} s  {np.mean(np.asarray(pf['cpu_ms'])[m]):6.1f}  {np.mean(np.asarray(pf['process_cpu_ms'])[m]):6.1f}"
                  f"  {int((~np.asarray(pf['shown'])[m]).sum())}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
