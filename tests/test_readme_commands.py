"""Every shell command the README and the docs pages show is one the kit accepts, and
every link in them leads somewhere.

A command is a line of a ```bash / ```sh / ```shell block (a ```console block's lines
that start with ``$ ``), or an inline span in backticks that starts with ``python
train.py``, ``python -m wcsac_rl``, ``make`` or ``wcsac-``. Each is checked without
doing its work:

* ``python train.py <overrides>`` (and ``wcsac-train``, ``python -m wcsac_rl.train``):
  the overrides pass the command line's key check (a misspelt key is refused naming the
  closest one), and every job the command starts — each combination of a sweep, with an
  experiment's own sweeper parameters — composes and passes ``validate_config``;
* ``python -m wcsac_rl.<module> <args>``, ``wcsac-<tool> <args>``, ``python <script>.py
  <args>``: the module's argparse parser accepts the arguments (paths need not exist);
* ``make <target>``: the Makefile has the target; ``pip install`` names extras
  ``pyproject.toml`` declares.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.util
import io
import re
import runpy
import shlex
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import open_dict

from wcsac_rl.training import ConfigError, validate_config
from wcsac_rl.training.config_keys import check_override_keys

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: pytest's own dependency
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]
SHELL_FENCES = ("bash", "sh", "shell", "console")
INLINE_STARTS = ("python train.py", "python -m wcsac_rl", "make ", "wcsac-")
# shell words a docs page may use around the kit's commands (a loop over runs)
SHELL_WORDS = ("export", "for", "done", "cd")
MAX_JOBS = 64  # jobs of one sweep checked (the paper's Table 1 is 21)
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
SCRIPTS = PYPROJECT["project"].get("scripts", {})
EXTRAS = set(PYPROJECT["project"].get("optional-dependencies", {}))
TRAIN_MODULE = "wcsac_rl.train"  # train.py installed: wcsac-train


# --- finding the commands -------------------------------------------------------------


def shell_commands(text: str) -> list[tuple[int, str]]:
    """``(line number, command)`` of every command in a markdown text."""
    found, prose = [], []
    fence, pending, start = None, "", 0
    for number, line in enumerate(text.splitlines(), 1):
        opening = re.match(r"^\s*```(\w*)\s*$", line)
        if fence is None and opening:
            fence = opening.group(1) or "text"
            prose.append("")
            continue
        if fence is not None:
            if line.strip() == "```":
                fence = None
            elif fence in SHELL_FENCES:
                if fence == "console":
                    if not line.startswith("$ "):
                        continue
                    line = line[2:]
                if not pending:
                    start = number
                pending += line.strip() if pending else line.rstrip()
                if pending.endswith("\\"):
                    pending = pending[:-1].rstrip() + " "
                    continue
                if pending.strip() and not pending.lstrip().startswith("#"):
                    found.append((start, pending.strip()))
                pending = ""
            prose.append("")
            continue
        prose.append(line)
    body = "\n".join(prose)
    for match in re.finditer(r"(?<!`)`([^`]+)`(?!`)", body):
        span = " ".join(match.group(1).split())
        if span.startswith(INLINE_STARTS) or span in ("make", "wcsac-train"):
            found.append((body.count("\n", 0, match.start()) + 1, span))
    return sorted(found)


# pages whose commands run what the reader writes first (their links are checked)
WRITE_FIRST = {
    "docs/own_algorithm.md": "trains conf/algo/wcsac_iqn_pid.yaml and penalty_sac.yaml, which it "
    "shows how to write"
}


def _all_commands() -> list[tuple[Path, int, str]]:
    return [
        (page, n, cmd)
        for page in PAGES
        if str(page.relative_to(ROOT)) not in WRITE_FIRST
        for n, cmd in shell_commands(page.read_text())
    ]


def _id(item: tuple[Path, int, str]) -> str:
    page, number, command = item
    return f"{page.relative_to(ROOT)}:{number}:{command[:50]}"


# --- checking one command -------------------------------------------------------------


class CommandRefused(Exception):
    """The command would not run as written (the message says why)."""


class _Parsed(Exception):
    def __init__(self, namespace: argparse.Namespace) -> None:
        self.namespace = namespace


def _optional_brackets(words: list[str]) -> list[str]:
    """A usage line's ``[--episodes 30]`` is given as ``--episodes 30`` (an extra's
    ``.[video]`` is left as it is)."""
    words = [w[1:] if w.startswith("[") else w for w in words]
    return [w[:-1] if w.endswith("]") and "[" not in w else w for w in words if w]


def check_command(command: str, *, docs_page: bool = False) -> None:
    """Raise :class:`CommandRefused` if ``command`` would not run as written."""
    try:
        words = shlex.split(command, comments=True)
    except ValueError as err:
        raise CommandRefused(f"not a shell command line: {err}") from None
    while words and re.match(r"^[A-Za-z_][A-Za-z0-9_]*=", words[0]):  # VAR=value cmd
        words = words[1:]
    if not words:
        return
    tool, args = words[0], _optional_brackets(words[1:])
    if tool == "make":
        _check_make(args)
    elif tool in ("python", "python3"):
        _check_python(args)
    elif tool == "wcsac-train":
        _check_train(args, via=tool)
    elif tool.startswith("wcsac-"):
        if tool not in SCRIPTS:
            raise CommandRefused(f"{tool} is not a console script of pyproject.toml")
        if args:  # (a bare name in the prose names the tool)
            _check_module(SCRIPTS[tool].split(":")[0], args)
    elif tool == "pip":
        _check_pip(args)
    elif tool in SHELL_WORDS and (docs_page or tool == "export"):
        return
    else:
        raise CommandRefused(f"{tool!r} is not a command this test knows how to check")


def _make_targets() -> set[str]:
    text = (ROOT / "Makefile").read_text()
    return set(re.findall(r"^([A-Za-z0-9][A-Za-z0-9_.-]*)\s*:(?!=)", text, flags=re.M))


def _check_make(args: list[str]) -> None:
    targets = _make_targets()
    for word in args:
        if "=" in word or word.startswith("-"):
            continue
        if word not in targets:
            raise CommandRefused(f"make {word}: the Makefile has {', '.join(sorted(targets))}")


def _check_pip(args: list[str]) -> None:
    if not args or args[0] != "install":
        raise CommandRefused("only pip install is checked")
    for word in args[1:]:
        extras = re.fullmatch(r"\.\[(.+)\]", word)
        for extra in extras.group(1).split(",") if extras else ():
            if extra not in EXTRAS:
                raise CommandRefused(f"no extra {extra!r} in pyproject.toml: {sorted(EXTRAS)}")


def _check_python(args: list[str]) -> None:
    if len(args) >= 2 and args[0] == "-m":
        module, rest = args[1], args[2:]
        if module == TRAIN_MODULE:
            _check_train(rest, via=f"python -m {module}")
        elif not module.startswith("wcsac_rl"):
            raise CommandRefused(f"python -m {module}: not one of the kit's modules")
        elif not rest:  # (a bare module in the prose names the tool)
            if importlib.util.find_spec(module) is None:
                raise CommandRefused(f"no module {module}")
        else:
            _check_module(module, rest)
    elif args and args[0] == "train.py":
        _check_train(args[1:], via="python train.py")
    elif args and args[0].endswith(".py"):
        _check_script(ROOT / args[0], args[1:])
    else:
        raise CommandRefused("python with neither -m MODULE nor a script")


def _check_module(module: str, args: list[str]) -> None:
    """The module's own ``parse_args`` (with its checks) if it has one, else its
    ``main(argv)`` stopped right after its parser has parsed."""
    try:
        loaded = importlib.import_module(module)
    except ImportError as err:
        raise CommandRefused(f"cannot import {module}: {err}") from None
    if hasattr(loaded, "parse_args"):
        _parse(lambda: loaded.parse_args(args), module)
    elif hasattr(loaded, "main"):
        _parse_stopped(lambda: loaded.main(args), module)
    else:
        raise CommandRefused(f"{module} has neither parse_args nor main")


def _check_script(path: Path, args: list[str]) -> None:
    if not path.is_file():
        raise CommandRefused(f"no script {path.relative_to(ROOT)}")
    if "argparse" not in path.read_text():
        raise CommandRefused(f"{path.name} has no argparse parser to check")
    saved = sys.argv, list(sys.path)
    sys.argv, sys.path[:0] = [str(path), *args], [str(path.parent)]
    try:
        _parse_stopped(lambda: runpy.run_path(str(path), run_name="__main__"), path.name)
    finally:
        sys.argv, sys.path[:] = saved[0], saved[1]


def _parse(call, name: str) -> None:
    said = io.StringIO()
    try:
        with contextlib.redirect_stderr(said):
            call()
    except SystemExit as stop:
        if stop.code not in (0, None):
            last = (said.getvalue().strip().splitlines() or [f"exit code {stop.code}"])[-1]
            raise CommandRefused(f"{name} refuses its arguments: {last}") from None


def _parse_stopped(call, name: str) -> None:
    """Run ``call`` until an argparse parser has parsed its command line, then stop."""
    original = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        raise _Parsed(original(self, args, namespace))

    argparse.ArgumentParser.parse_args = parse_then_stop
    try:
        _parse(call, name)
    except _Parsed:
        return
    finally:
        argparse.ArgumentParser.parse_args = original
    raise CommandRefused(f"{name} did not parse a command line")


HYDRA_CFG_PARTS = ("job", "hydra", "all")
"""What Hydra's ``--cfg`` / ``-c`` prints instead of running (the overrides still compose)."""


