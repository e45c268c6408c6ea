"""The human-in-the-loop study protocol (`vcfusion study hitl`): one participant's session.

1. optional simulator-sickness questionnaire (SSQ) before driving;
2. a practice drive (guidance on, its own seed, stored but not a study trip);
3. the study trips: `pairs` seeds, each driven once with guidance on and once off, in a
   counterbalanced order (`trip_plan`), with a pause screen between trips;
4. optional SSQ after the last trip.
Each trip is an ordinary run folder (`trip_NN_seedS_on|off/`); `protocol.json` lists them with
their condition, seed, order and status; `ssq.json` holds the answers and scores.

Counterbalancing (`trip_plan`): the first half drives the seeds in order with the conditions
alternating, A B A B ...; the second half drives the same seeds in the same order, each in the
other condition: B A B A ... So every seed is driven in both conditions (paired), its two drives
are `pairs` trips apart (the same spacing for every seed: less memory of the traffic), no block
of one condition, and with an even number of pairs both conditions have the same mean position
in the session (ABAB BABA; learning and fatigue fall equally on both). A = guidance on for
participants of order `on-first`, off for `off-first`; the default order alternates between
participants by a stable hash of the id (about half start with each).

SSQ: Kennedy, Lane, Berbaum & Lilienthal (1993), "Simulator Sickness Questionnaire: an enhanced
method for quantifying simulator sickness", Int. J. Aviation Psychology 3(3) 203-220: 16 symptoms
rated 0 (none) to 3 (severe); nausea, oculomotor and disorientation sums weighted 9.54, 7.58,
13.92, the total (sum of the three raw sums) 3.74.
"""

from __future__ import annotations

import hashlib
import json
import time as wallclock
from pathlib import Path

from vcfusion.errors import UsageError

SSQ_SYMPTOMS = (
    # symptom, subscales (N nausea, O oculomotor, D disorientation), Kennedy et al. 1993, Table 3
    ("General discomfort", "NO"), ("Fatigue", "O"), ("Headache", "O"), ("Eye strain", "O"),
    ("Difficulty focusing", "OD"), ("Increased salivation", "N"), ("Sweating", "N"), ("Nausea", "ND"),
    ("Difficulty concentrating", "NO"), ("Fullness of head", "D"), ("Blurred vision", "OD"),
    ("Dizzy (eyes open)", "D"), ("Dizzy (eyes closed)", "D"), ("Vertigo", "D"), ("Stomach awareness", "N"),
    ("Burping", "N"),
)
SSQ_WEIGHTS = {"N": 9.54, "O": 7.58, "D": 13.92}
SSQ_TOTAL_WEIGHT = 3.74


def ssq_scores(ratings: list[int]) -> dict:
    """Nausea, oculomotor, disorientation and total scores of 16 ratings 0..3."""
    if len(ratings) != len(SSQ_SYMPTOMS) or any(r not in (0, 1, 2, 3) for r in ratings):
        raise ValueError(f"SSQ: expected {len(SSQ_SYMPTOMS)} ratings of 0..3, got {ratings}")
    raw = {k: sum(r for r, (_, scales) in zip(ratings, SSQ_SYMPTOMS) if k in scales) for k in "NOD"}
    return {"nausea": raw["N"] * SSQ_WEIGHTS["N"], "oculomotor": raw["O"] * SSQ_WEIGHTS["O"],
            "disorientation": raw["D"] * SSQ_WEIGHTS["D"], "total": sum(raw.values()) * SSQ_TOTAL_WEIGHT}


def check_participant(participant: str) -> str:
    """UsageError unless the id can name a folder: no path separators, not . or .. (an id such as
    P07/x scattered trips into subfolders, ../x wrote them elsewhere)."""
    if "/" in participant or "\\" in participant or participant in (".", "..") or "\0" in participant:
        raise UsageError(f"--participant: expected an id without path separators (it names folders), got "
                         f"{participant!r}")
    return participant


def default_order(participant: str) -> str:
    """on-first or off-first, alternating between participants by a stable hash of the id."""
    return ("on-first", "off-first")[hashlib.sha256(participant.encode()).digest()[0] % 2]


def trip_plan(seeds: list[int], order: str) -> list[tuple[int, bool]]:
    """(seed, guidance on) of every study trip, in driving order (see the module doc)."""
    if order not in ("on-first", "off-first"):
        raise UsageError(f"--order: expected on-first or off-first, got {order!r}")
    a = order == "on-first"
    first = [(seed, a if k % 2 == 0 else not a) for k, seed in enumerate(seeds)]
    return first + [(seed, not on) for seed, on in first]


