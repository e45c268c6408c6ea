"""Frozen development / validation / held-out splits of imported recordings (issue 46).

A model tuned on real data must be judged on real data it never saw. The split of a recording is
therefore decided once, before any tuning, written to a small JSON file (unit ids and the rule that
made them, no data) and committed; training, decision tuning and the sim-to-real table then read
that file, and the held-out part is scored once, at the end.

Units: whole *recordings* (the `recording` of an imported dataset's seeds: CommonRoad's distinct
recordings) or whole *vehicles* (NGSIM: one recording of a few minutes; a vehicle id's track pieces,
`ID.1`, `ID.2`, ..., stay with the id). Never samples: the ticks of one vehicle are not independent.

Rule (:func:`freeze_split`): the unit ids, sorted, in the order of
``numpy.random.default_rng(seed).permutation``; among the units with a main-lane change, the
development part is the shortest prefix holding at least `fractions[0]` of the changes, the
validation part the next units up to `fractions[0] + fractions[1]`, the rest held out; the units
without a change are cut in the same order at those shares of their number (so each part gets its
share of lane changes and of lane-keeping traffic, the false alarms' denominator).

:func:`apply_split` writes a *split dataset*: the layout of `vcfusion dataset` whose seed
``3 * seed + part`` holds the samples and lane changes of one original seed's units of one part
(part 0 development, 1 validation, 2 held-out) and whose splits are train = development,
validation = validation, test = held-out. `vcfusion train`, `vcfusion evaluate` and
`vcfusion sim-to-real` read it unchanged. Features were computed on the whole recording before the
split (a held-out vehicle is still a neighbour in the development samples, as it is on the road);
only labels and scores are split.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.prediction.dataset import DATASET_JSON, DatasetError, load_dataset
from vcfusion.runio import atomic_write

SPLIT_FORMAT = "vcfusion-real-split/1"
PARTS = ("development", "validation", "held_out")
PART_SPLIT = {"development": "train", "validation": "validation", "held_out": "test"}
DEFAULT_FRACTIONS = (0.6, 0.2)
RULE = ("unit ids sorted, ordered by numpy.random.default_rng({seed}).permutation; units with main-lane changes: "
        "development = the shortest prefix holding >= {f0:g} of the changes, validation = the next units up to "
        ">= {f01:g}, held_out = the rest; units without a change: cut in the same order at {f0:g} and {f01:g} of "
        "their number")


def base_vehicle_id(vid: str) -> str:
    """A reader's track piece `ID.k` (a vehicle id split at a gap) belongs to vehicle `ID`."""
    head, sep, tail = str(vid).rpartition(".")
    return head if sep and tail.isdigit() else str(vid)


def _units(info, by: str) -> tuple[dict[int, str], pd.DataFrame]:
    """(recording of each seed, one row per (seed, vehicle_id) with its unit and lane changes)."""
    seeds_meta = info.meta.get("seeds", {})
    recording = {}
    for seed in info.seeds("all"):
        rec = seeds_meta.get(str(seed), {}).get("recording")
        if by == "recording" and not rec:
            raise DatasetError(f"{info.root / DATASET_JSON}: seeds.{seed}.recording: missing; a split by recording "
                               "needs an imported dataset (`vcfusion dataset --from-...`)")
        recording[seed] = rec or f"seed {seed}"
    rows = []
    for seed in info.seeds("all"):
        vids = pd.read_parquet(info.samples_file(seed), columns=["vehicle_id"])["vehicle_id"].astype(str).unique()
        lc = pd.read_parquet(info.run_folder(seed) / "lane_changes.parquet", columns=["vehicle_id"])
        n_lc = lc["vehicle_id"].astype(str).value_counts()
        for v in vids:
            rows.append({"seed": seed, "vehicle_id": v, "lane_changes": int(n_lc.get(v, 0)),
                         "unit": recording[seed] if by == "recording" else base_vehicle_id(v)})
    return recording, pd.DataFrame(rows, columns=["seed", "vehicle_id", "lane_changes", "unit"])


def freeze_split(dataset: Path, by: str, seed: int = 0, fractions: tuple[float, float] = DEFAULT_FRACTIONS,
                 name: str | None = None) -> dict:
    """The split of an imported dataset's units (see the module docstring) as a JSON-ready dict."""
    if by not in ("recording", "vehicle"):
        raise ValueError(f"by: expected recording or vehicle, got {by!r}")
    f0, f1 = fractions
    if not (0 < f0 < 1 and 0 < f1 < 1 and f0 + f1 < 1):
        raise ValueError(f"fractions: expected development and validation shares in (0, 1) summing below 1, "
                         f"got {fractions}")
    info = load_dataset(dataset)
    _, rows = _units(info, by)
    per_unit = rows.groupby("unit")["lane_changes"].sum()
    units = sorted(per_unit.index)
    order = [units[k] for k in np.random.default_rng(seed).permutation(len(units))]
    with_lc = [u for u in order if per_unit[u] > 0]
    without = [u for u in order if per_unit[u] == 0]
    if len(with_lc) < 3:
        raise DatasetError(f"{dataset}: {len(with_lc)} {by}s with a main-lane change are too few for three parts")
    running = np.cumsum([per_unit[u] for u in with_lc]) / per_unit.sum()
    cut0 = min(len(with_lc) - 2, int(np.searchsorted(running, f0 - 1e-12) + 1))
    cut1 = min(len(with_lc) - 1, max(cut0 + 1, int(np.searchsorted(running, f0 + f1 - 1e-12) + 1)))
    n0, n1 = round(f0 * len(without)), round((f0 + f1) * len(without))
    parts = {"development": with_lc[:cut0] + without[:n0], "validation": with_lc[cut0:cut1] + without[n0:n1],
             "held_out": with_lc[cut1:] + without[n1:]}
    counts = {}
    for part, members in parts.items():
        mine = rows[rows["unit"].isin(members)]
        counts[part] = {"units": len(members), "vehicles": int(len(mine)), "lane_changes": int(mine["lane_changes"].sum())}
    return {"format": SPLIT_FORMAT, "name": name or Path(dataset).name, "by": by, "seed": seed,
            "fractions": [f0, f1, round(1 - f0 - f1, 10)],
            "rule": RULE.format(seed=seed, f0=f0, f01=f0 + f1),
            "source": _source_names(info.meta.get("source", {})), "counts": counts,
            "parts": {k: sorted(v) for k, v in parts.items()}}


