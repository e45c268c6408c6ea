"""The pyrender scene of the highway: built once, then only vehicle poses change per frame.

A vehicle gets a node when its id first appears and loses it when it is gone; meshes are shared
by vehicles of the same shape and colour (see :func:`vcfusion.render.vehicles.vehicle_mesh`), so
the GPU buffers of a model are uploaded once. The ego itself is not drawn: the camera sits in it.
"""

from __future__ import annotations

import math

import numpy as np

import vcfusion.render  # noqa: F401  (sets PYOPENGL_PLATFORM before pyrender imports OpenGL)
import pyrender  # noqa: E402
import trimesh  # noqa: E402

from vcfusion.records import VehicleStates  # noqa: E402
from vcfusion.traffic.roadframe import RoadFrame  # noqa: E402
from vcfusion.records import EGO_ID  # noqa: E402
from vcfusion.render.meshes import SKY, ground_mesh, road_layouts, road_pieces  # noqa: E402
from vcfusion.render.vehicles import vehicle_mesh, vehicle_style  # noqa: E402

# The sun: from the south-west, 50 degrees above the horizon.
SUN_AZIMUTH_DEG, SUN_ELEVATION_DEG = 225.0, 50.0


MAX_INSTANCE_CODES = 255  # instance codes travel in the 8-bit alpha channel; 0 = no vehicle


SMOOTH_BELOW_DEG = 35.0  # faces meeting at smaller angles are shaded smooth (car bodies), larger ones flat (boxes)


def flat_primitive(mesh: trimesh.Trimesh, alpha: float = 0.0, glossy: bool = False) -> pyrender.Primitive:
    """One opaque primitive with per-face colours and materials (one draw call).

    ``alpha`` is the instance code / 255 that the camera's shader writes to the alpha channel.
    The face colours' alpha byte is the material id (:mod:`vcfusion.render.materials`), passed
    as the first texture coordinate. ``glossy`` primitives (vehicles) carry a second, unused
    texture coordinate: it makes pyrender compile the shader's variant with reflections and
    highlights for them only (see ``shaders/lambert.frag``). Normals: the vertex normal where it is within
    SMOOTH_BELOW_DEG of the face's (smooth bodies), else the face normal (crisp edges).
    """
    faces = mesh.faces
    positions = mesh.vertices[faces].reshape(-1, 3).astype(np.float32)
    face_n = np.repeat(mesh.face_normals[:, None, :], 3, axis=1)
    vertex_n = mesh.vertex_normals[faces]
    smooth = np.einsum("fkc,fkc->fk", face_n, vertex_n) > np.cos(np.radians(SMOOTH_BELOW_DEG))
    normals = np.where(smooth[..., None], vertex_n, face_n).reshape(-1, 3).astype(np.float32)
    face_colours = np.asarray(mesh.visual.face_colors)
    colours = np.repeat(face_colours[:, :3].astype(np.float32) / 255.0, 3, axis=0)
    texcoords = np.zeros((len(positions), 2), np.float32)
    texcoords[:, 0] = np.repeat(face_colours[:, 3], 3)
    material = pyrender.MetallicRoughnessMaterial(
        baseColorFactor=[1.0, 1.0, 1.0, alpha], metallicFactor=0.0, roughnessFactor=0.85, alphaMode="OPAQUE")
    return pyrender.Primitive(positions=positions, normals=normals, color_0=colours, texcoord_0=texcoords,
                              texcoord_1=np.zeros_like(texcoords) if glossy else None, material=material, mode=4)


def vehicle_pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0, x], [s, c, 0.0, y], [0.0, 0.0, 1.0, z], [0.0, 0.0, 0.0, 1.0]])


def sun_pose() -> np.ndarray:
    """Pose of a directional light (it shines along its -z) coming from the sun's direction."""
    az, el = math.radians(SUN_AZIMUTH_DEG), math.radians(SUN_ELEVATION_DEG)
    towards_sun = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    z = towards_sun
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, y, z
    return pose