def _without_cfg_flag(args: list[str], via: str) -> list[str]:
    """``args`` without Hydra's ``--cfg <part>`` (a part it does not know is refused)."""
    out, rest = [], iter(args)
    for arg in rest:
        if arg in ("--cfg", "-c"):
            part = next(rest, None)
            if part not in HYDRA_CFG_PARTS:
                raise CommandRefused(f"{via}: {arg} takes one of {HYDRA_CFG_PARTS}, got {part!r}")
            continue
        out.append(arg)
    return out


def _check_train(args: list[str], *, via: str) -> None:
    args = _without_cfg_flag(args, via)
    multirun = any(a in ("-m", "--multirun") for a in args)
    overrides = [a for a in args if a not in ("-m", "--multirun")]
    flags = [a for a in overrides if a.startswith("-")]
    if flags:
        raise CommandRefused(f"{via}: flags {flags} are not checked here")
    try:
        check_override_keys(overrides)  # what train.py checks before Hydra composes
    except ConfigError as err:
        raise CommandRefused(f"error: {err}") from None
    for job in _jobs(overrides, multirun=multirun):
        # (Hydra's own keys do not change a job's config: _jobs composed them once)
        job = [o for o in job if not o.lstrip("+~").startswith("hydra")]
        if tuple(job) in _VALID_JOBS:
            continue
        try:
            cfg = _compose(job)
            with open_dict(cfg):
                cfg.pop("hydra")
            validate_config(cfg)
        except ConfigError as err:
            raise CommandRefused(f"job {' '.join(job)}: error: {err}") from None
        _VALID_JOBS.add(tuple(job))


