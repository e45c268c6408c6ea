import numpy as np
import pytest

from vcfusion.prediction.features import FEATURE_NAMES
from vcfusion.prediction.model import LaneChangeModel, ModelFileError, build_torch_mlp, load_model, save_model


def _random_model(rng, names=FEATURE_NAMES, hidden=16):
    f = len(names)
    shapes = [(hidden, f), (hidden, hidden), (1, hidden)]
    weights = [(rng.normal(0, 0.5, s).astype(np.float32), rng.normal(0, 0.1, s[0]).astype(np.float32)) for s in shapes]
    return LaneChangeModel(tuple(names), rng.normal(0, 1, f), rng.uniform(0.5, 2, f), weights, tau=5.0, tau_g=2.0,
                           period_s=0.1, threshold=0.7, smoothing="conservative", tau_a_ticks=12, tau_c_ticks=4,
                           thresholds={"none": 0.9, "aggressive": 0.95, "conservative": 0.7})


def test_save_load_roundtrip_and_torch_equals_numpy(tmp_path):
    import torch

    rng = np.random.default_rng(1)
    model = _random_model(rng)
    path = save_model(model, tmp_path / "m.npz")
    loaded = load_model(path)
    assert loaded.feature_names == FEATURE_NAMES
    assert (loaded.tau, loaded.tau_g, loaded.threshold, loaded.smoothing, loaded.tau_a_ticks, loaded.tau_c_ticks) == \
        (5.0, 2.0, 0.7, "conservative", 12, 4)
    assert loaded.threshold_for("aggressive") == 0.95 and loaded.threshold_for("none") == 0.9
    x = rng.normal(0, 3, (500, len(FEATURE_NAMES))).astype(np.float32)
    p_np = loaded.predict_proba(x)
    np.testing.assert_array_equal(p_np, model.predict_proba(x))
    module = loaded.to_torch()
    assert isinstance(module, torch.nn.Sequential) and len([m for m in module if isinstance(m, torch.nn.Linear)]) == 3
    with torch.no_grad():
        xt = (torch.from_numpy(x) - torch.from_numpy(loaded.mean)) / torch.from_numpy(loaded.std)
        p_torch = torch.sigmoid(module(xt)[:, 0]).numpy()
    assert np.max(np.abs(p_np - p_torch)) < 5e-6  # float32, different summation order
    assert 0.01 < p_np.mean() < 0.99  # a non-degenerate check


def test_mismatched_feature_list_fails_clearly(tmp_path):
    rng = np.random.default_rng(2)
    names = list(FEATURE_NAMES[:-1]) + ["time_since_blinker_on"]
    path = save_model(_random_model(rng, names=names), tmp_path / "old.npz")
    with pytest.raises(ModelFileError, match=r"old\.npz: feature list does not match.*time_since_blinker_on.*retrain"):
        load_model(path)
    reordered = list(FEATURE_NAMES[1:]) + [FEATURE_NAMES[0]]
    path = save_model(_random_model(rng, names=reordered), tmp_path / "reordered.npz")
    with pytest.raises(ModelFileError, match="different order"):
        load_model(path)


def test_not_a_model_file(tmp_path):
    bad = tmp_path / "x.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ModelFileError, match="not a vcfusion lane-change model"):
        load_model(bad)
    with pytest.raises(ModelFileError, match="not found"):
        load_model(tmp_path / "missing.npz")


def test_torch_builder_shape():
    m = build_torch_mlp(len(FEATURE_NAMES), 8)
    assert [type(x).__name__ for x in m] == ["Linear", "ReLU", "Linear", "ReLU", "Linear"]
    widths = [(x.in_features, x.out_features) for x in m if type(x).__name__ == "Linear"]
    assert widths == [(len(FEATURE_NAMES), 8), (8, 8), (8, 1)]  # features -> hidden -> hidden -> one logit


def test_platt_calibration_recovers_a_known_mapping_and_is_saved(tmp_path):
    from vcfusion.prediction.model import fit_platt

    rng = np.random.default_rng(3)
    z = rng.normal(0, 3, 200_000)
    y = rng.random(len(z)) < 1 / (1 + np.exp(-(0.4 * z - 2.0)))  # true P(y | z) = sigmoid(0.4 z - 2)
    a, b = fit_platt(z, y)
    assert a == pytest.approx(0.4, abs=0.02) and b == pytest.approx(-2.0, abs=0.05)
    with pytest.raises(ValueError, match="both classes"):
        fit_platt(z, np.zeros(len(z)))
    model = _random_model(rng)
    x = rng.normal(0, 3, (300, len(FEATURE_NAMES))).astype(np.float32)
    raw = model.predict_proba(x)
    model.calibration = (a, b)
    loaded = load_model(save_model(model, tmp_path / "cal.npz"))
    assert loaded.calibration == pytest.approx((a, b))
    expected = 1 / (1 + np.exp(-(a * loaded.logits(x) + b)))
    np.testing.assert_allclose(loaded.predict_proba(x), expected, rtol=1e-5, atol=1e-6)
    assert not np.allclose(loaded.predict_proba(x), raw)  # calibration is applied, not just stored


def test_file_without_calibration_is_uncalibrated(tmp_path):
    import json

    rng = np.random.default_rng(4)
    model = _random_model(rng)
    path = save_model(model, tmp_path / "m.npz")
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(str(arrays["meta"]))
    del meta["calibration"]  # a file written before calibration existed
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "old.npz", **arrays)
    loaded = load_model(tmp_path / "old.npz")
    assert loaded.calibration == (1.0, 0.0)
    x = rng.normal(0, 3, (50, len(FEATURE_NAMES))).astype(np.float32)
    np.testing.assert_allclose(loaded.predict_proba(x), 1 / (1 + np.exp(-loaded.logits(x))), rtol=1e-5)


@pytest.mark.parametrize("kind", ["mlp", "gru"])
def test_a_model_write_cut_off_leaves_the_old_file_whole_and_nothing_else(tmp_path, monkeypatch, kind):
    # a writer killed (here: failing) after its first bytes: the file under the final name is still the
    # previous model, and no half-written temporary file stays beside it
    from test_prediction_sequence import _model

    from vcfusion.prediction.sequence import save_sequence_model

    save = save_model if kind == "mlp" else save_sequence_model
    model = _random_model(np.random.default_rng(0)) if kind == "mlp" else _model()
    path = save(model, tmp_path / "m.npz")
    before = path.read_bytes()

    def cut_off(file, **arrays):
        with open(file, "wb") as fh:
            fh.write(b"PK\x03\x04 half")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", cut_off)
    with pytest.raises(KeyboardInterrupt):
        save(model, path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz"]
