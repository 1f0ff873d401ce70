"""The compiled explicit step of the elastic terms: two passes per step, or tiles.

A step (any material) is two parallel passes, all compiled with the one reviewed option
set (``core/compiled.py``), no allocation:

1. the vertex pass, in work items of ``VERTEX_CHUNK`` vertices (each with its own scratch
   row) plus a share of the faces: per face the membrane's corner gradients
   (``core.terms.membrane.face_membrane``), per vertex the jet terms, bending and
   coupling with its strain side (:func:`.lanes.vertex_chunk`), into the stencil
   gradients;
2. the gather (every vertex's -dE/dx from its faces' corner gradients and the stencil
   gradients of the vertices whose jets hold it) and the update
   (``core.update.advance_vertex``).

Both passes share their work between the threads (:mod:`.workshare`): each thread runs
its own equal run of items first, then takes the others' remaining items from their far
ends, so a thread whose core is slower, or taken for a moment by another process, no
longer holds up the pass; which thread runs an item changes, what it computes does not.

Meshes of ``FUSE_MIN_VERTICES`` and more step tiled (:func:`run_tiled`, :mod:`.plan`):
each thread runs its part tile by tile and gathers and updates on the spot the vertices a
tile completes; the same forces and update, vertex for vertex and in the same order.

:func:`elastic_forces` is pass 1 and the gather alone (the internal force at any x, for
the critical dt and ``ClothSimulator.internal_forces``).
"""
from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from ..core.compiled import kernel
from ..core.update import advance_vertex, contact_list, contact_range
from ..core.air import air_faces, air_gather, air_pass
from .lanes import vertex_chunk
from .workshare import arrive, claim, split

__all__ = ['Work', 'run_two_pass', 'run_two_pass_coupled', 'run_region', 'run_region_coupled',
           'run_tiled', 'run_tiled_coupled', 'elastic_forces', 'elastic_forces_coupled']


class Work(NamedTuple):
    """The step's scratch (m faces, K stencil entries, nch chunks, T threads)."""

    fgrad: np.ndarray       # (m, 3, 3) corner gradients (rows by face or ring slot)
    contrib: np.ndarray     # (3, K) stencil gradients (lane order or ring slots)
    scratch: np.ndarray     # (nch, 5, S) one row per work item
    share: np.ndarray       # (T+1,) int64 work-sharing state of the passes (workshare.py)
    part: np.ndarray        # (nch, 3) the update's work, dissipation, bad per chunk
    force: np.ndarray       # (n, 3) the internal force of the last step
    ushare: np.ndarray      # (T+1,) int64 the update's work-sharing state (run_region)
    sync: np.ndarray        # (4,) int64 run_region's barrier: count, steps done, sleepers,
                            # spins before sleeping (workshare.arrive)


@kernel(inline='always')
def _vertex_pass(x, lanes, plan, faces, vf, vertices, coeff, work, coupled):
    """Pass 1 over all chunks in parallel (:func:`.lanes.vertex_chunk`), shared between
    the threads (:mod:`.workshare`, state ``work.share``): the same chunks, the same
    results, whichever thread runs them (against the static split of ``prange(nch)``:
    docs/performance.md).
    ``coupled``: a literal, one kernel each (:func:`vertex_pass`,
    :func:`vertex_pass_coupled`)."""
    g_vert, g_ptr, s_vert, s_ptr, s_wptr = (lanes.g_vert, lanes.g_ptr, lanes.s_vert,
                                            lanes.s_ptr, lanes.s_wptr)
    ln_idx, ln_w, ln_uv, ln_sigma = lanes.idx, lanes.w, lanes.uv, lanes.sigma
    sp_P, sp_entry, sp_ebar0 = lanes.sp_P, lanes.sp_entry, lanes.sp_ebar0
    g_wptr, fc_ptr, fc_slot = plan.g_wptr, plan.fc_ptr, plan.fc_slot
    fc_vert, fc_tpl, t_dinv, t_area = plan.fc_vert, plan.fc_tpl, plan.t_dinv, plan.t_area
    corners, dinv, face_area, K_face = faces.corners, faces.dinv, faces.area, faces.K
    vf_ptr, vf_face, vf_corner, vf_entry, vf_K = vf.ptr, vf.face, vf.corner, vf.entry, vf.K
    dual_area, ainv, rest_b = vertices.dual_area, vertices.ainv, vertices.rest_b
    zeta, xi, phi, stab = coeff.zeta, coeff.xi, coeff.phi, coeff.stab
    fgrad, contrib, scratch = work.fgrad, work.contrib, work.scratch
    share = work.share
    nch = plan.tile_ch[plan.tile_ch.shape[0] - 1]
    nr = split(share, nch)
    for t in nb.prange(nr):
        c, k = claim(share, t, nr, 0)
        while c >= 0:
            vertex_chunk(c, nch, c, x, g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, ln_idx,
                         ln_w, ln_uv, ln_sigma, sp_P, sp_entry, sp_ebar0, stab, dual_area, ainv,
                         rest_b, xi, phi, scratch, contrib, corners, dinv, face_area, K_face,
                         vf_ptr,
                         vf_face, vf_corner, vf_entry, vf_K, fc_vert, t_dinv, t_area, zeta, fc_ptr,
                         fc_tpl, fc_slot, fgrad, coupled)
            c, k = claim(share, t, nr, k)