_VALID_JOBS: set[tuple[str, ...]] = set()  # jobs already composed and validated


def _compose(overrides: list[str]):
    try:
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            return compose("config", overrides=list(overrides), return_hydra_config=True)
    except Exception as err:  # Hydra's own refusals: an unknown group option, a bad value
        raise CommandRefused(f"Hydra cannot compose {' '.join(overrides)}: {err}") from None


def _jobs(overrides: list[str], *, multirun: bool) -> list[list[str]]:
    """The override list of every job the command starts, as Hydra's basic sweeper
    expands them (the config's ``hydra.sweeper.params`` first, the command's after)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    parsed = parser.parse_overrides(overrides)
    swept = [o for o in parsed if o.is_sweep_override()]
    first = [
        f"{o.input_line.split('=', 1)[0]}={next(iter(o.sweep_string_iterator()))}"
        if o.is_sweep_override()
        else o.input_line
        for o in parsed
    ]
    cfg = _compose(first)
    if not multirun and str(cfg.hydra.mode) != "RunMode.MULTIRUN":
        if swept:
            raise CommandRefused(f"a sweep ({swept[0].input_line}) needs -m")
        return [overrides]
    params = cfg.hydra.sweeper.get("params") or {}
    arguments = [f"{key}={value}" for key, value in params.items()] + list(overrides)
    batches = BasicSweeper.split_arguments(parser.parse_overrides(arguments), None)
    jobs = [list(job) for batch in batches for job in batch]
    if len(jobs) > MAX_JOBS:
        raise CommandRefused(f"{len(jobs)} jobs: more than this test checks ({MAX_JOBS})")
    return jobs


# --- the tests ------------------------------------------------------------------------

COMMANDS = _all_commands()


@pytest.mark.parametrize("item", COMMANDS, ids=_id)
def test_every_command_of_the_readme_and_docs_is_accepted(item):
    page, _, command = item
    try:
        check_command(command, docs_page=page != README)
    except CommandRefused as err:
        pytest.fail(f"{page.relative_to(ROOT)}: `{command}` would not run: {err}")


def test_the_readme_shows_its_quickstart_commands():
    commands = {cmd for page, _, cmd in COMMANDS if page == README}
    for expected in (
        "make install",
        "make train",
        "make test",
        "python train.py algo=wcsac risk_level=0.5 env=dynamic",
        "python train.py -m experiment=table1_static",
        "python -m wcsac_rl.evaluate multirun/table1_static",
    ):
        assert any(cmd.split("#")[0].strip() == expected for cmd in commands), expected


@pytest.mark.parametrize(
    "command",
    [
        "python train.py algo=wcsac risk_levl=0.5",  # a misspelt key
        "python train.py algo=wcsca",  # a misspelt group option
        "python train.py -m algo=wcsac risk_level=0.1,1.5",  # a job out of range
        "python train.py algo=wcsac seed=0,10",  # a sweep without -m
        "python train.py --cfg job algo.kapa_init=1",  # Hydra's --cfg: the rest is checked
        "python train.py --cfg jobs",  # not a part --cfg prints
        "python -m wcsac_rl.evaluate multirun/alpha --episdes 100",
        "python -m wcsac_rl.calibration --episodes 30",  # no run directory
        "python -m wcsac_rl.evalute multirun/alpha",
        "python -m paper.compare --outt x runs/a",
        "python benchmarks/bench_update.py --compiled",
        "wcsac-report multirun/alpha --forse",
        "wcsac-evalute multirun/alpha",
        "make tests",
        'pip install -e ".[tensorbord]"',
        "rm -rf outputs",
    ],
)
def test_a_command_the_kit_would_refuse_fails_the_check(command):
    with pytest.raises(CommandRefused):
        check_command(command)


def test_the_checker_finds_block_and_inline_commands():
    text = (
        "Run `make train`, then `python train.py seed=1`; not `make_env(name)`.\n"
        "```bash\n"
        "python -m wcsac_rl.report \\\n"
        "  multirun/x --force   # comment\n"
        "# a comment line\n"
        "```\n"
        "```console\n$ make test\noutput line\n```\n"
        "```python\nmake = 1\n```\n"
    )
    assert shell_commands(text) == [
        (1, "make train"),
        (1, "python train.py seed=1"),
        (3, "python -m wcsac_rl.report multirun/x --force   # comment"),
        (8, "make test"),
    ]


# --- links ----------------------------------------------------------------------------


def _slug(heading: str) -> str:
    """GitHub's anchor of a markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return {_slug(h) for h in re.findall(r"^#+ (.+)$", text, flags=re.M)}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_leads_to_a_file_and_heading(page):
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"^[a-z]+://", target):
            continue
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        if path and not resolved.exists():
            broken.append(target)
            continue
        if anchor and resolved.suffix == ".md" and anchor not in _anchors(resolved):
            broken.append(target)
    assert broken == []


def test_the_readme_is_a_guide_of_at_most_300_lines():
    assert len(README.read_text().splitlines()) <= 300
