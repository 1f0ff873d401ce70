"""What the node says about itself: refused inputs (``~/rejections``, counted in
``/diagnostics``) and the ``/diagnostics`` status of the simulation.

The messages themselves are built by :mod:`.messages` (:func:`.messages.rejection`,
:func:`.messages.status`); this module decides their content.
"""
from __future__ import annotations

import threading
import time
from typing import Dict, Optional

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.qos import QoSProfile

from . import messages

__all__ = ['Rejections', 'Progress', 'diagnostics', 'solver_warning',
           'MAX_REJECTIONS_PER_TICK']

#: the most refusals published on ~/rejections between two ticks (the rest are counted
#: in /diagnostics and logged, throttled): a flood of bad input costs bounded work
MAX_REJECTIONS_PER_TICK = 20

#: the counters of refused inputs, one per input (``rejected_<name>`` in /diagnostics)
COUNTERS = ('vertex_forces', 'point_forces', 'force_field', 'wind', 'obstacles', 'handles',
            'cameras')


class Rejections:
    """Refuses inputs for ``node``: counts them (``counts``, the node's ``rejected``),
    logs them (throttled) and publishes them on ``~/rejections``."""

    def __init__(self, node):
        self.node = node
        self.counts: Dict[str, int] = {k: 0 for k in COUNTERS}
        self.sent = 0                            # published since the last tick
        self.pub = node.create_publisher(DiagnosticStatus, '~/rejections', QoSProfile(depth=50))

    def __call__(self, counter: str, reason: str, topic: Optional[str] = None,
                 values: Optional[Dict[str, object]] = None):
        """Refuse an input: count it under ``counter``, log it and publish it on
        ``~/rejections`` (:func:`.messages.rejection`; at most
        :data:`MAX_REJECTIONS_PER_TICK` between two ticks) named ``<node>/<topic>``
        (default: the counter's topic) with ``values``, the offending values."""
        self.counts[counter] += 1
        topic = counter if topic is None else topic
        node = self.node
        node.get_logger().warning(f'rejected ~/{topic}: {reason} '
                                  f'({self.counts[counter]} rejected so far)',
                                  throttle_duration_sec=1.0)
        if self.sent < MAX_REJECTIONS_PER_TICK:
            self.sent += 1
            fqn = node.get_fully_qualified_name()
            self.pub.publish(messages.rejection(f'{fqn}/{topic}', reason, node.sim.time,
                                                values or {}, fqn))


def solver_warning(report: Dict[str, object], tolerance: float) -> Optional[str]:
    """The WARN message of an implicit step's solve (``ClothSimulator.solve_report``), or
    None: an unconverged solve warns, the linearised solver (``linearized``: one Newton
    step a step by design) does not; both report their residual."""
    if report['converged'] or report['linearized']:
        return None
    return (f"implicit solve not converged (residual {report['residual']:.2g} > "
            f'solver.tolerance {tolerance:g})')


def _level(node):
    """(level, message) of the simulation's status: diverged, lagging, paused or OK."""
    if node.diverged:
        return DiagnosticStatus.ERROR, 'diverged: ' + node.diverged
    if node.pacer.lagging or (not node.paused and node.rtf < 0.9 * node.pacer.factor):
        return DiagnosticStatus.WARN, (f'cannot keep the real-time factor asked for (RTF '
                                       f'{node.rtf:.2f} of {node.pacer.factor:g})')
    if node.paused:
        return DiagnosticStatus.WARN, 'paused'
    return DiagnosticStatus.OK, 'running'


def _contact_values(sim) -> Dict[str, object]:
    """The obstacles' and the self-collision's counts of the last step."""
    vals: Dict[str, object] = {}
    if sim.obstacles:
        cs = sim.contact_state()
        vals.update(contacts=cs['contacts'], deepest_penetration_m=float(cs['deepest']),
                    feature_pairs=cs['feature_pairs'], feature_active=cs['feature_active'],
                    released_vertices=cs['released'])
    if sim.self_collision:
        sc = sim.self_contact_state()
        vals.update(self_pairs_active=sc['active'], self_pairs_live=sc['live'],
                    self_pairs_short=sc['left_short'],
                    self_closest_gap_m=float(sc['closest_gap']))
    return vals


def diagnostics(node) -> DiagnosticArray:
    """The node's ``/diagnostics``: level and message (:func:`_level`, an unconverged
    implicit solve warns), the pacing, the step, the mesh, the inputs refused so far and
    the contact counts."""
    sim = node.sim
    crit = sim.critical_dt()
    level, msg = _level(node)
    vals = {'real_time_factor': float(node.rtf),
            'real_time_factor_asked': float(node.pacer.factor),
            'step_cost_ms': float(node.pacer.step_cost * 1e3),
            'publish_cost_ms': float(node.pacer.publish_cost * 1e3),
            'dt': float(sim.dt), 'critical_dt': float(crit),
            'dt_over_critical': float(sim.dt / crit),
            'vertices': node.mesh.n_vertices, 'faces': node.mesh.n_faces,
            'sim_time': float(sim.time), 'paused': node.paused,
            'rejected_total': sum(node.rejected.values()), 'obstacles': len(sim.obstacles),
            'air': sim.air is not None, 'wind_speed': float(np.linalg.norm(sim.wind)),
            'solver': sim.solver_kind}
    if node.implicit:
        r = sim.solve_report
        vals.update({'solver_iterations': r['iterations'],
                     'solver_cg_iterations': r['cg_iterations'],
                     'solver_residual': float(r['residual']),
                     'solver_converged': r['converged'],
                     'solver_unconverged_steps': r['unconverged_steps']})
        warning = solver_warning(r, sim.solver_tolerance)
        if warning is not None and level == DiagnosticStatus.OK:
            level, msg = DiagnosticStatus.WARN, warning
    vals.update(_contact_values(sim))
    vals.update({f'rejected_{k}': v for k, v in node.rejected.items()})
    return messages.status(node.stamp_ns(), node.frame_id, f'{node.get_name()}: simulation',
                           level, msg, vals, node.get_fully_qualified_name())


class Progress:
    """Says ``what`` once at the start and then every ``period`` seconds with the time
    so far, from a thread of its own, until :meth:`stop` (or the ``with`` block's end):
    a long wait that blocks the main thread (a cold start's compilation) is not
    silent."""

    def __init__(self, log, what: str, period: float = 15.0):
        self.log, self.what, self.period = log, what, period
        self.t0 = time.monotonic()
        self.done = threading.Event()
        self.log.info(what)
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while not self.done.wait(self.period):
            self.log.info(f'{self.what}: {time.monotonic() - self.t0:.0f} s so far')

    def stop(self):
        self.done.set()
        self.thread.join()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
