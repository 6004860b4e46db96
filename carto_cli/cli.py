"""The `carto` command line: parses arguments and calls the library; nothing more."""
from __future__ import annotations

import functools
import inspect
import json
import re
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from typer.core import TyperCommand, TyperGroup

from carto_cli import __version__
from carto_cli.core.errors import CartoError

if TYPE_CHECKING:  # the commands are imported when run: `carto --help` loads none of them
    from carto_cli.commands.relocalize import RelocalizeRequest

EXIT_STATUS = ("Exit status, every command: 0 success; 1 internal error; 2 bad input or usage; 3 a check you "
               "asked for failed (a gate of eval or profile, a 'failed' map or a 'suspect' one with map --strict, "
               "a relocalization judged 'lost'); 4 a relocalization judged 'ambiguous'; 130 interrupted (Ctrl-C or "
               "SIGTERM).")

_MARKUP_TAG = re.compile(r"(\\*)(\[[a-z#/@][^[]*?])")  # what rich.markup.escape escapes, without importing rich


def _plain(text: str | None) -> str | None:
    if not text:
        return text
    paragraphs = inspect.cleandoc(text).split("\n\n")
    return "\n\n".join(p if p.startswith("\b") else _MARKUP_TAG.sub(r"\1\1\\\2", " ".join(p.split()))
                       for p in paragraphs)


def _tidy_help(command) -> None:
    """What carto's --help needs from typer's rich help, whichever typer renders it.

    - A paragraph reads as one: typer's rich markup mode keeps a docstring's line breaks (in the paragraphs after
      the first, and in the first too where a group lists its commands), so source wrapped at 120 columns came
      out as sentences broken mid-line.
    - Help is plain text: "[sigma_xy sigma_yaw]" is not a rich style tag to swallow.
    - A flag takes no value and shows none (typer >= 0.2x prints <bool> beside it, its own --help included); an
      argument's name and description say what it is (typer >= 0.2x adds <path>, <str>).
    - A required argument reads RECORDING, as in any usage line, not typer's {RECORDING} (_Command, _Group).
    """
    command.help = _plain(command.help)
    for param in command.params:
        if getattr(param, "help", None):
            param.help = _plain(param.help)
        if getattr(param, "is_flag", False) and param.metavar is None:
            param.metavar = ""
        if getattr(param, "param_type_name", None) == "argument" and hasattr(param, "display_type_rich"):
            param.display_type_rich = lambda ctx: None


def _usage_pieces(pieces: list[str]) -> list[str]:
    return [re.sub(r"^\{(.+)\}(\.\.\.)?$", r"\1\2", piece) for piece in pieces]


class _TidyHelp:
    """For typer's command and group classes: help tidied once made (_tidy_help), and --help shown as a flag."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        _tidy_help(self)

    def get_help_option(self, ctx):
        option = super().get_help_option(ctx)  # type: ignore[misc]  # a mixin: click's Command is next in the MRO
        if option is not None:
            option.metavar = ""
        return option


class _Command(_TidyHelp, TyperCommand):
    def collect_usage_pieces(self, ctx):
        return _usage_pieces(super().collect_usage_pieces(ctx))


class _Group(_TidyHelp, TyperGroup):
    pass


class _Typer(typer.Typer):
    """typer.Typer whose groups and commands tidy their help (_tidy_help), read as rich markup by any typer."""

    def __init__(self, **kwargs):
        kwargs.setdefault("cls", _Group)
        kwargs.setdefault("rich_markup_mode", "rich")
        super().__init__(**kwargs)

    def command(self, *args, **kwargs):
        kwargs.setdefault("cls", _Command)
        return super().command(*args, **kwargs)


PANEL_INPUT = "Input"  # what is read from the recording: topics, frames, the laser's mount, the cloud slice
PANEL_MAPPING = "Mapping"
PANEL_OUTPUT = "Output"
PANEL_GATES = "CI gates"
PANEL_PRIOR = "Prior"
PANEL_SCANS = "Scans"
PANEL_IMAGE = "Image"
PANEL_STUDY = "Study"
PANEL_OBJECTIVE = "Objective"
PANEL_PERFORMANCE = "Performance"

app = _Typer(
    add_completion=False,
    no_args_is_help=True,
    help="2D LiDAR SLAM from recorded data: maps, relocalization, tuning and profiling.",
    epilog=EXIT_STATUS,
    context_settings={"help_option_names": ["-h", "--help"]},
    pretty_exceptions_enable=False,
)


class _State:
    debug = False
    quiet = False


state = _State()


def _fail(message: str, code: int) -> None:
    typer.echo(f"carto: {message}", err=True)
    raise typer.Exit(code)


EXIT_INTERNAL = 1
EXIT_USAGE = 2  # bad input: the file and the problem in one line
EXIT_CHECK_FAILED = 3  # a check the user relies on failed: a gate, a 'failed' map, a 'lost' relocalization
EXIT_AMBIGUOUS = 4  # relocalize: an answer, but another place fits about as well
EXIT_INTERRUPTED = 130  # Ctrl-C or SIGTERM


def handle_errors(fn):
    """User errors: one line, exit 2. Internal errors: one line, exit 1. Interrupted: exit 130. Tracebacks only
    with --debug."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from carto_cli.core import interrupts

        interrupts.clear()
        try:
            try:
                return fn(*args, **kwargs)
            except typer.Exit:
                raise
            except Exception as e:
                # Ctrl-C or SIGTERM surfaces as whatever it broke: numba's SystemError around the
                # KeyboardInterrupt, a reader's "corrupt file", a child process gone. After one, every error is
                # its echo.
                if interrupts.is_interrupt(e):
                    raise KeyboardInterrupt from e
                raise
            finally:
                interrupts.hold()  # the command is over: a second Ctrl-C must not cut the report below short
        except typer.Exit:
            raise
        except CartoError as e:
            if state.debug:
                raise
            _fail(f"error: {e}", EXIT_USAGE)
        except KeyboardInterrupt:
            _fail("interrupted", EXIT_INTERRUPTED)
        except BrokenPipeError:
            # The reader went away (`carto options | head`): what it wanted was written; say nothing, as cat does.
            import os
            import sys

            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            raise typer.Exit(0) from None
        except Exception as e:
            if state.debug:
                raise
            _fail(f"internal error: {type(e).__name__}: {e} (rerun with --debug for a traceback)", EXIT_INTERNAL)

    return wrapper


def _version(value: bool):
    if value:
        typer.echo(f"carto {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks for errors."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress: neither the bar on a terminal nor the "
                               "lines in a log (stderr not a terminal)."),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
):
    state.debug = debug
    state.quiet = quiet
    from carto_cli.core import kernels

    kernels.on_compiling(None if quiet else _say_compiling)


