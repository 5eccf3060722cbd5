"""Reading a run's files back as data only: nothing in a checkpoint or a saved buffer runs.

Checkpoints: ``torch.load(weights_only=True)`` (:func:`load_data`), old checkpoints'
NumPy arrays rebuilt from their bytes by stand-ins (:class:`_NumpyArray`); saved
buffers: only data files admitted (:func:`check_buffer_files`); text records bounded
before they are parsed (:func:`load_yaml`, :func:`load_json`, :func:`check_size`).
The rules and what they leave open: docs/guarantees.md ("Checkpoints are loaded as data
only", "Saved replay buffers", "Other files").
"""

from __future__ import annotations

import io
import json
import math
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from omegaconf import DictConfig, ListConfig, OmegaConf

from wcsac_rl._messages import first_line
from wcsac_rl.training.config import ConfigError

__all__ = [
    "MAX_CHECKPOINT_BYTES",
    "MAX_RECORD_BYTES",
    "MAX_YAML_NODES",
    "UnreadableRecord",
    "check_buffer_files",
    "check_size",
    "load_data",
    "load_json",
    "load_yaml",
]

MAX_RECORD_BYTES = 64 * 2**20
"""The largest text record read from a run (``config.yaml``, ``evaluation.json``, ...:
kilobytes when the kit writes them)."""
MAX_YAML_NODES = 100_000
"""The most nodes a run's YAML record may expand to (a composed config has ~300)."""
MAX_CHECKPOINT_BYTES = 4 * 2**30
"""The largest checkpoint read (networks and optimisers: megabytes at the paper's sizes;
a saved replay buffer is its own files)."""


class UnreadableRecord(ValueError):
    """A run's record that is refused before it is parsed; the message names the file."""


def check_size(path: Path, limit: int, what: str = "record") -> None:
    """Raise :class:`UnreadableRecord` if ``path`` is larger than ``limit`` bytes (read
    from its size, not its contents: a sparse file costs nothing to refuse)."""
    size = Path(path).stat().st_size
    if size > limit:
        raise UnreadableRecord(
            f"{path}: {size / 2**30:.2f} GiB, larger than any {what} the kit writes "
            f"(at most {limit / 2**30:g} GiB read): not read"
        )


def _expanded_nodes(node: yaml.Node, seen: dict[int, int]) -> int:
    """How many nodes ``node`` stands for once every alias is expanded (each distinct node
    counted once, its count reused wherever an alias repeats it)."""
    if id(node) in seen:
        return seen[id(node)]
    count = 1
    if isinstance(node, yaml.MappingNode):
        count += sum(_expanded_nodes(k, seen) + _expanded_nodes(v, seen) for k, v in node.value)
    elif isinstance(node, yaml.SequenceNode):
        count += sum(_expanded_nodes(item, seen) for item in node.value)
    seen[id(node)] = min(count, MAX_YAML_NODES + 1)
    return seen[id(node)]


def load_yaml(path: Path) -> DictConfig | ListConfig:
    """``OmegaConf.load(path)`` of a run's record, bounded: a file larger than
    :data:`MAX_RECORD_BYTES`, nested deeper than the parser recurses, or expanding past
    :data:`MAX_YAML_NODES` nodes through its aliases is refused with one
    :class:`UnreadableRecord` line naming it, before anything is built from it."""
    path = Path(path)
    check_size(path, MAX_RECORD_BYTES)
    text = path.read_text(encoding="utf-8")
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        nodes = 0 if root is None else _expanded_nodes(root, {})
    except RecursionError:
        raise UnreadableRecord(f"{path}: nested too deeply to read") from None
    if nodes > MAX_YAML_NODES:
        raise UnreadableRecord(
            f"{path}: its aliases expand to more than {MAX_YAML_NODES} nodes (a composed "
            "config has a few hundred): not read"
        )
    return OmegaConf.create(text)


def load_json(path: Path) -> Any:
    """``json.loads`` of a run's record, bounded: a file larger than
    :data:`MAX_RECORD_BYTES` or nested deeper than the parser recurses is refused with
    one :class:`UnreadableRecord` line naming it."""
    path = Path(path)
    check_size(path, MAX_RECORD_BYTES)
    try:
        return json.loads(path.read_text())
    except RecursionError:
        raise UnreadableRecord(f"{path}: nested too deeply to read") from None