@kernel(parallel=True)
def vertex_pass(x, lanes, plan, faces, vf, vertices, coeff, work):
    """:func:`_vertex_pass` without coupling (phi = 0)."""
    _vertex_pass(x, lanes, plan, faces, vf, vertices, coeff, work, False)


@kernel(parallel=True)
def vertex_pass_coupled(x, lanes, plan, faces, vf, vertices, coeff, work):
    """:func:`_vertex_pass` with the coupling (phi != 0)."""
    _vertex_pass(x, lanes, plan, faces, vf, vertices, coeff, work, True)


@kernel(inline='always')
def gather(j, vf_ptr, vf_row, frow, tr_ptr, tr_slot, contrib):
    """-dE/dx_j: corner gradients of the incident faces plus the stencil gradients of every
    vertex whose jet uses x_j (the transposed stencil).

    The corner gradients are rows ``frow`` (3 m, 3) of fgrad: ``vf_row`` holds 3 face +
    corner (or 3 slot + corner, where the tiled step puts them) per vertex-face pair, and
    ``tr_slot`` the stencil gradients' positions in ``contrib``. Both are uint32: the gather
    streams 4 bytes per index instead of 8, and one index per face instead of two. All
    indices are read as unsigned: a signed index makes numba add its negative-index
    wrap-around (four integer instructions per load), which cost the gather ~25% at
    N = 40 (one thread, 42 -> 31 ns per vertex)."""
    j1 = nb.uint64(j + 1)
    j = nb.uint64(j)
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    for q in range(nb.uint64(vf_ptr[j]), nb.uint64(vf_ptr[j1])):
        r = nb.uint64(vf_row[q])
        g0 += frow[r, 0]
        g1 += frow[r, 1]
        g2 += frow[r, 2]
    for q in range(nb.uint64(tr_ptr[j]), nb.uint64(tr_ptr[j1])):
        k = nb.uint64(tr_slot[q])
        g0 += contrib[0, k]
        g1 += contrib[1, k]
        g2 += contrib[2, k]
    return -g0, -g1, -g2


@kernel(parallel=True)
def gather_forces(vf_ptr, vf_row, fgrad, tr_ptr, tr_slot, contrib, force):
    """force[j] = -dE/dx_j (n,3) [N] (:func:`gather`; fgrad (m, 3, 3) read as rows)."""
    n = force.shape[0]
    frow = fgrad.reshape((fgrad.shape[0] * 3, 3))
    for j in nb.prange(n):
        force[j, 0], force[j, 1], force[j, 2] = gather(j, vf_ptr, vf_row, frow, tr_ptr,
                                                       tr_slot, contrib)