def _say_compiling(sentence: str) -> None:
    typer.echo(f"carto: {sentence}", err=True)


# One default everywhere: the options' trajectory_builder_2d.min_z / max_z (io.recording.ReadOptions keeps them)
MIN_Z = typer.Option(None, "--min-z", metavar="M", rich_help_panel=PANEL_INPUT,
                     help="PointCloud2: lowest z of the 2D slice in the sensor frame (m; default -0.8 with --max-z; "
                          "neither: a band above the floor, chosen from the clouds).")
MAX_Z = typer.Option(None, "--max-z", metavar="M", rich_help_panel=PANEL_INPUT,
                     help="PointCloud2: highest z of the 2D slice in the sensor frame (m; default 2.0 with --min-z).")
# Commands that map take the slice as options (trajectory_builder_2d.min_z / max_z, and cloud_band=sensor when either
# is given): unset keeps the profile's
MAP_MIN_Z = typer.Option(None, "--min-z", metavar="M", rich_help_panel=PANEL_INPUT,
                         help="PointCloud2: lowest z, sensor frame (m; default: a band above the floor).")
MAP_MAX_Z = typer.Option(None, "--max-z", metavar="M", rich_help_panel=PANEL_INPUT,
                         help="PointCloud2: highest z, sensor frame (m; default: see --min-z).")
RECORDING = typer.Argument(..., metavar="RECORDING",
                           help="ROS1 .bag, ROS2 bag directory, .mcap or CARMEN .clf/.log[.gz].")
# Several: lasers mapped (relocalized) together, their scans merged (io.topics)
SCAN_TOPICS = typer.Option(None, "--scan-topic", metavar="TOPIC", rich_help_panel=PANEL_INPUT,
                           help="Which scan topic; repeat for several lasers.")
ODOM_TOPIC = typer.Option(None, "--odom-topic", metavar="TOPIC", rich_help_panel=PANEL_INPUT,
                          help="Which odometry topic, if there are several.")
IMU_TOPIC = typer.Option(None, "--imu-topic", metavar="TOPIC", rich_help_panel=PANEL_INPUT,
                         help="Which IMU topic, if there are several.")


def _topics(names: list[str] | None) -> str | tuple[str, ...] | None:
    """``--scan-topic`` as given: none, one, or several (lasers mapped together)."""
    if not names:
        return None
    return names[0] if len(names) == 1 else tuple(names)


def _with_z(overrides: list[str] | None, min_z: float | None, max_z: float | None,
            memory_budget: str | None = None) -> list[str]:
    """--min-z / --max-z (and --memory-budget) as option overrides, after --set so that they win."""
    out = list(overrides or [])
    if memory_budget is not None:
        from carto_cli.core.parse import megabytes

        mb = megabytes(memory_budget, "--memory-budget")
        out.append(f"pose_graph.constraint_builder.precomputation_memory={mb!r}")
    if min_z is not None:
        out.append(f"trajectory_builder_2d.min_z={min_z!r}")
    if max_z is not None:
        out.append(f"trajectory_builder_2d.max_z={max_z!r}")
    if min_z is not None or max_z is not None:
        # A slice given in z is the sensor frame's, as it always was; the floor-relative band is cloud_band's.
        out.append("trajectory_builder_2d.cloud_band=sensor")
    return out


@app.command()
@handle_errors
def info(
    recording: Path = RECORDING,
    as_json: bool = typer.Option(False, "--json", help="Machine-readable output."),
    min_z: float | None = MIN_Z,
    max_z: float | None = MAX_Z,
):
    """Describe a recording: topics, rates, scan geometry, static TF, warnings."""
    from carto_cli.commands.common import z_slice
    from carto_cli.commands.info import format_info, run_info
    from carto_cli.core.progress import progress

    read = z_slice(min_z, max_z)
    with progress(f"reading {recording.name}", None, state.quiet, unit="messages") as bar:
        result = run_info(recording, read, on_total=bar.set_total, on_record=bar.advance)
    if as_json:
        typer.echo(json.dumps(result.to_dict(), indent=2, allow_nan=False, default=_json_default))
    else:
        typer.echo(format_info(result))


def _json_default(value):
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


@app.command()
@handle_errors
def convert(
    source: Path = typer.Argument(..., metavar="SOURCE", help="Any recording carto reads."),
    out: Path = typer.Argument(..., metavar="OUT",
                               help="Output: .bag (ROS1), .mcap (standalone MCAP) or a directory (ROS2 bag)."),
    fmt: str | None = typer.Option(
        None, "--format", metavar="FORMAT", help="ros1, ros2-sqlite3, ros2-mcap or mcap (default: from OUT's suffix)."
    ),
    scan_topic: str | None = typer.Option(None, "--scan-topic", metavar="TOPIC", rich_help_panel=PANEL_INPUT,
                                          help="Only this scan topic."),
    odom_topic: str | None = typer.Option(None, "--odom-topic", metavar="TOPIC", rich_help_panel=PANEL_INPUT,
                                          help="Only this odometry topic."),
    imu_topic: str | None = typer.Option(None, "--imu-topic", metavar="TOPIC", rich_help_panel=PANEL_INPUT,
                                         help="Only this IMU topic."),
    force: bool = typer.Option(False, "--force", "-f", help="Replace OUT if it exists."),
    min_z: float | None = MIN_Z,
    max_z: float | None = MAX_Z,
):
    """Convert between ROS1 bags, ROS2 bags (sqlite3 / mcap storage) and MCAP (ROS1 <-> ROS2: every topic, lossless)."""
    from carto_cli.commands.common import z_slice
    from carto_cli.commands.convert import run_convert
    from carto_cli.core.progress import progress

    read = z_slice(min_z, max_z)
    with progress(f"converting {source.name}", None, state.quiet, unit="messages") as bar:
        done = run_convert(source, out, fmt=fmt, scan_topic=scan_topic, odom_topic=odom_topic, imu_topic=imu_topic,
                           overwrite=force, read=read, on_total=bar.set_total, on_record=bar.advance)
    for warning in done.warnings:
        typer.echo(f"carto: warning: {warning}", err=True)
    if done.left_out:
        typer.echo(f"carto: warning: not copied (carto's writer carries scans, odometry, IMU and static TF; ROS1 <-> "
                   f"ROS2 with every topic is lossless): {', '.join(done.left_out)}", err=True)
    if not state.quiet:
        how = ", lossless: every topic and stamp as recorded" if done.lossless else ""
        typer.echo(f"wrote {done.messages} messages to {done.out} ({done.format}{how})", err=True)


ODOM_FRAME = typer.Option(
    None, "--odom-frame", metavar="FRAME", rich_help_panel=PANEL_INPUT,
    help="Odometry from /tf when there is no Odometry topic: the odometry frame (default: odom*).")
