"""The tools' progress line (cosserat_ros/tools/progress.py): one line rewritten in place on a
terminal, nothing at all elsewhere. The tools' own runs on a pseudo-terminal are in
test_record_render.py."""
import io
import os


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_progress_is_one_line_on_a_terminal_and_nothing_elsewhere(monkeypatch):
    from cosserat_ros.tools import progress as pg
    monkeypatch.setenv('COLUMNS', '40')
    clock = [100.0]
    monkeypatch.setattr(pg.time, 'monotonic', lambda: clock[0])
    tty = _Terminal()
    p = pg.Progress('render', tty)
    assert p.enabled
    p.update('GIF frame 1 of 60')
    p.update('GIF frame 2 of 60')                   # too soon: not drawn
    clock[0] += pg.INTERVAL
    p.update('GIF frame 3 of 60')
    clock[0] += pg.INTERVAL
    p.update('GIF frame 3 of 60')                   # what is on screen: not again
    clock[0] += 0.01
    p.update('frame 4', force=True)                 # shorter: blanks over the rest
    p.update('a line much longer than the terminal is wide, cut to it')
    p.done()
    p.done()                                        # once
    text = tty.getvalue()
    assert text == ('\rrender: GIF frame 1 of 60' '\rrender: GIF frame 3 of 60'
                    '\rrender: frame 4' + ' ' * 10 + '\n')
    # clear() blanks the line for another to be printed, the next update draws at once
    tty = _Terminal()
    p = pg.Progress('record', tty)
    p.update('1.0 s')
    p.clear()
    tty.write('[INFO] a log line\n')
    p.update('1.1 s')
    p.done()
    assert tty.getvalue() == ('\rrecord: 1.0 s\r' + ' ' * 13 + '\r[INFO] a log line\n'
                              '\rrecord: 1.1 s\n')
    # the line never wraps: cut to the terminal's width
    tty = _Terminal()
    p = pg.Progress('record', tty)
    p.update('x' * 100)
    assert len(tty.getvalue()) == 1 + 39
    # not a terminal (a pipe, a file, a test's capture): nothing at all
    for stream in (io.StringIO(), open(os.devnull, 'w')):
        p = pg.Progress('render', stream)
        p.update('GIF frame 1 of 2', force=True)
        p.clear()
        p.done('drew')
        assert not p.enabled
        if isinstance(stream, io.StringIO):
            assert stream.getvalue() == ''
        stream.close()
