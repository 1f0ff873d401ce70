"""Randomized cloth episodes at scale, on Ray: ``batch run SPEC.yaml -o OUT``.

The pieces, each usable alone:

* :func:`load_spec` -- a YAML spec (or dict) checked whole (:mod:`.spec`);
* :func:`plan` -- every episode resolved from the spec's seed and its index (pure);
* :func:`run_episode` -- one episode into ``OUT/episodes/<id>/`` (pure: no Ray, no ROS
  graph; :mod:`.episode`);
* :func:`run_batch` -- all of them as Ray tasks, exactly one manifest line each
  (:mod:`.engine`); the command line is :mod:`.cli`.
"""
from .engine import read_manifest, run_batch
from .episode import run_episode
from .spec import Episode, SpecError, load_spec, plan

__all__ = ['load_spec', 'plan', 'run_episode', 'run_batch', 'read_manifest', 'Episode',
           'SpecError']