@kernel(inline='always')
def _update_chunk(c, size, vf_ptr, vf_row, tr_ptr, tr_slot, frow, contrib, x, v, force,
                  control, coeff, dt, vmax2, part):
    """Gather and update (Eq. 29) the vertices of chunk c (``size`` each) in order, and
    write the chunk's external work, dissipation and bad vertices to ``part[c]``."""
    work = 0.0
    diss = 0.0
    bad = 0
    for i in range(c * size, min(x.shape[0], (c + 1) * size)):
        f0, f1, f2 = gather(i, vf_ptr, vf_row, frow, tr_ptr, tr_slot, contrib)
        force[i, 0] = f0
        force[i, 1] = f1
        force[i, 2] = f2
        w, d, b = advance_vertex(i, f0, f1, f2, x, v, control, coeff, dt, vmax2)
        work += w
        diss += d
        bad += b
    if control.obstacles.shape[0] > 0:
        # int64 bounds: the signature the cold start's second process compiles
        w, d = contact_range(nb.int64(c * size), nb.int64(min(x.shape[0], (c + 1) * size)),
                             x, v, force, control, coeff, dt)
        work += w
        diss += d
    part[c, 0] = work
    part[c, 1] = diss
    part[c, 2] = bad


@kernel(parallel=True)
def integrate(tr_ptr, vf_ptr, plan, work, x, v, control, coeff, dt, vmax2, acc):
    """Pass 2: gather and update every vertex in place (chunks of the rows of
    ``work.part``, shared between the threads as in :func:`vertex_pass`); returns the
    number of vertices that went bad. Each chunk sums its external work and dissipation
    into its own row, and those rows are added in chunk order after the pass, so ``acc``
    gets the same sums whichever thread ran which chunk."""
    vf_row, tr_slot = plan.vf_row, plan.tr_slot
    fgrad, contrib, share, part, force = (work.fgrad, work.contrib, work.share, work.part,
                                          work.force)
    frow = fgrad.reshape((fgrad.shape[0] * 3, 3))
    n = x.shape[0]
    nch = part.shape[0]
    size = (n + nch - 1) // nch
    nr = split(share, nch)
    for t in nb.prange(nr):
        c, k = claim(share, t, nr, 0)
        while c >= 0:
            _update_chunk(c, size, vf_ptr, vf_row, tr_ptr, tr_slot, frow, contrib, x, v, force,
                          control, coeff, dt, vmax2, part)
            c, k = claim(share, t, nr, k)
    bad = 0
    for c in range(nch):
        acc[0] += part[c, 0]
        acc[1] += part[c, 1]
        bad += int(part[c, 2])
    return bad


@kernel()
def run_two_pass(nsteps, state, control, coeff, faces, vf, vertices, tr_ptr, lanes, plan,
                 work, dt, vmax2):
    """Advance ``nsteps`` steps: per step :func:`vertex_pass`, then :func:`integrate`.
    Returns the number of completed steps; fewer than ``nsteps`` means step ``returned
    value`` diverged (the state is then invalid: the caller restores it). Without coupling;
    :func:`run_two_pass_coupled` with it (a kernel each, so that a process compiles only
    the one its material needs)."""
    x, v, acc = state.x, state.v, state.acc
    for s in range(nsteps):
        if control.air[0] != 0.0:
            air_pass(x, v, faces.corners, vf.ptr, vf.face, control, work.part.shape[0])
        vertex_pass(x, lanes, plan, faces, vf, vertices, coeff, work)
        if integrate(tr_ptr, vf.ptr, plan, work, x, v, control, coeff, dt, vmax2, acc) > 0:
            return s
    return nsteps


@kernel()
def run_two_pass_coupled(nsteps, state, control, coeff, faces, vf, vertices, tr_ptr, lanes,
                         plan, work, dt, vmax2):
    """:func:`run_two_pass` with the coupling (phi != 0)."""
    x, v, acc = state.x, state.v, state.acc
    for s in range(nsteps):
        if control.air[0] != 0.0:
            air_pass(x, v, faces.corners, vf.ptr, vf.face, control, work.part.shape[0])
        vertex_pass_coupled(x, lanes, plan, faces, vf, vertices, coeff, work)
        if integrate(tr_ptr, vf.ptr, plan, work, x, v, control, coeff, dt, vmax2, acc) > 0:
            return s
    return nsteps


