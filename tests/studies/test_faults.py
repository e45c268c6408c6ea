"""Faults on real processes: a worker killed by SIGKILL costs its seed only; Ctrl-C leaves no
partial folder and says how to resume; on Dask a lost worker's seed is run again, then recorded."""

import functools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from scenario_files import REPO, tiny_scenario
from support.dying_workers import run_seed_or_die, wait_for
from vcfusion.studies.batch import Executor, run_batch

def _tiny(tmp_path: Path, max_time_s: float = 100) -> Path:
    return tiny_scenario(tmp_path, max_time_s)  # long enough (~1 s a seed) to catch a seed while it runs


def _endless(tmp_path: Path) -> Path:
    """A run that is still going whenever a signal comes: an inflow keeps the road busy for an
    hour of simulated time (the tiny scenario's 20 cars leave the road after ~1 s of wall time, so
    a late SIGINT on a loaded machine would find the process already shutting down)."""
    return tiny_scenario(tmp_path, 3600, "flows:\n  - {vehs_per_hour: 1800, lanes: [0, 1, 2], speed_mps: 25}\n")


def _vcfusion(*args, **kwargs) -> subprocess.Popen:
    # its own session: a signal sent to it reaches it alone, not this test's process group
    return subprocess.Popen([sys.executable, "-m", "vcfusion", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True, **kwargs)


def _complete(out: Path) -> list[int]:
    return sorted(int(p.name[5:]) for p in out.glob("seed_*") if (p / "manifest.json").is_file())


def _leftovers(out: Path) -> list[str]:
    return sorted(p.name for p in out.iterdir() if ".tmp-writing" in p.name or p.name == "running")


@pytest.mark.slow
def test_killed_worker_costs_its_seed_only_and_a_rerun_completes_it(tmp_path):
    scenario, out = _tiny(tmp_path), tmp_path / "batch"
    proc = _vcfusion("batch", scenario, "--seeds", "0-3", "--workers", "2", "--out", out)
    marker = out / "running" / "seed_0002.pid"  # the batch names the worker running seed 2
    wait_for(marker)
    os.kill(int(marker.read_text()), signal.SIGKILL)  # as the out-of-memory killer does
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 1, stderr
    assert "Traceback" not in stderr and "Traceback" not in stdout
    assert json.loads((out / "failures.json").read_text()) == {"2": "worker process died (signal 9: SIGKILL)"}
    assert "3 run, 0 already complete, 1 failed" in stdout
    assert "seed 2: worker process died (signal 9: SIGKILL)" in stdout
    assert _complete(out) == [0, 1, 3]
    assert pd.read_parquet(out / "batch_summary.parquet").seed.tolist() == [0, 1, 3]
    assert _leftovers(out) == []
    # a re-run runs seed 2 alone
    again = subprocess.run([sys.executable, "-m", "vcfusion", "batch", scenario, "--seeds", "0-3",
                            "--workers", "2", "--out", out], capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert "1 run, 3 already complete, 0 failed" in again.stdout
    assert not (out / "failures.json").exists()
    assert pd.read_parquet(out / "batch_summary.parquet").seed.tolist() == list(range(4))


@pytest.mark.slow
def test_dataset_loses_only_the_seed_whose_worker_died(tmp_path):
    out = tmp_path / "dataset"
    proc = _vcfusion("dataset", _tiny(tmp_path, max_time_s=60), "--seeds", "0-3", "--workers", "2", "--out", out)
    marker = out / "runs" / "running" / "seed_0001.pid"
    wait_for(marker)
    os.kill(int(marker.read_text()), signal.SIGKILL)
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 1, stderr
    assert "Traceback" not in stderr
    assert "seed 1: worker process died (signal 9: SIGKILL)" in stdout
    assert json.loads((out / "runs" / "failures.json").read_text()) == {"1": "worker process died (signal 9: SIGKILL)"}
    splits = json.loads((out / "dataset.json").read_text())["splits"]
    assert sorted(sum(splits.values(), [])) == [0, 2, 3]
    assert _complete(out / "runs") == [0, 2, 3] and _leftovers(out / "runs") == []


@pytest.mark.slow
def test_ctrl_c_during_a_run_leaves_no_folder_and_says_how_to_go_on(tmp_path):
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    out = tmp_path / "run"
    proc = _vcfusion("run", _endless(tmp_path), "--out", out, env=os.environ | {"TMPDIR": str(scratch)})
    while not list(scratch.glob("vcfusion-run-*")):  # the run's tables are being written
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130
    assert "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1] == ("interrupted: no run folder was written; run the same command "
                                               "again to redo the run")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.yaml", "tmp"]
    assert list(scratch.iterdir()) == []  # its temporary tables are gone too


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.mark.slow
@pytest.mark.parametrize("stop, code, word", [(signal.SIGINT, 130, "interrupted"),
                                              # a scheduler's, `timeout`'s or `kill`'s stop: by default it
                                              # killed the batch alone, and its workers ran on, untracked
                                              (signal.SIGTERM, 143, "terminated")])
def test_ctrl_c_during_a_batch_stops_its_workers_and_keeps_complete_seeds(tmp_path, stop, code, word):
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    out = tmp_path / "batch"
    proc = _vcfusion("batch", _tiny(tmp_path), "--seeds", "0-9", "--workers", "2", "--out", out,
                     env=os.environ | {"TMPDIR": str(scratch)})
    wait_for(out / "running" / "seed_0003.pid")
    workers = []
    for pid_file in (out / "running").glob("*.pid"):
        try:
            workers.append(int(pid_file.read_text()))
        except FileNotFoundError:  # that seed ended meanwhile
            pass
    assert workers  # the check below that they are stopped must have workers to check
    os.kill(proc.pid, stop)  # the batch passes it on to its workers
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == code
    assert "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1].startswith(f"{word}: complete seeds are kept, partial ones removed; "
                                                      "run the same command again to resume")
    # the worker is gone once its fork server has reaped it (a zombie still answers kill(pid, 0))
    deadline = time.monotonic() + 30
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(_alive(pid) for pid in workers)
    assert 2 <= len(_complete(out)) < 10  # seeds 0 and 1 ended before seed 3 began
    assert sorted(p.name for p in out.iterdir()) == [f"seed_{s:04d}" for s in _complete(out)]
    assert [p for p in scratch.iterdir() if p.name.startswith("vcfusion-")] == []