BASE_FRAME = typer.Option(
    None, "--base-frame", metavar="FRAME", rich_help_panel=PANEL_INPUT,
    help="Odometry from /tf: the robot's frame (default: where the laser's static TF ends, else base_footprint / "
         "base_link).")
PROFILE = typer.Option(None, "--profile", "-p", metavar="NAME",
                       help="Profile name (profiles/NAME.yaml) or path, layered over the default.")
MAP_PROFILE = typer.Option(
    None, "--profile", "-p", metavar="NAME",
    help="auto (the default: chosen from the recording, see the 'auto:' line), default (Cartographer's stock "
         "values), a profile's name (profiles/NAME.yaml) or path.")
SET = typer.Option(None, "--set", "-s", metavar="KEY=VALUE",
                   help="Override an option (its dotted name: `carto options`; angles in radians, or '20deg'). "
                        "Repeatable.")
MEMORY_BUDGET = typer.Option(
    None, "--memory-budget", metavar="SIZE", rich_help_panel=PANEL_PERFORMANCE,
    help="Memory for the loop-closure search's precomputation grids, e.g. 512MB or 1GB (default: "
         "precomputation_memory, 256MB); the least recently searched are rebuilt when needed. The map is the same "
         "for any budget.")


def _at_least_one(value: int | None) -> int | None:
    # Checked here rather than with min=1, which typer shows as "[x>=1]" beside the metavar.
    if value is not None and value < 1:
        raise typer.BadParameter(f"must be at least 1, got {value}")
    return value


JOBS = typer.Option(
    None, "--jobs", "-j", metavar="N", callback=_at_least_one, rich_help_panel=PANEL_PERFORMANCE,
    help="Threads (Cartographer: the pose graph beside local SLAM, loop-closure searches; GMapping: particles, "
         "final searches); default: every core. The map is the same for any number.")
# The names are carto_cli.gmapping.ALGORITHMS, checked by the command (importing it here would load numba
# for `carto --help`).
ALGORITHM = typer.Option(
    None, "--algorithm", metavar="NAME", rich_help_panel=PANEL_MAPPING,
    help="cartographer, gmapping (a Rao-Blackwellized particle filter; its options: `carto options gmapping`, "
         "e.g. --set gmapping.particles=30) or scan-to-map (gmapping's pipeline with one pose matched on a "
         "distance map: about a tenth of its CPU, but no recovery from a wrong match). Default: auto's choice, "
         "gmapping for key scans with odometry; cartographer with a named profile.")


def _options(profile: str | None, overrides: list[str] | None):
    from carto_cli.options import load_options

    options = load_options(profile, overrides or [])
    if profile is not None and str(profile).endswith(".lua"):
        from carto_cli.options.cartographer_lua import import_lua

        note = import_lua(profile).note()  # what a Cartographer configuration set that carto does not use
        if note:
            typer.echo(f"carto: note: {note}", err=True)
    return options


def _map_options(profile: str | None, overrides: list[str] | None):
    """--profile for commands that map: auto (None) chooses from the recording."""
    if profile in (None, "auto"):
        from carto_cli.pipeline import Auto

        auto = Auto(tuple(overrides or ()))
        auto.base  # noqa: B018 - a bad --set fails before the recording is read (and is loaded once)
        return auto
    return _options(profile, overrides)


def _say_configured(configured) -> None:
    if configured.auto is not None and not state.quiet:
        # describe() names the mapping system (auto's choice, or the user's --algorithm) when it is not Cartographer.
        typer.echo(f"auto: {configured.regime.describe()} -> {configured.auto.describe()}", err=True)


@app.command("map")
@handle_errors
def map_(
    recordings: list[Path] = typer.Argument(
        ..., metavar="RECORDING...",
        help="ROS1 .bag, ROS2 bag directory, .mcap or CARMEN .clf/.log[.gz]; several of one building make one map "
             "(each later one placed by loop closures)."),
    outdir: Path | None = typer.Option(None, "--output", "-o", metavar="DIR",
                                       help="Output directory (default: NAME_map here, NAME the first "
                                            "recording's)."),
    profile: str | None = MAP_PROFILE,
    overrides: list[str] | None = SET,
    force: bool = typer.Option(False, "--force", "-f", help="Replace a map already in the output directory."),
    algorithm: str | None = ALGORITHM,
    no_loop_closure: bool = typer.Option(
        False, "--no-loop-closure", rich_help_panel=PANEL_MAPPING,
        help="Local SLAM only (to tune local SLAM)."
    ),
    load_state: Path | None = typer.Option(
        None, "--load-state", metavar="FILE", rich_help_panel=PANEL_MAPPING,
        help="Continue mapping into this map.carto: the recording becomes a new trajectory."
    ),
    lifelong: bool = typer.Option(
        False, "--lifelong", rich_help_panel=PANEL_MAPPING,
        help="Several recordings: trim the superseded."
    ),
    align: str = typer.Option(
        "auto", "--align", metavar="MODE", rich_help_panel=PANEL_MAPPING, show_default=False,
        help="auto (default): square to the walls; none."
    ),
    no_clean: bool = typer.Option(False, "--no-clean", rich_help_panel=PANEL_MAPPING,
                                  help="Keep what left during the recording."),
    scan_topic: list[str] | None = SCAN_TOPICS,
    odom_topic: str | None = ODOM_TOPIC,
    imu_topic: str | None = IMU_TOPIC,
    no_odometry: bool = typer.Option(False, "--no-odometry", rich_help_panel=PANEL_INPUT,
                                     help="Ignore the recording's odometry."),
    odom_frame: str | None = ODOM_FRAME,
    base_frame: str | None = BASE_FRAME,
    laser_pose: list[str] | None = typer.Option(
        None, "--laser-pose", metavar="X,Y,YAW", rich_help_panel=PANEL_INPUT,
        help="The laser's pose on the robot (m, m, rad or 'deg'; TOPIC=X,Y,YAW for each of several); default: "
        "static TF, else identity."
    ),
    min_z: float | None = MAP_MIN_Z,
    max_z: float | None = MAP_MAX_Z,
    no_state: bool = typer.Option(False, "--no-state", rich_help_panel=PANEL_OUTPUT,
                                  help="Do not write map.carto (the file relocalize loads)."),
    show_removed: bool = typer.Option(False, "--show-removed", rich_help_panel=PANEL_OUTPUT,
                                      help="Mark in map.png what cleaning drew free."),
    timings: bool = typer.Option(False, "--timings", rich_help_panel=PANEL_OUTPUT,
                                 help="Print the per-stage timing tree."),
    strict: bool = typer.Option(False, "--strict", rich_help_panel=PANEL_OUTPUT,
                                help="Exit 3 on a 'suspect' map too (for CI)."),
    jobs: int | None = JOBS,
    memory_budget: str | None = MEMORY_BUDGET,
):
    """Build a map: map.pgm + map.yaml (map_server), map.png, trajectory.tum, map.carto, summary.json; with
    several recordings (or --load-state) also trajectory_N.tum per recording and sessions.json (their links).

    The outputs are written as one set (all replaced together or none); an earlier map in the output
    directory is kept unless --force. carto judges its own map: 'map quality: ok | suspect | failed' with the
    reasons (also in summary.json); a 'failed' map (or a 'suspect' one with --strict) exits 3, its outputs
    still written for a look."""
    from carto_cli.commands.map import run_map, summary_line
    from carto_cli.core import parse
    from carto_cli.core.progress import progress
    from carto_cli.core.timing import StageTimer, report_tree_text
    from carto_cli.mapping.alignment import Align
    from carto_cli.mapping.lifelong import SessionPolicy
    from carto_cli.pipeline import MapRequest, TopicChoice

    recording = recordings[0]
    request = MapRequest(
        recording, _map_options(profile, _with_z(overrides, min_z, max_z, memory_budget)), algorithm,
        TopicChoice(_topics(scan_topic), odom_topic, imu_topic, odom_frame, base_frame),
        laser_pose=parse.laser_poses(laser_pose, "--laser-pose") if laser_pose else None,
        use_odometry=not no_odometry,
        loop_closure=not no_loop_closure, load_state=load_state, jobs=jobs, later=tuple(recordings[1:]),
        sessions=SessionPolicy.LIFELONG if lifelong else SessionPolicy.LAST_SEEN, clean=not no_clean,
        align=Align.named(align))
    timer = StageTimer()
    label = recording.name + (f" + {len(recordings) - 1} more" if len(recordings) > 1 else "")
    with progress(f"mapping {label}", None, state.quiet) as bar:
        result, outputs = run_map(request, outdir, timer=timer, on_scan=bar.advance, on_total=bar.set_total,
                                  on_configured=_say_configured, state=not no_state, force=force,
                                  show_removed=show_removed)
    for warning in result.warnings:
        typer.echo(f"carto: warning: {warning}", err=True)
    if timings:
        typer.echo(report_tree_text(timer))
    _say_map(f"{summary_line(result, timer)} -> {outputs.yaml.parent}", result, strict)