@kernel(inline='always')
def _run_region(nsteps, state, control, coeff, faces, vf, vertices, tr_ptr, lanes, plan,
                work, dt, vmax2, nthr, coupled):
    """:func:`run_two_pass` in one parallel region for all ``nsteps`` steps, of ``nthr``
    iterations, one per thread (the threads numba runs, from Python). Per step: the
    vertex pass (chunks shared through ``work.share``), a barrier
    (:func:`.workshare.arrive`), the gather and update (chunks shared through
    ``work.ushare``), a barrier. Each work-sharing state is re-split by one thread while
    the others are in the other pass. Every thread then reads the chunks' bad counts, so
    that all leave at the same step, and one adds their work and dissipation to ``acc``
    in chunk order. The same numbers as the two passes, to the bit, without opening two
    parallel regions per step (each costs about ten barriers). Returns
    the steps done: fewer than ``nsteps`` when one went bad.

    The barrier waits for every iteration, so all ``nthr`` must run at once: the solver
    uses this kernel only with numba's static schedule on the OpenMP or workqueue layer
    and a CPU per thread (``core/solvers/explicit.py``). With ``nsteps`` = 1 and ``dt`` = 0
    it is the internal force alone (in ``work.force``; x and v stay as they are), so that a
    process compiles the vertex code once."""
    x, v, acc = state.x, state.v, state.acc
    g_vert, g_ptr, s_vert, s_ptr, s_wptr = (lanes.g_vert, lanes.g_ptr, lanes.s_vert,
                                            lanes.s_ptr, lanes.s_wptr)
    ln_idx, ln_w, ln_uv, ln_sigma = lanes.idx, lanes.w, lanes.uv, lanes.sigma
    sp_P, sp_entry, sp_ebar0 = lanes.sp_P, lanes.sp_entry, lanes.sp_ebar0
    g_wptr, fc_ptr, fc_slot = plan.g_wptr, plan.fc_ptr, plan.fc_slot
    fc_vert, fc_tpl, t_dinv, t_area = plan.fc_vert, plan.fc_tpl, plan.t_dinv, plan.t_area
    corners, dinv, face_area, K_face = faces.corners, faces.dinv, faces.area, faces.K
    vf_ptr, vf_face, vf_corner, vf_entry, vf_K = vf.ptr, vf.face, vf.corner, vf.entry, vf.K
    dual_area, ainv, rest_b = vertices.dual_area, vertices.ainv, vertices.rest_b
    zeta, xi, phi, stab = coeff.zeta, coeff.xi, coeff.phi, coeff.stab
    fgrad, contrib, scratch = work.fgrad, work.contrib, work.scratch
    share, ushare, sync, part, force = work.share, work.ushare, work.sync, work.part, work.force
    vf_row, tr_slot = plan.vf_row, plan.tr_slot
    frow = fgrad.reshape((fgrad.shape[0] * 3, 3))
    nch = plan.tile_ch[plan.tile_ch.shape[0] - 1]
    nuc = part.shape[0]
    size = (x.shape[0] + nuc - 1) // nuc
    nr = split(share, nch)
    nu = split(ushare, nuc)
    sync[0] = 0
    sync[1] = nsteps
    sync[2] = 0
    air = control.air[0] != 0.0
    per = 3 if air else 2                   # barriers per step
    asize = (x.shape[0] + nthr - 1) // nthr
    fsize = (corners.shape[0] + nthr - 1) // nthr
    for t in nb.prange(nthr):
        for s in range(nsteps):
            if t == 0 and s > 0:
                split(ushare, nuc)          # the others are in the vertex pass
            if air:
                # this thread's slices of the air force (core/air.py): the faces' from x
                # and v, which the last barrier left complete, then, after a barrier, the
                # vertices' f_applied, which only the update reads
                air_faces(nb.int64(t * fsize), nb.int64(min(corners.shape[0],
                                                             (t + 1) * fsize)),
                          x, v, corners, control)
                arrive(sync, per * s + 1, nthr)
                air_gather(nb.int64(t * asize), nb.int64(min(x.shape[0], (t + 1) * asize)),
                           vf_ptr, vf_face, control)
            c, k = claim(share, t, nr, 0)
            while c >= 0:
                vertex_chunk(c, nch, c, x, g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr,
                             ln_idx, ln_w, ln_uv, ln_sigma, sp_P, sp_entry, sp_ebar0, stab,
                             dual_area, ainv, rest_b, xi, phi, scratch, contrib, corners, dinv,
                             face_area, K_face, vf_ptr, vf_face, vf_corner, vf_entry, vf_K,
                             fc_vert, t_dinv, t_area, zeta, fc_ptr, fc_tpl, fc_slot, fgrad,
                             coupled)
                c, k = claim(share, t, nr, k)
            arrive(sync, per * s + per - 1, nthr)
            if t == 0:
                split(share, nch)           # the others are in the update
            c, k = claim(ushare, t, nu, 0)
            while c >= 0:
                _update_chunk(c, size, vf_ptr, vf_row, tr_ptr, tr_slot, frow, contrib, x, v,
                              force, control, coeff, dt, vmax2, part)
                c, k = claim(ushare, t, nu, k)
            arrive(sync, per * s + per, nthr)
            bad = 0
            for c in range(nuc):
                bad += int(part[c, 2])
            if t == 0:
                for c in range(nuc):
                    acc[0] += part[c, 0]
                    acc[1] += part[c, 1]
                if bad > 0:
                    sync[1] = s
            if bad > 0:
                break
    return sync[1]


