"""What a lane-change model file holds besides its network, the same for the MLP and the GRU: the
label windows it was trained for, its calibration and the decision settings tuned on validation
(smoothing method, thresholds, Algorithm 3/4 windows). Both model classes inherit it, so the two
file formats read and write these keys with one piece of code."""

from __future__ import annotations

from dataclasses import dataclass, field

# model-file metadata keys of the decision settings, with the type each must have
DECISION_META_KEYS = {"tau": (int, float), "tau_g": (int, float), "period_s": (int, float),
                      "threshold": (int, float), "smoothing": str, "tau_a_ticks": int, "tau_c_ticks": int,
                      "conservative_threshold": (int, float)}


@dataclass(kw_only=True)
class DecisionSettings:
    tau: float
    tau_g: float
    period_s: float
    threshold: float = 0.5
    smoothing: str = "aggressive"
    tau_a_ticks: int = 10
    tau_c_ticks: int = 10
    conservative_threshold: float = 0.5
    info: dict = field(default_factory=dict)
    # Probability threshold per smoothing (none / aggressive / conservative), tuned with it.
    thresholds: dict = field(default_factory=dict)
    # Platt scaling (a, b) of the logit: lc_prob = sigmoid(a * z + b); (1, 0) = uncalibrated.
    calibration: tuple[float, float] = (1.0, 0.0)

    def threshold_for(self, smoothing: str) -> float:
        return float(self.thresholds.get(smoothing, self.threshold))

    def decision_meta(self) -> dict:
        """These settings as model-file metadata."""
        return {"tau": self.tau, "tau_g": self.tau_g, "period_s": self.period_s, "threshold": self.threshold,
                "smoothing": self.smoothing, "tau_a_ticks": self.tau_a_ticks, "tau_c_ticks": self.tau_c_ticks,
                "conservative_threshold": self.conservative_threshold, "thresholds": self.thresholds,
                "calibration": [float(c) for c in self.calibration], "info": self.info}


def decision_settings_from_meta(meta: dict) -> dict:
    """Keyword arguments of the settings from checked model-file metadata (files written before
    calibration and per-smoothing thresholds existed get the uncalibrated defaults)."""
    return dict(tau=float(meta["tau"]), tau_g=float(meta["tau_g"]), period_s=float(meta["period_s"]),
                threshold=float(meta["threshold"]), smoothing=meta["smoothing"],
                tau_a_ticks=int(meta["tau_a_ticks"]), tau_c_ticks=int(meta["tau_c_ticks"]),
                conservative_threshold=float(meta["conservative_threshold"]), info=meta.get("info", {}),
                thresholds={k: float(v) for k, v in meta.get("thresholds", {}).items()},
                calibration=tuple(float(c) for c in meta.get("calibration", (1.0, 0.0))))


def check_model_meta(path, meta: dict, keys: dict, written_by: str) -> None:
    """A model file's metadata checked where every kind agrees: each of ``keys`` (name -> type) present
    with its type, the smoothing one of the methods, the calibration [a, b] (optional: (1, 0));
    ModelFileError naming the file and the field. ``written_by``: the command that writes such files."""
    from vcfusion.prediction.model import ModelFileError

    for key, kind in keys.items():
        if key not in meta:
            raise ModelFileError(f"{path}: meta.{key}: missing; expected a model file written by {written_by}")
        if not isinstance(meta[key], kind) or isinstance(meta[key], bool):
            raise ModelFileError(f"{path}: meta.{key}: expected a {getattr(kind, '__name__', 'number')}, "
                                 f"got {meta[key]!r}")
    if meta["smoothing"] not in ("none", "aggressive", "conservative"):
        raise ModelFileError(f"{path}: meta.smoothing: expected none, aggressive or conservative, "
                             f"got {meta['smoothing']!r}")
    calibration = meta.get("calibration", [1.0, 0.0])
    if not (isinstance(calibration, list) and len(calibration) == 2):
        raise ModelFileError(f"{path}: meta.calibration: expected [a, b], got {calibration!r}")


def write_model_file(path, meta: dict, arrays: dict):
    """One model file: ``arrays`` and the JSON ``meta`` in an .npz (no pickle), written atomically."""
    import json
    from pathlib import Path

    import numpy as np

    from vcfusion.runio import atomic_write

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda tmp: np.savez(tmp, meta=np.array(json.dumps(meta, sort_keys=True)), **arrays))
    return path
