"""A checkpoint never runs code: runs are shared, and opening one must be safe.

A ``checkpoints/last.pt`` whose pickle carries a ``__reduce__`` payload (here: one that
creates a marker file) is refused by every command of the kit that reads a run —
``train.py resume=DIR``, ``resume=auto``, ``python -m wcsac_rl.evaluate`` on the run and
on its sweep, ``python -m wcsac_rl.calibration``, ``python -m wcsac_rl.report`` with and
without trajectories — with one line naming the file and saying it was not executed; no
file of the sweep changes. A saved replay buffer with a pickle in it is refused before
TorchRL reads it. Checkpoints written by the kit hold plain data only, and older ones
(NumPy's RNG state as a tuple with an ``ndarray``) still resume and evaluate.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from _evaluation_helpers import copy_sweep, run_dirs
from _training_helpers import ROOT, TINY_CPO, compose_config, tree_digests

from wcsac_rl.calibration import main as calibration_main
from wcsac_rl.evaluate import main as evaluate_main
from wcsac_rl.evaluation.evaluator import evaluate_run
from wcsac_rl.report import main as report_main
from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint, save_checkpoint
from wcsac_rl.training.safe_load import load_data

NOT_EXECUTED = "it was not executed"


class _Touch:
    """Unpickling this creates ``marker`` (what a hostile checkpoint could do instead)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


class _System:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch '{self.marker}'",))


def _hostile_bytes(state: dict, payload: object) -> bytes:
    buf = io.BytesIO()
    torch.save({**state, "rng": {**state["rng"], "extra": payload}}, buf)
    return buf.getvalue()


def _assert_payload_is_live(data: bytes, marker: Path, load=None) -> None:
    """The payload does run when unpickled without ``weights_only`` (so the tests
    that show it does not run are not vacuous); removes the marker again."""
    assert not marker.exists()
    if load is None:
        torch.load(io.BytesIO(data), weights_only=False)
    else:
        load(data)
    assert marker.exists(), "the test's payload should create the marker when unpickled"
    marker.unlink()


def _refusal_lines(text: str, checkpoint: Path) -> list[str]:
    return [line for line in text.splitlines() if str(checkpoint) in line]


# ------------------------------------------------------------- the loader itself
@pytest.mark.parametrize("payload", [_Touch, _System])
def test_a_checkpoint_with_code_in_it_is_refused_in_one_line_and_never_run(tmp_path, payload):
    run = tmp_path / "run"
    trainer = make_trainer(compose_config("algo=sac", "env=tiny"), run)
    try:
        trainer.run()
    finally:
        trainer.close()
    marker = tmp_path / "MARKER"
    path = trainer.checkpoint_path
    data = _hostile_bytes(load_checkpoint(path), payload(marker))
    path.write_bytes(data)
    with pytest.raises(ConfigError) as err:
        load_checkpoint(path)
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(f"cannot read checkpoint {path}: it holds objects other than")
    assert NOT_EXECUTED in message and "only loads checkpoints as data" in message
    assert ("pathlib" in message) if payload is _Touch else ("system" in message)
    assert not marker.exists()
    _assert_payload_is_live(data, marker)


@pytest.mark.parametrize(
    "value",
    [
        np.array([1, "x"], dtype=object),  # an object array: pickles of its items
        np.zeros(2, dtype=[("a", "f4")]),  # structured dtypes
    ],
    ids=["object", "structured"],
)
def test_numpy_arrays_other_than_plain_numbers_are_refused(tmp_path, value):
    buf = io.BytesIO()
    torch.save({"x": value}, buf)
    with pytest.raises(ConfigError, match=f"as data .*; {NOT_EXECUTED}"):
        load_data(buf.getvalue(), tmp_path / "x.pt")


def _as_numpy1(data: bytes) -> bytes:
    """The same torch.save file as NumPy 1 pickles it (``numpy.core`` module names)."""
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(data)) as zin, zipfile.ZipFile(out, "w") as zout:
        for info in zin.infolist():
            record = zin.read(info.filename)
            if info.filename.endswith("data.pkl"):
                record = record.replace(b"numpy._core.", b"numpy.core.")
            zout.writestr(info.filename, record)
    return out.getvalue()


