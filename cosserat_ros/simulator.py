"""The cloth simulator: rest shape, material, state, forces and time stepping.

This module imports no ROS package: scripts, tests and benchmarks use it directly, and
``cosserat_ros.node`` is a thin layer over it.

Example::

    from cosserat_ros.mesh import grid_mesh
    from cosserat_ros.simulator import ClothSimulator, Material
    sim = ClothSimulator(grid_mesh(40, 40), Material(zeta=100.0, xi=1e-5, phi=0.0,
                                                     density=0.2, damping=0.05), dt=2e-4)
    sim.gravity = (0.0, 0.0, -9.81)
    sim.pin([0, 40])
    sim.step(1000)
    print(sim.energy()['total'])

Units are SI throughout: positions [m], velocities [m/s], forces [N], energies [J],
accelerations [m/s^2], time [s].
"""
from __future__ import annotations

import math
from typing import Dict, Optional
import warnings

import numba
import numpy as np

from . import forces as _forces
from .constants import (CRITICAL_DT_SAFETY, DIVERGENCE_SPEED_FACTOR, JET_STABILIZATION,
                        TILE_VERTICES, VERTEX_CHUNK, FUSE_MIN_VERTICES)
from .forces import DIVERGENCE_METHODS
from .geometry import (build_jet_operator, compute_geometry, CURVATURE_ESTIMATORS,
                       Geometry)
from .integrator import (METHOD_COVARIANT, METHOD_VARIATIONAL, run_covariant,
                         run_fused, run_tiled, run_variational, stability_limit,
                         variational_forces)
from .material import Material
from .mesh import ClothMesh
from .simd import LANES
from .workshare import start_threads, usable_cpus

__all__ = ['ClothSimulator', 'Material', 'SimulationDiverged', 'steps_tiled']


class SimulationDiverged(RuntimeError):
    """A step produced a non-finite value or a physically impossible speed.

    The simulator has been put back to the state it had before the failing ``step`` call.
    Attributes: ``step`` (the global step index that diverged), ``time`` [s] and ``hint``.
    """

    def __init__(self, step: int, time: float, hint: str):
        self.step = step
        self.time = time
        self.hint = hint
        super().__init__(f'simulation diverged at step {step} (t = {time:.6g} s): {hint}')


def steps_tiled(n_vertices: int, phi: float, divergence: str = 'variational') -> bool:
    """Whether :meth:`ClothSimulator.step` runs the tiled step (``integrator.run_tiled``)
    on a mesh of ``n_vertices`` with coupling ``phi``: the variational force without
    coupling, from ``FUSE_MIN_VERTICES`` vertices on (the simulator's own ``_tiled`` and
    phi; ``test_tiled_step.py`` checks that the two agree)."""
    return divergence == 'variational' and phi == 0.0 and n_vertices >= FUSE_MIN_VERTICES


def _sym3(t: np.ndarray) -> np.ndarray:
    """(n,2,2) symmetric -> (n,3) as (11, 12, 22)."""
    return np.ascontiguousarray(np.stack([t[:, 0, 0], t[:, 0, 1], t[:, 1, 1]], axis=1))


def _as_vec3(value, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64) if not isinstance(value, str) else None
    if arr is None or arr.shape != (3,):
        raise ValueError(f'{name} must be 3 numbers, got {value!r}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be finite, got {value!r}')
    return arr


