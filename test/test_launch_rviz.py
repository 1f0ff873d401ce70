"""The launch files and the RViz config, checked statically (launch_ros and rviz have no
wheels here): they are installed, parse, and name what the installed package has and what
the node publishes."""
import ast
import os
import xml.etree.ElementTree as ET

from ament_index_python.packages import get_package_prefix, get_package_share_directory
import yaml

from cosserat_ros.ros.params import PARAMETERS

SHARE = get_package_share_directory('cosserat_ros')
PREFIX = get_package_prefix('cosserat_ros')


def _executable_exists(package, executable):
    return os.access(os.path.join(PREFIX, 'lib', package, executable), os.X_OK)


def test_python_launch_file_parses_and_names_what_is_installed():
    path = os.path.join(SHARE, 'launch', 'cloth.launch.py')
    tree = ast.parse(open(path).read(), path)
    funcs = [n.name for n in tree.body if isinstance(n, ast.FunctionDef)]
    assert 'generate_launch_description' in funcs
    nodes, args = [], {}
    for call in (n for n in ast.walk(tree) if isinstance(n, ast.Call)):
        name = getattr(call.func, 'id', getattr(call.func, 'attr', ''))
        kw = {k.arg: k.value for k in call.keywords}
        if name == 'Node':
            nodes.append({k: v.value for k, v in kw.items() if isinstance(v, ast.Constant)})
        if name == 'DeclareLaunchArgument':
            args[call.args[0].value] = kw['default_value']
    ours = [n for n in nodes if n.get('package') == 'cosserat_ros']
    assert [n['executable'] for n in ours] == ['cloth_node']
    assert _executable_exists('cosserat_ros', 'cloth_node')
    # the default config: PathJoinSubstitution([share, 'config', 'cloth.yaml'])
    parts = [e.value for e in args['config'].args[0].elts if isinstance(e, ast.Constant)]
    assert os.path.isfile(os.path.join(SHARE, *parts)), parts
    assert args['rviz'].value == 'false'
    assert any('cloth.rviz' in ast.unparse(n) for n in ast.walk(tree)
               if isinstance(n, ast.List))


def test_xml_launch_file_is_the_twin():
    root = ET.parse(os.path.join(SHARE, 'launch', 'cloth.launch.xml')).getroot()
    assert root.tag == 'launch'
    args = {a.get('name'): a.get('default') for a in root.iter('arg')}
    prefix = '$(find-pkg-share cosserat_ros)/'
    assert args['config'].startswith(prefix)
    assert os.path.isfile(os.path.join(SHARE, args['config'][len(prefix):]))
    node = next(n for n in root.iter('node') if n.get('pkg') == 'cosserat_ros')
    assert node.get('exec') == 'cloth_node' and node.get('name') == 'cloth_node'
    assert node.find('param').get('from') == '$(var config)'
    rviz = next(n for n in root.iter('node') if n.get('pkg') == 'rviz2')
    assert rviz.get('if') == '$(var rviz)'
    assert os.path.isfile(os.path.join(SHARE, rviz.get('args').split(prefix)[1]))


def test_rviz_config_shows_what_the_node_publishes(tmp_path):
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter
    from cosserat_ros.ros.node import ClothNode
    cfg = yaml.safe_load(open(os.path.join(SHARE, 'rviz', 'cloth.rviz')))
    manager = cfg['Visualization Manager']
    assert manager['Global Options']['Fixed Frame'] == PARAMETERS['frame_id'][0]
    shown = {d['Topic']['Value']: d['Class'] for d in manager['Displays'] if 'Topic' in d}
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        node = ClothNode(context=ctx, parameter_overrides=[
            Parameter('mesh.nx', value=4), Parameter('mesh.ny', value=4)])
        published = dict(node.get_publisher_names_and_types_by_node('cloth_node', '/'))
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    for topic, cls in shown.items():
        assert topic in published, topic
        assert cls == 'rviz_default_plugins/MarkerArray'
        assert published[topic] == ['visualization_msgs/msg/MarkerArray']
    assert {'/cloth_node/mesh', '/cloth_node/obstacle_markers'} <= set(shown)