_NOT_EXECUTED = "it was not executed — wcsac_rl only loads checkpoints as data"


# --------------------------------------------------- NumPy arrays of old checkpoints
_NUMPY_CODES = frozenset(["b1", "i1", "i2", "i4", "i8", "u1", "u2", "u4", "u8", "f2", "f4", "f8"])
"""NumPy dtypes an old checkpoint's arrays may have (numbers and booleans only)."""


class _NumpyDtype:
    """A NumPy dtype named in an old checkpoint: its type code and byte order only."""

    def __init__(self, code: Any = None, *_flags: Any) -> None:
        if not isinstance(code, str) or code not in _NUMPY_CODES:
            raise pickle.UnpicklingError(f"unsupported NumPy dtype {code!r}")
        self.code = code
        self.byteorder = "="

    def __setstate__(self, state: Any) -> None:
        # NumPy's dtype state: (version, byteorder, subarray, names, fields, elsize, ...)
        ok = isinstance(state, tuple) and len(state) >= 5 and state[1] in ("<", ">", "|", "=")
        if not ok or any(part is not None for part in state[2:5]):
            raise pickle.UnpicklingError(f"unsupported NumPy dtype state {state!r}")
        self.byteorder = state[1]

    def numpy(self) -> np.dtype:
        return np.dtype(self.code).newbyteorder(self.byteorder)


class _NumpyArray:
    """A ``numpy.ndarray`` in an old checkpoint, rebuilt from its raw bytes
    (``numpy.ndarray`` itself stands for this class while loading)."""

    array: np.ndarray | None = None

    def __setstate__(self, state: Any) -> None:
        # NumPy's array state: (version, shape, dtype, is_fortran, raw bytes)
        if not (isinstance(state, tuple) and len(state) == 5):
            raise pickle.UnpicklingError("unsupported NumPy array state")
        _version, shape, dtype, fortran, raw = state
        if (
            not isinstance(shape, tuple)
            or not all(isinstance(n, int) and n >= 0 for n in shape)
            or not isinstance(dtype, _NumpyDtype)
            or not isinstance(raw, (bytes, bytearray))
        ):
            raise pickle.UnpicklingError("unsupported NumPy array state")
        dt = dtype.numpy()
        if len(raw) != math.prod(shape) * dt.itemsize:
            raise pickle.UnpicklingError("NumPy array state of the wrong size")
        order = "F" if fortran else "C"
        self.array = np.frombuffer(bytes(raw), dtype=dt).reshape(shape, order=order).copy()


def _numpy_reconstruct(*args: Any) -> _NumpyArray:
    if not args or args[0] is not _NumpyArray:
        raise pickle.UnpicklingError("only plain NumPy arrays can be read")
    return _NumpyArray()


def _numpy_scalar(*args: Any) -> np.generic:
    dtype, raw = args if len(args) == 2 else (None, None)
    if not isinstance(dtype, _NumpyDtype) or not isinstance(raw, (bytes, bytearray)):
        raise pickle.UnpicklingError("unsupported NumPy scalar")
    dt = dtype.numpy()
    if len(raw) != dt.itemsize:
        raise pickle.UnpicklingError("NumPy scalar of the wrong size")
    return np.frombuffer(bytes(raw), dtype=dt)[0]


def _empty_bytes(*args: Any) -> bytes:
    # pickle protocol 2 writes b"" (the data of an empty array) as ``bytes()``
    if args:
        raise pickle.UnpicklingError("only empty bytes are built by a call")
    return b""


_NUMPY_STAND_INS: dict[str, Any] = {
    "numpy.ndarray": _NumpyArray,
    "numpy.dtype": _NumpyDtype,
    # NumPy 2 pickles as numpy._core, NumPy 1 as numpy.core
    "numpy._core.multiarray._reconstruct": _numpy_reconstruct,
    "numpy.core.multiarray._reconstruct": _numpy_reconstruct,
    "numpy._core.multiarray.scalar": _numpy_scalar,
    "numpy.core.multiarray.scalar": _numpy_scalar,
    "builtins.bytes": _empty_bytes,
}
"""What the NumPy names an old checkpoint refers to are read with (each a stand-in of this
module, none of them NumPy's: ``torch.serialization.safe_globals`` maps a name to it)."""


