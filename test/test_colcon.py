"""colcon (from PyPI: colcon-core, colcon-ros, colcon-python-setup-py) builds and tests the
package as a ROS developer's workspace would, and installs the layout `ros2 run`,
`ros2 launch` and the ament index expect."""
import os
import shutil
import subprocess
import sys

import pytest

# the colcon tier: a workspace built and tested with colcon (make test, not test-fast)
pytestmark = pytest.mark.colcon

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SOURCES = ('cosserat_ros', 'config', 'launch', 'rviz', 'resource', 'test', 'setup.py',
           'setup.cfg', 'package.xml', 'README.md')
COLCON = os.path.join(os.path.dirname(sys.executable), 'colcon')


@pytest.fixture(scope='module')
def workspace(tmp_path_factory):
    if not os.access(COLCON, os.X_OK):
        pytest.fail(f'colcon not installed beside {sys.executable} (requirements-dev.txt)')
    ws = tmp_path_factory.mktemp('ws')
    src = ws / 'src' / 'cosserat_ros'
    src.mkdir(parents=True)
    ignore = shutil.ignore_patterns('__pycache__', '*.nbi', '*.nbc')
    for name in SOURCES:
        path = os.path.join(ROOT, name)
        if os.path.isdir(path):
            shutil.copytree(path, src / name, ignore=ignore)
        else:
            shutil.copy(path, src / name)
    # what a user sees (Python's default warning filters)
    env = {k: v for k, v in os.environ.items() if k != 'PYTHONWARNINGS'}
    res = subprocess.run([COLCON, 'build', '--base-paths', 'src'], cwd=ws, env=env,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    return ws, res.stdout + res.stderr


def test_colcon_build_installs_the_ros_layout(workspace):
    ws, output = workspace
    prefix = ws / 'install' / 'cosserat_ros'
    for exe in ('cloth_node', 'record', 'render'):
        assert os.access(prefix / 'lib' / 'cosserat_ros' / exe, os.X_OK), exe
    share = prefix / 'share' / 'cosserat_ros'
    assert (share / 'package.xml').is_file()
    for name in ('config/cloth.yaml', 'config/table.yaml', 'config/meshes/dome_with_hole.obj',
                 'launch/cloth.launch.py', 'launch/cloth.launch.xml', 'rviz/cloth.rviz'):
        assert (share / name).is_file(), name
    assert (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages'
            / 'cosserat_ros').is_file()
    assert 'deprecat' not in output.lower(), output


def test_colcon_test_runs_the_package_tests(workspace):
    ws, _ = workspace
    res = subprocess.run([COLCON, 'test', '--base-paths', 'src', '--pytest-args',
                          'test/test_commands.py', '-k', 'layouts or total_on'], cwd=ws,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    summary = subprocess.run([COLCON, 'test-result', '--test-result-base', 'build'], cwd=ws,
                             capture_output=True, text=True, timeout=60)
    assert summary.returncode == 0, summary.stdout + summary.stderr
    assert '0 errors, 0 failures' in summary.stdout and '2 tests' in summary.stdout, \
        summary.stdout
