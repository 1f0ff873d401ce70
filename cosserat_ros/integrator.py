"""Explicit time integration of Eq. 1 / 24 with the update of Eq. 29.

Per step, for every free vertex with lumped mass ``m_i = mu A_i`` and damping
``c_i = rho A_i``::

    v <- v + dt/m_i (f_int(x) + f_ext + m_i (g + F) - c_i v)      (Eq. 29, velocity first)
    x <- x + dt v                                                   (then position)

This is symplectic Euler (leapfrog with velocities at half steps): undamped runs keep a
shadow energy, so the total energy oscillates by O(dt^2) instead of drifting. Pinned
vertices keep their position and zero velocity.

Bookkeeping per step (accumulated in ``acc``): external work ``sum (f_ext + m F) . dx`` and
damping dissipation ``sum c_i v_old . dx`` with ``dx = dt v_new``, so that
``total(t) - total(0) = external_work - dissipated`` up to the O(dt^2) integration error.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .compiled import kernel
from .forces import (_gather, _vertex_chunk, covariant_forces, face_coupling, face_membrane,
                     gather_forces)
from .workshare import arrive, claim, split

METHOD_VARIATIONAL = 0
METHOD_COVARIANT = 1


@kernel(inline='always')
def _update(i, x, v, f0, f1, f2, f_applied, mass, damp, pinned, dt, g0, g1, g2, vmax2):
    """Eq. 29 for vertex i with internal force f: returns (external work, dissipation,
    1 if the vertex went bad (non-finite or faster than sqrt(vmax2)) else 0); a pinned
    vertex stays put: (0, 0, 0)."""
    i = nb.uint64(i)        # no negative-index wrap-around on the ~15 loads and stores
    if pinned[i]:
        return 0.0, 0.0, 0
    m = mass[i]
    c = damp[i]
    vo0 = v[i, 0]
    vo1 = v[i, 1]
    vo2 = v[i, 2]
    vn0 = vo0 + dt / m * (f0 + f_applied[i, 0] + m * g0 - c * vo0)
    vn1 = vo1 + dt / m * (f1 + f_applied[i, 1] + m * g1 - c * vo1)
    vn2 = vo2 + dt / m * (f2 + f_applied[i, 2] + m * g2 - c * vo2)
    s2 = vn0 * vn0 + vn1 * vn1 + vn2 * vn2
    bad = 0 if s2 <= vmax2 else 1  # also catches NaN
    v[i, 0] = vn0
    v[i, 1] = vn1
    v[i, 2] = vn2
    x[i, 0] += dt * vn0
    x[i, 1] += dt * vn1
    x[i, 2] += dt * vn2
    work = dt * (f_applied[i, 0] * vn0 + f_applied[i, 1] * vn1 + f_applied[i, 2] * vn2)
    diss = dt * c * (vo0 * vn0 + vo1 * vn1 + vo2 * vn2)
    return work, diss, bad


@kernel(inline='always')
def _update_chunk(c, size, gather, ops, frow, contrib, x, v, force, f_applied, mass, damp,
                  pinned, gravity, dt, vmax2, part):
    """Update (Eq. 29) the vertices of chunk c (``size`` each) in order, with the gather of
    their force first if ``gather``, and write the chunk's external work, dissipation and
    bad vertices to ``part[c]``."""
    tr_ptr, tr_slot, vf_ptr, vf_row = ops[13], ops[14], ops[15], ops[17]
    work = 0.0
    diss = 0.0
    bad = 0
    for i in range(c * size, min(x.shape[0], (c + 1) * size)):
        if gather:
            f0, f1, f2 = _gather(i, vf_ptr, vf_row, frow, tr_ptr, tr_slot, contrib)
            force[i, 0] = f0
            force[i, 1] = f1
            force[i, 2] = f2
        else:
            f0 = force[i, 0]
            f1 = force[i, 1]
            f2 = force[i, 2]
        w, d, b = _update(i, x, v, f0, f1, f2, f_applied, mass, damp, pinned, dt,
                          gravity[0], gravity[1], gravity[2], vmax2)
        work += w
        diss += d
        bad += b
    part[c, 0] = work
    part[c, 1] = diss
    part[c, 2] = bad


@kernel(parallel=True)
def vertex_pass(x, ops, mat, work, with_faces):
    """The vertex pass (:func:`forces._vertex_chunk`; the faces too if ``with_faces``) over
    all chunks in parallel, each with its own scratch row. The faces' corner gradients go
    to their own rows of fgrad (ops[29]; the tiled step's ring slots are its own).

    Each thread runs an equal run of chunks and then takes what is left of the others'
    from their far ends (:mod:`.workshare`, state ``work[8]``): the same chunks, the same
    results, but a thread whose core is slower or taken no longer holds up the pass.
    Paired against the static split of ``prange(nch)`` (same trajectory to the bit): the
    step 0.87 / 0.97x at N = 40 / 20, again 0.94 / 0.99x in a slower minute, with
    :func:`integrate` sharing its work too."""
    (_, _, _, _, dual_area, ainv, rest_b, _, _, _, ln_uv, ln_sigma, stab,
     _, _, vf_ptr, vf_face, _, vf_K, g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, ln_idx,
     ln_w, tile_ch, fc_ptr, fc_face, _, _, _, _, _, _, _, fc_vert, fc_tpl, f_dinv,
     f_area) = ops
    zeta, xi, phi = mat[0], mat[1], mat[2]
    eps, cstress, kap, epsbar, estab, fgrad, contrib, scratch, share, _, _, _ = work
    nch = tile_ch[tile_ch.shape[0] - 1]
    nr = split(share, nch)
    for t in nb.prange(nr):
        c, k = claim(share, t, nr, 0)
        while c >= 0:
            _vertex_chunk(c, nch, c, x, g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, ln_idx,
                          ln_w, ln_uv, ln_sigma, stab, vf_ptr, vf_face, eps, vf_K, dual_area,
                          ainv, rest_b, xi, phi, scratch, contrib, cstress, kap, epsbar, estab,
                          fc_vert, f_dinv, f_area, zeta, fc_ptr, fc_tpl, fc_face, with_faces,
                          fgrad, True)
            c, k = claim(share, t, nr, k)


@kernel()
def _gather_update(q0, q1, gl_vert, vf_ptr, vf_row, frow, tr_ptr, tr_slot, contrib, x, v,
                   force, f_applied, mass, damp, pinned, gravity, dt, vmax2):
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
        f0, f1, f2 = _gather(i, vf_ptr, vf_row, frow, tr_ptr, tr_slot, contrib)
        force[i, 0] = f0
        force[i, 1] = f1
        force[i, 2] = f2
        dw, dd, db = _update(i, x, v, f0, f1, f2, f_applied, mass, damp, pinned, dt,
                             gravity[0], gravity[1], gravity[2], vmax2)
        w += dw
        d += dd
        b += db
    return w, d, b


@kernel(parallel=True)
def vertex_parts(x, ops, mat, work, v, force, f_applied, mass, damp, pinned, gravity, dt,
                 vmax2, pacc):
    """The tiled step's first pass (phi = 0): the vertex pass with the faces
    (:func:`forces._vertex_chunk`), one part of the mesh per thread, and the gather and
    update (Eq. 29) of every vertex whose contributors all lie in the thread's part.

    Part p (ops[32]: its tiles) runs its chunks in order; after the last chunk of a tile
    (ops[27]: the tiles' chunk ranges) it gathers and updates the vertices the tile
    completed (ops[30], ops[31]: those whose last contributor is in the tile). Their
    stencil and corner gradients are still in this core's cache, and updating x[j] there
    is safe: the vertices and faces that read x[j] are exactly those that contribute to
    it, all done, and all in this part. The vertices on the seam between parts (the last
    range of ops[30]) are left for :func:`integrate_seam`. The lane groups' stencil gradients
    go where ops[33] says and are gathered from ops[34], the faces' corner gradients go
    to the rows ops[35] and are gathered from ops[36] (mostly rings that stay in cache,
    ClothSimulator._rings); the faces' corners and rest shapes are read in chunk order
    (ops[37:41], ClothSimulator._face_stream). Writes (external work, dissipation, bad
    vertices) of part p to pacc[p]."""
    (_, _, _, _, dual_area, ainv, rest_b, _, _, _, ln_uv, ln_sigma, stab,
     tr_ptr, _, vf_ptr, vf_face, _, vf_K, g_vert, g_ptr, _, s_vert, s_ptr,
     s_wptr, ln_idx, ln_w, tile_ch, fc_ptr, _, gl_ptr, gl_vert, part_tile, g_wptr,
     tr_slot, fc_slot, vf_row, fc_vert, fc_tpl, f_dinv, f_area) = ops
    zeta, xi, phi = mat[0], mat[1], mat[2]
    eps, cstress, kap, epsbar, estab, fgrad, contrib, scratch, _, _, _, _ = work
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
            _vertex_chunk(ch, nch, row, x, g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, ln_idx,
                          ln_w, ln_uv, ln_sigma, stab, vf_ptr, vf_face, eps, vf_K, dual_area,
                          ainv, rest_b, xi, phi, scratch, contrib, cstress, kap, epsbar, estab,
                          fc_vert, f_dinv, f_area, zeta, fc_ptr, fc_tpl, fc_slot, True, fgrad,
                          False)
            if ch + 1 == tile_ch[t + 1]:
                dw, dd, db = _gather_update(gl_ptr[t], gl_ptr[t + 1], gl_vert, vf_ptr, vf_row,
                                            frow, tr_ptr, tr_slot, contrib, x, v, force,
                                            f_applied, mass, damp, pinned, gravity, dt, vmax2)
                w += dw
                d += dd
                b += db
                t += 1
        pacc[p, 0] = w
        pacc[p, 1] = d
        pacc[p, 2] = b


@kernel()
def variational_stages(x, ops, mat, work):
    """Everything of the variational force but the final gather: the face and stencil
    gradients (work arrays). The face strains and the coupling stress are stored only
    when phi != 0 (the coupling reads them); kap, epsbar and the residual energy come
    from forces.vertex_fields, not from here."""
    faces, dinv, face_area, K = ops[0], ops[1], ops[2], ops[3]
    zeta, phi = mat[0], mat[2]
    eps, cstress, fgrad = work[0], work[1], work[5]
    if phi != 0.0:          # the vertex terms read eps: faces first, in their own pass
        face_membrane(x, faces, dinv, face_area, zeta, eps, fgrad)
    vertex_pass(x, ops, mat, work, phi == 0.0)
    if phi != 0.0:
        face_coupling(x, faces, dinv, face_area, K, cstress, fgrad)


@kernel()
def variational_forces(x, ops, mat, work, force):
    """Internal force -dE/dx (n,3) [N] of the discrete Cosserat energy at positions x."""
    variational_stages(x, ops, mat, work)
    gather_forces(ops[15], ops[17], work[5], ops[13], ops[14], work[6], force)


@kernel(parallel=True)
def integrate(ops, work_arrays, gather, x, v, force, f_applied, mass, damp, pinned, gravity,
              dt, vmax2, acc):
    """One symplectic Euler update in place of every vertex; returns the number of them
    that went bad (non-finite or faster than sqrt(vmax2)). With ``gather`` the last stage
    of the variational force (the gather of corner and stencil gradients) runs in the same
    pass and fills ``force``; otherwise ``force`` is read as given.

    The vertices go in chunks (as many as the rows of ``work_arrays[9]``), shared between
    the threads as in :func:`vertex_pass`. Each chunk sums its external work and
    dissipation into its own row, and those rows are added in chunk order after the pass,
    so ``acc`` gets the same sums whichever thread ran which chunk."""
    fgrad, contrib, share, part = work_arrays[5], work_arrays[6], work_arrays[8], work_arrays[9]
    frow = fgrad.reshape((fgrad.shape[0] * 3, 3))
    n = x.shape[0]
    nch = part.shape[0]
    size = (n + nch - 1) // nch
    nr = split(share, nch)
    for t in nb.prange(nr):
        c, k = claim(share, t, nr, 0)
        while c >= 0:
            _update_chunk(c, size, gather, ops, frow, contrib, x, v, force, f_applied, mass,
                          damp, pinned, gravity, dt, vmax2, part)
            c, k = claim(share, t, nr, k)
    bad = 0
    for c in range(nch):
        acc[0] += part[c, 0]
        acc[1] += part[c, 1]
        bad += int(part[c, 2])
    return bad


@kernel(parallel=True)
def integrate_seam(ops, work_arrays, x, v, force, f_applied, mass, damp, pinned, gravity, dt,
                   vmax2, acc):
    """:func:`integrate` with the gather, for the seam vertices of the tiled step only
    (``gl_vert[gl_ptr[-2]:]``, ops[30], ops[31]), reading the gradients where
    :func:`vertex_parts` put them (ops[34], ops[36])."""
    tr_ptr, vf_ptr, gl_ptr, gl_vert = ops[13], ops[15], ops[30], ops[31]
    fgrad, contrib = work_arrays[5], work_arrays[6]
    frow = fgrad.reshape((fgrad.shape[0] * 3, 3))
    q0 = gl_ptr[gl_ptr.shape[0] - 2]
    work = 0.0
    diss = 0.0
    bad = 0
    for q in nb.prange(gl_ptr[gl_ptr.shape[0] - 1] - q0):
        q1 = q0 + np.int64(q)
        w, d, b = _gather_update(q1, q1 + 1, gl_vert, vf_ptr, ops[36], frow, tr_ptr, ops[34],
                                 contrib, x, v, force, f_applied, mass, damp, pinned, gravity,
                                 dt, vmax2)
        work += w
        diss += d
        bad += b
    acc[0] += work
    acc[1] += diss
    return bad


@kernel()
def run_variational(nsteps, x, v, f_applied, mass, damp, pinned, gravity, dt, vmax2, acc,
                    ops, mat, work, force):
    """Advance ``nsteps`` steps with the variational force (the default) in compiled code.
    Returns the number of completed steps; fewer than ``nsteps`` means step ``returned
    value`` diverged (state then invalid).

    A step is two parallel passes (phi = 0): faces (strains, membrane gradients) and
    vertices (jets, bending, stencil gradients) in one, then gather + update. With a
    coupling (phi != 0) the vertex terms read the face strains and the face coupling
    gradients read the vertex terms: four passes (faces, vertices, faces, gather +
    update). Without coupling, large meshes step with :func:`run_tiled` instead and small
    ones, on a threading layer that allows it, with :func:`run_fused` (the same two passes
    in one parallel region per call)."""
    for s in range(nsteps):
        variational_stages(x, ops, mat, work)
        if integrate(ops, work, True, x, v, force, f_applied, mass, damp, pinned,
                     gravity, dt, vmax2, acc) > 0:
            return s
    return nsteps


@kernel(parallel=True)
def run_fused(nsteps, x, v, f_applied, mass, damp, pinned, gravity, dt, vmax2, acc, ops, mat,
              work, force, nthr):
    """:func:`run_variational` without coupling (phi = 0) in one parallel region for all
    ``nsteps`` steps, of ``nthr`` iterations, one per thread (the threads numba runs, from
    Python). Per step: the vertex pass of :func:`vertex_pass` (faces included; chunks
    shared through ``work[8]``), a barrier (:func:`workshare.arrive`), the gather and
    update of :func:`integrate` (chunks shared through ``work[10]``), a barrier. Each
    work-sharing state is re-split by one thread while the others are in the other pass.
    Every thread then reads the chunks' bad counts, so that all leave at the same step,
    and one adds their work and dissipation to ``acc`` in chunk order. The same numbers
    as the two passes, to the bit, without opening two parallel regions per step (~2.2 us
    each on the 2-core machine, against ~0.14 us per barrier). Returns the steps done:
    fewer than ``nsteps`` when one went bad.

    The barrier waits for every iteration, so all ``nthr`` must run at once: the caller
    uses this kernel only on the OpenMP or workqueue layer with numba's static schedule
    (``ClothSimulator._share_threads``). With ``nsteps`` = 1 and ``dt`` = 0 it is the
    internal force alone (in ``force``; x and v stay as they are), which the critical dt
    uses, so that a process compiles the vertex code once."""
    # the operators unpacked as in vertex_pass: an inlined helper shared by the two
    # (same bits, same speed) took a cold start 12 s longer to compile
    (_, _, _, _, dual_area, ainv, rest_b, _, _, _, ln_uv, ln_sigma, stab,
     _, _, vf_ptr, vf_face, _, vf_K, g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr, ln_idx,
     ln_w, tile_ch, fc_ptr, fc_face, _, _, _, _, _, _, _, fc_vert, fc_tpl, f_dinv,
     f_area) = ops
    zeta, xi, phi = mat[0], mat[1], mat[2]
    eps, cstress, kap, epsbar, estab, fgrad, contrib, scratch, share, part, ushare, sync = work
    nch = tile_ch[tile_ch.shape[0] - 1]
    frow = fgrad.reshape((fgrad.shape[0] * 3, 3))
    nuc = part.shape[0]
    size = (x.shape[0] + nuc - 1) // nuc
    nr = split(share, nch)
    nu = split(ushare, nuc)
    sync[0] = 0
    sync[1] = nsteps
    for t in nb.prange(nthr):
        for s in range(nsteps):
            if t == 0 and s > 0:
                split(ushare, nuc)          # the others are in the vertex pass
            c, k = claim(share, t, nr, 0)
            while c >= 0:
                _vertex_chunk(c, nch, c, x, g_vert, g_ptr, g_wptr, s_vert, s_ptr, s_wptr,
                              ln_idx, ln_w, ln_uv, ln_sigma, stab, vf_ptr, vf_face, eps, vf_K,
                              dual_area, ainv, rest_b, xi, phi, scratch, contrib, cstress, kap,
                              epsbar, estab, fc_vert, f_dinv, f_area, zeta, fc_ptr, fc_tpl,
                              fc_face, True, fgrad, True)
                c, k = claim(share, t, nr, k)
            arrive(sync, 2 * s + 1, nthr)
            if t == 0:
                split(share, nch)           # the others are in the update
            c, k = claim(ushare, t, nu, 0)
            while c >= 0:
                _update_chunk(c, size, True, ops, frow, contrib, x, v, force, f_applied, mass,
                              damp, pinned, gravity, dt, vmax2, part)
                c, k = claim(ushare, t, nu, k)
            arrive(sync, 2 * s + 2, nthr)
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


@kernel()
def run_tiled(nsteps, x, v, f_applied, mass, damp, pinned, gravity, dt, vmax2, acc, ops, mat,
              work, force):
    """:func:`run_variational` for a large mesh without coupling (phi = 0): per step
    :func:`vertex_parts` (each thread its part, tile by tile, gathering and updating a
    tile's vertices while their gradients are in cache), then gather + update of the seam
    vertices between the parts. The same forces and update, vertex for vertex, in the same
    arithmetic order, so the same trajectory to the bit. A kernel of its own: a small
    mesh never compiles it."""
    pacc = np.zeros((ops[32].shape[0] - 1, 3))
    for s in range(nsteps):
        vertex_parts(x, ops, mat, work, v, force, f_applied, mass, damp, pinned, gravity, dt,
                     vmax2, pacc)
        bad = integrate_seam(ops, work, x, v, force, f_applied, mass, damp, pinned,
                             gravity, dt, vmax2, acc)
        for p in range(pacc.shape[0]):
            acc[0] += pacc[p, 0]
            acc[1] += pacc[p, 1]
            bad += int(pacc[p, 2])
        if bad > 0:
            return s
    return nsteps


@kernel()
def run_covariant(nsteps, x, v, f_applied, mass, damp, pinned, gravity, dt, vmax2, acc, ops,
                  cov, mat, cwork, work, force):
    """:func:`run_variational` with the seed's covariant-divergence force. A kernel of its
    own (not a branch of one stepping kernel), so that a process that never selects it
    never compiles it."""
    for s in range(nsteps):
        covariant_forces(x, ops, cov, mat, cwork, force)
        if integrate(ops, work, False, x, v, force, f_applied, mass, damp, pinned,
                     gravity, dt, vmax2, acc) > 0:
            return s
    return nsteps


def stability_limit(omega_max: float, gamma_max: float) -> float:
    """Largest stable dt of the damped symplectic Euler update for a mode of angular
    frequency omega with damping rate gamma = rho/mu: the Jury conditions of
    ``x'' = -omega^2 x - gamma x'`` give ``omega^2 dt^2 + 2 gamma dt < 4`` and
    ``gamma dt < 2``, i.e. ``dt < (sqrt(gamma^2 + 4 omega^2) - gamma) / omega^2``."""
    if omega_max <= 0:
        return np.inf if gamma_max <= 0 else 2.0 / gamma_max
    return (np.sqrt(gamma_max ** 2 + 4.0 * omega_max ** 2) - gamma_max) / omega_max ** 2
