"""`vcfusion metrics` and `vcfusion report` on run and batch folders of real runs."""

import json
import shutil

import pandas as pd
import pytest

from scenario_files import write_scenario
from vcfusion.commands import main
from vcfusion.studies.batch import seed_folder

METRIC_FILES = ("metrics.parquet", "conflicts.parquet", "metric_histograms.parquet")


def _make_old(folder, keep_sumo=True):
    """What a run folder written before the metrics looks like."""
    for name in METRIC_FILES:
        (folder / name).unlink()
    if not keep_sumo:
        (folder / "sumo_emissions.parquet").unlink()
    summary = json.loads((folder / "summary.json").read_text())
    del summary["metrics"]
    (folder / "summary.json").write_text(json.dumps(summary))
    manifest = json.loads((folder / "manifest.json").read_text())
    del manifest["scenario"]["metrics"]
    (folder / "manifest.json").write_text(json.dumps(manifest))


@pytest.mark.slow
def test_metrics_of_an_old_run_folder_equal_the_run_that_wrote_it(tmp_path, accident_path, capsys):
    run = tmp_path / "run"
    assert main(["run", str(accident_path), "--seed", "3", "--out", str(run)]) == 0
    printed = capsys.readouterr().out
    written = json.loads((run / "summary.json").read_text())["metrics"]
    assert f"metrics ({written['traffic']['vehicles']} vehicles" in printed and "ego: min TTC" in printed
    old, bare = tmp_path / "old", tmp_path / "bare"
    shutil.copytree(run, old)
    shutil.copytree(run, bare)
    _make_old(old)
    _make_old(bare, keep_sumo=False)
    assert main(["metrics", str(old), str(bare)]) == 0
    for name in METRIC_FILES:
        assert (old / name).read_bytes() == (run / name).read_bytes(), name
    assert json.loads((old / "summary.json").read_text())["metrics"] == written
    out = capsys.readouterr().out
    assert "1 run folder(s) have no sumo_emissions.parquet" in out and str(bare) in out
    m = pd.read_parquet(bare / "metrics.parquet")
    assert m["sumo_co2_g"].isna().all() and m["movestar_co2_g"].notna().any()
    settings = json.loads((bare / "summary.json").read_text())["metrics"]["settings"]
    assert settings["sumo_emissions"].startswith("missing")
    pd.testing.assert_frame_equal(m.drop(columns=[c for c in m if c.startswith("sumo_")]),
                                  pd.read_parquet(run / "metrics.parquet").drop(
                                      columns=[c for c in m if c.startswith("sumo_")]))


@pytest.mark.slow
def test_batch_columns_table_rethreshold_and_report(tmp_path, accident_path, capsys):
    out = tmp_path / "b"
    assert main(["batch", str(accident_path), "--seeds", "0-2", "--workers", "2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "metrics over the seeds" in printed and "fuel, all rated vehicles" in printed
    batch = pd.read_parquet(out / "batch_summary.parquet")
    assert batch["seed"].tolist() == [0, 1, 2]
    summary = json.loads((seed_folder(out, 1) / "summary.json").read_text())
    assert batch.loc[1, "traffic_conflicts"] == summary["metrics"]["traffic"]["conflicts"]
    assert batch.loc[1, "ego_max_abs_jerk_mps3"] == pytest.approx(summary["metrics"]["ego"]["max_abs_jerk_mps3"])
    assert batch["traffic_fuel_g_per_km"].notna().all()
    # by default SUMO's model rates only what MOVESTAR does not: here the (parked) accident trucks
    sumo = pd.read_parquet(seed_folder(out, 0) / "sumo_emissions.parquet")
    assert sumo.dropna(subset=["co2_g"])["vehicle_id"].str.startswith("accident").all()
    # a higher TTC threshold from a scenario file: more time below it, never fewer conflicts
    text = accident_path.read_text().replace("network: ../sumo_net", "network: NET_DIR").replace(
        "vehicle_types: ../sumo_net", "vehicle_types: NET_DIR") + "\nmetrics:\n  ttc_threshold_s: 4.0\n"
    strict = write_scenario(tmp_path, text)
    assert main(["metrics", str(out), "--scenario", str(strict)]) == 0
    again = pd.read_parquet(out / "batch_summary.parquet")
    assert (again["traffic_tet_s"] >= batch["traffic_tet_s"]).all() and again["traffic_tet_s"].sum() > 0
    assert (again["traffic_conflicts"] >= batch["traffic_conflicts"]).all()
    assert json.loads((seed_folder(out, 0) / "summary.json").read_text())["metrics"]["settings"]["ttc_threshold_s"] == 4.0
    assert main(["report", str(out)]) == 0
    report = (out / "report" / "report.md").read_text()
    assert "| fuel, all rated vehicles | g/km | 3 |" in report and "passenger" in report
    # the runs' setting named (default `others`: it said "SUMO's model every class", and the cars read nan)
    assert "SUMO's model the vehicles MOVESTAR does not rate" in report
    for png in ("ttc_headway_distributions.png", "fuel_co2_by_class.png", "conflicts_by_position.png",
                "ego_time_series.png"):
        assert (out / "report" / png).stat().st_size > 5000, png
    capsys.readouterr()
    # resumed with the scenario's own block, the batch would pool runs of two TTC thresholds (it did,
    # and the report named one threshold for all): refused, nothing run
    assert main(["batch", str(accident_path), "--seeds", "0-3", "--out", str(out)]) == 2
    assert ("seed_0000: its metrics were recomputed with another metrics: block than this scenario's (they "
            "differ in: ttc_threshold_s)") in capsys.readouterr().err
    assert not seed_folder(out, 3).exists()
    # one run recomputed with its own block: a report would pool two definitions
    assert main(["metrics", str(seed_folder(out, 1))]) == 0
    assert main(["report", str(out)]) == 2
    assert "another metrics: block than" in capsys.readouterr().err
    # all recomputed alike, then a batch of seeds 0-1 into the folder: the report covers those two
    # (its header, tables and figures covered every run folder, its seeds table the batch's seeds)
    assert main(["metrics", str(out)]) == 0
    assert main(["batch", str(accident_path), "--seeds", "0-1", "--out", str(out)]) == 0
    assert main(["report", str(out)]) == 0
    report = (out / "report" / "report.md").read_text()
    assert "\n2 runs;" in report and "| fuel, all rated vehicles | g/km | 2 |" in report


def test_metrics_refuses_what_is_not_a_run_or_batch_folder(tmp_path, capsys):
    assert main(["metrics", str(tmp_path)]) == 2
    assert f"{tmp_path}: expected a run folder" in capsys.readouterr().err
    assert main(["report", str(tmp_path / "missing")]) == 2
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "manifest.json").write_text("{}")
    assert main(["metrics", str(broken)]) == 2
    assert "trajectories.parquet is missing" in capsys.readouterr().err
