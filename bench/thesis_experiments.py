"""The thesis' experiments over seeds, and their table: run them with any checkout's
``etar-bench``, then lay one or two result folders side by side.

    python bench/thesis_experiments.py run --out runs/thesis            # seeds 0-4, every experiment
    python bench/thesis_experiments.py run --out runs/old --etar-bench ../old/.venv/bin/etar-bench
    python bench/thesis_experiments.py table runs/old runs/thesis      # before | after, markdown

``run`` drives the CLI only (``etar-bench sweep`` per experiment, ``etar-bench compare``
on the valley's runs for Table C1, ``etar-bench run --clock realtime`` for the realtime
valley), so it measures any version of the testbench that has those commands; each
experiment lands in its own folder under ``--out`` and one already there is kept (a run
cut short goes on where it stopped).  ``table`` reads the sweeps' reports.

Experiments (thesis section 6; docs/results.md):
  valley      scenarios/valley.yaml, seeds 0-4 and 11 (whose model read the groove as the plate)
  table_c1    etar-bench compare on the valley's runs (Table C1, seeds 0-4)
  two_sides   scenarios/valley_two_sides.yaml with 3 and with 4 phases, per side
  star_etar   scenarios/star_vs_etar.yaml over the sensor's noise 1, 64, 256 x the Mini45's
  coupler     scenarios/hose_coupler.yaml
  realtime    the valley on the realtime clock over Zenoh, one seed (alone on the machine)
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
EXPERIMENTS = ("valley", "table_c1", "two_sides", "star_etar", "coupler", "realtime")
VALLEY_EXTRA_SEED = 11


def _seeds(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        try:
            out += list(range(int(lo), int(hi) + 1)) if hi else [int(lo)]
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected seeds such as 0-4 or 0,2,11, got {text!r}") from None
    if not out:
        raise argparse.ArgumentTypeError("no seeds")
    return out


def _call(cmd: list[str], log: Path, cwd: Path) -> None:
    print("$", " ".join(cmd), flush=True)
    t0 = time.monotonic()
    with open(log, "a") as fh:
        fh.write("$ " + " ".join(cmd) + "\n")
        fh.flush()
        rc = subprocess.call(cmd, stdout=fh, stderr=subprocess.STDOUT, cwd=cwd)
    print(f"  exit {rc} after {time.monotonic() - t0:.0f} s (log {log})", flush=True)
    if rc:
        raise SystemExit(f"thesis_experiments: {cmd[1]} failed (exit {rc}); see {log}")


def _sweep(args, scenario: str, out: Path, params: list[str], record: str, log: Path) -> None:
    if (out / "table.json").exists():
        print(f"{out}: done before, kept", flush=True)
        return
    cmd = [args.etar_bench, "sweep", scenario, "--out", str(out), "--replace", "--record", record, "--workers",
           str(args.workers)]
    for p in params:
        cmd += ["--param", p]
    _call(cmd, log, args.checkout)


def run(args) -> None:
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    log = out / "commands.log"
    seeds = ",".join(map(str, args.seeds))
    which = args.only or list(EXPERIMENTS)
    if "valley" in which or "table_c1" in which:
        valley_seeds = seeds + ("" if VALLEY_EXTRA_SEED in args.seeds else f",{VALLEY_EXTRA_SEED}")
        _sweep(args, "scenarios/valley.yaml", out / "valley", [f"seed={valley_seeds}"], "full", log)
    if "table_c1" in which:
        for run_dir in sorted((out / "valley" / "runs").iterdir()):
            if not (run_dir / "comparison.json").exists() and _run_seed(run_dir) in args.seeds:
                _call([args.etar_bench, "compare", str(run_dir), "--seeds", "3"], log, args.checkout)
    if "two_sides" in which:
        _sweep(args, "scenarios/valley_two_sides.yaml", out / "two_sides", [f"seed={seeds}", "learn.phases=3,4"],
               "summary", log)
    if "star_etar" in which:
        _sweep(args, "scenarios/star_vs_etar.yaml", out / "star_etar", [f"seed={seeds}", "cell.sensor_noise=1,64,256"],
               "summary", log)
    if "coupler" in which:
        _sweep(args, "scenarios/hose_coupler.yaml", out / "coupler", [f"seed={seeds}"], "summary", log)
    if "realtime" in which and not (out / "realtime" / "report.json").exists():
        _call([args.etar_bench, "run", "scenarios/valley.yaml", "--clock", "realtime", "--out", str(out / "realtime"),
               "--replace", "--no-figures"], log, args.checkout)


def _run_seed(run_dir: Path) -> int:
    """The seed a sweep's run ran with (its scenario file)."""
    import yaml

    scenario = yaml.safe_load((run_dir / "scenario.yaml").read_text())
    return int(scenario["seed"])