def test_numeric_numpy_arrays_and_scalars_of_old_checkpoints_are_read_as_data(tmp_path):
    values = {
        "rng": np.random.get_state(),
        "fortran": np.asfortranarray(np.arange(6, dtype=np.int64).reshape(2, 3)),
        "big_endian": np.arange(3, dtype=">u4"),
        "empty": np.zeros((0, 2)),
        "scalar": np.float64(2.5),
        "tensor": torch.arange(3),
    }
    buf = io.BytesIO()
    torch.save(values, buf)
    for data in (buf.getvalue(), _as_numpy1(buf.getvalue())):
        back = load_data(data, tmp_path / "old.pt")
        assert back["rng"][0] == "MT19937" and back["rng"][2:] == values["rng"][2:]
        for key in ("fortran", "big_endian", "empty"):
            assert back[key].dtype == values[key].dtype and np.array_equal(back[key], values[key])
        np.testing.assert_array_equal(back["rng"][1], values["rng"][1])
        assert back["scalar"] == 2.5 and torch.equal(back["tensor"], values["tensor"])


# ------------------------------------------------------ what the kit writes: data
@pytest.mark.parametrize(
    "overrides",
    [
        (
            "algo=wcsac",
            "env=tiny",
            "save_replay_buffer=true",
            "algo.kappa_signal=max",
            "algo.kappa_states=initial",
        ),
        (*TINY_CPO, "total_frames=400"),
        ("algo=random", "env=tiny"),
    ],
    ids=["wcsac", "cpo", "random"],
)
def test_the_kit_writes_checkpoints_of_tensors_and_plain_data_only(tmp_path, overrides):
    cfg = compose_config(*overrides, small="algo=cpo" not in overrides)
    trainer = make_trainer(cfg, tmp_path / "run")
    try:
        trainer.run()
    finally:
        trainer.close()
    # torch's own weights_only reader, with nothing added to what it accepts
    state = torch.load(trainer.checkpoint_path, weights_only=True)
    assert torch.serialization.get_unsafe_globals_in_checkpoint(trainer.checkpoint_path) == []
    assert isinstance(state["rng"]["numpy"], dict)


def test_an_old_checkpoint_with_numpys_rng_tuple_still_resumes_and_evaluates(tmp_path):
    run = tmp_path / "run"
    options = ("algo=sac", "env=tiny")
    trainer = make_trainer(compose_config(*options), run)
    try:
        trainer.run()
    finally:
        trainer.close()
    old = load_checkpoint(trainer.checkpoint_path)
    np.random.seed(123)
    old["rng"]["numpy"] = np.random.get_state()  # what checkpoints held before
    torch.save(old, trainer.checkpoint_path)
    assert torch.serialization.get_unsafe_globals_in_checkpoint(trainer.checkpoint_path)

    np.random.seed(0)
    resumed = make_trainer(compose_config(*options, "total_frames=1200", f"resume={run}"), run)
    try:
        restored = np.random.get_state()
        assert restored[0] == "MT19937" and restored[2:] == old["rng"]["numpy"][2:]
        np.testing.assert_array_equal(restored[1], old["rng"]["numpy"][1])
        resumed.run()
    finally:
        resumed.close()
    assert isinstance(load_checkpoint(resumed.checkpoint_path)["rng"]["numpy"], dict)
    assert evaluate_run(run, episodes=1, progress=False).summary["metrics"]["episodes"] == 1


# --------------------------------------------------- every command, hostile run
@pytest.fixture(scope="module")
def hostile(tmp_path_factory):
    """A copy of the tiny sweep, evaluated, whose first run's checkpoint then got a
    payload; ``(root, sweep, run, checkpoint, marker)``."""
    root = tmp_path_factory.mktemp("hostile")
    sweep = copy_sweep(root / "data")
    for run in run_dirs(sweep):
        evaluate_run(run, episodes=2, progress=False)
    run = run_dirs(sweep)[0]
    checkpoint = run / "checkpoints" / "last.pt"
    marker = root / "MARKER"
    data = _hostile_bytes(load_checkpoint(checkpoint), _Touch(marker))
    _assert_payload_is_live(data, marker)
    checkpoint.write_bytes(data)
    return root, sweep, run, checkpoint, marker


def _train_py(args, cwd):
    proc = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
    )
    return proc.returncode, proc.stderr


def _in_process(main, argv, capsys):
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.err


def _trainer(cfg, run_dir):
    try:
        make_trainer(cfg, run_dir).close()
    except ConfigError as err:
        return 1, f"error: {err}"
    return 0, ""


# the overrides the sweep's first run was trained with (_evaluation_helpers.train_run)
FIRST_SWEEP_RUN = (
    "algo=wcsac",
    "env=tiny",
    "env.max_episode_steps=50",
    "seed=0",
    "risk_level=0.5",
    "total_frames=800",
    "epoch_frames=400",
)

