"""AR overlay (the paper's Fig. 7): each neighbour's matched box drawn with its lane-change
probability, colour-coded (yellow medium, red high: the run's GuidancePolicy, vcfusion.guidance),
a small HUD, and the guidance records for the driver model; frames written as PNGs and an mp4.

Images are RGB uint8; colours below are RGB. Writing converts to OpenCV's BGR.
"""

from __future__ import annotations

import queue
import shutil
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from vcfusion.guidance import GUIDANCE_LEVELS, GuidancePolicy
from vcfusion.records import Guidance

YELLOW = (255, 210, 0)
RED = (230, 20, 20)
GREEN = (40, 200, 90)
WHITE = (255, 255, 255)


def level_colour(level: str) -> tuple[int, int, int]:
    return {"high": RED, "medium": YELLOW}.get(level, GREEN)


def make_guidance(time: float, vehicle_ids, lc_prob, boxes, policy: GuidancePolicy, decisions=None) -> list[Guidance]:
    """One Guidance per neighbour, levelled by `policy`; ``boxes`` holds each one's matched box
    (4 values) or None; ``decisions``, when given, the cloud's smoothed lane-change decision of
    each (0/1)."""
    out = []
    decisions = [None] * len(boxes) if decisions is None else [int(d) for d in decisions]
    for vid, p, box, d in zip(vehicle_ids, np.asarray(lc_prob, dtype=float), boxes, decisions):
        b = None if box is None else tuple(float(v) for v in box)
        out.append(Guidance(time=float(time), vehicle_id=str(vid), lc_prob=float(p),
                            level=policy.level(float(p), d), box=b))
    assert all(g.level in GUIDANCE_LEVELS for g in out)
    return out


@dataclass(frozen=True)
class Hud:
    time: float
    ego_speed_mps: float


def draw_overlay(image: np.ndarray, guidance: list[Guidance], hud: Hud | None, draw_low: bool = True) -> np.ndarray:
    """A copy of the RGB image with the guidance boxes, probabilities and the HUD drawn on it;
    `draw_low`: also outline matched neighbours of level none (thin green)."""
    out = np.ascontiguousarray(image.copy())
    font = cv2.FONT_HERSHEY_SIMPLEX
    # low first so that flagged boxes are drawn on top
    order = sorted(guidance, key=lambda g: GUIDANCE_LEVELS.index(g.level))
    for g in order:
        if g.box is None or (g.level == "none" and not draw_low):
            continue
        x1, y1, x2, y2 = (int(round(v)) for v in g.box)
        colour = level_colour(g.level)
        cv2.rectangle(out, (x1, y1), (x2, y2), colour, 1 if g.level == "none" else 3, cv2.LINE_AA)
        if g.level == "none":
            continue
        label = f"LC {100 * g.lc_prob:.0f}%"
        (tw, th), base = cv2.getTextSize(label, font, 0.5, 1)
        ty = max(y1 - 4, th + 4)
        cv2.rectangle(out, (x1, ty - th - 4), (x1 + tw + 6, ty + base - 2), colour, -1)
        text_colour = WHITE if g.level == "high" else (0, 0, 0)
        cv2.putText(out, label, (x1 + 3, ty - 2), font, 0.5, text_colour, 1, cv2.LINE_AA)
    if hud is not None:
        flagged = sum(g.level != "none" for g in guidance)
        lines = [f"t {hud.time:6.1f} s", f"ego {hud.ego_speed_mps * 3.6:5.1f} km/h", f"flagged {flagged}"]
        panel = out[4:4 + 18 * len(lines) + 6, 4:170]
        panel[:] = (0.45 * panel).astype(np.uint8)  # darkened panel keeps the scene visible
        for k, text in enumerate(lines):
            colour = RED if (k == 2 and flagged) else WHITE
            cv2.putText(out, text, (10, 22 + 18 * k), font, 0.5, colour, 1, cv2.LINE_AA)
    return out


class OverlayRecorder:
    """Writes frames as ``frames/000000.png`` ... and ``overlay.mp4`` into ``out_dir``, atomically:
    everything goes to a temporary folder beside it that is renamed when :meth:`close` completes
    (an error leaves no half-written output). Use as a context manager.

    Encoding runs on a writer thread (OpenCV releases the GIL while it encodes), so a tick hands its
    frame over and goes on with the next step; at most ``queue_frames`` frames wait, after which
    :meth:`add` waits for the writer. An error on the writer thread is raised by the next
    :meth:`add` or by :meth:`close`."""

    def __init__(self, out_dir, fps: float = 10.0, write_png: bool = True, video_name: str = "overlay.mp4",
                 queue_frames: int = 8):
        self.out_dir = Path(out_dir)
        if self.out_dir.exists():
            raise FileExistsError(f"{self.out_dir} already exists; choose a new output folder")
        self.out_dir.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.out_dir.name}.", dir=self.out_dir.parent))
        self.fps = fps
        self.write_png = write_png
        self.video_name = video_name
        self._writer = None
        self._size = None
        self.count = 0
        if write_png:
            (self._tmp / "frames").mkdir()
        self._queue: queue.Queue = queue.Queue(maxsize=max(1, queue_frames))
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None

    def add(self, frame_rgb: np.ndarray) -> None:
        self._raise_writer_error()
        h, w = frame_rgb.shape[:2]
        if self._writer is None:
            self._size = (w, h)
            self._writer = cv2.VideoWriter(str(self._tmp / self.video_name), cv2.VideoWriter_fourcc(*"mp4v"),
                                           self.fps, (w, h))
            if not self._writer.isOpened():
                raise RuntimeError("OpenCV cannot open an mp4v video writer on this system")
            self._thread = threading.Thread(target=self._write_frames, name="overlay-writer", daemon=True)
            self._thread.start()
        elif (w, h) != self._size:
            raise ValueError(f"frame size changed from {self._size} to {(w, h)}")
        # the conversion is also the copy the writer needs: the caller may draw into its array again
        self._queue.put((self.count, cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2BGR)))
        self.count += 1

    def _write_frames(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self._error is not None:
                continue  # drain after a failure; the error is raised on the caller's thread
            index, bgr = item
            try:
                self._writer.write(bgr)
                if self.write_png and not cv2.imwrite(str(self._tmp / "frames" / f"{index:06d}.png"), bgr):
                    raise OSError(f"{self._tmp / 'frames'}: cannot write frame {index:06d}.png")
            except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
                self._error = exc

    def _stop_writer(self) -> None:
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None
        if self._writer is not None:
            self._writer.release()
            self._writer = None

    def _raise_writer_error(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"overlay video writer failed: {self._error}") from self._error

    def close(self) -> Path:
        self._stop_writer()
        if self._error is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._raise_writer_error()
        self._tmp.rename(self.out_dir)
        return self.out_dir

    def abort(self) -> None:
        self._stop_writer()
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> "OverlayRecorder":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
