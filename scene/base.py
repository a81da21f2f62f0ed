"""The types every stage shares for a ground-truth scene: textured mesh parts, boxes, the scene.

A ``Scene`` is what the renderer draws and what the evaluation scores against. The planners
never see it (they plan on the proxy reconstructed from images).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import trimesh


@dataclass(frozen=True)
class Box:
    """Axis-aligned box in world metres."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.lo, float), np.asarray(self.hi, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) or not np.all(hi >= lo):
            raise ValueError(f"invalid box lo={self.lo} hi={self.hi}")

    @property
    def lo_array(self) -> np.ndarray:
        return np.asarray(self.lo, dtype=float)

    @property
    def hi_array(self) -> np.ndarray:
        return np.asarray(self.hi, dtype=float)

    @property
    def center(self) -> np.ndarray:
        """Centre (3,) in metres."""
        return 0.5 * (self.lo_array + self.hi_array)

    @property
    def extent(self) -> np.ndarray:
        """Side lengths (3,) in metres."""
        return self.hi_array - self.lo_array

    def contains(self, points) -> np.ndarray:
        """Boolean mask (N,) of the points (N, 3) inside the box (boundary included)."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        return np.all((p >= self.lo_array) & (p <= self.hi_array), axis=1)

    def expanded(self, margin_xy: float, margin_z_lo: float = 0.0, margin_z_hi: float = 0.0) -> Box:
        """A copy grown by ``margin_xy`` metres sideways and the given margins below and above."""
        lo = self.lo_array - np.array([margin_xy, margin_xy, margin_z_lo])
        hi = self.hi_array + np.array([margin_xy, margin_xy, margin_z_hi])
        return Box(tuple(lo.tolist()), tuple(hi.tolist()))

    def as_dict(self) -> dict:
        return {"lo": list(map(float, self.lo)), "hi": list(map(float, self.hi))}

    @classmethod
    def from_points(cls, points) -> Box:
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        if len(p) == 0:
            raise ValueError("cannot bound an empty point set")
        return cls(tuple(p.min(0).tolist()), tuple(p.max(0).tolist()))


@dataclass
class MeshPart:
    """One renderable piece of a scene: a triangle mesh with either a texture or vertex colours.

    Attributes:
        name: unique name within the scene.
        vertices: (N, 3) float64 world coordinates in metres.
        faces: (M, 3) int32 vertex indices, counter-clockwise seen from outside.
        uv: (N, 2) float32 texture coordinates in [0, 1]-ish (wrapping allowed), or None; u to the
            right, v up: v = 0 is the bottom row of the texture image (OBJ/trimesh convention).
        texture: key into ``Scene.textures`` for ``uv``, or None.
        vertex_colors: (N, 3) uint8 RGB, used when there is no texture, or None.
        tint: RGB (each 0-1) multiplying the texture (a grey material in the part's colour), or None.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    texture: str | None = None
    vertex_colors: np.ndarray | None = None
    tint: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int32)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"part {self.name!r}: vertices must be (N, 3), got {self.vertices.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise ValueError(f"part {self.name!r}: needs at least one (M, 3) face, got {self.faces.shape}")
        if not np.all(np.isfinite(self.vertices)):
            raise ValueError(f"part {self.name!r}: vertices contain NaN or inf")
        if self.faces.min() < 0 or self.faces.max() >= len(self.vertices):
            raise ValueError(f"part {self.name!r}: face index out of range")
        if self.uv is not None:
            self.uv = np.ascontiguousarray(self.uv, dtype=np.float32)
            if self.uv.shape != (len(self.vertices), 2):
                raise ValueError(f"part {self.name!r}: uv must be (N, 2), got {self.uv.shape}")
        if (self.uv is None) != (self.texture is None):
            raise ValueError(f"part {self.name!r}: uv and texture go together")
        if self.vertex_colors is not None:
            self.vertex_colors = np.ascontiguousarray(self.vertex_colors, dtype=np.uint8)
        if self.tint is not None and (len(self.tint) != 3 or not all(0.0 <= c <= 1.0 for c in self.tint)):
            raise ValueError(f"part {self.name!r}: tint must be three values in [0, 1], got {self.tint}")


@dataclass
class Scene:
    """A ground-truth scene in world metres (Z up, ground at z = 0).

    Attributes:
        name: scene name (``tomb``, ``church``, ``cathedral``, or the mesh file's stem).
        parts: renderable mesh parts, the ground plane included.
        textures: texture images (H, W, 3) uint8 by key.
        structure_bounds: box around the structure itself (no ground apron); flights are planned
            around it.
        evaluation_region: box around the structure plus a ground apron; only surface and points
            inside it are scored.
        seed: the seed the procedural scene was built with (None for loaded meshes).
        info: free-form facts for the record (source file, footprint, ...).
    """

    name: str
    parts: list[MeshPart]
    textures: dict[str, np.ndarray]
    structure_bounds: Box
    evaluation_region: Box
    seed: int | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.parts:
            raise ValueError(f"scene {self.name!r} has no mesh parts")
        for part in self.parts:
            if part.texture is not None and part.texture not in self.textures:
                raise ValueError(f"part {part.name!r} uses unknown texture {part.texture!r}")

    @cached_property
    def ground_truth_mesh(self) -> trimesh.Trimesh:
        """All parts merged into one untextured mesh (the surface the evaluation scores against)."""
        offsets = np.cumsum([0] + [len(p.vertices) for p in self.parts[:-1]])
        vertices = np.concatenate([p.vertices for p in self.parts])
        faces = np.concatenate([p.faces + o for p, o in zip(self.parts, offsets, strict=True)])
        return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)

    @property
    def n_faces(self) -> int:
        return int(sum(len(p.faces) for p in self.parts))

    @cached_property
    def fingerprint(self) -> str:
        """Hex digest of everything a camera could see: geometry, UVs, colours and texture pixels.

        Cache keys of rendered flights include it, so a change to a scene generator is never
        served a flight (or proxy) rendered from the scene before the change.
        """
        digest = hashlib.blake2b(digest_size=16)
        digest.update(self.name.encode())
        for part in self.parts:
            digest.update(repr((part.name, part.texture)).encode())
            if part.tint is not None:  # only then: procedural scenes keep their fingerprints
                digest.update(repr(part.tint).encode())
            for array in (part.vertices, part.faces, part.uv, part.vertex_colors):
                if array is not None:
                    digest.update(repr(array.shape).encode())
                    digest.update(np.ascontiguousarray(array).tobytes())
        for key in sorted(self.textures):
            digest.update(key.encode())
            digest.update(repr(self.textures[key].shape).encode())
            digest.update(np.ascontiguousarray(self.textures[key]).tobytes())
        return digest.hexdigest()
