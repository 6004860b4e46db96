"""Named, nested stage timing per scan, and its reports.

One ``StageTimer`` travels through the core; ``profile``, ``map --profile`` and
``tune``'s cost term all read the same numbers::

    timer = StageTimer()
    for scan in stream:
        with timer.scan():
            with timer.stage("preprocess"):
                with timer.stage("voxel"):
                    ...
            with timer.stage("matching"):
                ...
    with timer.stage("final_optimization"):   # outside any scan: recorded too
        ...
    timer.stop()
    text = report_tree_text(timer)          # the CLI prints it

The tree's root is the wall time since the timer was created (until ``stop()``);
its children are the ``scan`` pseudo-stage (all scans together) and the stages run
outside scans. Every node with children gets an explicit ``(other)`` line for its
self time, so each level adds up to its parent and the whole tree to the wall time.

Stages are meant for pieces of work of tens of microseconds or more (one enter and
exit costs about a microsecond); time inner loops with a sampling profiler instead.
Not thread-safe: a thread of its own gets a timer of its own from ``concurrent(name)``, whose tree the
report shows beside the main one (marked as running concurrently, so it is not part of the wall-time sum);
work measured on worker threads goes into such a branch after the fact with ``add`` (thread time, summed
over workers), never under a stage of this thread, which would then last less than its children.
Names are unique among siblings (a concurrent branch too: ``snapshot`` refuses a clash), so a path names one
stage. ``NullTimer`` has the same interface and does nothing, for runs without profiling.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

__all__ = [
    "SCAN_STAGE",
    "SCHEMA_VERSION",
    "NullTimer",
    "Snapshot",
    "StageStats",
    "StageTimer",
    "report_json",
    "report_tree_text",
]

SCHEMA_VERSION = 1
SCAN_STAGE = "scan"
SEP = "/"


class _Node:
    __slots__ = ("children", "count", "cpu_ns", "name", "sample_scans", "samples", "scan_mark", "scan_ns",
                 "total_ns")

    def __init__(self, name: str):
        self.name = name
        self.children: dict[str, _Node] = {}
        self.total_ns = 0
        self.cpu_ns = 0  # CPU time of the whole process (every thread) inside the stage, when measured
        self.count = 0
        self.scan_ns = 0          # accumulated within the current scan
        self.scan_mark = -1       # index of the scan scan_ns belongs to
        self.samples: list[int] = []       # per-scan sums, only for scans in which the stage ran
        self.sample_scans: list[int] = []  # the matching scan indices

    def child(self, name: str) -> _Node:
        node = self.children.get(name)
        if node is None:
            if not name or SEP in name:
                raise ValueError(f"stage names must be non-empty and contain no '{SEP}': {name!r}")
            node = self.children[name] = _Node(name)
        return node


# What ``export_tree`` gives: a timer's stages and, by name, its concurrent timers' own.
_Tree = tuple[_Node, list[tuple[str, "_Tree"]]]


class _Stage:
    __slots__ = ("_name", "_timer")

    def __init__(self, timer: StageTimer, name: str):
        self._timer = timer
        self._name = name

    # The CPU clock is read inside the wall interval, not around it: reading the process's CPU time is a system
    # call at which a busy machine often switches to other work (on 2 loaded cores, reads stalled up to 30 ms,
    # 0.8-2.2 s of a 10 s profile), and read outside the interval every stall went to the parent's "(other)"
    # (most of `match`'s time: its two children's four reads).
    def __enter__(self):
        t = self._timer
        t._starts.append(t._clock())
        top = t._stack[-1]
        t._stack.append(top.children.get(self._name) or top.child(self._name))
        if t._cpu_clock is not None:
            t._cpu_starts.append(t._cpu_clock())
        return self

    def __exit__(self, *exc):
        t = self._timer
        node = t._stack.pop()
        if t._cpu_clock is not None:
            node.cpu_ns += t._cpu_clock() - t._cpu_starts.pop()
        dt = t._clock() - t._starts.pop()
        node.total_ns += dt
        node.count += 1
        if t._in_scan:
            if node.scan_mark != t._num_scans:
                node.scan_mark = t._num_scans
                node.scan_ns = 0
                t._touched.append(node)
            node.scan_ns += dt
        return False


class _Scan:
    __slots__ = ("_timer",)

    def __init__(self, timer: StageTimer):
        self._timer = timer

    def __enter__(self):
        self._timer.begin_scan()
        return self

    def __exit__(self, *exc):
        self._timer.end_scan()
        return False


class StageTimer:
    """Records nested stages, per scan and outside scans. See the module docstring."""

    enabled = True

    def __init__(self, clock: Callable[[], int] = time.perf_counter_ns,
                 cpu_clock: Callable[[], int] | None = None):
        """``cpu_clock`` (e.g. ``time.process_time_ns``): also record each stage's CPU time, which a neighbour
        job on another core hardly changes (what ``carto profile``'s gates compare)."""
        self._clock = clock
        self._cpu_clock = cpu_clock
        self._cpu_starts: list[int] = []
        self._scan_cpu_start = 0
        self._root = _Node("total")
        self._scan_node: _Node | None = None
        self._stack: list[_Node] = [self._root]
        self._starts: list[int] = []
        self._in_scan = False
        self._scan_start = 0
        self._num_scans = 0
        self._touched: list[_Node] = []
        self._t0 = clock()
        self._t_stop: int | None = None
        self._concurrent: dict[str, StageTimer] = {}

    # -- recording

    def stage(self, name: str) -> _Stage:
        """Context manager timing ``name`` as a child of the innermost open stage."""
        return _Stage(self, name)

    def scan(self) -> _Scan:
        """Context manager delimiting one scan's sample."""
        return _Scan(self)

    def add(self, name: str, ns: int, count: int = 1) -> None:
        """Record ``count`` runs of ``name`` lasting ``ns`` in all, measured elsewhere, as a child of the innermost
        open stage: work that ran within that stage, or, in a ``concurrent`` timer, on other threads."""
        node = self._stack[-1].child(name)
        node.total_ns += int(ns)
        node.count += int(count)
        if self._in_scan:
            if node.scan_mark != self._num_scans:
                node.scan_mark = self._num_scans
                node.scan_ns = 0
                self._touched.append(node)
            node.scan_ns += int(ns)

    def concurrent(self, name: str) -> StageTimer:
        """A timer for a thread of its own (e.g. the pose graph's background worker) or for time measured on
        worker threads; its stages appear under ``name`` at the top of this timer's report, marked concurrent.
        The same name gives the same timer: one branch per name, however often it is asked for."""
        timer = self._concurrent.get(name)
        if timer is None:
            if not name or SEP in name:
                raise ValueError(f"stage names must be non-empty and contain no '{SEP}': {name!r}")
            timer = self._concurrent[name] = StageTimer(self._clock, self._cpu_clock)
        return timer

    def export_tree(self) -> _Tree:
        """The recorded stages, with those of this timer's concurrent timers, as one picklable value (a
        concurrent timer run in another process)."""
        if len(self._stack) != 1 or self._in_scan:
            raise RuntimeError("export_tree: a stage or scan is still open")
        return self._root, [(name, timer.export_tree()) for name, timer in self._concurrent.items()]

    def import_tree(self, tree: _Tree) -> None:
        """Take the stages ``export_tree`` gave, in place of this timer's own."""
        root, concurrent = tree
        self._root = root
        self._stack = [root]
        self._scan_node = root.children.get(SCAN_STAGE)
        self._concurrent = {}
        for name, subtree in concurrent:
            self.concurrent(name).import_tree(subtree)

    def begin_scan(self) -> None:
        if self._in_scan:
            raise RuntimeError("begin_scan: a scan is already open")
        if len(self._stack) != 1:
            raise RuntimeError(f"begin_scan: stage '{self._stack[-1].name}' is still open")
        if self._scan_node is None:
            self._scan_node = self._root.child(SCAN_STAGE)
        self._stack.append(self._scan_node)
        self._in_scan = True
        self._scan_start = self._clock()  # the CPU clock inside the wall interval, as for a stage
        if self._cpu_clock is not None:
            self._scan_cpu_start = self._cpu_clock()

    def end_scan(self) -> None:
        if not self._in_scan:
            raise RuntimeError("end_scan: no scan is open")
        if self._stack[-1] is not self._scan_node:
            raise RuntimeError(f"end_scan: stage '{self._stack[-1].name}' is still open")
        node = self._scan_node
        if self._cpu_clock is not None:
            node.cpu_ns += self._cpu_clock() - self._scan_cpu_start
        dt = self._clock() - self._scan_start
        node.total_ns += dt
        node.count += 1
        node.samples.append(dt)
        node.sample_scans.append(self._num_scans)
        for n in self._touched:
            n.samples.append(n.scan_ns)
            n.sample_scans.append(self._num_scans)
        self._touched.clear()
        self._stack.pop()
        self._in_scan = False
        self._num_scans += 1

    def next_scan(self) -> None:
        """End the open scan, if any, and begin the next (for loops that cannot use ``scan()``)."""
        if self._in_scan:
            self.end_scan()
        self.begin_scan()

    def stop(self) -> None:
        """End the open scan, if any, and freeze the wall clock of the report."""
        if self._in_scan:
            self.end_scan()
        if len(self._stack) != 1:
            raise RuntimeError(f"stop: stage '{self._stack[-1].name}' is still open")
        if self._t_stop is None:
            self._t_stop = self._clock()

    @property
    def num_scans(self) -> int:
        return self._num_scans

    # -- reading

    def snapshot(self) -> Snapshot:
        """An immutable copy of the tree. Open stages and an open scan count up to now."""
        now = self._t_stop if self._t_stop is not None else self._clock()
        open_ns: dict[int, int] = {}
        # _stack[0] is the root; with a scan open, _stack[1] is the scan node.
        starts = list(self._starts)
        if self._in_scan:
            starts.insert(0, self._scan_start)
        for node, start in zip(self._stack[1:], starts):
            open_ns[id(node)] = now - start
        scans = self._num_scans + (1 if self._in_scan else 0)
        wall = now - self._t0

        def build(node: _Node, path: str, in_scan: bool) -> StageStats:
            is_open = id(node) in open_ns
            extra = open_ns.get(id(node), 0)
            children = [build(c, f"{path}{SEP}{c.name}" if path else c.name,
                              in_scan or c is self._scan_node)
                        for c in node.children.values()]
            if node is self._root:
                total, count = wall, 1
            else:
                total, count = node.total_ns + extra, node.count + int(is_open)
            if node is self._root:
                children += [_graft(name, timer.snapshot().root) for name, timer in self._concurrent.items()]
                names = [c.name for c in children]
                if len(set(names)) < len(names):
                    raise ValueError(f"a concurrent branch is named as a stage beside it: {names}")
            return StageStats(
                name=node.name, path=path, total_ns=total, cpu_ns=node.cpu_ns if self._cpu_clock else None,
                self_ns=max(0, total - sum(c.total_ns for c in children if not c.concurrent)), count=count,
                in_scan=in_scan, samples_ns=np.asarray(node.samples, dtype=np.int64),
                sample_scans=np.asarray(node.sample_scans, dtype=np.int64),
                children=children)

        return Snapshot(wall_ns=wall, scans=scans, root=build(self._root, "", False))


def _graft(name: str, root: StageStats) -> StageStats:
    """A concurrent timer's tree as one top-level stage ``name``: its total is the thread's busy time."""
    def repath(s: StageStats, path: str) -> StageStats:
        return replace(s, path=path, children=[repath(c, f"{path}{SEP}{c.name}") for c in s.children])

    children = [repath(c, f"{name}{SEP}{c.name}") for c in root.children]
    # Its own concurrent branches (worker threads of that thread) are beside its busy time, not part of it.
    total = sum(c.total_ns for c in children if not c.concurrent)
    cpu = sum(c.cpu_ns or 0 for c in children if not c.concurrent) if root.cpu_ns is not None else None
    return StageStats(name=name, path=name, total_ns=total, self_ns=0, count=1, in_scan=False, cpu_ns=cpu,
                      children=children, concurrent=True)


class _Null:
    __slots__ = ()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


_NULL = _Null()


class NullTimer:
    """Same interface as StageTimer; records nothing."""

    enabled = False
    num_scans = 0

    def stage(self, name: str) -> _Null:
        return _NULL

    def scan(self) -> _Null:
        return _NULL

    def add(self, name: str, ns: int, count: int = 1) -> None:
        pass

    def concurrent(self, name: str) -> NullTimer:
        return self

    def export_tree(self) -> None:
        return None

    def import_tree(self, tree: object) -> None:
        pass

    def begin_scan(self) -> None:
        pass

    def end_scan(self) -> None:
        pass

    def next_scan(self) -> None:
        pass

    def stop(self) -> None:
        pass

    def snapshot(self) -> Snapshot:
        return Snapshot(wall_ns=0, scans=0, root=StageStats("total", "", 0, 0, 1, False), enabled=False)


# --------------------------------------------------------------------------- snapshot


@dataclass(frozen=True, eq=False)
class StageStats:
    name: str
    path: str                      # 'scan/preprocess/voxel'; '' for the root
    total_ns: int
    self_ns: int                   # total minus the children's totals: the '(other)' line
    count: int                     # times entered
    in_scan: bool                  # inside the scan pseudo-stage (or that stage itself)
    cpu_ns: int | None = None      # the process's CPU time inside the stage (None: not measured)
    samples_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))   # per scan where it ran
    sample_scans: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    children: list[StageStats] = field(default_factory=list)
    concurrent: bool = False       # ran on a thread of its own, beside the stages the wall time adds up

    def percentile_ms(self, q: float) -> float | None:
        if self.samples_ns.size == 0:
            return None
        return float(np.percentile(self.samples_ns, q)) / 1e6

    def walk(self):
        yield self
        for c in self.children:
            yield from c.walk()