@app.command("merge")
@handle_errors
def merge_(
    maps: list[Path] = typer.Argument(
        ..., metavar="MAP...",
        help="map.carto files (or Cartographer's .pbstream) of one building, made separately; the first fixes the "
             "frame and the options."),
    outdir: Path = typer.Option(..., "--output", "-o", metavar="DIR", help="Output directory."),
    force: bool = typer.Option(False, "--force", "-f", help="Replace a map already in the output directory."),
    timings: bool = typer.Option(False, "--timings", rich_help_panel=PANEL_OUTPUT,
                                 help="Print the per-stage timing tree."),
    strict: bool = typer.Option(False, "--strict", rich_help_panel=PANEL_OUTPUT,
                                help="Exit 3 on a 'suspect' map too, not only a 'failed' one (for CI)."),
    jobs: int | None = JOBS,
):
    """Merge saved maps without their recordings, each later one placed by loop closures.

    Each later map is placed by the loop-closure search and link rule that place a later recording of `carto map
    A B`, then optimized jointly; the same outputs and sessions.json. A map linked to none fails (exit 3), its
    outputs still written for a look."""
    from carto_cli.commands.merge import merged_line, run_merge
    from carto_cli.core.progress import progress
    from carto_cli.core.timing import StageTimer, report_tree_text

    timer = StageTimer()
    with progress(f"merging {len(maps)} maps", None, state.quiet, unit="nodes") as bar:
        result, outputs = run_merge(maps, outdir, force=force, jobs=jobs, timer=timer, on_total=bar.set_total,
                                    on_nodes=bar.advance)
    if timings:
        typer.echo(report_tree_text(timer))
    _say_map(f"{merged_line(result)} -> {outputs.yaml.parent}", result, strict)


def _say_map(summary: str, result, strict: bool) -> None:
    """A map just written, as `carto map` and `carto merge` say it: its summary, its sessions, its verdict (exit 3
    when it fails)."""
    from carto_cli.commands.map import cleaning_lines, sessions_lines

    typer.echo(summary)
    aligned = getattr(result, "alignment", None)
    for line in sessions_lines(result) + ([f"aligned: {aligned.describe()}"] if aligned else []) + cleaning_lines(
            result):
        typer.echo(line)
    if result.quality is not None:
        typer.echo(result.quality.line(), err=not result.quality.ok)
        if result.quality.fails(strict=strict):
            raise typer.Exit(EXIT_CHECK_FAILED)


def _finish_gates(gates, junit: Path | None, suite: str, label: str) -> None:
    """JUnit output if asked, one stderr line per failed gate, exit 3 if any failed."""
    from carto_cli.commands.common import record_gates

    failed = record_gates(gates, junit, suite)
    for g in failed:
        typer.echo(f"carto: {label}: {g.message}", err=True)
    if failed:
        raise typer.Exit(EXIT_CHECK_FAILED)


@app.command("eval")
@handle_errors
def eval_(
    trajectories: list[Path] = typer.Argument(
        ..., metavar="TRAJECTORY...",
        help="Trajectory to score: TUM (t x y z qx qy qz qw) or 't x y theta'. Several (a map's trajectory_N.tum): "
             "ATE of each in their common frame, one alignment for all."),
    relations: Path | None = typer.Option(None, "--relations", metavar="FILE",
                                          help="Relations file: t1 t2 dx dy dz droll dpitch dyaw."),
    ground_truth: list[Path] | None = typer.Option(
        None, "--ground-truth", metavar="FILE",
        help="Reference trajectory (TUM or 't x y theta'); with several trajectories, one for all or one each."),
    rpe_delta: float = typer.Option(1.0, "--rpe-delta", metavar="S", help="RPE step in seconds (with --ground-truth)."),
    as_json: bool = typer.Option(False, "--json", help="Machine-readable output."),
    max_trans_error: float | None = typer.Option(
        None, "--max-trans-error", metavar="M", rich_help_panel=PANEL_GATES,
        help="Exit 3 if the mean relation error (else ATE RMSE) exceeds M metres."),
    max_rot_error: float | None = typer.Option(
        None, "--max-rot-error", metavar="DEG", rich_help_panel=PANEL_GATES,
        help="Exit 3 if the mean rotational error exceeds DEG degrees."),
    junit: Path | None = typer.Option(None, "--junit", metavar="FILE", rich_help_panel=PANEL_GATES,
                                      help="Write the gates' outcome as JUnit XML."),
):
    """Score a trajectory: relation error (Kuemmerle et al.) and/or ATE + RPE against a ground truth."""
    from carto_cli.commands.eval import run_eval, run_eval_sessions
    from carto_cli.evaluation.metrics import format_table

    if len(trajectories) > 1:
        if relations is not None:
            raise CartoError("--relations scores one trajectory; several are scored by ATE (--ground-truth)")
        several = run_eval_sessions(trajectories, list(ground_truth or []), max_trans_error=max_trans_error,
                                    max_rot_error=max_rot_error)
        typer.echo(json.dumps(several.data, indent=2) if as_json else "\n".join(several.lines()))
        if several.gates is not None:
            _finish_gates(several.gates, junit, "carto.eval", "gate failed")
        return
    if ground_truth is not None and len(ground_truth) > 1:
        raise CartoError("one trajectory takes one --ground-truth")
    run = run_eval(trajectories[0], relations=relations, ground_truth=ground_truth[0] if ground_truth else None,
                   rpe_delta=rpe_delta, max_trans_error=max_trans_error, max_rot_error=max_rot_error)
    if as_json:
        typer.echo(json.dumps(run.data, indent=2))
    else:
        typer.echo(format_table(run.result))
    if run.gates is None:
        return
    _finish_gates(run.gates, junit, "carto.eval", "gate failed")