def _source_names(source: dict) -> dict:
    """The import's format and its input files' names (no folders: the file is committed)."""
    files = [Path(str(f)).name for key in ("files", "paths", "path") for f in
             (source.get(key) if isinstance(source.get(key), list) else [source.get(key)] if source.get(key) else [])]
    return {"format": source.get("format"), "files": files}


def write_split(split: dict, out: Path) -> Path:
    out = Path(out)
    atomic_write(out, lambda tmp: tmp.write_text(json.dumps(split, indent=1, sort_keys=True) + "\n"))
    return out


def read_split(path: Path) -> dict:
    """A split file, checked (DatasetError naming the file and the field)."""
    path = Path(path)
    try:
        split = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read a split file ({exc})") from None
    if not isinstance(split, dict) or split.get("format") != SPLIT_FORMAT:
        raise DatasetError(f"{path}: format: expected {SPLIT_FORMAT!r} (a file of `vcfusion real-split freeze`)")
    if split.get("by") not in ("recording", "vehicle"):
        raise DatasetError(f"{path}: by: expected recording or vehicle, got {split.get('by')!r}")
    parts = split.get("parts")
    if not isinstance(parts, dict) or set(parts) != set(PARTS) or not all(isinstance(v, list) for v in parts.values()):
        raise DatasetError(f"{path}: parts: expected lists {', '.join(PARTS)}")
    seen = {}
    for part in PARTS:
        for unit in parts[part]:
            if unit in seen:
                raise DatasetError(f"{path}: parts: unit {unit!r} in both {seen[unit]} and {part}")
            seen[unit] = part
    return split


def apply_split(dataset: Path, split_file: Path, out: Path) -> dict:
    """Write the split dataset of `dataset` under the frozen split `split_file` (module docstring).
    Every unit of the dataset must be in the split file: a dataset that is not the one frozen is
    refused before anything is written."""
    from vcfusion.prediction.dataset import SAMPLES
    from vcfusion.studies.batch import seed_folder

    split = read_split(split_file)
    info = load_dataset(dataset)
    _, rows = _units(info, split["by"])
    part_of = {u: p for p in PARTS for u in split["parts"][p]}
    unknown = sorted(set(rows["unit"]) - set(part_of))
    if unknown:
        raise DatasetError(f"{split_file}: {len(unknown)} {split['by']}s of {dataset} are in no part (e.g. "
                           f"{unknown[:3]}); this split was frozen on another dataset")
    out = Path(out)
    if out.exists():
        raise DatasetError(f"{out}: exists; give a new folder for the split dataset")
    tmp = out.with_name(out.name + ".partial")
    if tmp.exists():
        import shutil

        shutil.rmtree(tmp)
    splits = {"train": [], "validation": [], "test": []}
    seeds_meta, counts = {}, {p: {"vehicles": 0, "lane_changes": 0, "samples": 0} for p in PARTS}
    for seed in info.seeds("all"):
        samples = pd.read_parquet(info.samples_file(seed))
        samples["vehicle_id"] = samples["vehicle_id"].astype(str)
        lc = pd.read_parquet(info.run_folder(seed) / "lane_changes.parquet")
        lc_vid = lc["vehicle_id"].astype(str)
        mine = rows[rows["seed"] == seed]
        vid_part = dict(zip(mine["vehicle_id"], mine["unit"].map(part_of)))
        for k, part in enumerate(PARTS):
            vids = {v for v, p in vid_part.items() if p == part}
            if not vids:
                continue
            new = 3 * seed + k
            folder = seed_folder(tmp / "runs", new)
            folder.mkdir(parents=True)
            s = samples[samples["vehicle_id"].isin(vids)].assign(seed=np.int32(new))
            s.to_parquet(folder / SAMPLES, index=False)
            lc[lc_vid.isin(vids).to_numpy()].to_parquet(folder / "lane_changes.parquet", index=False)
            splits[PART_SPLIT[part]].append(new)
            n_lc = int(lc_vid.isin(vids).sum())
            seeds_meta[str(new)] = {**info.meta.get("seeds", {}).get(str(seed), {}), "original_seed": seed,
                                    "part": part, "vehicles": len(vids), "lane_changes": n_lc,
                                    "vehicle_hours": float(len(s) * info.period_s / 3600.0)}
            counts[part]["vehicles"] += len(vids)
            counts[part]["lane_changes"] += n_lc
            counts[part]["samples"] += int(len(s))
    digest = hashlib.sha256(Path(split_file).read_bytes()).hexdigest()
    meta = {**info.meta, "seeds": seeds_meta, "splits": splits,
            "real_split": {"file": Path(split_file).name, "sha256": digest, "by": split["by"],
                           "parts": {p: PART_SPLIT[p] for p in PARTS}, "counts": counts,
                           "original_dataset": str(Path(dataset).name)}}
    (tmp / DATASET_JSON).write_text(json.dumps(meta, indent=1, sort_keys=True))
    tmp.rename(out)
    return meta["real_split"]
