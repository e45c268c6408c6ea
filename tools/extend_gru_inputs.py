"""A GRU file with more inputs, the new ones at zero input weight (its probabilities unchanged), to
be fine-tuned with them (docs/components/real-data.md, "Lateral speed over the vehicle's own sway":
the candidate's pretrained weights, the sway inputs learnt from the recordings only).

    python tools/extend_gru_inputs.py MODEL DATASET... --inputs sway --out FILE

The new inputs are standardised on the train seeds of the DATASETs (for the recordings: their
development parts), as `vcfusion train` standardises a model's inputs on its training data.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from vcfusion.prediction.dataset import DatasetError
from vcfusion.prediction.features import SEQUENCE_INPUT_SETS, stored_columns, with_derived_columns
from vcfusion.prediction.model import load_model
from vcfusion.prediction.sequence import save_sequence_model
from vcfusion.prediction.train import combined_stream, load_datasets
from vcfusion.prediction.train_sequence import extend_inputs


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("model")
    p.add_argument("datasets", nargs="+")
    p.add_argument("--inputs", required=True, choices=sorted(SEQUENCE_INPUT_SETS))
    p.add_argument("--out", required=True, type=Path)
    a = p.parse_args()
    if a.out.exists():
        p.error(f"{a.out}: exists")
    try:
        model = load_model(a.model)
        if model.kind != "gru" or hasattr(model, "members"):
            got = "an ensemble; extend each member" if model.kind == "gru" else "an MLP"
            raise ValueError(f"{a.model}: a GRU file is expected (got {got})")
        names = SEQUENCE_INPUT_SETS[a.inputs]
        new = list(names[len(model.feature_names):])
        infos = load_datasets([Path(d) for d in a.datasets])
        stream, _ = combined_stream(infos, "train", ["seed", "vehicle_id", "time", *stored_columns(new)])
        with_derived_columns(stream, new, infos[0].period_s)
        x = stream[new].to_numpy(np.float64)
        out = extend_inputs(model, names, x.mean(axis=0), np.maximum(x.std(axis=0), 1e-6))
    except (DatasetError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out.info = {**(model.info or {}), "extended_inputs": {"from": str(a.model), "new": new,
                                                          "standardised_on": [str(d) for d in a.datasets]}}
    save_sequence_model(out, a.out)
    print(f"{a.out}: {len(names)} inputs ({', '.join(new)} new, zero input weights)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