@app.command("profile")
@handle_errors
def profile_(
    recording: Path = typer.Argument(..., metavar="RECORDING", help="Recording to run the whole pipeline on."),
    profile: str | None = MAP_PROFILE,
    overrides: list[str] | None = SET,
    as_json: bool = typer.Option(False, "--json", help="Print the report as JSON (schema carto.profile v1)."),
    output: Path | None = typer.Option(None, "--output", metavar="FILE",
                                       help="Also write the JSON report to this file."),
    force: bool = typer.Option(False, "--force", "-f", help="Replace the --output file if it exists."),
    algorithm: str | None = ALGORITHM,
    max_scans: int | None = typer.Option(None, "--max-scans", metavar="N", rich_help_panel=PANEL_MAPPING,
                                         help="Profile only the first N scans."),
    repeat: int = typer.Option(1, "--repeat", metavar="N", rich_help_panel=PANEL_MAPPING,
                               help="Map the recording N times; each stage keeps its lowest CPU time and the "
                                    "spread, which widens the gates' allowance (3 for CI baselines)."),
    relocalize_map: Path | None = typer.Option(
        None, "--relocalize", metavar="MAP", rich_help_panel=PANEL_MAPPING,
        help="Also profile relocalizing every 10th scan of RECORDING in this map.carto."),
    baseline: Path | None = typer.Option(None, "--baseline", metavar="FILE", rich_help_panel=PANEL_GATES,
                                         help="A previous --output to compare against."),
    max_regression: float = typer.Option(0.20, "--max-regression", metavar="FRACTION", rich_help_panel=PANEL_GATES,
                                         help="Allowed slow-down per stage (0.20 = 20%)."),
    calibrate: bool = typer.Option(False, "--calibrate", rich_help_panel=PANEL_GATES,
                                   help="Time a reference kernel first and compare normalized times."),
    junit: Path | None = typer.Option(None, "--junit", metavar="FILE", rich_help_panel=PANEL_GATES,
                                      help="Write the gates' outcome as JUnit XML."),
    scan_topic: list[str] | None = SCAN_TOPICS,
    odom_topic: str | None = ODOM_TOPIC,
    odom_frame: str | None = ODOM_FRAME,
    base_frame: str | None = BASE_FRAME,
    min_z: float | None = MAP_MIN_Z,
    max_z: float | None = MAP_MAX_Z,
    jobs: int | None = JOBS,
    memory_budget: str | None = MEMORY_BUDGET,
):
    """Per-stage timing tree of the whole pipeline (ms/scan, share, p50/p95/p99), with CI regression gates.

    The gates compare each stage's CPU time (every thread of the process), which a job on another core hardly
    changes; the tree shows wall time."""
    from carto_cli.commands.profile import run_profile
    from carto_cli.core.progress import progress
    from carto_cli.evaluation.profiling import format_relocalization, format_report
    from carto_cli.pipeline import MapRequest, TopicChoice

    request = MapRequest(recording, _map_options(profile, _with_z(overrides, min_z, max_z, memory_budget)),
                         algorithm, TopicChoice(_topics(scan_topic), odom_topic, odom_frame=odom_frame,
                                                base_frame=base_frame),
                         max_scans=max_scans, jobs=jobs)
    with progress(f"profiling {recording.name}", None, state.quiet) as bar:
        run = run_profile(request, output=output, baseline=baseline, calibrate_first=calibrate,
                          relocalize_map=relocalize_map, on_total=bar.set_total, on_scan=bar.advance, force=force,
                          repeat=repeat)
    for warning in run.warnings:
        typer.echo(f"carto: warning: {warning}", err=True)
    report = run.report
    typer.echo(json.dumps(report, indent=2) if as_json else format_report(report))
    if not as_json and "relocalization" in report:
        typer.echo("\n" + format_relocalization(report["relocalization"]))
    if run.baseline is None:
        return
    _finish_gates(run.gates(max_regression), junit, "carto.profile", "slower than baseline")


def _heading_sigma(text: str) -> float:
    """--sigma-yaw in radians, or degrees with a 'deg' suffix, as every angle carto reads."""
    import math

    from carto_cli.core import parse

    value = parse.angle(text, "--sigma-yaw", CartoError)
    if value > math.pi and not text.strip().lower().endswith("deg"):
        # --sigma-yaw took degrees until it followed --initial-pose: a bare number above half a turn is most
        # likely a command line from then, and read as radians it would silently widen the search to every heading.
        raise CartoError(f"--sigma-yaw is in radians: {text} rad is more than half a turn (for degrees: {text}deg)")
    return value