@dataclass(frozen=True, eq=False)
class Snapshot:
    wall_ns: int
    scans: int
    root: StageStats
    enabled: bool = True

    @property
    def scan_stage(self) -> StageStats | None:
        return self.find(SCAN_STAGE)

    def find(self, path: str) -> StageStats | None:
        """The stage at a '/'-separated path ('scan/matching'), or None."""
        node: StageStats | None = self.root
        for part in path.split(SEP) if path else []:
            assert node is not None
            node = next((c for c in node.children if c.name == part), None)
            if node is None:
                return None
        return node


# --------------------------------------------------------------------------- reports


def _snap(timer: StageTimer | NullTimer | Snapshot) -> Snapshot:
    return timer if isinstance(timer, Snapshot) else timer.snapshot()


def report_json(timer: StageTimer | NullTimer | Snapshot) -> dict:
    """The timing tree as JSON-ready data (milliseconds), with ``schema_version``.

    Each node: total/self ms, shares of the wall total (``share``, ``self_share``)
    and, inside scans, of the scan time (``share_of_scan``), calls, ms per scan and
    per-scan percentiles over the scans in which the stage ran. ``stages`` repeats
    every node's figures flat, keyed by path.
    """
    snap = _snap(timer)
    wall = snap.wall_ns
    scan_node = snap.scan_stage
    scan_total = scan_node.total_ns if scan_node is not None else 0
    flat: dict[str, dict] = {}

    def ratio(a: int, b: int) -> float | None:
        return a / b if b > 0 else None

    def node(s: StageStats) -> dict:
        d = {
            "name": s.name,
            "path": s.path,
            "total_ms": s.total_ns / 1e6,
            "self_ms": s.self_ns / 1e6,
            "share": ratio(s.total_ns, wall),
            "self_share": ratio(s.self_ns, wall),
            "share_of_scan": ratio(s.total_ns, scan_total) if s.in_scan else None,
            "calls": s.count,
            "in_scan": s.in_scan,
            "concurrent": s.concurrent,
            "ms_per_scan": (s.total_ns / 1e6 / snap.scans) if s.in_scan and snap.scans else None,
            "scans_with_stage": int(s.samples_ns.size) if s.in_scan else None,
            "p50_ms": s.percentile_ms(50),
            "p95_ms": s.percentile_ms(95),
            "p99_ms": s.percentile_ms(99),
            "max_ms": float(s.samples_ns.max()) / 1e6 if s.samples_ns.size else None,
        }
        if s.cpu_ns is not None and s.path:
            d["cpu_ms"] = s.cpu_ns / 1e6
            d["cpu_ms_per_scan"] = (s.cpu_ns / 1e6 / snap.scans) if s.in_scan and snap.scans else None
        flat[s.path or "total"] = dict(d)
        d["children"] = [node(c) for c in s.children]
        return d

    tree = node(snap.root)
    return {
        "schema_version": SCHEMA_VERSION,
        "enabled": snap.enabled,
        "clock": "time.perf_counter_ns",
        "unit": "ms",
        "wall_ms": wall / 1e6,
        "scans": snap.scans,
        "tree": tree,
        "stages": flat,
    }


