"""The executables' entry points (``setup.py``'s console scripts): each imports its module
only when called, so that a Ctrl-C or SIGTERM while numba, numpy and rclpy load (a second
or more) ends the program with one line instead of a traceback."""
from __future__ import annotations

import importlib
import signal
import sys

__all__ = ['cloth_node', 'record', 'render', 'fold_demo', 'flag_demo', 'batch']


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def _interrupted(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is ``exc`` or behind it (its cause or context)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def _run(program: str, module: str) -> int:
    # SIGTERM during the imports ends the program as SIGINT does (rclpy installs its own
    # handlers once it is up)
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        main = importlib.import_module(module).main
    except BaseException as exc:
        # a library's import may wrap the interrupt in its own error (rclpy's loader of
        # its C extension raises an AssertionError from it)
        if not _interrupted(exc):
            raise
        print(f'{program}: interrupted while starting', file=sys.stderr)
        return 130
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    return main()


def cloth_node() -> int:
    return _run('cloth_node', 'cosserat_ros.ros.node')


def record() -> int:
    return _run('record', 'cosserat_ros.tools.record')


def render() -> int:
    return _run('render', 'cosserat_ros.tools.render')


def fold_demo() -> int:
    return _run('fold_demo', 'cosserat_ros.tools.fold_demo')


def flag_demo() -> int:
    return _run('flag_demo', 'cosserat_ros.tools.flag_demo')


def batch() -> int:
    return _run('batch', 'cosserat_ros.batch.cli')
