"""The lane-change MLP (paper Section IV-B): model file, torch module and NumPy inference.

Three layers (two hidden ReLU layers and a sigmoid output unit), applied to standardised
features. A model file is one `.npz` (no pickle) holding the layer weights, the feature list
and its normalisation, the labelling windows tau / tau_g it was trained for, and the
run-time decision settings (probability threshold, smoothing tau_a / tau_c in V2C ticks).

Run time uses :meth:`LaneChangeModel.predict_proba`, plain NumPy in float32 (no torch import,
a few microseconds for a tick of 100 twins); it equals the torch module within float32 rounding.

Calibration. The network is trained on class-weighted, window-sampled data, so its raw sigmoid
is a score, not a probability. `calibration = (a, b)` (Platt scaling, fitted by `vcfusion
train` on the validation seeds' every-tick stream, see :func:`fit_platt`) maps the network's
logit z to P(the vehicle's lane change ends within tau s) = sigmoid(a z + b) on the stream a
deployed model sees; `predict_proba` returns that. A file without it (older files) has
(1, 0): the raw sigmoid. Decision thresholds in the file refer to the calibrated probability.
"""

from __future__ import annotations

import contextlib
import functools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vcfusion.errors import InputError
from vcfusion.prediction.decision import (DECISION_META_KEYS, DecisionSettings, check_model_meta,
                                          decision_settings_from_meta, write_model_file)
from vcfusion.threads import one_blas_thread

MODEL_FORMAT = "vcfusion-lane-change-mlp/1"
# The shipped default: the GRU sequence model, better than the MLP on the validation seeds of the
# scenario families (issue 14; docs/model-cards.md). The MLP stays selectable
# (`prediction.model: .../lane_change_mlp.npz`).
DEFAULT_MODEL_NAME = "lane_change_gru.npz"
SHIPPED_MODEL_NAMES = ("lane_change_mlp.npz", "lane_change_gru.npz")  # in vcfusion/assets


SMALL_BATCH_ROWS = 4096  # up to this many rows (a tick's twins) the MLP runs on one BLAS thread


class ModelFileError(InputError):
    """A model file that cannot be used here; the message is for the user."""


def default_model_path() -> Path:
    from vcfusion.resources import assets_dir

    return assets_dir() / DEFAULT_MODEL_NAME


