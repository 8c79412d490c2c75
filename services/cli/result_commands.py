"""``etar-bench`` report, info, diff, recover, figures, export and compare: reading a run's
folder and its recordings once the command line is parsed (``services.cli.bench``)."""

from __future__ import annotations

import json
from pathlib import Path

from services.cli.output import say
from services.runtime.visual_topics import check_visual_rate

# each seed is a whole EM fit per transition model: more than this is a mistyped number
MAX_COMPARE_SEEDS = 1000


def cmd_report(args) -> int:
    from services.results.folder import RunFolderError, read_report

    path = Path(args.run_dir)
    for name in ("report.txt", "report.json"):
        if not (path / name).exists():
            say(f"etar-bench report: {path / name} not found (is {path} a run directory?)")
            return 2
    try:
        report = read_report(path)
    except RunFolderError as exc:
        say(f"etar-bench report: {exc}")
        return 2
    if args.json:
        print(json.dumps(report, indent=1, allow_nan=False))
    else:
        print((path / "report.txt").read_text(), end="")
    if report.get("error"):
        say(f"etar-bench report: the run failed: {report['error']}")
        return 1
    return 0


def cmd_info(args) -> int:
    """What a recording or a run holds, as ``mcap info`` / ``ros2 bag info`` would say it;
    exit code 1 when a recording is incomplete or missing (described all the same)."""
    from services.results.folder import kept_recordings
    from services.results.info import describe, info_text

    try:
        described = describe(args.path)
    except ValueError as exc:  # InfoError, RecordingError: one line naming the file
        say(f"etar-bench info: error: {exc}")
        return 2
    print(json.dumps(described, indent=1, allow_nan=False) if args.json else info_text(described), flush=True)
    if described.get("kind") == "run":
        incomplete = described["totals"]["incomplete"] if kept_recordings(described["path"]) else 0
    else:
        incomplete = int(not described["complete"])
    if incomplete:
        say(f"etar-bench info: {args.path}: {incomplete} recording(s) incomplete or missing (INCOMPLETE above)")
        return 1
    return 0


def cmd_diff(args) -> int:
    """Like diff: 0 when the two runs recorded the same content and results, 1 when not,
    2 on trouble."""
    from services.results.diff import diff_runs

    try:
        result = diff_runs(args.run_a, args.run_b)
    except ValueError as exc:  # DiffError, RecordingError
        say(f"etar-bench diff: error: {exc}")
        return 2
    print(json.dumps(result.to_dict(), indent=1, allow_nan=False) if args.json else result.text(), flush=True)
    return 0 if result.same else 1


def cmd_recover(args) -> int:
    from services.recordings.format import RecordingError
    from services.recordings.recovery import NothingToRecover, recover

    if args.out is not None and len(args.files) > 1:
        say("etar-bench recover: --out names one output file: give one FILE with it")
        return 2
    missing = [f for f in args.files if not Path(f).is_file()]
    if missing:
        what = ("a folder, not a recording" if Path(missing[0]).is_dir() else
                "not a regular file" if Path(missing[0]).exists() else "no such file")
        say(f"etar-bench recover: error: {missing[0]}: {what}")
        return 2
    if args.out is not None:  # refused before anything is read or written
        out = Path(args.out)
        problem = ("a folder; --out names the output file" if out.is_dir() else
                   f"its folder {out.parent} does not exist" if not out.parent.is_dir() else
                   "exists (pass --force to replace it)" if out.exists() and not args.force else None)
        if problem:
            say(f"etar-bench recover: error: --out {args.out}: {problem}")
            return 2
    failed = 0
    for f in args.files:
        try:
            result = recover(f, args.out, overwrite=args.force)
        except NothingToRecover as exc:  # a finished file among those given: said, and no failure
            print(exc, flush=True)
            continue
        except RecordingError as exc:
            say(f"etar-bench recover: error: {exc}")
            failed += 1
            continue
        except OSError as exc:  # the output's folder not writable, a full disk
            say(f"etar-bench recover: error: {f}: could not write {exc.filename or args.out}: {exc.strerror}")
            failed += 1
            continue
        print(result.describe(), flush=True)
    return 1 if failed else 0


