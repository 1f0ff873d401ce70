"""The ``cloth_node`` executable: start a :class:`.node.ClothNode`, spin it, stop it.

A bad parameter, params file or an unmet security request ends it with exit status 2 and
one line on stderr (``cloth_node: error: <reason>``); SIGINT and SIGTERM end it cleanly
(status 0), also while it starts.
"""
from __future__ import annotations

import os
import sys
from typing import Optional

import rclpy
from rclpy.executors import ExternalShutdownException

from .params import ConfigError

__all__ = ['main']


def _security_requested() -> bool:
    return os.environ.get('ROS_SECURITY_ENABLE', '').lower() == 'true'


def _security_reason(exc: Exception) -> Optional[str]:
    """The one-line reason to give when ROS security was requested and rcl failed: the
    middleware's own first line, what was asked for, and where to look (README)."""
    if not _security_requested():
        return None
    text = str(exc).strip().splitlines()
    first = text[0] if text else type(exc).__name__
    if 'security libraries' in str(exc):
        first = 'this middleware (the PyPI Fast DDS) has no security libraries'
    keystore = os.environ.get('ROS_SECURITY_KEYSTORE', '')
    return (f'ROS security requested (ROS_SECURITY_ENABLE=true, strategy '
            f'{os.environ.get("ROS_SECURITY_STRATEGY", "Permissive")}, keystore '
            f'{keystore or "unset"}) but it cannot be provided: {first}; see doc/node.md, '
            '"Security"')


def main(args=None) -> int:
    """Entry point of the ``cloth_node`` executable (``ros2 run cosserat_ros cloth_node``)."""
    try:
        rclpy.init(args=args)
    except Exception as exc:       # e.g. an unreadable --params-file
        reason = _security_reason(exc) or str(exc).strip().splitlines()[0]
        print(f'cloth_node: error: {reason}', file=sys.stderr)
        return 2
    node = None
    code = 0
    if _security_requested():
        # rclpy's own note while it undoes a node that security kept from starting
        import warnings
        warnings.filterwarnings('ignore', message='Failed to fini rosout publisher')
    # A Ctrl-C that lands while a C library runs a callback into Python (llvmlite's, as
    # numba loads a cached kernel) cannot propagate: Python prints it as "Exception
    # ignored" with a traceback and goes on. Note it instead, and end once out of it.
    interrupts = []
    default_hook = sys.unraisablehook

    def quiet(unraisable):
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            interrupts.append(unraisable.exc_value)
        else:
            default_hook(unraisable)
    sys.unraisablehook = quiet
    try:
        from .node import ClothNode
        node = ClothNode(argv=args)                  # None: sys.argv, as rclpy.init
        if interrupts:
            raise KeyboardInterrupt
        rclpy.spin(node)
    except ConfigError as exc:
        print(f'cloth_node: error: {exc}', file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:
        reason = _security_reason(exc) if node is None else None
        if reason is not None:                   # the node could not even be created
            print(f'cloth_node: error: {reason}', file=sys.stderr)
            code = 2
        # SIGINT/SIGTERM shut the context down while a tick was publishing: the publish
        # fails with an RCLError. That is a shutdown, not a failure; anything else is.
        elif rclpy.ok():
            raise
    finally:
        sys.unraisablehook = default_hook
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code
