"""Writes ``generated/parameters.md`` and ``generated/interfaces.md``, the node's
parameter and topic tables, from the declarations the node runs on
(``cosserat_ros.ros.params.DECLARATIONS``, ``cosserat_ros.ros.interfaces.INTERFACES``)
when the build starts, so that the pages cannot drift from the code."""
import os

from cosserat_ros.ros.interfaces import INTERFACES
from cosserat_ros.ros.params import DECLARATIONS


def _cell(text) -> str:
    return str(text).replace('|', '\\|').replace('\n', ' ')


def parameters_table() -> str:
    """The Markdown table: one row per declared parameter, in declaration order."""
    rows = ['| parameter | default | unit | range | run time | meaning |',
            '|---|---|---|---|---|---|']
    for name, d in DECLARATIONS.items():
        span = f'{d.low:g} to {d.high:g}' if d.low is not None else ''
        rows.append(f'| `{name}` | `{_cell(repr(d.default))}` | {_cell(d.unit)} | {span} | '
                    f'{"yes" if d.runtime else "no"} | {_cell(d.text)} |')
    return '\n'.join(rows) + '\n'


_KIND = {'publisher': 'out', 'subscription': 'in', 'service': 'service'}


def interfaces_table() -> str:
    """The Markdown table: one row per declared topic or service, in declaration order."""
    rows = ['| name | type | | when | |', '|---|---|---|---|---|']
    for i in INTERFACES:
        when = ', '.join(f'`{w}`' for w in i.when.split())
        rows.append(f'| `{i.name}` | `{i.type}` | {_KIND[i.kind]} | {when} | '
                    f'{_cell(i.text)} |')
    return '\n'.join(rows) + '\n'


def _write(app) -> None:
    out = os.path.join(app.srcdir, 'generated')
    os.makedirs(out, exist_ok=True)
    for name, text in (('parameters.md', parameters_table()),
                       ('interfaces.md', interfaces_table())):
        path = os.path.join(out, name)
        old = open(path).read() if os.path.exists(path) else None
        if text != old:                             # unchanged: no rebuild of the page
            with open(path, 'w') as fh:
                fh.write(text)


def setup(app):
    app.connect('builder-inited', _write)
    return {'parallel_read_safe': True, 'parallel_write_safe': True}
