"""How fast each console script answers ``--help``: wall seconds of a fresh process.

Usage::

    python benchmarks/bench_help.py [--repeats N] [--scripts wcsac-train ...] [--json PATH]

Every script of ``pyproject.toml``'s ``[project.scripts]`` (default) is run as its
console-script wrapper runs it (``from <module> import <function>; sys.exit(<function>())``,
``--help`` its one argument) in a new interpreter, ``--repeats`` times; the table gives the
fastest and the median wall time, interpreter start included, and the modules the help
imported that a console script must not load before it has parsed its arguments (torch,
torchrl: they take seconds). ``--json PATH`` also writes the rows as JSON
(``tests/test_benchmarks.py`` reads it).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "torchrl", "tensordict", "matplotlib")
"""Modules whose import the benchmark reports (a ``--help`` should load none of them)."""


def console_scripts() -> dict[str, str]:
    """``name → "module:function"`` of ``pyproject.toml``'s ``[project.scripts]`` (read by
    line: ``tomllib`` is Python >= 3.11, the package supports 3.10)."""
    text = (ROOT / "pyproject.toml").read_text()
    section = text.split("[project.scripts]", 1)[1].split("\n[", 1)[0]
    return dict(re.findall(r'^([\w.-]+)\s*=\s*"([\w.]+:[\w.]+)"', section, flags=re.MULTILINE))


def _command(name: str, target: str) -> list[str]:
    module, function = target.split(":")
    code = "\n".join(
        [
            "import sys",
            f"sys.argv[0] = {name!r}",
            "try:",
            f"    from {module} import {function}",
            f"    code = {function}()",
            "finally:  # (--help exits from inside the parser)",
            f"    heavy = [m for m in {HEAVY!r} if m in sys.modules]",
            "    print('heavy modules:', ','.join(heavy), file=sys.stderr)",
            "sys.exit(code)",
        ]
    )
    return [sys.executable, "-c", code, "--help"]


def time_help(name: str, target: str, repeats: int) -> dict:
    """One row: the fastest and median seconds of ``name --help`` and what it imported."""
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
        "OMP_NUM_THREADS": "1",
    }
    seconds, heavy = [], ""
    for _ in range(repeats):
        start = time.perf_counter()
        proc = subprocess.run(
            _command(name, target), cwd=ROOT, env=env, capture_output=True, text=True
        )
        seconds.append(time.perf_counter() - start)
        if proc.returncode != 0 or not proc.stdout.strip():
            raise SystemExit(f"{name} --help failed (exit {proc.returncode}):\n{proc.stderr}")
        heavy = next(
            (line.split(":", 1)[1].strip() for line in proc.stderr.splitlines()
             if line.startswith("heavy modules:")),
            "?",
        )  # fmt: skip
    return {
        "script": name,
        "entry_point": target,
        "min_s": min(seconds),
        "median_s": statistics.median(seconds),
        "repeats": repeats,
        "help_lines": len(proc.stdout.splitlines()),
        "heavy_modules": heavy,
    }


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="processes per script (default 5)")
    parser.add_argument(
        "--scripts", nargs="+", default=None, help="console scripts to time (default: all)"
    )
    parser.add_argument("--json", type=Path, help="also write the rows here as JSON")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    scripts = console_scripts()
    unknown = sorted(set(args.scripts or ()) - set(scripts))
    if unknown:
        parser.error(f"no console script {', '.join(unknown)}; pyproject.toml has {list(scripts)}")
    chosen = args.scripts or list(scripts)
    print(f"# --help of each console script, {args.repeats} fresh processes each")
    print(f"# {platform.processor() or platform.machine()}, Python {platform.python_version()}")
    header = f"{'script':<20} {'min s':>7} {'median s':>9}  heavy modules imported"
    print(header)
    print("-" * len(header))
    rows = []
    for name in chosen:
        row = time_help(name, scripts[name], args.repeats)
        rows.append(row)
        print(
            f"{name:<20} {row['min_s']:>7.2f} {row['median_s']:>9.2f}  "
            f"{row['heavy_modules'] or 'none'}"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
