"""The `carto` command line: parses arguments and calls the library; nothing more."""
from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Optional

import typer

from carto_cli import __version__
from carto_cli.core.errors import CartoError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="2D LiDAR SLAM from recorded data: maps, relocalization, tuning and profiling.",
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


def handle_errors(fn):
    """User errors: one line, exit 2. Internal errors: one line, exit 1. Tracebacks only with --debug."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except typer.Exit:
            raise
        except CartoError as e:
            if state.debug:
                raise
            _fail(f"error: {e}", 2)
        except KeyboardInterrupt:
            _fail("interrupted", 130)
        except Exception as e:  # noqa: BLE001 - the last line of defence before a traceback
            if state.debug:
                raise
            _fail(f"internal error: {type(e).__name__}: {e} (rerun with --debug for a traceback)", 1)

    return wrapper


def _version(value: bool):
    if value:
        typer.echo(f"carto {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks for errors."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars."),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
):
    state.debug = debug
    state.quiet = quiet


def _read_options(min_z: float, max_z: float):
    from carto_cli.io.recording import ReadOptions

    if min_z > max_z:
        raise CartoError(f"--min-z ({min_z}) is above --max-z ({max_z})")
    return ReadOptions(min_z=min_z, max_z=max_z)


MIN_Z = typer.Option(-0.1, "--min-z", help="PointCloud2: lowest z kept when slicing to 2D (m).")
MAX_Z = typer.Option(0.1, "--max-z", help="PointCloud2: highest z kept when slicing to 2D (m).")


@app.command()
@handle_errors
def info(
    recording: Path = typer.Argument(..., help="ROS1 .bag, ROS2 bag directory, .mcap or CARMEN .clf/.log[.gz]."),
    as_json: bool = typer.Option(False, "--json", help="Machine-readable output."),
    min_z: float = MIN_Z,
    max_z: float = MAX_Z,
):
    """Describe a recording: topics, rates, scan geometry, static TF, warnings."""
    from carto_cli.commands.info import format_info, inspect_recording
    from carto_cli.io.sources.open import open_recording
    from carto_cli.core.progress import progress

    with open_recording(recording, _read_options(min_z, max_z)) as rec:
        total = sum(t.count for t in rec.topics() if t.kind in ("scan", "odometry", "imu"))
        with progress(f"reading {recording.name}", total, state.quiet) as bar:
            result = inspect_recording(rec, on_record=bar.advance)
    if as_json:
        typer.echo(json.dumps(result.to_dict(), indent=2, allow_nan=False, default=_json_default))
    else:
        typer.echo(format_info(result))


def _json_default(value):
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


@app.command()
@handle_errors
def convert(
    source: Path = typer.Argument(..., help="Any recording carto reads."),
    out: Path = typer.Argument(..., help="Output: .bag (ROS1), .mcap (standalone MCAP) or a directory (ROS2 bag)."),
    fmt: Optional[str] = typer.Option(
        None, "--format", help="ros1, ros2-sqlite3, ros2-mcap or mcap (default: from OUT's suffix)."
    ),
    scan_topic: Optional[str] = typer.Option(None, "--scan-topic", help="Only this scan topic."),
    odom_topic: Optional[str] = typer.Option(None, "--odom-topic", help="Only this odometry topic."),
    imu_topic: Optional[str] = typer.Option(None, "--imu-topic", help="Only this IMU topic."),
    force: bool = typer.Option(False, "--force", "-f", help="Replace OUT if it exists."),
    min_z: float = MIN_Z,
    max_z: float = MAX_Z,
):
    """Convert between ROS1 bags, ROS2 bags (sqlite3 / mcap storage) and MCAP; scans, odometry, IMU and static TF."""
    from carto_cli.io.sources.open import open_recording
    from carto_cli.io.recording_writers import format_for_output, write_recording
    from carto_cli.core.progress import progress

    out_format = format_for_output(out, fmt)
    with open_recording(source, _read_options(min_z, max_z)) as rec:
        topics = rec.topics()
        chosen = []
        for kind, wanted in (("scan", scan_topic), ("odometry", odom_topic), ("imu", imu_topic)):
            if wanted is not None:
                from carto_cli.io.topics import choose_topic

                chosen.append(choose_topic(rec, topics, kind, wanted, True))
            elif not any(w is not None for w in (scan_topic, odom_topic, imu_topic)):
                chosen.extend(t.name for t in topics if t.kind == kind)
        types = {t.name: t.msgtype for t in topics}
        total = sum(t.count for t in topics if t.name in chosen)
        with progress(f"converting {source.name}", total, state.quiet) as bar:
            n = write_recording(
                rec.records(chosen), out, out_format,
                static_transforms=rec.static_transforms(), topics={t: types[t] for t in chosen},
                on_record=bar.advance, overwrite=force,
            )
    if not state.quiet:
        typer.echo(f"wrote {n} messages to {out} ({out_format})", err=True)


PROFILE = typer.Option(None, "--profile", "-p", help="Profile name (profiles/NAME.yaml) or path, layered over the default.")
SET = typer.Option(None, "--set", "-s", help="Override an option: dotted.key=value (repeatable; angles in radians, or '20deg').")


def _options(profile: Optional[str], overrides: Optional[list[str]]):
    from carto_cli.options import load_options

    return load_options(profile, overrides or [])


@app.command("map")
@handle_errors
def map_(
    recording: Path = typer.Argument(..., help="ROS1 .bag, ROS2 bag directory, .mcap or CARMEN .clf/.log[.gz]."),
    outdir: Optional[Path] = typer.Option(None, "--output", "-o", help="Output directory (default: RECORDING_map)."),
    profile: Optional[str] = PROFILE,
    overrides: Optional[list[str]] = SET,
    scan_topic: Optional[str] = typer.Option(None, "--scan-topic"),
    odom_topic: Optional[str] = typer.Option(None, "--odom-topic"),
    imu_topic: Optional[str] = typer.Option(None, "--imu-topic"),
    no_odometry: bool = typer.Option(False, "--no-odometry", help="Ignore odometry even when the recording has it."),
    laser_pose: Optional[str] = typer.Option(
        None, "--laser-pose", help="x,y,yaw of the laser on the robot (m, m, rad; 'deg' suffix for degrees). Default: static TF, else identity."
    ),
    timings: bool = typer.Option(False, "--timings", help="Print the per-stage timing tree."),
    no_loop_closure: bool = typer.Option(
        False, "--no-loop-closure", help="Local SLAM only: no loop closure, no optimization (for tuning local SLAM)."
    ),
    no_state: bool = typer.Option(False, "--no-state", help="Do not write map.carto (the file relocalize loads)."),
    load_state: Optional[Path] = typer.Option(
        None, "--load-state", help="Continue mapping into this map.carto: the recording becomes a new trajectory."
    ),
):
    """Build a map: map.pgm + map.yaml (map_server), map.png, trajectory.tum."""
    from carto_cli.io.tf_tree import parse_pose
    from carto_cli.commands.map import run_map, summary_line
    from carto_cli.core.progress import progress
    from carto_cli.core.timing import StageTimer, report_tree_text

    options = _options(profile, overrides)
    mount = parse_pose(laser_pose, "--laser-pose") if laser_pose else None
    if outdir is None:
        outdir = recording.parent / f"{recording.name.split('.')[0]}_map"
    timer = StageTimer()
    with progress(f"mapping {recording.name}", None, state.quiet) as bar:
        result, outputs = run_map(
            recording, outdir, options, scan_topic=scan_topic, odom_topic=odom_topic, imu_topic=imu_topic,
            laser_pose=mount, use_odometry=not no_odometry, timer=timer, on_scan=bar.advance,
            on_total=lambda n: bar.set_total(n), loop_closure=not no_loop_closure, state=not no_state,
            load_state=load_state,
        )
    timer.stop()
    if timings:
        typer.echo(report_tree_text(timer))
    warm_up = timer.snapshot().find("jit warm-up")
    note = ""
    if warm_up is not None and warm_up.total_ns > 1e9:
        note = f" (incl. {warm_up.total_ns / 1e9:.0f} s compiling kernels: later runs load them from the cache)"
    typer.echo(f"{summary_line(result)}{note} -> {outputs.yaml.parent}")


def _finish_gates(gates, junit: Optional[Path], suite: str, label: str) -> None:
    """JUnit output if asked, one stderr line per failed gate, exit 1 if any failed."""
    from carto_cli.evaluation.gates import write_junit

    if junit is not None:
        write_junit(junit, suite, gates)
    failed = [g for g in gates if not g.passed]
    for g in failed:
        typer.echo(f"carto: {label}: {g.message}", err=True)
    if failed:
        raise typer.Exit(1)


@app.command("eval")
@handle_errors
def eval_(
    trajectory: Path = typer.Argument(..., help="Trajectory to score: TUM (t x y z qx qy qz qw) or 't x y theta'."),
    relations: Optional[Path] = typer.Option(None, "--relations", help="Relations file: t1 t2 dx dy dz droll dpitch dyaw."),
    ground_truth: Optional[Path] = typer.Option(None, "--ground-truth", help="Reference trajectory (TUM or 't x y theta')."),
    rpe_delta: float = typer.Option(1.0, "--rpe-delta", help="RPE step in seconds (with --ground-truth)."),
    as_json: bool = typer.Option(False, "--json", help="Machine-readable output."),
    max_trans_error: Optional[float] = typer.Option(
        None, "--max-trans-error", help="Gate: exit 1 if the mean relation error (else ATE RMSE) exceeds M metres."),
    max_rot_error: Optional[float] = typer.Option(
        None, "--max-rot-error", help="Gate: exit 1 if the mean rotational error exceeds DEG degrees."),
    junit: Optional[Path] = typer.Option(None, "--junit", help="Write the gates' outcome as JUnit XML."),
):
    """Score a trajectory: relation error (Kuemmerle et al.) and/or ATE + RPE against a ground truth."""
    from carto_cli.evaluation.metrics import evaluate, format_table, to_json
    from carto_cli.evaluation.gates import accuracy_gates

    if relations is None and ground_truth is None:
        raise CartoError("give --relations FILE and/or --ground-truth FILE")
    result = evaluate(trajectory, relations=relations, groundtruth=ground_truth,
                      rpe_delta=rpe_delta if ground_truth is not None else None)
    data = to_json(result)
    if as_json:
        typer.echo(json.dumps(data, indent=2))
    else:
        typer.echo(format_table(result))
    if max_trans_error is None and max_rot_error is None:
        return
    _finish_gates(accuracy_gates(data, max_trans_error, max_rot_error), junit, "carto.eval", "gate failed")


@app.command("profile")
@handle_errors
def profile_(
    recording: Path = typer.Argument(..., help="Recording to run the whole pipeline on."),
    profile: Optional[str] = PROFILE,
    overrides: Optional[list[str]] = SET,
    scan_topic: Optional[str] = typer.Option(None, "--scan-topic"),
    odom_topic: Optional[str] = typer.Option(None, "--odom-topic"),
    as_json: bool = typer.Option(False, "--json", help="Print the report as JSON (schema carto.profile v1)."),
    output: Optional[Path] = typer.Option(None, "--output", help="Also write the JSON report to this file."),
    baseline: Optional[Path] = typer.Option(None, "--baseline", help="A previous --output to compare against."),
    max_regression: float = typer.Option(0.20, "--max-regression", help="Allowed slow-down per stage (0.20 = 20%)."),
    calibrate: bool = typer.Option(False, "--calibrate", help="Time a reference kernel first and compare normalized times."),
    junit: Optional[Path] = typer.Option(None, "--junit", help="Write the gates' outcome as JUnit XML."),
    max_scans: Optional[int] = typer.Option(None, "--max-scans", help="Profile only the first N scans."),
    relocalize_map: Optional[Path] = typer.Option(
        None, "--relocalize", help="Also profile relocalizing every 10th scan of RECORDING in this map.carto."),
):
    """Per-stage timing tree of the whole pipeline (ms/scan, share, p50/p95/p99), with CI regression gates."""
    from carto_cli.evaluation.gates import compare_profiles
    from carto_cli.io.atomic import write_text_atomic
    from carto_cli.io.sources.open import open_recording
    from carto_cli.io.recording import ReadOptions
    from carto_cli.io.topics import select_topics
    from carto_cli.pipeline import build
    from carto_cli.evaluation.profiling import build_report, calibrate as run_calibration, format_report
    from carto_cli.core.progress import progress
    from carto_cli.core.timing import StageTimer

    options = _options(profile, overrides)
    base = None
    if baseline is not None:
        try:
            base = json.loads(baseline.read_text())
        except (OSError, ValueError) as e:
            raise CartoError(f"cannot read baseline: {e}", baseline) from None
    calibration = run_calibration() if calibrate else None
    tb = options.trajectory_builder_2d
    timer = StageTimer()
    with open_recording(recording, ReadOptions(min_z=tb.min_z, max_z=tb.max_z)) as rec:
        selection = select_topics(rec, scan_topic, odom_topic)
        total = next(t.count for t in rec.topics() if t.name == selection.scan)
        with progress(f"profiling {recording.name}", min(total, max_scans or total), state.quiet) as bar:
            result = build(rec, options, selection=selection, timer=timer, on_scan=bar.advance, max_scans=max_scans)
    timer.stop()
    report = build_report(result, timer, options, recording, calibration)
    if relocalize_map is not None:
        from carto_cli.io.map_file import load_map
        from carto_cli.evaluation.profiling import profile_relocalization

        with open_recording(recording, ReadOptions(min_z=tb.min_z, max_z=tb.max_z)) as rec:
            report["relocalization"] = profile_relocalization(load_map(relocalize_map), rec, scan_topic=scan_topic)
    if output is not None:
        write_text_atomic(output, json.dumps(report, indent=2) + "\n")
    typer.echo(json.dumps(report, indent=2) if as_json else format_report(report))
    if not as_json and "relocalization" in report:
        from carto_cli.evaluation.profiling import format_relocalization

        typer.echo("\n" + format_relocalization(report["relocalization"]))
    if base is None:
        return
    _finish_gates(compare_profiles(report, base, max_regression), junit, "carto.profile", "slower than baseline")


@app.command("relocalize")
@handle_errors
def relocalize_(
    map_file: Path = typer.Argument(..., help="map.carto written by `carto map`."),
    recording: Path = typer.Argument(..., help="Recording holding the scan(s) to relocalize."),
    initial_pose: Optional[str] = typer.Option(
        None, "--initial-pose", help="Prior x,y,yaw in the map frame (m, m, rad; 'deg' suffix for degrees)."),
    at: Optional[float] = typer.Option(None, "--at", help="Relocalize the scan nearest this time (s)."),
    scan_index: Optional[int] = typer.Option(None, "--scan-index", help="Relocalize the N-th scan (from 0)."),
    sigma_xy: Optional[float] = typer.Option(None, "--sigma-xy", help="Prior position uncertainty (m)."),
    sigma_yaw: Optional[float] = typer.Option(None, "--sigma-yaw", help="Prior heading uncertainty (degrees)."),
    corridor: bool = typer.Option(False, "--corridor", help="Keep submaps in a sector along the prior's heading."),
    global_: bool = typer.Option(False, "--global", help="No prior: search every submap."),
    queries: Optional[Path] = typer.Option(
        None, "--queries", help="Batch: lines 't|index x y yaw [sigma_xy sigma_yaw]'; writes a CSV."),
    csv_out: Optional[Path] = typer.Option(None, "--csv", help="Batch results CSV (default: QUERIES.results.csv)."),
    scan_topic: Optional[str] = typer.Option(None, "--scan-topic"),
    overrides: Optional[list[str]] = typer.Option(
        None, "--set", "-s", help="Override one of the map's options, e.g. relocalization.min_score=0.65 "
        "(repeatable; angles in radians, or '20deg')."),
    as_json: bool = typer.Option(False, "--json", help="Machine-readable output."),
):
    """Find scans in a saved map: windowed search from a prior, fallbacks, or a global search."""
    import math

    from carto_cli.io.map_file import load_map
    from carto_cli.io.sources.open import open_recording
    from carto_cli.core.progress import progress
    from carto_cli.relocalization.relocalizer import Relocalizer, parse_pose, read_queries, relocalize_many, scan_at, write_results_csv

    if queries is None and not global_ and initial_pose is None:
        raise CartoError("give --initial-pose x,y,yaw, or --global, or --queries FILE")
    if global_ and initial_pose is not None:
        raise CartoError("--global and --initial-pose exclude each other")
    if at is not None and scan_index is not None:
        raise CartoError("--at and --scan-index exclude each other")
    from carto_cli.options import apply_overrides

    loaded = load_map(map_file)
    relocalizer = Relocalizer(loaded, apply_overrides(loaded.options, overrides) if overrides else None)
    for w in relocalizer.warnings:
        typer.echo(f"carto: warning: {w}", err=True)
    with open_recording(recording) as rec:
        if queries is not None:
            qs = read_queries(queries)
            with progress("relocalizing", len(qs), state.quiet) as bar:
                results, summary = relocalize_many(relocalizer, rec, qs, scan_topic=scan_topic, corridor=corridor,
                                                   on_query=bar.advance)
            out = csv_out or queries.with_suffix(".results.csv")
            write_results_csv(out, results)
            if as_json:
                typer.echo(json.dumps(summary.to_dict(), indent=2))
            else:
                s = summary
                typer.echo(f"{s.successes}/{s.queries} relocalized ({100 * s.success_rate:.1f}%), "
                           f"p50 {s.p50_ms:.1f} ms, p95 {s.p95_ms:.1f} ms, p99 {s.p99_ms:.1f} ms -> {out}")
            return
        index, scan = scan_at(rec, time=at, index=scan_index, scan_topic=scan_topic)
    prior = None if global_ else parse_pose(initial_pose)
    result = relocalizer.relocalize(scan, prior, sigma_xy=sigma_xy,
                                    sigma_yaw=None if sigma_yaw is None else math.radians(sigma_yaw),
                                    corridor=corridor)
    data = result.to_dict()
    data["scan_index"] = index
    data["scan_time"] = scan.time
    if as_json:
        typer.echo(json.dumps(data, indent=2))
        return
    x, y, yaw = result.pose
    t = result.timings
    typer.echo(f"scan {index} at {scan.time:.3f}: pose {x:.3f} {y:.3f} {math.degrees(yaw):.2f}° "
               f"score {result.score:.3f} ({'ok' if result.success else 'UNRELIABLE'}) via {result.path}, "
               f"{len(result.submaps_considered)} submaps")
    typer.echo("timing " + ", ".join(f"{k} {v:.1f} ms" for k, v in t.items()) + f", total {result.total_ms:.1f} ms")
    if result.reason:
        typer.echo(f"{'why' if not result.success else 'notes'}: {result.reason}")
    if not result.success:
        raise typer.Exit(1)


profiles_app = typer.Typer(help="Environment profiles: list them, show the effective options.", no_args_is_help=True)
app.add_typer(profiles_app, name="profiles")


@profiles_app.command("list")
@handle_errors
def profiles_list():
    """Profiles shipped with carto (layered over default.yaml by --profile NAME)."""
    from carto_cli.options import list_profiles, profiles_dir

    for name in list_profiles():
        first = ""
        text = (profiles_dir() / f"{name}.yaml").read_text().splitlines()
        for line in text:
            if line.startswith("#"):
                first = line.lstrip("# ").strip()
                break
        typer.echo(f"{name:<12} {first}")


@profiles_app.command("show")
@handle_errors
def profiles_show(
    name: str = typer.Argument(..., help="Profile name or path."),
    overrides: Optional[list[str]] = SET,
    changed: bool = typer.Option(False, "--changed", help="Only the options that differ from the default."),
):
    """The merged, effective options of a profile (default + profile + --set), as YAML."""
    import yaml as _yaml

    from carto_cli.options import changed_options, dump_options_yaml

    options = _options(name, overrides)
    if changed:
        typer.echo(_yaml.safe_dump(changed_options(options), sort_keys=False).rstrip())
    else:
        typer.echo(dump_options_yaml(options).rstrip())


@app.command("tune")
@handle_errors
def tune_(
    recordings: list[Path] = typer.Argument(..., help="One or more recordings; a trial maps them all."),
    space: Optional[Path] = typer.Option(None, "--space", help="Search space YAML (default: the base profile's)."),
    trials: int = typer.Option(20, "--trials", help="Trials to add in this run (a rerun resumes the study)."),
    objective: str = typer.Option(
        "auto", "--objective", help="relations, ground-truth, relocalization, map-quality or auto."),
    relations: Optional[list[Path]] = typer.Option(None, "--relations", help="Relations file per recording."),
    ground_truth: Optional[list[Path]] = typer.Option(None, "--ground-truth", help="Reference trajectory per recording."),
    profile: Optional[str] = PROFILE,
    overrides: Optional[list[str]] = SET,
    time_weight: float = typer.Option(0.0, "--time-weight", help="Add W x (ms per scan) to the objective."),
    storage: Optional[str] = typer.Option(
        None, "--storage", help="Optuna storage URL (default: sqlite next to -o; postgresql://... to share)."),
    study: Optional[str] = typer.Option(None, "--study", help="Study name (default: the output's stem)."),
    n_jobs: int = typer.Option(1, "--n-jobs", help="Trials in parallel, each in its own process."),
    seed: Optional[int] = typer.Option(None, "--seed", help="Seed of the TPE sampler."),
    max_scans: Optional[int] = typer.Option(None, "--max-scans", help="Map only the first N scans of each recording."),
    out: Path = typer.Option(..., "--output", "-o", help="The tuned profile (YAML over the base profile)."),
):
    """Search options against a measured objective (Optuna TPE) and write the best as a profile."""
    from carto_cli.core.progress import progress
    from carto_cli.tuning.study import tune
    from carto_cli.tuning.space import default_space_path

    space_path = space if space is not None else default_space_path(profile)
    with progress("tuning", trials, state.quiet) as bar:
        def on_trial(number, value, best):
            bar.advance()
            if best is not None:
                bar.set_description(f"tuning (best {best:.4g})")

        result = tune(recordings, space_path, trials=trials, out=out, objective=objective, relations=relations,
                      ground_truth=ground_truth, base_profile=profile, overrides=overrides or [],
                      time_weight=time_weight, storage=storage, study_name=study, n_jobs=n_jobs, seed=seed,
                      max_scans=max_scans, on_trial=on_trial)
    base = "" if result.baseline_value is None else f" (base profile {result.baseline_value:.4g})"
    typer.echo(f"{result.n_trials} trials ({result.n_complete} complete, {result.n_pruned} pruned, "
               f"{result.n_failed} failed); best {result.objective} {result.best_value:.4g}{base} -> "
               f"{result.profile_path}, {result.csv_path.name}, {result.png_path.name}")


@app.command("options")
@handle_errors
def options_(
    filter_: Optional[str] = typer.Argument(None, metavar="[FILTER]", help="Only options whose name contains this."),
    as_json: bool = typer.Option(False, "--json", help="Machine-readable output."),
):
    """Every option: its name, type, default, unit, bounds and what it does."""
    from carto_cli.options import option_info

    infos = [i for i in option_info() if filter_ is None or filter_ in i.name]
    if as_json:
        typer.echo(json.dumps([i.__dict__ for i in infos], indent=2, default=str))
        return
    for i in infos:
        unit = f" {i.unit}" if i.unit else ""
        bounds = f"  [{i.bounds}]" if i.bounds else ""
        typer.echo(f"{i.name} = {i.default!r}{unit} ({i.type}){bounds}\n    {i.doc}")


def main() -> None:
    app(prog_name="carto")
