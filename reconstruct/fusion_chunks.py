"""Fusion of a large flight in chunks of views, at full map size, within a memory budget.

COLMAP's fusion holds every view it fuses (image, depth, normal map, mask: ~16 MB a 1024 x 768
view). Above the budget, the views are cut in flight order into chunks: each chunk's *own* views
plus the views its own views overlap most (COLMAP's ``check_num_images`` neighbours by shared
sparse points, the ones its fusion walks to). Each chunk is fused by COLMAP; a fused point is kept
by the chunk that owns the most of the views it was fused from (``owning_chunk``). Near a chunk
boundary a surface can come out of two chunks (each fused it from a different subset of views):
on the 33-view box with chunks of 16, a third more points than one pass, all on the same surfaces.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import scipy.sparse


@dataclass(frozen=True)
class FusionChunk:
    """Indices (into the flight's view list) of a chunk's own views and of its neighbour views."""

    own: np.ndarray
    neighbours: np.ndarray

    @property
    def views(self) -> np.ndarray:
        return np.concatenate([self.own, self.neighbours])


def shared_points(sparse_dir: Path, names: list[str]) -> scipy.sparse.csr_matrix:
    """(V, V) number of sparse points each pair of ``names`` both observe (diagonal zero)."""
    rec = pycolmap.Reconstruction(sparse_dir)
    index = {name: i for i, name in enumerate(names)}
    view_of_image = {image_id: index.get(image.name, -1) for image_id, image in rec.images.items()}
    rows, cols = [], []
    for k, point in enumerate(rec.points3D.values()):
        for element in point.track.elements:
            view = view_of_image.get(element.image_id, -1)
            if view >= 0:
                rows.append(view)
                cols.append(k)
    seen = scipy.sparse.csr_matrix(
        (np.ones(len(rows), dtype=np.float32), (rows, cols)), shape=(len(names), max(cols, default=-1) + 1)
    )
    seen.data[:] = 1.0  # a view that sees a point twice counts it once
    shared = (seen @ seen.T).tocsr()
    shared.setdiag(0)
    shared.eliminate_zeros()
    return shared


def top_neighbours(shared: scipy.sparse.csr_matrix, count: int) -> list[np.ndarray]:
    """Each view's ``count`` views with the most shared points (fewer when it overlaps fewer)."""
    neighbours = []
    for v in range(shared.shape[0]):
        start, end = shared.indptr[v], shared.indptr[v + 1]
        cols, counts = shared.indices[start:end], shared.data[start:end]
        order = np.lexsort((cols, -counts))[:count]
        neighbours.append(cols[order])
    return neighbours


def plan_chunks(neighbours: list[np.ndarray], max_views: int) -> list[FusionChunk]:
    """Consecutive runs of views, each with its own views' neighbours, at most ``max_views`` views
    in all."""
    if max_views < 1 + max((len(n) for n in neighbours), default=0):
        raise ValueError(f"fusion chunks: max_views {max_views} cannot hold a view and its neighbours")
    chunks, v, n = [], 0, len(neighbours)
    while v < n:
        own: list[int] = []
        members: set[int] = set()
        while v < n:
            grown = members | {v} | set(neighbours[v].tolist())
            if own and len(grown) > max_views:
                break
            own.append(v)
            members = grown
            v += 1
        own_arr = np.array(own)
        chunks.append(FusionChunk(own_arr, np.array(sorted(members - set(own)), dtype=int)))
    return chunks


def model_image_names(sparse_dir: Path) -> list[str]:
    """Image names in the order COLMAP's dense workspace indexes them (by image id)."""
    rec = pycolmap.Reconstruction(sparse_dir)
    return [rec.image(image_id).name for image_id in sorted(rec.reg_image_ids())]


def read_visibility(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP's ``<ply>.vis``: per fused point the number of views it was fused from, and all
    their workspace image indices, one point after the other."""
    raw = np.fromfile(path, dtype=np.uint8)
    n_points = int(raw[:8].view(np.uint64)[0])
    words = raw[8:].view(np.uint32)
    counts = np.empty(n_points, dtype=np.int64)
    flat = words.tolist()
    position = 0
    for k in range(n_points):
        counts[k] = flat[position]
        position += 1 + flat[position]
    if position != len(words):
        raise ValueError(f"{path}: {len(words)} words, its {n_points} points account for {position}")
    is_count = np.zeros(len(words), dtype=bool)
    is_count[np.cumsum(np.concatenate([[0], counts[:-1] + 1])).astype(np.int64)] = True
    return counts, words[~is_count].astype(np.int64)


def owning_chunk(counts: np.ndarray, indices: np.ndarray, chunk_of: np.ndarray, n_chunks: int) -> np.ndarray:
    """Per fused point, the chunk that owns the most of the views it was fused from (ties: the
    earlier chunk). ``chunk_of`` maps a workspace image index to the chunk owning that view."""
    point = np.repeat(np.arange(len(counts)), counts)
    votes = np.zeros((len(counts), n_chunks), dtype=np.int64)
    np.add.at(votes, (point, chunk_of[indices]), 1)
    return np.argmax(votes, axis=1)
