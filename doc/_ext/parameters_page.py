"""Writes ``generated/parameters.md``, the node's parameter table, from the declarations
the node validates against (``cosserat_ros.ros.params.PARAMETERS``) when the build
starts, so that the page cannot drift from the code."""
import os

from cosserat_ros.ros.params import PARAMETERS


def _cell(text) -> str:
    return str(text).replace('|', '\\|').replace('\n', ' ')


def _range(desc) -> str:
    for r in list(desc.floating_point_range) + list(desc.integer_range):
        return f'{r.from_value:g} to {r.to_value:g}'
    return ''


def parameters_table() -> str:
    """The Markdown table: one row per declared parameter, in declaration order."""
    rows = ['| parameter | default | range | run time | meaning |',
            '|---|---|---|---|---|']
    for name, (default, desc) in PARAMETERS.items():
        rows.append(f'| `{name}` | `{_cell(repr(default))}` | {_range(desc)} | '
                    f'{"no" if desc.read_only else "yes"} | {_cell(desc.description)} |')
    return '\n'.join(rows) + '\n'


def _write(app) -> None:
    out = os.path.join(app.srcdir, 'generated')
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, 'parameters.md')
    text = parameters_table()
    old = open(path).read() if os.path.exists(path) else None
    if text != old:                                 # unchanged: no rebuild of the page
        with open(path, 'w') as fh:
            fh.write(text)


def setup(app):
    app.connect('builder-inited', _write)
    return {'parallel_read_safe': True, 'parallel_write_safe': True}
