"""The lane-change sequence model (issue 14): a GRU over each twin's history at the V2C period.

Inputs per tick: the MLP's features (FEATURE_NAMES) plus SEQUENCE_EXTRA_NAMES (the distance to
the end of the own lane), standardised; one GRU layer (torch's GRUCell equations, gates r, z, n)
whose hidden state is carried from tick to tick per twin, and a linear output unit on the hidden
state: P(the twin's lane change ends within tau s) after Platt calibration (as the MLP,
:func:`vcfusion.prediction.model.fit_platt`). The state summarises the whole history of the
twin since it appeared, not a fixed window: SUMO's lane-change model decides from urges it
accumulates over many seconds, which a 2 s trend cannot reconstruct.

Model file: one `.npz` (no pickle) like the MLP's, with `meta.format` = SEQUENCE_FORMAT and
`meta.kind` = "gru"; :func:`vcfusion.prediction.model.load_model` reads either kind.

Run time (:class:`SequenceState`): one GRU step per tick for all twins of the snapshot (a batch),
in NumPy float32; a twin's state is created (zeros) when it appears, carried while it is seen,
and dropped when it has been absent for `reset_gap_ticks` ticks or more, i.e. when it reappears
more than `reset_gap_ticks` periods after it was last seen (it then starts again from zeros, as
a new twin; after a shorter gap its last state is kept). Offline (datasets, evaluation) the same
rule splits a vehicle's samples into segments at time gaps longer than reset_gap_ticks periods
(:func:`segment_bounds`), and
:meth:`SequenceModel.sequence_logits` runs the same NumPy step over all segments at once, so the
offline probabilities are the run-time ones (tested).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vcfusion.prediction.decision import (DECISION_META_KEYS, DecisionSettings, check_model_meta,
                                          decision_settings_from_meta, write_model_file)
from vcfusion.threads import one_blas_thread

SEQUENCE_FORMAT = "vcfusion-lane-change-gru/1"
DEFAULT_RESET_GAP_TICKS = 10  # a twin unseen for more than 1 s (at 0.1 s) starts from a zero state
_EPS = 1e-6


def _sigmoid_of_half(half_z: np.ndarray) -> np.ndarray:
    """sigmoid(z) from half_z = 0.5 z, in place of half_z (a new array of the caller's): the
    operations of 0.5 (1 + tanh(0.5 z)) in their order, without a new array for each (no
    overflow warning for large |z|)."""
    np.tanh(half_z, out=half_z)
    half_z += 1.0
    half_z *= 0.5
    return half_z


@dataclass
class SequenceModel(DecisionSettings):
    feature_names: tuple[str, ...]
    mean: np.ndarray
    std: np.ndarray
    w_ih: np.ndarray  # (3H, F) torch layout, gates r, z, n
    w_hh: np.ndarray  # (3H, H)
    b_ih: np.ndarray  # (3H,)
    b_hh: np.ndarray  # (3H,)
    w_out: np.ndarray  # (1, H)
    b_out: np.ndarray  # (1,)
    reset_gap_ticks: int = DEFAULT_RESET_GAP_TICKS
    kind = "gru"

    def __post_init__(self):
        f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
        self.mean, self.std = f32(self.mean), f32(self.std)
        self.w_ih, self.w_hh, self.b_ih, self.b_hh = f32(self.w_ih), f32(self.w_hh), f32(self.b_ih), f32(self.b_hh)
        self.w_out, self.b_out = f32(self.w_out), f32(self.b_out)
        self.hidden = self.w_hh.shape[1]
        # transposed for row batches (the standardisation is not folded into the weights: that
        # changes the float32 rounding, and the step must equal torch's GRUCell to 1e-6)
        self._wi_t = np.ascontiguousarray(self.w_ih.T)
        self._wh_t = np.ascontiguousarray(self.w_hh.T)
        self._wo = np.ascontiguousarray(self.w_out[0])

    def check_features(self, names, source: str = "model") -> None:
        from vcfusion.prediction.model import ModelFileError

        if tuple(names) != self.feature_names:
            raise ModelFileError(f"{source}: feature list does not match this version of "
                                 f"vcfusion.prediction.features (the model has {len(self.feature_names)} inputs, "
                                 f"the code computes {len(tuple(names))}); retrain with `vcfusion train --kind gru`")

    # --- the GRU step (NumPy float32) ---
    def step(self, h: np.ndarray, x: np.ndarray) -> np.ndarray:
        """New hidden states (N, H) from states h (N, H) and raw (unstandardised) features x (N, F)."""
        H = self.hidden
        # the operations of the GRUCell in their order, each into an array of its own step (one
        # new array fewer per operation than the expressions, the same float32 results)
        xs = np.array(x, dtype=np.float32)
        xs -= self.mean
        xs /= self.std
        with one_blas_thread():
            gi = xs @ self._wi_t
            gh = h @ self._wh_t
        gi += self.b_ih
        gh += self.b_hh
        rz = gi[:, :2 * H] + gh[:, :2 * H]
        rz *= 0.5
        rz = _sigmoid_of_half(rz)
        r, z = rz[:, :H], rz[:, H:]
        n = r * gh[:, 2 * H:]
        n += gi[:, 2 * H:]  # gi + r gh: the sum's operands swapped, the same IEEE sum
        np.tanh(n, out=n)
        out = h - n
        out *= z
        out += n  # n + z (h - n) = (1 - z) n + z h
        return out.astype(np.float32, copy=False)

    def output_logits(self, h: np.ndarray) -> np.ndarray:
        return h @ self._wo + self.b_out[0]

    def calibrated(self, z: np.ndarray) -> np.ndarray:
        a, b = self.calibration
        # float32 in, float32 out (NumPy's Python-scalar rule): the cast copies only other inputs
        t = np.float32(a) * z
        t += np.float32(b)
        t *= 0.5
        return _sigmoid_of_half(t).astype(np.float32, copy=False)

    def sequence_logits(self, x: np.ndarray, bounds: list[tuple[int, int]]) -> np.ndarray:
        """Logits of every row of x (rows of each segment (start, stop) in time order), each
        segment run from a zero state: all segments advance together, one batched step per tick."""
        x = np.asarray(x, dtype=np.float32)
        out = np.empty(len(x), dtype=np.float32)
        if not bounds:
            return out
        starts = np.array([a for a, _ in bounds], dtype=np.int64)
        lengths = np.array([b - a for a, b in bounds], dtype=np.int64)
        order = np.argsort(-lengths, kind="stable")  # longest first: the active segments are a prefix
        starts, lengths = starts[order], lengths[order]
        h = np.zeros((len(bounds), self.hidden), dtype=np.float32)
        for t in range(int(lengths[0]) if len(lengths) else 0):
            active = int(np.searchsorted(-lengths, -t, side="left"))  # segments longer than t
            rows = starts[:active] + t
            h[:active] = self.step(h[:active], x[rows])
            out[rows] = self.output_logits(h[:active])
        return out

    def stream_proba(self, stream, inputs: list[str]) -> np.ndarray:
        """Calibrated P per row of a samples stream sorted by (seed, vehicle_id, time)."""
        bounds = segment_bounds(stream, self.period_s, self.reset_gap_ticks)
        return self.calibrated(self.sequence_logits(stream[inputs].to_numpy(np.float32), bounds))

    def to_torch(self):
        """(torch.nn.GRUCell, torch.nn.Linear) with this model's weights (tests, comparisons)."""
        import torch

        cell = torch.nn.GRUCell(len(self.feature_names), self.hidden)
        head = torch.nn.Linear(self.hidden, 1)
        with torch.no_grad():
            for p, a in ((cell.weight_ih, self.w_ih), (cell.weight_hh, self.w_hh), (cell.bias_ih, self.b_ih),
                         (cell.bias_hh, self.b_hh), (head.weight, self.w_out), (head.bias, self.b_out)):
                p.copy_(torch.from_numpy(a))
        return cell, head


def segment_bounds(stream, period_s: float, reset_gap_ticks: int) -> list[tuple[int, int]]:
    """(start, stop) row ranges of a stream sorted by (seed, vehicle_id, time): one per vehicle
    track, split where consecutive samples are more than reset_gap_ticks periods apart."""
    seeds = stream["seed"].to_numpy()
    vids = stream["vehicle_id"].to_numpy()
    times = stream["time"].to_numpy(dtype=float)
    if not len(times):
        return []
    new = (seeds[1:] != seeds[:-1]) | (vids[1:] != vids[:-1]) | (
        np.diff(times) > reset_gap_ticks * period_s + _EPS)
    change = np.flatnonzero(new) + 1
    starts = np.concatenate([[0], change])
    stops = np.concatenate([change, [len(times)]])
    return list(zip(starts.tolist(), stops.tolist()))


class SequenceState:
    """The per-twin GRU states of the cloud predictor (see the module docstring)."""

    def __init__(self, model: SequenceModel):
        self.model = model
        self._row: dict[str, int] = {}
        self._ids: list[str] = []
        self._h = np.zeros((0, model.hidden), dtype=np.float32)
        self._last = np.zeros(0)  # time each kept state was last updated
        self._oldest = np.inf  # self._last.min() (inf when no state is kept)

    def __len__(self) -> int:
        return len(self._ids)

    def __call__(self, ids, time: float, features: np.ndarray) -> np.ndarray:
        """Calibrated probabilities of the twins `ids` at `time` from their features (N, F)."""
        m = self.model
        ids = list(ids)
        limit = m.reset_gap_ticks * m.period_s + _EPS
        if ids == self._ids and len(ids) and time - self._oldest <= limit:
            # the common tick: the very twins of the last tick, every state carried (the general
            # path below gives the same states and probabilities, with a dozen more array calls)
            h = m.step(self._h, features)
            self._h = h
            self._last = np.full(len(ids), time)
            self._oldest = float(time)
            return m.calibrated(m.output_logits(h))
        h = np.zeros((len(ids), m.hidden), dtype=np.float32)
        prev = np.array([self._row.get(v, -1) for v in ids], dtype=np.int64)
        known = prev >= 0
        if known.any():
            fresh = known.copy()
            fresh[known] = time - self._last[prev[known]] <= limit  # a longer gap: start again from zeros
            h[fresh] = self._h[prev[fresh]]
        h = m.step(h, features) if len(ids) else h
        prob = m.calibrated(m.output_logits(h)) if len(ids) else np.zeros(0, np.float32)
        # keep the twins absent this tick whose gap is still short enough
        seen = np.zeros(len(self._ids), dtype=bool)
        seen[prev[known]] = True
        keep = np.flatnonzero(~seen & (time - self._last <= limit))
        self._ids = ids + [self._ids[k] for k in keep]
        self._h = np.concatenate([h, self._h[keep]]) if len(keep) else h
        self._last = np.concatenate([np.full(len(ids), time), self._last[keep]])
        self._oldest = float(self._last.min()) if len(self._last) else np.inf
        self._row = dict(zip(self._ids, range(len(self._ids))))
        return prob


# --- model file ---------------------------------------------------------------------------------
SEQUENCE_META_KEYS = {"feature_names": list, **DECISION_META_KEYS, "hidden": int, "reset_gap_ticks": int,
                      "calibration": list, "thresholds": dict}
_ARRAYS = ("mean", "std", "w_ih", "w_hh", "b_ih", "b_hh", "w_out", "b_out")


def sequence_meta(model: SequenceModel) -> dict:
    """What a GRU's model file records besides its arrays (``_ARRAYS``); an ensemble's file records it per member."""
    return {"format": SEQUENCE_FORMAT, "kind": "gru", "feature_names": list(model.feature_names),
            "hidden": model.hidden, "reset_gap_ticks": model.reset_gap_ticks, **model.decision_meta()}


def save_sequence_model(model: SequenceModel, path) -> Path:
    return write_model_file(path, sequence_meta(model), {name: getattr(model, name) for name in _ARRAYS})


def sequence_model_from_file(path, meta: dict, arrays: dict) -> SequenceModel:
    """A SequenceModel from a model file's meta and arrays, each checked (ModelFileError naming
    the file and the field)."""
    from vcfusion.prediction.model import ModelFileError

    check_model_meta(path, meta, SEQUENCE_META_KEYS, "`vcfusion train --kind gru`")
    if meta["hidden"] < 1 or meta["reset_gap_ticks"] < 0:
        raise ModelFileError(f"{path}: meta.hidden / meta.reset_gap_ticks: expected >= 1 / >= 0, got "
                             f"{meta['hidden']} / {meta['reset_gap_ticks']}")
    f, h = len(meta["feature_names"]), meta["hidden"]
    shapes = {"mean": (f,), "std": (f,), "w_ih": (3 * h, f), "w_hh": (3 * h, h), "b_ih": (3 * h,),
              "b_hh": (3 * h,), "w_out": (1, h), "b_out": (1,)}
    for name, shape in shapes.items():
        a = arrays.get(name)
        if a is None:
            raise ModelFileError(f"{path}: {name}: missing array; expected one of shape {shape}")
        if a.shape != shape or not np.issubdtype(a.dtype, np.floating) or not np.isfinite(a).all():
            raise ModelFileError(f"{path}: {name}: expected a finite float array of shape {shape}, "
                                 f"got {a.dtype} {a.shape}")
    if not (arrays["std"] > 0).all():
        raise ModelFileError(f"{path}: std: expected positive standard deviations")
    return SequenceModel(
        feature_names=tuple(meta["feature_names"]), **{name: arrays[name] for name in _ARRAYS},
        reset_gap_ticks=int(meta["reset_gap_ticks"]), **decision_settings_from_meta(meta))
