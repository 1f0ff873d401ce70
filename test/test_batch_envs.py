"""The batch engine runs episodes of the Gymnasium environments with an agent:
the spec's ``env``, its refusals, and episodes the same as the environment run directly
(cosserat_ros/batch/env_episode.py)."""
import json
from pathlib import Path
import sys

import pytest
import yaml

gym = pytest.importorskip('gymnasium')

from cosserat_ros.batch import SpecError, load_spec, plan, run_episode  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent / 'data'))

FOLD = {'id': 'cosserat_ros/ClothFold-v0', 'options': {'resolution': 6, 'num_pickers': 2}}


def env_spec(episodes=2, **env):
    return {'batch': 1, 'seed': 5, 'episodes': episodes, 'env': {**FOLD, **env}}


def direct(episode, agent):
    """The episode's environment run without the batch: return, actions, final info."""
    e = gym.make(episode.policy['id'], **episode.policy['options'])
    try:
        obs, info = e.reset(seed=episode.seed)
        ret, n, done = 0.0, 0, False
        while not done:
            obs, r, te, tr, info = e.step(agent(e.unwrapped, obs))
            ret, n, done = ret + r, n + 1, te or tr
        return ret, n, info
    finally:
        e.close()


@pytest.mark.parametrize('change, words', [
    ({'duration': 1.0}, ['duration', 'env.options']),
    ({'scene': {'mesh.nx': 4}}, ['scene', 'drop scene']),
    ({'env': {'id': 'cosserat_ros/ClothIron-v0'}}, ['env.id', 'ClothFold-v0']),
    ({'env': {**FOLD, 'options': {'resolution': 1}}}, ['env.options', 'resolution']),
    ({'env': {**FOLD, 'options': {'colour': 'red'}}}, ['env.options', 'colour']),
    ({'env': {**FOLD, 'options': {'action_mode': 'handle_delta'}}},
     ['env.agent', 'pick_place']),
    ({'env': {**FOLD, 'agent': 'no_such_module:f'}}, ['env.agent', 'cannot import']),
    ({'env': {**FOLD, 'agent': 'batch_agents:nothing'}}, ['env.agent', "has no 'nothing'"]),
    ({'env': {**FOLD, 'options': {'randomize': {'material.damping': {'uniform': [0.1, 1e9]}}}}},
     ['env.options', 'material.damping']),
    ({'env': {**FOLD, 'steps': 3}}, ['env.steps', 'unknown key']),
    ({'env': {**FOLD, 'options': {'render_mode': 'rgb_array'}}}, ['render_mode']),
])
def test_a_bad_env_spec_is_refused_with_the_key_and_why(change, words):
    s = {**env_spec(), **change}
    with pytest.raises(SpecError) as info:
        load_spec(s)
    msg = str(info.value)
    assert '\n' not in msg
    for w in words:
        assert w in msg, (w, msg)


def test_an_env_spec_loads_to_itself_and_plans_a_seed_per_episode():
    s = load_spec(env_spec(episodes=3, agent='random'))
    assert s == load_spec(s)
    assert s['env'] == {**FOLD, 'agent': 'random'}
    eps = plan(s)
    assert [e.policy for e in eps] == [{'kind': 'env', **FOLD, 'agent': 'random'}] * 3
    assert len({e.seed for e in eps}) == 3
    # the seeds are the scene specs' own: episode i's draw from (seed, i) alone
    assert [e.seed for e in plan(load_spec(env_spec(episodes=2)))] == [e.seed for e in
                                                                        eps[:2]]


@pytest.mark.slow
def test_an_env_episode_is_the_environment_run_directly_with_its_seed(tmp_path):
    from cosserat_ros.envs.experts import random_agent
    from rosbags.highlevel import AnyReader
    eps = plan(load_spec(env_spec(episodes=2, agent='random',
                                  options={**FOLD['options'], 'horizon': 3})))
    results = [run_episode(ep, tmp_path) for ep in eps]
    for ep, res in zip(eps, results):
        assert res['status'] == 'ok', res['error']
        m = res['metrics']
        ret, n, info = direct(ep, lambda e, obs: random_agent(e))
        assert (m['return'], m['actions'], m['fold_distance'], m['success']) == (
            ret, n, info['fold_distance'], info['success'])           # to the bit
        assert n == 3 and m['truncated'] and not m['terminated']
        assert res['sim_time'] == info['sim_time']
        d = tmp_path / 'episodes' / ep.id
        assert yaml.safe_load((d / 'env.yaml').read_text()) == {
            'id': FOLD['id'], 'options': {**FOLD['options'], 'horizon': 3},
            'agent': 'random', 'seed': ep.seed}
        assert not (d / 'params.yaml').exists()
        with AnyReader([d / 'bag']) as reader:
            meshes = [t for c, t, _ in reader.messages() if c.topic == '/cloth_node/mesh']
        assert len(meshes) == n + 1                  # after the reset and each action
        assert meshes[-1] == round(info['sim_time'] * 1e9)
        assert json.loads((d / 'result.json').read_text()) == res
    assert results[0]['metrics']['return'] != results[1]['metrics']['return']
    # the same episode again: the same bytes
    again = run_episode(eps[1], tmp_path / 'again')
    assert again['bag_sha256'] == results[1]['bag_sha256']


@pytest.mark.slow
def test_the_expert_and_a_user_agent_act_and_a_failing_agent_fails_the_episode(tmp_path):
    from cosserat_ros.envs.experts import fold_expert
    ep = plan(load_spec(env_spec(episodes=1)))[0]
    res = run_episode(ep, tmp_path / 'expert')
    ret, n, info = direct(ep, lambda e, obs: fold_expert(e))
    assert res['status'] == 'ok' and res['metrics']['success'] and info['success']
    assert res['metrics']['return'] == ret and res['metrics']['terminated']

    import batch_agents
    ep = plan(load_spec(env_spec(episodes=1, agent='batch_agents:corner_to_centre',
                                 options={**FOLD['options'], 'horizon': 2})))[0]
    res = run_episode(ep, tmp_path / 'user')
    ret, n, info = direct(ep, batch_agents.corner_to_centre)
    assert res['status'] == 'ok' and (res['metrics']['return'], res['metrics']['actions'],
                                      ) == (ret, n)
    for name, words in (('raises', ['agent batch_agents:raises at action 0', 'RuntimeError',
                                    'this agent gives up']),
                        ('wrong_shape', ['agent batch_agents:wrong_shape at action 0',
                                         'ValueError']),
                        ('blow_up', ['the simulation diverged at action 1'])):
        ep = plan(load_spec(env_spec(episodes=1, agent=f'batch_agents:{name}')))[0]
        res = run_episode(ep, tmp_path / name)
        assert res['status'] == 'failed' and res['metrics'] is None
        for w in words:
            assert w in res['error'], res['error']
        assert not (tmp_path / name / 'episodes' / ep.id / 'bag').exists()
