"""Gymnasium environments of the cloth tasks (needs the ``envs`` extra: gymnasium).

Importing this package registers::

    cosserat_ros/ClothFlatten-v0   ClothFold-v0   ClothDrop-v0

so that ``import cosserat_ros.envs; gymnasium.make('cosserat_ros/ClothFold-v0',
**options)`` works (Gymnasium 1.x has no plugin entry points: ``gymnasium.make`` with the
module prefix, ``'cosserat_ros.envs:cosserat_ros/ClothFold-v0'``, imports it for you).
The scene, actions and observations: :mod:`.cloth`; the tasks and their metrics:
:mod:`.tasks`.
"""
from gymnasium.envs.registration import register, registry

from .cloth import ACTION_MODES, OBS_MODES, ClothEnv, env_coverage
from .tasks import ClothDrop, ClothFlatten, ClothFold, fold_distance, fold_groups

__all__ = ['ClothEnv', 'ClothFlatten', 'ClothFold', 'ClothDrop', 'ENV_IDS', 'ACTION_MODES',
           'OBS_MODES', 'env_coverage', 'fold_distance', 'fold_groups', 'make_vector_env']

#: the registered ids and their classes
ENV_IDS = {'cosserat_ros/ClothFlatten-v0': 'cosserat_ros.envs.tasks:ClothFlatten',
           'cosserat_ros/ClothFold-v0': 'cosserat_ros.envs.tasks:ClothFold',
           'cosserat_ros/ClothDrop-v0': 'cosserat_ros.envs.tasks:ClothDrop'}

for _id, _entry in ENV_IDS.items():
    if _id not in registry:
        # the episode's end is the environment's own horizon (truncated), so no
        # TimeLimit wrapper: max_episode_steps stays None
        register(id=_id, entry_point=_entry, disable_env_checker=False)


def _make_one(env_id: str, threads: int, options: dict):
    """In a vector's worker process: the kernels' thread count, then the environment
    (its kernels load from numba's on-disk cache, compiled once per machine)."""
    import gymnasium as gym
    import numba
    numba.set_num_threads(threads)
    return gym.make(env_id, **options)


def make_vector_env(env_id: str, num_envs: int, threads_per_env: int = 1, **options):
    """A :class:`gymnasium.vector.AsyncVectorEnv` of ``num_envs`` environments ``env_id``
    (``options`` as :func:`gymnasium.make`'s), one worker process each with
    ``threads_per_env`` numba threads (one per core: 2 workers on 2 cores). Each
    environment's results are the same bits as the same environment alone with the same
    thread count."""
    import functools

    import gymnasium as gym
    if env_id not in ENV_IDS:
        raise ValueError(f'env_id must be one of {sorted(ENV_IDS)}, got {env_id!r}')
    if not (isinstance(num_envs, int) and num_envs >= 1):
        raise ValueError(f'num_envs must be an integer >= 1, got {num_envs!r}')
    if not (isinstance(threads_per_env, int) and threads_per_env >= 1):
        raise ValueError(f'threads_per_env must be an integer >= 1, got {threads_per_env!r}')
    fn = functools.partial(_make_one, env_id, threads_per_env, options)
    return gym.vector.AsyncVectorEnv([fn] * num_envs, context='spawn')
