"""A user's policy for test_batch.py: ``policy: {script: batch_script:push_up}``."""
import json
import os

import numpy as np


def push_up(sim, rng, episode):
    """Push every vertex up with 1.5 g for half the episode, then let go; note what it
    was handed."""
    draw = float(rng.random())
    n = sim.n_vertices
    mass = sim.material.density * 1.0 / n          # the grid's area is 1 m^2
    sim.set_vertex_forces(np.arange(n), np.tile([0.0, 0.0, 1.5 * 9.81 * mass], (n, 1)))
    steps = sim.remaining_steps
    sim.step(steps // 2)
    sim.clear_vertex_forces()
    sim.step(10 ** 9)                              # past the end: stops there
    with open(os.path.join(os.environ['BATCH_SCRIPT_OUT'], f'script_{episode.id}.json'),
              'w') as fh:
        json.dump({'seed': episode.seed, 'draw': draw, 'steps': sim.step_count}, fh)


def blow_up(sim, rng, episode):
    """100 kN on one vertex: past the elastic speed limit in one step (diverged)."""
    sim.set_vertex_forces([0], [[0.0, 0.0, 1e5]])
    sim.step(sim.remaining_steps)


def hang_first(sim, rng, episode):
    """Episode 0 never finishes (a user's script stuck); the others step as usual."""
    if episode.index == 0:
        import time
        time.sleep(3600)
    sim.step(sim.remaining_steps)