# ------------------------------------------------------------------ the table


def _reports(sweep: Path) -> list[tuple[dict, dict]]:
    """(scenario, report) of every run of a sweep, in run order."""
    import yaml

    out = []
    for run_dir in sorted((sweep / "runs").iterdir()) if (sweep / "runs").is_dir() else ():
        if (run_dir / "report.json").exists():
            out.append((yaml.safe_load((run_dir / "scenario.yaml").read_text()),
                        json.loads((run_dir / "report.json").read_text())))
    return out


def _accuracy(reproductions: list[dict]) -> float | None:
    """Online phase accuracy pooled over the reproductions' scored estimates (the report's own)."""
    n = sum(r["phases"]["updates"] for r in reproductions if r.get("phases"))
    c = sum(r["phases"]["correct"] for r in reproductions if r.get("phases"))
    return c / n if n else None


def _transition_ms(reproductions: list[dict]) -> float | None:
    errors = [e for r in reproductions if r.get("phases") for e in r["phases"].get("transition_errors_s", [])]
    return 1e3 * sum(errors) / len(errors) if errors else None


def _f(x, digits=4) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _lines_per_seed(sweep: Path) -> dict[str, str]:
    """A sweep over seeds: phases chosen, reached the goal, accuracy, transition error."""
    rows = {}
    for scenario, report in _reports(sweep):
        r = report["reproductions"]
        rows[f"seed {scenario['seed']}"] = (
            f"{report['summary']['phases_chosen']} phases, {sum(x['reached_goal'] for x in r)}/{len(r)}, "
            f"acc {_f(_accuracy(r))}, {_f(_transition_ms(r), 0)} ms")
    return rows


def _lines_table_c1(folder: Path) -> dict[str, str]:
    rows = {}
    for run_dir in sorted((folder / "valley" / "runs").iterdir()) if (folder / "valley" / "runs").is_dir() else ():
        path = run_dir / "comparison.json"
        if not path.exists():
            continue
        s = json.loads(path.read_text())["table_c1"]["summary"]
        rows[f"seed {_run_seed(run_dir)}"] = ", ".join(
            f"{k} {s[k]['between_demonstrations']['mean']:.2f}/{s[k]['between_seeds']['mean']:.2f}"
            for k in ("A", "B", "Sigma", "W") if s.get(k) and s[k]["between_demonstrations"] and
            s[k]["between_seeds"])
    return rows


def _lines_two_sides(folder: Path) -> dict[str, str]:
    rows = {}
    for scenario, report in _reports(folder / "two_sides"):
        learn = next(s["learn"] for s in scenario["stages"] if "learn" in s)
        r = report["reproductions"]
        left, right = [x for x in r if x.get("side") == "left"], [x for x in r if x.get("side") == "right"]
        rows[f"{learn['phases']} phases, seed {scenario['seed']}"] = (
            f"{sum(x['reached_goal'] for x in r)}/{len(r)}, acc {_f(_accuracy(r))} "
            f"(left {_f(_accuracy(left), 3)}, right {_f(_accuracy(right), 3)})")
    return dict(sorted(rows.items()))


