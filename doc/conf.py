"""Sphinx configuration of the cosserat_ros manual (the layout rosdoc2 builds: this
directory with its conf.py and index). ``make docs`` builds it into build/doc with
warnings as errors. Pages are Markdown (MyST); the parameter table is written from the
node's declarations at every build (``_ext/parameters_page.py``)."""
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))          # the package, from the source tree
sys.path.insert(0, os.path.join(HERE, '_ext'))

project = 'cosserat_ros'
author = 'the cosserat_ros developers'
copyright = '2026, the cosserat_ros developers'

extensions = ['myst_parser', 'sphinx.ext.autodoc', 'sphinx.ext.napoleon',
              'parameters_page']
source_suffix = {'.md': 'markdown', '.rst': 'restructuredtext'}
root_doc = 'index'
exclude_patterns = ['_build', 'generated/*.md']
myst_enable_extensions = ['dollarmath']
myst_heading_anchors = 3

autodoc_member_order = 'bysource'
autodoc_default_options = {'members': True, 'undoc-members': False}
autodoc_typehints = 'none'
napoleon_numpy_docstring = True

html_theme = 'alabaster'
html_static_path = []