COMMANDS = {
    "train.py resume=DIR": lambda s, r, o, capsys: _train_py(
        [f"resume={r}", f"hydra.run.dir={o / 'hydra'}", "hydra.output_subdir=null"], cwd=o
    ),
    "Trainer resume=DIR": lambda s, r, o, capsys: _trainer(
        compose_config("algo=wcsac", "env=tiny", f"resume={r}"), r
    ),
    "Trainer resume=auto": lambda s, r, o, capsys: _trainer(
        compose_config(*FIRST_SWEEP_RUN, "resume=auto"), r
    ),
    "evaluate RUN": lambda s, r, o, capsys: _in_process(
        evaluate_main, [str(r), "--episodes", "1", "--no-progress"], capsys
    ),
    "evaluate RUN --force": lambda s, r, o, capsys: _in_process(
        evaluate_main, [str(r), "--episodes", "1", "--no-progress", "--force"], capsys
    ),
    "evaluate SWEEP": lambda s, r, o, capsys: _in_process(
        evaluate_main, [str(s), "--episodes", "1", "--no-progress"], capsys
    ),
    "calibration RUN": lambda s, r, o, capsys: _in_process(
        calibration_main, [str(r), "--episodes", "1", "--no-progress"], capsys
    ),
    "report SWEEP": lambda s, r, o, capsys: _in_process(
        report_main, [str(s), "--out", str(o / "report"), "--trajectory-episodes", "1"], capsys
    ),
    "report SWEEP --no-trajectories": lambda s, r, o, capsys: _in_process(
        report_main, [str(s), "--out", str(o / "report"), "--no-trajectories"], capsys
    ),
}


@pytest.mark.parametrize("command", list(COMMANDS))
def test_no_command_runs_a_hostile_checkpoint_or_changes_a_file(hostile, command, capsys):
    root, sweep, run, checkpoint, marker = hostile
    out = root / "out" / command.replace(" ", "_").replace("=", "-")
    out.mkdir(parents=True)
    before = tree_digests(sweep, skip=())
    code, stderr = COMMANDS[command](sweep, run, out, capsys)
    assert not marker.exists(), f"{command} ran the checkpoint's code"
    assert tree_digests(sweep, skip=()) == before, f"{command} changed the sweep's files"
    assert "Traceback" not in stderr
    assert code != 0, stderr
    lines = _refusal_lines(stderr, checkpoint)
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: ") and NOT_EXECUTED in lines[0], stderr


def test_report_draws_no_trajectories_from_a_hostile_checkpoint_its_evaluation_vouches_for(
    hostile, capsys
):
    """An evaluation.json edited to record the hostile checkpoint's hash (not stale):
    the tables come from the JSON and CSV files alone, and Figure 5, which needs the
    policy, refuses the checkpoint."""
    root, sweep, run, _, marker = hostile
    copy = root / "vouched"
    shutil.copytree(sweep.parents[2], copy)
    sweep = copy / sweep.relative_to(sweep.parents[2])
    run = sweep / run.name
    evaluation = json.loads((run / "evaluation.json").read_text())
    evaluation["checkpoint_sha256"] = hashlib.sha256(
        (run / "checkpoints" / "last.pt").read_bytes()
    ).hexdigest()
    (run / "evaluation.json").write_text(json.dumps(evaluation))
    before = tree_digests(sweep, skip=())
    out = root / "out" / "vouched"
    args = [str(sweep), "--trajectory-episodes", "1"]
    assert report_main([*args, "--out", str(out / "tables"), "--no-trajectories"]) == 0
    assert (out / "tables" / "table1.md").is_file()
    capsys.readouterr()
    assert report_main([*args, "--out", str(out / "figures")]) == 1
    lines = _refusal_lines(capsys.readouterr().err, run / "checkpoints" / "last.pt")
    assert len(lines) == 1 and NOT_EXECUTED in lines[0]
    assert not marker.exists()
    assert tree_digests(sweep, skip=()) == before


# ------------------------------------------------------------ saved buffers
BUFFER_OPTIONS = ("algo=wcsac", "env=tiny", "save_replay_buffer=true", "algo.kappa_states=initial")


@pytest.fixture(scope="module")
def buffered_run(tmp_path_factory):
    """A run with its replay and start-state buffers saved beside the checkpoint."""
    run = tmp_path_factory.mktemp("buffered") / "run"
    trainer = make_trainer(compose_config(*BUFFER_OPTIONS), run)
    try:
        trainer.run()
    finally:
        trainer.close()
    return run


def _pickle_file(path: Path, payload: object) -> None:
    path.write_bytes(pickle.dumps(payload))


