"""Leave no Ray process behind a driver that was killed outright.

Ray starts the processes of a private instance sharing the driver's fate, but on a SIGKILL
of the driver some outlive it (seen with Ray 2.60: the dashboard and runtime-env agents
notice that their raylet is gone and then hang on their way out). So the driver that
starts a private instance also starts this watcher, in a session of its own, with a pipe
on its standard input::

    python -m cosserat_ros.batch.reaper

The driver writes to the pipe the pids of the processes ``ray.init`` started (its
children that were not there before). Until the pipe closes (the driver ended, however),
the watcher notes every few tenths of a second those processes and their descendants
(Linux ``/proc``: pid and start time); then it kills those still there, and their own
descendants, with SIGKILL. Nothing else of the driver's is touched (a driver inside a
test or a notebook has other children). A process is killed only if its start time
is the one noted, so a reused pid is never hit. After a clean ``ray.shutdown()`` there is
nothing left to kill.
"""
from __future__ import annotations

import os
import select
import signal
import sys
from typing import Dict

__all__ = ['descendants', 'start']

#: [s] how often the descendants are noted
PERIOD = 0.3


def _stat(pid: int):
    """(parent pid, start time in clock ticks) of ``pid``, or None if it is gone."""
    try:
        with open(f'/proc/{pid}/stat', 'rb') as fh:
            data = fh.read()
    except OSError:
        return None
    fields = data[data.rfind(b')') + 2:].split()
    return int(fields[1]), int(fields[19])


def descendants(root: int) -> Dict[int, int]:
    """{pid: start time} of every process below ``root``."""
    children: Dict[int, list] = {}
    starts: Dict[int, int] = {}
    for name in os.listdir('/proc'):
        if name.isdigit():
            st = _stat(int(name))
            if st is not None:
                children.setdefault(st[0], []).append(int(name))
                starts[int(name)] = st[1]
    out, todo = {}, [root]
    while todo:
        for c in children.get(todo.pop(), ()):
            if c not in out:
                out[c] = starts[c]
                todo.append(c)
    return out


def main(argv=None) -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)      # a Ctrl-C is the driver's to handle
    seen: Dict[int, int] = {}
    roots: Dict[int, int] = {}
    buf = b''
    while True:
        for pid, started in list(roots.items()):
            if _stat(pid) is not None and _stat(pid)[1] == started:
                seen[pid] = started
                seen.update(descendants(pid))
        ready, _, _ = select.select([sys.stdin], [], [], PERIOD)
        if ready:
            data = os.read(sys.stdin.fileno(), 4096)
            if not data:
                break                                  # EOF: the driver is gone
            buf += data
            *lines, buf = buf.split(b'\n')
            for line in lines:
                for pid in line.split():
                    st = _stat(int(pid))
                    if st is not None:
                        roots[int(pid)] = st[1]
    for pid, started in list(seen.items()):
        seen.update(descendants(pid))                  # what they started since
    for pid, started in seen.items():
        st = _stat(pid)
        if st is not None and st[1] == started and pid != os.getpid():
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
    return 0


def start():
    """Start the watcher (Linux only; None elsewhere). Keep the returned Popen: write
    the pids to watch to its stdin (:func:`watch`); closing it (or this process's end)
    sets it off."""
    import subprocess
    if not os.path.isdir('/proc'):
        return None
    return subprocess.Popen([sys.executable, '-m', 'cosserat_ros.batch.reaper'],
                            stdin=subprocess.PIPE, start_new_session=True, close_fds=True)


def watch(reaper, pids) -> None:
    """Have ``reaper`` (:func:`start`'s) watch ``pids`` and what they start."""
    if reaper is not None and pids:
        reaper.stdin.write((' '.join(str(p) for p in pids) + '\n').encode())
        reaper.stdin.flush()


def stop(reaper) -> None:
    """Close the pipe (the watcher kills what is left of its pids) and wait for it."""
    if reaper is not None:
        try:
            reaper.stdin.close()
        except OSError:
            pass
        reaper.wait(timeout=30)


if __name__ == '__main__':
    sys.exit(main())