@app.command("relocalize")
@handle_errors
def relocalize_(
    map_file: Path = typer.Argument(
        ..., metavar="MAP",
        help="map.carto written by `carto map`, or a map_server YAML (PGM/PNG image: slam_toolbox, GMapping, "
                  "a floor plan)."),
    recording: Path = typer.Argument(..., metavar="RECORDING", help="Recording holding the scan(s) to relocalize."),
    initial_pose: str | None = typer.Option(
        None, "--initial-pose", metavar="X,Y,YAW", rich_help_panel=PANEL_PRIOR,
        help="Prior pose in the map frame (m, m, rad, or 'deg' suffixed)."),
    at: float | None = typer.Option(None, "--at", metavar="T", rich_help_panel=PANEL_SCANS,
                                    help="Relocalize the scan nearest this time (s)."),
    scan_index: int | None = typer.Option(None, "--scan-index", metavar="N", rich_help_panel=PANEL_SCANS,
                                          help="Relocalize the N-th scan (from 0)."),
    sigma_xy: float | None = typer.Option(None, "--sigma-xy", metavar="M", rich_help_panel=PANEL_PRIOR,
                                          help="Prior position uncertainty (m)."),
    sigma_yaw: str | None = typer.Option(None, "--sigma-yaw", metavar="ANGLE", rich_help_panel=PANEL_PRIOR,
                                         help="Prior heading uncertainty (rad, or 'deg' suffixed: 5deg)."),
    corridor: bool = typer.Option(False, "--corridor", rich_help_panel=PANEL_PRIOR,
                                  help="Search only a sector along the prior's heading."),
    global_: bool = typer.Option(False, "--global", rich_help_panel=PANEL_PRIOR,
                                 help="No prior: search every submap."),
    queries: Path | None = typer.Option(
        None, "--queries", metavar="FILE", rich_help_panel=PANEL_SCANS,
        help="Batch: a text file, one query a line, 'T x y yaw [sigma_xy sigma_yaw]' ('- - -': "
        "global). T is a time (s, the recording's clock), also without a header line; a first line 'index x y yaw' "
        "makes it a scan index (from 0). Writes a CSV."),
    csv_out: Path | None = typer.Option(None, "--csv", metavar="FILE", rich_help_panel=PANEL_SCANS,
                                        help="Batch results (default: QUERIES.results.csv)."),
    scan_topic: list[str] | None = SCAN_TOPICS,
    overrides: list[str] | None = typer.Option(
        None, "--set", "-s", metavar="KEY=VALUE",
        help="Override one of the map's options, e.g. relocalization.min_score=0.65 "
        "(repeatable; angles in radians, or '20deg')."),
    as_json: bool = typer.Option(False, "--json", help="Machine-readable output."),
    force: bool = typer.Option(False, "--force", "-f", help="Replace the results CSV if it exists."),
    max_jump: float | None = typer.Option(
        None, "--max-jump", metavar="M", rich_help_panel=PANEL_PRIOR,
        help="An answer farther than M from the prior (m) is judged 'lost'."),
    profile: str | None = typer.Option(
        None, "--profile", "-p", metavar="NAME",
        help="Relocalization settings of a profile (office, corridor, ... or a path), not the map's own; a map_server "
             "map takes the whole profile."),
    track: bool = typer.Option(
        False, "--track", rich_help_panel=PANEL_SCANS,
        help="A pose for every scan of the recording: first fix from --initial-pose or a global "
        "search, then odometry-predicted matches; writes trajectory.tum, track.csv, track.json into -o."),
    output: Path | None = typer.Option(None, "--output", "-o", metavar="DIR", rich_help_panel=PANEL_SCANS,
                                       help="--track: output directory (default NAME_track "
                                       "in the current directory)."),
    odom_topic: str | None = typer.Option(
        None, "--odom-topic", metavar="TOPIC", rich_help_panel=PANEL_INPUT,
        help="Odometry topic: --track's predictions, and the scans around a query that check "
        "an answer no prior's window confirmed."),
    odom_frame: str | None = ODOM_FRAME,
    base_frame: str | None = BASE_FRAME,
    min_z: float | None = MIN_Z,
    max_z: float | None = MAX_Z,
    jobs: int | None = typer.Option(None, "--jobs", "-j", metavar="N", callback=_at_least_one,
                                    rich_help_panel=PANEL_PERFORMANCE,
                                    help="--queries: queries relocalized at once; one query or --track: threads "
                                         "for a whole-map search (default: every core). The answers are the same "
                                         "for any number; a batch's timings include waiting for a core (1 for "
                                         "latency figures)."),
):
    """Find scans in a saved map: windowed search from a prior, fallbacks, or a global search.

    Every answer carries a verdict: ok (exit 0), ambiguous (another place fits about as well; exit 4) or lost
    (exit 3), with the reason, a covariance, the ambiguity ratio and the share of points on walls."""
    import math

    from carto_cli.commands.common import z_slice

    yaw_sigma = None if sigma_yaw is None else _heading_sigma(sigma_yaw)
    # Before the request, whose own checks (--max-jump) the command has always reported after this one.
    if output is not None and not track:
        raise CartoError("--output goes with --track")
    from carto_cli.commands.relocalize import RelocalizeRequest, RelocalizeScans, run_relocalize
    from carto_cli.pipeline import TopicChoice

    request = RelocalizeRequest(
        map_file, recording, initial_pose=initial_pose, sigma_xy=sigma_xy, sigma_yaw=yaw_sigma, max_jump=max_jump,
        profile=profile, overrides=tuple(overrides or ()),
        read=None if min_z is None and max_z is None else z_slice(min_z, max_z),
        topics=TopicChoice(scan=_topics(scan_topic), odometry=odom_topic, odom_frame=odom_frame,
                           base_frame=base_frame),
        jobs=jobs)
    if track:
        _track(request, output, force=force, as_json=as_json)
        return
    scans = RelocalizeScans(request, at=at, scan_index=scan_index, global_search=global_, corridor=corridor,
                            queries=queries, csv_out=csv_out)
    run = run_relocalize(scans, on_warning=lambda w: typer.echo(f"carto: warning: {w}", err=True),
                         quiet=state.quiet, force=force)
    if run.auto is not None and not as_json:
        typer.echo(f"auto: {run.auto.describe()}", err=True)
    from carto_cli.commands.common import compiling_note

    if as_json:
        typer.echo(json.dumps(run.to_dict(), indent=2))
    elif run.summary is not None:
        s = run.summary
        typer.echo(f"{s.successes}/{s.queries} relocalized ({100 * s.success_rate:.1f}%; "
                   + ", ".join(f"{k} {v}" for k, v in s.verdicts.items())
                   + f"), p50 {s.p50_ms:.1f} ms, p95 {s.p95_ms:.1f} ms, p99 {s.p99_ms:.1f} ms"
                   + f"{compiling_note(run.compile_s)} -> {run.csv}")
    else:
        result, scan = run.result, run.scan
        assert result is not None and scan is not None
        x, y, yaw = result.pose
        t = result.timings
        sig = result.sigmas
        typer.echo(f"scan {run.scan_index} at {scan.time:.3f}: pose {x:.3f} {y:.3f} {math.degrees(yaw):.2f}° "
                   f"verdict {result.verdict}, score {result.score:.3f} via {result.path}, "
                   f"{len(result.submaps_considered)} submaps")
        if sig is not None:
            typer.echo(f"sigma {sig[0]:.3f} m, {sig[1]:.3f} m, {math.degrees(sig[2]):.2f}°; ambiguity "
                       f"{result.ambiguity:.3f}; {100 * result.inlier_fraction:.0f} % of the points on walls")
        typer.echo("timing " + ", ".join(f"{k} {v:.1f} ms" for k, v in t.items())
                   + f", total {result.total_ms:.1f} ms{compiling_note(run.compile_s)}")
        if result.reason:
            typer.echo(f"{'why' if not result.success else 'notes'}: {result.reason}")
    if run.result is not None and run.result.verdict != "ok":
        raise typer.Exit(EXIT_AMBIGUOUS if run.result.verdict == "ambiguous" else EXIT_CHECK_FAILED)


