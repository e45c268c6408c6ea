"""Ensembles of lane-change GRUs: K sequence models of the same inputs in one model file, whose
calibrated probabilities are averaged every tick (`vcfusion ensemble-models A.npz B.npz ... --out E.npz`).

Members are GRUs (:class:`vcfusion.prediction.sequence.SequenceModel`) trained alike, typically
fine-tuned from one pretrained file with different `--seed`s: their figures on a small recording
move with the seed (docs: components/real-data.md, "Ensembles of fine-tuning seeds"), and the mean
of their probabilities moves less. All members must have the same inputs (names and order), label
windows tau / tau_g, V2C period and state-reset gap; anything else is refused, naming the file.

The ensemble behaves as one GRU with a hidden state of the members' states side by side:
:meth:`EnsembleModel.step` advances each member on its own block of the state, and
:meth:`EnsembleModel.output_logits` is the logit of the mean of the members' calibrated
probabilities, so the cloud's :class:`vcfusion.prediction.sequence.SequenceState`, the offline
streams (`stream_proba`) and re-calibration (`vcfusion retune`: a Platt scaling of that logit)
use it unchanged. The ensemble's own calibration starts as (1, 0), the identity: its probability
is then the members' mean (to float32 rounding). Its decision settings (smoothing, thresholds,
windows) start as the first member's, which were tuned on that member's probabilities; the
command says so, and `vcfusion retune` or `vcfusion set-decision` choose the ensemble's own.

File: one `.npz` (no pickle), `meta.format` = ENSEMBLE_FORMAT, `meta.members` the members' own
metadata (as their files hold it), member k's arrays under `m{k}_<name>`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vcfusion.prediction.decision import (DECISION_META_KEYS, DecisionSettings, check_model_meta,
                                          decision_settings_from_meta, write_model_file)
from vcfusion.prediction.sequence import (_ARRAYS, SequenceModel, _sigmoid_of_half, segment_bounds, sequence_meta,
                                         sequence_model_from_file)
from vcfusion.threads import one_blas_thread

ENSEMBLE_FORMAT = "vcfusion-lane-change-gru-ensemble/1"
# member properties that must agree: (attribute, what it is)
_MUST_AGREE = (("feature_names", "inputs"), ("tau", "label window tau, s"), ("tau_g", "label window tau_g, s"),
               ("period_s", "V2C period, s"), ("reset_gap_ticks", "state-reset gap, ticks"))


_LOGIT_LIMIT = 40.0  # |logit| cap: finite for a Platt fit (`vcfusion retune`), and sigmoid(+-40) is 1 / 0 in float64


def _logit(p: np.ndarray) -> np.ndarray:
    """log(p / (1 - p)) in float64, within +-_LOGIT_LIMIT (p of exactly 0 or 1 maps back to 0 or 1)."""
    p = np.asarray(p, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.clip(np.log(p) - np.log1p(-p), -_LOGIT_LIMIT, _LOGIT_LIMIT)


@dataclass
class EnsembleModel(DecisionSettings):
    members: tuple[SequenceModel, ...]
    kind = "gru"  # a sequence model wherever one is read (cloud, datasets, evaluation)

    def __post_init__(self):
        self.members = tuple(self.members)
        if not self.members:
            raise ValueError("an ensemble needs at least one member")
        first = self.members[0]
        self.feature_names = tuple(first.feature_names)
        self.reset_gap_ticks = first.reset_gap_ticks
        self.hidden = sum(m.hidden for m in self.members)  # the members' states side by side
        cuts = np.cumsum([0] + [m.hidden for m in self.members]).tolist()
        self._blocks = [(m, a, b) for m, a, b in zip(self.members, cuts[:-1], cuts[1:])]
        # Members of one hidden size and one standardisation (fine-tunings of one file) run as one
        # batched step: the same operations in the same order as each member's, on (K, N, .) arrays.
        self._stacked = len(self.members) > 1 and all(
            m.hidden == first.hidden and np.array_equal(m.mean, first.mean) and np.array_equal(m.std, first.std)
            for m in self.members)
        if self._stacked:
            self._wi_cat = np.ascontiguousarray(np.concatenate([m._wi_t for m in self.members], axis=1))
            self._wh = np.stack([m._wh_t for m in self.members])  # (K, H, 3H)
            self._b_ih = np.stack([m.b_ih for m in self.members])[:, None, :]  # (K, 1, 3H)
            self._b_hh = np.stack([m.b_hh for m in self.members])[:, None, :]
            self._wo = np.stack([m._wo for m in self.members])[:, :, None]  # (K, H, 1)
            self._b_out = np.stack([m.b_out for m in self.members])[:, None, :]  # (K, 1, 1)
            self._cal_a = np.array([m.calibration[0] for m in self.members], np.float32)[:, None, None]
            self._cal_b = np.array([m.calibration[1] for m in self.members], np.float32)[:, None, None]

    def check_features(self, names, source: str = "model") -> None:
        self.members[0].check_features(names, source)

    def step(self, h: np.ndarray, x: np.ndarray) -> np.ndarray:
        """New states (N, sum of hidden) from states h and raw features x (N, F): each member's step on its block."""
        if self._stacked:
            return self._stacked_step(h, x)
        out = np.empty((len(h), self.hidden), dtype=np.float32)
        for m, a, b in self._blocks:
            out[:, a:b] = m.step(h[:, a:b], x)
        return out

    def _stacked_step(self, h: np.ndarray, x: np.ndarray) -> np.ndarray:
        """SequenceModel.step of every member at once (members of one hidden size and standardisation)."""
        first, k, n_rows = self.members[0], len(self.members), len(h)
        H = first.hidden
        xs = np.array(x, dtype=np.float32)
        xs -= first.mean
        xs /= first.std
        hk = np.ascontiguousarray(np.asarray(h, dtype=np.float32).reshape(n_rows, k, H).transpose(1, 0, 2))
        with one_blas_thread():
            gi = (xs @ self._wi_cat).reshape(n_rows, k, 3 * H).transpose(1, 0, 2)  # (K, N, 3H)
            gh = np.matmul(hk, self._wh)
        gi = gi + self._b_ih
        gh += self._b_hh
        rz = gi[..., :2 * H] + gh[..., :2 * H]
        rz *= 0.5
        rz = _sigmoid_of_half(rz)
        r, z = rz[..., :H], rz[..., H:]
        n = r * gh[..., 2 * H:]
        n += gi[..., 2 * H:]
        np.tanh(n, out=n)
        out = hk - n
        out *= z
        out += n
        return np.ascontiguousarray(out.transpose(1, 0, 2)).reshape(n_rows, k * H)

    def mean_proba(self, h: np.ndarray) -> np.ndarray:
        """The mean of the members' calibrated probabilities from the states h."""
        if self._stacked:
            k, n_rows = len(self.members), len(h)
            hk = np.asarray(h, dtype=np.float32).reshape(n_rows, k, -1).transpose(1, 0, 2)
            t = np.matmul(hk, self._wo) + self._b_out  # (K, N, 1): each member's logit
            t = self._cal_a * t
            t += self._cal_b
            t *= 0.5
            p = _sigmoid_of_half(t)[:, :, 0]
            return (p.sum(axis=0, dtype=np.float32) / np.float32(k)).astype(np.float32, copy=False)
        total = None
        for m, a, b in self._blocks:
            p = m.calibrated(m.output_logits(h[:, a:b]))
            total = p if total is None else total + p
        return total / np.float32(len(self.members))

    def output_logits(self, h: np.ndarray) -> np.ndarray:
        return _logit(self.mean_proba(h))

    def calibrated(self, z: np.ndarray) -> np.ndarray:
        return SequenceModel.calibrated(self, z)

    def sequence_logits(self, x: np.ndarray, bounds: list[tuple[int, int]]) -> np.ndarray:
        """Logit of the members' mean calibrated probability for every row (as SequenceModel.sequence_logits)."""
        total = None
        for m in self.members:
            p = m.calibrated(m.sequence_logits(x, bounds))
            total = p if total is None else total + p
        if total is None:
            return np.empty(0)
        return _logit(total / np.float32(len(self.members)))

    def stream_proba(self, stream, inputs: list[str]) -> np.ndarray:
        """Calibrated P per row of a samples stream sorted by (seed, vehicle_id, time)."""
        bounds = segment_bounds(stream, self.period_s, self.reset_gap_ticks)
        return self.calibrated(self.sequence_logits(stream[inputs].to_numpy(np.float32), bounds))

    def to_torch(self):
        raise NotImplementedError("an ensemble has no single torch module; use a member's to_torch()")


