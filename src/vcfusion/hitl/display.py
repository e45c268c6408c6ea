"""The driver's window: the ego camera render with the AR overlay and a HUD, and text screens.

Every displayed frame is a fresh render of the ego camera at that SUMO step. The AR overlay's
content (which vehicle, its level and probability) changes only at fusion ticks (0.1 s); its
boxes follow their vehicles in between: each shown item's box is re-projected every frame as
that vehicle's extent in the frame's instance map (the render stands in for the AR display's
tracker; a vehicle hidden at that moment shows no box). In a scenario without the fusion stage
the guidance comes from the cloud (source `cloud`, no boxes); its items are boxed the same way,
standing for the twin projected into the view, so guidance on / off differ on screen in every
scenario.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from vcfusion.fusion.overlay import RED, WHITE, draw_overlay
from vcfusion.records import Guidance

FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclass(frozen=True)
class HudInfo:
    time_s: float
    speed_mps: float
    distance_left_m: float
    guidance_on: bool
    lag_s: float = 0.0


def reprojected(items: tuple[Guidance, ...], vehicle_ids: tuple[str, ...], instances: np.ndarray,
                box_unmatched: bool = False) -> list[Guidance]:
    """The guidance items with their boxes moved to where their vehicles are in this frame
    (`instances`: the render's instance map); items whose vehicle is not visible are left out.
    Items without a box (fusion did not match the twin to a detection) are left out too, unless
    `box_unmatched`: cloud guidance (no camera in the loop) has no boxes, and its display stands
    for projecting the twin into the view."""
    index = {vid: k for k, vid in enumerate(vehicle_ids)}
    out = []
    for g in items:
        k = index.get(g.vehicle_id)
        if k is None or (g.box is None and not box_unmatched):
            continue
        rows, cols = np.nonzero(instances == k)
        if rows.size == 0:
            continue
        out.append(replace(g, box=(float(cols.min()), float(rows.min()), float(cols.max()), float(rows.max()))))
    return out


def compose(rgb: np.ndarray, items: list[Guidance], hud: HudInfo) -> np.ndarray:
    """The driver's view: overlay boxes (guidance on), then the HUD panel."""
    out = draw_overlay(rgb, items, None, draw_low=False) if hud.guidance_on else np.ascontiguousarray(rgb.copy())
    lines = [f"{hud.speed_mps * 3.6:5.0f} km/h", f"t {hud.time_s:5.1f} s", f"{max(0.0, hud.distance_left_m):4.0f} m to go",
             "guidance " + ("on" if hud.guidance_on else "off")]
    scale = max(0.35, out.shape[0] / 960)
    step = int(40 * scale) + 4
    panel = out[4:8 + step * len(lines), 4:int(330 * scale)]
    panel[:] = (0.45 * panel).astype(np.uint8)
    for k, text in enumerate(lines):
        cv2.putText(out, text, (10, 4 + step * (k + 1) - 6), FONT, scale, WHITE, 1, cv2.LINE_AA)
    if hud.lag_s > 0.1:  # the simulation is behind the wall clock: say so on screen
        cv2.putText(out, f"lag {hud.lag_s:.2f} s", (10, out.shape[0] - 10), FONT, scale, RED, 1, cv2.LINE_AA)
    return out


def text_screen(size: tuple[int, int], lines: list[str]) -> np.ndarray:
    """A dark screen with centred lines of text (instructions, pause, questions)."""
    w, h = size
    out = np.full((h, w, 3), 24, np.uint8)
    scale = max(0.35, h / 900)
    step = int(38 * scale) + 6
    top = max(step, (h - step * len(lines)) // 2)
    for k, text in enumerate(lines):
        (tw, _), _ = cv2.getTextSize(text, FONT, scale, 1)
        cv2.putText(out, text, (max(4, (w - tw) // 2), top + step * k), FONT, scale, WHITE, 1, cv2.LINE_AA)
    return out


class Window:
    """A pygame window of the camera's size showing RGB arrays."""

    def __init__(self, pygame, size: tuple[int, int], title: str = "vcfusion drive"):
        self.pg = pygame
        self.size = size
        self.surface = pygame.display.set_mode(size)
        pygame.display.set_caption(title)

    def show(self, rgb: np.ndarray) -> None:
        h, w = rgb.shape[:2]
        image = self.pg.image.frombuffer(np.ascontiguousarray(rgb).tobytes(), (w, h), "RGB")
        self.surface.blit(image, (0, 0))
        self.pg.display.flip()

    def wait_for_start(self, lines: list[str], handle_event, timeout_s: float | None = None) -> None:
        """Show `lines` until the person presses Enter / Space or a joystick button (Escape
        aborts: DriveAborted); `timeout_s` ends the wait on its own (headless runs)."""
        import time

        from vcfusion.hitl.driver import DriveAborted

        self.show(text_screen(self.size, lines))
        started = time.perf_counter()
        while timeout_s is None or time.perf_counter() - started < timeout_s:
            events = self.pg.event.get()
            for k, event in enumerate(events):
                handle_event(event)
                if event.type == self.pg.QUIT or (event.type == self.pg.KEYDOWN and event.key == self.pg.K_ESCAPE):
                    raise DriveAborted("the driver closed the window")
                if (event.type == self.pg.KEYDOWN and event.key in (self.pg.K_RETURN, self.pg.K_SPACE)) \
                        or event.type == self.pg.JOYBUTTONDOWN:
                    for later in events[k + 1:]:  # what came after the start (a key already held) is the drive's
                        self.pg.event.post(later)
                    return
            time.sleep(0.01)

    def close(self) -> None:
        self.pg.display.quit()