def _track(request: RelocalizeRequest, output: Path | None, *, force: bool, as_json: bool) -> None:
    from carto_cli.commands.common import compiling_note
    from carto_cli.commands.relocalize import run_track
    from carto_cli.core.progress import progress

    with progress(f"tracking {request.recording.name}", None, state.quiet) as bar:
        run = run_track(request, output, force=force,
                        on_warning=lambda w: typer.echo(f"carto: warning: {w}", err=True),
                        on_scan=lambda _scan: bar.advance(), on_total=bar.set_total)
    s = run.summary
    if run.auto is not None and not as_json:
        typer.echo(f"auto: {run.auto.describe()}", err=True)
    if as_json:
        typer.echo(json.dumps(run.to_dict(), indent=2))
    else:
        first = ("no fix" if s.first_fix_index is None
                 else f"first fix at scan {s.first_fix_index} after {s.first_fix_s:.2f} s")
        typer.echo(f"{s.scans} scans: " + ", ".join(f"{k} {v}" for k, v in s.verdicts.items())
                   + f"; {first}; {s.relocalizations} searches; {s.scans_per_second:.0f} scans/s"
                   + f"{compiling_note(run.compile_s)} -> {run.outdir}")
    if s.first_fix_index is None:
        raise typer.Exit(EXIT_CHECK_FAILED)


@app.command("render")
@handle_errors
def render_(
    map_file: Path = typer.Argument(..., metavar="MAP",
                                    help="map.carto written by `carto map`, or Cartographer's .pbstream."),
    outdir: Path = typer.Option(..., "--output", "-o", metavar="DIR", help="Output directory."),
    resolution: float | None = typer.Option(None, "--resolution", metavar="M", rich_help_panel=PANEL_IMAGE,
                                            help="Cell size of the exported map (m; default the map's own)."),
    mode: str = typer.Option("trinary", "--mode", metavar="MODE", rich_help_panel=PANEL_IMAGE,
                             help="trinary (map.pgm) or scale (map.scale.png with alpha: the probabilities, unknown "
                                  "transparent)."),
    occupied_thresh: float | None = typer.Option(
        None, "--occupied-thresh", metavar="P", rich_help_panel=PANEL_IMAGE,
        help="Walls from this probability up: trinary cuts map.pgm there (default: more hit than miss evidence); "
             "scale leaves the cut to map_server. map.yaml carries it (default 0.65)."),
    free_thresh: float | None = typer.Option(
        None, "--free-thresh", metavar="P", rich_help_panel=PANEL_IMAGE,
        help="Free up to this probability (between: unknown in trinary, graded in scale); map.yaml carries it "
             "(default 0.196)."),
    png_scale: int | None = typer.Option(None, "--png-scale", metavar="N", rich_help_panel=PANEL_IMAGE,
                                         help="Pixels per cell in map.png (default: about 900 px on the longer side, "
                                              "at most 8)."),
    force: bool = typer.Option(False, "--force", "-f", help="Replace a map already in the output directory."),
    pbstream: bool = typer.Option(False, "--pbstream", help="Also write map.pbstream: the map as Cartographer's "
                                  "state (its tools and --load_state_filename read it)."),
    keep_transient: bool = typer.Option(
        False, "--keep-transient", rich_help_panel=PANEL_IMAGE,
        help="Draw what cleaning removed when the map was made (people, carts, doors that opened)."),
    show_removed: bool = typer.Option(False, "--show-removed", rich_help_panel=PANEL_IMAGE,
                                      help="Mark in map.png what cleaning removed (orange)."),
):
    """Re-export a saved map without its recording: map.pgm + map.yaml (nav2 / map_server) and map.png."""
    from carto_cli.commands.render import run_render

    done = run_render(map_file, outdir, resolution=resolution, mode=mode, occupied_thresh=occupied_thresh,
                      free_thresh=free_thresh, png_scale=png_scale, force=force, pbstream=pbstream,
                      keep_transient=keep_transient, show_removed=show_removed)
    h, w = done.image.shape
    extra = f", {done.pbstream}" if done.pbstream else ""
    typer.echo(f"{w} x {h} cells at {done.image.resolution:g} m -> {done.image_file}, {done.yaml}, {done.png}{extra}")


profiles_app = _Typer(help="Environment profiles: list them, show the effective options.", no_args_is_help=True)
app.add_typer(profiles_app, name="profiles")


@profiles_app.command("list")
@handle_errors
def profiles_list():
    """Profiles shipped with carto (layered over default.yaml by --profile NAME)."""
    from carto_cli.commands.profiles import format_profile_list

    typer.echo(format_profile_list())


@profiles_app.command("show")
@handle_errors
def profiles_show(
    name: str = typer.Argument(..., metavar="NAME", help="Profile name or path."),
    overrides: list[str] | None = SET,
    changed: bool = typer.Option(False, "--changed", help="Only the options that differ from the default."),
):
    """The merged, effective options of a profile (default + profile + --set), as YAML."""
    from carto_cli.commands.profiles import show_profile

    typer.echo(show_profile(name, overrides or [], changed=changed))


