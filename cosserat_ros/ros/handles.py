"""The node's grasp handles: ``handles.names``, and per handle ``~/handles/<n>/target``
(in), ``~/handles/<n>/grasp`` (service) and ``~/handles/<n>/wrench`` (out).

Parameters per handle: ``handles.<n>.radius`` [m] and ``handles.<n>.break_force`` [N] (0:
none) (:data:`.params.HANDLE_KEYS`); ``handles.max_speed`` [m/s] bounds every held
handle's motion. The grasp itself, the waypoints and the exact wrench are the simulator's
(:mod:`cosserat_ros.core.handles`).
"""
from __future__ import annotations

from typing import Dict

import numpy as np
from geometry_msgs.msg import PoseStamped, WrenchStamped
from std_srvs.srv import SetBool

from ..core.handles import MAX_WAYPOINTS, turn_angle
from . import commands, messages
from .params import ConfigError, group_names, HANDLE_KEYS

__all__ = ['HandleStreams']


class HandleStreams:
    """The handles of a node: ``streams[name]`` is a dict with ``radius``,
    ``break_force``, ``id`` (the simulator's handle while it holds the cloth, else None),
    ``target`` (the last accepted pose) and ``received`` (its sim time)."""

    def __init__(self, node, names, max_speed: float, qos):
        self.node = node
        self.sim = node.sim
        self.max_speed = max_speed                   # [m/s] handles.max_speed
        self.streams: Dict[str, dict] = {}
        for name in group_names('handles', names):
            cfg = node._declare_group('handles', name, HANDLE_KEYS, 'handle')
            if not (isinstance(cfg['radius'], float) and cfg['radius'] > 0):
                raise ConfigError(f'handles.{name}.radius must be a positive float, got '
                                  f'{cfg["radius"]!r}')
            if not (isinstance(cfg['break_force'], float) and cfg['break_force'] >= 0):
                raise ConfigError(f'handles.{name}.break_force must be a float >= 0 (0: '
                                  f'none), got {cfg["break_force"]!r}')
            h = {'radius': cfg['radius'], 'break_force': cfg['break_force'] or None,
                 'id': None, 'target': None, 'received': None,
                 'wrench': node.create_publisher(WrenchStamped, f'~/handles/{name}/wrench',
                                                 qos)}
            if not node.observe_only:
                # deep: a controller may stream a whole trajectory of stamped targets
                # at once (MAX_WAYPOINTS ahead), which a last-10 reader would cut
                node.create_subscription(PoseStamped, f'~/handles/{name}/target',
                                         lambda msg, n=name: self.on_target(n, msg),
                                         MAX_WAYPOINTS)
                node.create_service(SetBool, f'~/handles/{name}/grasp',
                                    lambda req, res, n=name: self.on_grasp(n, req, res))
            self.streams[name] = h

    def __len__(self):
        return len(self.streams)

    def on_target(self, name: str, msg: PoseStamped):
        """A pose for handle ``name``: places it if it holds nothing; if it holds the
        cloth, moves it there: with a header stamp of zero over the sim time since the
        previous target (at least a tick, at most 1 s), starting from where the handle is;
        with a stamp T, a sim time ahead of the node's, arriving at T after the targets
        already given before T (a trajectory streamed ahead; a stamp not ahead is
        refused as late).

        The speed is checked from where the motion starts (the handle now, or the
        waypoint before T), its turn counted at the grasp radius: ``(|p - p_from| + theta
        r) / (t - t_from)`` must not exceed ``handles.max_speed``. From where the handle
        is, not from the last target: many targets in one tick, or while paused, would
        each be one short hop and add up to a jump."""
        h = self.streams[name]
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        offending: Dict[str, object] = {'stamp': float(stamp)}
        try:
            p, q = commands.handle_target(msg, self.node.frame_id)
            offending.update(x=float(p[0]), y=float(p[1]), z=float(p[2]))
            if h['id'] is not None and h['id'] in self.sim.handles:
                self._move(name, h, p, q, stamp, offending)
        except commands.CommandError as exc:
            self.node._reject('handles', f'{name}: {exc}', f'handles/{name}/target',
                              offending)
            return
        h['target'], h['received'] = (p, q), self.sim.time
        self.node._dirty = True

    def _move(self, name: str, h: dict, p, q, stamp: float, offending: dict):
        """Move held handle ``name`` to (p, q): at sim time ``stamp`` if it is not zero,
        else over the time since the previous target; CommandError if too fast or late."""
        now, period = self.sim.time, self.node.period
        if stamp > 0:
            if stamp <= now:
                raise commands.CommandError(
                    f'stamped {stamp:.4f} s, not ahead of the simulation time {now:.4f} s '
                    f'({now - stamp:.4f} s late): a stamped target says when to be there')
            before = [w for w in self.sim.handle_waypoints(h['id']) if w[0] < stamp]
            t_from, p_from, q_from = before[-1]
            interval = stamp - t_from
        else:
            d = self.sim.handles[h['id']]
            t_from, p_from, q_from = now, np.asarray(d['position']), d['orientation']
            interval = period
            if h['target'] is not None:
                interval = min(max(now - h['received'], period), 1.0)
        theta = turn_angle(np.asarray(q_from), q)
        speed = (float(np.linalg.norm(p - np.asarray(p_from))) + theta * h['radius']) / interval
        offending['speed'] = speed
        if speed > self.max_speed:
            since = f'at {t_from:.4f} s ' if stamp > 0 else ''
            raise commands.CommandError(
                f'target {speed:.3g} m/s from where the handle is {since}(its turn at the '
                f'grasp radius included), above handles.max_speed {self.max_speed:.3g}')
        if stamp > 0:
            try:
                self.sim.move_handle(h['id'], p, q, at=stamp)
            except ValueError as exc:                 # too many waypoints ahead
                raise commands.CommandError(str(exc)) from None
        else:
            self.sim.move_handle(h['id'], p, q, duration=interval)

    def on_grasp(self, name: str, request, response):
        """``~/handles/<name>/grasp``: true grasps the cloth under the last target (within
        the handle's radius), false releases it."""
        h = self.streams[name]
        self.node._dirty = True
        response.success = True
        if not request.data:
            if h['id'] is not None and h['id'] in self.sim.handles:
                self.sim.release(h['id'])
            h['id'] = None
            response.message = f'{name} released'
        elif h['id'] is not None:
            response.message = f'{name} holds the cloth already'
        elif h['target'] is None:
            response.success = False
            response.message = (f'no target for {name} yet: publish '
                                f'~/handles/{name}/target first')
        else:
            p, q = h['target']
            try:
                h['id'] = self.sim.grasp(point=p, radius=h['radius'], name=name,
                                         break_force=h['break_force'], orientation=q)
            except ValueError as exc:
                response.success, response.message = False, str(exc)
                return response
            response.message = (f'{name} holds {len(self.sim.handles[h["id"]]["vertices"])} '
                                'vertices')
        return response

    def publish(self, stamp: int):
        """Each handle's wrench on the cloth (zero while it holds nothing); a handle that
        broke loose is noted as released."""
        held = self.sim.handles
        for h in self.streams.values():
            if h['id'] is not None and h['id'] not in held:
                h['id'] = None                       # it broke loose
            f = t = np.zeros(3)
            if h['id'] is not None:
                f, t = self.sim.handle_wrench(h['id'])
                if not (np.all(np.isfinite(f)) and np.all(np.isfinite(t))):
                    continue
            h['wrench'].publish(messages.wrench(stamp, self.node.frame_id, f, t))

    def restart(self):
        """After a reset: every handle holds nothing, its next target starts afresh."""
        for h in self.streams.values():
            h['id'] = None
            h['received'] = 0.0
