"""Test-session set-up: every run gets its own ROS domain and keeps discovery on localhost,
so parallel runs (and other ROS graphs on the machine) never see each other."""
import os

os.environ['ROS_DOMAIN_ID'] = str(1 + os.getpid() % 100)
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('RCUTILS_COLORIZED_OUTPUT', '0')