@dataclass
class LaneChangeModel(DecisionSettings):
    feature_names: tuple[str, ...]
    mean: np.ndarray
    std: np.ndarray
    weights: list[tuple[np.ndarray, np.ndarray]]  # (W (out, in), b (out,)) per layer, torch layout

    kind = "mlp"

    def stream_proba(self, stream, inputs: list[str]) -> np.ndarray:
        """P per row of a samples stream (each row on its own: the MLP has no state)."""
        return self.predict_proba(stream[inputs].to_numpy(np.float32))

    def __post_init__(self):
        self.mean = np.asarray(self.mean, dtype=np.float32)
        self.std = np.asarray(self.std, dtype=np.float32)
        self.weights = [(np.asarray(w, dtype=np.float32), np.asarray(b, dtype=np.float32)) for w, b in self.weights]
        self._wt = [(np.ascontiguousarray(w.T), b) for w, b in self.weights]
        self._inv_std = (1.0 / self.std).astype(np.float32)

    def logits(self, features: np.ndarray) -> np.ndarray:
        h = np.asarray(features, dtype=np.float32) - self.mean
        h *= self._inv_std
        last = len(self._wt) - 1
        with one_blas_thread() if len(h) <= SMALL_BATCH_ROWS else contextlib.nullcontext():
            for k, (wt, b) in enumerate(self._wt):
                h = h @ wt
                h += b  # in place: this runs every V2C tick on a few rows, where allocations are the cost
                if k < last:
                    np.maximum(h, 0.0, out=h)
        return h[:, 0]

    def predict_proba(self, features: np.ndarray) -> np.ndarray:
        """P(lane change ends within tau) per row of features (N, F), float32 (calibrated, see module doc)."""
        a, b = self.calibration
        z = self.logits(features)
        if (a, b) != (1.0, 0.0):
            z = np.float32(a) * z
            z += np.float32(b)
        # 1 / (1 + exp(-z)), in place
        np.negative(z, out=z)
        np.exp(z, out=z)
        z += np.float32(1.0)
        return np.reciprocal(z, out=z)

    def check_features(self, names, source: str = "model") -> None:
        names = tuple(names)
        if names != self.feature_names:
            missing = [n for n in self.feature_names if n not in names]
            extra = [n for n in names if n not in self.feature_names]
            detail = []
            if missing:
                detail.append(f"the model needs {missing} which the code does not compute")
            if extra:
                detail.append(f"the code computes {extra} which the model was not trained on")
            if not detail:
                detail.append("same features in a different order")
            from vcfusion.prediction.privileged import PRIVILEGED_NAMES

            if set(PRIVILEGED_NAMES) & set(missing):
                # not a stale model: a ceiling, which reads SUMO's own lane-change state
                raise ModelFileError(f"{source}: a privileged (ceiling) model, trained with `vcfusion train "
                                     "--privileged` on SUMO's lane-change state: it scores only datasets built "
                                     "with `vcfusion dataset --privileged`, and never runs in the cloud "
                                     "(prediction.model)")
            raise ModelFileError(f"{source}: feature list does not match this version of "
                                 f"vcfusion.prediction.features ({'; '.join(detail)}); retrain with `vcfusion train`")

    def to_torch(self):
        import torch

        module = build_torch_mlp(len(self.feature_names), self.weights[0][0].shape[0])
        with torch.no_grad():
            for layer, (w, b) in zip([m for m in module if isinstance(m, torch.nn.Linear)], self.weights):
                layer.weight.copy_(torch.from_numpy(w))
                layer.bias.copy_(torch.from_numpy(b))
        return module


def feature_scaling(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) standardising the training rows' features. A feature that never varies in training
    (no trucks: `length` is constant) gets std 1, not a floor of 1e-6: with that, the first truck the
    model met entered it as ~7e6 and was flagged changing lanes at every tick."""
    std = x.std(axis=0)
    return x.mean(axis=0), np.where(std > 1e-6, std, 1.0).astype(np.float32)


def fit_platt(logits: np.ndarray, labels: np.ndarray, iterations: int = 100) -> tuple[float, float]:
    """Platt scaling: (a, b) minimising the log loss of sigmoid(a z + b) against 0/1 labels.

    Newton's method with step halving (a plain Newton step from (1, 0) can overshoot badly when
    the raw scores are far from calibrated, as after class-weighted training)."""
    z = np.asarray(logits, dtype=np.float64)
    y = np.asarray(labels, dtype=np.float64)
    if not (0 < y.sum() < len(y)):
        raise ValueError("calibration needs both classes among the labels")

    def loss(a: float, b: float) -> float:
        u = a * z + b  # log(1 + e^u) - y u, computed stably
        return float(np.mean(np.logaddexp(0.0, u) - y * u))

    a, b = 1.0, 0.0
    current = loss(a, b)
    for _ in range(iterations):
        p = 0.5 * (1.0 + np.tanh(0.5 * (a * z + b)))  # sigmoid without overflow
        w = np.maximum(p * (1 - p), 1e-12)
        grad = np.array([np.mean((p - y) * z), np.mean(p - y)])
        hess = np.array([[np.mean(w * z * z), np.mean(w * z)], [np.mean(w * z), np.mean(w)]]) + 1e-12 * np.eye(2)
        step = np.linalg.solve(hess, grad)
        t = 1.0
        while t > 1e-6 and loss(a - t * step[0], b - t * step[1]) > current:
            t *= 0.5
        a, b = a - t * step[0], b - t * step[1]
        new = loss(a, b)
        if current - new < 1e-12:
            break
        current = new
    return float(a), float(b)


def build_torch_mlp(n_features: int, hidden: int):
    import torch

    return torch.nn.Sequential(
        torch.nn.Linear(n_features, hidden), torch.nn.ReLU(),
        torch.nn.Linear(hidden, hidden), torch.nn.ReLU(),
        torch.nn.Linear(hidden, 1),
    )


def save_model(model: LaneChangeModel, path: str | Path) -> Path:
    meta = {"format": MODEL_FORMAT, "feature_names": list(model.feature_names), "layers": len(model.weights),
            **model.decision_meta()}
    arrays = {"mean": model.mean, "std": model.std}
    for k, (w, b) in enumerate(model.weights):
        arrays[f"w{k}"] = w
        arrays[f"b{k}"] = b
    return write_model_file(path, meta, arrays)


def model_feature_names(path: str | Path) -> tuple[str, ...]:
    """The input features a model file was trained on (read without checking them)."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path}: model file not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            return tuple(json.loads(str(data["meta"]))["feature_names"])
    except Exception as exc:
        raise ModelFileError(f"{path}: not a vcfusion lane-change model file ({type(exc).__name__}: {exc})") from None


