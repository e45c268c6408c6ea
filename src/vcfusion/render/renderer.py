"""The ego camera renderer: RGB, metric depth and an instance map per frame (pyrender, offscreen).

Outputs of :meth:`EgoCameraRenderer.render` (a :class:`Frame`):
- ``rgb``: (H, W, 3) uint8;
- ``depth``: (H, W) float32, camera Z in metres (OpenCV camera frame, *not* the ray length);
  **sky (no surface within the far plane) is +inf**;
- ``instances``: (H, W) int32, the index of the vehicle seen at the pixel into
  ``Frame.vehicle_ids`` (so ``frame.vehicle_ids[instances[r, c]]`` is a SUMO vehicle id);
  **-1 where no vehicle is seen** (road, rails, ground, sky).

How (profiled under OSMesa/llvmpipe, where fragment shading dominates): one pass per frame.
The scene is drawn with our shader (``shaders/lambert.*``, in place of pyrender's PBR shader:
Lambert plus, per material, highlights, sky reflections and procedural ground) that writes each object's instance code into the alpha channel, so a single
RGBA + depth read-back gives all three images, pixel-consistent. The same pass on every OpenGL
platform: where pyrender draws into its own framebuffer (EGL) that framebuffer is made
single-sampled (:func:`_single_sampled`), so depth and instance codes are sampled at pixel centres
there as under OSMesa, and the RGB image is the same image (the GPU check's figures).

The RGB image is then finished (:mod:`vcfusion.render.presets`, the camera's ``render_preset``):
the sky pixels (depth +inf) get the sky gradient (:mod:`vcfusion.render.sky`), the quality preset
redraws the colour on a 2x2 grid of sub-pixel camera shifts and averages it (supersampling), and
the camera model (blur, exposure, noise) applies. Depth and instances
come from the one pass at the camera's resolution whatever the preset.
"""

from __future__ import annotations

import functools
import math
import os
import time
from dataclasses import dataclass

import cv2
import numpy as np

import vcfusion.render  # noqa: F401  (sets PYOPENGL_PLATFORM before pyrender imports OpenGL)
import pyrender  # noqa: E402
from OpenGL import GL  # noqa: E402
from pyrender.constants import ProgramFlags, RenderFlags  # noqa: E402
from pyrender.shader_program import ShaderProgram, ShaderProgramCache  # noqa: E402

from vcfusion.records import VehicleStates  # noqa: E402
from vcfusion.scenario import CameraConfig  # noqa: E402
from vcfusion.traffic.network import read_road, require_flat_network  # noqa: E402
from vcfusion.traffic.roadframe import RoadFrame  # noqa: E402
from vcfusion.records import EGO_ID  # noqa: E402
from vcfusion.render.camera import Intrinsics, opengl_camera_pose, world_to_camera  # noqa: E402
from vcfusion.render.presets import PRESETS, RenderPreset, finish_rgb  # noqa: E402
from vcfusion.render.sky import sky_image  # noqa: E402
from vcfusion.render.scene import TrafficScene  # noqa: E402

SHADER_DIR = os.path.join(os.path.dirname(__file__), "shaders")
_PYRENDER_SHADER_DIR = os.path.join(os.path.dirname(pyrender.__file__), "shaders")


@functools.cache
def _raw_uniform(kind: tuple) -> object:
    """PyOpenGL's raw (unwrapped) glUniform* function for a value kind: (n, 'f' | 'i' | 'u') for a
    vector of n, (rows, cols) for a matrix. The raw functions take a contiguous NumPy array of the
    GL type as is (7 Python calls a set against the wrapped functions' 31, which convert and check
    the array themselves)."""
    from OpenGL.raw.GL.VERSION import GL_2_0, GL_2_1, GL_3_0

    a, b = kind
    if isinstance(b, str):
        return getattr(GL_3_0 if b == "u" else GL_2_0, f"glUniform{a}{'ui' if b == 'u' else b}v")
    return getattr(GL_2_0, f"glUniformMatrix{a}fv") if a == b else getattr(GL_2_1, f"glUniformMatrix{a}x{b}fv")


