"""Checks of command-line values shared by the commands, and the defaults they share: each check
raises UsageError naming the option and what was expected (the command prints it and exits with 2)."""

from __future__ import annotations

import math

from pathlib import Path

from vcfusion.errors import UsageError

MAX_SEED = 2**31 - 1  # SUMO's --seed is a C int
MAX_SEEDS = 1_000_000  # seeds of one command: a typo like 0-99999999999 is refused, not enumerated

# What Ctrl-C leaves of a resumable batch of seeds (batch, dataset), for the user.
INTERRUPTED_BATCH = ("complete seeds are kept, partial ones removed; run the same command again to resume "
                     "(complete seeds are skipped)")


def check_seed(seed: int, option: str = "--seed") -> int:
    if not 0 <= seed <= MAX_SEED:
        raise UsageError(f"{option}: expected a seed from 0 to {MAX_SEED}, got {seed}")
    return seed


def parse_seeds(text: str, option: str = "--seeds") -> list[int]:
    """'0-99', '3', '1,4,7-9' -> sorted unique seeds (UsageError naming `option` otherwise)."""
    expected = f"{option}: expected seeds from 0 to {MAX_SEED} like '0-99' or '1,4,7-9'"
    ranges = []
    try:
        for part in text.split(","):
            lo, _, hi = part.strip().partition("-")
            lo, hi = int(lo), int(hi) if hi else int(lo)
            if not 0 <= lo <= hi <= MAX_SEED:
                raise ValueError
            ranges.append((lo, hi))
    except ValueError:
        raise UsageError(f"{expected}, got {text!r}") from None
    if sum(hi - lo + 1 for lo, hi in ranges) > MAX_SEEDS:
        raise UsageError(f"{expected} (at most {MAX_SEEDS:,} seeds), got {text!r}")
    return sorted({s for lo, hi in ranges for s in range(lo, hi + 1)})


def check_new_folder(out: Path, option: str = "--out") -> Path:
    """A folder the command will create: it must not exist, and no part of its path may be a file."""
    if out.exists():
        raise UsageError(f"{option}: {out} already exists; choose a new folder")
    check_folder_path(out, option)
    return out


def check_folder_path(out: Path, option: str = "--out") -> Path:
    """A folder the command creates or reuses: neither it nor a parent may be a file."""
    for part in (out, *out.parents):
        if part.exists() and not part.is_dir():
            raise UsageError(f"{option}: {part} is a file; expected a folder path")
    return out


def parse_size(text: str, option: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"{option}: expected WIDTHxHEIGHT such as 320x240, got {text!r}") from None
    if w <= 0 or h <= 0 or w % 16 or h % 16:
        raise UsageError(f"{option}: expected positive multiples of 16, got {text!r}")
    return w, h


def check_min_area(value: float, option: str = "--min-area") -> None:
    if not value >= 0:  # NaN too
        raise UsageError(f"{option}: expected a non-negative area in px^2 (0 = every box), got {value:g}")


def float_list(text: str, option: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise UsageError(f"{option}: expected comma-separated numbers such as 0,0.1,0.5, got {text!r}") from None
    if not values or any(v < 0 for v in values):
        raise UsageError(f"{option}: expected non-negative numbers, got {text!r}")
    return values


def default_run_dir(name: str, seed: int) -> Path:
    """runs/NAME-seedN, or the first of runs/NAME-seedN-2, -3, ... that does not exist."""
    base = Path("runs") / f"{name}-seed{seed}"
    candidate, n = base, 1
    while candidate.exists():
        n += 1
        candidate = base.with_name(f"{base.name}-{n}")
    return candidate


def check_pose_noise_deg(value: float, option: str = "--pose-noise-deg") -> float:
    """A camera pose error standard deviation in degrees, 0 to 10 (UsageError otherwise)."""
    if not math.isfinite(value) or not 0 <= value <= 10:
        raise UsageError(f"{option}: expected a standard deviation in degrees, 0 to 10, got {value}")
    return value
