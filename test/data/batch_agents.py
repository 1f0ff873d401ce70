"""Agents of a user for test_batch_envs.py: ``env: {agent: batch_agents:<name>}``."""
import numpy as np


def corner_to_centre(env, obs):
    """Pick the cloth where its first vertex lies (from the observation) and place it at
    the start's centre."""
    x = np.asarray(obs['positions'], dtype=float)
    a = np.zeros((env.num_pickers, 4), np.float32)
    a[:, :2] = np.clip((x[0, :2] - env.centre0) / env.cloth_size, -1.0, 1.0)
    return a


def raises(env, obs):
    raise RuntimeError('this agent gives up')


def wrong_shape(env, obs):
    return np.zeros(3)


def blow_up(env, obs):
    """Twenty times the stable step and a shaken cloth: the step diverges."""
    env.sim.dt = 20 * env.sim.critical_dt()
    rng = np.random.default_rng(0)
    env.sim.set_velocities(rng.normal(0.0, 1.0, env.sim.positions.shape))
    return np.zeros((env.num_pickers, 4), np.float32)