class _CameraProgram(ShaderProgram):
    """pyrender's shader program with each uniform's location asked of GL once per linked program
    and the values sent through PyOpenGL's raw functions.

    pyrender asks GL for the location at every set (131 sets a frame on the GPU check's frames),
    and for a uniform the shader does not declare (half of them: our shader reads no PBR material
    factors and no light counts) raises a ValueError and swallows it. Here such a uniform is skipped
    and any other failure raises. The values reach GL as pyrender sends them (float32, int32 or
    uint32 arrays, matrices row by row with transpose set), so the images are the same bit for bit
    (tests/render)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._locations: dict[str, int] = {}  # of the linked program; emptied when it is deleted

    def _remove_from_context(self):
        self._locations.clear()
        super()._remove_from_context()

    def set_uniform(self, name, value, unsigned=False):
        loc = self._locations.get(name)
        if loc is None:
            loc = self._locations[name] = GL.glGetUniformLocation(self._program_id, name)
        if loc == -1:
            return  # not declared by this program (or optimised away): nothing to set
        if isinstance(value, np.ndarray):
            if value.ndim == 2:  # a matrix, rows as given (GL_TRUE: transposed into GL's column order)
                kind, args = value.shape, (GL.GL_TRUE, np.ascontiguousarray(value, dtype=np.float32))
            elif unsigned or value.dtype.kind == "u":
                kind, args = (value.shape[0], "u"), (np.ascontiguousarray(value, dtype=np.uint32),)
            elif value.dtype.kind == "i":  # NumPy's signed integers (booleans, as in pyrender, go as floats)
                kind, args = (value.shape[0], "i"), (np.ascontiguousarray(value, dtype=np.int32),)
            else:
                kind, args = (value.shape[0], "f"), (np.ascontiguousarray(value, dtype=np.float32),)
            _raw_uniform(kind)(loc, 1, *args)
        elif isinstance(value, float):
            GL.glUniform1f(loc, value)
        elif isinstance(value, (bool, int)):
            (GL.glUniform1ui if unsigned else GL.glUniform1i)(loc, int(value))
        else:
            raise TypeError(f"uniform {name}: expected an array, a float or an int, got {type(value).__name__}")


class _CameraShaders(ShaderProgramCache):
    """pyrender's shader cache with its lit mesh shader replaced by ours (others unchanged).

    Programs are cached per renderer (one GL context each). pyrender keys its cache by
    ``OpenGL.contextdata.getContext()``, which under OSMesa differs from call to call, so it
    recompiled every shader for every draw call (profiled: half the frame time).
    """

    _OURS = {"mesh.vert": "lambert.vert", "mesh.frag": "lambert.frag"}

    def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
        def path(name):
            if name is None:
                return None
            if name in self._OURS:
                return os.path.join(SHADER_DIR, self._OURS[name])
            return os.path.join(_PYRENDER_SHADER_DIR, name)

        defines = defines or {}
        key = (vertex_shader, fragment_shader, geometry_shader, tuple(sorted(defines.items())))
        program = self._program_cache.get(key)
        if program is None:
            program = self._program_cache[key] = _CameraProgram(
                vertex_shader=path(vertex_shader), fragment_shader=path(fragment_shader),
                geometry_shader=path(geometry_shader), defines=defines)
        return program


NO_VEHICLE = -1


@dataclass(frozen=True)
class Frame:
    """One ego-camera frame: images plus the camera that took them (``Tick.frame``)."""

    time: float
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 camera Z in metres; +inf = sky
    instances: np.ndarray  # (H, W) int32 index into vehicle_ids; -1 = no vehicle
    vehicle_ids: tuple[str, ...]  # the vehicles drawn (all but the ego), instance value k -> vehicle_ids[k]
    K: np.ndarray  # (3, 3)
    T_world_to_camera: np.ndarray  # (4, 4), OpenCV camera frame

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])


def camera_road(scenario) -> RoadFrame:
    """The road frame whose road the ego camera draws: the ego's route's (or the scenario's)."""
    ego = scenario.ego
    route = ego.route if ego is not None and ego.route is not None else scenario.route
    return read_road(scenario.network, route)


def _single_sampled(gl_renderer) -> None:
    """Make pyrender's offscreen framebuffer (EGL) single-sampled; pyrender asks for 4 samples.

    A multisampled depth buffer reaches the read-back as one of its samples, off the pixel centre:
    on an NVIDIA H200 (EGL) depth came 0.2 px off, which on the road beyond 20 m is 1-10 % of the
    distance (10 % of all pixels outside max(0.05 m, 1 %) of OSMesa's, `vcfusion bench --sections
    GPU`); and resolved colour blends the instance codes written to alpha at edges. pyrender has
    no setting for it: its call is given 0 samples (a single-sampled buffer, the GL rule) while it
    builds the framebuffer."""
    import pyrender.renderer as gl_module

    configure = gl_renderer._configure_main_framebuffer

    def configure_single_sampled():
        multisample = gl_module.glRenderbufferStorageMultisample
        gl_module.glRenderbufferStorageMultisample = (
            lambda target, _samples, fmt, width, height: multisample(target, 0, fmt, width, height))
        try:
            configure()
        finally:
            gl_module.glRenderbufferStorageMultisample = multisample

    gl_renderer._configure_main_framebuffer = configure_single_sampled


def _lean_forward_pass(gl_renderer) -> None:
    """pyrender's forward pass of our shader with its per-draw Python work cut, the draws, their
    order and every uniform's value pyrender's (the frames are the same, bit for bit: tests/render):

    - the uniforms that are the same for every draw of a frame (the camera's V, P and position, the
      sun) are set once per program and frame, not before every primitive (pyrender: 332 sets a
      frame on the GPU check's frames, here 131);
    - a primitive's program is pyrender's choice, which depends on the pass's flags, the primitive's
      vertex buffers and its material's textures and kind only: it is looked up by those (pyrender
      makes the choice at every draw, asking GL for its texture units each time), and made again
      when the program left its context;
    - the context update (pyrender gathers every material's textures each frame) runs when the
      scene's meshes or the flags change;
    - poses and the far-to-near order are computed once a frame, for the visible nodes
      (:func:`_far_to_near`).

    Into pyrender's framebuffer (OFFSCREEN) it reads nothing back: the renderer reads colour and
    depth once, itself (:meth:`EgoCameraRenderer._draw_rgba`). Figures: docs/performance.md, "On an
    NVIDIA H200"."""
    programs: dict[tuple, object] = {}
    update_context, context_flags = gl_renderer._update_context, None

    def update_context_on_change(scene, flags):
        # with the same meshes and flags as the last update (vehicles come and go only now and
        # then, and the renderer never edits a material) there is nothing to add or delete
        nonlocal context_flags
        if flags != context_flags or scene.meshes != gl_renderer._meshes:
            context_flags = flags
            update_context(scene, flags)

    gl_renderer._update_context = update_context_on_change

    def program_of(primitive, flags):
        material = primitive.material
        key = (int(flags), int(primitive.buf_flags), int(material.tex_flags), type(material))
        program = programs.get(key)
        if program is None or not program._in_context():
            program = programs[key] = gl_renderer._get_primitive_program(primitive, flags, ProgramFlags.USE_MATERIAL)
        return program

    def forward_pass(scene, flags, seg_node_map=None):
        if flags & ~RenderFlags.OFFSCREEN:
            raise ValueError(f"the camera's pass draws colour only; got render flags {flags}")
        gl = gl_renderer
        gl._configure_forward_pass_viewport(flags)
        GL.glClearColor(*scene.bg_color)
        GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)
        V, P = gl._get_camera_matrices(scene)
        cam_pos = scene.get_pose(scene.main_camera_node)[:3, 3]
        ready, bound, program = set(), None, None
        nodes, poses = _far_to_near(scene, cam_pos)
        for node in nodes:
            for primitive in node.mesh.primitives:
                program = program_of(primitive, flags)
                if program is not bound:
                    program._bind()
                    bound = program
                if program not in ready:
                    program.set_uniform("V", V)
                    program.set_uniform("P", P)
                    program.set_uniform("cam_pos", cam_pos)
                    gl._bind_lighting(scene, program, node, flags)  # one sun: the same for every node
                    ready.add(program)
                gl._bind_and_draw_primitive(primitive=primitive, pose=poses[node], program=program, flags=flags)
                gl._reset_active_textures()
        if program is not None:
            program._unbind()
        GL.glFlush()

    gl_renderer._forward_pass = forward_pass