#: the rosdep keys of the Python libraries the package imports (llvmlite comes with numba;
#: mujoco, foxglove, mcap, ray, pyarrow and gymnasium are the optional extras' (setup.py:
#: bench, viz, batch, envs), not run dependencies)
PYTHON_KEYS = {'numpy': 'python3-numpy', 'numba': 'python3-numba', 'scipy': 'python3-scipy',
               'trimesh': 'python3-trimesh-pip', 'rosbags': 'python3-rosbags-pip',
               'matplotlib': 'python3-matplotlib', 'mpl_toolkits': 'python3-matplotlib',
               'yaml': 'python3-yaml',
               # bagfile's zstd codec: backports.zstd is a requirement of rosbags (installed
               # with python3-rosbags-pip); compression.zstd is the standard library's from 3.14
               'backports': 'python3-rosbags-pip'}
#: standard-library modules of Python versions newer than the one running the test
NEWER_STDLIB = {'compression'}
EXTRAS = {'llvmlite', 'mujoco', 'foxglove', 'mcap', 'mcap_ros2', 'google', 'websockets',
          'ray', 'pyarrow', 'gymnasium'}


def _imported_packages() -> set:
    """The top-level packages the installed code imports, outside the standard library
    (of this Python and of newer ones) and the package itself."""
    import sys
    code = os.path.dirname(os.path.abspath(__import__('cosserat_ros').__file__))
    imported = set()
    for dirpath, _, files in os.walk(code):
        for f in files:
            if f.endswith('.py'):
                for n in ast.walk(ast.parse(open(os.path.join(dirpath, f)).read())):
                    if isinstance(n, ast.Import):
                        imported |= {a.name.split('.')[0] for a in n.names}
                    elif isinstance(n, ast.ImportFrom) and n.level == 0 and n.module:
                        imported.add(n.module.split('.')[0])
    return imported - set(sys.stdlib_module_names) - NEWER_STDLIB - {'cosserat_ros'}


def test_every_package_the_code_imports_or_launches_is_a_run_dependency():
    """A ROS install resolves package.xml with rosdep: each ROS package the installed code
    imports (rclpy, the message and service packages, rcl_interfaces for the parameter
    types, ament_index_python) and each Python library must be an exec_depend, and so
    must rviz2, which the launch files start with rviz:=true."""
    root = ET.parse(os.path.join(SHARE, 'package.xml')).getroot()
    deps = {e.text for e in root.iter() if e.tag in ('exec_depend', 'depend')}
    third = _imported_packages() - EXTRAS
    assert {'rclpy', 'numpy', 'rcl_interfaces'} <= third                # the walk works
    missing = {PYTHON_KEYS.get(m, m) for m in third} - deps
    assert not missing, f'imported but not in package.xml: {sorted(missing)}'
    for name in ('cloth.launch.py', 'cloth.launch.xml'):
        if 'rviz2' in open(os.path.join(SHARE, 'launch', name)).read():
            assert 'rviz2' in deps, f'launch/{name} starts rviz2'


#: import name -> distribution name, where they differ
DISTRIBUTIONS = {'yaml': 'pyyaml', 'mpl_toolkits': 'matplotlib', 'backports': 'rosbags',
                 'foxglove': 'foxglove-sdk'}


def test_the_installed_distribution_requires_every_library_it_imports():
    """pip and colcon read the dependencies from setup.py: every third-party library the
    installed code imports (ROS's packages aside, which a ROS install provides) is in
    install_requires, or in the extra of the optional part that imports it."""
    import importlib.metadata
    import re
    requires = importlib.metadata.requires('cosserat_ros')
    runtime, extras = set(), set()
    for r in requires:
        name = re.match(r'[A-Za-z0-9_.-]+', r).group(0).lower()
        (extras if 'extra ==' in r else runtime).add(name)
    imported = _imported_packages()
    ros = {m for m in imported if m in ('rclpy', 'rcl_interfaces', 'ament_index_python',
                                         'builtin_interfaces', 'rosgraph_msgs')
           or m.endswith(('_msgs', '_srvs'))}
    third = imported - ros
    assert {'numpy', 'numba', 'ray'} <= third                          # the walk works
    dists = {DISTRIBUTIONS.get(m, m).lower() for m in third}
    assert not dists - runtime - extras, f'imported, not required: {dists - runtime - extras}'
    optional = {DISTRIBUTIONS.get(m, m).lower() for m in EXTRAS - {'llvmlite'}} & dists
    assert not optional & runtime, f'an optional library is a run dependency: {optional & runtime}'
