"""The spanning stage of pair selection, on arrays: input checks, a tie-stable maximum spanning
forest (Kruskal), connected components, and tree path lengths (rooted forest, lowest common
ancestors).

Images are nodes, candidate pairs are edges: ``num_images`` and ``edges: (E, 2) int64`` with
``i < j``, unique. Everything is deterministic: ties are broken by edge index, then image index.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import breadth_first_order
from scipy.sparse.csgraph import connected_components as _scipy_components

# ----------------------------------------------------------------------------------------
# Input checks
# ----------------------------------------------------------------------------------------


def _check_graph(num_images: int, edges: np.ndarray) -> np.ndarray:
    """Validate ``edges`` against ``num_images``; return them as (E, 2) int64."""
    if int(num_images) != num_images or num_images < 0:
        raise ValueError(f"num_images must be a non-negative integer, got {num_images}")
    edges = np.asarray(edges)
    if edges.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    if edges.ndim != 2 or edges.shape[1] != 2 or not np.issubdtype(edges.dtype, np.integer):
        raise ValueError(f"edges must be an (E, 2) integer array, got {edges.shape} {edges.dtype}")
    edges = edges.astype(np.int64)
    if edges.min() < 0 or edges.max() >= num_images:
        raise ValueError(f"edges hold image indices outside [0, {num_images})")
    if np.any(edges[:, 0] >= edges[:, 1]):
        bad = edges[np.flatnonzero(edges[:, 0] >= edges[:, 1])[0]]
        raise ValueError(
            f"edges must have i < j (no self pairs, canonical order); got {bad.tolist()}"
        )
    keys = edges[:, 0] * num_images + edges[:, 1]
    if np.unique(keys).size != keys.size:
        raise ValueError("edges contain duplicate pairs")
    return edges


def _check_per_edge(name: str, values: np.ndarray, num_edges: int) -> np.ndarray:
    values = np.asarray(values)
    if values.shape != (num_edges,):
        raise ValueError(f"{name} must have shape ({num_edges},), got {values.shape}")
    return values


# ----------------------------------------------------------------------------------------
# Spanning forest and components
# ----------------------------------------------------------------------------------------


def maximum_spanning_forest(num_images: int, edges: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Kruskal's maximum spanning forest.

    Args:
        num_images: number of nodes N.
        edges: (E, 2) int64, ``i < j``, unique.
        weight: (E,) float64, finite.
    Returns:
        (N - C,) int64 indices into ``edges`` of the forest's edges, ascending; C is the
        number of connected components (isolated images included). Edges are taken by
        weight descending, equal weights by lower edge index first.
    """
    edges = _check_graph(num_images, edges)
    weight = _check_per_edge("weight", weight, len(edges)).astype(np.float64)
    if not np.all(np.isfinite(weight)):
        raise ValueError("weight must be finite")
    order = np.lexsort((np.arange(len(edges)), -weight))
    parent = list(range(num_images))
    size = [1] * num_images

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]  # path halving
            x = parent[x]
        return x

    chosen: list[int] = []
    ends = edges.tolist()
    for e in order.tolist():
        ri, rj = find(ends[e][0]), find(ends[e][1])
        if ri == rj:
            continue
        if size[ri] < size[rj]:
            ri, rj = rj, ri
        parent[rj] = ri
        size[ri] += size[rj]
        chosen.append(e)
        if len(chosen) == num_images - 1:
            break
    return np.sort(np.asarray(chosen, dtype=np.int64))


def _adjacency(num_nodes: int, edges: np.ndarray) -> coo_matrix:
    data = np.ones(len(edges), dtype=np.int8)
    return coo_matrix((data, (edges[:, 0], edges[:, 1])), shape=(num_nodes, num_nodes))


def connected_components(num_images: int, edges: np.ndarray) -> np.ndarray:
    """Connected-component label per image.

    Args:
        num_images: number of images N; an image without edges is its own component.
        edges: (E, 2) int64 image pairs.
    Returns:
        (N,) int64 labels ``0..C-1``: component 0 is the largest, equal sizes are ordered
        by their smallest image index.
    """
    edges = _check_graph(num_images, edges)
    if num_images == 0:
        return np.zeros(0, dtype=np.int64)
    _, raw = _scipy_components(_adjacency(num_images, edges), directed=False)
    sizes = np.bincount(raw)
    first = np.full(len(sizes), num_images, dtype=np.int64)
    np.minimum.at(first, raw, np.arange(num_images))
    order = np.lexsort((first, -sizes))
    relabel = np.empty(len(sizes), dtype=np.int64)
    relabel[order] = np.arange(len(sizes))
    return relabel[raw]