def check_members(members, sources) -> None:
    """A ValueError naming the file of the first member that is not a GRU or differs from the first
    member in inputs, label windows, V2C period or state-reset gap."""
    for model, source in zip(members, sources):
        if isinstance(model, EnsembleModel):
            raise ValueError(f"{source}: an ensemble of {len(model.members)} GRUs; give its member files instead")
        if not isinstance(model, SequenceModel):
            raise ValueError(f"{source}: expected a GRU file (`vcfusion train --kind gru`), got an MLP")
    first, first_source = members[0], sources[0]
    for model, source in zip(members[1:], sources[1:]):
        for attr, what in _MUST_AGREE:
            if getattr(model, attr) != getattr(first, attr):
                if attr == "feature_names":
                    mine, theirs = list(model.feature_names), list(first.feature_names)
                    detail = (f"{len(mine)} inputs {mine}" if len(mine) != len(theirs) or set(mine) != set(theirs)
                              else f"the same inputs in another order {mine}")
                    raise ValueError(f"{source}: inputs differ from {first_source}'s: {detail}, expected "
                                     f"{len(theirs)} inputs {theirs}")
                raise ValueError(f"{source}: {what} {getattr(model, attr)} differs from {first_source}'s "
                                 f"{getattr(first, attr)}; members must be trained alike")


