"""Material ids of the camera's shader, carried per face in the face colour's alpha byte.

A trimesh face colour is RGBA; the camera never draws transparency, so the alpha byte names the
material instead, and it survives ``trimesh.util.concatenate`` with the colours.
:func:`vcfusion.render.scene.flat_primitive` hands it to the shader as the first texture
coordinate; ``shaders/lambert.frag`` shades by it. The ids here must equal the shader's
``MAT_*`` constants (checked by a test).
"""

from __future__ import annotations

import numpy as np
import trimesh

MATTE = 0  # Lambert only: tyres, plastic, plates, rails' posts
PAINT = 1  # car paint: Lambert + Blinn-Phong highlight + a Fresnel reflection of the sky
GLASS = 2  # dark glass reflecting the sky (and the ground below the horizon), sharp highlight
LAMP = 3  # lamp lenses: their own colour, barely shaded
SHADOW = 4  # a vehicle's contact shadow: projected onto the ground by the vertex shader, instance code 0
METAL = 5  # rims, guard rails: grey with a broad highlight
ASPHALT = 6  # road surface: procedural grain, patches and darker wheel tracks (texcoord v = lane coordinate)
PAINT_MARK = 7  # road markings: slightly worn white
GRASS = 8  # verge and fields: large-scale colour patches
FOLIAGE = 9  # roadside trees and bushes: Lambert with colour noise

NAMES = {MATTE: "MATTE", PAINT: "PAINT", GLASS: "GLASS", LAMP: "LAMP", SHADOW: "SHADOW", METAL: "METAL",
         ASPHALT: "ASPHALT", PAINT_MARK: "PAINT_MARK", GRASS: "GRASS", FOLIAGE: "FOLIAGE"}


def coloured(mesh: trimesh.Trimesh, rgb, material=MATTE) -> trimesh.Trimesh:
    """Give every face the colour ``rgb`` (a triple or an (F, 3) array) and the material (an id or (F,) ids)."""
    n = len(mesh.faces)
    colours = np.empty((n, 4), np.uint8)
    colours[:, :3] = np.broadcast_to(np.asarray(rgb, np.uint8), (n, 3))
    colours[:, 3] = np.broadcast_to(np.asarray(material, np.uint8), (n,))
    mesh.visual.face_colors = colours
    return mesh


def face_materials(mesh: trimesh.Trimesh) -> np.ndarray:
    return np.asarray(mesh.visual.face_colors)[:, 3].astype(np.int32)