@app.command("tune")
@handle_errors
def tune_(
    recordings: list[Path] = typer.Argument(..., metavar="RECORDINGS",
                                            help="One or more recordings; a trial maps them all."),
    space: Path | None = typer.Option(None, "--space", metavar="FILE", rich_help_panel=PANEL_STUDY,
                                      help="Search space YAML (default: the base profile's)."),
    trials: int = typer.Option(20, "--trials", metavar="N", rich_help_panel=PANEL_STUDY,
                               help="Trials to add in this run (a rerun resumes the study)."),
    objective: str = typer.Option(
        "auto", "--objective", metavar="NAME", rich_help_panel=PANEL_OBJECTIVE,
        help="relations, ground-truth, relocalization, map-quality or auto."),
    relations: list[Path] | None = typer.Option(None, "--relations", metavar="FILE", rich_help_panel=PANEL_OBJECTIVE,
                                                help="Relations file per recording."),
    ground_truth: list[Path] | None = typer.Option(None, "--ground-truth", metavar="FILE",
                                                   rich_help_panel=PANEL_OBJECTIVE,
                                                   help="Reference trajectory per recording."),
    profile: str | None = PROFILE,
    overrides: list[str] | None = SET,
    time_weight: float = typer.Option(0.0, "--time-weight", metavar="W", rich_help_panel=PANEL_OBJECTIVE,
                                      help="Add W x (ms per scan) to the objective."),
    storage: str | None = typer.Option(
        None, "--storage", metavar="URL", rich_help_panel=PANEL_STUDY,
        help="Optuna storage URL (default: sqlite next to -o; postgresql://... to share)."),
    study: str | None = typer.Option(None, "--study", metavar="NAME", rich_help_panel=PANEL_STUDY,
                                     help="Study name (default: the output's stem)."),
    n_jobs: int = typer.Option(1, "--n-jobs", metavar="N", rich_help_panel=PANEL_STUDY,
                               help="Trials in parallel, each in its own process."),
    seed: int | None = typer.Option(None, "--seed", metavar="N", rich_help_panel=PANEL_STUDY,
                                    help="Seed of the TPE sampler."),
    max_scans: int | None = typer.Option(None, "--max-scans", metavar="N", rich_help_panel=PANEL_INPUT,
                                         help="Map only the first N scans of each recording."),
    out: Path = typer.Option(..., "--output", "-o", metavar="FILE",
                             help="The tuned profile (YAML over the base profile)."),
    algorithm: str = typer.Option(
        "cartographer", "--algorithm", metavar="NAME",
        help="Mapping system each trial maps with: cartographer (the default), gmapping or scan-to-map; with "
             "those two the default --space is the gmapping.* space (spaces/gmapping.yaml)."),
    force: bool = typer.Option(False, "--force", "-f", help="Replace an -o file that is not this study's output "
                               "(rerunning the same study resumes it and rewrites its own outputs)."),
    sessions: bool = typer.Option(False, "--sessions", rich_help_panel=PANEL_OBJECTIVE,
                                  help="The recordings are sessions of one building: a trial maps them into one "
                                       "map, scored in its one frame."),
    min_z: float | None = MAP_MIN_Z,
    max_z: float | None = MAP_MAX_Z,
):
    """Search options against a measured objective (Optuna TPE) and write the best as a profile."""
    from carto_cli.commands.tune import StudyRequest, run_tune, summary_line
    from carto_cli.core.progress import progress

    with progress("tuning", trials, state.quiet, unit="trials") as bar:
        def on_trial(number, value, best):
            bar.advance()
            if best is not None:
                bar.set_description(f"tuning (best {best:.4g})")

        request = StudyRequest(recordings, out, space=space, trials=trials, objective=objective, relations=relations,
                               ground_truth=ground_truth, profile=profile, overrides=_with_z(overrides, min_z, max_z),
                               time_weight=time_weight, storage=storage, study_name=study, n_jobs=n_jobs, seed=seed,
                               max_scans=max_scans, algorithm=algorithm, sessions=sessions)
        result = run_tune(request, on_trial=on_trial, force=force)
    typer.echo(summary_line(result))
    if result.interrupted:
        typer.echo("carto: tune: interrupted; the profile holds the best trial so far", err=True)
        raise typer.Exit(EXIT_INTERRUPTED)


@app.command("options")
@handle_errors
def options_(
    filter_: str | None = typer.Argument(None, metavar="FILTER|import",
                                         help="Only options whose name contains this; or 'import' and a file."),
    lua: Path | None = typer.Argument(None, metavar="ROBOT.lua",
                                      help="With 'import': a Cartographer Lua configuration, printed as a carto "
                                      "profile (YAML) on stdout."),
    as_json: bool = typer.Option(False, "--json", help="Machine-readable output."),
):
    """Every option: its name, type, default, unit, bounds and what it does. `carto options import robot.lua >
    robot.yaml` turns a Cartographer configuration into a carto profile (`--profile robot.lua` reads it as it is)."""
    from carto_cli.commands.options import format_option, import_configuration, list_options

    if filter_ == "import" or lua is not None:
        if filter_ != "import" or lua is None:
            raise CartoError("usage: carto options import ROBOT.lua (a Cartographer configuration)")
        imported = import_configuration(lua)
        if as_json:
            typer.echo(json.dumps({"overrides": imported.overrides, "unused": imported.unused}, indent=2))
        else:
            typer.echo(imported.to_yaml(), nl=False)
        note = imported.note()
        if note:
            typer.echo(f"carto: note: {note}", err=True)
        return

    infos = list_options(filter_)
    if as_json:
        typer.echo(json.dumps([i.__dict__ for i in infos], indent=2, default=str))
        return
    for i in infos:
        typer.echo(format_option(i))


def stop_on_signals() -> None:
    """Ctrl-C and SIGTERM (a CI job cancelled, `timeout`, `docker stop`) stop a command alike: exit 130, the
    output set left as it was, whatever error the interrupt turns into where it lands (core.interrupts)."""
    from carto_cli.core import interrupts

    interrupts.install()


GLOBAL_FLAGS = ("--debug", "--quiet", "-q")


def hoist_global_flags(argv: list[str]) -> list[str]:
    """``carto map rec.bag --debug`` as ``carto --debug map rec.bag``: the global flags are accepted after the
    subcommand too (the error hint says "rerun with --debug", and users add it at the end). Nothing after a
    ``--`` moves."""
    if "--" in argv:
        head, tail = argv[:argv.index("--")], argv[argv.index("--"):]
    else:
        head, tail = argv, []
    flags = [a for a in head if a in GLOBAL_FLAGS]
    return flags + [a for a in head if a not in GLOBAL_FLAGS] + tail


def main() -> None:
    import sys

    stop_on_signals()
    try:
        app(prog_name="carto", args=hoist_global_flags(sys.argv[1:]))
    except SystemExit as stop:
        leave(stop.code)
    leave(0)


def leave(code) -> None:
    """End the process with ``code`` (as ``sys.exit`` takes it) once the command is done, without tearing the
    interpreter down: freeing numba's compiled kernels and every module took 0.5-0.9 s after a map was written
    (orebro, edmonton), a second or two of each short command. The exit handlers still run and the streams are
    flushed; only if a thread of ours is still working does the interpreter get to wait for it as usual."""
    import atexit
    import os
    import sys
    import threading

    from carto_cli.core import interrupts

    interrupts.hold()  # what is left is reporting and leaving: a signal now must not end in a traceback
    main_thread = threading.main_thread()
    if any(t is not main_thread and t.is_alive() and not t.daemon for t in threading.enumerate()):
        sys.exit(code)
    if code is None:
        status = 0
    elif isinstance(code, int):
        status = code
    else:
        typer.echo(str(code), err=True)
        status = 1
    atexit._run_exitfuncs()  # what the interpreter's own exit would run first: logging, coverage, finalizers
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass  # a closed pipe (`carto ... | head`): nothing left to say to it
    os._exit(status)
