"""Progress on stderr: plain, rate-limited lines when stderr is not a terminal (issue 42, item 6)."""
import io
import re
import subprocess
import sys

import pytest

from carto_cli.core.progress import LineProgress, progress

LINE = re.compile(r"^carto: mapping sim\.bag \d+% \d+/400 scans, [\d.]+ scans/s, ETA \d+ (s|min \d+ s)$")


class Clock:
    """Time moves only when the test says so."""

    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def lines(stream: io.StringIO) -> list[str]:
    return stream.getvalue().splitlines()


def test_line_progress_is_rate_limited():
    clock, out = Clock(), io.StringIO()
    bar = LineProgress("mapping x.bag", 1000, stream=out, clock=clock, every_s=30.0, min_gap_s=5.0)
    clock.now += 40.0  # reading and compiling before the first scan: neither part of the rate nor a reason to speak
    bar.advance()
    for _ in range(98):
        clock.now += 0.01
        bar.advance()
    assert lines(out) == []  # 99 of 1000: no tenth done yet
    clock.now += 0.01
    bar.advance()  # 100 of 1000, 99 scans in 0.99 s since the first
    assert lines(out) == ["carto: mapping x.bag 10% 100/1000 scans, 100.0 scans/s, ETA 9 s"]
    for _ in range(300):  # three more tenths within 3 s: closer than the minimum gap, so no line
        clock.now += 0.01
        bar.advance()
    assert len(lines(out)) == 1
    clock.now += 2.5
    bar.advance()  # 5.5 s after the last line, a tenth further: a line
    assert len(lines(out)) == 2 and lines(out)[-1].startswith("carto: mapping x.bag 40% 401/1000 scans, ")
    clock.now += 1.0
    bar.advance()  # no new tenth
    assert len(lines(out)) == 2


def test_line_progress_speaks_after_a_while_without_a_tenth():
    clock, out = Clock(), io.StringIO()
    bar = LineProgress("tracking", None, stream=out, clock=clock, every_s=30.0, min_gap_s=5.0)
    for _ in range(40):  # no total: only time brings a line, 30 s after the first scan
        clock.now += 1.0
        bar.advance()
    assert lines(out) == ["carto: tracking 31 scans, 1.0 scans/s"]
    bar.set_total(10_000)  # a tenth is far off: the next line comes after another 30 s
    bar.set_description("tracking run.bag")
    for _ in range(30):
        clock.now += 1.0
        bar.advance()
    assert lines(out)[1:] == ["carto: tracking run.bag 0% 61/10000 scans, 1.0 scans/s, ETA 2 h 45 min"]


def test_line_progress_units_and_a_slow_rate():
    clock, out = Clock(), io.StringIO()
    bar = LineProgress("tuning", 4, unit="trials", stream=out, clock=clock, every_s=30.0, min_gap_s=5.0)
    for _ in range(3):
        clock.now += 20.0
        bar.advance()
    assert lines(out) == ["carto: tuning 50% 2/4 trials, 0.05 trials/s, ETA 40 s",
                          "carto: tuning 75% 3/4 trials, 0.05 trials/s, ETA 20 s"]


def test_line_progress_outlives_a_reader_that_went_away():
    class Gone(io.StringIO):
        def write(self, text):
            raise BrokenPipeError

    clock = Clock()
    bar = LineProgress("mapping", 10, stream=Gone(), clock=clock)
    for _ in range(10):
        clock.now += 1.0
        bar.advance()  # the work goes on


def test_quiet_and_not_a_terminal(monkeypatch):
    out = io.StringIO()
    monkeypatch.setattr(sys, "stderr", out)
    with progress("mapping", 10, quiet=True) as bar:
        for _ in range(10):
            bar.advance()
    with progress("mapping", 10) as bar:
        assert isinstance(bar, LineProgress)
    assert out.getvalue() == ""


@pytest.fixture(scope="module")
def sim_400(tmp_path_factory):
    from carto_cli.io.recording_writers import write_recording
    from carto_cli.sim.lidar import Lidar
    from carto_cli.sim.recording import simulate
    from carto_cli.sim.trajectory import loop_trajectory
    from carto_cli.sim.world import loop_building

    world = loop_building()
    sim = simulate(world, loop_trajectory(world), duration=40.0, lidar=Lidar(beams=90), imu_rate=0, odom_rate=10)
    assert sim.counts()["/scan"] == 400
    rec = sim.recording()
    path = tmp_path_factory.mktemp("progress") / "sim.bag"
    write_recording(rec.records(), path, "ros1", static_transforms=rec.static_transforms(),
                    topics={t.name: t.msgtype for t in rec.topics()})
    return path


def test_a_non_terminal_run_of_carto_map_prints_progress_lines(sim_400, tmp_path):
    """Issue 42, item 6: with stderr not a terminal (CI, nohup, a pipe) a long run printed nothing until its end;
    now a 400-scan log prints at least one line with scans/s before it finishes, and -q silences it."""
    carto = [sys.executable, "-m", "carto_cli", "map", str(sim_400), "--no-state"]
    r = subprocess.run([*carto, "-o", str(tmp_path / "a")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    shown = [line for line in r.stderr.splitlines() if line.startswith("carto: mapping ")]
    assert shown and all(LINE.match(line) for line in shown), r.stderr
    quiet = subprocess.run([*carto, "-q", "-o", str(tmp_path / "b")], capture_output=True, text=True, timeout=300)
    assert quiet.returncode == 0, quiet.stderr
    assert "carto: mapping" not in quiet.stderr


def test_the_terminal_bar_starts_no_thread():
    """rich's bar redrew itself from a thread of its own, which makes forking unsafe: with a bar on the screen the
    pose graph ran on a thread beside local SLAM instead of in its own process, and mapping took twice as long."""
    import io

    from carto_cli.core.parallel import fork_safe
    from carto_cli.core.progress import TerminalBar

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    screen = Terminal()
    bar = TerminalBar("mapping x.bag", 50, screen)
    try:
        for _ in range(50):
            bar.advance()
            assert fork_safe() or not sys.platform.startswith("linux")
    finally:
        bar.close()
    assert "mapping x.bag" in screen.getvalue()
