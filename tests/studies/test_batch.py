"""The batch runner and the run command on real SUMO, in worker processes."""

import json
import subprocess
import sys

import pandas as pd
import pytest

from scenario_files import tiny_scenario, write_scenario
from vcfusion.errors import UsageError
from vcfusion.studies.batch import run_batch, seed_folder


@pytest.mark.slow
def test_batch_resumes_and_runs_identically(tmp_path, accident_path):
    out = tmp_path / "b"
    first = run_batch(accident_path, list(range(20)), out, workers=2, progress=False)
    assert first == {"done": 20, "skipped": 0, "failed": []}
    mtimes = {p: p.stat().st_mtime_ns for p in out.glob("seed_*/*.parquet")}
    second = run_batch(accident_path, list(range(20)), out, workers=2, progress=False)
    assert second == {"done": 0, "skipped": 20, "failed": []}
    assert {p: p.stat().st_mtime_ns for p in out.glob("seed_*/*.parquet")} == mtimes
    summary = pd.read_parquet(out / "batch_summary.parquet")
    assert summary.seed.tolist() == list(range(20))
    # A run in a worker process gives the same bytes as one in a fresh CLI process.
    cli_out = tmp_path / "cli"
    subprocess.run([sys.executable, "-m", "vcfusion", "run", str(accident_path), "--seed", "7",
                    "--out", str(cli_out)], check=True, capture_output=True)
    for name in ("trajectories", "twins", "ego", "lane_changes", "collisions", "vehicles", "metrics", "conflicts",
                 "metric_histograms", "sumo_emissions"):
        assert (cli_out / f"{name}.parquet").read_bytes() == (seed_folder(out, 7) / f"{name}.parquet").read_bytes()


def test_a_batch_resumes_only_its_own_runs(tmp_path):
    path = tiny_scenario(tmp_path, 2)
    out = tmp_path / "b"
    assert run_batch(path, [0, 1], out, workers=1, progress=False)["done"] == 2
    assert run_batch(path, [0, 1], out, workers=1, progress=False) == {"done": 0, "skipped": 2, "failed": []}
    # the same file edited: its old runs are not this scenario's; nothing is run or written
    tiny_scenario(tmp_path, 3)
    before = sorted(p.name for p in out.iterdir())
    with pytest.raises(UsageError, match=r"seed_0000: holds a run that is not this scenario's run of seed 0 "
                                         r"\(it differs in: simulation\)"):
        run_batch(path, [0, 1, 2], out, workers=1, progress=False)
    assert sorted(p.name for p in out.iterdir()) == before


def test_a_batch_does_not_resume_into_runs_of_a_network_rebuilt_under_the_same_name(tmp_path):
    # the same scenario file naming a network file whose content changed (other lane widths): a
    # manifest that named the network only would pool the old runs with the new
    import shutil

    from scenario_files import REPO

    (tmp_path / "net").mkdir()
    for name in ("highway.net.xml", "vtypes.add.xml"):
        shutil.copy(REPO / "sumo_net" / name, tmp_path / "net" / name)
    path = tiny_scenario(tmp_path, 2)
    path.write_text(path.read_text().replace((REPO / "sumo_net").as_posix(), (tmp_path / "net").as_posix()))
    out = tmp_path / "b"
    assert run_batch(path, [0], out, workers=1, progress=False)["done"] == 1
    net = tmp_path / "net" / "highway.net.xml"
    net.write_text(net.read_text() + "<!-- rebuilt -->\n")
    with pytest.raises(UsageError, match=r"seed_0000: holds a run that is not this scenario's run of seed 0 "
                                         r"\(it differs in: network file \(its content\)\)"):
        run_batch(path, [0, 1], out, workers=1, progress=False)


def test_a_batch_does_not_resume_into_runs_of_another_lane_change_model(tmp_path):
    # the model files shape the results too: the same file name with other weights made other runs
    import shutil

    from vcfusion.prediction.model import default_model_path

    model = tmp_path / "model.npz"
    shutil.copy(default_model_path(), model)
    path = tiny_scenario(tmp_path, 2, f"prediction: {{model: {model.as_posix()}}}\n")
    out = tmp_path / "b"
    assert run_batch(path, [0], out, workers=1, progress=False)["done"] == 1
    manifest = json.loads((seed_folder(out, 0) / "manifest.json").read_text())
    assert set(manifest["files_sha256"]) == {"network", "vehicle_types", "prediction_model"}
    # a folder written before the model's digest was recorded is compared without it
    old = dict(manifest, files_sha256={k: v for k, v in manifest["files_sha256"].items() if k != "prediction_model"})
    (seed_folder(out, 0) / "manifest.json").write_text(json.dumps(old))
    assert run_batch(path, [0], out, workers=1, progress=False) == {"done": 0, "skipped": 1, "failed": []}
    (seed_folder(out, 0) / "manifest.json").write_text(json.dumps(manifest))
    shutil.copy(default_model_path().with_name("lane_change_mlp.npz"), model)  # retrained: another model
    with pytest.raises(UsageError, match=r"seed_0000: .*\(it differs in: prediction_model file \(its content\)\)"):
        run_batch(path, [0, 1], out, workers=1, progress=False)


