"""pygame / SDL set-up for driving, and SDL's virtual joystick.

`init_sdl()` sets the hints before SDL starts: joystick events keep arriving when the window has
no focus (a wheel must not go dead because the experimenter clicked another window), and with
`headless` SDL's dummy video and audio drivers (CI, servers). `VirtualJoystick` attaches a joystick
through SDL's own `SDL_JoystickAttachVirtual` (reached with ctypes in the SDL library pygame
loaded); SDL then lists it like a plugged-in device and sends its axis events, so tests and the
benchmark drive the same code a wheel does.
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path

# SDL_JOYSTICK_ALLOW_BACKGROUND_EVENTS: without it SDL drops joystick events while the window is
# not focused (and the virtual joystick sends nothing under the dummy driver, which has no focus).
# SDL_FRAMEBUFFER_ACCELERATION=0: the window's pixels go to the screen in software (X11 XShm),
# never through an OpenGL context of SDL's: the camera renders with OSMesa (PYOPENGL_PLATFORM=osmesa),
# which shares Mesa's GL dispatch with libGL, and SDL's GL framebuffer then crashed in display.flip
# after the first render (seen under Xvfb; the dummy driver has no GL and did not show it).
SDL_HINTS = {"SDL_JOYSTICK_ALLOW_BACKGROUND_EVENTS": "1", "SDL_FRAMEBUFFER_ACCELERATION": "0"}
SDL_JOYSTICK_TYPE_WHEEL = 2
AXIS_MAX = 32767


def init_sdl(headless: bool = False):
    """Start pygame (display + joystick) with the hints above; returns the pygame module."""
    for name, value in SDL_HINTS.items():
        os.environ[name] = value
    if headless:
        os.environ["SDL_VIDEODRIVER"] = "dummy"
        os.environ["SDL_AUDIODRIVER"] = "dummy"
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    import pygame

    pygame.display.init()
    pygame.joystick.init()
    pygame.font.init()
    return pygame


def sdl_library() -> ctypes.CDLL:
    """The SDL2 library that pygame itself loaded (pygame's wheel bundles it beside the package;
    a pygame built against the system SDL uses that one)."""
    import pygame

    bundled = sorted((Path(pygame.__file__).parent.parent / "pygame.libs").glob("libSDL2-2*.so*"))
    lib = ctypes.CDLL(str(bundled[0]) if bundled else "libSDL2-2.0.so.0")
    lib.SDL_JoystickAttachVirtual.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int]
    lib.SDL_JoystickAttachVirtual.restype = ctypes.c_int
    lib.SDL_JoystickDetachVirtual.argtypes = [ctypes.c_int]
    lib.SDL_JoystickDetachVirtual.restype = ctypes.c_int
    lib.SDL_JoystickFromInstanceID.argtypes = [ctypes.c_int32]
    lib.SDL_JoystickFromInstanceID.restype = ctypes.c_void_p
    lib.SDL_JoystickSetVirtualAxis.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_int16]
    lib.SDL_JoystickSetVirtualAxis.restype = ctypes.c_int
    lib.SDL_JoystickSetVirtualButton.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_uint8]
    lib.SDL_JoystickSetVirtualButton.restype = ctypes.c_int
    lib.SDL_GetError.restype = ctypes.c_char_p
    return lib


class VirtualJoystick:
    """A wheel-type joystick with `axes` axes and `buttons` buttons, attached to SDL; `pygame_joystick`
    is the pygame handle of it (opened). Axis values are -1..1 (SDL's -32768..32767)."""

    def __init__(self, axes: int = 4, buttons: int = 4):
        import pygame

        self._lib = sdl_library()
        before = pygame.joystick.get_count()
        self.device_index = self._lib.SDL_JoystickAttachVirtual(SDL_JOYSTICK_TYPE_WHEEL, axes, buttons, 0)
        if self.device_index < 0:
            raise RuntimeError(f"SDL_JoystickAttachVirtual failed: {self._lib.SDL_GetError().decode()}")
        pygame.event.pump()  # the device-added event; pygame's joystick list follows SDL's
        if pygame.joystick.get_count() <= before:
            raise RuntimeError("SDL attached the virtual joystick but pygame does not list it")
        self.pygame_joystick = pygame.joystick.Joystick(self.device_index)
        self.pygame_joystick.init()
        self._handle = self._lib.SDL_JoystickFromInstanceID(self.pygame_joystick.get_instance_id())

    def set_axis(self, axis: int, value: float) -> None:
        raw = int(round(max(-1.0, min(1.0, value)) * AXIS_MAX))
        if self._lib.SDL_JoystickSetVirtualAxis(self._handle, axis, raw) != 0:
            raise RuntimeError(f"SDL_JoystickSetVirtualAxis failed: {self._lib.SDL_GetError().decode()}")

    def set_button(self, button: int, pressed: bool) -> None:
        if self._lib.SDL_JoystickSetVirtualButton(self._handle, button, int(pressed)) != 0:
            raise RuntimeError(f"SDL_JoystickSetVirtualButton failed: {self._lib.SDL_GetError().decode()}")

    def detach(self) -> None:
        self.pygame_joystick.quit()
        self._lib.SDL_JoystickDetachVirtual(self.device_index)
