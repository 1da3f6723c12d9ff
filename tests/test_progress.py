import io

from probecal.app.progress import Progress, Status


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_long_work_reports_quarters_in_logs():
    stream, clock = io.StringIO(), Clock()
    progress = Progress("working", stream=stream, clock=clock)
    for done in range(1, 101):
        clock.t = done * 0.1
        progress(done, 100)
    lines = stream.getvalue().splitlines()
    assert lines[-1].startswith("working: 100/100") and 3 <= len(lines) <= 5


def test_quick_work_stays_quiet_in_logs():
    stream, clock = io.StringIO(), Clock()
    progress = Progress("working", stream=stream, clock=clock)
    for done in range(1, 11):
        clock.t = done * 0.01
        progress(done, 10)
    assert stream.getvalue() == ""


def test_terminal_gets_a_live_bar():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    stream = Tty()
    progress = Progress("working", stream=stream)
    progress(5, 10)
    progress(10, 10)
    assert "\rworking [" in stream.getvalue() and stream.getvalue().endswith("\n")


def test_status_speaks_once_work_has_lasted_a_while():
    stream, clock = io.StringIO(), Clock()
    status = Status("calibrate", stream=stream, clock=clock)
    status("segmenting")
    clock.t = 1.5
    status("cross-validating the seed objective")
    assert stream.getvalue() == "calibrate: cross-validating the seed objective\n"


def test_a_short_report_keeps_its_steps_off_the_log_and_on_one_terminal_line():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    log, clock = io.StringIO(), Clock()
    status, progress = Status("calibrate", stream=log, clock=clock, log=False), Progress("x", stream=log, log=False)
    clock.t = 5.0
    status("fitting")
    progress(10, 10)
    assert log.getvalue() == ""
    tty = Tty()
    status = Status("calibrate", stream=tty, log=False)
    status("fitting")
    status("bootstrapping")
    assert tty.getvalue() == "\r\033[Kcalibrate: fitting\r\033[Kcalibrate: bootstrapping"
