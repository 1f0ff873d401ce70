"""The manual (doc/, built by ``make docs``) against the code: the parameter and topic
tables are generated from the node's declarations, the README stays the short front
door."""
import os
import re
import sys

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, 'doc', '_ext'))

from cosserat_ros.ros.params import PARAMETERS  # noqa: E402
from cosserat_ros.ros.interfaces import INTERFACES  # noqa: E402
from parameters_page import interfaces_table, parameters_table  # noqa: E402


def test_the_parameter_page_lists_every_declared_parameter_and_no_other():
    table = parameters_table()
    names = re.findall(r'^\| `([^`]+)` \|', table, flags=re.M)
    assert names == list(PARAMETERS)
    for name, (default, desc) in PARAMETERS.items():
        row = next(line for line in table.splitlines() if line.startswith(f'| `{name}` |'))
        assert f'`{default!r}`'.replace('|', '\\|') in row
        assert ('| no |' if desc.read_only else '| yes |') in row
    node = open(os.path.join(ROOT, 'doc', 'node.md')).read()
    assert '```{include} generated/parameters.md' in node


def test_the_topic_page_lists_every_declared_interface_and_no_other():
    """The topics and services table is generated from ros/interfaces.py (which
    test_params_refused.py holds against a running node's graph)."""
    table = interfaces_table()
    names = re.findall(r'^\| `([^`]+)` \|', table, flags=re.M)
    assert names == [i.name for i in INTERFACES]
    for i in INTERFACES:
        row = next(line for line in table.splitlines() if line.startswith(f'| `{i.name}` |'))
        assert f'`{i.type}`' in row
    node = open(os.path.join(ROOT, 'doc', 'node.md')).read()
    assert '```{include} generated/interfaces.md' in node
    assert '| `~/mesh` |' not in node                  # no hand-written table beside it


def test_every_page_is_in_the_table_of_contents():
    doc = os.path.join(ROOT, 'doc')
    index = open(os.path.join(doc, 'index.md')).read()
    pages = sorted(f[:-3] for f in os.listdir(doc) if f.endswith('.md') and f != 'index.md')
    listed = re.findall(r'^([a-z][a-z-]*)$', index, flags=re.M)
    assert sorted(listed) == pages


def test_the_readme_is_the_short_front_door():
    readme = open(os.path.join(ROOT, 'README.md')).read()
    assert len(readme.splitlines()) <= 200
    # no hand-written parameter table beside the generated one
    assert '| parameter | default |' not in readme
    for link in re.findall(r'\]\((doc/[^)#]+)', readme):
        assert os.path.exists(os.path.join(ROOT, link)), link


def _python_blocks(text):
    return re.findall(r'```python\n(.*?)```', text, flags=re.S)


@pytest.mark.process
def test_the_readme_library_example_runs_as_written():
    """The README's library example, extracted and run in a process of its own: it prints
    the energy report (a dict with a finite total, the cloth having fallen: gravity's
    energy below zero) and the critical dt. (The ROS example spins until stopped; the
    node tests drive the same topics.)"""
    import subprocess
    readme = open(os.path.join(ROOT, 'README.md')).read()
    blocks = [b for b in _python_blocks(readme) if 'ClothSimulator(' in b]
    assert len(blocks) == 1
    out = subprocess.run([sys.executable, '-c', blocks[0]], capture_output=True, text=True,
                         timeout=900, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    energy, crit = out.stdout.strip().splitlines()[-2:]
    report = eval(energy, {'np': __import__('numpy')})
    assert report['gravity'] < 0 and abs(report['total']) < 10
    assert 2e-4 <= float(crit) < 1e-3