def cmd_figures(args) -> int:
    from services.results.figures import FiguresError, read_run_report
    from services.results.html import write_figures_and_page

    run_dir = Path(args.run_dir)
    try:
        read_run_report(run_dir)  # a run's folder, with a report to draw from
    except FiguresError as exc:
        say(f"etar-bench figures: error: {exc}")
        return 2
    print(write_figures_and_page(run_dir, progress=say), flush=True)
    problems = [run_dir / name for name in ("figures.error", "report.html.error") if (run_dir / name).is_file()]
    for path in problems:
        say(f"etar-bench figures: {path}: {path.read_text().strip()}")
    return 1 if problems else 0


def cmd_export(args) -> int:
    from services.foxglove.export import export_foxglove
    from services.recordings.format import RecordingError
    from services.cli.run_commands import ros2_rates
    from services.ros2.bag import export_rosbag2
    from etar.parsing import empty_path

    if not (args.foxglove or args.rosbag2):
        say("etar-bench export: error: say what to export: --foxglove (visual topics added to the recordings) "
            "and/or --rosbag2 (ROS 2 bags beside them)")
        return 2
    if args.out is not None and not args.rosbag2:
        say("etar-bench export: error: --out is where --rosbag2 writes its bags; --foxglove adds to the recordings")
        return 2
    try:
        check_visual_rate(args.visual_rate_hz, "--visual-rate-hz")
        rates = ros2_rates(args)
    except ValueError as exc:
        say(f"etar-bench export: error: {exc}")
        return 2
    if not (Path(args.run_dir) / "recordings").is_dir():
        say(f"etar-bench export: error: {args.run_dir}: no recordings/ folder: not a run's folder")
        return 2
    if args.out is not None:  # the bags' folder made before any bag is: refused in one line here
        try:
            empty_path("--out", args.out, "the folder for the bags")
            Path(args.out).mkdir(parents=True, exist_ok=True)
        except ValueError as exc:
            say(f"etar-bench export: error: {exc}")
            return 2
        except OSError as exc:
            say(f"etar-bench export: error: --out {args.out!r}: cannot make that folder ({exc.strerror or exc}); "
                "--out names the folder for the bags")
            return 2
    try:
        if args.foxglove:
            results = export_foxglove(args.run_dir, args.visual_rate_hz, progress=print)
            added = sum(1 for r in results if r.added)
            say(f"etar-bench export: visual topics added to {added} of {len(results)} recording(s)")
        if args.rosbag2:
            bags = export_rosbag2(args.run_dir, args.out, rates, progress=print)
            made = [b for b in bags if b.bag is not None]
            where = made[0].bag.parent if made else args.out
            say(f"etar-bench export: {len(made)} ROS 2 bag(s) of {len(bags)} recording(s) in {where}")
            if len(made) < len(bags):
                return 1
    except (RecordingError, OSError) as exc:
        say(f"etar-bench export: error: {exc}")
        return 1
    return 0


def cmd_compare(args) -> int:
    from etar.demonstrations import DemonstrationError
    from etar.task import TaskError
    from services.recordings.format import RecordingError
    from services.results.compare import compare_run
    from services.results.figures import FiguresError

    if not 1 <= args.seeds <= MAX_COMPARE_SEEDS:
        say(f"etar-bench compare: error: --seeds must be 1..{MAX_COMPARE_SEEDS}, got {args.seeds}")
        return 2
    try:
        pair = tuple(int(x) for x in args.pair.split(","))
        if len(pair) != 2:
            raise ValueError
    except ValueError:
        say(f"etar-bench compare: error: --pair expects two demonstration numbers I,J (e.g. 0,1), got {args.pair!r}")
        return 2
    try:
        compare_run(args.run_dir, seeds=tuple(range(args.seeds)), progress=say, pair=pair)
    except (FiguresError, RecordingError, TaskError, DemonstrationError) as exc:
        # a damaged recording or model of the run: its own error names the file
        say(f"etar-bench compare: error: {exc}")
        return 2
    print((Path(args.run_dir) / "comparison.txt").read_text(), end="", flush=True)
    return 0

