"""Hand-made folders of finished guidance studies (`vcfusion study guidance` output reduced to what
the matrix and the tables tool read): summary.json and trips.parquet."""

import json
from pathlib import Path

import pandas as pd

from vcfusion.studies.guidance import EMISSION_METRICS, SAFETY_METRICS


def write_study_folder(folder: Path, scenario: str, rows: list[dict], wall_s: float = 12.5,
                       failed: dict | None = None, trips_from_log: int = 0) -> Path:
    """The folder with its summary and one trip row per dict of `rows`; every paired metric a row
    does not give is 1.0, the highlight counts 0."""
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text(json.dumps({"scenario": scenario, "wall_s": wall_s, "failed": failed or {},
                                                     "trips_from_log": trips_from_log}))
    base = {**{m[0]: 1.0 for m in SAFETY_METRICS + EMISSION_METRICS}, "collisions": 0, "highlights_right": 0,
            "highlights_wrong": 0, "missed_warnings": 0, "unseen_warnings": 0}
    pd.DataFrame([base | row for row in rows]).to_parquet(folder / "trips.parquet")
    return folder