def _fmt(x: float | None, spec: str) -> str:
    return "" if x is None else format(x, spec)


def report_tree_text(timer: StageTimer | NullTimer | Snapshot) -> str:
    """The timing tree as an aligned text table, every level summing to its parent."""
    snap = _snap(timer)
    if not snap.enabled:
        return "timing: disabled\n"
    wall = snap.wall_ns
    scan_node = snap.scan_stage
    scan_total = scan_node.total_ns if scan_node is not None else 0
    rows: list[tuple[str, ...]] = []

    def pct(a: int, b: int) -> str:
        return f"{100.0 * a / b:.1f}%" if b > 0 else ""

    def row(label: str, total: int, in_scan: bool, calls: str = "", p50: float | None = None,
            p95: float | None = None) -> None:
        rows.append((
            label,
            f"{total / 1e6:.1f}",
            _fmt(total / 1e6 / snap.scans, ".3f") if in_scan and snap.scans else "",
            pct(total, wall),
            pct(total, scan_total) if in_scan else "",
            calls,
            _fmt(p50, ".3f"),
            _fmt(p95, ".3f"),
        ))

    def visit(s: StageStats, prefix: str, branch: str) -> None:
        name = s.name if s.path else "total (wall)"
        if s.path == SCAN_STAGE:
            name = f"{SCAN_STAGE} ({snap.scans} scans)"
        elif s.concurrent:
            name = f"{s.name} (concurrent: other threads or a process, not in the sum)"
        row(prefix + branch + name, s.total_ns, s.in_scan, str(s.count) if s.path else "",
            s.percentile_ms(50), s.percentile_ms(95))
        if not s.children:
            return
        child_prefix = prefix + ("" if not s.path else ("│  " if branch == "├─ " else "   "))
        for c in s.children:
            visit(c, child_prefix, "├─ ")
        label = "(other)" if s.path else "(other: untimed)"
        row(child_prefix + "└─ " + label, s.self_ns, s.in_scan)

    visit(snap.root, "", "")
    header = ("stage", "total ms", "ms/scan", "%total", "%scan", "calls", "p50 ms", "p95 ms")
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(len(header))]
    lines = [f"timing: {snap.scans} scans, wall {wall / 1e9:.3f} s"]
    for r in [header] + rows:
        cells = [r[0].ljust(widths[0])] + [r[i].rjust(widths[i]) for i in range(1, len(r))]
        lines.append("  ".join(cells).rstrip())
    return "\n".join(lines) + "\n"