def _far_to_near(scene, cam_pos: np.ndarray) -> tuple[list, dict]:
    """The visible mesh nodes in pyrender's draw order (opaque ones, then transparent ones, each
    from the farthest origin to the nearest; a stable sort, so ties keep the scene's order) and each
    one's world pose, computed once a frame (pyrender computes it for the sort and again for the
    draw, and sorts the hidden nodes too: the road pieces out of view)."""
    solid, transparent, poses, distance = [], [], {}, {}
    for node in scene.mesh_nodes:
        mesh = node.mesh
        if not mesh.is_visible:
            continue
        pose = poses[node] = scene.get_pose(node)
        distance[node] = -np.linalg.norm(pose[:3, 3] - cam_pos)
        (transparent if mesh.is_transparent else solid).append(node)
    solid.sort(key=distance.__getitem__)
    transparent.sort(key=distance.__getitem__)
    return solid + transparent, poses


class EgoCameraRenderer:
    """Renders the ego camera of one scenario; the scene is built once and reused for all frames."""

    def __init__(self, road: RoadFrame, camera: CameraConfig, ego_id: str = EGO_ID, preset: RenderPreset | None = None):
        self.camera = camera
        self.road = road
        self.ego_id = ego_id
        self.preset = preset or PRESETS[camera.render_preset]
        self.intrinsics = k = Intrinsics.from_fov(camera.hfov_deg, camera.width_px, camera.height_px)
        if road.net_file is not None:
            require_flat_network(road.net_file)  # the world below is flat (z = 0)
        self.traffic = TrafficScene(road, skip_ids=(ego_id,))
        # pyrender's window coordinates put integer values at pixel corners, OpenCV's at pixel
        # centres: the renderer's principal point is half a pixel further.
        self._gl_camera = gl_camera = pyrender.IntrinsicsCamera(fx=k.fx, fy=k.fy, cx=k.cx + 0.5, cy=k.cy + 0.5,
                                                                znear=camera.near_m, zfar=camera.far_m)
        self.camera_node = self.traffic.scene.add(gl_camera, pose=np.eye(4))
        self._offscreen = pyrender.OffscreenRenderer(k.width, k.height)
        # Private pyrender attributes: the GL renderer behind the offscreen wrapper and its platform.
        self._gl = self._offscreen._renderer
        self._platform = self._offscreen._platform
        self._gl._program_cache = _CameraShaders()
        _lean_forward_pass(self._gl)
        # pyrender's own framebuffer (EGL) or the context's (OSMesa): where the pass is read back
        self._framebuffer = self._platform.supports_framebuffers()
        if self._framebuffer:
            _single_sampled(self._gl)
        self._sky_cache: tuple[bytes, np.ndarray] | None = None
        self.last_timings_ms: dict[str, float] = {}
        # Half-extents of the view frustum per unit depth, for culling vehicles out of view.
        self._tan_x = (k.width / 2 + 1) / k.fx
        self._tan_y = (k.height / 2 + 1) / k.fy
        # code -> index into the frame's vehicle_ids; -1 for code 0 (no vehicle).
        self._code_lut = np.full(256, -1, dtype=np.int32)

    @classmethod
    def for_scenario(cls, scenario, camera: CameraConfig | None = None, ego_id: str = EGO_ID,
                     preset: RenderPreset | None = None) -> "EgoCameraRenderer":
        """The ego camera of a scenario: the road of the ego's route (the scenario's when the ego
        names none) and the scenario's camera unless another is given."""
        return cls(camera_road(scenario), camera or scenario.camera, ego_id, preset)

    # -- camera ------------------------------------------------------------------------
    def extrinsics(self, truth: VehicleStates) -> np.ndarray:
        i = truth.index_of(self.ego_id)
        return world_to_camera(float(truth.x[i]), float(truth.y[i]), float(truth.z[i]), float(truth.heading[i]),
                               self.camera)

    def _in_view(self, centres: np.ndarray, radius: np.ndarray, T: np.ndarray) -> np.ndarray:
        """Conservative frustum test of bounding spheres (centres (N, 3) in world, radius (N,))."""
        pc = centres @ T[:3, :3].T + T[:3, 3]
        z = pc[:, 2]
        return ((z > -radius) & (z < self.camera.far_m + radius)
                & (np.abs(pc[:, 0]) <= z * self._tan_x + radius * math.hypot(1.0, self._tan_x))
                & (np.abs(pc[:, 1]) <= z * self._tan_y + radius * math.hypot(1.0, self._tan_y)))

    # -- rendering ---------------------------------------------------------------------
    def render(self, truth: VehicleStates, T_world_to_camera: np.ndarray | None = None) -> Frame:
        """Render what the ego's camera sees in the traffic state `truth`."""
        T = self.extrinsics(truth) if T_world_to_camera is None else np.asarray(T_world_to_camera, dtype=float)
        centres = np.column_stack([truth.x, truth.y, truth.z + truth.height / 2])
        radius = 0.5 * np.sqrt(truth.length ** 2 + truth.width ** 2 + truth.height ** 2)
        drawn = self.traffic.update(truth, self._in_view(centres, radius, T))
        spheres = self.traffic.piece_spheres
        self.traffic.show_road_pieces(self._in_view(spheres[:, :3], spheres[:, 3], T))
        self.traffic.scene.set_pose(self.camera_node, opengl_camera_pose(T))
        lut = self._code_lut
        lut[1:] = -1
        for index, vid in enumerate(drawn):
            lut[self.traffic.codes[vid]] = index
        t0 = time.perf_counter()
        rgb, codes, depth = self._draw()
        t1 = time.perf_counter()
        rgb = self._finish(rgb, depth, T, float(truth.time))
        # Where a frame's time goes (read by vcfusion.render.bench).
        self.last_timings_ms = {"draw": 1000.0 * (t1 - t0), "finish": 1000.0 * (time.perf_counter() - t1)}
        return Frame(time=float(truth.time), rgb=rgb, depth=depth, instances=lut[codes], vehicle_ids=tuple(drawn),
                     K=self.intrinsics.K, T_world_to_camera=T)

    def _sky(self, T: np.ndarray) -> np.ndarray:
        """The sky gradient for this camera orientation (cached: on a flat road it never changes)."""
        key = np.round(T[:3, 2], 4).tobytes()
        if self._sky_cache is None or self._sky_cache[0] != key:
            k = self.intrinsics
            self._sky_cache = (key, sky_image(k.K, T, k.width, k.height))
        return self._sky_cache[1]

    def _finish(self, rgb: np.ndarray, depth: np.ndarray, T: np.ndarray, time_s: float) -> np.ndarray:
        """Supersampled colour (quality), sky gradient, camera model: RGB only."""
        if self.preset.supersample > 1:
            rgb = self._draw_supersampled()
        sky = np.isinf(depth).view(np.uint8)
        cv2.copyTo(self._sky(T), sky, rgb)  # in place; 50x faster than np.copyto with a mask
        return finish_rgb(rgb, self.preset, time_s)

    def _draw_supersampled(self) -> np.ndarray:
        """The colour pass again with the camera shifted by sub-pixel offsets (an ss x ss grid), averaged.

        The same as drawing at ss x the resolution and averaging blocks down, but in the camera's
        own buffer: with a taller buffer llvmpipe rounds depth differently (measured), and the
        depth and instance maps must not depend on the preset.
        """
        ss, k, cam = self.preset.supersample, self.intrinsics, self._gl_camera
        w, h = k.width, k.height
        steps = (np.arange(ss) + 0.5) / ss - 0.5
        total = np.zeros((h, w, 3), np.float32)
        try:
            for dy in steps:
                for dx in steps:
                    # Moving the principal point by -d samples the image at pixel + d.
                    cam.cx, cam.cy = k.cx + 0.5 - dx, k.cy + 0.5 - dy
                    total += self._draw_rgba()[..., :3]
        finally:
            cam.cx, cam.cy = k.cx + 0.5, k.cy + 0.5
        return np.round(total / (ss * ss)).astype(np.uint8)

    def _draw_rgba(self) -> np.ndarray:
        """Draw the current scene; (H, W, 4) uint8, rows top-down. The buffer drawn into is left
        bound for reading (the depth read-back of :meth:`_draw`)."""
        w, h = self.intrinsics.width, self.intrinsics.height
        self._platform.make_current()
        self._gl.viewport_width, self._gl.viewport_height = w, h
        # EGL: into pyrender's framebuffer, single-sampled (_single_sampled), so read where it was
        # drawn; OSMesa: into the context's buffer
        self._gl.render(self.traffic.scene, RenderFlags.OFFSCREEN if self._framebuffer else RenderFlags.NONE)
        GL.glFinish()
        if self._framebuffer:
            GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._gl._main_fb_ms)
        else:
            GL.glReadBuffer(GL.GL_FRONT)
        rgba = np.frombuffer(GL.glReadPixels(0, 0, w, h, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE), dtype=np.uint8)
        # GL rows run bottom-up. OpenCV's flip and channel split copy 4-6 times faster than NumPy's
        # strided copies of the flipped view (2.1-2.8 -> 0.5 ms a 640x480 frame, the same bytes)
        return cv2.flip(rgba.reshape(h, w, 4), 0)

    def _draw(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb uint8, instance codes uint8, depth float32 camera Z with +inf sky) of the current scene."""
        w, h = self.intrinsics.width, self.intrinsics.height
        rgba = self._draw_rgba()
        window_z = cv2.flip(np.frombuffer(GL.glReadPixels(0, 0, w, h, GL.GL_DEPTH_COMPONENT, GL.GL_FLOAT),
                                          dtype=np.float32).reshape(h, w), 0)
        return cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB), cv2.extractChannel(rgba, 3), self._linear_depth(window_z)

    def _linear_depth(self, window_z: np.ndarray) -> np.ndarray:
        """Window depth in [0, 1] (perspective) -> camera Z in metres; the cleared value 1 -> +inf."""
        n, f = np.float32(self.camera.near_m), np.float32(self.camera.far_m)
        # z_ndc = 2 d - 1;  Z = 2 n f / (f + n - z_ndc (f - n)) = n f / (f - d (f - n)).
        # float32 suffices: its rounding (~2 mm at 100 m) is below the 24-bit depth buffer's step.
        depth = window_z * (f - n)
        np.subtract(f, depth, out=depth)
        with np.errstate(divide="ignore"):
            np.divide(n * f, depth, out=depth)
        depth[window_z >= 1.0] = np.inf
        return depth

    def silhouette(self, vehicle_id: str) -> np.ndarray:
        """Mask of one vehicle drawn alone (nothing occluding it), at the poses of the last render."""
        static = self.traffic.static_visibility()
        self.traffic.set_static_visibility([False] * len(static))
        self.traffic.set_only_vehicle(vehicle_id)
        try:
            _, codes, _ = self._draw()
        finally:
            self.traffic.set_only_vehicle(None)
            self.traffic.set_static_visibility(static)
        return codes == self.traffic.codes[vehicle_id]

    def vehicles_only(self) -> np.ndarray:
        """Instance map (as ``Frame.instances``) of the last render's vehicles drawn without the
        road and its surroundings: what each vehicle shows when only vehicles can hide it."""
        static = self.traffic.static_visibility()
        self.traffic.set_static_visibility([False] * len(static))
        try:
            _, codes, _ = self._draw()
        finally:
            self.traffic.set_static_visibility(static)
        return self._code_lut[codes]

    def close(self) -> None:
        if self._offscreen is not None:
            self._offscreen.delete()
            self._offscreen = None

    def __enter__(self) -> "EgoCameraRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
