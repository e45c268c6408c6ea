"""Every input the user controls, refused through the real `vcfusion` command: exit 2, one line
naming the file and the field or line and what was expected, no traceback, nothing written.

Each case builds its inputs in a fresh folder (the working directory of the command) from valid
ones with one defect; the sanity tests below check that the valid ones are valid, so every case
fails for its own defect.
"""

import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
import pytest

from scenario_files import REPO, lifted_highway, write_scenario
from vcfusion.commands import main
from vcfusion.prediction.dataset import ID_COLUMNS, SAMPLES_VERSION, load_dataset
from vcfusion.prediction.features import FEATURE_NAMES
from vcfusion.prediction.model import default_model_path
from vcfusion.scenario import load_scenario

BASE = """name: t
network: NET_DIR/highway.net.xml
vehicle_types: NET_DIR/vtypes.add.xml
simulation: {max_time_s: 2.0}
ego: {lane: 2, depart_pos_m: 50, speed_mps: 19}
vehicles: [{name: car, count: 1, vtype: car, lanes: [1], pos_m: [80, 120]}]
"""
# the on-ramp network's main line: tracks 1-3 are its lanes, track 0 the acceleration lane (700-950 m)
ONRAMP = BASE.replace("highway.net.xml", "onramp.net.xml") + "route: [main_in, accel, main_out]\n"
FUSION = "vision: {enabled: true}\nfusion: {enabled: true, detector: cnn, weights: WEIGHTS}\n"


# --- inputs with one defect, written into the case's folder ---------------------------------

def scenario(tmp: Path, text: str, name: str = "s.yaml") -> str:
    return str(write_scenario(tmp, text, name))


def run(tmp: Path, text: str) -> list[str]:
    return ["run", scenario(tmp, text), "--out", "out"]


def network(tmp: Path, xml: str) -> list[str]:
    (tmp / "bad.net.xml").write_text(xml)
    return run(tmp, BASE.replace("NET_DIR/highway.net.xml", "bad.net.xml"))


def elevated_network(tmp: Path) -> str:
    """BASE on the shipped straight highway lifted to z = 5 m (scenario_files.lifted_highway)."""
    lifted_highway(tmp, 5.0)
    return BASE.replace("NET_DIR/highway.net.xml", "hill.net.xml")


def vtypes(tmp: Path, xml: str) -> list[str]:
    (tmp / "bad.add.xml").write_text(xml)
    return run(tmp, BASE.replace("NET_DIR/vtypes.add.xml", "bad.add.xml"))


def bicycles(tmp: Path) -> str:
    """BASE with its car group on bicycles: the shipped vehicle types and a type 'bike' of vClass
    bicycle, in bikes.add.xml."""
    shipped = (REPO / "sumo_net" / "vtypes.add.xml").read_text()
    (tmp / "bikes.add.xml").write_text(shipped.replace(
        "</additional>", '<vType id="bike" vClass="bicycle" length="1.8" width="0.6" height="1.7"/></additional>'))
    return BASE.replace("vtype: car,", "vtype: bike,").replace("NET_DIR/vtypes.add.xml", "bikes.add.xml")


SHIPPED_MLP = default_model_path().with_name("lane_change_mlp.npz")  # the MLP file's checks


