"""The model: everything about the cloth that does not change while it moves.

:class:`Model` is built once from a :class:`..mesh.ClothMesh` (rest shape and topology):
the rest charts, the jet operators and their rest residuals, the triangles' rest shapes,
the incidence tables. It holds no material constant, so a material change at run time
builds new :class:`Coefficients` (``Model.coefficients``: milliseconds), not a new model.

The kernels read the model through flat named tuples of arrays (numba compiles them as
structs, so a kernel reads ``faces.dinv`` rather than ``ops[1]``):

================  ==================================================================
tuple             arrays (n vertices, m faces, K stencil entries, V vertex-face pairs)
================  ==================================================================
:class:`Faces`    ``corners`` (m,3) int64, ``dinv`` (m,2,2) rest edge inverse in the
                  face's orthonormal chart, ``area`` (m,), ``K`` (m,3,2,2) vertex chart
                  to face chart per corner
:class:`VertexFaces` CSR by vertex: ``ptr`` (n+1,), ``face`` (V,), ``corner`` (V,),
                  ``row`` (V,) uint32 = 3 face + corner (a row of the (3m,3) corner
                  gradients), ``K`` (V,4) the corner's K weighted by sqrt(area/3A),
                  ``entry`` (V,3) each of the face's corners as an entry of the vertex's
                  stencil (0 = the vertex itself)
:class:`Vertices` ``dual_area`` (n,), ``ainv`` (n,3) rest inverse metric (11, 12, 22),
                  ``rest_a``, ``rest_b`` (n,3) rest metric and curvature
:class:`Jets`     CSR stencils of the cubic jets (centre first): ``ptr`` (n+1,), ``idx``
                  (K,), ``w`` (9,K) weights, ``uv`` (2,K) chart coordinates, ``sigma``
                  (K,) rest residuals along the normal, ``owner`` (K,), the transposed
                  stencil ``tr_ptr`` (n+1,) and ``tr_slot`` (K,) (CSR positions), and
                  the weights per stencil template (``wptr`` (n,) into ``tw`` (9,T) and
                  ``tuv`` (2,T)): vertices of equal stencil shape share one block
:class:`Coefficients` the material on the mesh: ``zeta``, ``xi``, ``phi`` [SI], ``mass``
                  (n,) [kg], ``damp`` (n,) [kg/s], ``stab`` (n,) hourglass weights [N/m]
================  ==================================================================
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .constants import JET_STABILIZATION
from .geometry import build_jet_operator, compute_geometry, Geometry, JetOperator
from .material import Material
from .mesh import ClothMesh
from .terms.jet import normal_residuals

__all__ = ['Model', 'Faces', 'VertexFaces', 'Vertices', 'Jets', 'Coefficients']


class Faces(NamedTuple):
    """Per-face rest data (module table)."""

    corners: np.ndarray
    dinv: np.ndarray
    area: np.ndarray
    K: np.ndarray


class VertexFaces(NamedTuple):
    """Vertex-face incidence, CSR by vertex (module table)."""

    ptr: np.ndarray
    face: np.ndarray
    corner: np.ndarray
    row: np.ndarray
    K: np.ndarray
    entry: np.ndarray


class Vertices(NamedTuple):
    """Per-vertex rest data (module table)."""

    dual_area: np.ndarray
    ainv: np.ndarray
    rest_a: np.ndarray
    rest_b: np.ndarray


class Jets(NamedTuple):
    """The jet stencils in CSR order (module table)."""

    ptr: np.ndarray
    idx: np.ndarray
    w: np.ndarray
    uv: np.ndarray
    sigma: np.ndarray
    owner: np.ndarray
    tr_ptr: np.ndarray
    tr_slot: np.ndarray
    wptr: np.ndarray
    tw: np.ndarray
    tuv: np.ndarray


class Coefficients(NamedTuple):
    """The material on this mesh (module table)."""

    zeta: float
    xi: float
    phi: float
    mass: np.ndarray
    damp: np.ndarray
    stab: np.ndarray


def _sym3(t: np.ndarray) -> np.ndarray:
    """(n,2,2) symmetric -> (n,3) as (11, 12, 22)."""
    return np.ascontiguousarray(np.stack([t[:, 0, 0], t[:, 0, 1], t[:, 1, 1]], axis=1))


@dataclass(frozen=True, eq=False)
class Model:
    """Frozen rest data of a cloth mesh (see the module docstring); build with
    :meth:`from_mesh`."""

    mesh: ClothMesh
    jet: JetOperator
    rest: Geometry
    faces: Faces
    vertex_faces: VertexFaces
    vertices: Vertices
    jets: Jets
    #: (K,2,2) a neighbour's chart components in the vertex's chart (the seed route)
    st_T: np.ndarray

    @classmethod
    def from_mesh(cls, mesh: ClothMesh) -> 'Model':
        if not isinstance(mesh, ClothMesh):
            raise ValueError(f'mesh must be a ClothMesh, got {type(mesh).__name__}')
        n, m = mesh.n_vertices, mesh.n_faces
        jet = build_jet_operator(mesh)
        rest = compute_geometry(mesh.vertices, mesh, jet, 'jet')
        dinv, K = _face_charts(mesh, jet)
        faces = Faces(np.ascontiguousarray(mesh.faces, dtype=np.int64), dinv,
                      np.ascontiguousarray(mesh.face_areas), K)
        vertices = Vertices(np.ascontiguousarray(mesh.dual_areas),
                            _sym3(np.linalg.inv(rest.metric)), _sym3(rest.metric),
                            _sym3(rest.curvature))
        # each vertex's faces in fan order (geometry.fan_order, as its stencil's 1-ring);
        # the coupling's corner maps weighted by area_t / (3 A_i):
        # epsbar_i = sum_q vf_K[q]^T eps_t vf_K[q] (coupling.py)
        vf_face = np.ascontiguousarray(mesh.vf_face[jet.vf_order])
        vf_corner = np.ascontiguousarray(mesh.vf_corner[jet.vf_order])
        owner_vf = np.repeat(np.arange(n), np.diff(mesh.vf_ptr))
        vf_w = np.sqrt(mesh.face_areas[vf_face] / (3.0 * mesh.dual_areas[owner_vf]))
        vf_K = np.ascontiguousarray((K[vf_face, vf_corner] * vf_w[:, None, None]).reshape(-1, 4))
        if max(len(jet.st_idx), 3 * m) > np.iinfo(np.uint32).max:
            raise ValueError(f'mesh too large: {m} faces and {len(jet.st_idx)} stencil '
                             'entries, the step indexes them with 32 bits')
        vf_row = (3 * vf_face + vf_corner).astype(np.uint32)
        vf_entry = _corner_entries(jet, mesh.faces[vf_face], owner_vf)
        vertex_faces = VertexFaces(mesh.vf_ptr, vf_face, vf_corner, vf_row, vf_K, vf_entry)
        st_uv = np.ascontiguousarray(jet.st_x.T)
        sigma = np.zeros(len(jet.st_idx))
        normal_residuals(mesh.vertices, jet.st_ptr, jet.st_idx, jet.st_w, st_uv, sigma)
        owner = np.repeat(np.arange(n, dtype=np.int64), np.diff(jet.st_ptr))
        # the weights and chart coordinates per stencil template (equal to the bit for the
        # vertices that share it, geometry.build_jet_operator): vertex i's block at wptr[i]
        reps, tpl = np.unique(jet.template, return_inverse=True)
        size = np.diff(jet.st_ptr)[reps]
        blk = np.zeros(len(reps) + 1, dtype=np.int64)
        np.cumsum(size, out=blk[1:])
        tsrc = np.repeat(jet.st_ptr[reps] - blk[:-1], size) + np.arange(blk[-1])
        jets = Jets(jet.st_ptr, jet.st_idx, jet.st_w, st_uv, sigma, owner, jet.tr_ptr,
                    jet.tr_slot, blk[tpl.ravel()], np.ascontiguousarray(jet.st_w[:, tsrc]),
                    np.ascontiguousarray(st_uv[:, tsrc]))
        frames = jet.frames
        st_T = np.ascontiguousarray(
            np.einsum('kax,kbx->kab', frames[owner, :2], frames[jet.st_idx, :2]))
        return cls(mesh, jet, rest, faces, vertex_faces, vertices, jets, st_T)

    @property
    def n_vertices(self) -> int:
        return self.mesh.n_vertices

    def coefficients(self, material: Material) -> Coefficients:
        """The material on this mesh: lumped masses ``mu A_i``, damping ``rho A_i`` and the
        hourglass weights ``om_i = s xi A_i / h_i^4 / S_i`` (bending.py)."""
        if not isinstance(material, Material):
            raise ValueError(f'material must be a Material, got {type(material).__name__}')
        a = self.mesh.dual_areas
        stab = (JET_STABILIZATION * material.xi * a / self.jet.radius ** 4
                / (np.diff(self.jet.st_ptr) - 1))
        return Coefficients(material.zeta, material.xi, material.phi, material.density * a,
                            material.damping * a, stab)

    def geometry(self, x: np.ndarray, curvature: str = 'jet') -> Geometry:
        """Per-vertex geometry of positions x against the rest state (see
        :func:`..geometry.compute_geometry`)."""
        rest = self.rest if curvature == 'jet' else compute_geometry(
            self.mesh.vertices, self.mesh, self.jet, curvature)
        return compute_geometry(x, self.mesh, self.jet, curvature, rest=rest)


def _face_charts(mesh: ClothMesh, jet: JetOperator):
    """Rest edge matrices: Dinv_t (m,2,2) in each triangle's orthonormal chart, and
    K_it = D_t U_it^-1 (m,3,2,2) from vertex charts to triangle charts."""
    X = mesh.vertices
    f = mesh.faces
    e1 = X[f[:, 1]] - X[f[:, 0]]
    e2 = X[f[:, 2]] - X[f[:, 0]]
    t1 = e1 / np.linalg.norm(e1, axis=1)[:, None]
    t2 = np.cross(mesh.face_normals, t1)
    D = np.stack([np.stack([np.einsum('mk,mk->m', e1, t1), np.einsum('mk,mk->m', e2, t1)],
                           axis=1),
                  np.stack([np.einsum('mk,mk->m', e1, t2), np.einsum('mk,mk->m', e2, t2)],
                           axis=1)], axis=1)
    frames = jet.frames[f]   # (m, 3 corners, 3 axes, 3)
    U = np.stack([np.stack([np.einsum('mck,mk->mc', frames[:, :, 0], e1),
                            np.einsum('mck,mk->mc', frames[:, :, 0], e2)], axis=-1),
                  np.stack([np.einsum('mck,mk->mc', frames[:, :, 1], e1),
                            np.einsum('mck,mk->mc', frames[:, :, 1], e2)], axis=-1)],
                 axis=2)           # (m, 3, 2, 2)
    K = np.einsum('mab,mcbd->mcad', D, np.linalg.inv(U))
    return np.ascontiguousarray(np.linalg.inv(D)), np.ascontiguousarray(K)


def _corner_entries(jet: JetOperator, corners: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """(V,3) int64: for vertex-face pair q of vertex ``owner[q]``, the stencil entry (offset
    from the vertex's first entry) of each corner of the face; every corner is in the
    1-ring, so in the stencil."""
    n = len(jet.st_ptr) - 1
    src = np.repeat(np.arange(n, dtype=np.int64), np.diff(jet.st_ptr))
    key = src * n + jet.st_idx
    order = np.argsort(key, kind='stable')
    want = owner[:, None] * n + corners
    pos = np.searchsorted(key[order], want)
    found = order[np.minimum(pos, len(order) - 1)]
    if not np.all(key[found] == want):
        raise ValueError('a face corner is missing from its vertex stencil')
    return np.ascontiguousarray(found - jet.st_ptr[owner][:, None])