@pytest.mark.slow
def test_batch_isolates_failing_seeds(tmp_path):
    # Each seed draws one vehicle in [1950, 2100] m on a 2000 m road: beyond the end it cannot depart.
    path = write_scenario(tmp_path, """
name: impossible
network: NET_DIR/highway.net.xml
vehicle_types: NET_DIR/vtypes.add.xml
simulation: {step_s: 0.1, max_time_s: 5}
vehicles:
  - {name: far, count: 1, lanes: [0], pos_m: [1950, 2100]}
""")
    out = tmp_path / "b"
    proc = subprocess.run([sys.executable, "-m", "vcfusion", "batch", str(path), "--seeds", "0-9",
                           "--workers", "2", "--out", str(out)], capture_output=True, text=True)
    failures = json.loads((out / "failures.json").read_text())
    assert proc.returncode == 1
    assert 0 < len(failures) < 10
    assert all("impossible departure" in msg for msg in failures.values())
    done = sorted(p.name for p in out.glob("seed_*") if (p / "manifest.json").exists())
    assert len(done) == 10 - len(failures)
    assert f"{len(failures)} failed" in proc.stdout
    assert not list(out.glob("*.tmp-writing*"))


def test_a_batch_without_a_complete_seed_keeps_no_summary_of_an_earlier_one(tmp_path):
    """Seeds 0-2 of an earlier batch into the same folder left batch_summary.parquet; a re-run of
    seeds 10-11 that all failed kept it, and the batch's metrics then reported seeds 0-2."""
    from vcfusion.studies.batch import SeedOutcome, _write_index

    pd.DataFrame({"seed": [0, 1, 2]}).to_parquet(tmp_path / "batch_summary.parquet")
    _write_index(tmp_path, [10, 11], [SeedOutcome(10, False, None, "RunError: x"),
                                      SeedOutcome(11, False, None, "RunError: y")])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["failures.json"]
    assert json.loads((tmp_path / "failures.json").read_text()) == {"10": "RunError: x", "11": "RunError: y"}


@pytest.mark.slow
def test_accident_cut_ins_ahead_of_ego(tmp_path, accident_path):
    """Acceptance: >= 90 % of seeds 0-49 have a neighbour change into the ego lane ahead of the ego."""
    out = tmp_path / "b"
    report = run_batch(accident_path, list(range(50)), out, workers=2, progress=False)
    assert report["failed"] == []
    summary = pd.read_parquet(out / "batch_summary.parquet")
    assert (summary.cut_ins_ahead_of_ego > 0).mean() >= 0.9
    assert summary.collisions.sum() == 0


@pytest.mark.slow
def test_dask_cluster_gives_the_same_files(tmp_path, accident_path):
    from distributed import LocalCluster

    from vcfusion.studies.batch import Executor

    seeds = [0, 1, 2, 3]
    run_batch(accident_path, seeds, tmp_path / "pool", workers=2, progress=False)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        executor = Executor(dask_scheduler=cluster.scheduler_address)
        report = run_batch(accident_path, seeds, tmp_path / "dask", progress=False, executor=executor)
        assert report == {"done": 4, "skipped": 0, "failed": []}
        again = run_batch(accident_path, seeds, tmp_path / "dask", progress=False, executor=executor)
        assert again["skipped"] == 4 and again["done"] == 0
    for seed in seeds:
        for table in (tmp_path / "pool" / f"seed_{seed:04d}").glob("*.parquet"):
            assert table.read_bytes() == (tmp_path / "dask" / f"seed_{seed:04d}" / table.name).read_bytes(), table.name


def _worker_state():
    import os
    import sys

    import libsumo

    return os.getpid(), "vcfusion.worker_preload" in sys.modules, libsumo.simulation.isLoaded()


def test_workers_start_warm_and_without_a_simulation():
    """Workers come from the fork server that preloaded the run code and kernels; none inherits
    a SUMO simulation."""
    import multiprocessing
    import os

    from vcfusion.workers import run_jobs

    states = [state for _, state in run_jobs(_worker_state, [()] * 4, 2)]
    assert all(pid != os.getpid() for pid, _, _ in states)
    if "forkserver" in multiprocessing.get_all_start_methods():  # else spawned fresh
        assert all(preloaded for _, preloaded, _ in states)
    assert not any(loaded for _, _, loaded in states)