def load_model(path: str | Path | None = None, expected_features=None) -> "LaneChangeModel | SequenceModel":
    """Read a model file (None = the shipped default); checks it against the current feature list
    (expected_features; None = what this version computes for the file's kind: FEATURE_NAMES for
    the MLP, one of features.SEQUENCE_INPUT_SETS for the sequence model). The file says its kind
    (`meta.format`): the MLP (:class:`LaneChangeModel`), the GRU
    (:class:`vcfusion.prediction.sequence.SequenceModel`) or an ensemble of GRUs
    (:class:`vcfusion.prediction.ensemble.EnsembleModel`, read as a GRU everywhere).

    Files are cached by path and modification time: a batch process builds one co-simulation
    per seed, and reading the file each time cost ~1 ms of a ~200 ms trip. The model is never
    modified after loading, so sharing it is safe.
    """
    path = Path(path) if path is not None else default_model_path()
    if not path.is_file():
        raise ModelFileError(f"{path}: model file not found")
    expected = None if expected_features is None else tuple(expected_features)
    return _load_model_file(str(path.resolve()), path.stat().st_mtime_ns, expected)


def model_kind(path: str | Path) -> str:
    """'mlp' or 'gru': the kind of model a file holds (read without checking the rest)."""
    from vcfusion.prediction.ensemble import ENSEMBLE_FORMAT
    from vcfusion.prediction.sequence import SEQUENCE_FORMAT

    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path}: model file not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            fmt = json.loads(str(data["meta"])).get("format")
    except Exception as exc:
        raise ModelFileError(f"{path}: not a vcfusion lane-change model file ({type(exc).__name__}: {exc})") from None
    return "gru" if fmt in (SEQUENCE_FORMAT, ENSEMBLE_FORMAT) else "mlp"  # an ensemble of GRUs reads as one


def save_model_file(model, path: str | Path) -> Path:
    """Write any lane-change model (MLP, GRU or an ensemble of GRUs) in its own file format."""
    from vcfusion.prediction.ensemble import EnsembleModel, save_ensemble
    from vcfusion.prediction.sequence import save_sequence_model

    if isinstance(model, EnsembleModel):
        return save_ensemble(model, path)
    return (save_sequence_model if model.kind == "gru" else save_model)(model, path)


# metadata keys a model file must hold, with the type each must have
META_KEYS = {"feature_names": list, **DECISION_META_KEYS, "layers": int}