def ask_ssq(pygame, window, when: str, timeout_s: float | None = None) -> list[int]:
    """The 16 SSQ items on the window, one at a time, answered with keys 0-3 (Escape aborts).
    `timeout_s` per item for unattended runs: an item not answered in time raises UsageError."""
    from vcfusion.hitl.display import text_screen
    from vcfusion.hitl.driver import DriveAborted

    keys = {pygame.K_0: 0, pygame.K_1: 1, pygame.K_2: 2, pygame.K_3: 3,
            pygame.K_KP0: 0, pygame.K_KP1: 1, pygame.K_KP2: 2, pygame.K_KP3: 3}
    ratings = []
    pending: list = []  # events read but not used yet: a quick typist's next answers
    for k, (symptom, _) in enumerate(SSQ_SYMPTOMS):
        window.show(text_screen(window.size, [f"How do you feel {when}? ({k + 1} of {len(SSQ_SYMPTOMS)})", "",
                                              symptom, "", "0 none   1 slight   2 moderate   3 severe"]))
        started = wallclock.perf_counter()
        answer = None
        while answer is None:
            if not pending:
                pending.extend(pygame.event.get())
            if not pending:
                if timeout_s is not None and wallclock.perf_counter() - started > timeout_s:
                    raise UsageError(f"SSQ ({when}): no answer to {symptom!r}")
                wallclock.sleep(0.01)
                continue
            event = pending.pop(0)
            if event.type == pygame.QUIT or (event.type == pygame.KEYDOWN and event.key == pygame.K_ESCAPE):
                raise DriveAborted("the participant ended the questionnaire")
            if event.type == pygame.KEYDOWN and event.key in keys:
                answer = keys[event.key]
        ratings.append(answer)
    return ratings


def run_hitl_study(scenario_path: Path, participant: str, pairs: int, out: Path, *, input_spec: str = "keyboard",
                   axis_map_file: Path | None = None, first_seed: int = 0, practice_seed: int = 1000,
                   order: str | None = None, ssq: bool = False, headless: bool = False,
                   speed: float | None = 1.0, screen_timeout_s: float | None = None,
                   display_fps: float = 30.0) -> dict:
    """One participant's session (module doc). Returns the protocol written to protocol.json.
    `screen_timeout_s`: how long instruction / pause screens wait (None: until a key press)."""
    from vcfusion.hitl.display import Window
    from vcfusion.hitl.drive import drive
    from vcfusion.hitl.sdl import init_sdl
    from vcfusion.runio import write_json
    from vcfusion.scenario import load_scenario, require_camera_world

    if not participant:
        raise UsageError("--participant: give the participant's id")
    check_participant(participant)
    if pairs < 1:
        raise UsageError(f"--trips: expected at least 1 paired trip, got {pairs}")
    if first_seed <= practice_seed < first_seed + pairs:
        raise UsageError(f"--practice-seed {practice_seed}: one of the study's seeds; choose another")
    scenario = load_scenario(scenario_path)
    require_camera_world(scenario)  # the driver sees the camera's world
    if scenario.ego is None:
        raise UsageError(f"{scenario_path}: ego: a person drives the ego; the scenario has no ego block")
    # the input is checked before the session's folder exists (nothing is written for a bad one)
    from vcfusion.hitl.inputs import check_input_spec

    check_input_spec(input_spec)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    order = order or default_order(participant)
    plan = trip_plan(list(range(first_seed, first_seed + pairs)), order)
    protocol = {"participant": participant, "scenario": str(scenario_path), "order": order,
                "practice_seed": practice_seed, "input": input_spec, "trips": []}
    pygame = init_sdl(headless)
    size = (scenario.camera.width_px, scenario.camera.height_px)

    window = Window(pygame, size, f"vcfusion study: participant {participant}")  # one window for the session

    def screen(lines: list[str]) -> None:
        window.wait_for_start(lines, lambda event: None, screen_timeout_s)

    def questionnaire(when: str) -> dict:
        ratings = ask_ssq(pygame, window, when, screen_timeout_s)
        return {"ratings": dict(zip((s for s, _ in SSQ_SYMPTOMS), ratings)), "scores": ssq_scores(ratings)}

    try:
        answers = json.loads((out / "ssq.json").read_text()) if (out / "ssq.json").exists() else {}
        if ssq and "before" not in answers:
            answers["before"] = questionnaire("now, before driving")
            write_json(out / "ssq.json", answers)
        common = dict(input_spec=input_spec, axis_map_file=axis_map_file, participant=participant, headless=headless,
                      speed=speed, display_fps=display_fps, start_screen_s=screen_timeout_s, shared_window=window)
        practice_dir = out / "practice"
        if not practice_dir.exists():
            screen(["Practice drive", "", "Get used to the car and the controls.", "Press Enter to start."])
            drive(scenario, practice_seed, guidance_on=True, out_dir=practice_dir, **common)
        protocol["practice"] = practice_dir.name
        for k, (seed, on) in enumerate(plan, start=1):
            name = f"trip_{k:02d}_seed{seed}_{'on' if on else 'off'}"
            entry = {"trip": k, "seed": seed, "guidance": "on" if on else "off", "run": name}
            if not (out / name).exists():  # a session can be resumed: finished trips are kept
                screen([f"Trip {k} of {len(plan)}", "", f"AR guidance {'ON' if on else 'OFF'}", "",
                        "Take a break if you like.", "Press Enter to continue."])
                drive(scenario, seed, guidance_on=on, out_dir=out / name, **common)
            protocol["trips"].append(entry)
            write_json(out / "protocol.json", protocol)
        if ssq:
            answers["after"] = questionnaire("now, after driving")
            write_json(out / "ssq.json", answers)
        screen(["Thank you: the session is complete."] if screen_timeout_s is None else ["Session complete."])
        protocol["ssq"] = "ssq.json" if ssq else None
        write_json(out / "protocol.json", protocol)
        return protocol
    finally:
        window.close()
