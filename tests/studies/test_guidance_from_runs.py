"""`vcfusion study guidance --from-runs`: the study of run folders written by the real commands
(model trips of `vcfusion run` / `batch`, replayed human trips of `vcfusion drive`) gives the rows
the driver-model study computes, pairs by driver and seed, counts the unpaired, refuses non-runs."""

import json
import math
import shutil

import pandas as pd
import pytest
from scenario_files import SCENARIOS, write_scenario

from vcfusion.commands import main
from vcfusion.studies.guidance import ARM_TABLES, arm_metrics, choose_target, paired_summary, run_trip

# the accident trip, short and on a coarse step (a cut-in ahead of the ego at ~10 s for seed 0)
SHORT = f"""
extends: {(SCENARIOS / 'accident.yaml').as_posix()}
name: accident_short
simulation: {{step_s: 0.05, max_time_s: 14.0}}
"""


def missing(x) -> bool:
    return x is None or (isinstance(x, float) and math.isnan(x))


def same(a, b) -> bool:
    """Equal values; a missing value (None in a row, NaN / None in a table column) equals a missing one."""
    if missing(a) or missing(b):
        return missing(a) and missing(b)
    return a == pytest.approx(b, rel=1e-12, abs=0) if isinstance(a, float) else a == b


@pytest.mark.slow
def test_from_runs_gives_the_model_study_rows_and_pairs_human_trips(tmp_path, capsys):
    from vcfusion.hitl.drive import drive
    from vcfusion.scenario import load_scenario

    guided = write_scenario(tmp_path, SHORT, "short.yaml")
    unguided = write_scenario(tmp_path, f"extends: {guided.as_posix()}\ndriver: {{guidance: false}}\n", "off.yaml")
    runs = tmp_path / "runs"
    # model trips: a batch with guidance, single runs without, one more guided seed left unpaired
    assert main(["batch", str(guided), "--seeds", "0-1", "--workers", "1", "--out", str(runs / "batch")]) == 0
    for seed in (0, 1):
        assert main(["run", str(unguided), "--seed", str(seed), "--out", str(runs / f"off{seed}")]) == 0
    assert main(["run", str(guided), "--seed", "2", "--out", str(runs / "lonely")]) == 0
    # human trips: one participant's replayed drives, seeds 0 and 1 with guidance on and off
    (tmp_path / "in.csv").write_text("time_s,throttle,brake,steer\n0,0.4,0,0\n6,0,0.3,0\n8,0.2,0,0\n")
    sc = load_scenario(guided)
    human = {}
    for seed in (0, 1):
        for on in (True, False):
            folder = runs / "P07" / f"seed{seed}_{'on' if on else 'off'}"
            result = drive(sc, seed, input_spec=f"replay:{tmp_path / 'in.csv'}", guidance_on=on, speed=None,
                           out_dir=folder, participant="P07", window=False)
            human[(seed, "cloud" if on else "none")] = {
                "arm": "cloud" if on else "none", "scenario": sc, "summary": result.summary, "driver": {},
                "tables": {n: result.tables[n] for n in ARM_TABLES if n in result.tables},
                "process_models": "lane_change"}
    capsys.readouterr()

    out, renders = tmp_path / "study", tmp_path / "renders"
    assert main(["study", "guidance", "--from-runs", str(runs / "batch"), str(runs / "off0"), str(runs / "off1"),
                 str(runs / "lonely"), str(runs / "P07"), "--out", str(out), "--renders", str(renders)]) == 0
    printed = capsys.readouterr().out
    assert "4 paired trips from 9 run folders (1 participant(s), the driver model), 1 unpaired" in printed
    assert f"unpaired, left out: {(runs / 'lonely').resolve()} (its trip has only cloud)" in printed
    trips = pd.read_parquet(out / "trips.parquet")
    info = json.loads((out / "summary.json").read_text())
    assert info["unpaired_folders"] == 1 and info["run_folders"] == 9 and info["arms"] == ["none", "cloud"]
    assert len(trips) == 8 and set(trips["driver_kind"]) == {"human", "model"}
    assert set(trips.loc[trips["driver_kind"] == "human", "participant"]) == {"P07"}
    figures = sorted(renders.glob("guidance_fig*.png"))
    assert [f.name for f in figures] == ["guidance_fig8_safety_comfort.png", "guidance_fig9_fuel_emissions.png"]
    for fig in figures:
        assert fig.stat().st_size > 10_000

    # the model trips: exactly the rows the driver-model study computes for these seeds and arms
    model = trips[trips["driver_kind"] == "model"].set_index(["seed", "arm"])
    expected = []
    for seed in (0, 1):
        _, rows, error = run_trip(str(guided), seed, (), ("none", "cloud"))
        assert error is None
        expected += rows
    assert trips.loc[(trips["driver_kind"] == "model") & (trips["seed"] == 0), "target_id"].notna().all()
    for row in expected:
        got = model.loc[(row["seed"], row["arm"])]
        for col, value in row.items():
            if col not in ("seed", "arm", "arm_wall_s"):
                assert same(got[col], value), (row["seed"], row["arm"], col, got[col], value)
    # and the paired summary over them is the model study's
    mine = paired_summary(trips[trips["driver_kind"] == "model"], pair_on=("seed",))
    theirs = paired_summary(pd.DataFrame(expected))
    pd.testing.assert_frame_equal(mine, theirs)

    # the human trips: arm_metrics of the drives as they ran, against the pair's own target
    person = trips[trips["driver_kind"] == "human"].set_index(["seed", "arm"])
    for seed in (0, 1):
        pair = [human[(seed, "none")], human[(seed, "cloud")]]
        target = choose_target(pair)
        for run in pair:
            row, got = arm_metrics(run, target), person.loc[(seed, run["arm"])]
            for col, value in row.items():
                assert same(got[col], value), (seed, run["arm"], col, got[col], value)
    assert person["response_time_s"].isna().all()  # a person's reaction is not logged as a model's
    # the study's table over every pair (driver, seed) is what was written
    summary = pd.read_csv(out / "summary.csv")
    assert (summary["n_pairs"][summary["metric"] == "fuel_g_per_km"] == 4).all()

    # a run folder lacking a table the metrics need: refused, naming it (exit 2, one line)
    broken = tmp_path / "broken"
    shutil.copytree(runs / "off0", broken)
    (broken / "guidance.parquet").unlink()
    assert main(["study", "guidance", "--from-runs", str(broken), "--out", str(tmp_path / "s2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(broken) in err[0] and "guidance.parquet missing" in err[0]
    assert not (tmp_path / "s2").exists()
    # one trip and arm twice
    shutil.copytree(runs / "off0", tmp_path / "again")
    assert main(["study", "guidance", "--from-runs", str(runs / "batch"), str(runs / "off0"),
                 str(tmp_path / "again")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the same trip (seed 0, the driver model) in the same arm 'none'" in err[0], err
    # folders of one arm only; paired trips of two scenarios (here: another trip length)
    assert main(["study", "guidance", "--from-runs", str(runs / "off0"), str(runs / "off1")]) == 2
    assert "all in arm(s) none" in capsys.readouterr().err
    longer = write_scenario(tmp_path, SHORT.replace("14.0", "15.0"), "longer.yaml")
    for name, text in (("l_on", ""), ("l_off", "\ndriver: {guidance: false}\n")):
        path = write_scenario(tmp_path, f"extends: {longer.as_posix()}{text}", f"{name}.yaml")
        assert main(["run", str(path), "--seed", "0", "--out", str(tmp_path / "other" / name)]) == 0
    capsys.readouterr()
    assert main(["study", "guidance", "--from-runs", str(runs / "batch"), str(runs / "off0"),
                 str(tmp_path / "other"), "--out", str(tmp_path / "s3")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scenario.simulation.max_time_s differs" in err[0], err
    assert not (tmp_path / "s3").exists()
    # one folder of the other scenario, which pairs with nothing: refused too (was left out as unpaired)
    assert main(["study", "guidance", "--from-runs", str(runs / "batch"), str(runs / "off0"),
                 str(tmp_path / "other" / "l_off"), "--out", str(tmp_path / "s4")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scenario.simulation.max_time_s differs" in err[0], err
    assert not (tmp_path / "s4").exists()


def test_from_runs_refuses_what_is_not_a_run_folder(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "readme.txt").write_text("hello")
    for target in (tmp_path / "empty", tmp_path / "notes", tmp_path / "missing"):
        assert main(["study", "guidance", "--from-runs", str(target), "--out", str(tmp_path / "s")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(target) in err[0] and err[0].startswith("error: "), err
    assert not (tmp_path / "s").exists()
    # a folder whose manifest says it is a run, but not a run of a study (no ego driver)
    fake = tmp_path / "fake"
    fake.mkdir()
    (fake / "manifest.json").write_text('{"scenario": {"name": "x"}, "seed": 0}')
    (fake / "summary.json").write_text("{}")
    assert main(["study", "guidance", "--from-runs", str(fake)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "manifest.json: scenario." in err[0]


def test_from_runs_and_a_scenario_or_model_options_are_a_usage_error(tmp_path, capsys):
    (tmp_path / "r").mkdir()
    for argv, word in (([str(SCENARIOS / "accident.yaml"), "--from-runs", str(tmp_path / "r")], "SCENARIO"),
                       (["--from-runs", str(tmp_path / "r"), "--trips", "4"], "--trips"),
                       (["--from-runs", str(tmp_path / "r"), "--arms", "none,cloud"], "--arms"),
                       ([], "--from-runs")):
        assert main(["study", "guidance", *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and word in err[0], err


def test_folders_of_runs_batches_and_hitl_sessions(tmp_path):
    from vcfusion.studies.from_runs import find_run_folders

    def run(folder):
        folder.mkdir(parents=True)
        (folder / "manifest.json").write_text("{}")  # what marks a complete run folder
        return folder.resolve()

    batch = tmp_path / "batch"
    seeds = [run(batch / "seed_0000"), run(batch / "seed_0001")]
    (batch / "seed_0002.tmp-writing").mkdir()  # a seed killed while it was written
    session = tmp_path / "hitl-P07"
    run(session / "practice")
    trips = [run(session / "trip_01_seed0_off"), run(session / "trip_02_seed0_on")]
    (session / "protocol.json").write_text(json.dumps({"trips": [{"run": "trip_01_seed0_off"},
                                                                 {"run": "trip_02_seed0_on"}]}))
    single = run(tmp_path / "single")
    found, skipped = find_run_folders([batch, session, single, seeds[0].parent / "seed_0000"])
    assert found == seeds + trips + [single]  # the practice drive is no study trip; a folder named twice counts once
    assert skipped == [batch / "seed_0002.tmp-writing"]
    # a folder of sessions: each session's trips
    found, _ = find_run_folders([tmp_path])
    assert trips[0] in found and not any(p.name == "practice" for p in found)