@kernel(parallel=True)
def run_region(nsteps, state, control, coeff, faces, vf, vertices, tr_ptr, lanes, plan, work,
               dt, vmax2, nthr):
    """:func:`_run_region` without coupling (phi = 0)."""
    return _run_region(nsteps, state, control, coeff, faces, vf, vertices, tr_ptr, lanes, plan,
                       work, dt, vmax2, nthr, False)


@kernel(parallel=True)
def run_region_coupled(nsteps, state, control, coeff, faces, vf, vertices, tr_ptr, lanes, plan,
                       work, dt, vmax2, nthr):
    """:func:`_run_region` with the coupling (phi != 0)."""
    return _run_region(nsteps, state, control, coeff, faces, vf, vertices, tr_ptr, lanes, plan,
                       work, dt, vmax2, nthr, True)


@kernel()
def elastic_forces(x, coeff, faces, vf, vertices, tr_ptr, lanes, plan, work, force):
    """Internal force -dE/dx (n,3) [N] of the three elastic terms at positions x (the
    step's pass 1 and its gather, two-pass plan only), without coupling."""
    vertex_pass(x, lanes, plan, faces, vf, vertices, coeff, work)
    gather_forces(vf.ptr, plan.vf_row, work.fgrad, tr_ptr, plan.tr_slot, work.contrib, force)


@kernel()
def elastic_forces_coupled(x, coeff, faces, vf, vertices, tr_ptr, lanes, plan, work, force):
    """:func:`elastic_forces` with the coupling (phi != 0)."""
    vertex_pass_coupled(x, lanes, plan, faces, vf, vertices, coeff, work)
    gather_forces(vf.ptr, plan.vf_row, work.fgrad, tr_ptr, plan.tr_slot, work.contrib, force)


@kernel(refcount=False)
def _gather_update(q0, q1, gl_vert, vf_ptr, vf_row, frow, tr_ptr, tr_slot, contrib, x, v,
                   force, control, coeff, dt, vmax2):
    """Gather (force = -dE/dx) and update (Eq. 29) the vertices ``gl_vert[q0:q1]`` one after
    the other; returns (external work, dissipation, bad vertices). A plain call from
    :func:`vertex_parts` (once per tile) and :func:`integrate_seam` (once per vertex), not
    inlined: inlined, its code slowed the vertex code around it by ~5% (register
    pressure)."""
    w = 0.0
    d = 0.0
    b = 0
    for q in range(q0, q1):
        i = gl_vert[q]
        f0, f1, f2 = gather(i, vf_ptr, vf_row, frow, tr_ptr, tr_slot, contrib)
        force[i, 0] = f0
        force[i, 1] = f1
        force[i, 2] = f2
        dw, dd, db = advance_vertex(i, f0, f1, f2, x, v, control, coeff, dt, vmax2)
        w += dw
        d += dd
        b += db
    if control.obstacles.shape[0] > 0:
        dw, dd = contact_list(gl_vert, q0, q1, x, v, force, control, coeff, dt, False)
        w += dw
        d += dd
    return w, d, b