@functools.lru_cache(maxsize=8)
def _load_model_file(name: str, _mtime_ns: int, expected_features: tuple[str, ...] | None):
    from vcfusion.prediction.ensemble import ENSEMBLE_FORMAT, ensemble_from_file
    from vcfusion.prediction.features import FEATURE_NAMES, SEQUENCE_EXTRA_NAMES
    from vcfusion.prediction.sequence import SEQUENCE_FORMAT, sequence_model_from_file

    path = Path(name)
    try:
        with np.load(path, allow_pickle=False) as data:
            if "meta" not in data:
                raise ModelFileError(f"{path}: meta: missing; expected a model file written by `vcfusion train`")
            meta = json.loads(str(data["meta"]))
            if not isinstance(meta, dict) or meta.get("format") not in (MODEL_FORMAT, SEQUENCE_FORMAT, ENSEMBLE_FORMAT):
                got = meta.get("format") if isinstance(meta, dict) else meta
                raise ModelFileError(f"{path}: format: expected {MODEL_FORMAT!r}, {SEQUENCE_FORMAT!r} or "
                                     f"{ENSEMBLE_FORMAT!r}, got {got!r}")
            if meta["format"] == MODEL_FORMAT:
                _check_meta(path, meta)
            arrays = {k: data[k] for k in data.files if k != "meta"}
    except ModelFileError:
        raise
    except Exception as exc:
        raise ModelFileError(f"{path}: not a vcfusion lane-change model file ({type(exc).__name__}); "
                             "expected a .npz written by `vcfusion train`") from None
    if meta["format"] in (SEQUENCE_FORMAT, ENSEMBLE_FORMAT):
        seq = (sequence_model_from_file if meta["format"] == SEQUENCE_FORMAT else ensemble_from_file)(path, meta, arrays)
        if expected_features is None:  # any input list this version computes (the file records its own)
            from vcfusion.prediction.features import SEQUENCE_INPUT_SETS

            known = [names for names in SEQUENCE_INPUT_SETS.values() if names == seq.feature_names]
            expected_features = known[0] if known else (*FEATURE_NAMES, *SEQUENCE_EXTRA_NAMES)
        seq.check_features(expected_features, source=str(path))
        return seq
    expected_features = expected_features or FEATURE_NAMES
    weights, mean, std = _checked_arrays(path, meta, arrays)
    model = LaneChangeModel(tuple(meta["feature_names"]), mean, std, weights, **decision_settings_from_meta(meta))
    model.check_features(expected_features, source=str(path))
    return model


def _check_meta(path: Path, meta: dict) -> None:
    check_model_meta(path, meta, META_KEYS, "`vcfusion train`")
    if meta["layers"] < 1:
        raise ModelFileError(f"{path}: meta.layers: expected at least 1 layer, got {meta['layers']}")


def _checked_arrays(path: Path, meta: dict, arrays: dict) -> tuple[list, np.ndarray, np.ndarray]:
    """The layers, mean and std, each checked for presence and shape: layer k maps the previous
    layer's outputs (the features for k = 0) to its own, the last has one output."""
    n_features = len(meta["feature_names"])

    def array(name: str, shape: tuple) -> np.ndarray:
        if name not in arrays:
            raise ModelFileError(f"{path}: {name}: missing array; expected one of shape {shape}")
        a = arrays[name]
        ok = a.ndim == len(shape) and all(want is None or got == want for got, want in zip(a.shape, shape))
        if not ok or not np.issubdtype(a.dtype, np.floating):
            want = "(" + ", ".join("any" if w is None else str(w) for w in shape) + ("," * (len(shape) == 1)) + ")"
            raise ModelFileError(f"{path}: {name}: expected a float array of shape {want}, "
                                 f"got {a.dtype} {a.shape}")
        return a

    mean, std = array("mean", (n_features,)), array("std", (n_features,))
    weights, inputs = [], n_features
    for k in range(meta["layers"]):
        last = k == meta["layers"] - 1
        w = array(f"w{k}", (1 if last else None, inputs))
        weights.append((w, array(f"b{k}", (w.shape[0],))))
        inputs = w.shape[0]
    return weights, mean, std