def _lines_star_etar(folder: Path) -> dict[str, str]:
    """Per sensor noise, over the seeds: each model's reproductions that reached the goal,
    its accuracy (mean, min..max) and transition error, and in how many seeds ETAR's
    accuracy beat STAR's."""
    by_noise: dict[float, list] = {}
    for scenario, report in _reports(folder / "star_etar"):
        r = report["reproductions"]
        per = {}
        for model in ("ETAR", "STAR"):
            mine = [x for x in r if x.get("model") == model]
            per[model] = (sum(x["reached_goal"] for x in mine), len(mine), _accuracy(mine), _transition_ms(mine))
        by_noise.setdefault(float(scenario.get("cell", {}).get("sensor_noise", 1.0)), []).append(per)
    rows = {}
    for noise, seeds in sorted(by_noise.items()):
        text = []
        for model in ("ETAR", "STAR"):
            acc = [p[model][2] for p in seeds if p[model][2] is not None]
            ms = [p[model][3] for p in seeds if p[model][3] is not None]
            text.append(f"{model} {sum(p[model][0] for p in seeds)}/{sum(p[model][1] for p in seeds)} acc "
                        f"{_f(sum(acc) / len(acc) if acc else None)} ({_f(min(acc, default=None))}.."
                        f"{_f(max(acc, default=None))}) {_f(sum(ms) / len(ms) if ms else None, 0)} ms")
        wins = sum(1 for p in seeds if None not in (p["ETAR"][2], p["STAR"][2]) and p["ETAR"][2] > p["STAR"][2])
        rows[f"noise {noise:g}x, {len(seeds)} seeds"] = "; ".join(text) + f"; ETAR ahead in {wins} of {len(seeds)}"
    return rows


def _lines_realtime(folder: Path) -> dict[str, str]:
    path = folder / "realtime" / "report.json"
    if not path.exists():
        return {}
    report = json.loads(path.read_text())
    r = report["reproductions"]
    return {"seed 0": f"{sum(x['reached_goal'] for x in r)}/{len(r)}, acc {_f(_accuracy(r))}, "
                      f"{_f(_transition_ms(r), 0)} ms"}


LINES = {"valley": lambda f: _lines_per_seed(f / "valley"), "table_c1": _lines_table_c1,
         "two_sides": _lines_two_sides, "star_etar": _lines_star_etar,
         "coupler": lambda f: _lines_per_seed(f / "coupler"), "realtime": _lines_realtime}


def table(args) -> None:
    folders = [Path(f) for f in args.folders]
    for f in folders:
        if not f.is_dir():
            raise SystemExit(f"thesis_experiments table: {f} is not a folder of 'run'")
    head = " | ".join(f.name for f in folders)
    print(f"| experiment | case | {head} |\n|---|---|{'---|' * len(folders)}")
    for name, lines in LINES.items():
        per = [lines(f) for f in folders]
        for case in dict.fromkeys(k for p in per for k in p):
            print(f"| {name} | {case} | " + " | ".join(p.get(case, "-") for p in per) + " |")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="run the experiments into a folder")
    r.add_argument("--out", required=True, help="the folder of this set of results (made; experiments in it kept)")
    r.add_argument("--seeds", type=_seeds, default=_seeds("0-4"), help="data seeds (default 0-4)")
    r.add_argument("--only", type=lambda s: s.split(","), help=f"a comma list of {', '.join(EXPERIMENTS)}")
    r.add_argument("--workers", type=int, default=1, help="a sweep's processes (default 1: leave a CPU)")
    r.add_argument("--etar-bench", default=str(Path(sys.executable).parent / "etar-bench"),
                   help="the etar-bench to measure (default: this interpreter's)")
    r.add_argument("--checkout", type=Path, default=ROOT,
                   help="the repository whose scenarios/ the runs read (default: this one)")
    t = sub.add_parser("table", help="one or more result folders side by side (markdown)")
    t.add_argument("folders", nargs="+")
    args = ap.parse_args(argv)
    if args.cmd == "run":
        bad = set(args.only or ()) - set(EXPERIMENTS)
        if bad:
            ap.error(f"--only: unknown {', '.join(sorted(bad))} (choose from {', '.join(EXPERIMENTS)})")
        if args.workers < 1:
            ap.error(f"--workers must be >= 1, got {args.workers}")
        if not shutil.which(args.etar_bench):
            ap.error(f"--etar-bench {args.etar_bench}: not an executable")
        run(args)
    else:
        table(args)


if __name__ == "__main__":
    main()
