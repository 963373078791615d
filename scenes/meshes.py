"""Generated triangle meshes written as binary little-endian PLY (positions, normals, UVs).

Vertices are float32 ``x y z nx ny nz u v``; faces are ``uchar 3, int32 i j k`` triangles.
"""
from __future__ import annotations

import numpy as np

from scenes.noise import value_noise

MAX_TRIANGLES = 20_000
_FACE_DTYPE = np.dtype([("n", "u1"), ("i", "<i4", (3,))])


def ply_bytes(vertices: np.ndarray, normals: np.ndarray, uvs: np.ndarray,
              faces: np.ndarray) -> bytes:
    """Binary PLY of Vx3 positions, Vx3 unit normals, Vx2 UVs and Fx3 vertex indices."""
    n = len(vertices)
    if vertices.shape != (n, 3) or normals.shape != (n, 3) or uvs.shape != (n, 2):
        raise ValueError("ply_bytes: vertices/normals need shape Vx3 and uvs Vx2")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= n:
        raise ValueError("ply_bytes: faces must be Fx3 indices into the vertices")
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {n}\n"
        + "".join(f"property float {p}\n" for p in ("x", "y", "z", "nx", "ny", "nz", "u", "v"))
        + f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vdata = np.concatenate([vertices, normals, uvs], axis=1).astype("<f4")
    fdata = np.empty(len(faces), dtype=_FACE_DTYPE)
    fdata["n"] = 3
    fdata["i"] = faces
    return header.encode("ascii") + vdata.tobytes() + fdata.tobytes()


def heightfield(heights: np.ndarray) -> bytes:
    """PLY of a height field over the unit square: x, z in [-1, 1], y = ``heights`` (NxM,
    rows along +z, columns along +x); triangles face +Y, smooth normals, UVs in [0, 1]."""
    rows, cols = heights.shape
    if rows < 2 or cols < 2 or 2 * (rows - 1) * (cols - 1) > MAX_TRIANGLES:
        raise ValueError(f"height field {rows}x{cols} must have 2..{MAX_TRIANGLES} triangles")
    z, x = np.meshgrid(np.linspace(-1, 1, rows), np.linspace(-1, 1, cols), indexing="ij")
    vertices = np.stack([x, heights, z], axis=-1).reshape(-1, 3)
    dy_dz, dy_dx = np.gradient(heights, 2.0 / (rows - 1), 2.0 / (cols - 1))
    normals = np.stack([-dy_dx, np.ones_like(heights), -dy_dz], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    uvs = np.stack([(x + 1) / 2, (z + 1) / 2], axis=-1).reshape(-1, 2)
    idx = np.arange(rows * cols).reshape(rows, cols)
    v00, v01 = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    v10, v11 = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([v00, v10, v01], 1), np.stack([v01, v10, v11], 1)])
    return ply_bytes(vertices, normals.reshape(-1, 3), uvs, faces)


def random_terrain(rng: np.random.Generator, resolution: int = 96,
                   amplitude: float = 0.25) -> tuple[bytes, np.ndarray]:
    """A fractal-noise terrain PLY (resolution^2 vertices) and its heights (max ``amplitude``).

    Heights are 0 at the lowest point; returns the PLY bytes and the float64 height array.
    """
    h = value_noise(rng, resolution, resolution, int(rng.integers(2, 6)), octaves=4)
    h = (h - h.min()) / max(float(np.ptp(h)), 1e-9) * amplitude
    return heightfield(h), h