@kernel(inline='always')
def _vertex_parts(x, v, lanes, plan, faces, vf, vertices, tr_ptr, control, coeff, work, dt,
                  vmax2, pacc, coupled):
    """The tiled step's first pass: the vertex pass (:func:`.lanes.vertex_chunk`), one
    part of the mesh per thread, and the gather and update (Eq. 29) of every vertex whose
    contributors all lie in the thread's part.

    Part p (``plan.part_tile``: its tiles) runs its chunks in order; after the last chunk
    of a tile (``plan.tile_ch``) it gathers and updates the vertices the tile completed
    (``plan.gl_ptr``, ``plan.gl_vert``). Their stencil and corner gradients are still in
    this core's cache, and updating x[j] there is safe (:mod:`.plan`). The seam vertices
    between parts (the last range of ``gl_ptr``) are left for :func:`integrate_seam`.
    Writes (external work, dissipation, bad vertices) of part p to pacc[p]."""
    g_vert, g_ptr, s_vert, s_ptr, s_wptr = (lanes.g_vert, lanes.g_ptr, lanes.s_vert,
                                            lanes.s_ptr, lanes.s_wptr)
    ln_idx, ln_w, ln_uv, ln_sigma = lanes.idx, lanes.w, lanes.uv, lanes.sigma
    sp_P, sp_entry, sp_ebar0 = lanes.sp_P, lanes.sp_entry, lanes.sp_ebar0
    g_wptr, fc_ptr, fc_slot = plan.g_wptr, plan.fc_ptr, plan.fc_slot
    fc_vert, fc_tpl, t_dinv, t_area = plan.fc_vert, plan.fc_tpl, plan.t_dinv, plan.t_area
    corners, dinv, face_area, K_face = faces.corners, faces.dinv, faces.area, faces.K
    vf_ptr, vf_face, vf_corner, vf_entry, vf_K = vf.ptr, vf.face, vf.corner, vf.entry, vf.K
    dual_area, ainv, rest_b = vertices.dual_area, vertices.ainv, vertices.rest_b
    zeta, xi, phi, stab = coeff.zeta, coeff.xi, coeff.phi, coeff.stab
    fgrad, contrib, scratch = work.fgrad, work.contrib, work.scratch
    tile_ch, gl_ptr, gl_vert, part_tile, tr_slot, vf_row = (
        plan.tile_ch, plan.gl_ptr, plan.gl_vert, plan.part_tile, plan.tr_slot, plan.vf_row)
    force = work.force
    nch = tile_ch[tile_ch.shape[0] - 1]
    frow = fgrad.reshape((fgrad.shape[0] * 3, 3))
    for p in nb.prange(part_tile.shape[0] - 1):
        w = 0.0
        d = 0.0
        b = 0
        t = part_tile[p]
        row = tile_ch[t]        # the scratch row of the part's first chunk
        # one loop over the part's chunks (not tiles, then chunks: the deeper nest cost the
        # vertex code ~5%); a tile's vertices are gathered after its last chunk
        for ch in range(tile_ch[t], tile_ch[part_tile[p + 1]]):
            vertex_chunk(ch, nch, row, x, g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, ln_idx,
                         ln_w, ln_uv, ln_sigma, sp_P, sp_entry, sp_ebar0, stab, dual_area, ainv,
                         rest_b, xi, phi, scratch, contrib, corners, dinv, face_area, K_face,
                         vf_ptr,
                         vf_face, vf_corner, vf_entry, vf_K, fc_vert, t_dinv, t_area, zeta, fc_ptr,
                         fc_tpl, fc_slot, fgrad, coupled)
            if ch + 1 == tile_ch[t + 1]:
                dw, dd, db = _gather_update(gl_ptr[t], gl_ptr[t + 1], gl_vert, vf_ptr, vf_row,
                                            frow, tr_ptr, tr_slot, contrib, x, v, force,
                                            control, coeff, dt, vmax2)
                w += dw
                d += dd
                b += db
                t += 1
        pacc[p, 0] = w
        pacc[p, 1] = d
        pacc[p, 2] = b


