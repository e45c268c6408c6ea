"""The data shipped with the package, found with importlib.resources: the scenario files
(vcfusion/scenarios, families/ included), the SUMO networks with their plain-XML sources and the
vehicle types (vcfusion/sumo_net), the model weights (vcfusion/assets).

In a checkout, src/vcfusion/scenarios and src/vcfusion/sumo_net are links to the checkout's
top-level scenarios/ and sumo_net/ folders (the project's layout), so the package, whether run
from src/ or installed editable, reads and writes the checkout's own files; a wheel holds copies
of them inside the package. Scenario files name their network and vehicle types relative to
themselves (`../sumo_net/highway.net.xml`), which holds in both layouts.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

SCENARIO_SUFFIX = ".yaml"


def _package_path(name: str) -> Path:
    found = resources.files("vcfusion") / name
    if not isinstance(found, Path):  # SUMO, OpenGL and the YAML loader need files on disk
        raise RuntimeError(f"vcfusion/{name}: the package's data is not on the file system (imported from a zip?); "
                           "install vcfusion with pip")
    return found


def scenarios_dir() -> Path:
    """The folder of the shipped scenario files (the checkout's scenarios/ in a checkout)."""
    return _package_path("scenarios").resolve()


def networks_dir() -> Path:
    """The folder of the shipped SUMO networks, their sources and vtypes.add.xml (the checkout's sumo_net/)."""
    return _package_path("sumo_net").resolve()


def assets_dir() -> Path:
    """The folder of the shipped model weights."""
    return _package_path("assets").resolve()


# Found here, not beside the networks, so that finding them imports no torch (vcfusion.run).
def default_weights_path() -> Path:
    """The shipped CNN detector (package data), trained by the commands in docs/model-cards.md."""
    return assets_dir() / "detector.pt"


def default_box_head_path() -> Path:
    """The depth step's shipped far-box head (package data), trained by the commands in docs/model-cards.md."""
    return assets_dir() / "far_box_head.pt"


def networks_dir_is_checkout() -> bool:
    """Whether the shipped networks are a checkout's sumo_net/ folder (linked into the package), which
    `vcfusion build-net` may rebuild in place; an installed package's copies are not rewritten."""
    return _package_path("sumo_net").is_symlink()


def shipped_scenarios() -> dict[str, Path]:
    """Name -> file of every shipped scenario: `accident` for scenarios/accident.yaml,
    `families/dense` for scenarios/families/dense.yaml; sorted by name."""
    root = scenarios_dir()
    files = sorted(root.rglob(f"*{SCENARIO_SUFFIX}"))
    return {p.relative_to(root).with_suffix("").as_posix(): p for p in files}