def _hostile_prefetch(run: Path, marker: Path) -> Path:
    """A prefetch.pkl with a payload, and the checkpoint's manifest made to match it:
    whoever can write the buffer can write the checkpoint too."""
    checkpoint = run / "checkpoints" / "last.pt"
    state = load_checkpoint(checkpoint)
    manifest = state["learner"]["buffers"]
    target = run / "checkpoints" / manifest["dir"] / "replay_buffer" / "prefetch.pkl"
    _pickle_file(target, {"version": 1, "capacity": 0, "queue": [_Touch(marker)]})
    rel = str(target.relative_to(run / "checkpoints" / manifest["dir"]))
    data = target.read_bytes()
    manifest["files"][rel] = [len(data), hashlib.sha256(data).hexdigest()]
    save_checkpoint(checkpoint, state)
    return target


def _hostile_pickle_field(run: Path, marker: Path) -> Path:
    """A tensordict ``other.pickle`` (which TensorDict.load_memmap would unpickle) that
    the manifest does not list."""
    buffers = next((run / "checkpoints").glob("buffers-*"))
    target = buffers / "initial_state_buffer" / "storage" / "other.pickle"
    _pickle_file(target, {"x": _Touch(marker)})
    return target


def _hostile_legacy(run: Path, marker: Path) -> Path:
    """The layout from before manifests (``checkpoints/replay_buffer/``, unchecked)."""
    checkpoint = run / "checkpoints" / "last.pt"
    state = load_checkpoint(checkpoint)
    buffers = run / "checkpoints" / state["learner"].pop("buffers")["dir"]
    for name in ("replay_buffer", "initial_state_buffer"):
        shutil.move(buffers / name, run / "checkpoints" / name)
    buffers.rmdir()
    save_checkpoint(checkpoint, state)
    target = run / "checkpoints" / "replay_buffer" / "prefetch.pkl"
    _pickle_file(target, {"version": 1, "capacity": 0, "queue": [_Touch(marker)]})
    return target


@pytest.mark.parametrize("plant", [_hostile_prefetch, _hostile_pickle_field, _hostile_legacy])
def test_a_saved_buffer_with_a_pickle_in_it_is_refused_before_torchrl_reads_it(
    buffered_run, tmp_path, plant
):
    run = shutil.copytree(buffered_run, tmp_path / "run")
    marker = tmp_path / "MARKER"
    target = plant(run, marker)
    _assert_payload_is_live(target.read_bytes(), marker, pickle.loads)
    before = tree_digests(run, skip=())
    cfg = compose_config(*BUFFER_OPTIONS, "total_frames=1200", f"resume={run}")
    with pytest.raises(ConfigError) as err:
        make_trainer(cfg, run)
    message = str(err.value)
    assert not marker.exists()
    assert tree_digests(run, skip=()) == before
    assert "\n" not in message
    assert f"{target} is not plain data" in message and "nothing of it was loaded" in message
    assert "to resume without it" in message


def test_a_resume_with_its_saved_buffers_still_works(buffered_run, tmp_path):
    run = shutil.copytree(buffered_run, tmp_path / "run")
    trainer = make_trainer(
        compose_config(*BUFFER_OPTIONS, "total_frames=1200", f"resume={run}"), run
    )
    try:
        assert len(trainer.replay_buffer) == 800 and len(trainer.initial_state_buffer) > 0
        assert trainer.update_start_frames == trainer.init_random_frames  # not refilled
        trainer.run()
    finally:
        trainer.close()
    assert load_checkpoint(trainer.checkpoint_path)["frames"] == 1200


def test_a_file_beside_the_saved_buffers_is_refused(buffered_run, tmp_path):
    """``buffers-<frames>/`` holds the directories of the buffers it saved, nothing else:
    an ``evil.pkl`` beside them (which no manifest lists) is refused, naming it."""
    run = shutil.copytree(buffered_run, tmp_path / "run")
    marker = tmp_path / "MARKER"
    target = next((run / "checkpoints").glob("buffers-*")) / "evil.pkl"
    _pickle_file(target, {"x": _Touch(marker)})
    before = tree_digests(run, skip=())
    cfg = compose_config(*BUFFER_OPTIONS, "total_frames=1200", f"resume={run}")
    with pytest.raises(ConfigError) as err:
        make_trainer(cfg, run)
    message = str(err.value)
    assert not marker.exists()
    assert tree_digests(run, skip=()) == before
    assert "\n" not in message
    assert f"{target} is not one of its buffers" in message and "to resume without it" in message