@kernel(parallel=True)
def vertex_parts(x, v, lanes, plan, faces, vf, vertices, tr_ptr, control, coeff, work, dt,
                 vmax2, pacc):
    """:func:`_vertex_parts` without coupling (phi = 0)."""
    _vertex_parts(x, v, lanes, plan, faces, vf, vertices, tr_ptr, control, coeff, work, dt,
                  vmax2, pacc, False)


@kernel(parallel=True)
def vertex_parts_coupled(x, v, lanes, plan, faces, vf, vertices, tr_ptr, control, coeff, work,
                         dt, vmax2, pacc):
    """:func:`_vertex_parts` with the coupling (phi != 0)."""
    _vertex_parts(x, v, lanes, plan, faces, vf, vertices, tr_ptr, control, coeff, work, dt,
                  vmax2, pacc, True)


@kernel(parallel=True)
def integrate_seam(tr_ptr, vf_ptr, plan, work, x, v, control, coeff, dt, vmax2, acc):
    """Gather and update the seam vertices of the tiled step only (the last range of
    ``plan.gl_ptr``), reading the gradients where :func:`vertex_parts` put them."""
    gl_ptr, gl_vert, tr_slot, vf_row = plan.gl_ptr, plan.gl_vert, plan.tr_slot, plan.vf_row
    fgrad, contrib, force = work.fgrad, work.contrib, work.force
    frow = fgrad.reshape((fgrad.shape[0] * 3, 3))
    q0 = gl_ptr[gl_ptr.shape[0] - 2]
    wsum = 0.0
    diss = 0.0
    bad = 0
    for q in nb.prange(gl_ptr[gl_ptr.shape[0] - 1] - q0):
        q1 = q0 + np.int64(q)
        w, d, b = _gather_update(q1, q1 + 1, gl_vert, vf_ptr, vf_row, frow, tr_ptr, tr_slot,
                                 contrib, x, v, force, control, coeff, dt, vmax2)
        wsum += w
        diss += d
        bad += b
    acc[0] += wsum
    acc[1] += diss
    return bad


@kernel(inline='always')
def _run_tiled(nsteps, state, control, coeff, faces, vf, vertices, tr_ptr, lanes, plan, work,
               dt, vmax2, coupled):
    """:func:`run_two_pass` for a large mesh: per step :func:`vertex_parts` (each thread
    its part, tile by tile, gathering and updating a tile's vertices while their gradients
    are in cache), then gather + update of the seam vertices between the parts. The same
    forces and update, vertex for vertex, in the same arithmetic order, so the same
    trajectory to the bit. Kernels of their own: a small mesh never compiles them."""
    x, v, acc = state.x, state.v, state.acc
    pacc = np.zeros((plan.part_tile.shape[0] - 1, 3))
    for s in range(nsteps):
        if control.air[0] != 0.0:
            air_pass(x, v, faces.corners, vf.ptr, vf.face, control, work.part.shape[0])
        if coupled:
            vertex_parts_coupled(x, v, lanes, plan, faces, vf, vertices, tr_ptr, control,
                                 coeff, work, dt, vmax2, pacc)
        else:
            vertex_parts(x, v, lanes, plan, faces, vf, vertices, tr_ptr, control, coeff, work,
                         dt, vmax2, pacc)
        bad = integrate_seam(tr_ptr, vf.ptr, plan, work, x, v, control, coeff, dt, vmax2, acc)
        for p in range(pacc.shape[0]):
            acc[0] += pacc[p, 0]
            acc[1] += pacc[p, 1]
            bad += int(pacc[p, 2])
        if bad > 0:
            return s
    return nsteps


@kernel()
def run_tiled(nsteps, state, control, coeff, faces, vf, vertices, tr_ptr, lanes, plan, work,
              dt, vmax2):
    """:func:`_run_tiled` without coupling (phi = 0)."""
    return _run_tiled(nsteps, state, control, coeff, faces, vf, vertices, tr_ptr, lanes, plan,
                      work, dt, vmax2, False)


@kernel()
def run_tiled_coupled(nsteps, state, control, coeff, faces, vf, vertices, tr_ptr, lanes, plan,
                      work, dt, vmax2):
    """:func:`_run_tiled` with the coupling (phi != 0)."""
    return _run_tiled(nsteps, state, control, coeff, faces, vf, vertices, tr_ptr, lanes, plan,
                      work, dt, vmax2, True)
