"""tools/real_alarms_cv.py --seeds: per fold one fine-tuning per seed and their ensemble scored;
a work folder of single fine-tunings is never replaced by ensembles (or the reverse)."""

import sys

import numpy as np
import pytest

from vcfusion.commands import main
from vcfusion.prediction.ensemble import EnsembleModel
from vcfusion.prediction.features import SEQUENCE_INPUT_SETS
from vcfusion.prediction.model import load_model
from vcfusion.prediction.sequence import SequenceModel, save_sequence_model

from support.tool_modules import load_tool





def _fake_run(calls):
    """Stands in for `vcfusion ARGS`: `train` writes a small GRU drawn from its --seed, the rest runs."""
    def run(*args):
        calls.append(args)
        if args[0] != "train":
            assert main(list(args)) == 0
            return
        seed = int(args[len(args) - 1 - args[::-1].index("--seed") + 1])
        names = SEQUENCE_INPUT_SETS["lateral"]
        rng, f, h = np.random.default_rng(seed), len(names), 3
        save_sequence_model(SequenceModel(names, np.zeros(f), np.ones(f), rng.normal(0, 1, (3 * h, f)),
                                          rng.normal(0, 1, (3 * h, h)), np.zeros(3 * h), np.zeros(3 * h),
                                          rng.normal(0, 1, (1, h)), np.zeros(1), tau=5.0, tau_g=2.0, period_s=0.1),
                            args[args.index("--out") + 1])
    return run


def test_seeds_fine_tune_once_per_seed_and_score_their_ensemble(tmp_path, monkeypatch):
    tool = load_tool("real_alarms_cv")
    calls = []
    monkeypatch.setattr(tool, "run", _fake_run(calls))
    tool.scored_models(tmp_path, 2, "init.npz", "3e-4", ["--", "--inputs", "lateral"], [0, 4])
    trains = [c for c in calls if c[0] == "train"]
    assert [c[c.index("--seed") + 1] for c in trains] == ["0", "4"] and all(c.count("--seed") == 1 for c in trains)
    assert [c[c.index("--out") + 1] for c in trains] == [str(tmp_path / "ft_cv2_seed0.npz"),
                                                         str(tmp_path / "ft_cv2_seed4.npz")]
    assert all("--" not in c and "--inputs" in c for c in trains)
    ens = load_model(tmp_path / "ft_cv2.npz")
    assert isinstance(ens, EnsembleModel) and len(ens.members) == 2
    assert ens.info["ensemble"]["members"] == ["ft_cv2_seed0.npz", "ft_cv2_seed4.npz"]
    # run again: the members are kept, the ensemble rewritten from them
    calls.clear()
    tool.scored_models(tmp_path, 2, "init.npz", "3e-4", [], [0, 4])
    assert [c[0] for c in calls] == ["ensemble-models"]
    # a single fine-tuning does not take the ensemble's place, nor the reverse
    with pytest.raises(SystemExit, match="an ensemble"):
        tool.scored_models(tmp_path, 2, "init.npz", "3e-4", [], None)
    tool.scored_models(tmp_path, 1, "init.npz", "3e-4", ["--seed", "1"], None)
    assert calls[-1][0] == "train" and calls[-1][-1] == str(tmp_path / "ft_cv1.npz")
    with pytest.raises(SystemExit, match="a single fine-tuning"):
        tool.scored_models(tmp_path, 1, "init.npz", "3e-4", [], [0, 1])


def test_seed_is_not_read_as_an_abbreviation_of_seeds(tmp_path, monkeypatch, capsys):
    tool = load_tool("real_alarms_cv")
    monkeypatch.setattr(sys, "argv", ["real_alarms_cv.py", "ng", "cr", "init.npz", str(tmp_path / "w"),
                                      "--seeds", "0,1", "--seed", "3"])
    with pytest.raises(SystemExit):
        tool.main()
    assert "--seeds and --seed: give one of them" in capsys.readouterr().err