class ClothSimulator:
    """Elastic Cosserat surface on a triangle mesh, integrated explicitly (Eq. 29).

    Parameters
    ----------
    mesh : ClothMesh
        The rest shape (flat or curved, open or closed).
    material : Material
        Constants zeta, xi, phi, density, damping (SI units).
    dt : float
        Time step [s]; a warning is issued when it exceeds :meth:`critical_dt`.
    divergence : {"variational", "covariant"}
        Discretisation of the internal force N^a|_a: the exact negative gradient of the
        discrete energy (default; any boundary), or the seed's covariant derivatives
        (comparison only; needs every boundary vertex pinned).
    check_dt : bool
        Compare ``dt`` with :meth:`critical_dt` on construction (costs ~100 force
        evaluations) and warn when it is too large.
    simd : bool
        Run the vertex pass four vertices per SIMD vector (default). False runs it one
        vertex at a time, the same formulas; kept for tests and comparison.
    """

    def __init__(self, mesh: ClothMesh, material: Material, dt: float = 2e-4,
                 divergence: str = 'variational', check_dt: bool = True, simd: bool = True):
        if not isinstance(mesh, ClothMesh):
            raise ValueError(f'mesh must be a ClothMesh, got {type(mesh).__name__}')
        if not isinstance(material, Material):
            raise ValueError(f'material must be a Material, got {type(material).__name__}')
        if divergence not in DIVERGENCE_METHODS:
            raise ValueError(f'divergence must be one of {DIVERGENCE_METHODS}, '
                             f'got {divergence!r}')
        self.mesh = mesh
        self._divergence = divergence
        self._method = METHOD_VARIATIONAL if divergence == 'variational' else METHOD_COVARIANT
        n, m = mesh.n_vertices, mesh.n_faces
        self._jet = build_jet_operator(mesh)
        self._rest_geometry: Dict[str, Geometry] = {}
        rest = self._rest('jet')
        self._rest_a = _sym3(rest.metric)
        self._ainv = _sym3(np.linalg.inv(rest.metric))
        self._rest_b = _sym3(rest.curvature)
        self._dinv, self._K = self._face_charts()
        # the vertex strain average's corner maps in vertex-face order, weighted by
        # area_t / (3 A_i): epsbar_i = sum_q vf_K[q]^T eps_t vf_K[q] (forces.py)
        vf_w = np.sqrt(mesh.face_areas[mesh.vf_face] / (3.0 * mesh.dual_areas[
            np.repeat(np.arange(n), np.diff(mesh.vf_ptr))]))
        self._vf_K = np.ascontiguousarray(
            (self._K[mesh.vf_face, mesh.vf_corner] * vf_w[:, None, None]).reshape(-1, 4))
        self._stab = np.zeros(n)
        st_sigma = np.zeros(len(self._jet.st_idx))
        st_uv = np.ascontiguousarray(self._jet.st_x.T)
        _forces.jet_normal_residuals(mesh.vertices, self._jet.st_ptr, self._jet.st_idx,
                                     self._jet.st_w, st_uv, st_sigma)
        frames = self._jet.frames
        src = np.repeat(np.arange(n), np.diff(self._jet.st_ptr))
        self._st_T = np.ascontiguousarray(
            np.einsum('kax,kbx->kab', frames[src, :2], frames[self._jet.st_idx, :2]))
        # the vertex pass reads the stencils in lane order (forces.lane_layout: groups of
        # four vertices with interleaved entries, for the SIMD lanes; weight blocks shared
        # by groups with the same stencil templates, and blocks of neighbour offsets and
        # rest residuals shared by groups where those are equal); its stencil gradients
        # come out in that order, so the transposed stencil points there too
        (g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, pos, wsrc, ln_idx,
         ln_sigma) = _forces.lane_layout(self._jet.st_ptr, self._jet.template,
                                         self._jet.st_idx, st_sigma, LANES if simd else 1)
        ln_w = np.ascontiguousarray(self._jet.st_w[:, wsrc])
        ln_uv = np.ascontiguousarray(st_uv[:, wsrc])
        # ops: the CSR stencils (st_ptr, st_idx, st_w) serve the covariant route; the
        # vertex pass reads ln_* (uv and sigma in its kernels' st_uv, st_sigma slots,
        # ln_idx in the st_idx slot) and the transposed stencil points into its entry
        # order
        # ... and the gathers read 32-bit indices: the stencil gradients' positions and one
        # row 3 face + corner of fgrad (m, 3, 3) per vertex-face pair
        if max(len(self._jet.st_idx), 3 * m) > np.iinfo(np.uint32).max:
            raise ValueError(f'mesh too large: {m} faces and {len(self._jet.st_idx)} '
                             'stencil entries, the step indexes them with 32 bits')
        vf_row = (3 * mesh.vf_face + mesh.vf_corner).astype(np.uint32)
        self._ops = (mesh.faces, self._dinv, mesh.face_areas, self._K, mesh.dual_areas,
                     self._ainv, self._rest_b, self._jet.st_ptr, self._jet.st_idx,
                     self._jet.st_w, ln_uv, ln_sigma, self._stab,
                     self._jet.tr_ptr, pos[self._jet.tr_slot].astype(np.uint32),
                     mesh.vf_ptr, mesh.vf_face, vf_row, self._vf_K,
                     g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, ln_idx, ln_w)
        self._cov = (self._rest_a, self._st_T)
        # the energy's fields (forces.vertex_fields) read the stencils in plain CSR order:
        # the rest residuals in that order too, the weights and chart coordinates in a
        # block per stencil template (equal to the bit for the vertices that share it,
        # geometry.build_jet_operator), and its gather the transposed stencil's CSR
        # positions
        st_ptr = self._jet.st_ptr
        reps, tpl = np.unique(self._jet.template, return_inverse=True)
        size = np.diff(st_ptr)[reps]
        blk = np.zeros(len(reps) + 1, dtype=np.int64)
        np.cumsum(size, out=blk[1:])
        tsrc = np.repeat(st_ptr[reps] - blk[:-1], size) + np.arange(blk[-1])
        self._csr = (blk[tpl], np.ascontiguousarray(self._jet.st_w[:, tsrc]),
                     np.ascontiguousarray(st_uv[:, tsrc]), st_sigma,
                     self._jet.tr_slot.astype(np.uint32))
        nch = -(-n // VERTEX_CHUNK)
        # large meshes without coupling step tile by tile (integrator.run_tiled)
        self._tiled = n >= FUSE_MIN_VERTICES
        self._ops += self._schedule(nch, TILE_VERTICES, max(1, numba.get_num_threads()),
                                    self._tiled)
        # scratch slots per row: the largest lane group's stencil, padded by a cache line
        # so that rows in use by two threads never share one (false sharing)
        smax = -(-LANES * int(np.diff(self._jet.st_ptr).max()) // 8) * 8 + 8
        # eps, cstress, kap, epsbar, estab, fgrad, contrib, scratch (a row per chunk; the
        # tiled step uses the row of each part's first chunk), the work-sharing state (a
        # range per thread that numba may run: workshare.py), the update's sums per
        # chunk of vertices (integrator.integrate), and for the steps in one parallel
        # region (integrator.run_fused) the update's own work-sharing state and the
        # barrier's counter and the steps done
        self._work = (np.zeros((m, 3)), np.zeros((n, 3)),
                      np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n), np.zeros((m, 3, 3)),
                      np.zeros((3, len(self._jet.st_idx))),
                      np.zeros((nch, 5, smax)), np.zeros(numba.config.NUMBA_NUM_THREADS + 1,
                                                         dtype=np.int64),
                      np.zeros((nch, 3)),
                      np.zeros(numba.config.NUMBA_NUM_THREADS + 1, dtype=np.int64),
                      np.zeros(2, dtype=np.int64))
        # the internal force alone through run_fused (one step of dt = 0): its velocities
        # and sums, never read
        self._fscratch = (np.zeros((n, 3)), np.zeros(2))
        self._cwork = (np.zeros((n, 3, 3)), np.zeros((n, 2, 2, 2)), np.zeros((n, 2, 2)),
                       np.zeros((n, 2, 2)), np.zeros((n, 2, 3)))
        self._force = np.zeros((n, 3))
        self._x = mesh.vertices.copy()
        self._v = np.zeros((n, 3))
        self._pinned = np.zeros(n, dtype=bool)
        self._f_vertex = np.zeros((n, 3))
        self._force_field = np.zeros(3)
        self._gravity = np.zeros(3)
        self._acc = np.zeros(2)
        self._time = 0.0
        self._steps = 0
        self._critical_dt: Optional[float] = None
        self._material = material
        self._set_material_arrays(material)
        self._share_threads()
        self._dt = self._check_positive(dt, 'dt')
        if check_dt:
            self._warn_if_unstable(self._dt)

    # ------------------------------------------------------------------ set-up helpers
    def _schedule(self, nch: int, tile_vertices: int, parts: int, tiled: bool = True):
        """The step's work plan (integrator.vertex_parts), ops[27:41]:

        * ``tile_ch`` (T+1,): chunk boundaries of the tiles (a tile is a run of
          ``tile_vertices / VERTEX_CHUNK`` chunks; no tile spans two parts);
        * ``fc_ptr`` (nch+1,), ``fc_face`` (m,) uint32: the faces of each chunk
          (``tiled``: a face goes with the chunk of its latest corner; otherwise equal
          runs of faces, which measured 2-6% faster on small meshes);
        * ``gl_ptr`` (T+2,), ``gl_vert`` (n,): the vertices each tile completes (those whose
          contributors, the vertices whose stencils hold them and their incident faces,
          all lie in the tile's part and the last of them in the tile), then the seam (the
          rest), a permutation of all vertices;
        * ``part_tile`` (parts+1,): the tiles of each part (equal runs of chunks; one part
          per thread);
        * ``g_wptr``, ``tr_slot``, ``fc_slot``, ``vf_row``, ops[33:37]: where the tiled step
          writes each lane group's stencil gradients and each face's corner gradients, and
          where its gathers read them (:meth:`_rings`; without ``tiled`` ops[21], an empty
          array, fc_face and an empty array);
        * ops[37:41]: the faces' corners and rest shapes in chunk order
          (:meth:`_face_stream`).
        """
        n, faces = self.mesh.n_vertices, self.mesh.faces
        chunk = _forces.chunk_of_vertex(n, nch, self._ops[19], self._ops[22])
        face_chunk = (chunk[faces].max(axis=1) if tiled
                      else np.arange(len(faces)) // -(-len(faces) // nch))
        fc_face = np.argsort(face_chunk, kind='stable').astype(np.uint32)
        fc_ptr = np.zeros(nch + 1, dtype=np.int64)
        np.cumsum(np.bincount(face_chunk, minlength=nch), out=fc_ptr[1:])
        # first and last contributing chunk of every vertex
        src = np.repeat(chunk, np.diff(self._jet.st_ptr))
        first, last = chunk.copy(), chunk.copy()
        for idx, c in ((self._jet.st_idx, src), (faces.ravel(), np.repeat(face_chunk, 3))):
            np.minimum.at(first, idx, c)
            np.maximum.at(last, idx, c)
        part_ch = np.linspace(0, nch, parts + 1).round().astype(np.int64)
        per_tile = max(1, tile_vertices // VERTEX_CHUNK)
        starts = [np.arange(part_ch[p], part_ch[p + 1], per_tile) for p in range(parts)]
        part_tile = np.zeros(parts + 1, dtype=np.int64)
        np.cumsum([len(t) for t in starts], out=part_tile[1:])
        tile_ch = np.append(np.concatenate(starts), nch).astype(np.int64)
        ntile = len(tile_ch) - 1
        inner = (np.searchsorted(part_ch, first, 'right')
                 == np.searchsorted(part_ch, last, 'right'))
        key = np.where(inner, np.searchsorted(tile_ch, last, 'right') - 1, ntile)
        gl_vert = np.argsort(key, kind='stable').astype(np.int64)
        gl_ptr = np.zeros(ntile + 2, dtype=np.int64)
        np.cumsum(np.bincount(key, minlength=ntile + 1), out=gl_ptr[1:])
        plan = (tile_ch, fc_ptr, fc_face, gl_ptr, gl_vert, part_tile)
        if not tiled:       # the same types, so that the kernels compile once
            none = np.zeros(0, dtype=np.uint32)
            rings = (self._ops[21], none, fc_face, none)
        else:
            rings = self._rings(nch, tile_ch, part_tile, key, fc_ptr, fc_face)
        return plan + rings + self._face_stream(fc_face)

    def _rings(self, nch, tile_ch, part_tile, key, fc_ptr, fc_face):
        """Where the tiled step writes its gradients, and where its gathers read them:
        the lane groups' stencil gradients (``contrib``: ``g_wptr`` with column 2
        replaced, the transposed stencil's slots to match) and the faces' corner
        gradients (rows of ``fgrad``: ``fc_slot`` per face in chunk order, ``vf_row`` =
        3 slot + corner per vertex-face pair). The gathers' two index arrays are uint32.

        A group (a face) whose gradients are all gathered inside its part (every target
        vertex's contributors lie in that part, ``key`` < T) is dead once the last of
        those targets' tiles has gathered them; its slot is reused after that. Each part's
        such groups (faces) go, in the order the part writes them, round a ring
        (:meth:`_ring_slots`). So the step writes its gradients into a few hundred kB that
        stay in the core's cache, instead of streaming ~600 B per vertex out to memory and
        back (each store's line is read first). Those with a target on the seam (gathered
        after every part is done), the 5% read the latest after they are written, and the
        single vertices keep slots of their own. The forces are the same numbers,
        gathered in the same order."""
        g_vert, g_ptr, g_wptr = self._ops[19], self._ops[20], self._ops[21]
        st_ptr, st_idx = self._jet.st_ptr, self._jet.st_idx
        faces, vf_face = self.mesh.faces, self.mesh.vf_face
        K, m = len(st_idx), len(faces)
        tile_of_chunk = np.searchsorted(tile_ch, np.arange(nch), 'right') - 1
        w, tr = g_wptr, self._ops[14]
        if len(g_vert):
            size = np.diff(g_ptr)
            # the tile each group is written in and the last tile reading it
            g_tile = tile_of_chunk[np.arange(len(g_vert)) // -(-len(g_vert) // nch)]
            g_last = np.maximum.reduceat(key[st_idx], st_ptr[:-1])[g_vert].max(axis=1)
            # after the single vertices' entries, which keep their slots
            base, end = self._place(size, g_tile, g_last, part_tile, int(g_ptr[0]))
            if end <= K:        # else no room to spare (a tiny mesh): entry positions
                w = g_wptr.copy()
                w[:, 2] = base
                # position -> slot, for the transposed stencil (ops[14] holds positions):
                # a group's entry at g_ptr[g] + r goes to base[g] + r
                slot = np.arange(K, dtype=np.int64)
                slot[g_ptr[0]:] += np.repeat(base - g_ptr[:-1], size)
                tr = slot[self._ops[14]]
        f_tile = tile_of_chunk[np.repeat(np.arange(nch), np.diff(fc_ptr))]
        base, end = self._place(np.ones(m, dtype=np.int64), f_tile,
                                key[faces[fc_face]].max(axis=1), part_tile, 0)
        if end > m:
            base = fc_face.copy()      # each face its own row
        slot_of_face = np.empty(m, dtype=np.int64)
        slot_of_face[fc_face] = base
        # 32-bit: the gathers stream 4 bytes per index, and one index per face
        vf_row = 3 * slot_of_face[vf_face] + self.mesh.vf_corner
        return w, tr.astype(np.uint32), base.astype(np.uint32), vf_row.astype(np.uint32)

    def _face_stream(self, fc_face):
        """What the step's vertex pass reads of the faces, in its order (``fc_face``):
        ops[37:41] = their corners (m,3) uint32, and for each its row (m,) uint32 in a
        table of the distinct rest shapes (Dinv (T,2,2), area (T,)), in order of first
        use. Rows are equal when their bits are: the step computes the same numbers as
        from ``dinv`` and ``face_areas`` themselves. A structured sheet has a few dozen
        shapes (18 on the scene's grids), so the step streams 20 bytes per face (corners,
        row and ring slot) where it streamed 80 (int64 corners, Dinv, area, face and slot
        indices); an irregular mesh, whose table has a row per face, streams 60."""
        m = len(fc_face)
        shape = np.concatenate([self._dinv[fc_face].reshape(m, 4),
                                self.mesh.face_areas[fc_face, None]], axis=1)
        _, first, row = np.unique(shape.view(np.int64), axis=0, return_index=True,
                                  return_inverse=True)
        order = np.argsort(first)
        rank = np.empty(len(order), dtype=np.int64)
        rank[order] = np.arange(len(order))
        table = shape[first[order]]
        return (self.mesh.faces[fc_face].astype(np.uint32),
                rank[row.ravel()].astype(np.uint32),
                np.ascontiguousarray(table[:, :4].reshape(-1, 2, 2)),
                np.ascontiguousarray(table[:, 4]))

    def _place(self, size, tile, last, part_tile, start):
        """Slots for items (lane groups, faces) of ``size`` entries, written in order, in
        tiles ``tile``, last read at the end of tile ``last`` (T: the seam): those read
        inside their part, but for the 5% read the latest, go round a ring per part; the
        others get slots of their own from ``start`` on. Returns (slots, end)."""
        ntile = int(part_tile[-1])
        part = np.searchsorted(part_tile, tile, 'right') - 1
        ring = last < ntile
        # the few read much later than most (lanes far apart, e.g. along a boundary)
        # would set the ring's length alone
        if ring.any():
            ring &= last - tile <= int(np.quantile((last - tile)[ring], 0.95))
        base = np.empty(len(size), dtype=np.int64)
        own = np.nonzero(~ring)[0]
        base[own] = start + np.cumsum(size[own]) - size[own]
        end = start + int(size[own].sum())
        for p in range(len(part_tile) - 1):
            end = -(-end // 8) * 8          # each ring starts on a cache line of its own
            q = np.nonzero(ring & (part == p))[0]
            if len(q):
                lin, R = self._ring_slots(size[q], tile[q], last[q])
                base[q] = end + lin
                end += R
        return base, end

    @staticmethod
    def _ring_slots(size, tile, last):
        """Ring slots for groups of ``size`` entries written in order in tiles ``tile`` and
        read up to the end of tile ``last``: (slot of each group, ring length R). A
        group's slot is its place in the written sequence modulo R, moved to the ring's
        start if it would wrap; R is the smallest multiple of the largest group that
        keeps every group's entries until its last reader is done."""
        step = int(size.max())
        total = int(size.sum())
        R = step
        while True:
            if R >= total:
                return np.cumsum(size) - size, total
            if size.min() == step:      # equal sizes (faces): R is a multiple, no gaps
                lin = np.cumsum(size) - size
            else:
                lin = np.empty(len(size), dtype=np.int64)
                at = 0
                for q, m in enumerate(size.tolist()):
                    if at % R + m > R:
                        at += R - at % R
                    lin[q] = at
                    at += m
            # entries written up to the end of each tile, and the span each group needs
            done = np.maximum.accumulate(lin + size)
            upto = done[np.searchsorted(tile, last, 'right') - 1]
            need = int((upto - lin).max())
            if need <= R:
                return lin % R, R
            R = -(-need // step) * step

    def _rest(self, curvature: str) -> Geometry:
        if curvature not in self._rest_geometry:
            self._rest_geometry[curvature] = compute_geometry(self.mesh.vertices, self.mesh,
                                                              self._jet, curvature)
        return self._rest_geometry[curvature]

    def _face_charts(self):
        """Rest edge matrices: Dinv_t (m,2,2) in each triangle's orthonormal chart, and
        K_it = D_t U_it^-1 (m,3,2,2) from vertex charts to triangle charts."""
        X = self.mesh.vertices
        f = self.mesh.faces
        e1 = X[f[:, 1]] - X[f[:, 0]]
        e2 = X[f[:, 2]] - X[f[:, 0]]
        t1 = e1 / np.linalg.norm(e1, axis=1)[:, None]
        t2 = np.cross(self.mesh.face_normals, t1)
        D = np.stack([np.stack([np.einsum('mk,mk->m', e1, t1), np.einsum('mk,mk->m', e2, t1)],
                               axis=1),
                      np.stack([np.einsum('mk,mk->m', e1, t2), np.einsum('mk,mk->m', e2, t2)],
                               axis=1)], axis=1)
        frames = self._jet.frames[f]   # (m, 3 corners, 3 axes, 3)
        U = np.stack([np.stack([np.einsum('mck,mk->mc', frames[:, :, 0], e1),
                                np.einsum('mck,mk->mc', frames[:, :, 0], e2)], axis=-1),
                      np.stack([np.einsum('mck,mk->mc', frames[:, :, 1], e1),
                                np.einsum('mck,mk->mc', frames[:, :, 1], e2)], axis=-1)],
                     axis=2)           # (m, 3, 2, 2)
        K = np.einsum('mab,mcbd->mcad', D, np.linalg.inv(U))
        return np.ascontiguousarray(np.linalg.inv(D)), np.ascontiguousarray(K)

    def _set_material_arrays(self, material: Material):
        self._mat = np.array([material.zeta, material.xi, material.phi])
        # jet hourglass control c_i omega = s xi A_i / h_i^4 / S_i (S_i stencil entries
        # besides the centre; see forces.py), in place: the
        # compiled operators hold this array
        self._stab[:] = (JET_STABILIZATION * material.xi * self.mesh.dual_areas
                         / self._jet.radius ** 4 / (np.diff(self._jet.st_ptr) - 1))
        self._mass = material.density * self.mesh.dual_areas
        self._damp = material.damping * self.mesh.dual_areas
        self._vmax = DIVERGENCE_SPEED_FACTOR * material.wave_speed + 100.0
        self._update_applied()

    def _update_applied(self):
        self._f_applied = self._f_vertex + self._mass[:, None] * self._force_field[None, :]

    def _share_threads(self) -> int:
        """Set the work-sharing states' range count (``work[8][0]``, ``work[10][0]``,
        workshare.py) to the threads numba runs now; called from Python before the compiled
        passes that share their work, because ``numba.get_num_threads()`` in compiled code
        makes numba refuse to cache the kernel. A stale count gives the same numbers, only
        slower.

        Returns the thread count for the steps in one parallel region
        (``integrator.run_fused``, which :meth:`step` and the critical dt's force then
        run), or 0 where it does not apply: any step but the variational one without
        coupling below the tiled step's size, or where its barrier could wait forever or spin
        away the time of the threads it waits for: each of its iterations must run on a
        thread of its own, at once, which numba's static schedule (no
        ``set_parallel_chunksize``) on the OpenMP or workqueue layer does, and each
        thread needs a CPU of its own (``workshare.usable_cpus``). numba picks its layer
        at the first parallel call (``workshare.start_threads``)."""
        nthr = numba.get_num_threads()
        self._work[8][0] = nthr
        self._work[10][0] = nthr
        fused = self._method == METHOD_VARIATIONAL and self._mat[2] == 0.0 \
            and not self._tiled
        return nthr if fused and start_threads() in ('omp', 'workqueue') \
            and numba.get_parallel_chunksize() == 0 and nthr <= usable_cpus() else 0

    @staticmethod
    def _check_positive(value, name: str) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating,
                                                             np.integer)):
            raise ValueError(f'{name} must be a number, got {value!r}')
        value = float(value)
        if not math.isfinite(value) or value <= 0:
            raise ValueError(f'{name} must be positive and finite, got {value!r}')
        return value

    def _indices(self, indices, name: str = 'indices') -> np.ndarray:
        arr = np.asarray(indices)
        n = self.mesh.n_vertices
        if arr.dtype == bool:
            if arr.shape != (n,):
                raise ValueError(f'a boolean {name} mask must have shape ({n},), '
                                 f'got {arr.shape}')
            return np.flatnonzero(arr)
        arr = np.atleast_1d(arr)
        if arr.ndim != 1:
            raise ValueError(f'{name} must be a 1-D list of vertex indices, got shape '
                             f'{arr.shape}')
        if arr.size == 0:
            return arr.astype(np.int64)
        if not np.issubdtype(arr.dtype, np.integer):
            if (np.issubdtype(arr.dtype, np.floating) and np.all(np.isfinite(arr))
                    and np.all(arr == np.round(arr))):
                arr = arr.astype(np.int64)
            else:
                raise ValueError(f'{name} must be integers, got {indices!r}')
        if arr.min() < 0 or arr.max() >= n:
            raise ValueError(f'{name} must lie in [0, {n - 1}], got range '
                             f'[{arr.min()}, {arr.max()}]')
        return arr.astype(np.int64)

    def _warn_if_unstable(self, dt: float):
        crit = self.critical_dt()
        if dt > crit:
            warnings.warn(f'dt = {dt:.3g} s exceeds the stable limit {crit:.3g} s of this '
                          'mesh and material: the explicit update will diverge',
                          RuntimeWarning, stacklevel=3)

    # ------------------------------------------------------------------ state
    @property
    def n_vertices(self) -> int:
        """Number of vertices."""
        return self.mesh.n_vertices

    @property
    def positions(self) -> np.ndarray:
        """Current positions (n, 3) [m] (a copy)."""
        return self._x.copy()

    def set_positions(self, x) -> None:
        """Set positions (n, 3) [m]; pinned vertices move too (to script a grasp)."""
        self._x[:] = self._checked_state(x, 'positions')

    @property
    def velocities(self) -> np.ndarray:
        """Current velocities (n, 3) [m/s] (a copy; at the half step of the leapfrog)."""
        return self._v.copy()

    def set_velocities(self, v) -> None:
        """Set velocities (n, 3) [m/s]; pinned vertices keep zero velocity."""
        arr = self._checked_state(v, 'velocities')
        arr[self._pinned] = 0.0
        self._v[:] = arr

    def _checked_state(self, value, name: str) -> np.ndarray:
        arr = np.array(value, dtype=np.float64)
        if arr.shape != (self.mesh.n_vertices, 3):
            raise ValueError(f'{name} must have shape ({self.mesh.n_vertices}, 3), '
                             f'got {arr.shape}')
        if not np.all(np.isfinite(arr)):
            raise ValueError(f'{name} must be finite')
        return arr

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        return self._time

    @property
    def step_count(self) -> int:
        """Number of steps taken since construction or :meth:`reset`."""
        return self._steps

    @property
    def dt(self) -> float:
        """Time step [s]."""
        return self._dt

    @dt.setter
    def dt(self, value: float):
        self._dt = self._check_positive(value, 'dt')

    @property
    def divergence(self) -> str:
        """The discretisation of N^a|_a in use."""
        return self._divergence

    @property
    def material(self) -> Material:
        """Material constants; assigning a new :class:`Material` takes effect at once."""
        return self._material

    @material.setter
    def material(self, material: Material):
        if not isinstance(material, Material):
            raise ValueError(f'material must be a Material, got {type(material).__name__}')
        self._material = material
        self._critical_dt = None
        self._set_material_arrays(material)

    @property
    def gravity(self) -> np.ndarray:
        """Gravitational acceleration g (3,) [m/s^2]; (0, 0, 0) by default."""
        return self._gravity.copy()

    @gravity.setter
    def gravity(self, g):
        self._gravity = _as_vec3(g, 'gravity')

    @property
    def force_field(self) -> np.ndarray:
        """Uniform external force per unit mass F (3,) [m/s^2], e.g. wind."""
        return self._force_field.copy()

    @force_field.setter
    def force_field(self, f):
        self._force_field = _as_vec3(f, 'force_field')
        self._update_applied()

    @property
    def pinned(self) -> np.ndarray:
        """Boolean mask (n,) of pinned vertices (a copy)."""
        return self._pinned.copy()

    def pin(self, indices) -> None:
        """Pin vertices (indices or a boolean mask): they keep their position."""
        idx = self._indices(indices)
        self._pinned[idx] = True
        self._v[idx] = 0.0

    def unpin(self, indices) -> None:
        """Release pinned vertices (indices or a boolean mask)."""
        self._pinned[self._indices(indices)] = False

    def set_vertex_forces(self, indices, forces) -> None:
        """Replace the external nodal forces [N]: ``forces`` (k, 3) on vertices ``indices``
        (k,). Repeated indices add up. Previous nodal forces are removed."""
        idx = self._indices(indices)
        f = np.asarray(forces, dtype=np.float64)
        if f.shape != (len(idx), 3):
            raise ValueError(f'forces must have shape ({len(idx)}, 3) for {len(idx)} '
                             f'indices, got {f.shape}')
        if not np.all(np.isfinite(f)):
            raise ValueError('forces must be finite')
        fv = np.zeros_like(self._f_vertex)
        np.add.at(fv, idx, f)
        self._f_vertex = fv
        self._update_applied()

    def clear_vertex_forces(self) -> None:
        """Remove all external nodal forces."""
        self._f_vertex = np.zeros_like(self._f_vertex)
        self._update_applied()

    @property
    def vertex_forces(self) -> np.ndarray:
        """External nodal forces currently applied (n, 3) [N] (a copy)."""
        return self._f_vertex.copy()

    def reset(self) -> None:
        """Back to the rest shape at rest: positions, velocities, time, step count and the
        energy-balance integrals. Pins, forces, gravity and material are kept."""
        self._x[:] = self.mesh.vertices
        self._v[:] = 0.0
        self._acc[:] = 0.0
        self._time = 0.0
        self._steps = 0

    # ------------------------------------------------------------------ dynamics
    def step(self, n: int = 1) -> None:
        """Advance ``n`` steps of size :attr:`dt` inside compiled code.

        Raises :class:`SimulationDiverged` (and restores the state from before this call)
        when a step produces a non-finite value or an impossible speed.
        """
        if isinstance(n, bool) or int(n) != n or n < 0:
            raise ValueError(f'n must be a non-negative integer, got {n!r}')
        n = int(n)
        if n == 0:
            return
        backup = (self._x.copy(), self._v.copy(), self._acc.copy())
        nthr = self._share_threads()
        args = (n, self._x, self._v, self._f_applied, self._mass, self._damp, self._pinned,
                self._gravity, self._dt, self._vmax ** 2, self._acc, self._ops)
        if nthr > 0:
            done = run_fused(*args, self._mat, self._work, self._force, nthr)
        elif self._method == METHOD_VARIATIONAL:
            run = run_tiled if self._tiled and self._mat[2] == 0.0 else run_variational
            done = run(*args, self._mat, self._work, self._force)
        else:
            done = run_covariant(*args, self._cov, self._mat, self._cwork, self._work,
                                 self._force)
        if done < n:
            self._x[:], self._v[:], self._acc[:] = backup
            crit = self.critical_dt()
            if self._dt > crit:
                hint = (f'dt = {self._dt:.3g} s is above the stable limit {crit:.3g} s; '
                        'reduce dt or soften the material')
            else:
                hint = ('a speed exceeded the elastic limit or a value became non-finite; '
                        'check the applied forces and the material, then reset')
            raise SimulationDiverged(self._steps + done + 1, self._time + (done + 1) * self._dt,
                                     hint)
        self._steps += n
        self._time += n * self._dt

    def internal_forces(self) -> np.ndarray:
        """Internal force N^a|_a integrated over each dual cell, (n, 3) [N], now."""
        out = np.zeros_like(self._force)
        self._internal(self._x, out)
        return out

    def _internal(self, x, out):
        nthr = self._share_threads()
        if nthr > 0:
            # the step's own kernel, one step of dt = 0 (x and v stay; the force is the
            # same to the bit), so that the process compiles the vertex code once
            v, acc = self._fscratch
            v[:] = 0.0
            run_fused(1, x.copy(), v, self._f_applied, self._mass, self._damp,
                      self._pinned, self._gravity, 0.0, np.inf, acc, self._ops,
                      self._mat, self._work, out, nthr)
        elif self._method == METHOD_VARIATIONAL:
            variational_forces(x, self._ops, self._mat, self._work, out)
        else:
            _forces.covariant_forces(x, self._ops, self._cov, self._mat, self._cwork, out)

    # ------------------------------------------------------------------ energy
    def energy_and_densities(self):
        """:meth:`energy` and :meth:`energy_densities` from one force evaluation."""
        f = np.empty_like(self._force)
        # the step stores no fields (face strains, kap, epsbar, residual energy): one pass
        # of their own fills them and the face and stencil gradients, the latter in CSR
        # order (the contrib and fgrad work arrays; the next step rewrites them), and the
        # force is the gather of those through the CSR transposed stencil
        eps, cstress, kap, epsbar, estab, fgrad, contrib, scratch = self._work[:8]
        o = self._ops
        wptr, w, uv, sigma, tr_slot = self._csr
        _forces.vertex_fields(self._x, o[0], o[1], o[2], self._mat[0], o[7], wptr, o[8], w, uv,
                              sigma, o[12], o[15], o[16], o[18], o[4], o[5], o[6],
                              self._mat[1], self._mat[2], scratch, contrib, fgrad, eps,
                              cstress, kap, epsbar, estab)
        if self._mat[2] != 0.0:
            _forces.face_coupling(self._x, o[0], o[1], o[2], o[3], cstress, fgrad)
        _forces.gather_forces(o[15], o[17], fgrad, o[13], tr_slot, contrib, f)
        if self._method != METHOD_VARIATIONAL:
            f = self.internal_forces()
        out = np.empty((self.mesh.n_vertices, 4))
        _forces.energy_densities(eps, kap, epsbar, estab, self.mesh.faces, self.mesh.face_areas,
                                 self.mesh.vf_ptr, self.mesh.vf_face, self.mesh.dual_areas,
                                 self._ainv, *self._mat, out)
        sums = np.empty(5)
        _forces.energy_totals(out, self.mesh.dual_areas, f, self._f_applied, self._mass,
                              self._damp, self._v, self._x, self._pinned, self._gravity,
                              self._dt, sums)
        dens = {'stretching': out[:, 0], 'bending': out[:, 1], 'coupling': out[:, 2],
                'total': out[:, 3]}
        stretching, bending, coupling, kinetic, gravity = (float(e) for e in sums)
        elastic = stretching + bending + coupling
        energy = {'kinetic': kinetic, 'stretching': stretching, 'bending': bending,
                  'coupling': coupling, 'elastic': elastic, 'gravity': gravity,
                  'external_work': float(self._acc[0]), 'dissipated': float(self._acc[1]),
                  'total': kinetic + elastic + gravity}
        return energy, dens

    def energy_densities(self) -> Dict[str, np.ndarray]:
        """Per-vertex energy densities [J/m^2] (seed Fig. 4): ``stretching``, ``bending``,
        ``coupling`` and ``total``, each (n,)."""
        return self.energy_and_densities()[1]

    def energy(self) -> Dict[str, float]:
        """Energies [J] of the current state and the running balance terms.

        ``kinetic`` uses the velocity synchronised with the positions (the leapfrog
        half-step correction v + dt/2 a), ``stretching``, ``bending``, ``coupling`` are the
        discrete elastic energy terms (``elastic`` their sum), ``gravity`` is
        -sum m g . x, ``total`` = kinetic + elastic + gravity. ``external_work`` (nodal
        forces and force field) and ``dissipated`` (damping) accumulate since the last
        reset, so ``total - total(0) ~ external_work - dissipated``.
        """
        return self.energy_and_densities()[0]

    # ------------------------------------------------------------------ inspection
    def geometry(self, curvature: str = 'jet') -> Geometry:
        """Per-vertex geometry of the current state (see :class:`Geometry`).

        ``curvature`` selects the curvature estimator: ``"jet"`` (cubic least-squares
        jet, convergent, default) or ``"seed"`` (normal differences along the 1-ring, the
        seed's Sec. 5.2; does not converge, kept for comparison).
        """
        if curvature not in CURVATURE_ESTIMATORS:
            raise ValueError(f'curvature must be one of {CURVATURE_ESTIMATORS}, '
                             f'got {curvature!r}')
        return compute_geometry(self._x, self.mesh, self._jet, curvature,
                                rest=self._rest(curvature))

    def resultants(self) -> Dict[str, np.ndarray]:
        """Per-vertex contact quantities from the vertex strains, for inspection:
        ``M`` = M^ab (n,2,2), ``N`` = N^ab (n,2,2) (Eq. 28), ``N3`` = N^3b = M^ba|_a (n,2),
        ``force_vectors`` N^b (n,2,3) (Eq. 26), and the material tensors ``Phi``, ``Psi``,
        ``Theta`` (n,2,2,2,2) of Eq. 19."""
        from .material import material_tensor
        basis, chris, mres, nres, nvec = (np.zeros_like(a) for a in self._cwork)
        _forces.covariant_resultants(self._x, self._jet.st_ptr, self._jet.st_idx,
                                     self._jet.st_w, self._rest_a, self._ainv, self._rest_b,
                                     *self._mat, basis, chris, mres, nres)
        _forces.covariant_force_vectors(self._jet.st_ptr, self._jet.st_idx, self._jet.st_w,
                                        self._st_T, basis, chris, mres, nres, nvec)
        n3 = np.einsum('nbk,nk->nb', nvec, basis[:, 2])
        A = self._rest('jet').metric
        mat = self._material
        return {'M': mres, 'N': nres, 'N3': n3, 'force_vectors': nvec,
                'Phi': material_tensor(mat.zeta, A), 'Psi': material_tensor(mat.xi, A),
                'Theta': material_tensor(mat.phi, A)}

    # ------------------------------------------------------------------ stability
    def critical_dt(self) -> float:
        """Largest stable time step [s] for this mesh and material (cached).

        The highest angular frequency omega_max of the linearised system around the rest
        shape is found by Lanczos iteration on M^-1/2 K M^-1/2 (K v from central
        differences of the internal force), and the damped symplectic Euler limit
        ``dt < (sqrt(gamma^2 + 4 omega^2) - gamma) / omega^2`` (gamma = rho/mu) is applied.
        For membranes omega_max ~ 2 c / h (c = sqrt(6 zeta/mu)), giving the rule of thumb
        dt <~ 0.8 h / c of model.md; bending adds ~ sqrt(D/mu) (k/h)^2 on fine meshes. The
        result is CRITICAL_DT_SAFETY (0.8) times that linear limit, because strained states
        pump energy into the highest modes near it (constants.py has the measurement).
        """
        if self._critical_dt is None:
            om = math.sqrt(self.max_eigenvalue())
            gamma = self._material.damping / self._material.density
            self._critical_dt = CRITICAL_DT_SAFETY * stability_limit(om, gamma)
        return self._critical_dt

    def max_eigenvalue(self, iterations: int = 60, seed: int = 0,
                       at: Optional[np.ndarray] = None) -> float:
        """omega_max^2 [1/s^2] of the free system linearised at rest, or at positions
        ``at`` (Lanczos, an upper estimate: largest Ritz value plus its residual)."""
        X = self.mesh.vertices if at is None else np.asarray(at, dtype=np.float64)
        n3 = 3 * self.mesh.n_vertices
        minv_sqrt = np.repeat(1.0 / np.sqrt(self._mass), 3)
        h = self.mesh.mean_edge_length
        f_p = np.empty_like(self._force)
        f_m = np.empty_like(self._force)

        def op(q):
            d = (minv_sqrt * q).reshape(-1, 3)
            eps = 1e-6 * h / max(np.abs(d).max(), 1e-300)
            self._internal(X + eps * d, f_p)
            self._internal(X - eps * d, f_m)
            return -minv_sqrt * ((f_p - f_m).ravel() / (2 * eps))

        k = min(iterations, n3)
        rng = np.random.default_rng(seed)
        Q = np.zeros((k + 1, n3))
        alpha = np.zeros(k)
        beta = np.zeros(k)
        q = rng.standard_normal(n3)
        Q[0] = q / np.linalg.norm(q)
        for j in range(k):
            w = op(Q[j])
            alpha[j] = Q[j] @ w
            w -= Q[:j + 1].T @ (Q[:j + 1] @ w)   # full re-orthogonalisation
            w -= Q[:j + 1].T @ (Q[:j + 1] @ w)
            beta[j] = np.linalg.norm(w)
            if beta[j] < 1e-12 * abs(alpha[j]) or j == k - 1:
                k = j + 1
                break
            Q[j + 1] = w / beta[j]
        T = np.diag(alpha[:k]) + np.diag(beta[:k - 1], 1) + np.diag(beta[:k - 1], -1)
        theta, s = np.linalg.eigh(T)
        return float(theta[-1] + abs(beta[k - 1] * s[-1, -1]))

    def __repr__(self) -> str:
        return (f'ClothSimulator({self.mesh!r}, {self._material}, dt={self._dt:g}, '
                f'divergence={self._divergence!r})')