# ----------------------------------------------------------------------------------------
# Tree paths
# ----------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RootedForest:
    """A spanning forest rooted at each tree's smallest image, with binary-lifting tables.

    Attributes:
        parent: (N,) int64 parent image; a root is its own parent.
        depth: (N,) int64 tree edges from the root.
        tree_id: (N,) int64 tree label (as :func:`connected_components`).
        ancestors: (K, N) int64, ``ancestors[k, v]`` is the ``2**k``-th ancestor of ``v``
            (the root when the tree is shallower).
    """

    parent: np.ndarray
    depth: np.ndarray
    tree_id: np.ndarray
    ancestors: np.ndarray

    @classmethod
    def from_edges(cls, num_images: int, tree_edges: np.ndarray) -> RootedForest:
        """Root the forest given by ``tree_edges: (N - C, 2) int64``; ValueError on cycles."""
        tree_edges = _check_graph(num_images, tree_edges)
        tree_id = connected_components(num_images, tree_edges)
        num_trees = int(tree_id.max()) + 1 if num_images else 0
        if len(tree_edges) != num_images - num_trees:
            raise ValueError("tree_edges contain a cycle: they are not a forest")
        roots = np.full(num_trees, num_images, dtype=np.int64)
        np.minimum.at(roots, tree_id, np.arange(num_images))
        # One BFS from a virtual node N linked to every root roots all trees at once.
        super_root = np.full(num_trees, num_images, dtype=np.int64)
        linked = np.concatenate([tree_edges, np.stack([roots, super_root], axis=1)])
        _, pred = breadth_first_order(
            _adjacency(num_images + 1, linked), num_images, directed=False, return_predecessors=True
        )
        index = np.arange(num_images)
        parent = pred[:num_images].astype(np.int64)
        parent[parent == num_images] = index[parent == num_images]
        # Pointer jumping: after k rounds `jump` is the 2**k-th ancestor, `dist` the edges to it.
        levels = max(1, int(num_images - 1).bit_length())
        dist = (parent != index).astype(np.int64)
        jump = parent
        table = []
        for _ in range(levels):
            table.append(jump)
            dist, jump = dist + dist[jump], jump[jump]
        return cls(parent=parent, depth=dist, tree_id=tree_id, ancestors=np.stack(table))

    def lca(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(Q,) int64 lowest common ancestors of images ``u, v: (Q,)`` in the same tree."""
        u = np.asarray(u, dtype=np.int64).copy()
        v = np.asarray(v, dtype=np.int64).copy()
        swap = self.depth[u] < self.depth[v]
        u[swap], v[swap] = v[swap], u[swap]
        diff = self.depth[u] - self.depth[v]
        for k, up in enumerate(self.ancestors):
            bit = ((diff >> k) & 1).astype(bool)
            u[bit] = up[u[bit]]
        for up in self.ancestors[::-1]:
            differ = up[u] != up[v]
            u[differ], v[differ] = up[u[differ]], up[v[differ]]
        return np.where(u == v, u, self.parent[u])

    def path_lengths(self, pairs: np.ndarray) -> np.ndarray:
        """Tree edges between the images of each pair.

        Args:
            pairs: (Q, 2) int image indices.
        Returns:
            (Q,) float64; ``inf`` where the two images lie in different trees. A non-tree
            edge with path length L closes a cycle of L + 1 edges.
        """
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        out = np.full(len(pairs), np.inf)
        same = self.tree_id[pairs[:, 0]] == self.tree_id[pairs[:, 1]]
        u, v = pairs[same, 0], pairs[same, 1]
        out[same] = self.depth[u] + self.depth[v] - 2 * self.depth[self.lca(u, v)]
        return out

    def diameter(self) -> int:
        """Longest tree path in the forest (tree edges); 0 without edges."""
        num_images = len(self.parent)
        if num_images == 0:
            return 0
        # The deepest image of a tree is one end of a longest path of that tree.
        order = np.lexsort((np.arange(num_images), -self.depth, self.tree_id))
        first = np.ones(num_images, dtype=bool)
        first[1:] = self.tree_id[order[1:]] != self.tree_id[order[:-1]]
        deepest = np.empty(self.tree_id.max() + 1, dtype=np.int64)
        deepest[self.tree_id[order[first]]] = order[first]
        ends = np.stack([deepest[self.tree_id], np.arange(num_images)], axis=1)
        return int(self.path_lengths(ends).max())


def tree_path_lengths(num_images: int, tree_edges: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(Q,) float64 tree edges between the images of each of ``pairs: (Q, 2)``; inf across trees."""
    return RootedForest.from_edges(num_images, tree_edges).path_lengths(pairs)


def take_capped_per_view(ranked: np.ndarray, edges: np.ndarray, budget: int, max_per_view: int) -> list[int]:
    """The first ``budget`` of ``ranked`` (indices into ``edges: (E, 2)``, best first), skipping an
    edge once one of its images is already in ``max_per_view`` taken edges."""
    count: dict[int, int] = {}
    taken: list[int] = []
    for e in np.asarray(ranked).tolist():
        if len(taken) == budget:
            break
        i, j = int(edges[e][0]), int(edges[e][1])
        if count.get(i, 0) < max_per_view and count.get(j, 0) < max_per_view:
            count[i] = count.get(i, 0) + 1
            count[j] = count.get(j, 0) + 1
            taken.append(e)
    return taken