class TrafficScene:
    """Static road + one node per vehicle; :meth:`update` syncs it with a VehicleStates.

    Each vehicle node holds an *instance code* in 1..255 for as long as it is in the scene (its
    mesh's material alpha, see :func:`flat_primitive`). Vehicles that cannot be in view are
    hidden (not drawn) and hold no code, so the 255 codes are only needed for vehicles in front
    of the camera within the far plane.
    """

    def __init__(self, road: RoadFrame, skip_ids: tuple[str, ...] = (EGO_ID,)):
        # bg alpha 0: the sky's instance code is 0.
        self.scene = pyrender.Scene(bg_color=[*SKY, 0.0], ambient_light=[0.42, 0.44, 0.48])
        # The road is cut into pieces so that those out of view are not drawn (under llvmpipe,
        # vertex work for the whole 2 km of posts and dashes would dominate a frame).
        layouts = road_layouts(road)
        self.static_nodes = [self.scene.add(pyrender.Mesh([flat_primitive(ground_mesh(road, layouts))]), name="ground")]
        self.piece_spheres = []  # (centre x, y, z, radius) per road piece
        for name, piece in road_pieces(layouts):
            self.static_nodes.append(self.scene.add(pyrender.Mesh([flat_primitive(piece)]), name=name))
            lo, hi = piece.bounds
            self.piece_spheres.append([*((lo + hi) / 2), 0.5 * np.linalg.norm(hi - lo)])
        self.piece_spheres = np.array(self.piece_spheres)
        self.scene.add(pyrender.DirectionalLight(color=[1.0, 0.97, 0.92], intensity=0.75), pose=sun_pose())
        self.skip_ids = set(skip_ids)
        self.nodes: dict[str, pyrender.Node] = {}
        self.codes: dict[str, int] = {}
        self._free_codes = list(range(MAX_INSTANCE_CODES, 0, -1))
        self._models: dict[tuple, trimesh.Trimesh] = {}  # style -> model (its contact shadow inside)

    def _mesh_for(self, vid: str, vclass: str, length: float, width: float, height: float, code: int) -> pyrender.Mesh:
        """The vehicle's mesh (its contact shadow inside, drawn with code 0 by the shader)."""
        style = vehicle_style(vid, vclass, length, width, height)
        model = self._models.get(style)
        if model is None:  # built once per style: many vehicles share one
            model = self._models[style] = vehicle_mesh(style)
        return pyrender.Mesh([flat_primitive(model, alpha=code / 255.0, glossy=True)])

    def update(self, truth: VehicleStates, in_view: np.ndarray) -> list[str]:
        """Add, move, hide and remove vehicle nodes; returns the drawn vehicle ids in record order.

        ``in_view`` (bool per record row) says which vehicles may be seen; the others are hidden.
        """
        drawn = []
        present = set()
        for i, vid in enumerate(truth.ids):
            if vid in self.skip_ids:
                continue
            present.add(vid)
            if not in_view[i]:
                if vid in self.nodes:
                    self._remove(vid)
                continue
            pose = vehicle_pose(truth.x[i], truth.y[i], truth.z[i], truth.heading[i])
            node = self.nodes.get(vid)
            if node is None:
                if not self._free_codes:
                    raise RuntimeError(f"more than {MAX_INSTANCE_CODES} vehicles in front of the camera")
                code = self._free_codes.pop()
                mesh = self._mesh_for(vid, truth.vclass[i], float(truth.length[i]), float(truth.width[i]),
                                      float(truth.height[i]), code)
                self.nodes[vid] = self.scene.add(mesh, name=vid, pose=pose)
                self.codes[vid] = code
            else:
                self.scene.set_pose(node, pose)
            drawn.append(vid)
        for vid in [v for v in self.nodes if v not in present]:
            self._remove(vid)
        return drawn

    def _remove(self, vid: str) -> None:
        self.scene.remove_node(self.nodes.pop(vid))
        self._free_codes.append(self.codes.pop(vid))

    def show_road_pieces(self, visible: np.ndarray) -> None:
        """Draw only the road pieces flagged visible (the ground is always drawn)."""
        for node, flag in zip(self.static_nodes[1:], visible):
            node.mesh.is_visible = bool(flag)

    def static_visibility(self) -> list[bool]:
        return [node.mesh.is_visible for node in self.static_nodes]

    def set_static_visibility(self, flags: list[bool]) -> None:
        for node, flag in zip(self.static_nodes, flags):
            node.mesh.is_visible = flag

    def set_only_vehicle(self, vid: str | None) -> None:
        """Show one vehicle alone (no road, no other vehicles) or, with None, all vehicles again."""
        for other, node in self.nodes.items():
            node.mesh.is_visible = vid is None or other == vid
