"""The scene as the viewport's main thread knows it: the last snapshot, and the vertex positions
the G-buffer draws. A moved object is re-placed here from its object-space vertices (never in a
snapshot the worker holds) and sent to the worker as a `MoveVertices` edit; anything a move
cannot express (instances, mirroring, new topology) is a full snapshot.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import sync, updates
from .worker_messages import FullScene, MoveVertices, SetShading


class SceneMirror:
    """The scene as the main thread knows it: the last snapshot, and the vertex positions the
    G-buffer draws (moved objects are updated in place here, never in a snapshot the worker holds).
    """

    def __init__(self):
        self.snapshot = None
        self.structure = None
        self.geometry_gen = 0  # bumped whenever the G-buffer's geometry changes
        self.gpu_dirty = None  # None | "positions" | "full": what the G-buffer must re-upload
        self._matrices: dict = {}
        self._ids: dict = {}  # name -> `updates.object_id` at the full sync
        self._local: dict = {}
        self._positions = None
        self._normals = None
        self._tangents = None

    def full_sync(self, depsgraph):
        """Snapshot the whole scene; returns the worker edit."""
        # A world map still baking reads as its uniform colour until `ViewportSession.poll_world`.
        self.snapshot = sync.snapshot_from_depsgraph(depsgraph, wait_for_world=False)
        self.structure = updates.scene_structure(depsgraph)
        # Placement of every plain (non-instanced) object: moves are applied relative to it.
        self._matrices = updates.plain_object_matrices(depsgraph)
        self._ids = updates.plain_object_ids(depsgraph)
        self._local.clear()
        self._positions = self._normals = self._tangents = None
        self.geometry_gen += 1
        self.gpu_dirty = "full"
        return FullScene(self.snapshot)

    def move(self, name: str, matrix: np.ndarray, object_id=None):
        """Edit for a plain object now placed by `matrix`: a MoveVertices, () when the object has
        no triangles, or None when only a full sync can express the change (instances, mirroring,
        a name that belonged to another object at the full sync: `object_id` differs)."""
        if name not in self._matrices:
            return None
        if object_id is not None and self._ids.get(name) != object_id:
            return None
        if not _invertible(self._matrices[name][:3, :3]):
            # Placed flat at the full sync (a scale of 0): its vertices there cannot be taken
            # back to object space, and its collapsed triangles are not in the snapshot at all.
            return None
        local = self._local.get(name)
        if local is None:
            local = self._local[name] = self._object_local(name)
        if local is None:
            return ()  # no triangles in the snapshot: nothing to move
        indices, pos_local, nrm_local, det_sign, tan_local = local
        linear = matrix[:3, :3]
        det = np.linalg.det(linear)
        if not np.isfinite(det) or abs(det) < 1e-30 or np.sign(det) != det_sign:
            return None  # degenerate or mirrored: the winding changes, the full sync handles it
        positions = (pos_local @ linear.T + matrix[:3, 3]).astype(np.float32)
        normals = nrm_local @ np.linalg.inv(linear)
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        normals = normals.astype(np.float32)
        if self._positions is None:
            self._positions = self.snapshot.geometry.positions.copy()
            self._normals = self.snapshot.geometry.normals.copy()
        rotated = not np.allclose(normals, self._normals[indices], atol=1e-6)
        self._positions[indices] = positions
        self._normals[indices] = normals
        if tan_local is not None:
            # Normal-map tangents turn with the object (the G-buffer's full upload carries them).
            if self._tangents is None:
                self._tangents = self.snapshot.geometry.tangents.copy()
            tangents = tan_local[:, :3] @ linear.T
            length = np.linalg.norm(tangents, axis=1, keepdims=True)
            tangents = np.divide(tangents, length, out=np.zeros_like(tangents), where=length > 0).astype(np.float32)
            rotated = rotated or not np.allclose(tangents, self._tangents[indices, :3], atol=1e-6)
            self._tangents[indices, :3] = tangents
        # The G-buffer can replace its positions alone; new normals need a full upload.
        self.gpu_dirty = "full" if rotated or self.gpu_dirty == "full" else "positions"
        self.geometry_gen += 1
        return MoveVertices(indices, positions.copy(), normals.copy())

    def _object_local(self, name: str):
        """(vertex indices, object-space positions and normals, det sign) of an object, from the
        snapshot and the matrix of the full sync (so repeated moves never accumulate error)."""
        snap = self.snapshot
        names = [o.name for o in snap.objects]
        if name not in names:
            return None
        g = snap.geometry
        indices = np.unique(g.triangles[g.object_index == names.index(name)])
        if indices.size == 0:
            return None
        m0 = self._matrices[name]
        linear0 = m0[:3, :3]
        pos_local = (g.positions[indices].astype(np.float64) - m0[:3, 3]) @ np.linalg.inv(linear0).T
        # World normals are local normals times inv(linear0): undo it.
        nrm_local = g.normals[indices].astype(np.float64) @ linear0
        tan_local = None
        if g.tangents is not None:
            tan_local = g.tangents[indices].astype(np.float64)
            tan_local[:, :3] = tan_local[:, :3] @ np.linalg.inv(linear0).T
        return indices, pos_local, nrm_local, np.sign(np.linalg.det(linear0)), tan_local

    def set_shading(self, lights=None, world=None, materials=None):
        snap = self.snapshot
        self.snapshot = dataclasses.replace(
            snap,
            lights=snap.lights if lights is None else lights,
            world=snap.world if world is None else world,
            materials=snap.materials if materials is None else materials,
        )
        if materials is not None:
            self.gpu_dirty = "full"  # material colours are the G-buffer's per-draw constants
        return SetShading(lights=lights, world=world, materials=materials)

    def gpu_snapshot(self):
        """The snapshot with the positions, normals and tangents the G-buffer must draw."""
        if self._positions is None:
            return self.snapshot
        tangents = self._tangents if self._tangents is not None else self.snapshot.geometry.tangents
        geometry = dataclasses.replace(self.snapshot.geometry, positions=self._positions, normals=self._normals,
                                       tangents=tangents)
        return dataclasses.replace(self.snapshot, geometry=geometry)

    @property
    def gpu_positions(self):
        return self._positions if self._positions is not None else self.snapshot.geometry.positions


#: Condition number of an object's 3x3 placement above which its object-space vertices are not
#: recovered from the world-space ones (a scale of 0, or 1e-6 of the other axes').
MAX_CONDITION = 1e6


def _invertible(linear: np.ndarray) -> bool:
    return bool(np.isfinite(linear).all()) and float(np.linalg.cond(linear)) < MAX_CONDITION
