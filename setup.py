"""ament_python set-up for cosserat_ros (colcon and `make` both install through this file)."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'cosserat_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.json')),
        ('share/' + package_name + '/config/meshes', glob('config/meshes/*')),
        ('share/' + package_name + '/config/batch', glob('config/batch/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.*')),
        ('share/' + package_name + '/rviz', glob('rviz/*.rviz')),
    ],
    # what the installed code imports, unversioned so that a ROS install's system packages
    # satisfy them (requirements.txt pins the versions `make` installs and the tests ran;
    # package.xml names the same libraries for rosdep). rclpy and the message packages are
    # not listed: a ROS install provides them (from PyPI: ros-jazzy-rclpy[fastrtps] and
    # ros-jazzy-common-interfaces, requirements.txt).
    install_requires=['setuptools', 'numpy', 'numba', 'llvmlite', 'scipy', 'trimesh',
                      'rosbags', 'matplotlib', 'PyYAML'],
    # the peer engine of the benchmark (requirements-bench.txt pins it), the live view
    # (foxglove.port; requirements-viz.txt), the batch engine (requirements-batch.txt) and
    # the Gymnasium tasks (requirements-envs.txt)
    extras_require={'bench': ['mujoco'], 'viz': ['foxglove-sdk'],
                    'batch': ['ray>=2.60', 'pyarrow', 'mcap'],
                    'envs': ['gymnasium>=1.2,<2']},
    zip_safe=False,
    maintainer='cosserat_ros developers',
    maintainer_email='cosserat-ros@example.com',
    description='Cosserat-surface cloth simulation served as a ROS 2 node.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'cloth_node = cosserat_ros.entry:cloth_node',
            'record = cosserat_ros.entry:record',
            'render = cosserat_ros.entry:render',
            'fold_demo = cosserat_ros.entry:fold_demo',
            'flag_demo = cosserat_ros.entry:flag_demo',
            'batch = cosserat_ros.entry:batch',
        ],
    },
)