@pytest.mark.slow
def test_dask_runs_a_lost_workers_seed_again_then_records_it(tmp_path):
    out = tmp_path / "batch"
    # seed 1 loses its worker once: run again, complete; seed 2 twice: recorded
    task = functools.partial(run_seed_or_die, deaths={1: 1, 2: 2})
    report = run_batch(_tiny(tmp_path, max_time_s=20), [0, 1, 2, 3], out, progress=False, task=task,
                       executor=Executor(dask_local=2, lost_worker_retries=1))
    assert report["done"] == 3 and [seed for seed, _ in report["failed"]] == [2]
    cause = json.loads((out / "failures.json").read_text())["2"]
    assert cause.startswith("worker process died (2 Dask workers lost running it)")
    assert sorted(p.name for p in out.glob("death-*")) == ["death-1-0", "death-2-0", "death-2-1"]
    assert pd.read_parquet(out / "batch_summary.parquet").seed.tolist() == [0, 1, 3]
    assert not list(out.glob("*.tmp-writing*"))


@pytest.mark.slow
def test_guidance_study_loses_only_the_trip_whose_worker_died(tmp_path):
    from vcfusion.studies.guidance import run_guidance_study

    text = (REPO / "scenarios" / "accident.yaml").read_text().replace("../sumo_net", str(REPO / "sumo_net"))
    scenario = tmp_path / "accident.yaml"
    scenario.write_text(text)
    res = run_guidance_study(scenario, trips=3, workers=2, out=tmp_path / "study", renders=tmp_path / "renders",
                             process_model_specs=("support.dying_workers:dies_once",), progress=False,
                             arms=("none", "cloud"))
    assert len(res["failed"]) == 1
    dead, cause = res["failed"][0]
    assert cause == "worker process died (signal 9: SIGKILL)"
    assert json.loads((tmp_path / "study" / "failures.json").read_text()) == {str(dead): cause}
    trips = pd.read_parquet(tmp_path / "study" / "trips.parquet")
    assert sorted(set(trips["seed"])) == sorted({0, 1, 2} - {dead})
    assert res["info"]["trips_failed"] == 1
    # the dead trip is not in the trip log: the same study again runs it alone (the model dies only once)
    again = run_guidance_study(scenario, trips=3, workers=2, out=tmp_path / "study", renders=tmp_path / "renders",
                               process_model_specs=("support.dying_workers:dies_once",), progress=False,
                               arms=("none", "cloud"))
    assert again["failed"] == [] and again["info"]["trips_from_log"] == 2
    assert sorted(set(again["trips"]["seed"])) == [0, 1, 2]
    assert not (tmp_path / "study" / "failures.json").exists()
