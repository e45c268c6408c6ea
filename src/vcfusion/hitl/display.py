"""The driver's window: the ego camera render with the AR overlay and a HUD, and text screens.

Every displayed frame is a fresh render of the ego camera at that SUMO step. The AR overlay's
content (which vehicle, its level and probability, its box) changes only at fusion ticks (0.1 s)
and comes only from what the car knows; nothing drawn is read from the render's instance map:

- fusion guidance (source ``fusion``): the box the fusion matched, as it drew it at the tick. On
  the frames shown between two ticks the box is carried forward (:func:`tracked_boxes`): its
  corners are back-projected at the depth the fusion measured for it (``Guidance.box_depth_m``),
  moved by the matched twin's reported velocity (the cloud's report: GNSS error and latency
  included) and projected into the camera as the ego's own pose places it now (the ego's own
  state, its odometry). A wrong match shows a box on the wrong vehicle, as the car would.
- cloud guidance (source ``cloud``, no camera in the loop): the twin's cuboid as the cloud reports
  it (its GNSS position with its error and latency, its heading and size; carried forward by its
  reported speed between ticks) projected into the camera (:func:`cloud_boxes`). It is drawn
  where the cloud puts the twin, whichever vehicle is there.

Which vehicle each drawn box lands on is found afterwards, for scoring only (the driver's
``display`` table, :func:`displayed_rows`).
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


def _moved_box(box, depth_m: float, K: np.ndarray, T_then: np.ndarray, T_now: np.ndarray, shift: np.ndarray,
               size: tuple[int, int], near_m: float = 0.5):
    """`box` (x1, y1, x2, y2, px) of camera `T_then` back-projected at camera-Z `depth_m`, moved by
    `shift` (world, m) and projected into camera `T_now`; clipped to the image (`size` = (w, h)); None
    when it falls behind the near plane or off the image."""
    from vcfusion.render.camera import project_points

    x1, y1, x2, y2 = box
    uv1 = np.array([[x1, y1, 1.0], [x2, y1, 1.0], [x1, y2, 1.0], [x2, y2, 1.0]])
    cam = (uv1 @ np.linalg.inv(K).T) * depth_m  # camera-then points at that depth
    R, t = T_then[:3, :3], T_then[:3, 3]
    world = (cam - t) @ R + shift  # R^T (p - t)
    w, h = size
    p = project_points(world, K, T_now, w, h)
    if not (np.asarray(p.depth) > near_m).all():
        return None
    uv = np.asarray(p.uv, float)
    lo = np.clip(uv.min(axis=0), -0.5, [w - 0.5, h - 0.5])
    hi = np.clip(uv.max(axis=0), -0.5, [w - 0.5, h - 0.5])
    if hi[0] <= lo[0] or hi[1] <= lo[1]:
        return None
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


def _twin_velocity(twins, vehicle_id: str) -> np.ndarray:
    """The twin's reported velocity (world, m/s), zero when the cloud has no such twin."""
    if twins is None or vehicle_id not in twins.ids:
        return np.zeros(3)
    i = twins.ids.index(vehicle_id)
    v, h = float(twins.speed[i]), float(twins.heading[i])
    return np.array([v * np.cos(h), v * np.sin(h), 0.0])


def tracked_boxes(items, K: np.ndarray, T_then: np.ndarray, T_now: np.ndarray, dt_s: float,
                  size: tuple[int, int], twins=None) -> list[Guidance]:
    """The fusion's items with their matched boxes carried from the tick's camera `T_then` to the
    camera `T_now`, `dt_s` later (module doc). Items without a box (no match) are left out; a box
    without a measured depth stays where the fusion drew it; a box carried off the image is left out."""
    out = []
    for g in items:
        if g.box is None:
            continue
        if g.box_depth_m is None or dt_s == 0.0:
            out.append(g)
            continue
        box = _moved_box(g.box, g.box_depth_m, K, T_then, T_now, _twin_velocity(twins, g.vehicle_id) * dt_s, size)
        if box is not None:
            out.append(replace(g, box=box))
    return out


def cloud_boxes(items, twins, camera) -> list[Guidance]:
    """Cloud items boxed where the cloud puts their twins: each twin's reported cuboid (`twins`:
    the tick's neighbour twins, already carried to the frame's time) projected into `camera` (a
    CameraView); twins out of view are left out."""
    from vcfusion.fusion.matching import project_twins

    if twins is None or not len(twins):
        return []
    proj = project_twins(twins, camera)
    index = {vid: k for k, vid in enumerate(twins.ids)}
    out = []
    for g in items:
        k = index.get(g.vehicle_id)
        if k is None or not proj.in_view[k]:
            continue
        out.append(replace(g, box=tuple(float(v) for v in proj.expected_box[k])))
    return out


def carried_twins(twins, dt_s: float):
    """The twins moved `dt_s` along their reported heading at their reported speed (their reports'
    error and latency kept: what the cloud knows, carried to the frame's time)."""
    if twins is None or dt_s == 0.0 or not len(twins):
        return twins
    travel = np.asarray(twins.speed, float) * dt_s
    heading = np.asarray(twins.heading, float)
    return replace(twins, x=np.asarray(twins.x) + travel * np.cos(heading),
                   y=np.asarray(twins.y) + travel * np.sin(heading))


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