def shipped_model_arrays() -> dict:
    with np.load(SHIPPED_MLP, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def model_file(tmp: Path, change: Callable[[dict, dict], None]) -> Path:
    """The shipped lane-change model with `change(arrays, meta)` applied."""
    arrays = shipped_model_arrays()
    meta = json.loads(str(arrays["meta"]))
    change(arrays, meta)
    arrays["meta"] = np.array(json.dumps(meta))
    path = tmp / "bad.npz"
    np.savez(path, **arrays)
    return path


def with_model(tmp: Path, change) -> list[str]:
    model_file(tmp, change)
    return run(tmp, BASE + "prediction: {model: bad.npz}\n")


def weights_file(tmp: Path, change: Callable[[dict], None]) -> Path:
    """The shipped detector weights with `change(blob)` applied."""
    import torch

    from vcfusion.detection.detector_net import default_weights_path

    blob = torch.load(default_weights_path(), map_location="cpu", weights_only=True)
    change(blob)
    path = tmp / "bad.pt"
    torch.save(blob, path)
    return path


def with_weights(tmp: Path, change) -> list[str]:
    weights_file(tmp, change)
    return run(tmp, BASE + FUSION.replace("WEIGHTS", "bad.pt"))


def dataset(tmp: Path) -> Path:
    """A small valid dataset folder (3 seeds: train, validation, test)."""
    root = tmp / "ds"
    rng = np.random.default_rng(0)
    for seed in range(3):
        folder = root / "runs" / f"seed_{seed:04d}"
        folder.mkdir(parents=True)
        n = 40
        frame = pd.DataFrame({"seed": np.full(n, seed, np.int32), "time": np.arange(n) * 0.1,
                              "vehicle_id": ["v"] * n, "event_id": np.zeros(n, np.int64), "lc_reason": ["strategic"] * n,
                              "time_to_lc": 4.0 - np.arange(n) * 0.1, "time_since_lc": np.full(n, np.nan),
                              "window_label": (np.arange(n) % 2).astype(np.int8),
                              "stream_label": (np.arange(n) % 2).astype(np.int8)})
        for name in FEATURE_NAMES:
            frame[name] = rng.normal(size=n).astype(np.float32)
        frame.to_parquet(folder / "samples.parquet", index=False)
    meta = {"scenario": "t", "tau": 5.0, "tau_g": 2.0, "period_s": 0.1, "feature_names": list(FEATURE_NAMES),
            "samples_version": SAMPLES_VERSION, "splits": {"train": [0], "validation": [1], "test": [2]}}
    (root / "dataset.json").write_text(json.dumps(meta))
    return root


def coco_folder(tmp: Path, change: Callable[[dict], object] = lambda c: None, name: str = "coco",
                n_images: int = 6) -> str:
    """A small valid COCO folder with `change(annotations)` applied to its annotations.json."""
    from support.synthetic_coco import make_synthetic_coco

    folder = make_synthetic_coco(tmp / name, n_images=n_images, size=(64, 48))
    coco = json.loads((folder / "annotations.json").read_text())
    coco = change(coco) or coco
    (folder / "annotations.json").write_text(json.dumps(coco))
    return name


def _set(path: str, value):
    """A change setting coco[key][index][field] = value, path 'key.index.field'."""
    key, index, field = path.split(".")
    return lambda coco: coco[key][int(index)].__setitem__(field, value)


def train_on(tmp: Path, change: Callable[[Path], None]) -> list[str]:
    root = dataset(tmp)
    change(root)
    return ["train", str(root), "--out", "out.npz", "--epochs", "1"]


def set_meta(**changes):
    def change(root: Path) -> None:
        meta = json.loads((root / "dataset.json").read_text())
        meta.update(changes)
        for key in [k for k, v in changes.items() if v is None]:
            del meta[key]
        (root / "dataset.json").write_text(json.dumps(meta))
    return change


def samples_of(seed: int, root: Path) -> Path:
    return root / "runs" / f"seed_{seed:04d}" / "samples.parquet"


def drop_column(root: Path) -> None:
    f = samples_of(1, root)
    pd.read_parquet(f).drop(columns=["window_label"]).to_parquet(f, index=False)


@dataclass(frozen=True)
class Case:
    name: str
    build: Callable[[Path], list[str]]  # writes the inputs into the folder, returns the command line
    expected: tuple[str, ...]  # fragments of the one error line: file, field or line, expectation


CASES = [
    # scenario YAML: syntax, shape, types, ranges, unknown keys, periods, the road it names
    Case("yaml syntax", lambda t: run(t, "name: t\nsimulation: {step_s: 0.01\n"),
         ("s.yaml", "line 3", "not valid YAML")),
    Case("yaml key given twice", lambda t: run(t, BASE + "v2c: {latency_s: 0.1}\nv2c: {jitter_s: 0.1}\n"),
         ("s.yaml", "line 8, column 1", "key 'v2c' given twice")),
    Case("yaml not a mapping", lambda t: run(t, "- name: t\n"),
         ("s.yaml", "expected a mapping of scenario fields", "got a list")),
    Case("yaml empty", lambda t: run(t, ""), ("s.yaml", "expected a mapping", "got an empty file")),
    Case("scenario missing", lambda t: ["run", "nope.yaml", "--out", "out"], ("nope.yaml", "scenario file not found")),
    Case("field type", lambda t: run(t, BASE + "v2c: {latency_s: soon}\n"),
         ("s.yaml", "v2c.latency_s", "valid number", "'soon'")),
    Case("field range", lambda t: run(t, BASE + "v2c: {loss_probability: 1.5}\n"),
         ("s.yaml", "v2c.loss_probability", "less than or equal to 1")),
    Case("unknown key", lambda t: run(t, BASE + "simulaton: {step_s: 0.01}\n"),
         ("s.yaml", "simulaton: unknown key", "expected one of:", "simulation")),
    Case("unknown nested key", lambda t: run(t, BASE + "v2c: {latency: 0.1}\n"),
         ("s.yaml", "v2c.latency: unknown key", "latency_s")),
    Case("period not a multiple of the step", lambda t: run(t, BASE + "v2c: {period_s: 0.015}\n"),
         ("s.yaml", "v2c.period_s", "whole multiple of simulation.step_s")),
    Case("AR period not a multiple of the V2C period", lambda t: run(t, BASE + "ar: {period_s: 0.15}\n" + FUSION.replace("WEIGHTS", "null")),
         ("s.yaml", "ar.period_s", "whole multiple of v2c.period_s (0.1)", "got 0.15")),
    Case("time infinite", lambda t: run(t, BASE.replace("max_time_s: 2.0", "max_time_s: .inf")),
         ("s.yaml", "simulation.max_time_s", "finite number")),
    Case("step SUMO would round", lambda t: run(t, BASE.replace("{max_time_s: 2.0}", "{max_time_s: 2.0, step_s: 0.0015}")),
         ("s.yaml", "simulation.step_s", "whole number of milliseconds", "0.0015")),
    Case("run shorter than a step", lambda t: run(t, BASE.replace("max_time_s: 2.0", "max_time_s: 0.001")),
         ("s.yaml", "simulation.max_time_s", "at least one step", "got 0.001")),
    Case("departure faster than the type allows", lambda t: run(t, BASE.replace("pos_m: [80, 120]}", "pos_m: [80, 120], speed_mps: 41}")),
         ("s.yaml", "vehicles[0].speed_mps", "maxSpeed of vehicle type 'car' in vtypes.add.xml (40 m/s)", "got 41")),
    Case("lane not on the road", lambda t: run(t, BASE.replace("lane: 2", "lane: 5")),
         ("s.yaml", "ego.lane", "0 to 2", "got 5")),
    Case("position beyond the road", lambda t: run(t, BASE + "accident: {pos_m: 5000, lanes: [0]}\n"),
         ("s.yaml", "accident.pos_m", "at most its length, 2000 m")),
    Case("extends a missing file", lambda t: run(t, "extends: base.yaml\nname: t\n"),
         ("s.yaml", "extends: file not found: base.yaml")),
    Case("extends cycle", lambda t: (scenario(t, "extends: s.yaml\nname: b\n", "b.yaml"),
                                     run(t, "extends: b.yaml\nname: t\n"))[1],
         ("b.yaml", "extends: s.yaml makes a cycle", "s.yaml -> ")),
    # network files
    Case("network malformed XML", lambda t: network(t, '<net><edge id="x"'),
         ("s.yaml: network:", "bad.net.xml", "line 1", "not well-formed XML")),
    Case("network empty", lambda t: network(t, ""), ("bad.net.xml", "empty file", "expected a SUMO network")),
    Case("network wrong root", lambda t: network(t, "<additional/>"),
         ("bad.net.xml", "root element <additional>", "expected <net>")),
    Case("network of several edges, no route", lambda t: network(t, '<net><edge id="a"/><edge id="b"/></net>'),
         ("s.yaml", "route:", "bad.net.xml", "not one chain of edges", "give the route")),
    # routes (issue 19): the field that names the route, its edge, the lane
    Case("route unknown edge", lambda t: run(t, ONRAMP.replace("main_out]", "nope]")),
         ("s.yaml", "route[2]:", "unknown edge 'nope'", "onramp.net.xml")),
    Case("route edges do not connect", lambda t: run(t, ONRAMP.replace("main_in, accel, main_out", "main_in, main_out")),
         ("s.yaml", "route[1]:", "'main_in' and 'main_out' do not connect")),
    Case("vehicle group route unknown edge", lambda t: run(t, ONRAMP.replace(
        "vehicles: [{name: car,", "vehicles: [{name: car, route: [ramp, accel, x],")),
         ("s.yaml", "vehicles[0].route[2]:", "unknown edge 'x'")),
    Case("lane absent where placed", lambda t: run(t, ONRAMP.replace("lanes: [1]", "lanes: [0]")),
         ("s.yaml", "vehicles[0].lanes:", "lane 0 does not exist between 80 and 120 m", "lanes there: [1, 2, 3]")),
    Case("ego lane ends before the trip's end", lambda t: run(t, ONRAMP.replace(
        "ego: {lane: 2, depart_pos_m: 50", "ego: {lane: 0, depart_pos_m: 720")),
         ("s.yaml", "ego.lane:", "lane 0 ends at 946 m", "before the trip's end (1020 m)")),
    Case("ego route numbering its lanes otherwise", lambda t: run(t, ONRAMP.replace(
        "ego: {lane: 2,", "ego: {route: [main_out], lane: 0,")),
         ("s.yaml", "ego.route:", "SUMO lane main_out_0", "lane 1 of the scenario's route")),
    Case("ego route starting off the scenario's route", lambda t: run(t, ONRAMP.replace(
        "ego: {lane: 2, depart_pos_m: 50", "ego: {route: [ramp, accel, main_out], lane: 0, depart_pos_m: 50")),
         ("s.yaml", "ego.route:", "SUMO lane ramp_0", "which is not on the scenario's route")),
    Case("accident edge off the route", lambda t: run(t, ONRAMP + "accident: {edge: ramp, pos_m: 10, lanes: [0]}\n"),
         ("s.yaml", "accident.edge:", "expected an edge of the route", "'ramp'")),
    Case("network lane without shape", lambda t: network(
        t, '<net><edge id="a"><lane id="a_0" index="0" speed="25" width="3.5"/></edge></net>'),
         ("bad.net.xml", "lane 'a_0': shape", "expected 'x,y x,y ...'")),
    Case("network missing", lambda t: run(t, BASE.replace("highway.net.xml", "nope.net.xml")),
         ("s.yaml", "network: file not found", "nope.net.xml")),
    # vehicle types
    Case("unknown vehicle type", lambda t: run(t, BASE.replace("vtype: car", "vtype: bus")),
         ("s.yaml", "vehicles[0].vtype", "'bus' is not defined in vtypes.add.xml", "expected one of: car")),
    Case("vehicle types missing", lambda t: run(t, BASE.replace("vtypes.add.xml", "nope.add.xml")),
         ("s.yaml", "vehicle_types: file not found", "nope.add.xml")),
    Case("vehicle types malformed", lambda t: vtypes(t, '<additional><vType id="car"'),
         ("s.yaml: vehicle_types:", "bad.add.xml", "not well-formed XML")),
    Case("vehicle types without vType", lambda t: vtypes(t, "<additional/>"),
         ("bad.add.xml", "no <vType> elements", "expected at least one vehicle type")),
    # lane-change model files
    Case("model garbage", lambda t: ((t / "bad.npz").write_bytes(b"\x00garbage" * 10),
                                     run(t, BASE + "prediction: {model: bad.npz}\n"))[1],
         ("s.yaml: prediction.model:", "bad.npz", "not a vcfusion lane-change model file")),
    Case("model wrong format", lambda t: with_model(t, lambda a, m: m.update(format="other/1")),
         ("bad.npz", "format: expected 'vcfusion-lane-change-mlp/1'", "'other/1'")),
    Case("model missing metadata key", lambda t: with_model(t, lambda a, m: m.pop("tau")),
         ("bad.npz", "meta.tau: missing")),
    Case("model wrong shape in a hidden layer", lambda t: with_model(t, lambda a, m: a.update(w1=a["w1"][:, :64])),
         ("bad.npz", "w1: expected a float array of shape (any, 128)", "(128, 64)")),
    Case("model missing a layer", lambda t: with_model(t, lambda a, m: a.pop("b2")),
         ("bad.npz", "b2: missing array")),
    Case("model for another V2C period", lambda t: with_model(t, lambda a, m: m.update(period_s=0.2)),
         ("s.yaml: prediction.model:", "trained for a V2C period of 0.2 s", "expected v2c.period_s to match")),
    Case("model given to evaluate", lambda t: (model_file(t, lambda a, m: a.update(w2=a["w2"][:, :3])),
                                               ["evaluate", "bad.npz", str(dataset(t)), "--out", "out"])[1],
         ("bad.npz", "w2: expected a float array of shape (1, 128)")),
    # detector weights
    Case("weights garbage", lambda t: ((t / "bad.pt").write_bytes(b"not torch"),
                                       run(t, BASE + FUSION.replace("WEIGHTS", "bad.pt")))[1],
         ("s.yaml: fusion.weights:", "bad.pt", "not a vcfusion detector weights file")),
    Case("weights wrong format", lambda t: with_weights(t, lambda b: b.update(format="yolo")),
         ("bad.pt", "format: expected 'vcfusion-centernet-v1'", "'yolo'")),
    Case("weights missing key", lambda t: with_weights(t, lambda b: b.pop("class_ids")),
         ("bad.pt", "missing keys ['class_ids']")),
    Case("weights wrong layer shape", lambda t: (
        weights_file(t, lambda b: b["state_dict"].update({"s8.0.0.weight": b["state_dict"]["s8.0.0.weight"][:, :8]})),
        ["eval-detector", "coco", "--weights", "bad.pt"])[1],
         ("bad.pt", "state_dict.s8.0.0.weight: expected shape (64, 32, 3, 3)", "(64, 8, 3, 3)")),
    Case("onnx without class ids", lambda t: ["eval-detector", "coco", "--onnx", "m.onnx", "--classes", "1,car"],
         ("--classes", "expected the category ids", "'1,car'")),
    # dataset folders
    Case("COCO folder missing", lambda t: ["eval-detector", "nope"], ("nope", "dataset folder not found")),
    Case("COCO folder listed twice", lambda t: ["eval-detector", coco_folder(t), "coco"],
         ("data: coco holds the same images as coco", "each scene counts once")),
    Case("COCO folder and its copy", lambda t: (coco_folder(t), shutil.copytree(t / "coco", t / "copy"),
                                                ["eval-detector", "coco", "copy"])[2],
         ("data: copy holds the same images as coco",)),
    Case("negative min area", lambda t: ["eval-detector", coco_folder(t), "--min-area", "-5"],
         ("--min-area", "expected a non-negative area", "got -5")),
    Case("negative GNSS noise", lambda t: ["eval-detector", coco_folder(t), "--gnss-noise", "-0.5"],
         ("--gnss-noise", "expected a standard deviation >= 0", "got -0.5")),
    Case("box head missing", lambda t: ["eval-detector", coco_folder(t), "--box-head", "head.pt"],
         ("head.pt", "box-head weights not found")),
    Case("box head zero epochs", lambda t: ["train-box-head", "coco", "--out", "h.pt", "--epochs", "0"],
         ("--epochs >= 1", "got 0")),
    Case("negative min train area", lambda t: ["train-detector", coco_folder(t), "--out", "w.pt",
                                               "--min-train-area", "-1"],
         ("--min-train-area", "expected a non-negative area", "got -1")),
    Case("identification study min area", lambda t: ["study", "identification", scenario(t, BASE), "--seeds", "0",
                                                     "--out", "st", "--min-area", "-5"],
         ("--min-area", "expected a non-negative area", "got -5")),
    Case("identification study folder exists", lambda t: ((t / "st").mkdir(),
                                                          ["study", "identification", scenario(t, BASE), "--seeds",
                                                           "0", "--out", "st"])[1],
         ("--out", "st already exists; choose a new folder")),
    Case("resize quality out of range", lambda t: ["resize-dataset", "coco", "--out", "small", "--quality", "0"],
         ("--quality", "expected 1 to 100", "got 0")),
    Case("resize a corrupt COCO folder", lambda t: ((t / "coco").mkdir(), (t / "coco" / "annotations.json").write_text("{"),
                                                    ["resize-dataset", "coco", "--out", "small"])[2],
         ("annotations.json", "not valid JSON")),
    # options of the commands a review found without a check (tracebacks), and outputs under a file
    Case("drive negative seed", lambda t: ["drive", str(REPO / "scenarios" / "accident_ar.yaml"), "--seed", "-1",
                                           "--input", "keyboard", "--headless", "--no-window"],
         ("--seed", "expected a seed from 0", "got -1")),
    Case("drive display rate infinite", lambda t: ["drive", str(REPO / "scenarios" / "accident_ar.yaml"),
                                                   "--fps", "inf", "--input", "keyboard", "--headless"],
         ("--fps", "expected display frames per second from 1 to 240", "got inf")),
    Case("drive display rate nan", lambda t: ["drive", str(REPO / "scenarios" / "accident_ar.yaml"),
                                              "--fps", "nan", "--input", "keyboard", "--headless"],
         ("--fps", "got nan")),
    Case("drive axis map without a joystick", lambda t: ["drive", str(REPO / "scenarios" / "accident_ar.yaml"),
                                                         "--axis-map", "nope.json", "--input", "keyboard",
                                                         "--headless"],
         ("--axis-map", "read only with --input joystick", "keyboard")),
    Case("drive participant with a slash", lambda t: ["drive", str(REPO / "scenarios" / "accident_ar.yaml"),
                                                      "--participant", "../x", "--input", "keyboard", "--headless"],
         ("--participant", "without path separators", "'../x'")),
    Case("hitl study negative first seed", lambda t: ["study", "hitl", str(REPO / "scenarios" / "accident_ar.yaml"),
                                                      "--participant", "P1", "--first-seed", "-5", "--headless"],
         ("--first-seed", "expected a seed from 0", "got -5")),
    Case("hitl study bad input, nothing written",
         lambda t: ["study", "hitl", str(REPO / "scenarios" / "accident_ar.yaml"), "--participant", "P1",
                    "--input", "bogus", "--headless", "--out", "h"],
         ("--input", "expected keyboard, joystick or replay:FILE", "'bogus'")),
    Case("hitl participant with a slash", lambda t: ["study", "hitl", str(REPO / "scenarios" / "accident_ar.yaml"),
                                                     "--participant", "a/b", "--headless"],
         ("--participant", "without path separators", "'a/b'")),
    Case("train learning rate nan", lambda t: train_on(t, lambda r: None) + ["--learning-rate", "nan"],
         ("--learning-rate", "expected a positive rate", "nan")),
    Case("train-detector negative lr", lambda t: ["train-detector", "coco", "--out", "d.pt", "--lr", "-1"],
         ("--lr", "expected a positive learning rate", "-1")),
    Case("train-detector unknown device", lambda t: ["train-detector", "coco", "--out", "d.pt", "--device", "gpu"],
         ("--device", "expected auto, cpu or cuda", "'gpu'")),
    Case("bench sensor without P2", lambda t: ["bench", "--sections", "P1", "--depth-sensor", "lidar"],
         ("--depth-sensor", "expected P2 among --sections", "P1")),
    Case("bench pose noise out of range", lambda t: ["bench", "--sections", "P2", "--pose-noise-deg", "20"],
         ("--pose-noise-deg", "0 to 10", "20")),
    Case("bench gpu reference without GPU", lambda t: ["bench", "--sections", "P1", "--gpu-reference", "r.npz"],
         ("--gpu-reference", "expected GPU among --sections", "P1")),
    Case("bench gpu reference missing", lambda t: ["bench", "--sections", "GPU", "--gpu-reference", str(t / "r.npz")],
         ("--gpu-reference", "no such file", "r.npz")),
    Case("bench gpu reference not npz", lambda t: ["bench", "--sections", "GPU", "--write-gpu-reference", "r.txt"],
         ("--write-gpu-reference", "expected a .npz file", "r.txt")),
    Case("bench gpu reference both ways", lambda t: ["bench", "--sections", "GPU", "--gpu-reference", "a.npz",
                                                     "--write-gpu-reference", "b.npz"],
         ("--gpu-reference / --write-gpu-reference", "expected one of them")),
    Case("bench-render no frames", lambda t: ["bench-render", "--frames", "0"], ("--frames", "expected a positive", "0")),
    Case("bench-predict negative twins", lambda t: ["bench-predict", "--twins", "-5"],
         ("--twins", "expected a positive number", "-5")),
    Case("output folder under a file", lambda t: ((t / "afile").write_text("x"),
                                                  ["render-scenes", "--family", "jam", "--seeds", "0-0",
                                                   "--out", "afile/x"])[1],
         ("afile", "is a file; expected a folder")),
    Case("render no workers", lambda t: ["render", str(REPO / "scenarios" / "overlap.yaml"), "--seeds", "0",
                                         "--out", "x", "--workers", "0"],
         ("--workers", "expected at least 1", "got 0")),
    Case("render-scenes no workers", lambda t: ["render-scenes", "--seeds", "0-1", "--out", "x", "--workers", "0"],
         ("--workers", "expected at least 1", "got 0")),
    Case("train-detector no iterations", lambda t: ["train-detector", "coco", "--out", "d.pt", "--iterations", "0"],
         ("--iterations", "expected a positive number", "got 0")),
    Case("train-detector nothing to train on",
         lambda t: ["train-detector", "coco", "--out", "d.pt", "--val-fraction", "1"],
         ("--val-fraction", "expected a share in [0, 1)", "got 1.0")),
    Case("train-detector negative seed", lambda t: ["train-detector", "coco", "--out", "d.pt", "--seed", "-1"],
         ("--seed", "expected 0 or more", "got -1")),
    Case("train-detector out is a folder", lambda t: ((t / "w").mkdir(), ["train-detector", "coco", "--out", "w"])[1],
         ("--out w", "expected a weights file in an existing folder")),
    Case("train-detector validation without boxes",
         lambda t: ["train-detector", coco_folder(t), "--out", "d.pt", "--val",
                    coco_folder(t, lambda c: c.__setitem__("annotations", []), "empty")],
         ("empty", "the validation images hold no boxes", "--val-fraction 0")),
    Case("train-detector one scene to split",  # trained without validation, without a word, before
         lambda t: ["train-detector", coco_folder(t, n_images=1), "--out", "d.pt", "--iterations", "1"],
         ("holds one scene", "cannot be split", "--val-fraction 0")),
    Case("COCO two images with one id", lambda t: ["eval-detector", coco_folder(t, _set("images.1.id", 1))],
         ("annotations.json", "images[1].id", "1 is the id of an earlier image")),
    Case("COCO box of no image", lambda t: ["eval-detector", coco_folder(t, _set("annotations.0.image_id", 999))],
         ("annotations.json", "annotations[0].image_id", "999 is the id of no image")),
    Case("COCO negative box width", lambda t: ["eval-detector", coco_folder(t, _set("annotations.0.bbox", [1, 1, -3, 4]))],
         ("annotations[0].bbox", "width, height >= 0", "[1, 1, -3, 4]")),
    Case("COCO file not an object", lambda t: ["eval-detector", coco_folder(t, lambda c: [c])],
         ("annotations.json", "expected a COCO object")),
    Case("ultralytics input size", lambda t: ["eval-detector", "coco", "--onnx", "m.onnx", "--layout", "ultralytics",
                                              "--input-size", "640x600"],
         ("error: --input-size", "multiples of 16", "'640x600'")),  # not blamed on --keep
    Case("weights input size not a multiple of 16",
         lambda t: with_weights(t, lambda blob: blob.__setitem__("input_wh", [100, 100])),
         ("bad.pt", "input_wh", "expected multiples of 16")),
    Case("COCO annotations corrupt", lambda t: ((t / "coco").mkdir(), (t / "coco" / "annotations.json").write_text("{"),
                                                ["eval-detector", "coco"])[2],
         ("annotations.json", "not valid JSON")),
    Case("dataset folder missing", lambda t: ["train", "nope", "--out", "out.npz"],
         ("nope", "not a dataset folder", "vcfusion dataset")),
    Case("dataset.json corrupt", lambda t: train_on(t, lambda r: (r / "dataset.json").write_text('{"tau": 5,')),
         ("dataset.json", "line 1", "not valid JSON")),
    Case("dataset.json missing key", lambda t: train_on(t, set_meta(tau=None)),
         ("dataset.json", "tau: expected a number", "None")),
    Case("dataset of older labels and features", lambda t: train_on(t, set_meta(samples_version=None)),
         ("dataset.json", "samples_version: 1", f"version {SAMPLES_VERSION}", "--refeature")),
    Case("samples not Parquet", lambda t: train_on(t, lambda r: samples_of(0, r).write_bytes(b"PAR1 junk")),
         ("seed_0000/samples.parquet", "not a readable Parquet file")),
    Case("samples missing a column", lambda t: train_on(t, drop_column),
         ("seed_0001/samples.parquet", "missing columns ['window_label']")),
    Case("evaluate horizon", lambda t: (
        ["evaluate", str(default_model_path()), str(dataset(t)), "--out", "out", "--horizon", "-1"]),
         ("--horizon", "expected a positive number of seconds")),
    # command-line values
    Case("seed range reversed", lambda t: ["batch", scenario(t, BASE), "--seeds", "5-2", "--out", "out"],
         ("--seeds", "expected seeds from 0 to 2147483647", "'5-2'")),
    Case("seed range too large", lambda t: ["batch", scenario(t, BASE), "--seeds", "0-99999999999", "--out", "out"],
         ("--seeds", "'0-99999999999'")),
    Case("negative seed", lambda t: ["run", scenario(t, BASE), "--seed", "-1", "--out", "out"],
         ("--seed", "expected a seed from 0 to 2147483647", "got -1")),
    Case("no workers", lambda t: ["batch", scenario(t, BASE), "--seeds", "0-3", "--workers", "0", "--out", "out"],
         ("--workers", "expected a positive number of processes", "got 0")),
    Case("dataset workers", lambda t: ["dataset", scenario(t, BASE), "--seeds", "0-3", "--workers", "-2",
                                       "--out", "out"],
         ("--workers", "expected a positive number", "got -2")),
    Case("run folder exists", lambda t: ((t / "out").mkdir(), run(t, BASE))[1], ("--out", "out already exists")),
    Case("output under a file", lambda t: ((t / "afile").write_text("x"),
                                           ["batch", scenario(t, BASE), "--seeds", "0", "--out", "afile/b"])[1],
         ("--out", "afile is a file; expected a folder path")),
    Case("train epochs", lambda t: ["train", str(dataset(t)), "--out", "out.npz", "--epochs", "0"],
         ("--epochs", "expected a positive number", "got 0")),
    Case("model output under a file", lambda t: ((t / "afile").write_text("x"),
                                                 ["train", str(dataset(t)), "--out", "afile/m.npz"])[1],
         ("--out", "afile is a file; expected a folder path")),
    Case("dataset output under a file", lambda t: ((t / "afile").write_text("x"),
                                                   ["dataset", scenario(t, BASE), "--seeds", "0", "--out", "afile/d"])[1],
         ("--out", "afile is a file; expected a folder path")),
    Case("process model whose factory raises",
         lambda t: ["study", "guidance", scenario(t, BASE), "--trips", "2", "--out", "out",
                    "--process-model", "json:dumps"],
         ("--process-model", "json:dumps(scenario 't') raised TypeError")),
    Case("process model factory returning no model",
         lambda t: ["study", "guidance", scenario(t, BASE), "--trips", "2", "--out", "out",
                    "--process-model", "builtins:str"],
         ("--process-model", "builtins:str(scenario) returned a str", "expected a process model")),
    Case("guidance study without an ego",
         lambda t: ["study", "guidance", scenario(t, BASE.replace("ego: {lane: 2, depart_pos_m: 50, speed_mps: 19}\n", "")),
                    "--trips", "2", "--out", "out"],
         ("s.yaml", "ego: the guidance study needs an ego")),
    Case("camera on a vehicle class it cannot draw",
         lambda t: run(t, bicycles(t) + "vision: {enabled: true}\n"),
         ("s.yaml", "vehicles[0].vtype (vision.enabled)", "'bike' of bikes.add.xml", "vClass 'bicycle'",
          "expected one of: passenger, truck")),
    Case("render a vehicle class it cannot draw",
         lambda t: ["render", scenario(t, bicycles(t)), "--seeds", "0", "--out", "out"],
         ("s.yaml", "vehicles[0].vtype", "vClass 'bicycle'", "neither draw nor label")),
    Case("camera on a network with elevation",
         lambda t: run(t, elevated_network(t) + "vision: {enabled: true}\n"),
         ("s.yaml", "network (vision.enabled)", "hill.net.xml", "lies 5.00 m off z = 0", "--flatten")),
    Case("render a network with elevation",
         lambda t: ["render", scenario(t, elevated_network(t)), "--seeds", "0", "--out", "out"],
         ("hill.net.xml", "lies 5.00 m off z = 0", "--flatten")),
    Case("guidance camera arms on a network with elevation",
         lambda t: ["study", "guidance", scenario(t, elevated_network(t)), "--trips", "2", "--arms", "none,fusion",
                    "--out", "out"],
         ("hill.net.xml", "lies 5.00 m off z = 0", "--flatten")),
    Case("render every", lambda t: ["render", scenario(t, BASE), "--seeds", "0", "--every", "0", "--out", "out"],
         ("--every", "expected a positive number of V2C ticks")),
]


def tree(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_size if p.is_file() else -1 for p in folder.rglob("*")}


def test_at_least_25_bad_inputs():
    assert len(CASES) >= 25 and len({c.name for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input_is_refused_in_one_line(case, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    argv = case.build(tmp_path)
    before = tree(tmp_path)
    code = main(argv)
    captured = capsys.readouterr()
    assert code == 2, captured.err
    assert "Traceback" not in captured.err and captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
    for fragment in case.expected:
        assert fragment in lines[0], f"{fragment!r} not in {lines[0]!r}"
    assert tree(tmp_path) == before  # nothing written: no output folder, no temporary left behind


def test_several_problems_in_one_scenario_give_one_line_each(tmp_path, capsys):
    path = write_scenario(tmp_path, BASE + "v2c: {latency_s: -1, jitter_s: x}\ncolour: red\n")
    assert main(["run", str(path), "--out", str(tmp_path / "out")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 3 and all(line.startswith(f"error: {path}: ") for line in lines)
    assert {line.split(": ")[2] for line in lines} == {"v2c.latency_s", "v2c.jitter_s", "colour"}
    assert not (tmp_path / "out").exists()


def test_the_valid_inputs_the_cases_start_from_are_valid(tmp_path):
    sc = load_scenario(write_scenario(tmp_path, BASE))
    assert sc.ego.lane == 2 and sc.vehicles[0].vtype == "car"
    onramp = load_scenario(write_scenario(tmp_path, ONRAMP, "onramp.yaml"))
    assert onramp.route == ["main_in", "accel", "main_out"]
    load_scenario(write_scenario(tmp_path, BASE.replace("highway.net.xml", "curved.net.xml"), "curved.yaml"))
    # bicycles ride in a traffic-only run; only the camera refuses them
    biked = load_scenario(write_scenario(tmp_path, bicycles(tmp_path), "bikes.yaml"))
    assert biked.vehicles[0].vtype == "bike"
    # a network with elevation carries traffic (SUMO drives it); only the camera refuses it
    lifted = load_scenario(write_scenario(tmp_path, elevated_network(tmp_path), "hill.yaml"))
    assert lifted.network == tmp_path / "hill.net.xml"
    model_file(tmp_path, lambda a, m: None)
    weights_file(tmp_path, lambda b: None)
    (tmp_path / "sub").mkdir()
    fused = load_scenario(write_scenario(tmp_path, BASE + FUSION.replace("WEIGHTS", "../bad.pt") +
                                         "prediction: {model: ../bad.npz}\n", "sub/f.yaml"))
    assert fused.fusion.weights == tmp_path / "bad.pt" and fused.prediction.model == tmp_path / "bad.npz"
    info = load_dataset(dataset(tmp_path))
    assert info.splits == {"train": [0], "validation": [1], "test": [2]}


def test_a_subprocess_gets_one_line_and_exit_2(tmp_path):
    """The installed entry point (not only main()): a malformed network file, as a user hits it."""
    argv = network(tmp_path, '<net><edge id="x"')
    proc = subprocess.run([sys.executable, "-m", "vcfusion", *argv], capture_output=True, text=True, cwd=tmp_path,
                          env={"PYTHONPATH": str(REPO / "src"), "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert "bad.net.xml: line 1, column" in proc.stderr and not (tmp_path / "out").exists()


def test_a_vehicle_sumo_refuses_is_one_line_and_exit_1(tmp_path, monkeypatch, capsys):
    """A departure speed above the vehicle class's default maxSpeed (the type names none, so only
    SUMO knows the limit: 200 km/h for passenger cars): SUMO's refusal, one line, nothing written."""
    (tmp_path / "types.add.xml").write_text('<additional><vType id="car" vClass="passenger" length="4.6" '
                                            'width="1.8" height="1.5"/>'
                                            '<vType id="ego" vClass="passenger" length="4.6" width="1.8" '
                                            'height="1.5"/></additional>')
    text = BASE.replace("NET_DIR/vtypes.add.xml", "types.add.xml").replace("pos_m: [80, 120]}",
                                                                          "pos_m: [80, 120], speed_mps: 60}")
    monkeypatch.chdir(tmp_path)
    assert main(run(tmp_path, text)) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: SUMO refused the scenario's vehicles: Departure speed "
                                                   "for vehicle 'car0' is too high for the vehicle type 'car'")
    assert not (tmp_path / "out").exists()


def test_output_into_a_closed_pipe_ends_quietly_with_sigpipes_status():
    """`vcfusion scenarios | head -0`: the reader is gone before anything is written. The command
    ends with 128 + SIGPIPE and no traceback, neither from its own print nor at interpreter exit."""
    import signal

    read_end, write_end = os.pipe()
    os.close(read_end)  # nobody will read
    try:
        proc = subprocess.run([sys.executable, "-m", "vcfusion", "scenarios"], stdout=write_end,
                              stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write_end)
    assert proc.returncode == 128 + signal.SIGPIPE, proc.stderr
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr, proc.stderr


def test_a_broken_pipe_other_than_standard_output_is_a_failure(monkeypatch):
    """A worker's pipe breaking is not the reader of our output going away: it is raised, not
    turned into a quiet exit."""
    from vcfusion.commands import simulation

    def worker_pipe_broke(args):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(simulation, "cmd_scenarios", worker_pipe_broke)
    with pytest.raises(BrokenPipeError):
        main(["scenarios"])