def build_ensemble(paths) -> EnsembleModel:
    """The ensemble of the GRU model files `paths` (in order), with the first member's decision
    settings and the identity calibration; ModelFileError for a bad or mismatched file."""
    from vcfusion.prediction.model import ModelFileError, load_model

    paths = [Path(p) for p in paths]
    if not paths:
        raise ModelFileError("ensemble: expected at least one member model file")
    members = [load_model(p) for p in paths]
    try:
        check_members(members, [str(p) for p in paths])
    except ValueError as exc:
        raise ModelFileError(str(exc)) from None
    first = members[0]
    settings = decision_settings_from_meta(first.decision_meta())
    settings["calibration"] = (1.0, 0.0)
    settings["info"] = {"ensemble": {
        "members": [p.name for p in paths],
        "combination": "mean of the members' calibrated probabilities, each tick",
        "decision_from": paths[0].name,
        "note": f"decision settings copied from {paths[0].name} (tuned on its probabilities, not the ensemble's); "
                "`vcfusion retune` or `vcfusion set-decision` choose the ensemble's own"}}
    return EnsembleModel(members=tuple(members), **settings)


def save_ensemble(model: EnsembleModel, path) -> Path:
    arrays = {f"m{k}_{name}": getattr(m, name) for k, m in enumerate(model.members) for name in _ARRAYS}
    meta = {"format": ENSEMBLE_FORMAT, "kind": "gru-ensemble", "feature_names": list(model.feature_names),
            "members": [sequence_meta(m) for m in model.members], **model.decision_meta()}
    return write_model_file(path, meta, arrays)


def ensemble_from_file(path, meta: dict, arrays: dict) -> EnsembleModel:
    """An EnsembleModel from a model file's meta and arrays, each checked (ModelFileError naming the
    file and the field)."""
    from vcfusion.prediction.model import ModelFileError

    check_model_meta(path, meta, {**DECISION_META_KEYS, "feature_names": list, "members": list, "calibration": list,
                                  "thresholds": dict}, "`vcfusion ensemble-models`")
    if not meta["members"] or not all(isinstance(m, dict) for m in meta["members"]):
        raise ModelFileError(f"{path}: meta.members: expected a non-empty list of member metadata")
    members, sources = [], []
    for k, member_meta in enumerate(meta["members"]):
        source = f"{path}: members[{k}]"
        own = {name: arrays[f"m{k}_{name}"] for name in _ARRAYS if f"m{k}_{name}" in arrays}
        members.append(sequence_model_from_file(source, member_meta, own))
        sources.append(source)
    try:
        check_members(members, sources)
    except ValueError as exc:
        raise ModelFileError(str(exc)) from None
    if list(members[0].feature_names) != meta["feature_names"]:
        raise ModelFileError(f"{path}: meta.feature_names: expected the members' inputs "
                             f"{list(members[0].feature_names)}, got {meta['feature_names']}")
    return EnsembleModel(members=tuple(members), **decision_settings_from_meta(meta))