def _numpy_values(obj: Any) -> Any:
    """``obj`` with the stand-ins replaced by the NumPy arrays and dtypes they read."""
    if isinstance(obj, _NumpyArray):
        if obj.array is None:
            raise pickle.UnpicklingError("a NumPy array without its data")
        return obj.array
    if isinstance(obj, _NumpyDtype):
        return obj.numpy()
    if isinstance(obj, dict):  # OrderedDict (state dicts) too: in place keeps its type
        for key, value in obj.items():
            obj[key] = _numpy_values(value)
        return obj
    if isinstance(obj, list):
        obj[:] = [_numpy_values(value) for value in obj]
        return obj
    if type(obj) is tuple:
        return tuple(_numpy_values(value) for value in obj)
    return obj


# -------------------------------------------------------------- checkpoints
def _unsafe_globals(data: bytes) -> list[str]:
    """The names a torch.save file refers to beyond what :func:`load_data` reads
    (found by reading its pickle's opcodes, not by running them)."""
    try:
        names = torch.serialization.get_unsafe_globals_in_checkpoint(io.BytesIO(data))
    except Exception:
        return []
    return sorted(set(names) - set(_NUMPY_STAND_INS))


def load_data(data: bytes, path: Path) -> Any:
    """What ``torch.save`` wrote into ``data`` (the bytes of ``path``), read as data only
    (``torch.load(weights_only=True)``, and old checkpoints' NumPy arrays); one
    ``ConfigError`` line for a file that refers to anything else (saying it was not
    executed) or cannot be read.
    """
    stand_ins = [(obj, name) for name, obj in _NUMPY_STAND_INS.items()]
    try:
        with torch.serialization.safe_globals(stand_ins):
            state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        return _numpy_values(state)
    except pickle.UnpicklingError as err:
        names = _unsafe_globals(data)
        if names:
            raise ConfigError(
                f"cannot read checkpoint {path}: it holds objects other than tensors and "
                f"plain data ({', '.join(names)}); {_NOT_EXECUTED}"
            ) from None
        reason = str(err).split("WeightsUnpickler error:")[-1].strip()  # torch's own words
        reason = reason.splitlines()[0] if reason else type(err).__name__
        raise ConfigError(
            f"cannot read checkpoint {path} as data ({reason}); {_NOT_EXECUTED}"
        ) from None
    except Exception as err:  # a corrupt or foreign file: one clear line
        raise ConfigError(f"cannot read checkpoint {path}: {first_line(err)}") from None


# ------------------------------------------------------------ saved buffers
_BUFFER_DATA_SUFFIXES = (".json", ".memmap")
PREFETCH_FILE = "prefetch.pkl"
"""TorchRL's ``ReplayBuffer.dumps`` pickles the buffer's prefetch queue (empty in the kit)."""


class _PlainDataUnpickler(pickle.Unpickler):
    """Builds ``dict``, ``list``, ``tuple``, ``str``, ``bytes``, numbers, ``bool`` and
    ``None`` only: every class or function a pickle names is refused, so nothing runs."""

    def find_class(self, module: str, name: str) -> Any:
        raise pickle.UnpicklingError(f"{module}.{name}")


def _plain_prefetch_state(path: Path) -> bool:
    try:
        state = _PlainDataUnpickler(io.BytesIO(path.read_bytes())).load()
    except Exception:
        return False
    return isinstance(state, dict) and not state.get("queue")


def check_buffer_files(directory: Path, checkpoint: Path, *, remove: Path) -> None:
    """Refuse, in one ``ConfigError`` line naming the first other file and saying to delete
    ``remove``, a saved buffer ``directory`` that holds anything but ``*.json`` and
    ``*.memmap`` files and a top-level ``prefetch.pkl`` of plain data with an empty queue
    (checked before TorchRL reads anything of it).
    """
    fix = f"delete {remove} to resume without it (the buffer is then refilled)"
    for path in sorted(directory.rglob("*")):
        if path.is_dir() and not path.is_symlink():
            continue
        rel = path.relative_to(directory)
        if path.suffix in _BUFFER_DATA_SUFFIXES and path.is_file() and not path.is_symlink():
            continue
        if str(rel) == PREFETCH_FILE and not path.is_symlink() and _plain_prefetch_state(path):
            continue
        raise ConfigError(
            f"cannot load the replay buffer saved with {checkpoint}: {directory / rel} is not "
            f"plain data (tensors or JSON); nothing of it was loaded or executed; {fix}"
        )
